"""position_sensor: noisy partial position measurements z = C x + v of the truth."""

from __future__ import annotations

from functools import partial

from geometry_msgs.msg import PointStamped
from nav_msgs.msg import Odometry
from rclpy.node import Node

from snn_estimator.blocks import PositionSensor
from snn_estimator.gates import NewestFirst

from . import qos
from .codec import MessageError, encode_point, read_input
from .diagnostics import DiagnosticsPublisher, Rejections
from .parameters import SENSOR, cw_model, declare
from .runtime import Answers, ProcessHooks, clock_ns, on_clock_jump_back, run_node


class SensorNode(ProcessHooks, Node):
    """Wraps :class:`snn_estimator.blocks.PositionSensor`: one measurement per truth sample,
    stamped with the truth's time, NaN on the axes it does not measure."""

    def __init__(self, **kwargs):
        super().__init__('position_sensor', **kwargs)
        p = declare(self, SENSOR)
        self._p = p
        self._axes = tuple(int(a) for a in p['measured_axes'])
        model = cw_model(p, measured_axes=self._axes)
        self._sensor = PositionSensor(model, p['measurement_noise'], seeds=[p['seed']])
        self._published = 0
        self._rejected = Rejections()
        self._gate = NewestFirst(p['time_jump_threshold'])
        self._now = partial(clock_ns, self)  # the gate reads the clock only when it needs it
        self._time_jumps = 0
        self._answers = Answers()
        self._events = qos.QosEvents(self)
        self._pub = qos.publisher(self, self._events, PointStamped, qos.MEASUREMENT)
        self._diagnostics = DiagnosticsPublisher(self, 'position_sensor', p['diagnostics_period'], self._events)
        qos.subscription(self, self._events, Odometry, qos.TRUTH, self._on_truth, qos.INPUT_QOS)
        self._jump = on_clock_jump_back(self, self._on_time_jump)
        self.get_logger().info(f'measuring axes {self._axes} with R = {self._sensor.r.diagonal().tolist()} m^2')

    def _on_truth(self, data: bytes) -> None:
        try:
            truth, x = read_input('state', data, self._p['frame_id'])
        except MessageError as error:
            self._rejected[error.reason] += 1
            self.get_logger().warning(f'rejected truth ({error})', throttle_duration_sec=5.0)
            return
        stamp_ns = truth.stamp_ns
        kind = self._gate.classify(stamp_ns, self._now)
        if kind == 'repeat':
            if self._answers.resend(stamp_ns, self._pub):  # the plant sent it again: same measurement
                self._published += 1
            else:
                self._rejected['not_newer'] += 1
                self.get_logger().warning('truth stamp did not advance; not measured twice',
                                          throttle_duration_sec=5.0)
            self._publish_diagnostics(self._gate.last_ns)
            return
        if kind == 'restarted':
            self.get_logger().warning('truth time went back: starting over')
            self._time_jumps += 1
            self._answers.clear()
        z = self._sensor.measure(x)[0]
        data = encode_point(z, self._axes, stamp_ns, self._p['frame_id'])
        self._pub.publish(data)
        self._answers.remember(stamp_ns, data)
        self._published += 1
        if self._diagnostics.due(stamp_ns):
            self._publish_diagnostics(stamp_ns)

    def _on_time_jump(self, seconds: float) -> None:
        self.get_logger().warning(f'the clock jumped back by {seconds:.3f} s: starting over')
        self._time_jumps += 1
        self._gate.reset()
        self._answers.clear()

    def _publish_diagnostics(self, stamp_ns: int) -> None:
        values = {'measurements_published': self._published, 'measurements_resent': self._answers.resent,
                  'time_jumps': self._time_jumps,
                  **self._rejected.as_values('truth')}
        problems = [f'{self._rejected.total} truth messages rejected'] if self._rejected.total else []
        self._diagnostics.publish(stamp_ns, values, problems)

    def close(self) -> None:
        """Final diagnostics, so the totals of the run are on record."""
        if self._gate.last_ns is not None:
            self._publish_diagnostics(self._gate.last_ns)  # run_node waits for its acknowledgement


def main(args=None) -> int:
    return run_node(SensorNode, args, 'position_sensor')


if __name__ == '__main__':
    raise SystemExit(main())
