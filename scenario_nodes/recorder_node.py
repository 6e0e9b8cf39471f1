"""recorder: writes the pipeline's topics to a rosbag2 directory (MCAP or sqlite3) with rosbags.

The same format ``ros2 bag record`` writes (metadata version 9, CDR payloads as received, RIHS01
type hashes and message definitions from the Jazzy type store, offered QoS profiles), so
``ros2 bag info/play``, Foxglove and PlotJuggler open it. Receive timestamps come from the node
clock (simulated time with use_sim_time, like ``ros2 bag record --use-sim-time``) and never
go backwards. SIGINT/SIGTERM close the bag cleanly.

Samples published before the recorder's subscription matched their publisher (discovery on a
loaded machine can take longer than the plant's start_delay) are not lost: for the topics whose
publishers keep a ``<topic>/history`` (measurement, control, estimate: qos.HISTORY_DEPTHS; a suite's
sensor on the topic named after it, found in the graph: SENSOR_TYPES), the
recorder also reads that transient-local history and writes, under the topic itself, every
sample whose stamp it has not recorded yet (counted as ``backfilled``).

The unstamped topics (spike_count, spikes) cannot be repaired that way, so the recorder also
holds the plant's start: it subscribes to 'truth' only once every publisher of the other topics
it records has matched its subscription (and 'measurement', 'control', 'estimate' and
'spike_count', when recorded, each have one), or after ``match_wait`` s with a warning naming
what did not match. The plant starts on ``min_truth_subscribers`` matched 'truth' subscriptions
(the demo: 2 with the recorder), so it starts when the recorder hears the whole loop: a match the
plant cannot see (estimator <-> recorder, under load once 0.5 s late and 114 estimates lost).
"""

from __future__ import annotations

import struct
import time
from datetime import datetime
from pathlib import Path

from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, TypesysError, get_typestore

from . import qos
from .parameter_tables import RECORDER
from .qos import message_class
from .ros_parameters import declare
from .runtime import ProcessHooks, clock_ns, run_node

KNOWN_TYPES = {
    qos.TRUTH: 'nav_msgs/msg/Odometry',
    qos.MEASUREMENT: 'geometry_msgs/msg/PointStamped',
    qos.CONTROL: 'geometry_msgs/msg/AccelStamped',
    qos.ESTIMATE: 'nav_msgs/msg/Odometry',
    qos.SPIKE_COUNT: 'std_msgs/msg/UInt32',
    qos.SPIKES: 'std_msgs/msg/UInt32MultiArray',
    qos.DIAGNOSTICS: 'diagnostic_msgs/msg/DiagnosticArray',
    'clock': 'rosgraph_msgs/msg/Clock',
}

#: Topics whose type depends on the sensor (its measurement model: PointStamped, Vector3Stamped,
#: Range): taken from the graph, as for any other topic; the known type is the bag's connection
#: when no publisher ever showed up.
TYPE_FROM_GRAPH = frozenset({qos.MEASUREMENT})
#: The sensors' message types (scenario_nodes.conversions.MEASUREMENT_CLASSES): a topic found in
#: the graph with one of them is a sensor's (a suite's sensors publish on topics named after
#: them), whose ``<topic>/history`` the recorder reads as well.
SENSOR_TYPES = frozenset({'geometry_msgs/msg/PointStamped', 'sensor_msgs/msg/Range',
                          'geometry_msgs/msg/Vector3Stamped'})

_ZERO = QosTime(sec=0, nsec=0)
_STAMP = struct.Struct('<iI')  # header.stamp after the 4-byte CDR encapsulation header
#: Stamps remembered per backfilled topic (the newest; a history holds at most a few hundred).
SEEN_STAMPS = 5000
#: Wall s a history subscription stays after its first sample (its backlog arrives at once; later
#: samples are copies of live ones, which would double the recorder's work).
BACKFILL_WINDOW = 1.0
#: Topics of the loop the recorder waits to hear from before it subscribes to 'truth'.
LOOP_TOPICS = (qos.MEASUREMENT, qos.CONTROL, qos.ESTIMATE, qos.SPIKE_COUNT)


def header_stamp(raw: bytes) -> int | None:
    """The header stamp (ns) of a CDR message that starts with a std_msgs/Header; None if too short."""
    if len(raw) < 12:
        return None
    sec, nanosec = _STAMP.unpack_from(raw, 4)
    return sec * 1_000_000_000 + nanosec


def bag_qos(profile: QoSProfile) -> Qos:
    """rosbags' description of an rclpy QoS profile (for metadata.yaml)."""
    keep_all = profile.history == HistoryPolicy.KEEP_ALL
    return Qos(
        history=QosHistory.KEEP_ALL if keep_all else QosHistory.KEEP_LAST,
        depth=0 if keep_all else profile.depth,
        reliability=(QosReliability.RELIABLE if profile.reliability == ReliabilityPolicy.RELIABLE
                     else QosReliability.BEST_EFFORT),
        durability=(QosDurability.TRANSIENT_LOCAL if profile.durability == DurabilityPolicy.TRANSIENT_LOCAL
                    else QosDurability.VOLATILE),
        deadline=_ZERO, lifespan=_ZERO, liveliness=QosLiveliness.AUTOMATIC,
        liveliness_lease_duration=_ZERO, avoid_ros_namespace_conventions=False)


def adapted_qos(publishers) -> QoSProfile:
    """A subscription profile compatible with every publisher (as rosbag2 adapts)."""
    reliable = all(p.qos_profile.reliability == ReliabilityPolicy.RELIABLE for p in publishers)
    latched = all(p.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL for p in publishers)
    return QoSProfile(history=HistoryPolicy.KEEP_ALL,
                      reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE)


class RecorderNode(ProcessHooks, Node):
    """Subscribes with raw=True and hands the CDR bytes to a rosbags Writer."""

    def __init__(self, **kwargs):
        super().__init__('recorder', **kwargs)
        p = declare(self, RECORDER)
        output = p['output'] or f"bag_{datetime.now().strftime('%Y%m%d-%H%M%S')}"
        self.path = Path(output).expanduser().resolve()
        if self.path.exists():
            raise ValueError(f'output {self.path} exists already: choose a new bag directory')
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._typestore = get_typestore(Stores.ROS2_JAZZY)
        plugin = StoragePlugin.MCAP if p['storage'] == 'mcap' else StoragePlugin.SQLITE3
        self._writer = Writer(self.path, version=9, storage_plugin=plugin)
        self._writer.open()
        self._closed = False
        self._drain_timeout = p['drain_timeout']
        self._last_stamp = 0
        self.counts: dict[str, int] = {}
        self.backfilled: dict[str, int] = {}
        self._seen: dict[str, dict[int, None]] = {}  # backfilled topic -> recorded stamps (ordered)
        self.skipped: dict[str, str] = {}  # topic -> why it cannot be recorded
        self._waiting: dict[str, str] = {}  # fully qualified topic -> requested name
        self._live: dict[str, object] = {}  # recorded topic -> its live subscription
        self._held: tuple | None = None  # ('truth', subscribe) until the loop's publishers matched
        self._match_wait = p['match_wait']
        steady = Clock(clock_type=ClockType.STEADY_TIME)
        for topic in p['topics']:
            name = self.resolve_topic_name(topic)
            base = name.rsplit('/', 1)[-1]
            if base in TYPE_FROM_GRAPH:
                self._waiting[name] = topic
            elif topic in KNOWN_TYPES or base in KNOWN_TYPES:
                type_name = KNOWN_TYPES.get(topic, KNOWN_TYPES.get(base))
                if base == 'clock':
                    self._record(name, type_name, qos.CLOCK_QOS, qos.CLOCK_QOS)
                elif base == qos.TRUTH and self._match_wait > 0:  # in the bag now, subscribed later
                    self._record(name, type_name, qos.RECORDER_QOS, qos.PUBLISHER_QOS, hold=True)
                else:
                    self._record(name, type_name, qos.RECORDER_QOS, qos.PUBLISHER_QOS)
            else:
                self._waiting[name] = topic
        if self._waiting:
            self._discovery = self.create_timer(0.1, self._discover, clock=steady)
        if self._held:
            self._hold_started = time.monotonic()
            self._hold_timer = self.create_timer(0.02, self._release_truth, clock=steady)
        self.get_logger().info(f"recording {sorted(self.counts) + sorted(self._waiting)} to {self.path} "
                               f"({p['storage']})")

    def _record(self, topic: str, type_name: str, profile: QoSProfile, offered: QoSProfile,
                hold: bool = False, backfill: bool | None = None) -> bool:
        """Subscribe with ``profile`` (``hold``: later, :meth:`_release_truth`); metadata.yaml
        states ``offered`` (the publishers' QoS), which ``ros2 bag play`` republishes with. False,
        with an error logged, when the type cannot be recorded: the bag needs its definition
        from the typestore. ``backfill``: also read ``<topic>/history`` (default: for the
        pipeline topics that keep one, qos.HISTORY_DEPTHS)."""
        try:
            message_type = message_class(type_name)
        except (ImportError, AttributeError) as error:
            return self._skip(topic, type_name, f'no Python message class ({error})')
        try:
            connection = self._writer.add_connection(topic, type_name, typestore=self._typestore,
                                                     offered_qos_profiles=[bag_qos(offered)])
        except TypesysError as error:
            return self._skip(topic, type_name, f'not in the rosbags Jazzy typestore ({error})')
        self.counts[topic] = 0
        base = topic.rsplit('/', 1)[-1]
        if backfill is None:
            backfill = base in qos.HISTORY_DEPTHS
        seen = self._seen.setdefault(topic, {}) if backfill else None

        def on_message(raw: bytes, connection=connection, topic=topic) -> None:
            if seen is not None:
                self._remember(seen, header_stamp(raw))
            self._write(connection, topic, raw)

        def subscribe() -> None:
            self._live[topic] = self.create_subscription(message_type, topic, on_message, profile, raw=True)
            if seen is not None:
                self._backfill(topic, message_type, connection, seen)

        if hold:
            self._held = (topic, subscribe)
        else:
            subscribe()
        return True

    def unmatched(self) -> list[str]:
        """The recorded topics (but 'truth') not heard from yet: a publisher in the graph that
        has not matched this recorder's subscription, or no publisher at all on a loop topic."""
        missing = [f'{name} (not in the graph yet)' for name in self._waiting]
        for topic, subscription in self._live.items():
            publishers = len(self.get_publishers_info_by_topic(topic))
            if publishers and subscription.get_publisher_count() < publishers:
                missing.append(f'{topic} ({subscription.get_publisher_count()} of {publishers} publishers matched)')
            elif not publishers and topic.rsplit('/', 1)[-1] in LOOP_TOPICS:
                missing.append(f'{topic} (no publisher)')
        return missing

    def _release_truth(self) -> None:
        """Subscribe to 'truth' (the plant's start signal) once the loop is heard, or after match_wait."""
        missing = self.unmatched()
        waited = time.monotonic() - self._hold_started
        if missing and waited < self._match_wait:
            return
        self._hold_timer.cancel()
        if missing:
            self.get_logger().warning(f"recording '{self._held[0]}' after {waited:.1f} s although not every "
                                      f'publisher matched yet: {missing}; samples they publish before '
                                      'matching may be missing from the bag')
        else:
            self.get_logger().info(f"every publisher matched after {waited:.2f} s: recording '{self._held[0]}'")
        (_, subscribe), self._held = self._held, None
        subscribe()

    @property
    def recording_truth(self) -> bool:
        """True once 'truth' is subscribed (or was never asked for)."""
        return self._held is None

    def _backfill(self, topic: str, message_type, connection, seen: dict) -> None:
        """Read ``<topic>/history`` and write the samples the live subscription missed."""
        self.backfilled[topic] = 0
        reader = {}

        def on_history(raw: bytes) -> None:
            if 'closing' not in reader:  # the backlog comes at once: after it only copies of live samples
                steady = Clock(clock_type=ClockType.STEADY_TIME)
                reader['closing'] = self.create_timer(BACKFILL_WINDOW, lambda: close_history(), clock=steady)
            stamp = header_stamp(raw)
            if stamp is None or stamp in seen:
                return
            self._remember(seen, stamp)
            self._write(connection, topic, raw)
            self.backfilled[topic] += 1

        def close_history() -> None:
            reader['closing'].cancel()
            self.destroy_subscription(reader.pop('subscription'))

        reader['subscription'] = self.create_subscription(message_type, qos.history_topic(topic), on_history,
                                                          qos.HISTORY_QOS, raw=True)

    @staticmethod
    def _remember(seen: dict, stamp: int | None) -> None:
        if stamp is None:
            return
        seen[stamp] = None
        if len(seen) > SEEN_STAMPS:
            del seen[next(iter(seen))]

    def _skip(self, topic: str, type_name: str, reason: str) -> bool:
        """Leave ``topic`` out of the bag, saying why; the other topics are still recorded."""
        self.skipped[topic] = f'{type_name}: {reason}'
        self.get_logger().error(f'not recording {topic} ({type_name}): {reason}; recording the others')
        return False

    def _write(self, connection, topic: str, raw: bytes) -> None:
        if self._closed:
            return
        stamp = max(clock_ns(self), self._last_stamp)
        self._last_stamp = stamp
        self._writer.write(connection, stamp, raw)
        self.counts[topic] += 1

    def _discover(self) -> None:
        types = dict(self.get_topic_names_and_types())
        for name in list(self._waiting):
            if name in types:
                publishers = self.get_publishers_info_by_topic(name)
                profiles = ((adapted_qos(publishers), publishers[0].qos_profile) if publishers
                            else (qos.RECORDER_QOS, qos.PUBLISHER_QOS))
                del self._waiting[name]
                backfill = (name.rsplit('/', 1)[-1] in qos.HISTORY_DEPTHS or types[name][0] in SENSOR_TYPES
                            or qos.history_topic(name) in types)
                if self._record(name, types[name][0], *profiles, backfill=backfill):
                    self.get_logger().info(f'found {name} ({types[name][0]}): recording')
        if not self._waiting:
            self._discovery.cancel()

    def drain(self, executor, quiet: float = 0.5) -> None:
        """Keep writing until nothing arrived for ``quiet`` s (messages still queued when the
        stop came), at most ``drain_timeout`` s (the pipeline may still be running)."""
        limit = self._drain_timeout
        started = last_change = time.monotonic()
        total = sum(self.counts.values())
        while time.monotonic() - last_change < quiet and time.monotonic() - started < limit:
            executor.spin_once(timeout_sec=0.05)
            now_total = sum(self.counts.values())
            if now_total != total:
                total, last_change = now_total, time.monotonic()

    def close(self) -> None:
        """Close the bag (idempotent): writes the summary and metadata.yaml."""
        if self._closed:
            return
        self._closed = True
        started = time.monotonic()
        for name in self._waiting:  # never published: the bag still lists the pipeline's topics
            base = name.rsplit('/', 1)[-1]
            if base in TYPE_FROM_GRAPH:
                self._writer.add_connection(name, KNOWN_TYPES[base], typestore=self._typestore,
                                            offered_qos_profiles=[bag_qos(qos.PUBLISHER_QOS)])
                self.counts[name] = 0
        self._writer.close()
        total = sum(self.counts.values())
        backfilled = {topic: n for topic, n in sorted(self.backfilled.items()) if n}
        self.get_logger().info(f'closed {self.path}: {total} messages '
                               f'{dict(sorted(self.counts.items()))} ({time.monotonic() - started:.2f} s)'
                               + (f'; from the publishers\' history (published before this recorder matched '
                                  f'them): {backfilled}' if backfilled else ''))


def main(args=None) -> int:
    return run_node(RecorderNode, args, 'recorder')


if __name__ == '__main__':
    raise SystemExit(main())
