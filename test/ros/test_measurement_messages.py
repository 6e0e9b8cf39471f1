"""Measurement models' messages (docs/sensors.md): round trips through the codec, our bytes
equal to rclpy's, limits and variance in sensor_msgs/Range, refusals."""

import math

import numpy as np
import pytest

pytest.importorskip('rclpy')

from geometry_msgs.msg import PointStamped, Vector3Stamped  # noqa: E402
from rclpy.serialization import deserialize_message, serialize_message  # noqa: E402
from sensor_msgs.msg import Range  # noqa: E402
from test_measurements import NOISE  # noqa: E402 (one noise per model, for every test)

from scenario_nodes.codec import (  # noqa: E402
    decode_range,
    decode_vector3,
    encode_no_measurement,
    encode_point,
    encode_range,
    encode_vector3,
    read_measurement,
)
from scenario_nodes.conversions import (  # noqa: E402
    MessageError,
    measurement_to_message,
    message_to_measurement,
    ns_to_stamp,
    stamp_to_ns,
)
from snn_estimator.measurements import MODELS, make_model  # noqa: E402

#: A model's message_form -> the type its samples must travel in (docs/sensors.md).
TYPES = {'point': PointStamped, 'range': Range, 'vector': Vector3Stamped}
FRAMES = ['', 'a', 'ab', 'abc', 'lidar', 'camera_1', 'sensor']


@pytest.mark.parametrize('name', list(MODELS))
def test_every_models_sample_round_trips_through_its_message(name):
    model = make_model(name, NOISE[name], field_of_view=3.0, min_range=0.5, max_range=500.0)
    rng = np.random.default_rng(1)
    x = np.array([-80.0, 10.0, -5.0, 0.3, -0.1, 0.05]) + rng.normal(size=6)
    z = model.h(x)
    msg = measurement_to_message(model, z, 12_300_000_000, 'lidar')
    assert isinstance(msg, TYPES[model.message_form])
    assert stamp_to_ns(msg.header.stamp) == 12_300_000_000 and msg.header.frame_id == 'lidar'
    again = deserialize_message(serialize_message(msg), TYPES[model.message_form])
    back = message_to_measurement(model, again)
    if name == 'range':  # float32 on the wire
        np.testing.assert_allclose(back, z, rtol=1e-7)
    else:
        np.testing.assert_array_equal(back, z)


def test_vector3_components_are_in_model_order_with_nan_on_unused_ones():
    rae = make_model('range_azimuth_elevation', NOISE['range_azimuth_elevation'])
    msg = measurement_to_message(rae, np.array([120.0, -0.5, 0.25]), 0, 'lidar')
    assert (msg.vector.x, msg.vector.y, msg.vector.z) == (120.0, -0.5, 0.25)
    camera = make_model('line_of_sight', NOISE['line_of_sight'])
    los = measurement_to_message(camera, np.array([0.1, -0.2]), 0, 'camera')
    assert (los.vector.x, los.vector.y) == (0.1, -0.2) and math.isnan(los.vector.z)
    rate = measurement_to_message(make_model('range_rate', 1e-6), np.array([-0.7]), 0, 'rf')
    assert rate.vector.x == -0.7 and math.isnan(rate.vector.y) and math.isnan(rate.vector.z)


def test_range_message_carries_field_of_view_limits_and_variance():
    model = make_model('range', 4e-4, field_of_view=0.5, min_range=1.0, max_range=2000.0)
    msg = measurement_to_message(model, np.array([150.25]), 5, 'laser')
    assert msg.radiation_type == Range.INFRARED
    np.testing.assert_allclose([msg.field_of_view, msg.min_range, msg.max_range, msg.range, msg.variance],
                               [0.5, 1.0, 2000.0, 150.25, 4e-4], rtol=1e-7)
    unlimited = measurement_to_message(make_model('range', 4e-4), np.array([3.0]), 5, 'laser')
    assert unlimited.max_range == math.inf and unlimited.min_range == 0.0
    np.testing.assert_allclose(unlimited.field_of_view, 2 * math.pi, rtol=1e-7)


@pytest.mark.parametrize('frame', FRAMES)
def test_our_vector3_and_range_bytes_are_what_rclpy_reads_and_we_read_rclpys(frame):
    """(Bytes are compared through the decoders: rclpy leaves arbitrary padding bytes.)"""
    vector = deserialize_message(encode_vector3(np.array([1.5, -2.5, 3.25]), 4_000_000_001, frame), Vector3Stamped)
    assert (vector.vector.x, vector.vector.y, vector.vector.z) == (1.5, -2.5, 3.25)
    assert stamp_to_ns(vector.header.stamp) == 4_000_000_001 and vector.header.frame_id == frame
    vector.vector.y = 8.0
    assert decode_vector3(serialize_message(vector)).vector.tolist() == [1.5, 8.0, 3.25]
    mine = deserialize_message(encode_range(42.125, 7, frame, 0.25, 0.5, 100.0, 1e-3), Range)
    assert (mine.radiation_type, mine.field_of_view, mine.min_range, mine.max_range, mine.range) == (
        Range.INFRARED, 0.25, 0.5, 100.0, 42.125)
    assert abs(mine.variance - 1e-3) < 1e-10 and stamp_to_ns(mine.header.stamp) == 7 and mine.header.frame_id == frame
    message = Range(radiation_type=Range.INFRARED, field_of_view=0.25, min_range=0.5, max_range=100.0,
                    range=42.125, variance=1e-3)
    message.header.stamp, message.header.frame_id = ns_to_stamp(7), frame
    record = decode_range(serialize_message(message))
    assert (record.stamp_ns, record.frame_id, record.radiation_type) == (7, frame, Range.INFRARED)
    assert (record.range, record.min_range, record.max_range) == (42.125, 0.5, 100.0)


def test_a_sample_that_is_not_finite_never_leaves_and_bad_ranges_are_refused():
    rae = make_model('range_azimuth_elevation', NOISE['range_azimuth_elevation'])
    with pytest.raises(MessageError, match='non_finite'):
        measurement_to_message(rae, np.array([10.0, math.nan, 0.0]), 0, 'lidar')
    with pytest.raises(MessageError, match='non_finite'):
        measurement_to_message(rae, np.array([10.0, 0.0]), 0, 'lidar')  # wrong size
    msg = measurement_to_message(rae, np.array([10.0, 0.1, 0.2]), 0, 'lidar')
    msg.vector.z = math.inf
    with pytest.raises(MessageError) as error:
        message_to_measurement(rae, msg)
    assert error.value.reason == 'non_finite'
    ranger = make_model('range', 1e-4, min_range=1.0, max_range=100.0)
    msg = measurement_to_message(ranger, np.array([50.0]), 0, 'laser')
    for value, reason in ((150.0, 'out_of_range'), (0.5, 'out_of_range'), (math.nan, 'non_finite')):
        msg.range = value
        with pytest.raises(MessageError) as error:
            message_to_measurement(ranger, msg)
        assert error.value.reason == reason


@pytest.mark.parametrize('name', [name for name in MODELS if name != 'position'])
def test_a_sample_the_sensor_could_not_measure_says_so_and_reads_as_none(name):
    """Outside its limits a sensor publishes "nothing measured" (REP 117's -inf too close, +inf
    no detection for sensor_msgs/Range; NaN in every component of a Vector3Stamped, or of
    relative_gps's PointStamped), which reads as z None: the estimator predicts over that step
    at once (docs/sensors.md). Table 6's position, which has no limits, says no such thing: a
    NaN point stays a broken sample."""
    model = make_model(name, NOISE[name], min_range=1.0, max_range=100.0)
    for reason in ('too_close', 'too_far', 'out_of_view', 'singular'):
        data = encode_no_measurement(model, reason, 12_300_000_000, 'lidar')
        msg = deserialize_message(data, TYPES[model.message_form])  # a message rclpy reads
        assert message_to_measurement(model, msg) is None
        assert read_measurement(model, data, 'lidar') == (12_300_000_000, None)
        if name == 'range':
            assert msg.range == (-math.inf if reason == 'too_close' else math.inf)
    with pytest.raises(MessageError, match='wrong_frame'):
        read_measurement(model, data, 'camera')
    with pytest.raises(ValueError, match='no limits'):
        encode_no_measurement(make_model('position', 1e-2), 'too_far', 0, 'lvlh')
    with pytest.raises(MessageError, match='non_finite'):
        read_measurement(make_model('position', 1e-2), encode_point(np.full(3, math.nan), (0, 1, 2), 0, 'lvlh'), 'lvlh')
    partly = measurement_to_message(model, model.h(np.array([[50.0, 1.0, 2.0, 0.0, 0.0, 0.0]]))[0], 0, 'lidar')
    if model.dim > 1 and name != 'range':  # one NaN among finite components is a broken sample
        (partly.point if model.message_form == 'point' else partly.vector).x = math.nan
        with pytest.raises(MessageError, match='non_finite'):
            message_to_measurement(model, partly)
