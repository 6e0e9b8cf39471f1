"""lqr_controller: u = -K x_hat (Eq. 42) from each state estimate, stamped with the estimate's time.

With ``guidance`` approach the setpoint is the approach guidance's (snn_estimator.plant.approach:
holds, go/no-go from the estimate and its covariance, corridor, CAM), u = u_ff - K (x_hat -
x_ref) by the same core call as the offline loop (approach_control), with the observability
manoeuvre ``observability_manoeuvre`` names (the angles suite's out-of-plane hop); each guidance
event goes out on `guidance` (diagnostic_msgs/DiagnosticArray, status approach_guidance) stamped
with the estimate's time, before the control of that step.

Safe mode: zero thrust at every simulated step, said once and reported, while the estimator is
down (no usable estimate for ``estimate_timeout`` simulated seconds), the sensors are down (no
message on any of ``measurement_topics`` for as long: the estimates are predictions) or the
clock stopped (``peer_timeout`` wall seconds: the plant is gone); it ends when the cause does.
"""

from __future__ import annotations

from functools import partial

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import AccelStamped
from nav_msgs.msg import Odometry
from rcl_interfaces.msg import SetParametersResult
from rclpy.clock import Clock, ClockType
from rclpy.node import Node

from snn_estimator.plant.approach import approach_control
from snn_estimator.plant.control import lqr_control, lqr_gain
from snn_estimator.runners.gates import NewestFirst
from snn_estimator.runners.peers import OK, PeerWatch
from snn_estimator.validation import as_matrix, as_vector

from . import qos
from .codec import NS, MessageError, decode_stamp, encode_accel, read_input, seconds_to_ns
from .conversions import guidance_event
from .core_objects import approach_guidance, cw_model, filter_model
from .diagnostics import DiagnosticsPublisher, Rejections
from .parameter_tables import CONTROLLER
from .ros_parameters import declare
from .runtime import Answers, MatchHold, ProcessHooks, ThrottledLog, clock_ns, on_clock_jump_back, run_node

GAIN_PARAMETERS = {'lqr_state_weight', 'lqr_input_weight', 'gain'}


def sensor_topics(topics) -> list[str]:
    """The ``measurement_topics`` parameter checked: at least one, each named once."""
    topics = [str(topic) for topic in topics]
    if not topics or not all(topics) or len(set(topics)) != len(topics):
        raise ValueError(f'measurement_topics {topics}: give each sensor topic once (e.g. [camera, lidar], '
                         f'the topics of the estimator\'s sensors), at least one')
    return topics


def design_gain(values: dict) -> np.ndarray:
    """K from the ``gain`` parameter, or designed by python-control from Qc and Rc on the
    ``dynamics_model`` (its A(0))."""
    if values.get('gain'):
        return as_matrix(values['gain'], (3, 6), 'gain (K)')
    model = filter_model(values)
    return lqr_gain(model, values['lqr_state_weight'], values['lqr_input_weight'])


class ControllerNode(ProcessHooks, Node):
    """Wraps :func:`snn_estimator.plant.control.lqr_control`."""

    def __init__(self, **kwargs):
        super().__init__('lqr_controller', **kwargs)
        p = declare(self, CONTROLLER)
        self._p = p
        self._gain = design_gain(p)
        self._law = self._control_law()
        self._setpoint = as_vector(p['setpoint'], 6, 'setpoint')
        self._guidance = self._make_guidance()
        self._events_sent = 0  # the guidance's events published so far
        self._published = 0
        self._safe_steps = 0
        self._safe = False
        self._safe_reason = ''
        self._time_jumps = 0
        self._rejected = Rejections()
        self._gate = NewestFirst(p['time_jump_threshold'], p['max_input_age'], p['time_step'])
        self._now = partial(clock_ns, self)  # the gate reads the clock only when it needs it
        self._last_estimate_ns = None  # simulated time of the newest usable estimate
        self._last_measurement_ns = None  # and of the newest measurement (is the sensor there?)
        self._last_clock_ns = 0
        self._sensor_topics = sensor_topics(p['measurement_topics'])
        self._peers = PeerWatch([qos.ESTIMATE, *self._sensor_topics, 'clock'], p['peer_timeout'],
                                log=ThrottledLog(self.get_logger()))
        self._answers = Answers()
        self._events = qos.QosEvents(self)
        self._pub = qos.HistoryPublisher(self, self._events, AccelStamped, qos.CONTROL)
        self._guidance_pub = (qos.publisher(self, self._events, DiagnosticArray, qos.GUIDANCE)
                              if self._guidance is not None else None)
        self._diagnostics = DiagnosticsPublisher(self, 'lqr_controller', p['diagnostics_period'], self._events,
                                                 peers=self._peers)
        # estimates only once the controls reach min_control_subscribers (docs/decisions.md, 41)
        self._hold = MatchHold(self, self._pub.get_subscription_count, p['min_control_subscribers'],
                               p['match_wait'], self._subscribe_estimate, self._pub.topic.topic_name,
                               f"subscribing to '{qos.ESTIMATE}'")
        # any sensor model's message (PointStamped, Vector3Stamped, Range): only its stamp is read
        self._measurements = [qos.PublishedTypeSubscription(self, self._events, topic,
                                                            partial(self._on_measurement, topic))
                              for topic in self._sensor_topics]
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self._jump = on_clock_jump_back(self, self._on_time_jump)
        self.create_timer(0.05, self._on_watchdog, clock=Clock(clock_type=ClockType.STEADY_TIME))
        self._safe_timer = None  # a simulated-time timer, only while in safe mode
        self._log_gain()

    def _subscribe_estimate(self) -> None:
        qos.subscription(self, self._events, Odometry, qos.ESTIMATE, self._on_estimate)

    @property
    def gain(self) -> np.ndarray:
        return self._gain.copy()

    @property
    def safe_mode(self) -> bool:
        """True while no usable estimate came for estimate_timeout: zero thrust."""
        return self._safe

    def _log_gain(self) -> None:
        model = cw_model(self._p)
        poles = np.linalg.eigvals(model.jacobian(np.zeros(6), np.zeros(3)) - model.input_matrix @ self._gain)
        self.get_logger().info(
            f'LQR gain K = {np.array2string(self._gain, precision=4, max_line_width=200)}; '
            f'slowest closed-loop pole {poles.real.max():.4f} 1/s')

    def _reject(self, reason: str, detail: str, stamp_ns: int) -> None:
        self._rejected[reason] += 1
        self.get_logger().warning(f'rejected estimate ({detail})', throttle_duration_sec=5.0)
        self._publish_diagnostics(max(stamp_ns, self._gate.last_ns or 0))

    def _on_measurement(self, topic: str, data: bytes) -> None:
        """Only whether a sensor is there: the newest stamp of any of them."""
        self._peers.saw(topic)
        try:
            stamp_ns = decode_stamp(data)
        except MessageError:
            return
        self._last_measurement_ns = max(stamp_ns, self._last_measurement_ns or stamp_ns)

    def _on_estimate(self, data: bytes) -> None:
        self._peers.saw(qos.ESTIMATE)
        try:
            estimate, x_hat = read_input('state', data, self._p['frame_id'])
        except MessageError as error:
            self._reject(error.reason, str(error), 0)
            return
        stamp_ns = estimate.stamp_ns
        kind = self._gate.classify(stamp_ns, self._now)
        if kind == 'repeat':
            if self._answers.resend(stamp_ns, self._pub):  # the estimate came again: same control
                self._published += 1
                self._publish_diagnostics(self._gate.last_ns)
            else:
                self._reject('not_newer', f'stamp {stamp_ns * 1e-9:.3f} s did not advance', stamp_ns)
            return
        if kind in ('too_old', 'future'):  # accepted, a future one would blind the watchdog
            self._reject(kind, f'stamp {stamp_ns * 1e-9:.3f} s against the clock at '
                         f'{clock_ns(self) * 1e-9:.3f} s', stamp_ns)
            return
        if kind == 'restarted':
            self.get_logger().warning('estimate time went back: starting over')
            self._time_jumps += 1
            self._answers.clear()
        self._last_estimate_ns = stamp_ns
        reason = self._unsafe(clock_ns(self))
        if self._safe and reason is None:
            self._leave_safe_mode(f'estimates are back at t = {stamp_ns * 1e-9:.3f} s')
        elif reason is not None and not self._safe:
            self._enter_safe_mode(reason)
        if self._safe:
            self._publish_control(np.zeros(3), stamp_ns)  # predicted without a sensor: no thrust
            return
        if self._guidance is None:
            self._publish_control(self._law(x_hat - self._setpoint), stamp_ns)
            return
        u = approach_control(self._guidance, self._gain, stamp_ns / NS, self._p['time_step'], x_hat,
                             estimate.covariance)
        self._publish_guidance_events(stamp_ns)
        self._publish_control(u, stamp_ns)

    def _make_guidance(self):
        """The core approach guidance (guidance approach), or None (steer to setpoint)."""
        if self._p['guidance'] == 'none':
            if self._p['observability_manoeuvre'] != 'none':
                raise ValueError(f"observability_manoeuvre {self._p['observability_manoeuvre']} is flown by the "
                                 'approach guidance: set guidance approach, or observability_manoeuvre none')
            return None
        if self._p['controller_type'] != 'lqr':
            raise ValueError(f"guidance approach flies the LQR (controller_type lqr), not "
                             f"{self._p['controller_type']}: set controller_type lqr")
        return approach_guidance(self._p)

    def _publish_guidance_events(self, stamp_ns: int) -> None:
        """The guidance's new events, one message each (stamped at the estimate's time)."""
        for event in self._guidance.events[self._events_sent:]:
            self._guidance_pub.publish(guidance_event(stamp_ns, self.get_fully_qualified_name(), event.name,
                                                      self._guidance.phase, event.detail))
            level = 'error' if event.name == 'abort' else 'info'
            getattr(self.get_logger(), level)(f'guidance at t = {event.time:.1f} s: {event.name} '
                                              f'(phase {self._guidance.phase})')
        self._events_sent = len(self._guidance.events)

    def _control_law(self):
        """u(x_hat - setpoint): lqr_control, or a SpikingLQR network (controller_type snn_lqr)."""
        if self._p['controller_type'] != 'snn_lqr':
            return partial(lqr_control, self._gain)
        from snn_estimator.spiking.lqr import SpikingLQR  # numba: loaded only for the spiking law
        network = SpikingLQR(self._gain, self._p['snn_lqr_neurons'], self._p['snn_lqr_leak'])
        return partial(network.control, dt=self._p['time_step'])

    def _unsafe(self, now: int) -> str | None:
        """Why the loop is not safe to steer now (None: it is)."""
        timeout = seconds_to_ns(self._p['estimate_timeout'])
        if self._last_estimate_ns is None:
            return None  # not started
        if now > 0 and now - self._last_estimate_ns > timeout:
            return f'no estimate since t = {self._last_estimate_ns * 1e-9:.3f} s'
        if self._last_measurement_ns is not None and now > 0 and now - self._last_measurement_ns > timeout:
            return (f'no measurement since t = {self._last_measurement_ns * 1e-9:.3f} s on '
                    f"{', '.join(self._sensor_topics)} (the estimates are predictions)")
        if self._peers.levels['clock'] != OK:
            return f'the clock stopped at t = {now * 1e-9:.3f} s'
        return None

    def _on_watchdog(self) -> None:
        """Wall-clock check: peers, and whether safe mode starts or ends."""
        now = clock_ns(self)
        if now != self._last_clock_ns and self._last_clock_ns > 0:
            self._peers.saw('clock')
        self._last_clock_ns = now
        changed = self._peers.check()
        reason = self._unsafe(now)
        if reason is not None and not self._safe:
            self._enter_safe_mode(reason)
            self._on_safe_step()
            changed = True
        elif reason is None and self._safe:
            self._leave_safe_mode(f"{self._safe_reason.split(' (')[0]}: over")
            changed = True
        if changed and self._gate.last_ns is not None:
            self._publish_diagnostics(max(now, self._gate.last_ns))

    def _enter_safe_mode(self, reason: str) -> None:
        self._safe, self._safe_reason = True, reason
        self.get_logger().error(f'{reason}: safe mode, zero thrust')
        self._safe_timer = self.create_timer(self._p['time_step'], self._on_safe_step)

    def _on_safe_step(self) -> None:
        """Simulated-time timer while in safe mode: zero thrust for every new step."""
        now = clock_ns(self)
        if self._safe and (self._gate.last_ns is None or now > self._gate.last_ns):
            self._safe_steps += 1
            self._gate.last_ns = now
            self._publish_control(np.zeros(3), now)

    def _leave_safe_mode(self, why: str) -> None:
        self._safe = False
        if self._safe_timer is not None:
            self.destroy_timer(self._safe_timer)
            self._safe_timer = None
        self.get_logger().info(f'{why}: leaving safe mode')

    def _publish_control(self, u: np.ndarray, stamp_ns: int) -> None:
        data = encode_accel(u, stamp_ns, self._p['frame_id'])
        self._pub.publish(data)
        self._answers.remember(stamp_ns, data)
        self._published += 1
        if self._diagnostics.due(stamp_ns):
            self._publish_diagnostics(stamp_ns)

    def _on_time_jump(self, seconds: float) -> None:
        self.get_logger().warning(f'the clock jumped back by {seconds:.3f} s: starting over')
        self._time_jumps += 1
        self._gate.reset()
        self._law = self._control_law()  # a spiking network starts over too
        self._guidance, self._events_sent = self._make_guidance(), 0  # so does the approach
        self._last_estimate_ns = None
        self._answers.clear()
        if self._safe:
            self._leave_safe_mode('clock reset')

    def _on_set_parameters(self, parameters) -> SetParametersResult:
        """Gains change between two estimates, after the new ones were checked."""
        changes = {p.name: p.value for p in parameters if not p.name.startswith('qos_overrides.')}
        if not GAIN_PARAMETERS & set(changes):
            if 'estimate_timeout' in changes and changes['estimate_timeout'] <= 0:
                return SetParametersResult(successful=False, reason='estimate_timeout must be > 0')
            try:
                setpoint = as_vector(changes.get('setpoint', self._p['setpoint']), 6, 'setpoint')
            except ValueError as error:
                return SetParametersResult(successful=False, reason=str(error))
            self._p, self._setpoint = dict(self._p, **changes), setpoint
            self._gate.max_input_age = self._p['max_input_age']
            return SetParametersResult(successful=True)
        values = dict(self._p, **changes)
        try:
            gain = design_gain(values)
        except ValueError as error:
            return SetParametersResult(successful=False, reason=str(error))
        self._p, self._gain = values, gain
        self._law = self._control_law()
        self._log_gain()
        return SetParametersResult(successful=True)

    def _publish_diagnostics(self, stamp_ns: int) -> None:
        values = {'controls_published': self._published, 'controls_resent': self._answers.resent,
                  'safe_mode': self._safe,
                  'safe_mode_steps': self._safe_steps, 'time_jumps': self._time_jumps,
                  **({'guidance_phase': self._guidance.phase} if self._guidance is not None else {}),
                  **self._rejected.as_values('estimates')}
        problems = [f'{self._rejected.total} estimates rejected'] if self._rejected.total else []
        if self._safe:
            problems.append(f'safe mode: zero thrust ({self._safe_reason})')
        self._diagnostics.publish(stamp_ns, values, problems)

    def close(self) -> None:
        """Final diagnostics, so the totals of the run are on record."""
        if self._gate.last_ns is not None:
            self._publish_diagnostics(self._gate.last_ns)  # run_node waits for its acknowledgement


def main(args=None) -> int:
    return run_node(ControllerNode, args, 'lqr_controller')


if __name__ == '__main__':
    raise SystemExit(main())
