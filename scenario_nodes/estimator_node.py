"""estimator: a managed (lifecycle) node hosting one core filter (README, "Filters").

configure: validate the parameters, build the filter (network and compiled kernels), read what
the topics' publishers keep (an earlier estimator's newest estimate, the sensor's measurements,
the controller's controls) and start from it (snn_estimator.runner: hot swap, least-squares
restart, or the parameters at the first measurement); from then on the filter runs on every
input. activate: publish the estimates. deactivate: stop publishing, keep running (warm).
cleanup/shutdown: release everything. With ``autostart`` (default) the node configures and
activates itself; with ``standby`` it stays inactive until the active estimator stops
publishing, then activates itself (hot standby).

Timing (snn_estimator.runner): the estimate x_hat_k stamped t_k is published; the controller
answers with u_k; when z_k and u_k are both here the filter steps and x_hat_{k+1} is published
stamped t_k + time_step.
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

from snn_estimator import kernels, make_estimator
from snn_estimator.costs import CostModel, energy_pj
from snn_estimator.runner import FilterRunner, History, RunnerSettings

from . import qos
from .codec import (
    MessageError,
    check_frame,
    control_of,
    decode_accel,
    decode_odometry,
    decode_point,
    encode_odometry,
    encode_spikes,
    encode_uint32,
    measurement_of,
    state_of,
)
from .diagnostics import DiagnosticsPublisher
from .history import read_history
from .parameters import ESTIMATOR, check_choices, cw_model, declare, estimator_config, read, silenced_set
from .runtime import Answers, ProcessHooks, ThrottledLog, clock_ns, on_clock_jump_back, run_node

#: Parameters applied between steps through the parameter services; everything else is read-only.
RUNTIME = {'leak_rate', 'boundary_layer', 'process_noise_scale', 'measurement_noise_scale',
           'membrane_noise', 'silenced_neurons', 'silenced_fraction', 'nis_threshold', 'nis_window',
           'max_input_age'}
SUCCESS, FAILURE = TransitionCallbackReturn.SUCCESS, TransitionCallbackReturn.FAILURE


def runner_settings(p: dict) -> RunnerSettings:
    return RunnerSettings(time_step=p['time_step'], max_input_age=p['max_input_age'],
                          nis_threshold=p['nis_threshold'], nis_window=p['nis_window'],
                          initial_fit_window=p['initial_fit_window'],
                          time_jump_threshold=p['time_jump_threshold'])


def decode_history(raw: dict, frame_id: str, axes) -> History:
    """The history's samples as the runner takes them; malformed ones or ones in another frame
    are skipped (they are not inputs of this loop)."""
    readers = {qos.MEASUREMENT: (decode_point, lambda record: measurement_of(record, axes)),
               qos.CONTROL: (decode_accel, control_of),
               qos.ESTIMATE: (decode_odometry, lambda record: (state_of(record), record.covariance))}
    decoded = {topic: {} for topic in readers}
    for topic, (decode, extract) in readers.items():
        for data in raw.get(topic, ()):
            try:
                record = check_frame(decode(data), frame_id)
                decoded[topic][record.stamp_ns] = extract(record)
            except MessageError:
                continue
    return History(decoded[qos.MEASUREMENT], decoded[qos.CONTROL], decoded[qos.ESTIMATE])


class EstimatorNode(ProcessHooks, LifecycleNode):
    """Converts messages, calls the core runner and filter, publishes; holds no filter math."""

    def __init__(self, **kwargs):
        super().__init__('estimator', **kwargs)
        self._p = declare(self, ESTIMATOR, check=False)  # checked by configure
        self._log = ThrottledLog(self.get_logger())
        self._events = qos.QosEvents(self)
        self._runner: FilterRunner | None = None
        self._costs: CostModel | None = None
        self._owned_publishers: list = []
        self._owned_subscriptions: list = []
        self._watchdog = self._monitor = None
        self._active = False
        self._published = self._spikes_published = 0
        self._answers = Answers()
        self._announce = False
        self._foreign_ns = -1  # newest estimate on `estimate` from another estimator (standby)
        self._ahead_since: float | None = None
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
        except ValueError as error:  # a bad parameter: the message names it and the fix
            self.configure_error = str(error)
            self.get_logger().error(f'configure failed: {error}')
            self._release()
            return FAILURE
        except Exception as error:  # lifecycle would swallow it: say what happened first
            self.configure_error = f'{type(error).__name__}: {error}'
            self.get_logger().error(f'configure failed: {self.configure_error}')
            self._release()
            raise
        return SUCCESS

    def _configure(self) -> None:
        p = self._p = read(self, ESTIMATOR)
        check_choices(p, ESTIMATOR)
        axes = self._axes = tuple(int(a) for a in p['measured_axes'])
        estimator = make_estimator(p['filter_type'], estimator_config(p),
                                   cw_model(p, form=p['cw_model'], measured_axes=axes))
        estimator.prepare(p['time_step'])  # leak and P0 against the step: names the fix
        kernels.warm_up()
        covariance = estimator.settings.r_hat / p['measurement_noise_scale']  # R per sample
        history = self._history() if p['initialization'] != 'parameters' else None
        self._runner = FilterRunner(estimator, runner_settings(p), covariance, self._publish, self._log)
        self._costs = CostModel.of(estimator) if estimator.spiking else None
        self._make_endpoints()
        started = self._runner.start(p['initialization'], history)
        self.get_logger().info(
            f"{p['filter_type']} configured ({estimator.neuron_count} neurons, {p['discretization']} steps "
            f"of {p['time_step']} s, axes {axes}); start: {started}")

    def _history(self) -> History:
        """What the topics' publishers keep, decoded and gated like live inputs (bad samples skipped)."""
        raw = read_history(self, {qos.ESTIMATE: Odometry, qos.MEASUREMENT: PointStamped,
                                  qos.CONTROL: AccelStamped}, self._p['history_wait'])
        self.get_logger().info('history: ' + ', '.join(f"{len(raw[t])} on '{t}'" for t in raw))
        return decode_history(raw, self._p['frame_id'], self._axes)

    def _make_endpoints(self) -> None:
        events, p = self._events, self._p
        self._estimate_pub = qos.publisher(self, events, Odometry, qos.ESTIMATE, lifecycle=True)
        self._count_pub = qos.publisher(self, events, UInt32, qos.SPIKE_COUNT, lifecycle=True)
        self._spikes_pub = (qos.publisher(self, events, UInt32MultiArray, qos.SPIKES, lifecycle=True)
                            if p['publish_spikes'] else None)
        self._diagnostics = DiagnosticsPublisher(self, 'estimator', p['diagnostics_period'], events, True)
        self._owned_publishers = [self._estimate_pub, self._count_pub, self._diagnostics.publisher]
        self._owned_publishers += [self._spikes_pub] if self._spikes_pub else []
        self._owned_subscriptions = [
            qos.subscription(self, events, PointStamped, qos.MEASUREMENT, self._on_measurement, qos.INPUT_QOS),
            qos.subscription(self, events, AccelStamped, qos.CONTROL, self._on_control, qos.INPUT_QOS),
            qos.subscription(self, events, Odometry, qos.SET_STATE, self._on_set_state)]
        self._watchdog = self.create_timer(0.05, self._on_watchdog, clock=Clock(clock_type=ClockType.STEADY_TIME))
        if p['standby']:  # watch the active estimator
            self._monitor = qos.subscription(self, events, Odometry, qos.ESTIMATE, self._on_foreign_estimate)
            self._owned_subscriptions.append(self._monitor)

    def on_activate(self, state) -> TransitionCallbackReturn:
        super().on_activate(state)  # enables the lifecycle publishers
        self._active = True
        if self._monitor is not None:
            self._owned_subscriptions.remove(self._monitor)
            self.destroy_subscription(self._monitor)  # from now on `estimate` carries our own
            self._monitor = None
        # a filter already running (hot swap, standby) publishes its current estimate as soon as
        # a subscriber matched (watchdog); one that waits for its first measurement publishes then
        self._announce = self._runner.started
        self._on_watchdog()
        self.get_logger().info('active: publishing estimates')
        return SUCCESS

    def on_deactivate(self, state) -> TransitionCallbackReturn:
        super().on_deactivate(state)
        self._active = self._announce = False
        self.get_logger().info('inactive: the filter keeps running, nothing is published')
        return SUCCESS

    def on_cleanup(self, state) -> TransitionCallbackReturn:
        self._release()
        return SUCCESS

    def on_shutdown(self, state) -> TransitionCallbackReturn:
        self.close()
        self._release()
        return SUCCESS

    def on_error(self, state) -> TransitionCallbackReturn:
        self._release()
        return SUCCESS

    def _release(self) -> None:
        """Destroy every endpoint and timer and drop the filter."""
        self._active = False
        for publisher in self._owned_publishers:
            self.destroy_lifecycle_publisher(publisher)
        for subscription in self._owned_subscriptions:
            self.destroy_subscription(subscription)
        if self._watchdog is not None:
            self.destroy_timer(self._watchdog)
        self._owned_publishers, self._owned_subscriptions = [], []
        self._runner = self._watchdog = self._monitor = None

    # ---------------------------------------------------------------- inputs
    def _on_measurement(self, data: bytes) -> None:
        try:
            record = decode_point(data)
            if record.frame_id != self._p['frame_id']:
                raise MessageError('wrong_frame', f"frame '{record.frame_id}', expected '{self._p['frame_id']}'")
            z = measurement_of(record, self._axes)
        except MessageError as error:
            self._runner.measurements_received += 1
            self._runner.rejected[error.reason] += 1
            self._log('warning', f'rejected measurement: {error}')
            self._publish_diagnostics()
            return
        if (self._active and self._runner.has_measurement(record.stamp_ns)
                and self._answers.resend(record.stamp_ns, self._estimate_pub)):
            self._published += 1  # the same sample again (a lockstep resend): the same answer
            self._runner.repeated()
            return
        if self._runner.measurement(record.stamp_ns, z, clock_ns(self)) is not None:
            self._publish_diagnostics()

    def _on_control(self, data: bytes) -> None:
        try:
            record = decode_accel(data)
            if record.frame_id != self._p['frame_id']:
                raise MessageError('wrong_frame', f"frame '{record.frame_id}', expected '{self._p['frame_id']}'")
            u = control_of(record)
        except MessageError as error:
            self._runner.control_rejected[error.reason] += 1
            self._log('warning', f'rejected control: {error}')
            self._publish_diagnostics()
            return
        if self._runner.control(record.stamp_ns, u) is not None:
            self._publish_diagnostics()

    def _on_set_state(self, data: bytes) -> None:
        try:
            record = decode_odometry(data)
            self._runner.set_state(state_of(record), record.covariance)
        except ValueError as error:  # MessageError included
            self._runner.events['set_state_rejected'] += 1
            self._log('warning', f'rejected set_state: {error}')
            return
        self.get_logger().info(f'state set to {np.array2string(self._runner.estimator.x_hat, precision=4)}')

    def _on_foreign_estimate(self, data: bytes) -> None:
        try:
            self._foreign_ns = max(self._foreign_ns, decode_odometry(data).stamp_ns)
        except MessageError:
            pass

    def _on_watchdog(self) -> None:
        runner = self._runner
        now = clock_ns(self)
        runner.watchdog(now)
        if self._announce and runner.started and self._estimate_pub.get_subscription_count() > 0:
            self._announce = False  # just activated: the controller can answer at once
            self._publish(runner.time_ns)
        if self._p['standby'] and not self._active and runner.started:
            self._standby_check(now)

    def _standby_check(self, now_ns: int) -> None:
        """Activate when our estimate is newer than the active estimator's for standby_timeout
        wall seconds, or by two steps of simulated time (it stopped publishing)."""
        if runner_ahead := self._runner.time_ns > self._foreign_ns:
            self._ahead_since = self._ahead_since or time.monotonic()
        else:
            self._ahead_since = None
            return
        lag_ns = self._runner.time_ns - max(self._foreign_ns, self._runner.start_ns)
        waited = time.monotonic() - self._ahead_since
        if runner_ahead and (waited >= self._p['standby_timeout'] or lag_ns >= 2 * int(self._p['time_step'] * 1e9)):
            self.get_logger().warning(
                f'standby: no estimate newer than t = {self._foreign_ns * 1e-9:.3f} s on '
                f"'{qos.ESTIMATE}' for {waited:.3f} s: activating")
            self._runner.events['standby_activations'] += 1
            self.trigger_activate()

    # ---------------------------------------------------------------- outputs
    def _publish(self, stamp_ns: int) -> None:
        est = self._runner.estimator
        data = encode_odometry(est.x_hat, est.P, stamp_ns, self._p['frame_id'], self._p['child_frame_id'])
        self._answers.remember(stamp_ns, data)  # inactive too: a resend after activation needs it
        if not self._active:
            return
        self._announce = False
        self._estimate_pub.publish(data)
        self._count_pub.publish(encode_uint32(est.spike_count))
        if self._spikes_pub is not None:
            self._spikes_pub.publish(encode_spikes(est.spikes if est.spiking else ()))
            self._spikes_published += 1
        self._published += 1
        if self._diagnostics.due(stamp_ns):
            self._publish_diagnostics(stamp_ns)

    def values(self) -> dict:
        values = self._runner.values() if self._runner else {}
        if self._costs is not None and self._runner.estimator.steps:  # the last step's cost
            costs = self._costs.step(self._runner.estimator.spike_count)
            values.update(synops_per_step=int(costs.synops), neuron_updates_per_step=int(costs.neuron_updates),
                          dense_macs_per_step=int(costs.dense_macs),
                          energy_per_step_pj_loihi=float(energy_pj(costs, 'loihi')))
        values.update(estimates_published=self._published, estimates_resent=self._answers.resent,
                      spikes_published=self._spikes_published,
                      active=self._active, standby=self._p['standby'])
        return values

    def _publish_diagnostics(self, stamp_ns: int | None = None) -> None:
        runner = self._runner
        stamp_ns = stamp_ns if stamp_ns is not None else runner.time_ns
        if stamp_ns is not None and self._active:
            self._diagnostics.publish(stamp_ns, self.values(), runner.problems())

    # ---------------------------------------------------------------- services, parameters, time
    def _on_reset(self, request, response):
        if self._runner is None:
            response.success, response.message = False, 'not configured'
            return response
        self._runner.restart('reset requested', 'resets')
        response.success = True
        response.message = 'filter reset: the next measurement starts it from initial_state, P0'
        return response

    def _on_time_jump(self, seconds: float) -> None:
        if self._runner is not None:
            self._runner.restart(f'the clock jumped back by {seconds:.3f} s', 'time_jumps')

    def _on_set_parameters(self, parameters) -> SetParametersResult:
        """Validate all changes together and apply them between two steps, or none of them.
        Before configure, every parameter may change (configure reads them)."""
        changes = {p.name: p.value for p in parameters if not p.name.startswith('qos_overrides.')}
        if self._runner is None or not changes:  # before configure: configure reads them
            return SetParametersResult(successful=True)
        read_only = sorted(n for n in changes if n not in RUNTIME and n in {s.name for s in ESTIMATOR})
        if read_only:
            return SetParametersResult(successful=False, reason=f'{read_only[0]} is read-only while configured '
                                       '(ros2 lifecycle set /estimator cleanup, then configure again)')
        estimator = self._runner.estimator
        values = dict(self._p, **changes)
        retune = {k: changes[k] for k in estimator.RETUNABLE if k in changes}
        if 'boundary_layer' in retune:
            retune['boundary_layer'] = list(retune['boundary_layer'])
        try:  # validate everything before changing anything
            silenced = silenced_set(values, estimator.neuron_count, estimator.settings.seed)
            settings = runner_settings(values)
            if retune:  # validated first (also against time_step); raises without changing
                estimator.retune(**retune)
        except ValueError as error:
            return SetParametersResult(successful=False, reason=str(error))
        self._runner.replace_settings(settings)
        if estimator.spiking and ('silenced_neurons' in changes or 'silenced_fraction' in changes):
            estimator.silence(silenced)
            self._runner.events['silencing_changes'] += 1
        self._p = values
        self.get_logger().info(f'parameters changed: {changes}')
        return SetParametersResult(successful=True)

    def close(self) -> None:
        """Final diagnostics, so the totals of the run are on record."""
        if self._runner is not None and self._runner.started and self._active:
            self._publish_diagnostics()
            self._diagnostics.flush()


def main(args=None) -> int:
    return run_node(EstimatorNode, args, 'estimator')


if __name__ == '__main__':
    raise SystemExit(main())
