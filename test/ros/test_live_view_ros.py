"""The live_view node over ROS: the MarkerArray on `markers` carries the estimate and its
covariance as published; a Foxglove WebSocket client (the `websockets` library, subprotocol
foxglove.sdk.v1) connected during a short demo decodes scene, plot and raster messages whose
values are the run's recorded estimates, truths and spikes; and during a 60 s realtime run a
client we did not write (Foxglove's @foxglove/ws-protocol on Node, foxglove.websocket.v1) and
ours (foxglove.sdk.v1) decode every channel, on simulated time on the run's start."""

import hashlib
import json
import os
import re
import shutil
import subprocess
import time
from pathlib import Path

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
from snn_tools.live.client import FoxgloveClient, free_port, protobuf_class  # noqa: E402

SUBPROTOCOL = 'foxglove.sdk.v1'
JS_CLIENT = Path(__file__).resolve().parents[1] / 'js_client'


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


# ---------------------------------------------------------------- Foxglove clients during a demo
def epoch_of(record: dict) -> int:
    """The log times' epoch (ns) from a /plots record: its stamp on the epoch less its simulated time."""
    return record['timestamp']['sec'] * 10 ** 9 + record['timestamp']['nsec'] - round(record['time'] * 1e9)


def test_the_plant_waits_for_the_live_view_and_the_recorder_on_truth(tmp_path):
    """The recorder subscribes to 'truth' last (once it hears the loop); the live view
    subscribes at once. Counted only as sensor + recorder, the live view's subscription let the
    plant start before the recorder's and the bag lost the first 17 s of truth."""
    from snn_tools.paths import config_file
    from snn_tools.run.demo import Pipeline, pipeline_env
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
    from snn_tools.bags.data import read_bag
    from snn_tools.run.demo import run_pipeline
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
    epoch = epoch_of(json.loads(plots[0][1]))
    for log_time, payload in plots:
        record = json.loads(payload)
        stamp = record['timestamp']['sec'] * 10 ** 9 + record['timestamp']['nsec'] - epoch
        assert epoch_of(record) == epoch and stamp <= log_time - epoch  # logged with its frame, at or after it
        x_hat, variance = estimates[stamp]
        np.testing.assert_allclose([record['estimate'][s] for s in states], x_hat, rtol=0, atol=1e-12)
        np.testing.assert_allclose([record['error'][s] for s in states], x_hat - truths[stamp], rtol=0, atol=1e-12)
        np.testing.assert_allclose([record['three_sigma'][s] for s in states], 3 * np.sqrt(variance), rtol=1e-12)
        assert record['range_true'] == pytest.approx(np.linalg.norm(truths[stamp][:3]), rel=1e-12)
    stamps = [log_time for log_time, _ in plots]
    assert stamps == sorted(stamps) and len(set(stamps)) == len(stamps)

    SceneUpdate = protobuf_class(topics['/scene'])
    checked = 0
    for _, payload in client.messages['/scene']:
        entities = {e.id: e for e in SceneUpdate.FromString(payload).entities}
        stamp = entities['chaser_estimate'].timestamp.ToNanoseconds() - epoch if 'chaser_estimate' in entities else None
        if stamp not in estimates:
            continue
        x_hat, variance = estimates[stamp]
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


@pytest.fixture(scope='module')
def js_client() -> Path:
    """client.mjs beside its node_modules, installed once per package-lock.json with `npm ci` in
    the user's cache (never in the source tree); skipped without node and npm (a failure under CI,
    whose .ci/run installs them)."""
    node, npm = shutil.which('node'), shutil.which('npm')
    if node is None or npm is None:
        pytest.skip("node or npm is not installed (.ci/run installs Debian's nodejs and npm)")
    sources = [JS_CLIENT / name for name in ('package.json', 'package-lock.json')]
    key = hashlib.sha256(b''.join(path.read_bytes() for path in sources)).hexdigest()[:16]
    cache = Path(os.environ.get('XDG_CACHE_HOME') or Path.home() / '.cache') / 'snn_rendezvous' / f'js_client-{key}'
    if not (cache / 'node_modules' / '.package-lock.json').exists():
        building = cache.with_name(f'{cache.name}.{os.getpid()}')
        shutil.rmtree(building, ignore_errors=True)
        building.mkdir(parents=True)
        for path in sources:
            shutil.copy(path, building)
        subprocess.run([npm, 'ci', '--no-audit', '--no-fund', '--loglevel=error'], cwd=building, check=True,
                       timeout=300)
        shutil.rmtree(cache, ignore_errors=True)
        building.rename(cache)
    shutil.copy(JS_CLIENT / 'client.mjs', cache)
    return cache / 'client.mjs'


def layout_plot_paths() -> set[str]:
    """The /plots paths the layout's plots draw (series and x axis)."""
    from snn_tools.live.layout import LAYOUT_FILE
    return set(re.findall(r'"(/plots\.[\w.]+)"', LAYOUT_FILE.read_text()))


@pytest.mark.slow
def test_clients_of_both_subprotocols_decode_every_channel_on_simulated_time_in_a_60_s_realtime_run(
        tmp_path, js_client):
    """Foxglove's own client library (@foxglove/ws-protocol 0.8.0 on Node, its default subprotocol
    foxglove.websocket.v1) and ours (foxglove.sdk.v1) watch one live view through a 60 s realtime
    flight at 2x: both get the three channels and the same messages, decode every one with 0
    failures, and the log times never go backwards within a channel; they are simulated time on the
    run's start (60 s of them in ~30 s of wall-clock time), as is the server's clock."""
    pytest.importorskip('websockets')
    pytest.importorskip('foxglove')
    from snn_tools.run.demo import run_pipeline
    port = free_port()
    node = subprocess.Popen(['node', str(js_client), '--url', f'ws://127.0.0.1:{port}', '--seconds', '240'],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    ours = FoxgloveClient(port, seconds=240.0, subprotocol='foxglove.sdk.v1')
    ours.start()
    before_ns = time.time_ns()
    try:
        run_pipeline(tmp_path / 'run', mode='realtime', real_time_factor=2.0, duration=60.0, live_view=True,
                     extra={'live_view': {'port': port}})
        out, err = node.communicate(timeout=60)
    finally:
        node.kill()
    after_ns = time.time_ns()
    ours.join(30.0)
    assert node.returncode == 0, err
    summary = json.loads(out)
    # Foxglove's client, on the subprotocol it offers by default
    assert summary['subprotocol_offered'] == summary['subprotocol'] == 'foxglove.websocket.v1'
    assert summary['errors'] == [] and 'time' in summary['server']['capabilities']
    topics = summary['topics']
    assert set(topics) == {'/scene', '/plots', '/spike_raster'}
    for name, topic in topics.items():
        assert topic['decode_failures'] == 0, (name, topic['first_failure'])
        assert topic['log_time_backwards'] == 0, name
        assert topic['messages'] >= (20 if name == '/spike_raster' else 100), name
    assert {'target', 'keep_out', 'corridor', 'chaser_true', 'chaser_estimate', 'covariance', 'thrust',
            'trail_true', 'trail_estimate'} <= set(summary['scene']['entity_ids'])
    assert summary['scene']['frame_ids'] == ['lvlh']
    plots = summary['plots']
    assert layout_plot_paths() <= set(plots['paths']), layout_plot_paths() - set(plots['paths'])
    assert plots['time_backwards'] == 0 and plots['time_first'] < 5.0 and plots['time_last'] > 58.0
    assert plots['range_true_last'] < plots['range_true_first']
    assert summary['raster']['encodings'] == ['mono8'] and summary['raster']['bad_data_length'] == 0
    # the server's clock (what a viewer's timeline follows): never back
    assert summary['time']['backwards'] == 0 and summary['time']['messages'] >= 100

    # ours, on foxglove.sdk.v1: the same channels, every message decoded, the same bytes
    assert ours.error is None and ours.subprotocol == 'foxglove.sdk.v1'
    channels = {c['topic']: c for c in ours.channels.values()}
    assert {t: (c['encoding'], c['schemaName']) for t, c in channels.items()} == {
        t: (c['encoding'], c['schemaName']) for t, c in topics.items()}
    decoders = {'/scene': protobuf_class(channels['/scene']).FromString, '/plots': json.loads,
                '/spike_raster': protobuf_class(channels['/spike_raster']).FromString}
    for name, messages in ours.messages.items():
        log_times = [log_time for log_time, _ in messages]
        assert all(b >= a for a, b in zip(log_times, log_times[1:])), name
        for _, payload in messages:
            decoders[name](payload)  # raises on a message that does not decode
        digests = {str(t): hashlib.sha1(payload).hexdigest()[:16] for t, payload in messages}
        theirs = topics[name]['digests']
        common = digests.keys() & theirs.keys()
        assert len(common) >= 0.9 * min(len(digests), len(theirs)), name
        assert all(digests[t] == theirs[t] for t in common), name

    # log time = the run's start + simulated time: 60 simulated s in ~30 wall-clock s
    records = [json.loads(payload) for _, payload in ours.messages['/plots']]
    epoch = epoch_of(records[0])
    assert all(abs(epoch_of(r) - epoch) <= 1000 for r in records)  # one epoch (float s of `time`: < 1 us)
    assert before_ns - 1e9 <= epoch <= before_ns + 20e9  # the run's start, not 1970
    first, last = (int(topics['/scene'][key]) - epoch for key in ('first_log_time_ns', 'last_log_time_ns'))
    assert first < 5e9 and 59e9 < last <= 60.2e9 and after_ns > before_ns
    received = ours.received_at['/scene']
    assert (last - first) * 1e-9 > 1.5 * (received[1] - received[0])  # received in ~half that (2x)
