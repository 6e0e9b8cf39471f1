"""estimator: hosts one core filter (SNN-EMSIF, SNN-EKF, SNN-EMSIF*, EMSIF, EKF, ESIF).

Timing: the estimate x_hat_k stamped t_k is published first; the controller answers with u_k
stamped t_k; when both the measurement z_k (stamped t_k) and u_k are here, the filter steps and
x_hat_{k+1} is published stamped t_k + time_step. If u_k is
still missing two steps later, the last control is held (as the plant does) and counted.
"""

from __future__ import annotations

import time

import numpy as np
from geometry_msgs.msg import AccelStamped, PointStamped
from nav_msgs.msg import Odometry
from rclpy.node import Node
from std_msgs.msg import UInt32, UInt32MultiArray

from snn_estimator import make_estimator

from . import qos
from .conversions import (MessageError, accel_to_control, point_to_measurement, seconds_to_ns,
                          spike_count_message, spikes_message, stamp_to_ns, state_to_odometry)
from .diagnostics import DiagnosticsPublisher, Rejections
from .parameters import ESTIMATOR, cw_model, declare, estimator_config
from .runtime import run_node


class EstimatorNode(Node):
    """Converts messages, calls ``Estimator.step``, publishes; holds no filter math."""

    def __init__(self, **kwargs):
        super().__init__('estimator', **kwargs)
        p = declare(self, ESTIMATOR)
        self._p = p
        self._axes = tuple(int(a) for a in p['measured_axes'])
        model = cw_model(p, form=p['cw_model'], measured_axes=self._axes)
        self._estimator = make_estimator(p['filter_type'], estimator_config(p), model)
        self._dt = p['time_step']
        self._dt_ns = seconds_to_ns(self._dt)
        self._frame, self._child = p['frame_id'], p['child_frame_id']
        self._pending: dict[int, np.ndarray] = {}
        self._controls: dict[int, np.ndarray] = {}
        self._t_ns: int | None = None
        self._last_measurement_ns: int | None = None
        self._held_control = np.zeros(3)
        self._rejected = Rejections()          # measurements
        self._control_rejected = Rejections()
        self._controls_missing = 0
        self._measurements = 0
        self._step_times: list[float] = []
        self._published = 0

        self._estimate_pub = self.create_publisher(Odometry, qos.ESTIMATE, qos.PIPELINE_QOS)
        self._count_pub = self.create_publisher(UInt32, qos.SPIKE_COUNT, qos.PIPELINE_QOS)
        self._spikes_pub = (self.create_publisher(UInt32MultiArray, qos.SPIKES, qos.PIPELINE_QOS)
                            if p['publish_spikes'] else None)
        self._diagnostics = DiagnosticsPublisher(self, 'estimator', p['diagnostics_period'])
        self.create_subscription(PointStamped, qos.MEASUREMENT, self._on_measurement, qos.PIPELINE_QOS)
        self.create_subscription(AccelStamped, qos.CONTROL, self._on_control, qos.PIPELINE_QOS)
        est = self._estimator
        self.get_logger().info(
            f"{p['filter_type']}: " + (
                f"N = {est.neuron_count}, lambda = {p['leak_rate']}, delta = {list(p['boundary_layer'])}, "
                f"rule {p['spike_rule']}, S = {list(p['state_scale'])}, " if est.spiking else '')
            + f"{p['discretization']} steps of {self._dt} s, measured axes {self._axes}")

    @property
    def estimator(self):
        return self._estimator

    # ---------------------------------------------------------------- inputs
    def _on_measurement(self, msg: PointStamped) -> None:
        stamp_ns = stamp_to_ns(msg.header.stamp)
        try:
            z = point_to_measurement(msg, self._axes)
        except MessageError as error:
            self._reject(error.reason, f'measurement at {stamp_ns * 1e-9:.3f} s: {error}')
            return
        if self._t_ns is None:  # first measurement: the initial estimate belongs to its time
            self._t_ns = stamp_ns
            self._publish(stamp_ns)
        if stamp_ns in self._pending or stamp_ns == self._last_measurement_ns:
            self._reject('duplicate', f'second measurement stamped {stamp_ns * 1e-9:.3f} s')
            return
        if stamp_ns < self._t_ns:
            self._reject('stale', f'measurement at {stamp_ns * 1e-9:.3f} s is older than the '
                         f'estimate at {self._t_ns * 1e-9:.3f} s')
            return
        self._measurements += 1
        self._pending[stamp_ns] = z
        self._process()

    def _on_control(self, msg: AccelStamped) -> None:
        try:
            u = accel_to_control(msg)
        except MessageError as error:
            self._control_rejected[error.reason] += 1
            self.get_logger().warning(f'rejected control: {error}', throttle_duration_sec=5.0)
            return
        self._controls[stamp_to_ns(msg.header.stamp)] = u
        self._process()

    def _control_for(self, stamp_ns: int) -> np.ndarray | None:
        for control_ns, u in self._controls.items():
            if abs(control_ns - stamp_ns) * 2 < self._dt_ns:
                return u
        return None

    # ---------------------------------------------------------------- stepping
    def _process(self) -> None:
        """Step through every measurement whose control is known (in stamp order)."""
        while self._pending:
            stamp_ns = min(self._pending)
            if stamp_ns != self._t_ns:
                self._reject('misaligned', f'measurement at {stamp_ns * 1e-9:.3f} s does not fall on '
                             f'the estimate time {self._t_ns * 1e-9:.3f} s (time_step {self._dt} s?)')
                del self._pending[stamp_ns]
                continue
            u = self._control_for(stamp_ns)
            if u is None:
                # The next measurement may overtake this step's control on the way here; only
                # when two newer ones are waiting did the plant go on without our control.
                if len(self._pending) <= 2:
                    return
                u = self._held_control
                self._controls_missing += 1
                self.get_logger().warning(f'no control for t = {stamp_ns * 1e-9:.3f} s: holding the last one',
                                          throttle_duration_sec=5.0)
            z = self._pending.pop(stamp_ns)
            self._last_measurement_ns = stamp_ns
            self._held_control = u
            started = time.perf_counter()
            self._estimator.step(z, u, self._dt)
            self._step_times.append(time.perf_counter() - started)
            self._t_ns = stamp_ns + self._dt_ns
            self._controls = {t: v for t, v in self._controls.items() if t > stamp_ns}
            self._publish(self._t_ns)

    def _publish(self, stamp_ns: int) -> None:
        est = self._estimator
        self._estimate_pub.publish(state_to_odometry(est.x_hat, est.P, stamp_ns, self._frame, self._child))
        self._count_pub.publish(spike_count_message(est.spike_count))
        if self._spikes_pub is not None:
            spikes = est.spikes if est.spiking else np.zeros(0, dtype=np.uint32)
            self._spikes_pub.publish(spikes_message(spikes))
        self._published += 1
        if self._diagnostics.due(stamp_ns):
            self._publish_diagnostics(stamp_ns)

    # ---------------------------------------------------------------- reporting
    def _reject(self, reason: str, detail: str) -> None:
        """Count, log (throttled) and report at once on diagnostics."""
        self._rejected[reason] += 1
        self.get_logger().warning(f'rejected {detail}', throttle_duration_sec=5.0)
        if self._t_ns is not None:
            self._publish_diagnostics(self._t_ns)

    def values(self) -> dict:
        est = self._estimator
        steps = est.steps
        times = np.asarray(self._step_times[-1000:]) * 1e6
        values = {
            'filter': est.kind, 'neurons': est.neuron_count, 'steps': steps,
            'estimates_published': self._published, 'measurements_received': self._measurements,
            'spikes_total': est.total_spikes,
            'spike_fraction': (est.total_spikes / (steps * est.neuron_count)
                               if steps and est.neuron_count else 0.0),
            'step_time_us_last': float(times[-1]) if times.size else 0.0,
            'step_time_us_median': float(np.median(times)) if times.size else 0.0,
            'controls_missing': self._controls_missing,
        }
        values.update(self._rejected.as_values('measurements'))
        values.update(self._control_rejected.as_values('controls'))
        return values

    def _publish_diagnostics(self, stamp_ns: int) -> None:
        problems = []
        if self._rejected.total or self._control_rejected.total:
            problems.append(f'{self._rejected.total + self._control_rejected.total} inputs rejected')
        if self._controls_missing:
            problems.append(f'{self._controls_missing} controls missing')
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
