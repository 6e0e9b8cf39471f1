"""Read what publishers that keep history still hold on a few topics, once, synchronously.

A node that joins a running loop (a replacement estimator) starts better from the topics'
history: the newest estimate of the estimator it replaces, the sensor's recent measurements,
the controller's recent controls. The pipeline's publishers keep it on ``<topic>/history``
(transient local; the topics themselves are volatile, so that a late joiner such as ``ros2
topic echo`` sees the present). It is read by a short-lived transient-local reader per topic,
the way ``ros2 topic echo --qos-durability transient_local`` reads it. It runs
inside a lifecycle transition (the executor is busy running it), so it waits on its own wait
set, as ``rclpy.wait_for_message`` does.
"""

from __future__ import annotations

import time

from geometry_msgs.msg import AccelStamped, PointStamped
from nav_msgs.msg import Odometry
from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.qos import DurabilityPolicy

from snn_estimator.runners.start_up import History

from . import qos
from .codec import MessageError, read_input, read_measurement
from .conversions import MEASUREMENT_CLASSES
from .qos import HISTORY_QOS

#: Seconds a node that has just started gives discovery to show it the publishers there are.
DISCOVERY = 0.5
#: Seconds without a new sample, once every history-keeping publisher matched, after which
#: the history is taken to be complete (it follows the match at once).
QUIET = 0.1


def resolved_history(node, topic: str) -> str:
    """``topic``'s history as its publisher names it: beside the topic remapped (qos.HistoryPublisher)."""
    return qos.history_topic(node.resolve_topic_name(topic))


def keeping_publishers(node, topic: str) -> int:
    """Publishers of ``topic``'s history for late joiners (transient local)."""
    return sum(1 for info in node.get_publishers_info_by_topic(resolved_history(node, topic))
               if info.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL)


def read_history(node, topics: dict, wait: float) -> dict[str, list[bytes]]:
    """The serialized samples that ``topics`` (name -> message type) hold, oldest first.

    Looks for history-keeping publishers for DISCOVERY s (at most ``wait``), reads from those
    it finds until each matched and nothing new came for QUIET s, and gives up after ``wait``
    wall-clock seconds in all.
    """
    samples: dict[str, list[bytes]] = {topic: [] for topic in topics}
    quiet_events = SubscriptionEventCallbacks(incompatible_qos=lambda event: None)
    readers = {}
    started = time.monotonic()
    deadline = started + wait
    last_sample = matched_since = None
    try:
        while time.monotonic() < deadline:
            for topic in topics:
                if topic not in readers and keeping_publishers(node, topic):
                    readers[topic] = node.create_subscription(
                        topics[topic], resolved_history(node, topic), lambda _: None, HISTORY_QOS, raw=True,
                        event_callbacks=quiet_events)
                    matched_since = None
            if _take(node, readers, samples):
                last_sample = time.monotonic()
            now = time.monotonic()
            matched = all(reader.get_publisher_count() >= keeping_publishers(node, topic)
                          for topic, reader in readers.items())
            if matched and matched_since is None:
                matched_since = now
            if (now - started >= min(DISCOVERY, wait) and matched
                    and now - max(matched_since, last_sample or 0.0) >= QUIET):
                break
    finally:
        for reader in readers.values():
            node.destroy_subscription(reader)
    return samples


def _take(node, readers: dict, samples: dict) -> int:
    """Wait up to 20 ms for samples on ``readers``, append all that are there, return how many."""
    if not readers:
        time.sleep(0.02)
        return 0
    wait_set = _rclpy.WaitSet(len(readers), 0, 0, 0, 0, 0, node.context.handle)
    for reader in readers.values():
        wait_set.add_subscription(reader.handle)
    wait_set.wait(int(0.02 * 1e9))
    ready = set(wait_set.get_ready_entities('subscription'))
    taken_now = 0
    for topic, reader in readers.items():
        if reader.handle.pointer in ready:
            while (taken := reader.handle.take_message(reader.msg_type, True)) is not None:
                samples[topic].append(taken[0])
                taken_now += 1
    return taken_now


def collect_history(node, frame_id: str, axes, wait: float, model=None, sensor_frame_id: str = '') -> History:
    """What the pipeline's topics hold for a joining estimator (an earlier estimator's
    estimates, the sensor's measurements of ``model``, None: position; the controller's
    controls), decoded and logged."""
    topics = {qos.ESTIMATE: Odometry, qos.CONTROL: AccelStamped}
    if model is None or model.message_form in MEASUREMENT_CLASSES:  # several sensors: no `measurement`
        topics[qos.MEASUREMENT] = PointStamped if model is None else MEASUREMENT_CLASSES[model.message_form]
    raw = read_history(node, topics, wait)
    node.get_logger().info('history: ' + ', '.join(f"{len(raw[t])} on '{t}'" for t in raw))
    return decode_history(raw, frame_id, axes, model, sensor_frame_id)


def decode_history(raw: dict, frame_id: str, axes, model=None, sensor_frame_id: str = '') -> History:
    """The history's samples as the runner takes them; malformed ones, ones in another frame
    and "nothing measured" ones are skipped (they are not measurements of this loop)."""
    kinds = {qos.MEASUREMENT: 'measurement', qos.CONTROL: 'control', qos.ESTIMATE: 'state'}
    decoded = {topic: {} for topic in kinds}
    for topic, kind in kinds.items():
        for data in raw.get(topic, ()):
            try:
                if kind == 'measurement' and model is not None:
                    stamp_ns, value = read_measurement(model, data, sensor_frame_id)
                    if value is not None:
                        decoded[topic][stamp_ns] = value
                    continue
                record, value = read_input(kind, data, frame_id, axes)
            except MessageError:
                continue
            decoded[topic][record.stamp_ns] = (value, record.covariance) if kind == 'state' else value
    return History(decoded[qos.MEASUREMENT], decoded[qos.CONTROL], decoded[qos.ESTIMATE])
