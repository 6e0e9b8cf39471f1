"""Message objects <-> arrays, for tests, tools and users' own nodes, through the one codec.

The nodes work on CDR bytes with :mod:`scenario_nodes.codec` (rclpy-free, also used by the bag
tools); the helpers here build and read rclpy message objects by serializing them and going
through that same codec, so there is one mapping between messages and arrays.
"""

from __future__ import annotations

from typing import Mapping, Sequence

import numpy as np
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import AccelStamped, PointStamped, Vector3Stamped
from nav_msgs.msg import Odometry
from rclpy.serialization import deserialize_message, serialize_message
from sensor_msgs.msg import Range
from std_msgs.msg import UInt32MultiArray

from snn_estimator.plant.approach import ENDS_WITHOUT_CONTACT

from .codec import (  # noqa: F401 (re-exported)
    NS,
    MessageError,
    control_of,
    decode_accel,
    decode_measurement,
    decode_odometry,
    decode_point,
    decode_range,
    decode_vector3,
    encode_accel,
    encode_measurement,
    encode_odometry,
    encode_point,
    encode_range,
    encode_spikes,
    encode_vector3,
    measurement_of,
    split_stamp,
    state_of,
)


def ns_to_stamp(nanoseconds: int) -> Time:
    sec, nanosec = split_stamp(nanoseconds)
    return Time(sec=sec, nanosec=nanosec)


def stamp_to_ns(stamp: Time) -> int:
    return int(stamp.sec) * NS + int(stamp.nanosec)


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


#: A measurement model's message_form -> its rclpy message class (codec.MEASUREMENT_TYPES).
MEASUREMENT_CLASSES = {'point': PointStamped, 'range': Range, 'vector': Vector3Stamped}


def measurement_to_message(model, z: np.ndarray, stamp_ns: int, frame_id: str):
    """The message of one sample of a measurement model (PointStamped, Range or Vector3Stamped,
    by its message_form; docs/sensors.md); MessageError if ``z`` is not finite."""
    return deserialize_message(encode_measurement(model, z, stamp_ns, frame_id),
                               MEASUREMENT_CLASSES[model.message_form])


def message_to_measurement(model, msg) -> np.ndarray | None:
    """``z`` of a measurement message of ``model`` (None: the sensor measured nothing);
    MessageError for a value not finite, or a range outside the message's limits."""
    return decode_measurement(model, serialize_message(msg))[2]


def values_to_vector3(values: np.ndarray, stamp_ns: int, frame_id: str) -> Vector3Stamped:
    """Vector3Stamped with up to three values in x, y, z and NaN after them."""
    return deserialize_message(encode_vector3(values, stamp_ns, frame_id), Vector3Stamped)


def range_message(value: float, stamp_ns: int, frame_id: str, field_of_view: float, min_range: float,
                  max_range: float, variance: float) -> Range:
    """sensor_msgs/Range (radiation_type INFRARED: a laser ranger)."""
    return deserialize_message(encode_range(value, stamp_ns, frame_id, field_of_view, min_range, max_range,
                                            variance), Range)


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


# ---------------------------------------------------------------- the approach guidance's events
#: The status name of a guidance event on `guidance` (one DiagnosticArray per event).
GUIDANCE_STATUS = 'approach_guidance'


def guidance_event(stamp_ns: int, hardware_id: str, name: str, phase: str,
                   detail: Mapping[str, object]) -> DiagnosticArray:
    """One guidance event at ``stamp_ns``: message ``name`` ('go 5 km', 'arrive 250 m', 'abort'),
    values phase (after the event), event and ``detail`` (the go criteria, the abort's bound);
    level ERROR for an abort, WARN for a no-go, else OK."""
    level = (DiagnosticStatus.ERROR if phase == 'abort' else DiagnosticStatus.WARN if phase == 'no_go'
             else DiagnosticStatus.OK)
    array = DiagnosticArray()
    array.header.stamp = ns_to_stamp(stamp_ns)
    array.status = [diagnostic_status(GUIDANCE_STATUS, hardware_id, level, name,
                                      {'phase': phase, 'event': name, **detail})]
    return array


def guidance_end(msg: DiagnosticArray) -> int | None:
    """The stamp (ns) of a guidance event that ended the approach without contact, else None."""
    for status in msg.status:
        if status.name == GUIDANCE_STATUS and diagnostic_values(status).get('phase') in ENDS_WITHOUT_CONTACT:
            return stamp_to_ns(msg.header.stamp)
    return None
