"""QoS of the pipeline, defined once, and the helpers every node creates its endpoints with.

* every publisher (truth, measurement, control, estimate, spike_count, spikes, diagnostics):
  reliable, volatile, keep last 5000. It matches any subscriber, a lagging recorder never
  loses a sample, and a late joiner gets the present (``ros2 topic echo --once`` adapts to
  the publisher's durability: with transient local it printed the oldest sample it was given).
* the history of the topics a joining estimator starts from, on ``<topic>/history``
  (measurement, control, estimate: keep last 200, 20 s; a joining estimator takes the newest
  estimate, the recorder backfills what it missed): reliable, transient local, published
  beside the topic (2 us a sample with nobody listening).
* every subscription of the loop: best effort, volatile, keep last 100 (the estimator's
  inputs 1000). It matches publishers with the default profile (``ros2 topic pub``,
  robot_localization), the sensor-data profile (drivers) and ours, as nav2 and
  robot_localization subscribe to sensors.
* the estimator's start-up history reader: reliable, transient local, keep last 1000: reads,
  once, what publishers that keep history still hold (scenario_nodes.history).
* the recorder: adapts to the publishers (reliable and transient local for ours), keep all.
* /clock: best effort, volatile, keep last 1, as rclpy's time source subscribes.

Every pipeline publisher and subscription accepts the standard QoS overrides, e.g.
``-p qos_overrides./measurement.subscription.reliability:=reliable`` (history, depth,
reliability, durability). An incompatible peer is counted (``qos_incompatible.<topic>`` in
the node's diagnostics) and logged once, naming the profile to use.
"""

from __future__ import annotations

from collections import Counter

from rclpy.duration import Duration
from rclpy.event_handler import PublisherEventCallbacks, SubscriptionEventCallbacks
from rclpy.qos import DurabilityPolicy, HistoryPolicy, LivelinessPolicy, QoSProfile, ReliabilityPolicy
from rclpy.qos_overriding_options import QoSOverridingOptions, QoSPolicyKind

# The topic names live in .topics (no rclpy there); re-exported here beside their QoS.
from .topics import (  # noqa: F401
    APPLIED_CONTROL,
    CLOCK,
    CONTROL,
    DIAGNOSTICS,
    ESTIMATE,
    GUIDANCE,
    MEASUREMENT,
    PIPELINE_TOPICS,
    SET_STATE,
    SPIKE_COUNT,
    SPIKES,
    TRUTH,
)


def _profile(reliability, durability, depth: int) -> QoSProfile:
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth, reliability=reliability,
                      durability=durability)


PUBLISHER_QOS = _profile(ReliabilityPolicy.RELIABLE, DurabilityPolicy.VOLATILE, 5000)
#: Samples each ``<topic>/history`` keeps for late joiners (a least-squares start fits 10 s).
HISTORY_DEPTHS = {'measurement': 200, 'control': 200, 'estimate': 200}
SUBSCRIPTION_QOS = _profile(ReliabilityPolicy.BEST_EFFORT, DurabilityPolicy.VOLATILE, 100)
#: The estimator's inputs: a deeper queue, so a burst (a replayed bag) is not cut.
INPUT_QOS = _profile(ReliabilityPolicy.BEST_EFFORT, DurabilityPolicy.VOLATILE, 1000)
HISTORY_QOS = _profile(ReliabilityPolicy.RELIABLE, DurabilityPolicy.TRANSIENT_LOCAL, 1000)

#: What the recorder subscribes with: KEEP_ALL, so its reader queue never overwrites a sample
#: its Python side has not written yet (it may lag behind the loop and catch up later).
RECORDER_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_ALL,
    reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE)
#: A reliable reader of the pipeline topics that keeps everything (tests, tools).
LISTENER_QOS = RECORDER_QOS

#: /clock as rosgraph expects it (rclpy's time source subscribes best-effort, depth 1).
CLOCK_QOS = _profile(ReliabilityPolicy.BEST_EFFORT, DurabilityPolicy.VOLATILE, 1)

#: The target's local-vertical/local-horizontal frame (x V-bar, y -H, z R-bar toward Earth).
LVLH_FRAME = 'lvlh'
CHASER_FRAME = 'chaser'

_OVERRIDABLE = (QoSPolicyKind.HISTORY, QoSPolicyKind.DEPTH, QoSPolicyKind.RELIABILITY,
                QoSPolicyKind.DURABILITY)


class QosEvents:
    """Counts incompatible-QoS events per topic and logs the first of each, naming the fix."""

    def __init__(self, node):
        self._node = node
        self.incompatible = Counter()

    def _on_incompatible(self, topic: str, side: str):
        def callback(event) -> None:
            first = topic not in self.incompatible
            self.incompatible[topic] += max(1, int(getattr(event, 'total_count_change', 1)))
            if first:
                policy = getattr(getattr(event, 'last_policy_kind', None), 'name', 'a policy')
                peer = 'publisher' if side == 'subscription' else 'subscription'
                self._node.get_logger().warning(
                    f"'{topic}': a {peer} with incompatible QoS ({policy}) cannot be matched. "
                    f'This {side} uses {describe(PUBLISHER_QOS if side == "publisher" else SUBSCRIPTION_QOS)}; '
                    'publish with the default or the sensor-data profile, or set '
                    f"qos_overrides./<ns>/{topic}.{side}.<policy> (README, 'Topics and QoS')")
        return callback

    def subscription_callbacks(self, topic: str) -> SubscriptionEventCallbacks:
        return SubscriptionEventCallbacks(incompatible_qos=self._on_incompatible(topic, 'subscription'))

    def publisher_callbacks(self, topic: str) -> PublisherEventCallbacks:
        return PublisherEventCallbacks(incompatible_qos=self._on_incompatible(topic, 'publisher'))

    def values(self) -> dict:
        values = {'qos_incompatible': sum(self.incompatible.values())}
        values.update({f'qos_incompatible.{topic}': n for topic, n in sorted(self.incompatible.items())})
        return values


def describe(profile: QoSProfile) -> str:
    return (f'{profile.reliability.name.lower()}, {profile.durability.name.lower()}, '
            f'{profile.history.name.lower()} {profile.depth}')


def history_topic(topic: str) -> str:
    """Where ``topic``'s recent samples are kept for late joiners."""
    return f'{topic}/history'


class HistoryPublisher:
    """A pipeline publisher and, beside it, the transient-local ``<topic>/history`` one:
    ``publish`` sends each sample on both."""

    def __init__(self, node, events: QosEvents, message_type, topic: str, profile: QoSProfile | None = None):
        self.topic = publisher(node, events, message_type, topic, profile=profile)
        # beside the topic as resolved, remappings included (a suite's sensor publishes
        # 'measurement' remapped to its own name: its history goes with it)
        self.history = node.create_publisher(
            message_type, history_topic(self.topic.topic_name),
            _profile(ReliabilityPolicy.RELIABLE, DurabilityPolicy.TRANSIENT_LOCAL, HISTORY_DEPTHS[topic]))

    def publish(self, data) -> None:
        self.topic.publish(data)
        self.history.publish(data)

    def get_subscription_count(self) -> int:
        return self.topic.get_subscription_count()

    def destroy(self, node) -> None:
        node.destroy_publisher(self.topic)
        node.destroy_publisher(self.history)


def with_liveliness(profile: QoSProfile, lease: float) -> QoSProfile:
    """``profile`` whose publisher asserts liveliness automatically within ``lease`` wall s:
    its subscribers learn within the lease that a killed or stopped process is gone (a
    subscription with the default profile requests an infinite lease: it matches)."""
    return QoSProfile(history=profile.history, depth=profile.depth, reliability=profile.reliability,
                      durability=profile.durability, liveliness=LivelinessPolicy.AUTOMATIC,
                      liveliness_lease_duration=Duration(nanoseconds=int(lease * 1e9)))


def publisher(node, events: QosEvents, message_type, topic: str, lifecycle: bool = False,
              profile: QoSProfile | None = None):
    """A pipeline publisher: PUBLISHER_QOS (or ``profile``), overridable, incompatibilities counted."""
    create = node.create_lifecycle_publisher if lifecycle else node.create_publisher
    return create(message_type, topic, profile or PUBLISHER_QOS, event_callbacks=events.publisher_callbacks(topic),
                  qos_overriding_options=QoSOverridingOptions(_OVERRIDABLE))


def subscription(node, events: QosEvents, message_type, topic: str, callback, profile: QoSProfile = None):
    """A pipeline subscription taking CDR bytes: best effort and volatile unless overridden,
    so any publisher matches it."""
    return node.create_subscription(
        message_type, topic, callback, profile or SUBSCRIPTION_QOS, raw=True,
        event_callbacks=events.subscription_callbacks(topic),
        qos_overriding_options=QoSOverridingOptions(_OVERRIDABLE))


def message_class(type_name: str):
    """'pkg/msg/Type' (as the graph names a topic's type) -> the Python message class."""
    import importlib
    package, _, name = type_name.split('/')
    return getattr(importlib.import_module(f'{package}.msg'), name)


class PublishedTypeSubscription:
    """A pipeline subscription to ``topic`` in the type its publishers use, for a node that
    reads only what every candidate type shares (the header): `measurement` is PointStamped,
    Vector3Stamped or sensor_msgs/Range by the sensor's model (docs/sensors.md), and one
    process (one DDS participant) cannot hold two types on one topic. Subscribes once the graph
    shows a publisher (checked every ``period`` wall s)."""

    def __init__(self, node, events: QosEvents, topic: str, callback, period: float = 0.1):
        from rclpy.clock import Clock, ClockType
        self._node, self._events, self._topic, self._callback = node, events, topic, callback
        self.subscription = None
        self.type_name = None
        self._timer = node.create_timer(period, self._look, clock=Clock(clock_type=ClockType.STEADY_TIME))

    def _look(self) -> None:
        publishers = self._node.get_publishers_info_by_topic(self._node.resolve_topic_name(self._topic))
        if not publishers:
            return
        self._timer.cancel()
        self.type_name = publishers[0].topic_type
        self.subscription = subscription(self._node, self._events, message_class(self.type_name), self._topic,
                                         self._callback)


def liveliness_monitor(node, message_type, topic: str, lease: float, on_change):
    """A subscription that only watches which publishers of ``topic`` are alive: it requests
    a liveliness lease of ``lease`` wall s (Fast DDS times a writer out on the reader's lease),
    so it matches only publishers that offer one at most that long (ours, see
    :func:`with_liveliness`), quietly; ``on_change(info)`` gets the live count. Within one
    process (one DDS participant) a writer counts as alive only while it publishes."""
    callbacks = SubscriptionEventCallbacks(incompatible_qos=lambda event: None, liveliness=on_change)
    return node.create_subscription(message_type, topic, lambda data: None,
                                    with_liveliness(SUBSCRIPTION_QOS, lease), raw=True, event_callbacks=callbacks)
