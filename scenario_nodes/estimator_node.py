"""estimator: hosts one core filter (SNN-EMSIF, SNN-EKF, SNN-EMSIF*, EMSIF, EKF, ESIF).

Timing: the estimate x_hat_k stamped t_k is published first; the controller answers with u_k
stamped t_k; when both the measurement z_k (stamped t_k) and u_k are here, the filter steps and
x_hat_{k+1} is published stamped t_k + time_step. If u_k is still missing two measurements
later, the last control is held (as the plant does) and counted; if z_k is still missing when
the clock is two steps ahead, the filter predicts without it (sensor dropout).

Start-up: the first measurement initialises the filter from the parameters. When the filter
joins a running loop (hot swap), it starts instead from the newest estimate another estimator
still offers on `estimate` (replaying the measurements and controls since then), or, after a
crash took that history with it, from a least-squares fit over the sensor's history.
"""

from __future__ import annotations

import time
from collections import Counter

import numpy as np
from geometry_msgs.msg import AccelStamped, PointStamped
from nav_msgs.msg import Odometry
from rcl_interfaces.msg import SetParametersResult
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from std_msgs.msg import UInt32, UInt32MultiArray
from std_srvs.srv import Trigger

from snn_estimator import make_estimator
from snn_estimator.simulation import batch_initial_state

from . import qos
from .conversions import (MessageError, control_of, decode_accel, decode_odometry, decode_point,
                          encode_odometry, encode_spikes, encode_uint32, measurement_of, seconds_to_ns,
                          state_of)
from .diagnostics import DiagnosticsPublisher, Rejections
from .parameters import ESTIMATOR, cw_model, declare, estimator_config, silenced_set
from .runtime import (clock_ns, on_clock_jump_back, run_node, seconds_ahead_of_clock,
                      time_base_restarted)

#: Parameters applied between steps through the parameter services; everything else is read-only.
RUNTIME = {'leak_rate', 'boundary_layer', 'process_noise_scale', 'measurement_noise_scale',
           'membrane_noise', 'silenced_neurons', 'silenced_fraction', 'nis_threshold', 'nis_window',
           'max_input_age'}
CONTROL_MEMORY = 2000  # controls kept for replay after a hot swap
WARM_START_PATIENCE = 5.0  # wall s a joining estimator waits for the controls of its window
DROPOUT_WAIT = 0.25  # wall s without any measurement before predicting up to the clock


class EstimatorNode(Node):
    """Converts messages, calls the core estimator, publishes; holds no filter math."""

    def __init__(self, **kwargs):
        super().__init__('estimator', **kwargs)
        p = declare(self, ESTIMATOR)
        self._p = p
        self._axes = tuple(int(a) for a in p['measured_axes'])
        model = cw_model(p, form=p['cw_model'], measured_axes=self._axes)
        self._estimator = make_estimator(p['filter_type'], estimator_config(p), model)
        # one step now loads the compiled kernels (not in the loop's first step) and checks leak
        # and P0 against time_step (check_time_step: a ValueError is a configuration error)
        self._measurement_r = self._estimator.settings.r_hat / p['measurement_noise_scale']
        self._estimator.innovation_nis(np.zeros(len(self._axes)), self._measurement_r)
        self._estimator.step(np.zeros(len(self._axes)), np.zeros(3), p['time_step'])
        self._estimator.reset()
        self._dt = p['time_step']
        self._dt_ns = seconds_to_ns(self._dt)
        self._frame, self._child = p['frame_id'], p['child_frame_id']
        self._first_arrival: float | None = None  # wall time of the first measurement
        self._pending: dict[int, np.ndarray] = {}
        self._controls: dict[int, np.ndarray] = {}
        self._previous: tuple[int, np.ndarray, np.ndarray] | None = None  # newest foreign estimate
        self._t_ns: int | None = None
        self._init_ns: int | None = None
        self._last_measurement_ns: int | None = None
        self._newest_ns: int | None = None  # newest measurement stamp accepted
        self._last_arrival = time.monotonic()  # wall time of the last accepted measurement
        self._held_control = np.zeros(3)
        self._rejected = Rejections()          # measurements
        self._control_rejected = Rejections()
        self._events = Counter()               # resets, time jumps, reinitialisations, ...
        self._controls_missing = 0
        self._dropout_steps = 0
        self._high_nis = 0
        self._measurements = 0  # received = rejected + used + dropped + pending
        self._used = 0
        self._dropped = 0
        self._step_times: list[float] = []
        self._published = self._spikes_published = 0

        self._estimate_pub = self.create_publisher(Odometry, qos.ESTIMATE, qos.PUBLISHER_QOS)
        self._count_pub = self.create_publisher(UInt32, qos.SPIKE_COUNT, qos.PUBLISHER_QOS)
        self._spikes_pub = (self.create_publisher(UInt32MultiArray, qos.SPIKES, qos.PUBLISHER_QOS)
                            if p['publish_spikes'] else None)
        self._diagnostics = DiagnosticsPublisher(self, 'estimator', p['diagnostics_period'])
        self.create_subscription(PointStamped, qos.MEASUREMENT, self._on_measurement, qos.HISTORY_QOS,
                                 raw=True)
        self.create_subscription(AccelStamped, qos.CONTROL, self._on_control, qos.HISTORY_QOS, raw=True)
        self.create_subscription(Odometry, qos.SET_STATE, self._on_set_state, qos.SUBSCRIBER_QOS, raw=True)
        self._previous_sub = (self.create_subscription(Odometry, qos.ESTIMATE, self._on_previous_estimate,
                                                       qos.HISTORY_QOS, raw=True)
                              if p['initialization'] != 'parameters' else None)
        self.create_service(Trigger, '~/reset', self._on_reset)
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self._jump = on_clock_jump_back(self, self._on_time_jump)
        steady = Clock(clock_type=ClockType.STEADY_TIME)
        # Wall-clock watchdogs (not per simulated step: they would cost a callback every step)
        self.create_timer(0.05, self._on_watchdog, clock=steady)
        self._init_timer = self.create_timer(0.1, self._try_initialise, clock=steady)
        est = self._estimator
        self.get_logger().info(
            f"{p['filter_type']}: " + (
                f"N = {est.neuron_count}, lambda = {p['leak_rate']}, delta = {list(p['boundary_layer'])}, "
                f"rule {p['spike_rule']}, S = {list(p['state_scale'])}, " if est.spiking else '')
            + f"{p['discretization']} steps of {self._dt} s, measured axes {self._axes}, "
            f"initialization {p['initialization']}")

    @property
    def estimator(self):
        return self._estimator

    # ---------------------------------------------------------------- inputs
    def _now_ns(self) -> int:
        return clock_ns(self)

    def _too_old(self, stamp_ns: int) -> bool:
        """More than max_input_age behind the newest measurement received: a straggler. (Not
        relative to the clock: a filter that is behind must still take its queued inputs.)"""
        newest = self._newest_ns
        return newest is not None and stamp_ns < newest - seconds_to_ns(self._p['max_input_age'])

    def _on_measurement(self, data: bytes) -> None:
        self._measurements += 1
        try:
            measurement = decode_point(data)
        except MessageError as error:
            self._reject(error.reason, f'measurement: {error}')
            return
        stamp_ns = measurement.stamp_ns
        where = f'measurement at {stamp_ns * 1e-9:.3f} s'
        if measurement.frame_id != self._frame:
            self._reject('wrong_frame', f"{where} in frame '{measurement.frame_id}', expected '{self._frame}'")
            return
        try:
            z = measurement_of(measurement, self._axes)
        except MessageError as error:
            self._reject(error.reason, f'{where}: {error}')
            return
        # Without a running clock, stamps far in the past mean the time base restarted (with a
        # clock, its own jump callback says so, and old stamps are only late history).
        if self._t_ns is not None and time_base_restarted(self, stamp_ns, self._t_ns,
                                                         self._p['time_jump_threshold']):
            self._restart(f'measurement time went back from {self._t_ns * 1e-9:.3f} s to '
                          f'{stamp_ns * 1e-9:.3f} s', 'time_jumps')
        if stamp_ns in self._pending or stamp_ns == self._last_measurement_ns:
            self._reject('duplicate', f'second {where}')
            return
        if self._t_ns is not None and self._too_old(stamp_ns):  # (history may come out of order)
            self._reject('too_old', f"{where} is more than {self._p['max_input_age']} s older than "
                         f'the newest measurement ({self._newest_ns * 1e-9:.3f} s)')
            return
        if self._t_ns is not None and stamp_ns < self._t_ns:
            self._reject('stale', f'{where} is older than the estimate at {self._t_ns * 1e-9:.3f} s')
            return
        if self._t_ns is not None and (stamp_ns - self._t_ns) % self._dt_ns:
            self._reject('misaligned', f'{where} does not fall on the estimate time '
                         f'{self._t_ns * 1e-9:.3f} s plus steps of {self._dt} s (time_step?)')
            return
        ahead = seconds_ahead_of_clock(self._now_ns(), stamp_ns, self._p)
        if ahead:  # queued, it would make every real measurement 'too_old' and stall the watchdog
            self._reject('future', f'{where} is {ahead:.3f} s ahead of the clock')
            return
        self._newest_ns = stamp_ns if self._newest_ns is None else max(self._newest_ns, stamp_ns)
        self._last_arrival = time.monotonic()
        if self._first_arrival is None:
            self._first_arrival = self._last_arrival
        self._pending[stamp_ns] = z
        if self._t_ns is None:
            self._try_initialise()
        else:
            self._process()

    def _on_control(self, data: bytes) -> None:
        try:
            control = decode_accel(data)
        except MessageError as error:
            self._reject_control(error.reason, str(error))
            return
        if control.frame_id != self._frame:
            self._reject_control('wrong_frame', f"control in frame '{control.frame_id}'")
            return
        try:
            u = control_of(control)
        except MessageError as error:
            self._reject_control(error.reason, str(error))
            return
        stamp_ns = control.stamp_ns
        if self._init_ns is not None and stamp_ns < self._init_ns:
            self._reject_control('before_init', f'control at {stamp_ns * 1e-9:.3f} s predates the '
                                 f'initialisation at {self._init_ns * 1e-9:.3f} s')
            return
        self._controls[stamp_ns] = u
        if len(self._controls) > CONTROL_MEMORY:
            del self._controls[min(self._controls)]
        if self._t_ns is not None:
            self._process()

    def _on_previous_estimate(self, data: bytes) -> None:
        """Estimates on our own output topic published before we initialised (hot swap)."""
        if self._t_ns is not None:
            return
        try:
            previous = decode_odometry(data)
            x = state_of(previous)
        except MessageError:
            return
        stamp_ns = previous.stamp_ns
        if self._previous is None or stamp_ns > self._previous[0]:
            self._previous = (stamp_ns, x, previous.covariance)
        self._try_initialise()

    def _control_for(self, stamp_ns: int) -> np.ndarray | None:
        u = self._controls.get(stamp_ns)
        if u is not None:
            return u
        for control_ns, value in self._controls.items():
            if abs(control_ns - stamp_ns) * 2 < self._dt_ns:
                return value
        return None

    # ---------------------------------------------------------------- initialisation
    def _try_initialise(self) -> None:
        if self._t_ns is not None or not self._pending:
            return
        mode = self._p['initialization']
        previous = self._previous
        # the topics' history (if any) comes in right after the first measurement
        waited = time.monotonic() - self._first_arrival
        history_complete = waited >= self._p['warm_start_wait']
        if previous is not None and mode != 'parameters' and history_complete \
                and previous[0] <= max(self._pending):
            stamp_ns, x, covariance = previous
            self._estimator.reset()
            try:
                self._estimator.set_state(x, self._warm_start_covariance(covariance))
            except ValueError as error:
                self.get_logger().warning(f'cannot warm start from the earlier estimate: {error}')
                self._previous = None
                return
            self._drop({t for t in self._pending if t < stamp_ns}, 'it predates the warm start')
            self._begin(stamp_ns, publish=False)
            self._events['warm_starts'] += 1
            self.get_logger().info(f'warm start from the estimate of {stamp_ns * 1e-9:.3f} s on '
                                   f"'{qos.ESTIMATE}'; replaying {len(self._pending)} measurements")
            self._process()
            return
        if mode == 'last_estimate' or (mode == 'auto' and not history_complete):
            return  # an earlier estimate may still be on its way
        if mode == 'auto' and len(self._pending) >= self._p['warm_start_min_samples']:
            if self._batch_start(waited):
                return
            if waited < WARM_START_PATIENCE:
                return  # the controls of the window are still on their way
        self._estimator.reset()
        self._begin(min(self._pending), publish=True)
        self._events['cold_starts'] += 1
        self.get_logger().info(f'started from the parameters at t = {self._init_ns * 1e-9:.3f} s '
                               f'({len(self._pending)} measurements queued)')
        self._process()

    def _batch_start(self, waited: float) -> bool:
        """Hot swap after a crash: the sensor's history is here but no earlier estimate. Fit the
        state by least squares over the newest ``warm_start_min_samples`` measurements (controls
        from the controller's history) and start at the newest, which the next step uses.
        False while controls of the window are missing (up to WARM_START_PATIENCE s)."""
        stamps = sorted(self._pending)[-self._p['warm_start_min_samples']:]
        known = [self._control_for(stamp_ns) for stamp_ns in stamps[:-1]]
        if any(u is None for u in known) and waited < WARM_START_PATIENCE:
            return False
        controls, held = [], np.zeros(3)
        for u in known + [None]:
            held = u if u is not None else held
            controls.append(held)
        try:
            x, covariance = batch_initial_state(
                self._estimator.model, np.asarray(stamps) * 1e-9, [self._pending[t] for t in stamps],
                controls, self._measurement_r)
            self._estimator.reset()
            self._estimator.set_state(x, covariance if self._estimator.has_covariance else None)
        except (ValueError, np.linalg.LinAlgError) as error:
            self.get_logger().warning(f'no least-squares start from the history: {error}')
            return False
        self._drop({t for t in self._pending if t < stamps[0]}, 'older than the least-squares window')
        for stamp_ns in stamps[:-1]:
            del self._pending[stamp_ns]
        self._used += len(stamps) - 1
        self._events['batch_starts'] += 1
        self._begin(stamps[-1], publish=True)
        self.get_logger().info(
            f'started from a least-squares fit of {len(stamps) - 1} measurements '
            f'({stamps[0] * 1e-9:.1f}-{stamps[-2] * 1e-9:.1f} s) at t = {stamps[-1] * 1e-9:.3f} s')
        self._process()
        return True

    def _warm_start_covariance(self, blocks: np.ndarray) -> np.ndarray | None:
        """The received covariance blocks, or P0 where they are not positive definite."""
        if not self._estimator.has_covariance:
            return None
        p0 = self._estimator.settings.initial_covariance
        if (np.all(np.isfinite(blocks)) and np.allclose(blocks, blocks.T)
                and np.all(np.linalg.eigvalsh(blocks[:3, :3]) > 0)
                and np.all(np.linalg.eigvalsh(blocks[3:, 3:]) > 0)):
            return blocks
        return p0

    def _begin(self, stamp_ns: int, publish: bool) -> None:
        self._t_ns = self._init_ns = stamp_ns
        self._init_timer.cancel()
        self._controls = {t: u for t, u in self._controls.items() if t >= stamp_ns}
        if self._previous_sub is not None:
            self.destroy_subscription(self._previous_sub)
            self._previous_sub = None
        if publish:
            self._publish(stamp_ns)

    def _restart(self, why: str, event: str) -> None:
        """Back to the configured initial state, initialised again by the next measurement."""
        self._events[event] += 1
        self.get_logger().warning(f'{why}: restarting the filter from its initial state')
        self._estimator.reset()
        self._t_ns = self._init_ns = self._last_measurement_ns = self._newest_ns = None
        self._first_arrival = None
        self._init_timer.reset()
        self._drop(set(self._pending), 'the filter restarted')
        self._controls.clear()
        self._previous = None
        self._high_nis = 0

    def _drop(self, stamps, why: str) -> None:
        """Discard queued measurements (counted as dropped, not as rejected)."""
        for stamp_ns in stamps:
            del self._pending[stamp_ns]
            self._dropped += 1
            self.get_logger().warning(f'dropped the measurement at {stamp_ns * 1e-9:.3f} s: {why}',
                                      throttle_duration_sec=5.0)

    # ---------------------------------------------------------------- stepping
    def _process(self) -> None:
        """Step through every measurement whose control is known (in stamp order); a missing
        measurement between two that came is predicted over."""
        while self._pending and self._t_ns is not None:
            first = min(self._pending)
            if first < self._t_ns or (first - self._t_ns) % self._dt_ns:
                self._drop({first}, 'it does not fall on a step of the estimate')
                continue
            if self._control_for(self._t_ns) is None and len(self._pending) <= 2:
                return  # wait: the next measurement may overtake this step's control
            self._step(self._pending.pop(first) if first == self._t_ns else None, self._t_ns)

    def _step(self, z: np.ndarray | None, stamp_ns: int) -> None:
        u = self._control_for(stamp_ns)
        if u is None:
            u = self._held_control
            self._controls_missing += 1
            self.get_logger().warning(f'no control for t = {stamp_ns * 1e-9:.3f} s: holding the last one',
                                      throttle_duration_sec=5.0)
        self._held_control = u
        if z is None:
            self._dropout_steps += 1
        else:
            self._used += 1
            self._last_measurement_ns = stamp_ns
            self._check_consistency(z)
        started = time.perf_counter()
        try:
            self._estimator.step(z, u, self._dt)
        except FloatingPointError as error:
            self._reinitialise(z, f'{error}', 'non_finite_state')
        self._step_times.append(time.perf_counter() - started)
        if len(self._step_times) > 2000:
            del self._step_times[:1000]
        self._t_ns = stamp_ns + self._dt_ns
        self._controls = {t: v for t, v in self._controls.items() if t > stamp_ns}
        self._publish(self._t_ns)

    def _check_consistency(self, z: np.ndarray) -> None:
        """Normalised innovation squared over ``nis_threshold`` for ``nis_window`` steps in a
        row means the filter lost the truth: re-initialise from the measurement."""
        nis = float(self._estimator.innovation_nis(z, self._measurement_r)[0])
        self._high_nis = self._high_nis + 1 if nis > self._p['nis_threshold'] else 0
        if self._high_nis >= self._p['nis_window'] > 0:
            self._reinitialise(z, f'normalised innovation squared {nis:.1f} > '
                               f"{self._p['nis_threshold']} for {self._high_nis} steps", 'inconsistent_innovation')

    def _reinitialise(self, z: np.ndarray | None, why: str, reason: str) -> None:
        """Measured position from ``z``, the rest of the estimate kept where finite (else the
        initial state), covariance P0."""
        est = self._estimator
        x = np.array(est.x_hat, dtype=float)
        x = np.where(np.isfinite(x), x, est.settings.initial_state)
        if z is not None:
            x[list(self._axes)] = z
        try:
            est.reset(x, est.settings.initial_covariance)
        except ValueError:  # not representable (absurd measurement): back to the parameters
            est.reset()
        self._high_nis = 0
        self._events[f'reinitialisations.{reason}'] += 1
        self.get_logger().error(f'filter re-initialised from the measurement: {why}')

    def _on_watchdog(self) -> None:
        """When the simulated clock is two steps past the estimate and no measurement came
        (sensor dropout), predict up to the clock."""
        if self._t_ns is None or self._pending or time.monotonic() - self._last_arrival < DROPOUT_WAIT:
            return  # measurements may still be queued: not a dropout yet
        now = self._now_ns()
        if now >= self._t_ns + 2 * self._dt_ns:
            while self._t_ns + self._dt_ns <= now:
                self._step(None, self._t_ns)

    def _publish(self, stamp_ns: int) -> None:
        est = self._estimator
        self._estimate_pub.publish(encode_odometry(est.x_hat, est.P, stamp_ns, self._frame, self._child))
        self._count_pub.publish(encode_uint32(est.spike_count))
        if self._spikes_pub is not None:
            self._spikes_pub.publish(encode_spikes(est.spikes if est.spiking else ()))
            self._spikes_published += 1
        self._published += 1
        if self._diagnostics.due(stamp_ns):
            self._publish_diagnostics(stamp_ns)

    # ---------------------------------------------------------------- services, parameters, time
    def _on_reset(self, request, response):
        self._restart('reset requested', 'resets')
        response.success = True
        response.message = 'filter reset: the next measurement initialises it from initial_state, P0'
        return response

    def _on_set_state(self, data: bytes) -> None:
        try:
            state = decode_odometry(data)
            x = state_of(state)
            self._estimator.set_state(x, self._warm_start_covariance(state.covariance))
        except ValueError as error:  # MessageError included
            self._events['set_state_rejected'] += 1
            self.get_logger().warning(f'rejected set_state: {error}', throttle_duration_sec=5.0)
            return
        self._high_nis = 0
        self._events['set_state'] += 1
        self.get_logger().info(f'state set to {np.array2string(x, precision=4)}')

    def _on_time_jump(self, seconds: float) -> None:
        self._restart(f'the clock jumped back by {seconds:.3f} s', 'time_jumps')

    def _on_set_parameters(self, parameters) -> SetParametersResult:
        """Validate all changes together and apply them between two steps, or none of them."""
        changes = {p.name: p.value for p in parameters}
        for name in changes:
            if name not in RUNTIME and name in {s.name for s in ESTIMATOR}:
                return SetParametersResult(successful=False, reason=f'{name} is read-only')
        values = dict(self._p, **changes)
        retune = {k: changes[k] for k in self._estimator.RETUNABLE if k in changes}
        if 'boundary_layer' in retune:
            retune['boundary_layer'] = list(retune['boundary_layer'])
        try:  # validate everything before changing anything
            silenced = silenced_set(values, self._estimator.neuron_count, self._estimator.settings.seed)
            if retune:  # validated first (also against time_step); raises without changing
                self._estimator.retune(**retune)
        except ValueError as error:
            return SetParametersResult(successful=False, reason=str(error))
        if self._estimator.spiking and ('silenced_neurons' in changes or 'silenced_fraction' in changes):
            self._estimator.silence(silenced)
            self._events['silencing_changes'] += 1
        self._p = values
        self.get_logger().info(f'parameters changed: {changes}')
        return SetParametersResult(successful=True)

    # ---------------------------------------------------------------- reporting
    def _reject(self, reason: str, detail: str) -> None:
        """Count, log (throttled) and report at once on diagnostics."""
        self._rejected[reason] += 1
        self.get_logger().warning(f'rejected {detail}', throttle_duration_sec=5.0)
        if self._t_ns is not None:
            self._publish_diagnostics(self._t_ns)

    def _reject_control(self, reason: str, detail: str) -> None:
        self._control_rejected[reason] += 1
        self.get_logger().warning(f'rejected {detail}', throttle_duration_sec=5.0)
        if self._t_ns is not None:
            self._publish_diagnostics(self._t_ns)

    def values(self) -> dict:
        est = self._estimator
        steps = est.steps
        times = np.asarray(self._step_times[-1000:]) * 1e6
        values = {
            'filter': est.kind, 'neurons': est.neuron_count, 'steps': steps,
            'estimates_published': self._published, 'spikes_published': self._spikes_published,
            'measurements_received': self._measurements,
            'measurements_used': self._used, 'measurements_dropped': self._dropped,
            'measurements_pending': len(self._pending),
            'spikes_total': est.total_spikes,
            'spike_fraction': (est.total_spikes / (steps * est.neuron_count)
                               if steps and est.neuron_count else 0.0),
            'silenced_neurons': len(est.silenced),
            'step_time_us_last': float(times[-1]) if times.size else 0.0,
            'step_time_us_median': float(np.median(times)) if times.size else 0.0,
            'controls_missing': self._controls_missing, 'dropout_steps': self._dropout_steps,
        }
        values.update(self._rejected.as_values('measurements'))
        values.update(self._control_rejected.as_values('controls'))
        values.update(sorted(self._events.items()))
        values['reinitialisations'] = sum(v for k, v in self._events.items() if k.startswith('reinit'))
        return values

    def _publish_diagnostics(self, stamp_ns: int) -> None:
        problems = []
        rejected = self._rejected.total + self._control_rejected.total
        if rejected:
            problems.append(f'{rejected} inputs rejected')
        if self._controls_missing:
            problems.append(f'{self._controls_missing} controls missing')
        if self._dropout_steps:
            problems.append(f'{self._dropout_steps} steps without measurement')
        reinit = sum(v for k, v in self._events.items() if k.startswith('reinit'))
        if reinit:
            problems.append(f'{reinit} re-initialisations')
        self._diagnostics.publish(stamp_ns, self.values(), problems)

    def close(self) -> None:
        """Final diagnostics, so the totals of the run are on record."""
        if self._t_ns is not None:
            self._publish_diagnostics(self._t_ns)
            self._diagnostics.flush()


def main(args=None) -> int:
    return run_node(EstimatorNode, args, 'estimator')


if __name__ == '__main__':
    raise SystemExit(main())
