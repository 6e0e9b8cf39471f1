"""Messages <-> arrays. No other module touches message fields.

Conventions (documented in README, "Topics"):

* state ``[x, y, z, vx, vy, vz]`` in the LVLH frame <-> nav_msgs/Odometry: pose.pose.position and
  twist.twist.linear; orientation is not estimated (identity). The position block of the 6x6
  covariance goes to pose.covariance[0:3, 0:3], the velocity block to twist.covariance[0:3, 0:3];
  the position-velocity cross terms have no place in Odometry and are not published.
* a partial position measurement <-> geometry_msgs/PointStamped with NaN on unmeasured axes;
* the control (specific force, m/s^2) <-> geometry_msgs/AccelStamped accel.linear.
"""

from __future__ import annotations

import math
from typing import Mapping, Sequence

import numpy as np
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticStatus, KeyValue
from geometry_msgs.msg import AccelStamped, PointStamped
from nav_msgs.msg import Odometry
from std_msgs.msg import MultiArrayDimension, UInt32, UInt32MultiArray

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


def _padded(block: np.ndarray) -> np.ndarray:
    """A 3x3 block in the top-left of a flat 6x6 ROS covariance."""
    full = np.zeros((6, 6))
    full[:3, :3] = block
    return full.ravel()


def state_to_odometry(x: np.ndarray, covariance: np.ndarray | None, stamp_ns: int,
                      frame_id: str, child_frame_id: str) -> Odometry:
    """Odometry of a 6-state ``x``; ``covariance`` None publishes zeros (not computed)."""
    msg = Odometry()
    msg.header.stamp = ns_to_stamp(stamp_ns)
    msg.header.frame_id = frame_id
    msg.child_frame_id = child_frame_id
    position, velocity = msg.pose.pose.position, msg.twist.twist.linear
    position.x, position.y, position.z = float(x[0]), float(x[1]), float(x[2])
    velocity.x, velocity.y, velocity.z = float(x[3]), float(x[4]), float(x[5])
    msg.pose.pose.orientation.w = 1.0
    if covariance is not None:
        msg.pose.covariance = _padded(covariance[:3, :3])
        msg.twist.covariance = _padded(covariance[3:, 3:])
    return msg


def odometry_to_state(msg: Odometry) -> tuple[np.ndarray, np.ndarray]:
    """(x, covariance with the two published blocks); raises MessageError if not finite."""
    p, v = msg.pose.pose.position, msg.twist.twist.linear
    x = np.array([p.x, p.y, p.z, v.x, v.y, v.z], dtype=float)
    if not np.all(np.isfinite(x)):
        raise MessageError('non_finite', f'state has NaN/Inf: {x.tolist()}')
    covariance = np.zeros((6, 6))
    covariance[:3, :3] = np.asarray(msg.pose.covariance, dtype=float).reshape(6, 6)[:3, :3]
    covariance[3:, 3:] = np.asarray(msg.twist.covariance, dtype=float).reshape(6, 6)[:3, :3]
    return x, covariance


def measurement_to_point(z: np.ndarray, measured_axes: Sequence[int], stamp_ns: int,
                         frame_id: str) -> PointStamped:
    """PointStamped with the measured axes filled in and NaN elsewhere."""
    values = [math.nan, math.nan, math.nan]
    for value, axis in zip(z, measured_axes):
        values[axis] = float(value)
    msg = PointStamped()
    msg.header.stamp = ns_to_stamp(stamp_ns)
    msg.header.frame_id = frame_id
    msg.point.x, msg.point.y, msg.point.z = values
    return msg


def point_to_measurement(msg: PointStamped, measured_axes: Sequence[int]) -> np.ndarray:
    """The measured axes of a PointStamped; raises MessageError if one of them is not finite."""
    values = (msg.point.x, msg.point.y, msg.point.z)
    z = np.array([values[axis] for axis in measured_axes], dtype=float)
    if not np.all(np.isfinite(z)):
        raise MessageError('non_finite', f'measured axes {list(measured_axes)} hold {z.tolist()}')
    return z


def control_to_accel(u: np.ndarray, stamp_ns: int, frame_id: str) -> AccelStamped:
    msg = AccelStamped()
    msg.header.stamp = ns_to_stamp(stamp_ns)
    msg.header.frame_id = frame_id
    msg.accel.linear.x, msg.accel.linear.y, msg.accel.linear.z = (float(v) for v in u)
    return msg


def accel_to_control(msg: AccelStamped) -> np.ndarray:
    linear = msg.accel.linear
    u = np.array([linear.x, linear.y, linear.z], dtype=float)
    if not np.all(np.isfinite(u)):
        raise MessageError('non_finite', f'control has NaN/Inf: {u.tolist()}')
    return u


def spike_count_message(count: int) -> UInt32:
    return UInt32(data=int(count))


def spikes_message(spikes: np.ndarray) -> UInt32MultiArray:
    """Per-neuron spike counts of one step (label 'neuron')."""
    msg = UInt32MultiArray()
    msg.layout.dim = [MultiArrayDimension(label='neuron', size=int(spikes.size), stride=int(spikes.size))]
    msg.data = np.asarray(spikes, dtype=np.uint32)
    return msg


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
