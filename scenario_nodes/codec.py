"""The pipeline's messages as CDR bytes <-> arrays: the one codec, free of rclpy.

The nodes read and write the loop's topics as serialized CDR (``raw=True`` subscriptions,
``publish(bytes)``): building and walking rclpy message objects cost more CPU per step than
everything else a node does (docs/performance.md). The bag tools decode recorded bags with the
same functions. The bytes are the standard types' CDR, so ``ros2 topic echo``, bags and any
other node read them as usual.

Conventions (README, "Topics and QoS"):

* state ``[x, y, z, vx, vy, vz]`` in the LVLH frame <-> nav_msgs/Odometry: pose.pose.position and
  twist.twist.linear; orientation is not estimated (identity). The position block of the 6x6
  covariance goes to pose.covariance[0:3, 0:3], the velocity block to twist.covariance[0:3, 0:3];
  the position-velocity cross terms have no place in Odometry and are not published.
* a partial position measurement <-> geometry_msgs/PointStamped with NaN on unmeasured axes;
* the control (specific force, m/s^2) <-> geometry_msgs/AccelStamped accel.linear;
* any measurement model's sample (snn_estimator.measurements) <-> the message of its
  ``message_form`` (:func:`encode_measurement`, :func:`decode_measurement`; docs/sensors.md):
  'point' PointStamped as above, 'range' sensor_msgs/Range (field of view, limits and variance
  in the message), 'vector' geometry_msgs/Vector3Stamped with the components in model order
  and NaN on unused ones;
* a sample the sensor took and could not measure (outside its field of view or range:
  :func:`encode_no_measurement`) <-> a Range whose range is -inf (too close) or +inf (no
  detection), as REP 117 prescribes, or a Vector3Stamped with NaN in every component; it decodes
  to z None, so that an estimator predicts over that step at once.

Fast path: plain little-endian CDR, recognised by the representation identifier (bytes 0-1 of
the encapsulation header, 0x0001); the options (bytes 2-3) are ignored, as the XTypes standard
lets a middleware set them. Any other representation (big-endian CDR, ...) is decoded by the
rosbags type store (slower, general). Every malformed or out-of-range input raises
:class:`MessageError` with a reason key for the diagnostics counters.
"""

from __future__ import annotations

import functools
import math
import struct
from typing import NamedTuple, Sequence

import numpy as np

from snn_estimator.runners.gates import NS, seconds_to_ns  # noqa: F401 (re-exported: one time helper)

#: Representation identifier of little-endian plain CDR (bytes 0-1 of the encapsulation header).
CDR_LE_ID = b'\x00\x01'
CDR_LE = CDR_LE_ID + b'\x00\x00'
#: A builtin_interfaces/Time holds int32 seconds.
MAX_STAMP_NS = (2 ** 31 - 1) * NS + NS - 1

_STAMP_AND_LENGTH = struct.Struct('<iII')  # header.stamp.sec, .nanosec, frame_id length
_U32 = struct.Struct('<I')
_STAMP = struct.Struct('<iI')  # builtin_interfaces/Time: sec, nanosec
# Odometry after its child_frame_id: 85 doubles, in this order
_POSITION, _POSE_COVARIANCE, _LINEAR, _TWIST_COVARIANCE = slice(0, 3), slice(7, 43), slice(43, 46), slice(49, 85)
_ORIENTATION_W = 6
_ODOMETRY_DOUBLES = 85

ODOMETRY = 'nav_msgs/msg/Odometry'
POINT_STAMPED = 'geometry_msgs/msg/PointStamped'
ACCEL_STAMPED = 'geometry_msgs/msg/AccelStamped'
VECTOR3_STAMPED = 'geometry_msgs/msg/Vector3Stamped'
RANGE = 'sensor_msgs/msg/Range'
#: sensor_msgs/Range.radiation_type: a laser (LIDAR) ranger is INFRARED; the type has no radar or RF.
RANGE_INFRARED = 1
#: A measurement model's message_form -> the message type it travels in.
MEASUREMENT_TYPES = {'point': POINT_STAMPED, 'range': RANGE, 'vector': VECTOR3_STAMPED}
_RANGE_FLOATS = struct.Struct('<5f')  # field_of_view, min_range, max_range, range, variance


class MessageError(ValueError):
    """A message that cannot be used; ``reason`` is a short key for counters."""

    def __init__(self, reason: str, detail: str):
        super().__init__(f'{reason}: {detail}')
        self.reason = reason


def split_stamp(stamp_ns: int) -> tuple[int, int]:
    """(sec, nanosec) of a builtin_interfaces/Time; MessageError outside int32 seconds."""
    stamp_ns = int(stamp_ns)
    if not 0 <= stamp_ns <= MAX_STAMP_NS:
        raise MessageError('out_of_range', f'stamp {stamp_ns} ns is outside a ROS time (int32 seconds, '
                           'not negative)')
    return divmod(stamp_ns, NS)


class OdometryRecord(NamedTuple):
    """A received nav_msgs/Odometry: header, child frame and its 85 doubles (a read-only view
    of the bytes). ``state`` and ``covariance`` are built when asked for: most readers need only
    the state."""
    stamp_ns: int
    frame_id: str
    child_frame_id: str
    values: np.ndarray

    @property
    def state(self) -> np.ndarray:
        """[x, y, z, vx, vy, vz] as received (may be NaN)."""
        return np.concatenate((self.values[_POSITION], self.values[_LINEAR]))

    @property
    def covariance(self) -> np.ndarray:
        """6x6 with the two published blocks, zeros elsewhere."""
        covariance = np.zeros((6, 6))
        covariance[:3, :3] = self.values[_POSE_COVARIANCE].reshape(6, 6)[:3, :3]
        covariance[3:, 3:] = self.values[_TWIST_COVARIANCE].reshape(6, 6)[:3, :3]
        return covariance


class StampedVector(NamedTuple):
    """A stamped 3-vector: PointStamped.point or AccelStamped.accel.linear, as received."""
    stamp_ns: int
    frame_id: str
    vector: np.ndarray


# ---------------------------------------------------------------- CDR primitives
def _body_offset(offset: int, alignment: int) -> int:
    """``offset`` (from the start of the bytes) moved up to ``alignment``; CDR aligns relative to
    the end of the 4-byte encapsulation header."""
    return offset + (-(offset - 4) % alignment)


def _pad(out: bytearray, alignment: int) -> None:
    out += bytes(-(len(out) - 4) % alignment)


def _write_string(out: bytearray, text: str) -> None:
    encoded = text.encode() + b'\0'
    _pad(out, 4)
    out += _U32.pack(len(encoded))
    out += encoded


def _read_string(data: bytes, offset: int) -> tuple[str, int]:
    offset = _body_offset(offset, 4)
    (length,) = _U32.unpack_from(data, offset)
    end = offset + 4 + length
    if length == 0 or end > len(data):
        raise MessageError('malformed', f'string of {length} bytes at offset {offset} in {len(data)} bytes')
    return data[offset + 4:end - 1].decode(), end


def _header(stamp_ns: int, frame_id: str) -> bytearray:
    sec, nanosec = split_stamp(stamp_ns)
    encoded = frame_id.encode() + b'\0'
    out = bytearray(CDR_LE)
    out += _STAMP_AND_LENGTH.pack(sec, nanosec, len(encoded))
    out += encoded
    return out


def _read_header(data: bytes) -> tuple[int, str, int]:
    """(stamp in ns, frame_id, offset after the header)."""
    sec, nanosec, length = _STAMP_AND_LENGTH.unpack_from(data, 4)
    end = 16 + length
    if length == 0 or end > len(data):
        raise MessageError('malformed', f'frame_id of {length} bytes in {len(data)} bytes')
    if sec < 0 or nanosec >= NS:
        raise MessageError('out_of_range', f'stamp sec={sec} nanosec={nanosec} is not a valid time')
    return sec * NS + nanosec, data[16:end - 1].decode(), end


def decode_stamp(data: bytes) -> int:
    """The header stamp (ns) of any message that starts with a std_msgs/Header."""
    if len(data) < 16:
        raise MessageError('malformed', f'{len(data)} bytes hold no header')
    return _read_header(data)[0]


def _doubles(out: bytearray, values: np.ndarray) -> bytes:
    _pad(out, 8)
    out += np.ascontiguousarray(values, dtype='<f8').tobytes()
    return bytes(out)


@functools.lru_cache(maxsize=1)
def _typestore():
    from rosbags.typesys import Stores, get_typestore
    return get_typestore(Stores.ROS2_JAZZY)


def _stamp_of(header) -> int:
    return int(header.stamp.sec) * NS + int(header.stamp.nanosec)


def _general(data: bytes, type_name: str):
    """Decode any CDR representation with the rosbags type store (MessageError if it cannot)."""
    try:
        return _typestore().deserialize_cdr(data, type_name)
    except Exception as error:  # noqa: BLE001 - rosbags raises several types; one error for callers
        raise MessageError('malformed', f'cannot read {len(data)} bytes as {type_name}: {error}') from None


def _decoder(type_name: str, general):
    """Decorate a little-endian CDR decoder: another representation goes through
    ``general(message)`` on the rosbags-decoded message; truncated or garbled bytes raise
    MessageError('malformed')."""
    def decorate(decode):
        @functools.wraps(decode)
        def wrapper(data: bytes):
            try:
                if bytes(data[:2]) != CDR_LE_ID:
                    if len(data) < 4:
                        raise MessageError('malformed', f'{len(data)} bytes cannot hold a CDR header')
                    return general(_general(bytes(data), type_name))
                return decode(data)
            except MessageError:
                raise
            except (struct.error, ValueError, UnicodeDecodeError) as error:
                raise MessageError('malformed', f'cannot decode {len(data)} bytes as {type_name}: {error}') from None
        return wrapper
    return decorate


# ---------------------------------------------------------------- messages
def encode_odometry(x: np.ndarray, covariance: np.ndarray | None, stamp_ns: int,
                    frame_id: str, child_frame_id: str) -> bytes:
    """CDR of the Odometry of a 6-state ``x``; ``covariance`` None publishes zeros (not computed)."""
    out = _header(stamp_ns, frame_id)
    _write_string(out, child_frame_id)
    values = np.zeros(_ODOMETRY_DOUBLES)
    values[_POSITION] = x[:3]
    values[_ORIENTATION_W] = 1.0
    values[_LINEAR] = x[3:6]
    if covariance is not None:
        # the 3x3 blocks in the top-left of the flat 6x6 ROS covariances (mirror of the decoder)
        values[_POSE_COVARIANCE].reshape(6, 6)[:3, :3] = covariance[:3, :3]
        values[_TWIST_COVARIANCE].reshape(6, 6)[:3, :3] = covariance[3:, 3:]
    return _doubles(out, values)


def _odometry_from_message(msg) -> OdometryRecord:
    values = np.zeros(_ODOMETRY_DOUBLES)
    pose, twist = msg.pose.pose, msg.twist.twist
    values[_POSITION] = (pose.position.x, pose.position.y, pose.position.z)
    values[3:7] = (pose.orientation.x, pose.orientation.y, pose.orientation.z, pose.orientation.w)
    values[_POSE_COVARIANCE] = msg.pose.covariance
    values[_LINEAR] = (twist.linear.x, twist.linear.y, twist.linear.z)
    values[46:49] = (twist.angular.x, twist.angular.y, twist.angular.z)
    values[_TWIST_COVARIANCE] = msg.twist.covariance
    return OdometryRecord(_stamp_of(msg.header), msg.header.frame_id, msg.child_frame_id, values)


@_decoder(ODOMETRY, _odometry_from_message)
def decode_odometry(data: bytes) -> OdometryRecord:
    """The stamp, frames, state and covariance blocks of an Odometry's CDR."""
    stamp_ns, frame_id, offset = _read_header(data)
    child, offset = _read_string(data, offset)
    values = np.frombuffer(data, '<f8', _ODOMETRY_DOUBLES, _body_offset(offset, 8))
    return OdometryRecord(stamp_ns, frame_id, child, values)


def encode_point(z: np.ndarray, measured_axes: Sequence[int], stamp_ns: int, frame_id: str) -> bytes:
    """CDR of a PointStamped with the measured axes filled in and NaN elsewhere."""
    values = np.full(3, math.nan)
    values[list(measured_axes)] = z
    return _doubles(_header(stamp_ns, frame_id), values)


def _stamped_vector(data: bytes) -> StampedVector:
    """A Header followed by (at least) three doubles."""
    stamp_ns, frame_id, offset = _read_header(data)
    vector = np.frombuffer(data, '<f8', 3, _body_offset(offset, 8)).copy()
    return StampedVector(stamp_ns, frame_id, vector)


def _point_from_message(msg) -> StampedVector:
    p = msg.point
    return StampedVector(_stamp_of(msg.header), msg.header.frame_id, np.array([p.x, p.y, p.z]))


def _accel_from_message(msg) -> StampedVector:
    a = msg.accel.linear
    return StampedVector(_stamp_of(msg.header), msg.header.frame_id, np.array([a.x, a.y, a.z]))


@_decoder(POINT_STAMPED, _point_from_message)
def decode_point(data: bytes) -> StampedVector:
    """The stamp, frame and point of a PointStamped's CDR."""
    return _stamped_vector(data)


def encode_accel(u: np.ndarray, stamp_ns: int, frame_id: str) -> bytes:
    """CDR of an AccelStamped: ``u`` in accel.linear, zero angular acceleration."""
    values = np.zeros(6)
    values[:3] = u
    return _doubles(_header(stamp_ns, frame_id), values)


@_decoder(ACCEL_STAMPED, _accel_from_message)
def decode_accel(data: bytes) -> StampedVector:
    """The stamp, frame and accel.linear (it comes before angular) of an AccelStamped's CDR."""
    return _stamped_vector(data)


def encode_vector3(values: np.ndarray, stamp_ns: int, frame_id: str) -> bytes:
    """CDR of a Vector3Stamped holding up to three ``values`` in x, y, z (NaN after them)."""
    vector = np.full(3, math.nan)
    values = np.asarray(values, dtype=float).ravel()
    vector[:values.size] = values
    return _doubles(_header(stamp_ns, frame_id), vector)


def _vector3_from_message(msg) -> StampedVector:
    v = msg.vector
    return StampedVector(_stamp_of(msg.header), msg.header.frame_id, np.array([v.x, v.y, v.z]))


@_decoder(VECTOR3_STAMPED, _vector3_from_message)
def decode_vector3(data: bytes) -> StampedVector:
    """The stamp, frame and vector of a Vector3Stamped's CDR."""
    return _stamped_vector(data)


class RangeRecord(NamedTuple):
    """A received sensor_msgs/Range (float32 fields as received)."""
    stamp_ns: int
    frame_id: str
    radiation_type: int
    field_of_view: float
    min_range: float
    max_range: float
    range: float
    variance: float


def encode_range(value: float, stamp_ns: int, frame_id: str, field_of_view: float, min_range: float,
                 max_range: float, variance: float, radiation_type: int = RANGE_INFRARED) -> bytes:
    """CDR of a sensor_msgs/Range. Its fields are float32: a range is rounded to ~6e-8 of itself."""
    out = _header(stamp_ns, frame_id)
    out += struct.pack('<B', int(radiation_type))
    _pad(out, 4)
    out += _RANGE_FLOATS.pack(field_of_view, min_range, max_range, value, variance)
    return bytes(out)


def _range_from_message(msg) -> RangeRecord:
    return RangeRecord(_stamp_of(msg.header), msg.header.frame_id, int(msg.radiation_type), float(msg.field_of_view),
                       float(msg.min_range), float(msg.max_range), float(msg.range), float(msg.variance))


@_decoder(RANGE, _range_from_message)
def decode_range(data: bytes) -> RangeRecord:
    """The fields of a sensor_msgs/Range's CDR."""
    stamp_ns, frame_id, offset = _read_header(data)
    radiation_type = data[offset]
    values = _RANGE_FLOATS.unpack_from(data, _body_offset(offset + 1, 4))
    return RangeRecord(stamp_ns, frame_id, radiation_type, *(float(v) for v in values))


def encode_measurement(model, z: np.ndarray, stamp_ns: int, frame_id: str) -> bytes:
    """CDR of one sample ``z`` of a measurement model (snn_estimator.measurements), in the message
    of the model's ``message_form``. A sample that is not finite raises MessageError('non_finite'):
    never a NaN out."""
    z = np.asarray(z, dtype=float).ravel()
    if z.size != model.dim or not np.isfinite(z).all():
        raise MessageError('non_finite', f'{model.name} sample {z.tolist()} is not {model.dim} finite numbers')
    form = model.message_form
    if form == 'point':
        return encode_point(z, model.measured_axes, stamp_ns, frame_id)
    if form == 'range':
        return encode_range(z[0], stamp_ns, frame_id, model.field_of_view, model.min_range,
                            model.max_range or math.inf, float(model.noise[0, 0]))
    if form == 'vector':
        return encode_vector3(z, stamp_ns, frame_id)
    raise ValueError(f"message_form must be one of {', '.join(MEASUREMENT_TYPES)}; got {form!r}")


def encode_no_measurement(model, reason: str, stamp_ns: int, frame_id: str) -> bytes:
    """CDR of "sampled at ``stamp_ns``, nothing measured" (``reason``: a REASONS key of
    snn_estimator.measurements) for a model with limits: Range -inf when too close, +inf
    otherwise (REP 117); a Vector3Stamped, or a PointStamped (relative_gps), of NaN. A model
    without limits (position) measures or loses every sample: ValueError."""
    form = model.message_form
    if not model.has_limits:
        raise ValueError(f'{model.name} has no limits: every sample is measured or lost')
    if form == 'point':
        return encode_point(np.full(model.dim, math.nan), model.measured_axes, stamp_ns, frame_id)
    if form == 'range':
        return encode_range(-math.inf if reason == 'too_close' else math.inf, stamp_ns, frame_id,
                            model.field_of_view, model.min_range, model.max_range or math.inf,
                            float(model.noise[0, 0]))
    if form == 'vector':
        return encode_vector3(np.full(3, math.nan), stamp_ns, frame_id)
    raise ValueError(f'{model.name} has no limits: every sample is measured or lost')


def decode_measurement(model, data: bytes) -> tuple[int, str, np.ndarray | None]:
    """(stamp in ns, frame_id, z) of a measurement of ``model`` (the mirror of
    :func:`encode_measurement`); z None for a sample the sensor says it could not measure
    (:func:`encode_no_measurement`); MessageError for a value that is not finite, and for a
    range outside the message's own [min_range, max_range] (sensor_msgs/Range: discard it)."""
    form = model.message_form
    if form == 'point':
        record = decode_point(data)
        if model.has_limits and np.isnan(record.vector).all():  # relative_gps out of its range
            return record.stamp_ns, record.frame_id, None
        return record.stamp_ns, record.frame_id, measurement_of(record, model.measured_axes)
    if form == 'range':
        record = decode_range(data)
        if math.isinf(record.range):  # REP 117: -inf too close, +inf nothing within max_range
            return record.stamp_ns, record.frame_id, None
        if not math.isfinite(record.range):
            raise MessageError('non_finite', f'range {record.range} (REP 117: no detection)')
        if not record.min_range <= record.range <= record.max_range:
            raise MessageError('out_of_range', f'range {record.range} m outside [{record.min_range}, '
                               f'{record.max_range}] m')
        return record.stamp_ns, record.frame_id, np.array([record.range])
    if form == 'vector':
        record = decode_vector3(data)
        if np.isnan(record.vector).all():
            return record.stamp_ns, record.frame_id, None
        z = record.vector[:model.dim]
        if not np.isfinite(z).all():
            raise MessageError('non_finite', f'{model.name} components {z.tolist()}')
        return record.stamp_ns, record.frame_id, z
    raise ValueError(f"message_form must be one of {', '.join(MEASUREMENT_TYPES)}; got {form!r}")


def sensor_report(type_name: str, data: bytes) -> tuple[int, bool]:
    """(stamp in ns, measured) of any sensor's message, without knowing its model: False for
    "nothing measured" (:func:`encode_no_measurement`: a Range of -inf or +inf, REP 117; a
    Vector3Stamped, or PointStamped, of NaN only). For reading recorded runs."""
    if type_name == RANGE:
        record = decode_range(data)
        return record.stamp_ns, not math.isinf(record.range)
    if type_name not in (POINT_STAMPED, VECTOR3_STAMPED):
        raise ValueError(f"a sensor report is one of {', '.join(sorted(MEASUREMENT_TYPES.values()))}; "
                         f'got {type_name!r}')
    record = decode_point(data)  # PointStamped and Vector3Stamped: one layout
    return record.stamp_ns, not np.isnan(record.vector).all()


def encode_clock(stamp_ns: int) -> bytes:
    """CDR of a rosgraph_msgs/Clock (what the plant publishes on /clock every step)."""
    return CDR_LE + _STAMP.pack(*split_stamp(stamp_ns))


def encode_uint32(value: int) -> bytes:
    """CDR of a std_msgs/UInt32."""
    value = int(value)
    if not 0 <= value < 2 ** 32:
        raise MessageError('out_of_range', f'{value} does not fit a UInt32')
    return CDR_LE + _U32.pack(value)


@_decoder('std_msgs/msg/UInt32', lambda msg: int(msg.data))
def decode_uint32(data: bytes) -> int:
    return _U32.unpack_from(data, 4)[0]


def encode_spikes(spikes: np.ndarray) -> bytes:
    """CDR of a UInt32MultiArray of per-neuron spike counts of one step (one dimension, label
    'neuron')."""
    counts = np.asarray(spikes).ravel()
    if counts.size and (counts.min() < 0 or counts.max() >= 2 ** 32):
        raise MessageError('out_of_range', 'spike counts must fit a UInt32')
    counts = counts.astype('<u4')
    out = bytearray(CDR_LE)
    out += _U32.pack(1)  # layout.dim: one dimension
    _write_string(out, 'neuron')
    _pad(out, 4)
    out += struct.pack('<III', counts.size, counts.size, 0)  # size, stride, layout.data_offset
    out += _U32.pack(counts.size)
    out += counts.tobytes()
    return bytes(out)


def _spikes_from_message(msg) -> np.ndarray:
    return np.asarray(msg.data, dtype=np.int64)


@_decoder('std_msgs/msg/UInt32MultiArray', _spikes_from_message)
def decode_spikes(data: bytes) -> np.ndarray:
    """Per-neuron counts of a UInt32MultiArray's CDR (any layout: read from its data field)."""
    (dims,) = _U32.unpack_from(data, 4)
    offset = 8
    for _ in range(dims):  # MultiArrayDimension: label, size, stride
        _, offset = _read_string(data, offset)
        offset = _body_offset(offset, 4) + 8
    offset = _body_offset(offset, 4) + 4  # data_offset
    (count,) = _U32.unpack_from(data, offset)
    if offset + 4 + 4 * count > len(data):
        raise MessageError('malformed', f'{count} counts in {len(data)} bytes')
    return np.frombuffer(data, '<u4', count, offset + 4).astype(np.int64)


# ---------------------------------------------------------------- records -> arrays, checked
def read_measurement(model, data: bytes, frame_id: str) -> tuple[int, np.ndarray | None]:
    """(stamp in ns, z or None: nothing measured) of a measurement of ``model`` in ``frame_id``
    (:func:`decode_measurement`); MessageError('wrong_frame') for another frame."""
    stamp_ns, frame, z = decode_measurement(model, data)
    if frame != frame_id:
        raise MessageError('wrong_frame', f"frame '{frame}', expected '{frame_id}'")
    return stamp_ns, z


def check_frame(record, frame_id: str):
    """``record`` if it is in ``frame_id``; MessageError('wrong_frame') otherwise."""
    if record.frame_id != frame_id:
        raise MessageError('wrong_frame', f"frame '{record.frame_id}', expected '{frame_id}'")
    return record


def state_of(record: OdometryRecord) -> np.ndarray:
    """The state; raises MessageError if it is not finite."""
    state = record.state
    if not np.isfinite(state).all():
        raise MessageError('non_finite', f'state has NaN/Inf: {state.tolist()}')
    return state


def measurement_of(record: StampedVector, measured_axes: Sequence[int]) -> np.ndarray:
    """The measured axes; raises MessageError if one of them is not finite."""
    z = record.vector[list(measured_axes)]
    if not np.isfinite(z).all():
        raise MessageError('non_finite', f'measured axes {list(measured_axes)} hold {z.tolist()}')
    return z


def control_of(record: StampedVector) -> np.ndarray:
    """The control; raises MessageError if it is not finite."""
    if not np.isfinite(record.vector).all():
        raise MessageError('non_finite', f'control has NaN/Inf: {record.vector.tolist()}')
    return record.vector


#: What each input of the loop is: its decoder and the checked value a node uses.
_INPUTS = {
    'state': (decode_odometry, lambda record, axes: state_of(record)),
    'measurement': (decode_point, lambda record, axes: measurement_of(record, axes)),
    'control': (decode_accel, lambda record, axes: control_of(record)),
}


def read_input(kind: str, data: bytes, frame_id: str, measured_axes: Sequence[int] = ()) -> tuple:
    """Decode one input of the loop (``kind``: state | measurement | control, as raw CDR),
    check its frame and extract its finite value: (record, value). Raises MessageError with the
    reason (malformed, wrong_frame, non_finite), what every node counts and logs."""
    decode, extract = _INPUTS[kind]
    record = check_frame(decode(data), frame_id)
    return record, extract(record, measured_axes)
