"""cw_plant: the Clohessy-Wiltshire truth. Owns simulated time and publishes /clock.

Start: with ``wait_for_loop`` the scenario (x0, the clock) starts only once the loop is there:
'truth' matched by ``min_truth_subscribers`` subscriptions and 'measurement', 'estimate' and
'control' each with a publisher and a subscription, then ``start_delay`` wall seconds. It says
what it waits for. lockstep: publish x_k at t_k, wait for the control stamped t_k, step, repeat
(a control that does not come within ``control_timeout`` wall-clock seconds is replaced by the
last one and counted). realtime: step on a wall-clock timer at ``real_time_factor`` with the
latest control.
"""

from __future__ import annotations

import time

import numpy as np
from geometry_msgs.msg import AccelStamped
from nav_msgs.msg import Odometry
from rcl_interfaces.msg import SetParametersResult
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rosgraph_msgs.msg import Clock as ClockMessage

from snn_estimator.blocks import Plant

from . import qos
from .codec import MessageError, control_of, decode_accel, encode_clock, encode_odometry, seconds_to_ns
from .diagnostics import DiagnosticsPublisher, Rejections
from .parameters import PLANT, cw_model, declare
from .runtime import ProcessHooks, run_node

#: Steps at the start during which the lockstep plant waits for controls without a timeout.
STARTUP_STEPS = 10
#: Wall-clock seconds between two notices of what the plant is still waiting for.
STARTUP_NOTICE_PERIOD = 5.0


def loop_missing(node, truth_subscribers: int, min_truth_subscribers: int, whole_loop: bool) -> list[str]:
    """What the loop still lacks before the plant may start (empty: ready), from the graph:
    matched subscriptions on 'truth' and, with ``whole_loop``, a node in each role of the loop,
    recognised by what it subscribes and publishes (a recorder or ``ros2 topic echo`` on a
    topic does not stand in for the controller)."""
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

    roles = (('a sensor (truth -> measurement)', subscribing(qos.TRUTH) & publishing(qos.MEASUREMENT)),
             ('an estimator (measurement, control -> estimate)',
              subscribing(qos.MEASUREMENT) & subscribing(qos.CONTROL) & publishing(qos.ESTIMATE)),
             ('a controller (estimate -> control)', subscribing(qos.ESTIMATE) & publishing(qos.CONTROL)))
    return missing + [role for role, present in roles if not present]


class PlantNode(ProcessHooks, Node):
    """Wraps :class:`snn_estimator.blocks.Plant`; holds no dynamics of its own."""

    NAME, SPECS = 'cw_plant', PLANT

    def __init__(self, **kwargs):
        super().__init__(self.NAME, **kwargs)
        p = declare(self, self.SPECS)
        self._p = p
        self._plant = self.make_plant(p)
        self._dt = p['time_step']
        self._dt_ns = seconds_to_ns(self._dt)
        self._t_ns = self._start_ns = seconds_to_ns(p['start_time'])
        self._total_steps = int(round(p['duration'] / self._dt)) if p['duration'] > 0 else None
        self._lockstep = p['mode'] == 'lockstep'
        self._control = np.zeros(3)
        self._step = 0
        self._timeouts = 0
        self._controls_received = 0
        self._rejected = Rejections()
        self._truth_published = 0
        self._truth_resent = 0
        self._late_controls = 0  # realtime: steps taken with a held control
        self._sent_at = 0.0
        self._waiting_since = None
        self._started_wall = None
        self._finished_wall = None
        self._finished_unix = 0.0
        self._held = None
        self._early: dict[int, np.ndarray] = {}

        self._events = qos.QosEvents(self)
        self._truth_pub = qos.publisher(self, self._events, Odometry, qos.TRUTH)
        self._clock_pub = (self.create_publisher(ClockMessage, qos.CLOCK, qos.CLOCK_QOS)
                           if p['publish_clock'] else None)
        self._diagnostics = DiagnosticsPublisher(self, self.NAME, p['diagnostics_period'], self._events)
        qos.subscription(self, self._events, AccelStamped, qos.CONTROL, self._on_control)
        self.add_on_set_parameters_callback(self._on_set_parameters)
        steady = Clock(clock_type=ClockType.STEADY_TIME)
        if self._lockstep:
            self._watchdog = self.create_timer(min(0.05, p['control_timeout'] / 4), self._on_watchdog,
                                               clock=steady)
        else:
            period = self._dt / p['real_time_factor']
            self._ticker = self.create_timer(period, self._on_tick, clock=steady)
        self.get_logger().info(
            f"{p['mode']} CW truth, dt {self._dt} s, n = {self._plant.model.mean_motion:.4e} rad/s, "
            f"{'until stopped' if self._total_steps is None else f'{self._total_steps} steps'}")
        self._ready = False
        self._loop_since = None  # wall time the loop was first seen complete
        self._notice_at = time.monotonic()
        self._readiness = self.create_timer(0.02, self._check_ready, clock=steady)

    def make_plant(self, p: dict):
        """The core truth the parameters describe: the CW model with process noise."""
        return Plant(cw_model(p), p['initial_state'], p['process_noise'], seeds=[p['seed']])

    def _check_ready(self) -> None:
        """Start the scenario (publish x0) once the loop is there (wait_for_loop) and
        start_delay has passed; say what is missing every STARTUP_NOTICE_PERIOD s."""
        if self._ready:
            return
        p = self._p
        matched = self._truth_pub.get_subscription_count()
        missing = loop_missing(self, matched, p['min_truth_subscribers'], p['wait_for_loop'])
        now = time.monotonic()
        if missing:
            self._loop_since = None
            if now - self._notice_at > STARTUP_NOTICE_PERIOD:
                self.get_logger().info(f"waiting for {', '.join(missing)} before the first step")
                self._notice_at = now
            return
        self._loop_since = self._loop_since or now
        if now - self._loop_since < p['start_delay']:
            return
        self._ready = True
        self.destroy_timer(self._readiness)
        self.get_logger().info(f'the loop is there: starting the scenario at t = {self._t_ns * 1e-9:.3f} s')
        self._publish_sample()

    # ---------------------------------------------------------------- events
    def _on_control(self, data: bytes) -> None:
        try:
            control = decode_accel(data)
        except MessageError as error:
            self._reject(error.reason, str(error))
            return
        if control.frame_id != self._p['frame_id']:
            self._reject('wrong_frame', f"control in frame '{control.frame_id}', expected "
                         f"'{self._p['frame_id']}'")
            return
        try:
            u = control_of(control)
        except MessageError as error:
            self._reject(error.reason, str(error))
            return
        stamp_ns = control.stamp_ns
        if stamp_ns < self._start_ns:
            self._reject('before_init', f'control stamped {stamp_ns * 1e-9:.3f} s, before the start '
                         f'at {self._start_ns * 1e-9:.3f} s')
            return
        self._controls_received += 1
        if self._finished:
            return
        if not self._lockstep:  # kept by stamp: the step from t_k applies u_k, as in lockstep
            self._early[stamp_ns] = u
            return
        if abs(stamp_ns - self._t_ns) * 2 < self._dt_ns and self._waiting_since is not None:
            if self._p['paused']:
                self._held = u  # applied on resume
            else:
                self._advance(u)
        elif stamp_ns < self._t_ns:
            self._reject('stale', f'control stamped {stamp_ns * 1e-9:.3f} s, plant at {self._t_ns * 1e-9:.3f} s')
        else:  # ahead of the plant (it paused or held a control): use it at its step
            self._early[stamp_ns] = u
            for old in [t for t in self._early if t < self._t_ns]:
                del self._early[old]

    def _on_set_parameters(self, parameters) -> SetParametersResult:
        for parameter in parameters:
            if parameter.name == 'paused':
                self._p['paused'] = bool(parameter.value)
                self.get_logger().info(f"{'paused' if parameter.value else 'resumed'} at "
                                       f't = {self._t_ns * 1e-9:.3f} s')
                if not parameter.value and self._held is not None and self._lockstep:
                    held, self._held = self._held, None
                    self._advance(held)
        return SetParametersResult(successful=True)

    def _on_watchdog(self) -> None:
        if self._waiting_since is None or self._finished or self._p['paused']:
            if self._p['paused'] and self._waiting_since is not None:
                self._waiting_since = time.monotonic()
            return
        now = time.monotonic()
        waited = now - self._waiting_since
        if now - self._sent_at > self._p['resend_period']:
            # a sample lost on a best-effort link would stall the lockstep loop: send it again;
            # every node answers a repeated input with its answer to it (docs/decisions.md, 21)
            self._truth_resent += 1
            self._publish_sample(resend=True)
        if self._step < STARTUP_STEPS:  # processes still warming up: no timeouts yet
            if waited > STARTUP_NOTICE_PERIOD:
                self.get_logger().info(f"waiting for the control of t = {self._t_ns * 1e-9:.1f} s on "
                                       "'control' (are the other nodes running?)")
                self._waiting_since = time.monotonic()
            return
        if waited > self._p['control_timeout']:
            self._timeouts += 1
            self.get_logger().warning(
                f'no control for t = {self._t_ns * 1e-9:.3f} s within {self._p["control_timeout"]} s: '
                f'holding the last control ({self._timeouts} timeouts so far)', throttle_duration_sec=5.0)
            self._advance(self._control)

    def _on_tick(self) -> None:
        """realtime: step with the control stamped for this step (the one the estimator pairs
        with z_k), or, if it is late, hold the newest one and count it."""
        if not self._ready or self._finished or self._p['paused']:
            return
        due = [t for t in self._early if abs(t - self._t_ns) * 2 < self._dt_ns]
        if due:
            u = self._early.pop(due[0])
        else:
            older = [t for t in self._early if t < self._t_ns]
            u = self._early[max(older)] if older else self._control
            self._late_controls += self._step >= 1  # the first step may come before any control
        for old in [t for t in self._early if t <= self._t_ns]:
            del self._early[old]
        self._advance(u)

    # ---------------------------------------------------------------- stepping
    def _advance(self, u: np.ndarray) -> None:
        """Step with ``u``; then go on at once with controls that came early for later steps."""
        while True:
            if self._started_wall is None:
                self._started_wall = time.monotonic()
            self._control = u
            saturated = int(self._plant.saturated_steps[0])
            self._plant.step(u, self._dt)
            if self._plant.saturated_steps[0] > saturated:
                self.get_logger().warning(
                    f'thrust limit: commanded {np.array2string(u, precision=4)} m/s^2, applied '
                    f'{np.array2string(self._plant.applied[0], precision=4)} m/s^2', throttle_duration_sec=5.0)
            self._step += 1
            self._t_ns += self._dt_ns
            self._publish_sample()
            if self._total_steps is not None and self._step >= self._total_steps:
                self._finish()
                return
            early = [t for t in self._early if abs(t - self._t_ns) * 2 < self._dt_ns]
            if not (early and self._lockstep and not self._p['paused']):
                return
            u = self._early.pop(early[0])

    def _publish_sample(self, resend: bool = False) -> None:
        if self._clock_pub is not None:
            self._clock_pub.publish(encode_clock(self._t_ns))
        x = self._plant.x[0]
        self._truth_pub.publish(encode_odometry(
            x, None, self._t_ns, self._p['frame_id'], self._p['child_frame_id']))
        self._truth_published += 1
        self._sent_at = time.monotonic()
        if resend:
            return
        self._waiting_since = self._sent_at
        if self._diagnostics.due(self._t_ns):
            self._publish_diagnostics()

    def _finish(self) -> None:
        self._finished_wall = time.monotonic()
        self._finished_unix = time.time()  # when stepping ended, for tools outside the process
        self._waiting_since = None
        self._publish_diagnostics()
        values = self.values()
        self.get_logger().info(
            f"done: {values['steps']} steps, {values['sim_time']:.1f} s simulated in "
            f"{values['wall_time']:.2f} s (x{values['real_time_factor']:.0f}), "
            f"{self._timeouts} control timeouts, final range {values['range']:.4f} m")
        # run_node flushes the publishers before the process ends, so subscribers get the end
        self.done = self._p['exit_when_done']

    def close(self) -> None:
        """Stopped before the last step (SIGINT/SIGTERM): the totals so far go on record too
        (run_node then waits for the subscribers to acknowledge them)."""
        if not self._finished:
            self._publish_diagnostics()

    @property
    def _finished(self) -> bool:
        """The last step is done: no more steps, whatever the mode."""
        return self._finished_wall is not None

    # ---------------------------------------------------------------- reporting
    def _reject(self, reason: str, detail: str) -> None:
        self._rejected[reason] += 1
        self.get_logger().warning(f'rejected control ({reason}): {detail}', throttle_duration_sec=5.0)
        self._publish_diagnostics()

    def values(self) -> dict:
        end = self._finished_wall or time.monotonic()
        wall = (end - self._started_wall) if self._started_wall else 0.0
        sim = self._step * self._dt
        values = {
            'steps': self._step, 'sim_time': sim, 'wall_time': wall,
            'real_time_factor': sim / wall if wall > 0 else 0.0,
            'control_timeouts': self._timeouts, 'controls_received': self._controls_received,
            'truth_published': self._truth_published, 'truth_resent': self._truth_resent,
            'late_controls': self._late_controls,
            'saturated_steps': int(self._plant.saturated_steps[0]),
            'range': float(np.linalg.norm(self._plant.x[0, :3])), 'done': self._finished,
            'finished_unix_time': self._finished_unix,
        }
        values.update(self._rejected.as_values('controls'))
        return values

    def _publish_diagnostics(self) -> None:
        problems = [f'{self._timeouts} control timeouts'] if self._timeouts else []
        if self._rejected.total:
            problems.append(f'{self._rejected.total} controls rejected')
        self._diagnostics.publish(self._t_ns, self.values(), problems)


def main(args=None) -> int:
    return run_node(PlantNode, args, 'cw_plant')



if __name__ == '__main__':
    raise SystemExit(main())
