"""Messages <-> arrays. No other module touches message fields.

Conventions (documented in README, "Topics"):

* state ``[x, y, z, vx, vy, vz]`` in the LVLH frame <-> nav_msgs/Odometry: pose.pose.position and
  twist.twist.linear; orientation is not estimated (identity). The position block of the 6x6
  covariance goes to pose.covariance[0:3, 0:3], the velocity block to twist.covariance[0:3, 0:3];
  the position-velocity cross terms have no place in Odometry and are not published.
* a partial position measurement <-> geometry_msgs/PointStamped with NaN on unmeasured axes;
* the control (specific force, m/s^2) <-> geometry_msgs/AccelStamped accel.linear.

Wire format. The loop's topics are read and written as serialized CDR bytes (``raw=True``
subscriptions, ``publish(bytes)``) by the ``encode_*``/``decode_*`` functions below: building
and walking rclpy message objects cost more CPU per step than everything else a node does
(README, "Performance"). The bytes are the standard types' CDR, so ``ros2 topic echo``, bags and
any other node read them as usual. The message-object helpers (``state_to_odometry`` and the
like, for tests, tools and users' own nodes) go through the same codec, so there is one mapping.
"""

from __future__ import annotations

import functools
import math
import struct
from typing import Mapping, NamedTuple, Sequence

import numpy as np
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticStatus, KeyValue
from geometry_msgs.msg import AccelStamped, PointStamped
from nav_msgs.msg import Odometry
from rclpy.serialization import deserialize_message, serialize_message
from std_msgs.msg import UInt32MultiArray

NS = 1_000_000_000


class MessageError(ValueError):
    """A message that cannot be used; ``reason`` is a short key for counters."""

    def __init__(self, reason: str, detail: str):
        super().__init__(f'{reason}: {detail}')
        self.reason = reason


def ns_to_stamp(nanoseconds: int) -> Time:
    nanoseconds = int(nanoseconds)
    return Time(sec=nanoseconds // NS, nanosec=nanoseconds % NS)


def stamp_to_ns(stamp: Time) -> int:
    return int(stamp.sec) * NS + int(stamp.nanosec)


def seconds_to_ns(seconds: float) -> int:
    return int(round(seconds * NS))


# ---------------------------------------------------------------- wire format (CDR)
#: Encapsulation header of plain CDR, little-endian: what rmw_fastrtps and rmw_cyclonedds write
#: for ROS 2 types. Anything else (big-endian, XCDR2) is decoded through rclpy instead.
CDR_LE = b'\x00\x01\x00\x00'
_STAMP_AND_LENGTH = struct.Struct('<iII')  # header.stamp.sec, .nanosec, frame_id length
_U32 = struct.Struct('<I')
_STAMP = struct.Struct('<iI')  # builtin_interfaces/Time: sec, nanosec
# Odometry after its child_frame_id: 85 doubles, in this order
_POSITION, _POSE_COVARIANCE, _LINEAR, _TWIST_COVARIANCE = slice(0, 3), slice(7, 43), slice(43, 46), slice(49, 85)
_ORIENTATION_W = 6
_ODOMETRY_DOUBLES = 85


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


def _body_offset(offset: int, alignment: int) -> int:
    """``offset`` (from the start of the bytes) moved up to ``alignment``; CDR aligns relative to
    the end of the 4-byte encapsulation header."""
    return offset + (-(offset - 4) % alignment)


def _pad(out: bytearray, alignment: int) -> None:
    """Zero bytes up to ``alignment`` (counted, like every CDR offset, after the
    encapsulation header)."""
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
    sec, nanosec = divmod(int(stamp_ns), NS)
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
    return sec * NS + nanosec, data[16:end - 1].decode(), end


def _doubles(out: bytearray, values: np.ndarray) -> bytes:
    _pad(out, 8)
    out += np.ascontiguousarray(values, dtype='<f8').tobytes()
    return bytes(out)


def _through_rclpy(data: bytes, message_type) -> bytes:
    """Re-serialized by rclpy (as little-endian CDR on this machine); MessageError if it
    cannot read the bytes. (rclpy raises its own error types, hence the broad except.)"""
    try:
        return serialize_message(deserialize_message(data, message_type))
    except Exception as error:  # noqa: BLE001 - converted into the one error callers handle
        raise MessageError('malformed', f'rclpy cannot read {len(data)} bytes as '
                           f'{message_type.__name__}: {error}') from None


def _decoder(message_type):
    """Decorate a little-endian CDR decoder of ``message_type``: other encodings go through
    rclpy first (slow but general); truncated or garbled bytes raise MessageError('malformed')."""
    def decorate(decode):
        @functools.wraps(decode)
        def wrapper(data: bytes):
            try:
                if data[:4] != CDR_LE:
                    data = _through_rclpy(data, message_type)
                    if data[:4] != CDR_LE:
                        raise MessageError('malformed', f'unsupported CDR encapsulation {data[:4].hex()}')
                return decode(data)
            except MessageError:
                raise
            except (struct.error, ValueError, UnicodeDecodeError) as error:
                raise MessageError('malformed', f'cannot decode {len(data)} bytes as '
                                   f'{message_type.__name__}: {error}') from None
        return wrapper
    return decorate


def _padded(block: np.ndarray) -> np.ndarray:
    """A 3x3 block in the top-left of a flat 6x6 ROS covariance."""
    full = np.zeros((6, 6))
    full[:3, :3] = block
    return full.ravel()


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
        values[_POSE_COVARIANCE] = _padded(covariance[:3, :3])
        values[_TWIST_COVARIANCE] = _padded(covariance[3:, 3:])
    return _doubles(out, values)


@_decoder(Odometry)
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


@_decoder(PointStamped)
def decode_point(data: bytes) -> StampedVector:
    """The stamp, frame and point of a PointStamped's CDR."""
    return _stamped_vector(data)


def encode_accel(u: np.ndarray, stamp_ns: int, frame_id: str) -> bytes:
    """CDR of an AccelStamped: ``u`` in accel.linear, zero angular acceleration."""
    values = np.zeros(6)
    values[:3] = u
    return _doubles(_header(stamp_ns, frame_id), values)


@_decoder(AccelStamped)
def decode_accel(data: bytes) -> StampedVector:
    """The stamp, frame and accel.linear (it comes before angular) of an AccelStamped's CDR."""
    return _stamped_vector(data)


def encode_clock(stamp_ns: int) -> bytes:
    """CDR of a rosgraph_msgs/Clock (what the plant publishes on /clock every step)."""
    sec, nanosec = divmod(int(stamp_ns), NS)
    return CDR_LE + _STAMP.pack(sec, nanosec)


def encode_uint32(value: int) -> bytes:
    """CDR of a std_msgs/UInt32."""
    return CDR_LE + _U32.pack(int(value))


def encode_spikes(spikes: np.ndarray) -> bytes:
    """CDR of a UInt32MultiArray of per-neuron spike counts of one step (one dimension, label
    'neuron')."""
    counts = np.asarray(spikes).astype('<u4', copy=False).ravel()
    out = bytearray(CDR_LE)
    out += _U32.pack(1)  # layout.dim: one dimension
    _write_string(out, 'neuron')
    _pad(out, 4)
    out += struct.pack('<III', counts.size, counts.size, 0)  # size, stride, layout.data_offset
    out += _U32.pack(counts.size)
    out += counts.tobytes()
    return bytes(out)


# ---------------------------------------------------------------- records -> arrays, checked
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


# ---------------------------------------------------------------- message objects (same codec)
def state_to_odometry(x: np.ndarray, covariance: np.ndarray | None, stamp_ns: int,
                      frame_id: str, child_frame_id: str) -> Odometry:
    """Odometry of a 6-state ``x``; ``covariance`` None publishes zeros (not computed)."""
    return deserialize_message(encode_odometry(x, covariance, stamp_ns, frame_id, child_frame_id), Odometry)


def odometry_to_state(msg: Odometry) -> tuple[np.ndarray, np.ndarray]:
    """(x, covariance with the two published blocks); raises MessageError if not finite."""
    record = decode_odometry(serialize_message(msg))
    return state_of(record), record.covariance


def measurement_to_point(z: np.ndarray, measured_axes: Sequence[int], stamp_ns: int,
                         frame_id: str) -> PointStamped:
    """PointStamped with the measured axes filled in and NaN elsewhere."""
    return deserialize_message(encode_point(z, measured_axes, stamp_ns, frame_id), PointStamped)


def point_to_measurement(msg: PointStamped, measured_axes: Sequence[int]) -> np.ndarray:
    """The measured axes of a PointStamped; raises MessageError if one of them is not finite."""
    return measurement_of(decode_point(serialize_message(msg)), measured_axes)


def control_to_accel(u: np.ndarray, stamp_ns: int, frame_id: str) -> AccelStamped:
    return deserialize_message(encode_accel(u, stamp_ns, frame_id), AccelStamped)


def accel_to_control(msg: AccelStamped) -> np.ndarray:
    return control_of(decode_accel(serialize_message(msg)))


def spikes_message(spikes: np.ndarray) -> UInt32MultiArray:
    """Per-neuron spike counts of one step (label 'neuron')."""
    return deserialize_message(encode_spikes(spikes), UInt32MultiArray)


def diagnostic_status(name: str, hardware_id: str, level: bytes, message: str,
                      values: Mapping[str, object]) -> DiagnosticStatus:
    """``level`` is one of DiagnosticStatus.OK, WARN, ERROR, STALE."""
    status = DiagnosticStatus(name=name, hardware_id=hardware_id, message=message, level=level)
    status.values = [KeyValue(key=str(k), value=_format_value(v)) for k, v in values.items()]
    return status


def _format_value(value) -> str:
    if isinstance(value, float):
        return repr(value)
    return str(value)


def diagnostic_values(status: DiagnosticStatus) -> dict:
    """KeyValue pairs of a status as a dict of strings."""
    return {kv.key: kv.value for kv in status.values}
