"""position_sensor: noisy measurements z = h(x) + v of the truth, by any measurement model
(``model``: position, the default, z = C x; range_azimuth_elevation, line_of_sight, range,
range_rate: docs/sensors.md)."""

from __future__ import annotations

from functools import partial

import numpy as np
from nav_msgs.msg import Odometry
from rclpy.clock import Clock, ClockType
from rclpy.node import Node

from snn_estimator.measurements import REASONS, VALID
from snn_estimator.plant.sensors import MeasurementSensor, SamplePeriod
from snn_estimator.runners.gates import NewestFirst
from snn_estimator.runners.peers import PeerWatch

from . import qos
from .codec import MessageError, encode_measurement, encode_no_measurement, read_input
from .conversions import MEASUREMENT_CLASSES
from .core_objects import measurement_model
from .diagnostics import DiagnosticsPublisher, Rejections
from .parameter_tables import SENSOR
from .ros_parameters import declare
from .runtime import Answers, MatchHold, ProcessHooks, ThrottledLog, clock_ns, on_clock_jump_back, run_node

#: An angle variance (rad^2) from which the node warns: 0.1 rad (5.7 deg) of noise.
ANGLE_VARIANCE_WARNING = 1e-2
#: Reasons a sample is published as "nothing measured" (publish_not_measured; codec.encode_no_measurement):
#: the sensor looked and saw nothing. A dropout is a lost message, a non-finite truth a broken input.
SAYS_NOT_MEASURED = frozenset({'too_close', 'too_far', 'out_of_view', 'singular'})


class SensorNode(ProcessHooks, Node):
    """Wraps :class:`snn_estimator.plant.sensors.MeasurementSensor`: one measurement per truth sample,
    stamped with the truth's time, in the message of the model (position: PointStamped with NaN
    on the axes it does not measure, PositionSensor's numbers). A sample outside the field of
    view or the range limits is published as "nothing measured" (publish_not_measured: REP 117's
    +-inf range, a NaN vector), so that an estimator predicts over it at once; one dropped is not
    published. Both are counted (measurement_rejected.<reason>)."""

    def __init__(self, **kwargs):
        super().__init__('position_sensor', **kwargs)
        p = declare(self, SENSOR)
        self._p = p
        self._axes = tuple(int(a) for a in p['measured_axes'])
        model = measurement_model(p, p['measurement_noise'],
                                  **{name: p[name] for name in ('field_of_view', 'min_range', 'max_range',
                                                                   'range_noise_growth')})
        self._model = model
        self._frame = p['frame_id'] if model.message_form == 'point' else p['sensor_frame_id']
        self._sensor = MeasurementSensor(model, seeds=[p['seed']], dropout_probability=p['dropout_probability'])
        self._not_measured = Rejections()
        self._unmeasured_ns = None  # the stamp of the last truth that gave no measurement
        self._period = SamplePeriod(p['measurement_period'])
        # every truth answered (a sample or "nothing measured"), or only the samples it measured
        self._reports_every_truth = bool(p['publish_not_measured'] and model.has_limits)
        self._unpublished = 0  # samples due but not published (dropped; limits when not said)
        self._published = 0
        self._rejected = Rejections()
        self._gate = NewestFirst(p['time_jump_threshold'])
        self._now = partial(clock_ns, self)  # the gate reads the clock only when it needs it
        self._time_jumps = 0
        self._answers = Answers()
        self._events = qos.QosEvents(self)
        self._pub = qos.HistoryPublisher(self, self._events, MEASUREMENT_CLASSES[model.message_form], qos.MEASUREMENT)
        self._peers = PeerWatch([qos.TRUTH], p['peer_timeout'], log=ThrottledLog(self.get_logger()))
        self._diagnostics = DiagnosticsPublisher(self, self.get_name(), p['diagnostics_period'], self._events,
                                                 peers=self._peers)
        steady = Clock(clock_type=ClockType.STEADY_TIME)
        self.create_timer(0.1, self._on_peer_check, clock=steady)
        self._hold = MatchHold(self, self._pub.get_subscription_count, p['min_measurement_subscribers'],
                               p['match_wait'], self._subscribe_truth, self._pub.topic.topic_name,
                               f"subscribing to '{qos.TRUTH}'")
        self._jump = on_clock_jump_back(self, self._on_time_jump)
        if model.message_form == 'point':
            self.get_logger().info(f'measuring axes {self._axes} with R = {self._sensor.r.diagonal().tolist()} m^2')
        else:
            self.get_logger().info(f'measuring {model.describe()}, frame {self._frame!r}')
            angles = np.diagonal(model.noise)[list(model.angle_components)]
            if angles.size and angles.max() >= ANGLE_VARIANCE_WARNING:
                self.get_logger().warning(
                    f'measurement_noise gives {model.name} angles a standard deviation of '
                    f'{np.degrees(np.sqrt(angles.max())):.1f} deg: R is in rad^2 for angles '
                    '(the default 1e-2 is the position noise of Table 6; docs/sensors.md)')

    def _subscribe_truth(self) -> None:
        """Subscribe to 'truth' once the measurement publisher has matched
        ``min_measurement_subscribers`` subscriptions (at once without it), or after
        ``match_wait`` s with a warning: a subscriber that DDS matched on its side only would
        lose the first samples (docs/decisions.md, 33)."""
        qos.subscription(self, self._events, Odometry, qos.TRUTH, self._on_truth, qos.INPUT_QOS)

    def _on_peer_check(self) -> None:
        if self._peers.check() and self._gate.last_ns is not None:
            self._publish_diagnostics(self._gate.last_ns)

    def _on_truth(self, data: bytes) -> None:
        self._peers.saw(qos.TRUTH)
        try:
            truth, x = read_input('state', data, self._p['frame_id'])
        except MessageError as error:
            self._rejected[error.reason] += 1
            self.get_logger().warning(f'rejected truth ({error})', throttle_duration_sec=5.0)
            return
        stamp_ns = truth.stamp_ns
        kind = self._gate.classify(stamp_ns, self._now)
        if kind == 'repeat':
            if stamp_ns == self._unmeasured_ns:  # nothing was measured at this stamp: nothing again
                return
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
            self._period.reset()
        if not self._period.due(stamp_ns):  # between two samples (measurement_period): said, with limits
            if self._reports_every_truth:
                self._send(stamp_ns, encode_no_measurement(self._model, 'between_samples', stamp_ns, self._frame))
            else:
                self._unmeasured_ns = stamp_ns
            return
        sample = self._sensor.measure(x[None])
        reason = REASONS[int(sample.reason[0])]
        try:
            if reason != REASONS[VALID]:
                raise MessageError(reason, 'no measurement')
            data = encode_measurement(self._model, sample.z[0], stamp_ns, self._frame)
        except MessageError as error:  # out of view or range, dropped, not finite: no measurement
            self._not_measured[error.reason] += 1
            if error.reason not in SAYS_NOT_MEASURED or not self._p['publish_not_measured']:
                self._unmeasured_ns = stamp_ns
                self._unpublished += 1
                if self._diagnostics.due(stamp_ns):
                    self._publish_diagnostics(stamp_ns)
                return
            data = encode_no_measurement(self._model, error.reason, stamp_ns, self._frame)
        self._send(stamp_ns, data)
        if self._diagnostics.due(stamp_ns):
            self._publish_diagnostics(stamp_ns)

    def _send(self, stamp_ns: int, data: bytes) -> None:
        """Publish one message at ``stamp_ns``, kept to answer a resend of that truth."""
        self._pub.publish(data)
        self._answers.remember(stamp_ns, data)
        self._published += 1

    def _on_time_jump(self, seconds: float) -> None:
        self.get_logger().warning(f'the clock jumped back by {seconds:.3f} s: starting over')
        self._time_jumps += 1
        self._gate.reset()
        self._answers.clear()
        self._period.reset()

    def _publish_diagnostics(self, stamp_ns: int) -> None:
        # what a recorded run is checked against, per sensor (snn_tools.bags.data.sensor_reports)
        values = {'measurements_published': self._published, 'measurements_resent': self._answers.resent,
                  'topic': self._pub.topic.topic_name, 'sample_period': self._p['measurement_period'],
                  'reports_every_truth': self._reports_every_truth, 'samples_unpublished': self._unpublished,
                  'time_jumps': self._time_jumps,
                  **self._rejected.as_values('truth'), **self._not_measured.as_values('measurement')}
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
