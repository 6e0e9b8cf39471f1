"""cw_plant: the relative-motion truth (``dynamics_model``: Clohessy-Wiltshire, or the nonlinear
motion about a circular orbit). Owns simulated time and publishes /clock.

Start: with ``wait_for_loop`` the scenario (x0, the clock) starts only once the loop is there:
'truth' matched by ``min_truth_subscribers`` subscriptions and 'measurement', 'estimate' and
'control' each with a publisher and a subscription, then ``start_delay`` wall seconds. It says
what it waits for. When and with which control it steps (lockstep, realtime, resend, timeouts)
is decided by :class:`snn_estimator.runners.plant_runner.PlantRunner`; this node converts, runs the
timers and publishes. The run ends after ``duration``, at the docking port (``stop_at_port``:
contact, as the truth sees it) or after the step in which the approach guidance ended without
contact (``end_on_guidance``).
"""

from __future__ import annotations

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import AccelStamped
from nav_msgs.msg import Odometry
from rcl_interfaces.msg import SetParametersResult
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rosgraph_msgs.msg import Clock as ClockMessage

from snn_estimator.models import relative_motion
from snn_estimator.plant.approach import at_port, port_contact
from snn_estimator.plant.truth import Plant
from snn_estimator.runners.peers import PeerWatch
from snn_estimator.runners.plant_runner import PlantRunner, PlantSettings, StartGate

from . import qos
from .codec import (
    MessageError,
    check_frame,
    control_of,
    decode_accel,
    encode_accel,
    encode_clock,
    encode_odometry,
)
from .conversions import guidance_end
from .diagnostics import DiagnosticsPublisher, Rejections
from .parameter_tables import PLANT
from .ros_parameters import declare
from .runtime import ProcessHooks, ThrottledLog, run_node

#: Wall-clock seconds between two notices of what the plant is still waiting for.
STARTUP_NOTICE_PERIOD = 5.0


def loop_missing(node, truth_subscribers: int, min_truth_subscribers: int, whole_loop: bool,
                 measurement_topics=(qos.MEASUREMENT,)) -> list[str]:
    """What the loop still lacks before the plant may start (empty: ready), from the graph:
    matched subscriptions on 'truth' and, with ``whole_loop``, a node in each role of the loop,
    recognised by what it subscribes and publishes (a recorder or ``ros2 topic echo`` on a
    topic does not stand in for the controller): a sensor on each of ``measurement_topics``, an
    estimator subscribing to all of them."""
    missing = []
    if truth_subscribers < min_truth_subscribers:
        missing.append(f"{min_truth_subscribers - truth_subscribers} subscription(s) on '{qos.TRUTH}'")
    if not whole_loop:
        return missing

    def nodes(info) -> set:
        return {(endpoint.node_namespace, endpoint.node_name) for endpoint in info}

    def publishing(topic):
        return nodes(node.get_publishers_info_by_topic(node.resolve_topic_name(topic)))

    def subscribing(topic):
        return nodes(node.get_subscriptions_info_by_topic(node.resolve_topic_name(topic)))

    estimator = subscribing(qos.CONTROL) & publishing(qos.ESTIMATE)
    sensors = []
    for topic in measurement_topics:
        sensors.append((f'a sensor (truth -> {topic})', subscribing(qos.TRUTH) & publishing(topic)))
        estimator &= subscribing(topic)
    roles = (*sensors, (f"an estimator ({', '.join(measurement_topics)}, control -> estimate)", estimator),
             ('a controller (estimate -> control)', subscribing(qos.ESTIMATE) & publishing(qos.CONTROL)))
    return missing + [role for role, present in roles if not present]


class PlantNode(ProcessHooks, Node):
    """Wraps :class:`snn_estimator.plant.truth.Plant` in a :class:`PlantRunner`; holds no dynamics
    and no stepping logic of its own."""

    NAME, SPECS = 'cw_plant', PLANT

    def __init__(self, **kwargs):
        super().__init__(self.NAME, **kwargs)
        p = declare(self, self.SPECS)
        self._p = p
        self._log = ThrottledLog(self.get_logger())
        self._runner = PlantRunner(self.make_plant(p), plant_settings(p), self._publish_sample,
                                   self._finish, self._log, applied=self._publish_applied,
                                   stop=at_port if p['stop_at_port'] else None)
        self._rejected = Rejections()
        self._events = qos.QosEvents(self)
        self._truth_pub = qos.publisher(self, self._events, Odometry, qos.TRUTH)
        self._applied_pub = qos.publisher(self, self._events, AccelStamped, qos.APPLIED_CONTROL)
        self._clock_pub = (self.create_publisher(ClockMessage, qos.CLOCK, qos.CLOCK_QOS)
                           if p['publish_clock'] else None)
        self._peers = PeerWatch([qos.CONTROL], p['peer_timeout'], log=self._log)
        self._diagnostics = DiagnosticsPublisher(self, self.NAME, p['diagnostics_period'], self._events,
                                                 peers=self._peers)
        self.create_timer(0.1, self._on_peer_check, clock=Clock(clock_type=ClockType.STEADY_TIME))
        qos.subscription(self, self._events, AccelStamped, qos.CONTROL, self._on_control)
        if p['end_on_guidance']:  # reliable: an end is said once
            self.create_subscription(DiagnosticArray, qos.GUIDANCE, self._on_guidance, qos.LISTENER_QOS)
        self.add_on_set_parameters_callback(self._on_set_parameters)
        steady = Clock(clock_type=ClockType.STEADY_TIME)
        if self._runner.lockstep:
            self.create_timer(min(0.05, p['control_timeout'] / 4), self._runner.watchdog, clock=steady)
        else:
            self.create_timer(p['time_step'] / p['real_time_factor'], self._runner.tick, clock=steady)
        total = self._runner.total_steps
        truth = getattr(self._runner.plant.model, 'dynamics_model', 'Basilisk')
        self.get_logger().info(
            f"{p['mode']} {truth} truth, dt {p['time_step']} s, n = {self._runner.plant.model.mean_motion:.4e} "
            f"rad/s, {'until stopped' if total is None else f'{total} steps'}")
        self._gate = StartGate(p['start_delay'], STARTUP_NOTICE_PERIOD, self._log)
        self._readiness = self.create_timer(0.02, self._check_ready, clock=steady)

    def make_plant(self, p: dict):
        """The core truth the parameters describe: the ``dynamics_model`` with process noise."""
        model = relative_motion(p['dynamics_model'], orbit_radius=p['orbit_radius'], mu=p['gravitational_parameter'])
        return Plant(model, p['initial_state'], p['process_noise'], seeds=[p['seed']])

    def _check_ready(self) -> None:
        """Start the scenario (publish x0) once the loop is there (wait_for_loop) and
        start_delay has passed."""
        p = self._p
        missing = loop_missing(self, self._truth_pub.get_subscription_count(), p['min_truth_subscribers'],
                               p['wait_for_loop'], p['measurement_topics'])
        if self._runner.started or not self._gate.check(missing):
            return
        self.destroy_timer(self._readiness)
        self.get_logger().info(f'the loop is there: starting the scenario at t = {self._runner.t_ns * 1e-9:.3f} s')
        self._runner.begin()

    # ---------------------------------------------------------------- events
    def _on_peer_check(self) -> None:
        if self._peers.check() and not self._p['paused']:
            self._publish_diagnostics()

    def _on_control(self, data: bytes) -> None:
        self._peers.saw(qos.CONTROL)
        try:
            control = check_frame(decode_accel(data), self._p['frame_id'])
            u = control_of(control)
        except MessageError as error:
            self._reject(error.reason, str(error))
            return
        rejected = self._runner.control(control.stamp_ns, u)
        if rejected is not None:
            self._reject(*rejected)

    def _on_guidance(self, msg: DiagnosticArray) -> None:
        """The guidance ended (abort, no-go): the run ends after the step from its stamp."""
        stamp_ns = guidance_end(msg)
        if stamp_ns is not None:
            self.get_logger().info(f'the guidance ended at t = {stamp_ns * 1e-9:.3f} s: ending the run')
            self._runner.end_after(stamp_ns)

    def _on_set_parameters(self, parameters) -> SetParametersResult:
        for parameter in parameters:
            if parameter.name == 'paused':
                self._p['paused'] = bool(parameter.value)
                self._runner.set_paused(bool(parameter.value))
        return SetParametersResult(successful=True)

    # ---------------------------------------------------------------- outputs
    def _publish_applied(self, stamp_ns: int, u) -> None:
        self._applied_pub.publish(encode_accel(u, stamp_ns, self._p['frame_id']))

    def _publish_sample(self, stamp_ns: int, resend: bool) -> None:
        if self._clock_pub is not None:
            self._clock_pub.publish(encode_clock(stamp_ns))
        x = self._runner.plant.x[0]
        self._truth_pub.publish(encode_odometry(x, None, stamp_ns, self._p['frame_id'], self._p['child_frame_id']))
        if not resend and self._diagnostics.due(stamp_ns):
            self._publish_diagnostics()

    def _finish(self) -> None:
        self._publish_diagnostics()
        values = self.values()
        if self._runner.ended_by == 'stop':
            self.get_logger().info(f"contact at t = {values['sim_time']:.1f} s: closing speed "
                                   f"{values['contact_closing_speed']:.4f} m/s, lateral offset "
                                   f"{values['contact_lateral']:.4f} m")
        self.get_logger().info(
            f"done: {values['steps']} steps, {values['sim_time']:.1f} s simulated in "
            f"{values['wall_time']:.2f} s (x{values['real_time_factor']:.0f}), "
            f"{values['control_timeouts']} control timeouts, final range {values['range']:.4f} m")
        # run_node flushes the publishers before the process ends, so subscribers get the end
        self.done = self._p['exit_when_done']

    def close(self) -> None:
        """Stopped before the last step (SIGINT/SIGTERM): the totals so far go on record too
        (run_node then waits for the subscribers to acknowledge them)."""
        if not self._runner.finished:
            self._publish_diagnostics()

    # ---------------------------------------------------------------- reporting
    def _reject(self, reason: str, detail: str) -> None:
        self._rejected[reason] += 1
        self.get_logger().warning(f'rejected control ({reason}): {detail}', throttle_duration_sec=5.0)
        self._publish_diagnostics()

    def values(self) -> dict:
        """The runner's counts, rejections, and at the port (stop_at_port) the contact conditions."""
        contact = ({f'contact_{k}': v for k, v in port_contact(self._runner.plant.x[0]).items()}
                   if self._runner.ended_by == 'stop' else {})
        return {**self._runner.values(), **self._rejected.as_values('controls'), **contact}

    def _publish_diagnostics(self) -> None:
        problems = self._runner.problems()
        if self._rejected.total:
            problems.append(f'{self._rejected.total} controls rejected')
        self._diagnostics.publish(self._runner.t_ns, self.values(), problems)


def plant_settings(p: dict) -> PlantSettings:
    """The runner's settings from the plant's parameters."""
    return PlantSettings(time_step=p['time_step'], mode=p['mode'], duration=p['duration'],
                         start_time=p['start_time'], control_timeout=p['control_timeout'],
                         resend_period=p['resend_period'], control_validity=p['control_validity'],
                         notice_period=STARTUP_NOTICE_PERIOD)


def main(args=None) -> int:
    return run_node(PlantNode, args, 'cw_plant')



if __name__ == '__main__':
    raise SystemExit(main())
