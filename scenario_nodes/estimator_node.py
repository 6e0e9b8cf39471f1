"""estimator: a managed (lifecycle) node hosting one core filter (README, "Filters").

configure: validate the parameters, build the filter (network and compiled kernels), read what
the topics' publishers keep (an earlier estimator's newest estimate, the sensor's measurements,
the controller's controls) and start from it (snn_estimator.runners.filter_runner: hot swap, least-squares
restart, or the parameters at the first measurement); from then on the filter runs on every
input. activate: publish the estimates. deactivate: stop publishing, keep running (warm).
cleanup/shutdown: release everything. With ``autostart`` (default) the node configures and
activates itself; with ``standby`` it stays inactive until every other estimator on `estimate`
is gone (liveliness), then activates itself (hot standby). Exactly one is active: the
`estimate` publisher exists only while active (the plant starts only once there is one), and
an active estimator that sees another one alive yields by name (snn_estimator.runners.filter_runner.Standby).

Timing (snn_estimator.runners.filter_runner): the estimate x_hat_k stamped t_k is published; the controller
answers with u_k; when z_k and u_k are both here the filter steps and x_hat_{k+1} is published
stamped t_k + time_step. Once the plant reports the controls it applied, that step is
provisional until the report of step k comes; a report that differs from u_k takes the step
again and publishes x_hat_{k+1} once more, under the same stamp (``provisional_steps``).
"""

from __future__ import annotations

import time

import numpy as np
from geometry_msgs.msg import AccelStamped, PointStamped
from nav_msgs.msg import Odometry
from rcl_interfaces.msg import SetParametersResult
from rclpy.clock import Clock, ClockType
from rclpy.lifecycle import LifecycleNode, TransitionCallbackReturn
from std_msgs.msg import UInt32, UInt32MultiArray
from std_srvs.srv import Trigger

from snn_estimator import make_estimator
from snn_estimator.runners.filter_runner import FilterRunner, RunnerSettings, Standby
from snn_estimator.runners.peers import PeerWatch
from snn_estimator.schema import config_values
from snn_estimator.spiking.costs import CostModel, energy_pj

from . import qos
from .codec import (
    MessageError,
    decode_odometry,
    encode_odometry,
    encode_spikes,
    encode_uint32,
    read_input,
    read_measurement,
    state_of,
)
from .conversions import MEASUREMENT_CLASSES
from .core_objects import estimator_config, filter_model, measurement_model, silenced_set
from .diagnostics import DiagnosticsPublisher
from .history import collect_history
from .parameter_tables import ESTIMATOR, ESTIMATOR_RUNTIME
from .ros_parameters import check_choices, declare, read
from .runtime import Answers, MatchHold, ProcessHooks, ThrottledLog, clock_ns, on_clock_jump_back, run_node
from .sensor_inputs import FusedInputs, declare_sensors

#: Parameters applied between steps through the parameter services (the tables' read_only=False).
RUNTIME = ESTIMATOR_RUNTIME
SUCCESS, FAILURE = TransitionCallbackReturn.SUCCESS, TransitionCallbackReturn.FAILURE


def runner_settings(p: dict) -> RunnerSettings:
    return RunnerSettings(time_step=p['time_step'], max_input_age=p['max_input_age'],
                          nis_threshold=p['nis_threshold'], nis_window=p['nis_window'],
                          initial_fit_window=p['initial_fit_window'],
                          time_jump_threshold=p['time_jump_threshold'],
                          control_validity=p['control_validity'],
                          measurement_timing=p['measurement_timing'],
                          provisional_steps=p['provisional_steps'])


class Inputs:
    """The estimator's subscriptions: measurements, controls and set_state, converted and gated
    at the edge and handed to the runner; a message that cannot be used is counted by reason,
    logged (throttled) and reported, never a crash. A measurement that comes again (a lockstep
    resend) is answered with the estimate it got before."""

    def __init__(self, node, runner: FilterRunner, outputs: 'Outputs', p: dict, report, sensors=None):
        self._node, self._runner, self._out, self._report = node, runner, outputs, report
        self._frame, self._axes = p['frame_id'], tuple(int(a) for a in p['measured_axes'])
        self._model = runner.estimator.measurement  # None: position, z = C x (read_input)
        self._sensor_frame = p['sensor_frame_id']
        events = node.events
        #: several sensors (`sensors`): their own subscriptions, assembled per stamp
        self.fused = (FusedInputs(node, runner, outputs, sensors, report, runner.settings.dropout_wait, self._refuse)
                      if sensors else None)
        #: the measurements' subscriptions come with subscribe_measurements() (the node may hold
        #: them until its estimates reach the controller: min_estimate_subscribers)
        self.subscriptions = [
            qos.subscription(node, events, AccelStamped, qos.CONTROL, self.on_control, qos.INPUT_QOS),
            qos.subscription(node, events, AccelStamped, qos.APPLIED_CONTROL, self.on_applied, qos.INPUT_QOS),
            qos.subscription(node, events, Odometry, qos.SET_STATE, self.on_set_state)]
        self.measuring = False

    def subscribe_measurements(self) -> None:
        """Subscribe to the measurement topic (or to every sensor's), once."""
        if self.measuring:
            return
        self.measuring = True
        if self.fused is not None:
            self.subscriptions += self.fused.subscribe()
            return
        measurement_type = PointStamped if self._model is None else MEASUREMENT_CLASSES[self._model.message_form]
        self.subscriptions.append(qos.subscription(self._node, self._node.events, measurement_type, qos.MEASUREMENT,
                                                   self.on_measurement, qos.INPUT_QOS))

    def on_measurement(self, data: bytes) -> None:
        self._node.peers.saw(qos.MEASUREMENT)
        runner = self._runner
        try:
            if self._model is None:
                record, z = read_input('measurement', data, self._frame, self._axes)
                stamp_ns = record.stamp_ns
            else:  # z None: the sensor looked and measured nothing (outside its limits)
                stamp_ns, z = read_measurement(self._model, data, self._sensor_frame)
        except MessageError as error:
            return self._refuse(runner.measurement_unreadable, 'measurement', error)
        if self._node.active and runner.has_measurement(stamp_ns) and self._out.resend(stamp_ns):
            runner.repeated()  # the same sample again (a lockstep resend): the same answer
        elif z is None:
            if runner.no_measurement(stamp_ns, clock_ns(self._node)) is not None:
                self._report()
        elif runner.measurement(stamp_ns, z, clock_ns(self._node)) is not None:
            self._report()

    def on_control(self, data: bytes) -> None:
        self._node.peers.saw(qos.CONTROL)
        self._offer_control(data, 'control', self._runner.control)

    def on_applied(self, data: bytes) -> None:
        """The plant's report of the control it stepped with (``applied_control``)."""
        self._offer_control(data, 'applied control', self._runner.applied)

    def _offer_control(self, data: bytes, what: str, take) -> None:
        try:
            record, u = read_input('control', data, self._frame)
        except MessageError as error:
            return self._refuse(self._runner.control_unreadable, what, error)
        if take(record.stamp_ns, u) is not None:
            self._report()

    def on_set_state(self, data: bytes) -> None:
        try:
            record = decode_odometry(data)
            self._runner.set_state(state_of(record), record.covariance)
        except ValueError as error:  # MessageError included
            self._runner.count('set_state_rejected')
            self._node.log('warning', f'rejected set_state: {error}')
            return
        self._node.get_logger().info(f'state set to {np.array2string(self._runner.estimator.x_hat, precision=4)}')

    def _refuse(self, count, what: str, error: MessageError) -> None:
        """Count (``count(reason)``), log and report an input that could not be read."""
        count(error.reason)
        self._node.log('warning', f'rejected {what}: {error}')
        self._report()


class Outputs:
    """What the estimator publishes (estimate, spike counts, diagnostics) and the counts of it:
    lifecycle publishers, published only while the node is active. Each estimate is kept by
    stamp (also while inactive) so a repeated input can be answered again after activation."""

    def __init__(self, node, events: qos.QosEvents, p: dict, costs: CostModel | None):
        self._node, self._events = node, events
        self._frame, self._child = p['frame_id'], p['child_frame_id']
        self._estimate_qos = qos.with_liveliness(qos.PUBLISHER_QOS, p['standby_timeout'])
        self.estimate = None  # only while active: the graph shows who is active (the plant waits for one)
        self._count = qos.publisher(node, events, UInt32, qos.SPIKE_COUNT, lifecycle=True)
        self._spikes = (qos.publisher(node, events, UInt32MultiArray, qos.SPIKES, lifecycle=True)
                        if p['publish_spikes'] else None)
        self.diagnostics = DiagnosticsPublisher(node, 'estimator', p['diagnostics_period'], events, True,
                                                peers=node.peers)
        self.publishers = [self._count, self.diagnostics.publisher] + [self._spikes] * bool(self._spikes)
        self._costs = costs
        self.answers = Answers()
        self.published = self.spikes_published = self.corrected = 0
        self._published_wall = -1e9

    def open(self) -> None:
        """Create the `estimate` publisher (on activation), with a liveliness lease of
        standby_timeout: a standby learns within it that this estimator is gone."""
        if self.estimate is None:
            self.estimate = qos.HistoryPublisher(self._node, self._events, Odometry, qos.ESTIMATE, self._estimate_qos)

    def published_within(self, seconds: float) -> bool:
        return time.monotonic() - self._published_wall < seconds

    def close(self) -> None:
        """Destroy the `estimate` publisher (on deactivation): the node no longer looks active."""
        if self.estimate is not None:
            self.estimate.destroy(self._node)
            self.estimate = None

    def publish(self, estimator, stamp_ns: int, active: bool, corrected: bool = False) -> None:
        """The estimate at ``stamp_ns`` and its step's spikes; ``corrected``: the estimate of a stamp
        published before, taken again with the control the plant applied (the estimate alone:
        spike_count and spikes carry one message per step, as first taken)."""
        data = encode_odometry(estimator.x_hat, estimator.P, stamp_ns, self._frame, self._child)
        self.answers.remember(stamp_ns, data)  # inactive too: a resend after activation needs it
        if not active or self.estimate is None:
            return
        self.estimate.publish(data)
        self._published_wall = time.monotonic()
        if corrected:
            self.corrected += 1
            self.published += 1
            return
        self._count.publish(encode_uint32(estimator.spike_count))
        if self._spikes is not None:
            self._spikes.publish(encode_spikes(estimator.spikes if estimator.spiking else ()))
            self.spikes_published += 1
        self.published += 1

    def resend(self, stamp_ns: int) -> bool:
        """Publish again the estimate that answered the measurement at ``stamp_ns``."""
        if self.estimate is None:
            return False
        sent = self.answers.resend(stamp_ns, self.estimate)
        self.published += sent
        return sent

    def values(self, estimator) -> dict:
        values = {'estimates_published': self.published, 'estimates_resent': self.answers.resent,
                  'estimates_corrected': self.corrected, 'spikes_published': self.spikes_published}
        if self._costs is not None and estimator.steps:  # the last step's cost (snn_estimator.spiking.costs)
            costs = self._costs.step(estimator.spike_count)
            values.update(synops_per_step=int(costs.synops), neuron_updates_per_step=int(costs.neuron_updates),
                          dense_macs_per_step=int(costs.dense_macs),
                          energy_per_step_pj_loihi=float(energy_pj(costs, 'loihi')))
        return values


def apply_runtime_changes(runner: FilterRunner, values: dict, changes: dict) -> dict:
    """Apply ``changes`` (parameter name -> value) to a running filter, all or none: ValueError
    with the reason (a read-only parameter, a value the core refuses) changes nothing. Returns
    the new parameter values."""
    read_only = sorted(n for n in changes if n not in RUNTIME and n in {s.name for s in ESTIMATOR})
    if read_only:
        raise ValueError(f'{read_only[0]} is read-only while configured (ros2 lifecycle set /estimator '
                         'cleanup, then configure again)')
    estimator = runner.estimator
    values = dict(values, **changes)
    retune = config_values({k: changes[k] for k in estimator.RETUNABLE if k in changes})
    silencing = 'silenced_neurons' in changes or 'silenced_fraction' in changes
    if silencing:
        retune['silenced_neurons'] = silenced_set(values, estimator.neuron_count, estimator.settings.seed)
    settings = runner_settings(values)  # validate first
    if retune:
        runner.settle('parameters changed')  # a held step is never taken again with other settings
        estimator.retune(**retune)  # validated (also against the step in use) before it changes anything
    runner.replace_settings(settings)
    if estimator.spiking and silencing:
        runner.count('silencing_changes')
    return values


class EstimatorNode(ProcessHooks, LifecycleNode):
    """Converts messages, calls the core runner and filter, publishes; holds no filter math."""

    def __init__(self, **kwargs):
        super().__init__('estimator', **kwargs)
        self._p = declare(self, ESTIMATOR, check=False)  # checked by configure
        self.log = ThrottledLog(self.get_logger())
        self.events = qos.QosEvents(self)
        self._runner: FilterRunner | None = None
        self._out: Outputs | None = None
        self._owned_subscriptions: list = []
        self._measurement_hold = None  # MatchHold while the measurements wait (min_estimate_subscribers)
        self._watchdog = None
        self._active = self._announce = False
        self._announced = None  # (stamp, subscribers) of the estimate announced on activation
        self._standby = Standby()
        self._standing_by = False  # inactive, ready to take over (standby, or yielded)
        self._alive_on_estimate = 0  # live publishers on `estimate`, ours included
        self.configure_error: str | None = None
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self.create_service(Trigger, '~/reset', self._on_reset)
        self._jump = on_clock_jump_back(self, self._on_time_jump)

    @property
    def estimator(self):
        return self._runner.estimator if self._runner else None

    @property
    def runner(self) -> FilterRunner | None:
        return self._runner

    @property
    def active(self) -> bool:
        """True in the active lifecycle state: estimates are published."""
        return self._active

    def start(self) -> None:
        """autostart: configure (a failure is a configuration error: exit 2), then activate
        unless in standby."""
        if not self._p['autostart']:
            self.get_logger().info('unconfigured: waiting for ros2 lifecycle set /estimator configure')
            return
        if self.trigger_configure() != SUCCESS:
            raise ValueError(self.configure_error or 'configure failed')
        if not self._p['standby']:
            self.trigger_activate()

    # ---------------------------------------------------------------- lifecycle
    def on_configure(self, state) -> TransitionCallbackReturn:
        try:
            self._configure()
            return SUCCESS
        except Exception as error:  # lifecycle would swallow it: say what happened first
            self.configure_error = str(error) if isinstance(error, ValueError) else f'{type(error).__name__}: {error}'
            self.get_logger().error(f'configure failed: {self.configure_error}')
            self._release()
            if not isinstance(error, ValueError):  # a bad parameter (the message names it) fails
                raise
            return FAILURE

    def _configure(self) -> None:
        p = self._p = read(self, ESTIMATOR)
        check_choices(p, ESTIMATOR)
        axes = tuple(int(a) for a in p['measured_axes'])
        config = estimator_config(p)
        # position: z = C x of the model, exactly as before; any other model: H(x_hat) each step;
        # several sensors: one stacked measurement of their models (sensor_inputs)
        self._sensors = None
        if p['sensors']:
            self._sensors, measurement, deltas = declare_sensors(self, list(p['sensors']))
            config = config.replace(measurement_noise=measurement.noise, boundary_layer=deltas)
        else:
            measurement = None if p['model'] == 'position' else measurement_model(p, config.measurement_noise)
        estimator = make_estimator(p['filter_type'], config, filter_model(p, measured_axes=axes),
                                   measurement=measurement)
        estimator.prepare(p['time_step'])  # leak and P0 against the step: names the fix
        estimator.warm_up()  # its kernels compiled (or loaded) now, not at the first step
        covariance = estimator.settings.r_hat / p['measurement_noise_scale']  # R per sample
        history = (collect_history(self, p['frame_id'], axes, p['history_wait'], measurement, p['sensor_frame_id'])
                   if p['initialization'] != 'parameters' else None)
        self._runner = FilterRunner(estimator, runner_settings(p), covariance, self._publish, self.log,
                                    republish=self._republish)
        measured = [s.topic for s in self._sensors] if self._sensors else [qos.MEASUREMENT]
        self.peers = PeerWatch([*measured, qos.CONTROL, 'clock'], p['peer_timeout'], log=self.log)
        self._last_clock_ns = 0
        self._out = Outputs(self, self.events, p, CostModel.of(estimator) if estimator.spiking else None)
        self._make_endpoints()
        started = self._runner.start(p['initialization'], history)
        self.get_logger().info(
            f"{p['filter_type']} configured ({estimator.neuron_count} neurons, {p['discretization']} steps "
            f"of {p['time_step']} s, "
            + (f'axes {axes}' if measurement is None else measurement.describe()
               + ('' if self._sensors else f" in '{p['sensor_frame_id']}'"))
            + f'); start: {started}')

    def _make_endpoints(self) -> None:
        p = self._p
        self._inputs = Inputs(self, self._runner, self._out, p, self._publish_diagnostics, self._sensors)
        self._owned_subscriptions = self._inputs.subscriptions
        # measurements at once, or (min_estimate_subscribers, a node that activates itself) once
        # its estimates reach the controller: on_activate (docs/decisions.md, 41)
        self._measurement_hold = None
        if p['min_estimate_subscribers'] <= 0 or p['standby'] or not p['autostart']:
            self._inputs.subscribe_measurements()
        self._watchdog = self.create_timer(0.05, self._on_watchdog, clock=Clock(clock_type=ClockType.STEADY_TIME))
        # who else publishes estimates, by their liveliness (a standby waits for them to go, an
        # active estimator yields to another by the rule of snn_estimator.runners.filter_runner.Standby)
        self._standby, self._standing_by = Standby(), bool(p['standby'])
        self._owned_subscriptions.append(qos.liveliness_monitor(
            self, Odometry, qos.ESTIMATE, p['standby_timeout'], self._on_liveliness))

    def on_activate(self, state) -> TransitionCallbackReturn:
        super().on_activate(state)  # enables the lifecycle publishers
        self._out.open()
        if not self._inputs.measuring and self._measurement_hold is None:
            estimate, p = self._out.estimate, self._p

            def others() -> int:  # not counting this node's own liveliness monitor on `estimate`
                return estimate.get_subscription_count() - 1
            self._measurement_hold = MatchHold(self, others, p['min_estimate_subscribers'],
                                               p['match_wait'], self._inputs.subscribe_measurements,
                                               estimate.topic.topic_name, 'subscribing to the measurements')
        self._active, self._standing_by = True, False
        # a filter already running (hot swap, standby) publishes its current estimate as soon as
        # a subscriber matched (watchdog); one that waits for its first measurement publishes then
        self._announce, self._announced = self._runner.started, None
        self._on_watchdog()
        self.get_logger().info('active: publishing estimates')
        return SUCCESS

    def on_deactivate(self, state) -> TransitionCallbackReturn:
        super().on_deactivate(state)
        self._stop_holding()
        self._out.close()
        self._active = self._announce = False
        self.get_logger().info('inactive: the filter keeps running, nothing is published')
        return SUCCESS

    def on_cleanup(self, state) -> TransitionCallbackReturn:
        return self._release()

    def on_shutdown(self, state) -> TransitionCallbackReturn:
        self.close()
        return self._release()

    def on_error(self, state) -> TransitionCallbackReturn:
        return self._release()

    def _stop_holding(self) -> None:
        """Subscribe to the measurements now if still waiting for the estimate's subscribers (an
        inactive estimator keeps its filter running on them)."""
        if self._measurement_hold is not None and not self._measurement_hold.done:
            self._measurement_hold.cancel()
            self._inputs.subscribe_measurements()

    def _release(self) -> TransitionCallbackReturn:
        """Destroy every endpoint and timer and drop the filter."""
        self._active = False
        if self._measurement_hold is not None:
            self._measurement_hold.cancel()
            self._measurement_hold = None
        if self._out is not None:
            self._out.close()
        for publisher in self._out.publishers if self._out else ():
            self.destroy_lifecycle_publisher(publisher)
        for subscription in self._owned_subscriptions:
            self.destroy_subscription(subscription)
        if self._watchdog is not None:
            self.destroy_timer(self._watchdog)
        self._owned_subscriptions = []
        self._runner = self._out = self._watchdog = None
        return SUCCESS

    # ---------------------------------------------------------------- inputs
    def _on_liveliness(self, info) -> None:
        self._alive_on_estimate = info.alive_count

    def _on_watchdog(self) -> None:
        runner = self._runner
        now = clock_ns(self)
        if self._inputs.fused is not None:
            self._inputs.fused.expire()
        runner.watchdog(now)
        if now != self._last_clock_ns and self._last_clock_ns > 0:
            self.peers.saw('clock')
        self._last_clock_ns = now
        if self.peers.check():
            self._publish_diagnostics()
        estimate = self._out.estimate
        if self._announce and runner.started and estimate is not None and estimate.get_subscription_count() > 0:
            self._announce = False  # just activated: the controller can answer at once
            self._publish(runner.time_ns)
            self._announced = (runner.time_ns, estimate.get_subscription_count())
        elif self._active and self._announced and self._announced[0] == runner.time_ns:
            # the publisher is new: a subscriber that matched after the announcement (the
            # controller, best effort) gets the current estimate again until the next step
            if estimate.get_subscription_count() > self._announced[1]:
                self._out.resend(runner.time_ns)
                self._announced = (runner.time_ns, estimate.get_subscription_count())
        self._standby.update(*self._estimators_alive())
        if self._standing_by and not self._active and self._standby.takes_over(runner.started):
            self.get_logger().warning(f"standby: no other estimator is alive on '{qos.ESTIMATE}': activating")
            runner.count('standby_activations')
            self.trigger_activate()
        elif self._active and self._standby.yields(self.get_name()):
            self.get_logger().warning(f"another estimator is active on '{qos.ESTIMATE}' "
                                      f"({', '.join(self._standby.others)}): yielding (the first name in "
                                      'order publishes); standing by')
            runner.count('yields')
            self.trigger_deactivate()
            self._standing_by = True

    def _estimators_alive(self) -> tuple[int, list[str]]:
        """How many other estimators of this package are alive on `estimate` (the live
        publishers, less our own and those without a liveliness lease: ``ros2 topic pub``, a
        third-party filter) and their node names (from the graph)."""
        infos = self.get_publishers_info_by_topic(self.resolve_topic_name(qos.ESTIMATE))
        leased = [i for i in infos if i.qos_profile.liveliness_lease_duration.nanoseconds < 2 ** 62]
        own = (self.get_namespace(), self.get_name())
        others = {i.node_name for i in leased if (i.node_namespace, i.node_name) != own}
        # our own publisher counts while it published within the lease (one participant: it is
        # alive only while it publishes); counted generously, so another one is never imagined
        lease = self._p['standby_timeout']
        own_alive = self._out.estimate is not None and self._out.published_within(1.5 * lease)
        return self._alive_on_estimate - own_alive, sorted(others)

    # ---------------------------------------------------------------- outputs
    def _publish(self, stamp_ns: int) -> None:
        self._out.publish(self._runner.estimator, stamp_ns, self._active)
        self._announce = self._announce and not self._active
        if self._active and self._out.diagnostics.due(stamp_ns):
            self._publish_diagnostics(stamp_ns)

    def _republish(self, stamp_ns: int) -> None:
        """A corrected estimate (snn_estimator.runners.provisional): the same stamp again."""
        self._out.publish(self._runner.estimator, stamp_ns, self._active, corrected=True)

    def values(self) -> dict:
        """Everything the diagnostics report: the runner's counters, the outputs, the state."""
        if self._runner is None:
            return {'active': False, 'standby': self._p['standby']}
        fused = self._inputs.fused.values() if self._inputs.fused is not None else {}
        return {**self._runner.values(), **self._out.values(self._runner.estimator), **fused,
                'active': self._active, 'standby': self._p['standby']}

    def _publish_diagnostics(self, stamp_ns: int | None = None) -> None:
        stamp_ns = stamp_ns if stamp_ns is not None else self._runner.time_ns
        if stamp_ns is not None and self._active:
            self._out.diagnostics.publish(stamp_ns, self.values(), self._runner.problems())

    # ---------------------------------------------------------------- services, parameters, time
    def _on_reset(self, request, response):
        if self._runner is None:
            response.success, response.message = False, 'not configured'
            return response
        start = self._runner.reset('reset requested')
        response.success = True
        response.message = ('filter reset: the next measurement re-initialises it from the recent measurements'
                            if start == 'data' else
                            'filter reset: the next measurement starts it from initial_state, P0')
        return response

    def _on_time_jump(self, seconds: float) -> None:
        if self._runner is not None:
            self._runner.restart(f'the clock jumped back by {seconds:.3f} s', 'time_jumps')

    def _on_set_parameters(self, parameters) -> SetParametersResult:
        """Validate all changes together and apply them between two steps, or none of them.
        Before configure, every parameter may change (configure reads them)."""
        changes = {p.name: p.value for p in parameters if not p.name.startswith('qos_overrides.')}
        if self._runner is None or not changes:
            return SetParametersResult(successful=True)
        try:
            self._p = apply_runtime_changes(self._runner, self._p, changes)
        except ValueError as error:
            return SetParametersResult(successful=False, reason=str(error))
        self.get_logger().info(f'parameters changed: {changes}')
        return SetParametersResult(successful=True)

    def close(self) -> None:
        """Final diagnostics, so the totals of the run are on record."""
        if self._runner is not None and self._runner.started and self._active:
            self._publish_diagnostics()
            self._out.diagnostics.flush()


def main(args=None) -> int:
    return run_node(EstimatorNode, args, 'estimator')


if __name__ == '__main__':
    raise SystemExit(main())
