"""The live view: the scene and plot values against independent computations (no ROS), the
MarkerArray a live_view node publishes against the estimate and covariance it was given, and
the Foxglove layout file in step with its generator."""

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from scenario_nodes.scene import (
    LiveScene,
    LogClock,
    SceneSettings,
    corridor_mesh,
    covariance_ellipsoid,
    nees,
    plot_record,
    quaternion_of,
    raster_image,
)


def random_covariance(rng, scale=1.0):
    a = rng.standard_normal((3, 3))
    return scale * (a @ a.T + 0.1 * np.eye(3))


def ellipsoid_covariance(radii, quaternion, sigma):
    """The covariance an ellipsoid stands for: R diag((r / sigma)^2) R^T (scipy's rotation)."""
    rotation = Rotation.from_quat(quaternion).as_matrix()
    return rotation @ np.diag((np.asarray(radii) / sigma) ** 2) @ rotation.T


def test_the_covariance_ellipsoid_reproduces_the_covariance_it_was_drawn_from():
    rng = np.random.default_rng(1)
    for _ in range(20):
        covariance = random_covariance(rng, 10.0 ** rng.uniform(-6, 1))
        sphere = covariance_ellipsoid('c', (1.0, 2.0, 3.0), covariance, 3.0, (1, 1, 1, 1))
        assert sphere.center == (1.0, 2.0, 3.0)
        np.testing.assert_allclose(ellipsoid_covariance(sphere.radii, sphere.orientation, 3.0), covariance,
                                   rtol=1e-9, atol=1e-12 * np.abs(covariance).max())


def test_quaternion_of_matches_scipy_for_random_rotations():
    for rotation in Rotation.random(50, random_state=3):
        q = np.array(quaternion_of(rotation.as_matrix()))
        expected = rotation.as_quat()
        assert min(np.abs(q - expected).max(), np.abs(q + expected).max()) < 1e-12


def test_nees_is_e_p_inverse_e_and_absent_for_a_covariance_that_is_not_positive_definite():
    rng = np.random.default_rng(2)
    p = np.zeros((6, 6))
    p[:3, :3], p[3:, 3:] = random_covariance(rng), random_covariance(rng, 1e-4)
    e = rng.standard_normal(6)
    assert nees(e, p) == pytest.approx(float(e @ np.linalg.inv(p) @ e), rel=1e-10)
    assert nees(e, np.zeros((6, 6))) is None
    assert nees(e, np.diag([1.0, 1, 1, 1, 1, -1])) is None


def test_every_corridor_vertex_lies_in_the_cone_and_its_rim_on_the_cone():
    axis, half_angle, length = np.array([70.0, 30.0, -5.0]), 15.0, 100.0
    points = corridor_mesh(axis, half_angle, length)
    unit = axis / np.linalg.norm(axis)
    along = points @ unit
    assert len(points) % 3 == 0 and along.min() >= -1e-9 and along.max() == pytest.approx(length)
    off_apex = np.linalg.norm(points, axis=1) > 1e-9
    angles = np.degrees(np.arccos(np.clip(along[off_apex] / np.linalg.norm(points[off_apex], axis=1), -1, 1)))
    assert angles.max() == pytest.approx(half_angle, abs=1e-9)  # the rim
    assert (angles <= half_angle + 1e-9).all()


def test_a_plot_sample_pairs_the_estimate_with_the_truth_of_its_own_stamp():
    rng = np.random.default_rng(4)
    scene = LiveScene(SceneSettings(covariance_sigma=3.0))
    truths = {k * 100_000_000: rng.standard_normal(6) for k in range(6)}
    covariance = np.zeros((6, 6))
    covariance[:3, :3], covariance[3:, 3:] = random_covariance(rng), random_covariance(rng, 1e-2)
    x_hat = rng.standard_normal(6)
    for stamp in list(truths)[:3]:
        scene.add_truth(stamp, truths[stamp])
    # the estimate for t = 0.4 s arrives before its truth: the plot waits for it
    scene.add_estimate(400_000_000, x_hat, covariance)
    scene.add_spikes(total=17, per_neuron=np.array([0, 2, 0, 1]))
    frame = scene.frame()
    assert frame.sample is None
    np.testing.assert_array_equal(frame.raster[:, -1], [0, 2, 0, 1])
    scene.add_truth(300_000_000, truths[300_000_000])
    scene.add_truth(400_000_000, truths[400_000_000])
    scene.add_truth(500_000_000, truths[500_000_000])  # newer than the estimate: not its pair
    sample = scene.frame().sample
    assert sample.stamp_ns == 400_000_000 and sample.spikes == 17
    np.testing.assert_allclose(sample.error, x_hat - truths[400_000_000], rtol=0, atol=1e-15)
    np.testing.assert_allclose(sample.three_sigma, 3 * np.sqrt(np.diag(covariance)), rtol=1e-15)
    assert sample.range_true == pytest.approx(np.linalg.norm(truths[400_000_000][:3]))
    assert sample.nees == pytest.approx(float(sample.error @ np.linalg.solve(covariance, sample.error)))
    assert scene.frame() is None  # nothing new: no frame
    scene.add_control(np.zeros(3))
    assert scene.frame().sample is None  # a new frame, but that sample was plotted already


def test_the_scene_draws_every_part_at_the_estimate_and_the_thrust_scaled():
    scene = LiveScene(SceneSettings(thrust_scale=500.0, keep_out_radius=3.0))
    x_hat, covariance = np.array([10.0, 5, -1, 0, 0, 0]), np.diag([4e-4, 1e-4, 9e-4, 1e-6, 1e-6, 1e-6])
    scene.add_truth(0, np.array([10.1, 5, -1, 0, 0, 0]))
    scene.add_estimate(0, x_hat, covariance)
    scene.add_control(np.array([1e-3, 0.0, -2e-3]))
    drawn = scene.frame().scene
    assert set(drawn.names()) == {'target', 'keep_out', 'corridor', 'chaser_true', 'chaser_estimate',
                                  'covariance', 'thrust'}
    assert drawn.get('chaser_estimate').center == (10.0, 5.0, -1.0)
    assert drawn.get('keep_out').radii == (3.0, 3.0, 3.0)
    np.testing.assert_allclose(drawn.get('thrust').end, x_hat[:3] + 500.0 * np.array([1e-3, 0, -2e-3]))
    assert sorted(drawn.get('covariance').radii) == pytest.approx(sorted(3 * np.sqrt([4e-4, 1e-4, 9e-4])))


def test_plot_values_are_finite_only_and_the_raster_is_binary():
    scene = LiveScene()
    covariance = np.eye(6)
    covariance[0, 0] = math.nan
    scene.add_truth(0, np.zeros(6))
    scene.add_estimate(0, np.ones(6), covariance)
    record = plot_record(scene.frame().sample)
    assert 'x' not in record['three_sigma'] and record['three_sigma']['y'] == 3.0
    assert 'nees' not in record and 'spikes' not in record
    np.testing.assert_array_equal(raster_image(np.array([[0, 3], [1, 0]])), [[0, 255], [255, 0]])


@pytest.mark.parametrize('field, value', [('covariance_sigma', 0.0), ('corridor_half_angle', 90.0),
                                          ('corridor_axis', (0.0, 0.0, 0.0)), ('trail_length', 1)])
def test_bad_scene_settings_are_refused_naming_the_parameter(field, value):
    with pytest.raises(ValueError, match=field):
        SceneSettings(**{field: value})


def test_the_foxglove_layout_file_is_what_its_generator_writes():
    pytest.importorskip('foxglove')
    from snn_tools.live.layout import LAYOUT_FILE, layout_json
    text = layout_json()
    assert LAYOUT_FILE.read_text() == text, 'stale: python -m snn_tools.live.layout --write'
    for path in ('/scene', '/plots.error.x', '/plots.three_sigma.vz', '/plots.nees', '/plots.spikes', '/spike_raster'):
        assert f'"{path}"' in text, path


def test_every_plot_of_the_layout_draws_against_the_messages_simulated_time():
    """x = /plots.time (simulated s) over all messages, not the receive time: the 360 s of the
    approach whatever the real-time factor."""
    pytest.importorskip('foxglove')
    import json

    from snn_tools.live.layout import LAYOUT_FILE

    def plots(node):
        if isinstance(node, dict):
            if 'paths' in node and 'xAxisVal' in node:
                yield node
            for value in node.values():
                yield from plots(value)
        elif isinstance(node, list):
            for value in node:
                yield from plots(value)
    configs = list(plots(json.loads(LAYOUT_FILE.read_text())))
    assert len(configs) == 9
    for config in configs:
        assert (config['xAxisVal'], config['xAxisPath'], config['timeRange']) == (
            'custom', {'value': '/plots.time', 'enabled': True}, 'all')


def test_the_foxglove_scene_update_carries_the_scene():
    pytest.importorskip('foxglove')
    from scenario_nodes.foxglove_view import arrow_pose, scene_update
    rng = np.random.default_rng(5)
    for _ in range(10):  # the arrow's rotation takes +x onto its direction
        start, end = rng.standard_normal(3), rng.standard_normal(3)
        _, q, length = arrow_pose(start, end)
        np.testing.assert_allclose(Rotation.from_quat(q).apply([length, 0, 0]), end - start, atol=1e-12)
    scene = LiveScene()
    scene.add_estimate(0, np.ones(6), np.eye(6))
    update = scene_update(scene.frame().scene)
    assert len(update.encode()) > 100  # encodes as protobuf (decoded field by field in test_live_view_ros)


def test_a_trail_keeps_the_newest_positions_oldest_first_and_at_most_its_points():
    from scenario_nodes.scene import TRAIL_POINTS, Trail
    trail = Trail(length=300)
    for k in range(1000):
        trail.append(np.array([k, 0.0, 0.0]))
    x = trail.points()[:, 0]
    assert len(x) == TRAIL_POINTS and x[0] == 700 and x[-1] == 999 and (np.diff(x) > 0).all()
    short = Trail(length=300)
    for k in range(5):
        short.append(np.array([k, 1.0, 2.0]))
    np.testing.assert_array_equal(short.points(), [[k, 1.0, 2.0] for k in range(5)])


@pytest.mark.parametrize('subprotocol', ['foxglove.sdk.v1', 'foxglove.websocket.v1'])
def test_a_client_that_does_not_read_loses_messages_and_never_blocks_the_view(subprotocol):
    """A client subscribes, then stops reading (its socket fills): every frame is still logged
    (a view that waited for the client would hang here) and the server drops the oldest messages
    instead of queueing 15 MB for it; through the gateway (foxglove.websocket.v1) too."""
    pytest.importorskip('foxglove')
    websockets = pytest.importorskip('websockets')
    import asyncio
    import json
    import threading
    import time

    from scenario_nodes.foxglove_view import FoxgloveView
    view = FoxgloveView(port=0, backlog=8)
    subscribed, release, received = threading.Event(), threading.Event(), []

    async def stalled_client():
        async with websockets.connect(f'ws://127.0.0.1:{view.port}', subprotocols=[subprotocol],
                                      max_size=None, max_queue=1) as ws:
            while True:
                op = json.loads(await ws.recv())
                if op['op'] == 'advertise':
                    break
            await ws.send(json.dumps({'op': 'subscribe', 'subscriptions': [
                {'id': c['id'], 'channelId': c['id']} for c in op['channels']]}))
            subscribed.set()
            while not release.is_set():  # not reading: the socket's buffers fill up
                await asyncio.sleep(0.05)
            while True:
                try:
                    message = await asyncio.wait_for(ws.recv(), 1.0)
                except (asyncio.TimeoutError, websockets.ConnectionClosed):
                    return
                if isinstance(message, bytes):
                    received.append(len(message))

    client = threading.Thread(target=lambda: asyncio.run(stalled_client()), daemon=True)
    client.start()
    try:
        assert subscribed.wait(10.0)
        time.sleep(0.3)  # the server has the subscription
        scene = LiveScene(raster_steps=400)
        rng = np.random.default_rng(0)
        frames, started = 1000, time.perf_counter()  # more bytes than loopback socket buffers hold
        for k in range(frames):
            scene.add_truth(k, rng.standard_normal(6))
            scene.add_estimate(k, rng.standard_normal(6), np.eye(6))
            scene.add_spikes(total=1, per_neuron=rng.integers(0, 2, 200))
            view.publish(scene.frame())
        publishing = time.perf_counter() - started  # all logged while the client read nothing
        release.set()
        client.join(20.0)
    finally:
        view.close()
    assert publishing < 60.0  # a view that waited for this client would never have finished
    assert 0 < len(received) < 3 * frames  # it got some, the server dropped the rest


def test_a_taken_port_is_refused_naming_the_parameter():
    pytest.importorskip('foxglove')
    from scenario_nodes.foxglove_view import FoxgloveView
    first = FoxgloveView(port=0)
    try:
        with pytest.raises(ValueError, match="choose another 'port'"):
            FoxgloveView(port=first.port)
    finally:
        first.close()


# ---------------------------------------------------------------- time
def test_a_frames_time_is_the_newest_stamp_heard_and_never_goes_back_while_its_plot_is_older():
    """The truth of an estimate's stamp arrives after the estimate, so the plot sample is a step
    behind the scene: each frame still has one time, the newest stamp heard (was: the plots
    logged at their sample's stamp, behind the scene's, and the log time stepped back)."""
    scene = LiveScene()
    rng = np.random.default_rng(8)
    times, plotted = [], []
    scene.add_truth(500_000_000, rng.standard_normal(6))  # truth before the first estimate
    for k in range(1, 40):
        stamp = k * 100_000_000
        scene.add_estimate(stamp, rng.standard_normal(6), np.eye(6))  # estimate of t_k first
        frame = scene.frame()
        times.append(frame.stamp_ns)
        if frame.sample is not None:
            plotted.append(frame.sample.stamp_ns)
            assert frame.sample.stamp_ns <= frame.stamp_ns
        scene.add_truth(stamp, rng.standard_normal(6))  # then its truth
    assert times == sorted(times) and times[-1] == 39 * 100_000_000
    assert times[0] == 500_000_000  # the scene's own stamp (the first estimate, 0.1 s) is older
    assert plotted == sorted(set(plotted)) and len(plotted) >= 33
    assert sum(p < t for p, t in zip(plotted, times[-len(plotted):])) >= 30  # a step behind the frame


def test_the_log_clock_puts_simulated_time_on_the_runs_start_or_a_given_epoch():
    wall = iter([1_800_000_000_000_000_000, 0])
    clock = LogClock(wall_ns=lambda: next(wall))
    assert clock(2_000_000_000) == 1_800_000_000_000_000_000  # first frame: now, at 2 s of the run
    assert clock.epoch_ns == 1_799_999_998_000_000_000 and clock(362_000_000_000) == clock.epoch_ns + 362 * 10 ** 9
    assert LogClock(1_700_000_000 * 10 ** 9)(5) == 1_700_000_000 * 10 ** 9 + 5
    with pytest.raises(ValueError, match='log_epoch'):
        LogClock(-1)


def test_the_raster_throttle_keeps_its_rate_at_any_frame_rate():
    from scenario_nodes.foxglove_view import Throttle
    now = [0.0]
    due = Throttle(5.0, clock=lambda: now[0])
    yeses = 0
    for k in range(2000):  # 100 s of frames at 20 Hz, jittered
        now[0] = 0.05 * k + 0.01 * math.sin(k)
        yeses += due()
    assert yeses == pytest.approx(500, abs=2)
    assert not Throttle(0.0)()
    with pytest.raises(ValueError, match='raster_rate'):
        Throttle(-1.0)


# ---------------------------------------------------------------- both subprotocols on one port
REQUEST = (b'GET / HTTP/1.1\r\nHost: localhost:8765\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n'
           b'Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 13\r\n%s\r\n')


def test_the_gateway_rewrites_the_handshake_of_a_client_offering_only_the_legacy_subprotocol():
    from scenario_nodes.foxglove_gateway import client_response, offered_subprotocols, upstream_request
    legacy = REQUEST % b'sec-websocket-protocol: foxglove.websocket.v1\r\n'
    upstream, answer = upstream_request(legacy)
    assert answer == 'foxglove.websocket.v1' and offered_subprotocols(upstream) == ['foxglove.sdk.v1']
    assert upstream.startswith(b'GET / HTTP/1.1\r\n') and upstream.endswith(b'\r\n\r\n')
    assert b'Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\n' in upstream  # the accept key stays valid
    # offering both (Lichtblick 1.22+), the SDK's only, or neither: passed unchanged
    for offer in (b'Sec-WebSocket-Protocol: foxglove.websocket.v1\r\nSec-WebSocket-Protocol: foxglove.sdk.v1\r\n',
                  b'Sec-WebSocket-Protocol: foxglove.sdk.v1\r\n', b'Sec-WebSocket-Protocol: other\r\n', b''):
        assert upstream_request(REQUEST % offer) == (REQUEST % offer, None)
    response = (b'HTTP/1.1 101 Switching Protocols\r\nconnection: Upgrade\r\nupgrade: websocket\r\n'
                b'sec-websocket-protocol: foxglove.sdk.v1\r\n'
                b'sec-websocket-accept: s3pPLMBiTxaQ9kYGzzhZRbK+xOo=\r\n\r\n')
    answered = client_response(response, answer)
    assert offered_subprotocols(answered) == ['foxglove.websocket.v1']
    assert b'sec-websocket-accept: s3pPLMBiTxaQ9kYGzzhZRbK+xOo=\r\n' in answered
    assert client_response(response, None) == response
    refused = b'HTTP/1.1 400 Bad Request\r\ncontent-length: 0\r\n\r\n'
    assert client_response(refused, answer) == refused


def test_clients_of_both_subprotocols_get_the_same_messages_on_one_port_and_others_are_refused():
    pytest.importorskip('foxglove')
    websockets = pytest.importorskip('websockets')
    import asyncio
    import time

    from scenario_nodes.foxglove_view import FoxgloveView
    from snn_tools.live.client import FoxgloveClient
    view = FoxgloveView(port=0, raster_rate=20.0)
    try:
        clients = [FoxgloveClient(view.port, seconds=30.0, subprotocol=p)
                   for p in ('foxglove.websocket.v1', 'foxglove.sdk.v1')]
        for client in clients:
            client.start()
        deadline = time.monotonic() + 10.0
        while not all(c.subscribed_at for c in clients) and time.monotonic() < deadline:
            time.sleep(0.05)
        time.sleep(0.3)  # the server has the subscriptions
        scene = LiveScene()
        rng = np.random.default_rng(9)
        for k in range(30):
            scene.add_truth(k * 100_000_000, rng.standard_normal(6))
            scene.add_estimate(k * 100_000_000, rng.standard_normal(6), np.eye(6))
            scene.add_spikes(total=3, per_neuron=rng.integers(0, 2, 20))
            view.publish(scene.frame())
            time.sleep(0.06)

        async def offer(subprotocol):
            async with websockets.connect(f'ws://127.0.0.1:{view.port}', subprotocols=[subprotocol]):
                pass
        with pytest.raises(websockets.InvalidStatus, match='400'):
            asyncio.run(offer('foxglove.websocket.v2'))
        time.sleep(0.3)
    finally:
        view.close()
    for client in clients:
        client.join(10.0)
    legacy, sdk = clients
    assert (legacy.error, sdk.error) == (None, None)
    assert (legacy.subprotocol, sdk.subprotocol) == ('foxglove.websocket.v1', 'foxglove.sdk.v1')
    assert sorted(c['topic'] for c in legacy.channels.values()) == ['/plots', '/scene', '/spike_raster']
    assert legacy.channels == sdk.channels
    for topic in ('/scene', '/plots', '/spike_raster'):
        assert len(legacy.messages[topic]) >= 25
        assert legacy.messages[topic] == sdk.messages[topic], topic  # byte for byte, same log times
