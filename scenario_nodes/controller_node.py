"""lqr_controller: u = -K x_hat (Eq. 42) from each state estimate, stamped with the estimate's time."""

from __future__ import annotations

import numpy as np
from geometry_msgs.msg import AccelStamped
from nav_msgs.msg import Odometry
from rclpy.node import Node

from snn_estimator.simulation import lqr_control, lqr_gain
from snn_estimator.validation import as_matrix

from . import qos
from .conversions import MessageError, control_to_accel, odometry_to_state, stamp_to_ns
from .diagnostics import DiagnosticsPublisher, Rejections
from .parameters import CONTROLLER, cw_model, declare
from .runtime import run_node


def design_gain(values: dict) -> np.ndarray:
    """K from the ``gain`` parameter, or designed by python-control from Qc and Rc."""
    if values.get('gain'):
        return as_matrix(values['gain'], (3, 6), 'gain (K)')
    model = cw_model(values, form=values['cw_model'])
    return lqr_gain(model, values['lqr_state_weight'], values['lqr_input_weight'])


class ControllerNode(Node):
    """Wraps :func:`snn_estimator.simulation.lqr_control`."""

    def __init__(self, **kwargs):
        super().__init__('lqr_controller', **kwargs)
        p = declare(self, CONTROLLER)
        self._p = p
        self._gain = design_gain(p)
        self._published = 0
        self._rejected = Rejections()
        self._last_stamp_ns = None
        self._pub = self.create_publisher(AccelStamped, qos.CONTROL, qos.PIPELINE_QOS)
        self._diagnostics = DiagnosticsPublisher(self, 'lqr_controller', p['diagnostics_period'])
        self.create_subscription(Odometry, qos.ESTIMATE, self._on_estimate, qos.PIPELINE_QOS)
        poles = np.linalg.eigvals(cw_model(p).jacobian(np.zeros(6), np.zeros(3))
                                  - cw_model(p).input_matrix @ self._gain)
        self.get_logger().info(
            f'LQR gain K = {np.array2string(self._gain, precision=4, max_line_width=200)}; '
            f'slowest closed-loop pole {poles.real.max():.4f} 1/s')

    @property
    def gain(self) -> np.ndarray:
        return self._gain.copy()

    def _on_estimate(self, msg: Odometry) -> None:
        stamp_ns = stamp_to_ns(msg.header.stamp)
        try:
            x_hat, _ = odometry_to_state(msg)
        except MessageError as error:
            self._rejected[error.reason] += 1
            self.get_logger().warning(f'rejected estimate ({error})', throttle_duration_sec=5.0)
            return
        if self._last_stamp_ns is not None and stamp_ns <= self._last_stamp_ns:
            self._rejected['not_newer'] += 1
            self.get_logger().warning('estimate stamp did not advance; ignored', throttle_duration_sec=5.0)
            return
        self._last_stamp_ns = stamp_ns
        u = lqr_control(self._gain, x_hat)
        self._pub.publish(control_to_accel(u, stamp_ns, self._p['frame_id']))
        self._published += 1
        if self._diagnostics.due(stamp_ns):
            self._publish_diagnostics(stamp_ns)

    def _publish_diagnostics(self, stamp_ns: int) -> None:
        values = {'controls_published': self._published, **self._rejected.as_values('estimates')}
        problems = [f'{self._rejected.total} estimates rejected'] if self._rejected.total else []
        self._diagnostics.publish(stamp_ns, values, problems)

    def close(self) -> None:
        """Final diagnostics, so the totals of the run are on record."""
        if self._last_stamp_ns is not None:
            self._publish_diagnostics(self._last_stamp_ns)
            self._diagnostics.flush()


def main(args=None) -> int:
    return run_node(ControllerNode, args, 'lqr_controller')


if __name__ == '__main__':
    raise SystemExit(main())
