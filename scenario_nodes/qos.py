"""Topic names, frames and QoS of the pipeline, defined once.

Every pipeline topic is RELIABLE and TRANSIENT_LOCAL: a node that starts late still receives
what was published before it matched, which is how the lockstep loop starts without a handshake
and how a replacement estimator finds the sensor's history.

* publishers keep the last 5000 samples (8 minutes of the 0.1 s loop): a subscriber's DDS
  reader, e.g. a recorder that lags, may fall that far behind before an unacknowledged sample
  could be overwritten;
* subscribers of the loop keep 10 (at most two are ever outstanding in lockstep), the
  estimator's inputs 1000 (the history a replacement estimator starts from), the recorder all.
"""

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

# The topic names live in .topics (no rclpy there); re-exported here beside their QoS.
from .topics import (CLOCK, CONTROL, DIAGNOSTICS, ESTIMATE, MEASUREMENT, PIPELINE_TOPICS,  # noqa: F401
                     SET_STATE, SPIKE_COUNT, SPIKES, TRUTH)


def _latched(depth: int) -> QoSProfile:
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth,
                      reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)


PUBLISHER_QOS = _latched(5000)
SUBSCRIBER_QOS = _latched(10)
HISTORY_QOS = _latched(1000)
#: Kept for users' own nodes: a profile that matches both ends of the pipeline topics.
PIPELINE_QOS = SUBSCRIBER_QOS

#: What the recorder subscribes with: KEEP_ALL, so its reader queue never overwrites a sample
#: its Python side has not written yet (it may lag behind the loop and catch up later).
RECORDER_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_ALL,
    reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)

#: /clock as rosgraph expects it (rclpy's time source subscribes best-effort, depth 1).
CLOCK_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST, depth=1,
    reliability=ReliabilityPolicy.BEST_EFFORT, durability=DurabilityPolicy.VOLATILE)

#: The target's local-vertical/local-horizontal frame (x V-bar, y -H, z R-bar toward Earth).
LVLH_FRAME = 'lvlh'
CHASER_FRAME = 'chaser'
