"""live_view: the loop as it flies, in Foxglove (WebSocket, ws://localhost:8765) and RViz (`markers`).

Subscribes to truth, estimate, control, spike_count and spikes (best effort, shallow queues:
it never holds the loop back), keeps only the newest messages as received bytes, and at most
``publish_rate`` times per wall-clock second decodes them into a
:class:`scenario_nodes.scene.LiveScene` frame and sends it: to Foxglove clients of either
subprotocol through :class:`scenario_nodes.foxglove_view.FoxgloveView` (log times: simulated
time on the run's start, ``log_epoch``; the raster at most ``raster_rate`` a second), and as a
MarkerArray on ``markers`` (:mod:`scenario_nodes.scene_markers`). Inputs between two frames are coalesced; a client that
does not keep up loses its oldest queued messages (foxglove-sdk), and the marker publisher keeps
only the last frame: nothing here blocks.
"""

from __future__ import annotations

from collections import deque

from geometry_msgs.msg import AccelStamped
from nav_msgs.msg import Odometry
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import UInt32, UInt32MultiArray
from visualization_msgs.msg import MarkerArray

from . import qos
from .codec import MessageError, decode_accel, decode_odometry, decode_spikes, decode_uint32, state_of
from .parameter_tables import LIVE_VIEW
from .ros_parameters import declare
from .runtime import ProcessHooks, run_node
from .scene import LiveScene, SceneSettings
from .scene_markers import marker_array
from .topics import MARKERS

#: What the live view subscribes with: best effort and shallow (it matches every publisher and
#: takes nothing from the loop; older samples are overwritten, never waited for).
VIEW_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10, reliability=ReliabilityPolicy.BEST_EFFORT,
                      durability=DurabilityPolicy.VOLATILE)
#: The markers: reliable (RViz's default subscription matches), the newest frame only.
MARKER_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1, reliability=ReliabilityPolicy.RELIABLE,
                        durability=DurabilityPolicy.VOLATILE)


def scene_settings(p: dict) -> SceneSettings:
    """The scene's settings from the node's parameter values (ValueError names a bad one)."""
    return SceneSettings(
        covariance_sigma=p['covariance_sigma'], keep_out_radius=p['keep_out_radius'],
        corridor_axis=tuple(p['corridor_axis']), corridor_half_angle=p['corridor_half_angle'],
        corridor_length=p['corridor_length'], thrust_scale=p['thrust_scale'], trail_length=p['trail_length'])


class LiveViewNode(ProcessHooks, Node):
    """Receives the loop's topics as bytes, draws frames on a wall-clock timer."""

    def __init__(self, **kwargs):
        super().__init__('live_view', **kwargs)
        p = declare(self, LIVE_VIEW)
        self._scene = LiveScene(scene_settings(p), p['frame_id'], raster_steps=p['raster_steps'])
        self._truths = deque(maxlen=64)
        self._spikes = deque(maxlen=p['raster_steps'])
        self._newest = {}  # topic -> bytes of its newest message
        self.decoded = 0
        self.rejected = 0
        self._view = None
        if p['foxglove']:
            from .foxglove_view import FoxgloveView
            self._view = FoxgloveView(p['host'], p['port'], p['message_backlog'], legacy=p['legacy_subprotocol'],
                                      epoch_ns=round(p['log_epoch'] * 1e9) or None, raster_rate=p['raster_rate'])
        self._markers = self.create_publisher(MarkerArray, MARKERS, MARKER_QOS) if p['markers'] else None
        self.create_subscription(Odometry, qos.TRUTH, lambda data: self._truths.append(data), VIEW_QOS, raw=True)
        self.create_subscription(UInt32MultiArray, qos.SPIKES, lambda data: self._spikes.append(data), VIEW_QOS,
                                 raw=True)
        for message_type, topic in ((Odometry, qos.ESTIMATE), (AccelStamped, qos.CONTROL), (UInt32, qos.SPIKE_COUNT)):
            self.create_subscription(message_type, topic, self._keeper(topic), VIEW_QOS, raw=True)
        self.create_timer(1.0 / p['publish_rate'], self._on_frame, clock=Clock(clock_type=ClockType.STEADY_TIME))
        where = (f"Foxglove: open {self._view.url} (foxglove.sdk.v1"
                 f"{' and foxglove.websocket.v1' if p['legacy_subprotocol'] else ' only'})"
                 if self._view else 'Foxglove server off')
        self.get_logger().info(f"live view at {p['publish_rate']:g} Hz; {where}"
                               f"{'; MarkerArray on ' + self.resolve_topic_name(MARKERS) if self._markers else ''}")

    def _keeper(self, topic: str):
        def keep(data: bytes) -> None:
            self._newest[topic] = data
        return keep

    def _feed(self) -> None:
        """Decode what arrived since the last frame into the scene (bad messages counted)."""
        scene = self._scene
        while self._truths:
            self._decode(lambda r: scene.add_truth(r.stamp_ns, state_of(r)), decode_odometry, self._truths.popleft())
        newest = self._newest
        self._newest = {}
        if qos.ESTIMATE in newest:
            self._decode(lambda r: scene.add_estimate(r.stamp_ns, state_of(r), r.covariance), decode_odometry,
                         newest[qos.ESTIMATE])
        if qos.CONTROL in newest:
            self._decode(lambda r: scene.add_control(r.vector), decode_accel, newest[qos.CONTROL])
        if qos.SPIKE_COUNT in newest:
            self._decode(lambda n: scene.add_spikes(total=n), decode_uint32, newest[qos.SPIKE_COUNT])
        while self._spikes:
            self._decode(lambda counts: scene.add_spikes(per_neuron=counts), decode_spikes, self._spikes.popleft())

    def _decode(self, use, decode, data: bytes) -> None:
        try:
            use(decode(data))
            self.decoded += 1
        except MessageError as error:
            self.rejected += 1
            self.get_logger().warning(f'live view: message not drawn ({error})', throttle_duration_sec=5.0)

    def _on_frame(self) -> None:
        self._feed()
        markers = self._markers is not None and self._markers.get_subscription_count() > 0
        if not markers and not (self._view is not None and self._view.watched):
            return  # nobody looks: the scene is kept up to date, no frame is built
        frame = self._scene.frame()
        if frame is None:
            return
        if self._view is not None:
            self._view.publish(frame)
        if markers and frame.scene is not None:
            self._markers.publish(marker_array(frame.scene))

    def close(self) -> None:
        self.get_logger().info(f'live view: {self._scene.frames} frames from {self.decoded} decoded messages '
                               f'({self.rejected} rejected)')
        if self._view is not None:
            self._view.close()


def main(args=None) -> int:
    return run_node(LiveViewNode, args, 'live_view')


if __name__ == '__main__':
    raise SystemExit(main())
