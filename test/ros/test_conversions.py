"""Message conversions: round trips, NaN conventions and refusals."""

import math
import struct

import numpy as np
import pytest

pytest.importorskip('rclpy')

from diagnostic_msgs.msg import DiagnosticStatus  # noqa: E402
from rclpy.serialization import deserialize_message, serialize_message  # noqa: E402

from scenario_nodes.conversions import (  # noqa: E402
    MessageError,
    accel_to_control,
    control_to_accel,
    diagnostic_status,
    diagnostic_values,
    measurement_to_point,
    ns_to_stamp,
    odometry_to_state,
    point_to_measurement,
    spikes_message,
    stamp_to_ns,
    state_to_odometry,
)


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


# ---------------------------------------------------------------- the wire codec against rclpy's
from geometry_msgs.msg import AccelStamped, PointStamped  # noqa: E402
from nav_msgs.msg import Odometry  # noqa: E402
from rosgraph_msgs.msg import Clock  # noqa: E402
from std_msgs.msg import UInt32, UInt32MultiArray  # noqa: E402

from scenario_nodes.codec import (  # noqa: E402
    NS,
    decode_accel,
    decode_odometry,
    decode_point,
    encode_accel,
    encode_clock,
    encode_odometry,
    encode_point,
    encode_spikes,
    encode_uint32,
)

FRAMES = ['', 'a', 'ab', 'abc', 'lvlh', 'lvlh5', 'chaser', 'target_7', 'ünïcode']  # every alignment


@pytest.mark.parametrize('frame', FRAMES)
@pytest.mark.parametrize('child', FRAMES[:5])
def test_our_odometry_bytes_are_what_rclpy_reads_and_we_read_rclpys(frame, child):
    rng = np.random.default_rng(len(frame) * 10 + len(child))
    x = rng.normal(size=6) * 100
    a = rng.normal(size=(6, 6))
    covariance = a @ a.T
    stamp_ns = int(rng.integers(0, 2**40))
    msg = deserialize_message(encode_odometry(x, covariance, stamp_ns, frame, child), Odometry)
    assert stamp_to_ns(msg.header.stamp) == stamp_ns
    assert (msg.header.frame_id, msg.child_frame_id) == (frame, child)
    p, v, q = msg.pose.pose.position, msg.twist.twist.linear, msg.pose.pose.orientation
    assert [p.x, p.y, p.z, v.x, v.y, v.z] == x.tolist()
    assert (q.x, q.y, q.z, q.w) == (0.0, 0.0, 0.0, 1.0)
    pose_cov = np.asarray(msg.pose.covariance).reshape(6, 6)
    twist_cov = np.asarray(msg.twist.covariance).reshape(6, 6)
    np.testing.assert_array_equal(pose_cov[:3, :3], covariance[:3, :3])
    np.testing.assert_array_equal(twist_cov[:3, :3], covariance[3:, 3:])
    assert not pose_cov[3:].any() and not pose_cov[:, 3:].any()
    msg.twist.twist.angular.z = 7.0  # fields we ignore must not shift what we read
    msg.pose.pose.orientation.x = 0.5
    record = decode_odometry(serialize_message(msg))
    assert (record.stamp_ns, record.frame_id, record.child_frame_id) == (stamp_ns, frame, child)
    np.testing.assert_array_equal(record.state, x)
    np.testing.assert_array_equal(record.covariance[:3, :3], covariance[:3, :3])
    np.testing.assert_array_equal(record.covariance[3:, 3:], covariance[3:, 3:])


@pytest.mark.parametrize('frame', FRAMES)
def test_point_and_accel_bytes_agree_with_rclpy(frame):
    point = deserialize_message(encode_point(np.array([1.5, -2.5]), (0, 2), 123, frame), PointStamped)
    assert (point.point.x, point.point.z, point.header.frame_id) == (1.5, -2.5, frame)
    assert math.isnan(point.point.y) and stamp_to_ns(point.header.stamp) == 123
    point.point.y = 4.0
    record = decode_point(serialize_message(point))
    assert record.vector.tolist() == [1.5, 4.0, -2.5] and record.frame_id == frame
    accel = deserialize_message(encode_accel(np.array([1e-3, -2e-3, 3e-3]), 4_000_000_001, frame),
                                AccelStamped)
    assert [accel.accel.linear.x, accel.accel.linear.y, accel.accel.linear.z] == [1e-3, -2e-3, 3e-3]
    assert accel.accel.angular.x == 0.0 and stamp_to_ns(accel.header.stamp) == 4_000_000_001
    accel.accel.angular.y = 9.0
    record = decode_accel(serialize_message(accel))
    assert record.vector.tolist() == [1e-3, -2e-3, 3e-3] and record.stamp_ns == 4_000_000_001


@pytest.mark.parametrize('size', [0, 1, 2, 5, 200])
def test_spike_bytes_agree_with_rclpy(size):
    spikes = np.arange(size) % 4
    msg = deserialize_message(encode_spikes(spikes), UInt32MultiArray)
    assert list(msg.data) == spikes.tolist()
    assert [(d.label, d.size, d.stride) for d in msg.layout.dim] == [('neuron', size, size)]
    assert deserialize_message(encode_uint32(4_000_000_000), UInt32).data == 4_000_000_000


@pytest.mark.parametrize('stamp_ns', [0, 1, 999_999_999, 1_000_000_000, 360_100_000_000, 2**31 * NS - 1])
def test_clock_bytes_agree_with_rclpy(stamp_ns):
    msg = deserialize_message(encode_clock(stamp_ns), Clock)
    assert (msg.clock.sec, msg.clock.nanosec) == divmod(stamp_ns, NS)
    assert encode_clock(stamp_ns) == serialize_message(Clock(clock=ns_to_stamp(stamp_ns)))


def test_truncated_or_garbled_bytes_are_refused_with_a_reason():
    good = encode_odometry(np.ones(6), None, 5, 'lvlh', 'chaser')
    for bad in (good[:3], good[:20], good[:-8], good[:4] + b'\xff' * 12 + good[16:]):
        with pytest.raises(MessageError) as error:
            decode_odometry(bad)
        assert error.value.reason == 'malformed'
    with pytest.raises(MessageError):
        decode_point(encode_point(np.zeros(3), (0, 1, 2), 0, 'lvlh')[:30])


def test_big_endian_cdr_is_read_through_rclpy():
    """Another middleware may send big-endian CDR: decoded the slow, general way."""
    body = struct.pack('>iII', 2, 5, 5) + b'lvlh\0' + bytes(7) + struct.pack('>3d', 1.0, 2.0, 3.0)
    try:
        deserialize_message(b'\x00\x00\x00\x00' + body, PointStamped)
    except Exception:  # this rmw's deserializer does not take big-endian CDR: nothing to test
        pytest.skip('rclpy cannot deserialize big-endian CDR here')
    record = decode_point(b'\x00\x00\x00\x00' + body)
    assert record.stamp_ns == 2_000_000_005 and record.frame_id == 'lvlh'
    assert record.vector.tolist() == [1.0, 2.0, 3.0]
