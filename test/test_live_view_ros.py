"""The live_view node over ROS: the MarkerArray on `markers` carries the estimate and its
covariance as published; and a real Foxglove WebSocket client (the `websockets` library,
subprotocol foxglove.sdk.v1) connected during a short demo decodes scene, plot and raster
messages whose values are the run's recorded estimates, truths and spikes."""

import asyncio
import json
import socket
import struct
import threading
import time

import numpy as np
import pytest

rclpy = pytest.importorskip('rclpy')

from nav_msgs.msg import Odometry  # noqa: E402
from rclpy.qos import QoSProfile, ReliabilityPolicy  # noqa: E402
from ros_helpers import make, ros_context, spin_until  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402
from visualization_msgs.msg import MarkerArray  # noqa: E402

from scenario_nodes import qos  # noqa: E402
from scenario_nodes.codec import encode_accel, encode_odometry  # noqa: E402
from scenario_nodes.live_view_node import LiveViewNode  # noqa: E402
from snn_tools.live_client import protobuf_class  # noqa: E402

SUBPROTOCOL = 'foxglove.sdk.v1'


def covariance_of(radii, quaternion, sigma):
    rotation = Rotation.from_quat(quaternion).as_matrix()
    return rotation @ np.diag((np.asarray(radii) / sigma) ** 2) @ rotation.T


def test_markers_carry_the_estimate_and_its_covariance_ellipsoid():
    rng = np.random.default_rng(7)
    a = rng.standard_normal((3, 3))
    covariance = np.zeros((6, 6))
    covariance[:3, :3] = 1e-3 * (a @ a.T + 0.1 * np.eye(3))
    covariance[3:, 3:] = 1e-6 * np.eye(3)
    x_hat, truth, u = np.array([40.0, 12.0, -3.0, -1.0, -0.5, 0.1]), np.array([40.1, 12.0, -3.0, 0, 0, 0]), \
        np.array([2e-3, -1e-3, 5e-4])
    stamp = 1_300_000_000
    with ros_context() as (context, executor, nodes):
        make(LiveViewNode, context, executor, nodes, 'live_view', start=False, foxglove=False,
             thrust_scale=100.0, covariance_sigma=3.0, publish_rate=50.0)
        node = rclpy.create_node('feeder', context=context)
        nodes.append(node)
        executor.add_node(node)
        received = []
        node.create_subscription(MarkerArray, 'markers', received.append,
                                 QoSProfile(depth=5, reliability=ReliabilityPolicy.RELIABLE))
        truth_pub = node.create_publisher(Odometry, qos.TRUTH, qos.PUBLISHER_QOS)
        estimate_pub = node.create_publisher(Odometry, qos.ESTIMATE, qos.PUBLISHER_QOS)
        from geometry_msgs.msg import AccelStamped
        control_pub = node.create_publisher(AccelStamped, qos.CONTROL, qos.PUBLISHER_QOS)
        assert spin_until(executor, lambda: estimate_pub.get_subscription_count() and
                          truth_pub.get_subscription_count() and control_pub.get_subscription_count(), 10.0)
        truth_pub.publish(encode_odometry(truth, None, stamp, 'lvlh', 'chaser'))
        control_pub.publish(encode_accel(u, stamp, 'lvlh'))
        estimate_pub.publish(encode_odometry(x_hat, covariance, stamp, 'lvlh', 'chaser'))

        def complete():
            return received and {'covariance', 'thrust', 'chaser_true'} <= {m.ns for m in received[-1].markers}
        assert spin_until(executor, complete, 10.0)
    markers = {m.ns: m for m in received[-1].markers}
    assert all(m.header.frame_id == 'lvlh' and m.header.stamp.nanosec == 300_000_000 and m.header.stamp.sec == 1
               for m in markers.values())
    ellipsoid = markers['covariance']
    position = [ellipsoid.pose.position.x, ellipsoid.pose.position.y, ellipsoid.pose.position.z]
    np.testing.assert_allclose(position, x_hat[:3], rtol=0, atol=1e-12)
    q = ellipsoid.pose.orientation
    radii = 0.5 * np.array([ellipsoid.scale.x, ellipsoid.scale.y, ellipsoid.scale.z])  # scale: diameters
    np.testing.assert_allclose(covariance_of(radii, [q.x, q.y, q.z, q.w], 3.0), covariance[:3, :3], rtol=1e-9,
                               atol=1e-15)
    p = markers['chaser_estimate'].pose.position
    np.testing.assert_allclose([p.x, p.y, p.z], x_hat[:3], rtol=0, atol=1e-12)
    p = markers['chaser_true'].pose.position
    np.testing.assert_allclose([p.x, p.y, p.z], truth[:3], rtol=0, atol=1e-12)
    tail, head = markers['thrust'].points
    np.testing.assert_allclose([head.x - tail.x, head.y - tail.y, head.z - tail.z], 100.0 * u, rtol=1e-12)
    assert markers['corridor'].type == markers['corridor'].TRIANGLE_LIST and len(markers['corridor'].points) % 3 == 0


# ---------------------------------------------------------------- Foxglove client during a demo
def free_port() -> int:
    with socket.socket() as s:
        s.bind(('127.0.0.1', 0))
        return s.getsockname()[1]


class FoxgloveClient(threading.Thread):
    """Connects (retrying until the server is up), subscribes to every channel, keeps the
    decoded messages per topic until the server closes or ``seconds`` pass."""

    def __init__(self, port: int, seconds: float):
        super().__init__(daemon=True)
        self.port, self.seconds = port, seconds
        self.channels, self.messages, self.subprotocol, self.error = {}, {}, None, None

    def run(self):
        try:
            asyncio.run(self._run())
        except Exception as error:  # noqa: BLE001 - reported by the test
            self.error = error

    async def _run(self):
        import websockets
        deadline = time.monotonic() + self.seconds
        while True:
            try:
                ws = await websockets.connect(f'ws://127.0.0.1:{self.port}', subprotocols=[SUBPROTOCOL], max_size=None)
                break
            except OSError:
                if time.monotonic() > deadline:
                    raise
                await asyncio.sleep(0.05)
        self.subprotocol = ws.subprotocol
        async with ws:
            while time.monotonic() < deadline:
                try:
                    message = await asyncio.wait_for(ws.recv(), 0.5)
                except asyncio.TimeoutError:
                    continue
                except websockets.ConnectionClosed:
                    return
                if isinstance(message, str):
                    op = json.loads(message)
                    if op['op'] == 'advertise':
                        for channel in op['channels']:
                            self.channels[channel['id']] = channel
                        await ws.send(json.dumps({'op': 'subscribe', 'subscriptions': [
                            {'id': c['id'], 'channelId': c['id']} for c in op['channels']]}))
                    continue
                opcode, subscription, log_time = struct.unpack_from('<BIQ', message)
                assert opcode == 1  # message data
                topic = self.channels[subscription]['topic']
                self.messages.setdefault(topic, []).append((log_time, message[13:]))


def test_the_plant_waits_for_the_live_view_and_the_recorder_on_truth(tmp_path):
    """The recorder subscribes to 'truth' last (once it hears the loop); the live view
    subscribes at once. Counted only as sensor + recorder, the live view's subscription let the
    plant start before the recorder's and the bag lost the first 17 s of truth."""
    from snn_tools.demo import Pipeline, pipeline_env
    from snn_tools.paths import config_file
    for record, live_view, expected in ((True, True, 3), (True, False, 2), (False, True, 2)):
        overrides = {}
        Pipeline(tmp_path, config_file(), overrides, pipeline_env(), record=record, live_view=live_view)
        assert overrides['cw_plant']['min_truth_subscribers'] == expected, (record, live_view)
        # each sensor waits for its estimator, controller and recorder (test_nodes.py)
        assert overrides['position_sensor']['min_measurement_subscribers'] == 2 + record
        # and upstream: the controller's controls, then the estimator's estimates (decisions.md, 41)
        assert overrides['lqr_controller']['min_control_subscribers'] == 2 + record + live_view
        assert overrides['estimator']['min_estimate_subscribers'] == 1 + record + live_view


@pytest.mark.slow
def test_a_foxglove_client_receives_the_published_estimates_during_a_demo(tmp_path):
    pytest.importorskip('websockets')
    pytest.importorskip('foxglove')
    from snn_tools.bag_tools import read_bag
    from snn_tools.demo import run_pipeline
    port = free_port()
    client = FoxgloveClient(port, seconds=120.0)
    client.start()
    result = run_pipeline(tmp_path / 'run', mode='realtime', real_time_factor=10.0, duration=20.0, live_view=True,
                          extra={'live_view': {'port': port, 'publish_rate': 20.0}})
    assert result['scheduling'] == 'normal'  # realtime runs the normal policy by default (decision 39)
    client.join(30.0)
    assert client.error is None, client.error
    assert client.subprotocol == SUBPROTOCOL
    topics = {c['topic']: c for c in client.channels.values()}
    assert set(topics) == {'/scene', '/plots', '/spike_raster'}
    run = read_bag(tmp_path / 'run' / 'bag')
    estimates = {int(round(t * 1e9)): (x, v) for t, x, v in zip(run.estimate_t, run.estimate, run.estimate_variance)}
    truths = {int(round(t * 1e9)): x for t, x in zip(run.truth_t, run.truth)}
    states = ('x', 'y', 'z', 'vx', 'vy', 'vz')

    plots = client.messages['/plots']
    assert len(plots) >= 10  # 2 s of flight at up to 20 frames/s
    for log_time, payload in plots:
        record = json.loads(payload)
        stamp = record['timestamp']['sec'] * 10 ** 9 + record['timestamp']['nsec']
        assert stamp == log_time
        x_hat, variance = estimates[stamp]
        np.testing.assert_allclose([record['estimate'][s] for s in states], x_hat, rtol=0, atol=1e-12)
        np.testing.assert_allclose([record['error'][s] for s in states], x_hat - truths[stamp], rtol=0, atol=1e-12)
        np.testing.assert_allclose([record['three_sigma'][s] for s in states], 3 * np.sqrt(variance), rtol=1e-12)
        assert record['range_true'] == pytest.approx(np.linalg.norm(truths[stamp][:3]), rel=1e-12)
    stamps = [log_time for log_time, _ in plots]
    assert stamps == sorted(stamps) and len(set(stamps)) == len(stamps)

    SceneUpdate = protobuf_class(topics['/scene'])
    checked = 0
    for log_time, payload in client.messages['/scene']:
        entities = {e.id: e for e in SceneUpdate.FromString(payload).entities}
        if log_time not in estimates:
            continue
        x_hat, variance = estimates[log_time]
        pose = entities['chaser_estimate'].spheres[0].pose.position
        np.testing.assert_allclose([pose.x, pose.y, pose.z], x_hat[:3], rtol=0, atol=1e-12)
        sphere = entities['covariance'].spheres[0]
        q = sphere.pose.orientation
        covariance = covariance_of(0.5 * np.array([sphere.size.x, sphere.size.y, sphere.size.z]),
                                   [q.x, q.y, q.z, q.w], 3.0)
        np.testing.assert_allclose(np.diag(covariance), variance[:3], rtol=1e-8)
        assert entities['covariance'].frame_id == 'lvlh'
        checked += 1
    assert checked >= 10

    spikes = run.spikes > 0
    RawImage = protobuf_class(topics['/spike_raster'])
    rasters = [RawImage.FromString(payload) for _, payload in client.messages['/spike_raster']]
    assert rasters and all(r.encoding == 'mono8' and r.height == spikes.shape[1] for r in rasters)
    for raster in rasters[-3:]:  # the columns are consecutive steps of the recorded spikes
        image = np.frombuffer(raster.data, np.uint8).reshape(raster.height, raster.width) > 0
        width = image.shape[1]
        assert any((spikes[j - width:j].T == image).all() for j in range(width, len(spikes) + 1))
