"""Topic names, frames and QoS of the pipeline, defined once.

All pipeline topics are RELIABLE and TRANSIENT_LOCAL with a history of 1000: a node that starts
late (or a recorder) still receives what was published before it matched, which is how the
lockstep loop starts without a handshake; and a subscriber's DDS reader may fall up to 1000
samples behind before a sample could be overwritten unacknowledged.
"""

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

PIPELINE_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST, depth=1000,
    reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)

#: What the recorder subscribes with: KEEP_ALL, so its reader queue never overwrites a sample
#: its Python side has not written yet (it may lag behind the loop and catch up later).
RECORDER_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_ALL,
    reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)

#: /clock as rosgraph expects it (rclpy's time source subscribes best-effort, depth 1).
CLOCK_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST, depth=1,
    reliability=ReliabilityPolicy.BEST_EFFORT, durability=DurabilityPolicy.VOLATILE)

# Relative names, so namespaces and remapping work.
TRUTH = 'truth'
MEASUREMENT = 'measurement'
CONTROL = 'control'
ESTIMATE = 'estimate'
SPIKE_COUNT = 'spike_count'
SPIKES = 'spikes'
DIAGNOSTICS = 'diagnostics'
SET_STATE = 'set_state'  # estimator input: replace the estimate (nav_msgs/Odometry)
CLOCK = '/clock'

PIPELINE_TOPICS = (TRUTH, MEASUREMENT, CONTROL, ESTIMATE, SPIKE_COUNT, SPIKES, DIAGNOSTICS)

#: The target's local-vertical/local-horizontal frame (x V-bar, y -H, z R-bar toward Earth).
LVLH_FRAME = 'lvlh'
CHASER_FRAME = 'chaser'
