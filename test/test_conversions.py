"""Message conversions: round trips, NaN conventions and refusals."""

import math

import numpy as np
import pytest

pytest.importorskip('rclpy')

from diagnostic_msgs.msg import DiagnosticStatus  # noqa: E402
from rclpy.serialization import deserialize_message, serialize_message  # noqa: E402

from scenario_nodes.conversions import (MessageError, accel_to_control, control_to_accel,  # noqa: E402
                                        diagnostic_status, diagnostic_values, measurement_to_point,
                                        ns_to_stamp, odometry_to_state, point_to_measurement,
                                        spikes_message, stamp_to_ns, state_to_odometry)


def test_state_and_covariance_blocks_round_trip_through_odometry():
    x = np.array([70.0, 30.0, -5.0, -1.7, -0.9, 0.25])
    a = np.arange(36.0).reshape(6, 6)
    covariance = a @ a.T
    msg = deserialize_message(serialize_message(
        state_to_odometry(x, covariance, 1_234_567_890_123, 'lvlh', 'chaser')), type(
        state_to_odometry(x, None, 0, 'a', 'b')))
    state, blocks = odometry_to_state(msg)
    np.testing.assert_array_equal(state, x)
    np.testing.assert_array_equal(blocks[:3, :3], covariance[:3, :3])
    np.testing.assert_array_equal(blocks[3:, 3:], covariance[3:, 3:])
    assert np.all(blocks[:3, 3:] == 0.0)  # cross terms have no place in Odometry
    assert stamp_to_ns(msg.header.stamp) == 1_234_567_890_123
    assert msg.header.frame_id == 'lvlh' and msg.child_frame_id == 'chaser'
    assert msg.pose.pose.orientation.w == 1.0


def test_unmeasured_axes_travel_as_nan_and_measured_ones_must_be_finite():
    msg = measurement_to_point(np.array([1.5, -2.5]), (0, 2), 10, 'lvlh')
    assert msg.point.x == 1.5 and math.isnan(msg.point.y) and msg.point.z == -2.5
    np.testing.assert_array_equal(point_to_measurement(msg, (0, 2)), [1.5, -2.5])
    msg.point.z = math.inf
    with pytest.raises(MessageError, match='non_finite'):
        point_to_measurement(msg, (0, 2))
    with pytest.raises(MessageError) as error:
        point_to_measurement(msg, (0, 1, 2))
    assert error.value.reason == 'non_finite'


def test_control_round_trip_and_refusal():
    msg = control_to_accel(np.array([0.01, -0.02, 0.03]), 5, 'lvlh')
    np.testing.assert_array_equal(accel_to_control(msg), [0.01, -0.02, 0.03])
    msg.accel.linear.y = math.nan
    with pytest.raises(MessageError):
        accel_to_control(msg)


def test_stamps_are_exact_in_nanoseconds():
    for ns in (0, 1, 999_999_999, 1_000_000_000, 359_900_000_000, 2**40 + 7):
        assert stamp_to_ns(ns_to_stamp(ns)) == ns


def test_spikes_and_diagnostics_messages():
    msg = spikes_message(np.array([0, 3, 1], dtype=np.int64))
    assert list(msg.data) == [0, 3, 1] and msg.layout.dim[0].label == 'neuron'
    status = diagnostic_status('estimator', '/estimator', DiagnosticStatus.WARN, 'x', {'a': 1, 'b': 0.5})
    assert status.level == DiagnosticStatus.WARN
    assert diagnostic_values(status) == {'a': '1', 'b': '0.5'}
