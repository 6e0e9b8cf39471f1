"""Recorder and report: the bag is a real rosbag2, complete, and survives SIGTERM; the report's
numbers are the bag's numbers."""

import json
import re
import signal
import time

import numpy as np
import pytest
import yaml

pytest.importorskip('rclpy')

from nav_msgs.msg import Goals, Odometry  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.serialization import deserialize_message  # noqa: E402
from ros_helpers import make, ros_context, spin_until  # noqa: E402
from rosbags.rosbag2 import Reader  # noqa: E402
from rosbags.typesys import Stores, get_typestore  # noqa: E402

from scenario_nodes import qos  # noqa: E402
from scenario_nodes.recorder_node import KNOWN_TYPES, RecorderNode, message_class  # noqa: E402
from scenario_nodes.runtime import run_node  # noqa: E402
from snn_tools.bags.data import read_bag, summarize  # noqa: E402
from snn_tools.bags.report import moving_rms, write_report  # noqa: E402
from snn_tools.paths import config_file  # noqa: E402
from snn_tools.run.demo import Pipeline, pipeline_env, run_pipeline  # noqa: E402

pytestmark = pytest.mark.slow
TOPICS = ('truth', 'measurement', 'control', 'estimate', 'spike_count', 'spikes', 'diagnostics')


@pytest.fixture(scope='module')
def recorded(tmp_path_factory):
    """A 60 s snn_ekf run (MCAP) and a 20 s run under a namespace with sqlite3 storage."""
    mcap = tmp_path_factory.mktemp('mcap_run')
    run_pipeline(mcap, estimator='snn_ekf', duration=60.0, timeout=180.0)
    sqlite = tmp_path_factory.mktemp('sqlite_run')
    run_pipeline(sqlite, estimator='emsif', duration=20.0, timeout=180.0, storage='sqlite3',
                 namespace='/chaser1')
    return mcap, sqlite


def test_bag_has_every_topic_with_its_type_hash_and_definition(recorded):
    mcap, _ = recorded
    typestore = get_typestore(Stores.ROS2_JAZZY)
    metadata = yaml.safe_load((mcap / 'bag' / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    assert metadata['storage_identifier'] == 'mcap' and metadata['version'] == 9
    hashes = {entry['topic_metadata']['name']: entry['topic_metadata']['type_description_hash']
              for entry in metadata['topics_with_message_count']}
    with Reader(mcap / 'bag') as reader:
        by_topic = {c.topic: c for c in reader.connections}
        assert set(by_topic) == {f'/{t}' for t in TOPICS}
        for topic in TOPICS:
            connection = by_topic[f'/{topic}']
            assert connection.msgtype == KNOWN_TYPES[topic]
            assert connection.digest == typestore.hash_rihs01(connection.msgtype)
            assert connection.msgdef.data  # the message definition is stored
            assert hashes[f'/{topic}'] == connection.digest
        # rclpy can deserialise what was recorded, and agrees with rosbags
        for connection, _, raw in reader.messages(connections=[by_topic['/estimate']]):
            with_rclpy = deserialize_message(raw, message_class(connection.msgtype))
            with_rosbags = typestore.deserialize_cdr(raw, connection.msgtype)
            assert with_rclpy.pose.pose.position.x == with_rosbags.pose.pose.position.x
            assert list(with_rclpy.pose.covariance) == list(with_rosbags.pose.covariance)
            break


def test_bag_holds_every_message_the_nodes_published_with_monotonic_stamps(recorded):
    for run in recorded:
        data = read_bag(run / 'bag')
        summary = summarize(data)
        for name, counts in summary['messages'].items():
            assert counts['recorded'] == counts['published'] > 0, (run, name, counts)
        # stamps never go back; a stamp twice is a lockstep resend, counted by its sender
        resent = {'truth': 'truth_resent', 'estimate': 'estimates_resent',
                  'measurement': 'measurements_resent', 'control': 'controls_resent'}
        senders = {'truth': 'cw_plant', 'estimate': 'estimator', 'measurement': 'position_sensor',
                   'control': 'lqr_controller'}
        for name, times in (('truth', data.truth_t), ('estimate', data.estimate_t),
                            ('measurement', data.measurement_t), ('control', data.control_t)):
            assert np.all(np.diff(times) >= 0), name
            repeats = int(np.sum(np.diff(times) == 0))
            assert repeats == int(data.last_diagnostics(senders[name]).get(resent[name], 0)), name
        for topic, receive in data.receive_times.items():
            assert np.all(np.diff(receive) >= 0), topic


def test_namespace_and_sqlite_storage(recorded):
    _, sqlite = recorded
    metadata = (sqlite / 'bag' / 'metadata.yaml').read_text()
    assert 'storage_identifier: sqlite3' in metadata
    data = read_bag(sqlite / 'bag')
    assert data.namespace == '/chaser1'
    assert '/chaser1/estimate' in data.counts and summarize(data)['steps'] == 200


def test_a_bag_cut_off_by_sigterm_mid_run_still_opens(tmp_path):
    run_dir = tmp_path / 'cut'
    run_dir.mkdir()
    pipeline = Pipeline(run_dir, config_file(), {
        'cw_plant': {'duration': 3600.0, 'mode': 'lockstep'},
        'recorder': {'output': str(run_dir / 'bag')}}, pipeline_env())
    pipeline.start()
    try:
        # mid-run: 3 s after the loop started (the estimator's first step; on a loaded machine
        # that can be seconds after the recorder opened the bag)
        estimator_log = run_dir / 'logs' / 'estimator.log'
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and 'started from' not in estimator_log.read_text():
            time.sleep(0.1)
        time.sleep(3.0)
        recorder = pipeline.processes['recorder']
        recorder.send_signal(signal.SIGTERM)
        assert recorder.wait(30) == 0
    finally:
        pipeline.stop_all()
    with Reader(run_dir / 'bag') as reader:
        counts = {c.topic: c.msgcount for c in reader.connections}
        assert counts['/truth'] > 10
        assert sum(1 for _ in reader.messages()) == sum(counts.values())


def test_a_topic_of_a_type_rosbags_does_not_know_is_skipped_and_the_others_recorded(tmp_path, capfd):
    # nav_msgs/Goals: importable in rclpy, missing from the rosbags Jazzy typestore
    with ros_context() as (context, executor, nodes):
        recorder = make(RecorderNode, context, executor, nodes, 'recorder', use_sim_time=False,
                        topics=['truth', 'goals'], output=str(tmp_path / 'bag'))
        talker = Node('talker', context=context)
        executor.add_node(talker)
        nodes.append(talker)
        truth = talker.create_publisher(Odometry, 'truth', qos.PUBLISHER_QOS)
        goals = talker.create_publisher(Goals, 'goals', 10)
        talker.create_timer(0.05, lambda: (truth.publish(Odometry()), goals.publish(Goals())))
        assert spin_until(executor, lambda: '/goals' in recorder.skipped and recorder.counts.get('/truth', 0) >= 3)
        recorder.close()
    assert 'nav_msgs/msg/Goals' in recorder.skipped['/goals']
    assert re.search(r'ERROR.*/goals.*nav_msgs/msg/Goals', capfd.readouterr().err)
    with Reader(tmp_path / 'bag') as reader:
        assert {c.topic: c.msgcount for c in reader.connections} == {'/truth': recorder.counts['/truth']}


def _publish_before_and_after_a_recorder(tmp_path, topic: str, cli_args=()):
    """40 points published on a sensor's history-keeping ``measurement`` before a recorder of
    ``topic`` exists (they must come from the history), then 20 live; returns the recorder
    and the name of the sensor's history topic."""
    from geometry_msgs.msg import PointStamped

    from scenario_nodes.codec import encode_point

    name = '/' + topic
    with ros_context() as (context, executor, nodes):
        talker = Node('sensor', context=context, cli_args=list(cli_args))
        executor.add_node(talker)
        nodes.append(talker)
        measurement = qos.HistoryPublisher(talker, qos.QosEvents(talker), PointStamped, qos.MEASUREMENT)
        history = measurement.history.topic_name
        step = 100_000_000
        for k in range(40):  # before any recorder exists
            measurement.publish(encode_point(np.array([70.0 - k, 30.0, -5.0]), (0, 1, 2), k * step, 'lvlh'))
        recorder = make(RecorderNode, context, executor, nodes, 'recorder', use_sim_time=False,
                        topics=[topic], output=str(tmp_path / 'bag'))
        assert spin_until(executor, lambda: recorder.backfilled.get(name) == 40)
        assert spin_until(executor, lambda: measurement.get_subscription_count() > 0)
        for k in range(40, 60):  # live
            measurement.publish(encode_point(np.array([70.0 - k, 30.0, -5.0]), (0, 1, 2), k * step, 'lvlh'))
        assert spin_until(executor, lambda: recorder.counts[name] >= 60)
        spin_until(executor, lambda: False, timeout=1.0)  # the history's copies of the live samples
        recorder.close()
    return recorder, history


def test_samples_published_before_the_recorder_matched_are_backfilled_from_the_history(tmp_path):
    """A sensor that publishes before the recorder's subscription matched it (discovery on a
    loaded machine took longer than the plant's start_delay: CI once lost the first 176
    measurements of a run): the recorder writes them from the sensor's transient-local
    ``measurement/history``, once each, and the series reads in stamp order."""
    recorder, _ = _publish_before_and_after_a_recorder(tmp_path, 'measurement')
    assert recorder.counts['/measurement'] == 60 and recorder.backfilled['/measurement'] == 40
    data = read_bag(tmp_path / 'bag')
    assert np.allclose(data.measurement_t, 0.1 * np.arange(60)) and data.repeats.get('measurement', 0) == 0
    np.testing.assert_allclose(data.measurement[:, 0], 70.0 - np.arange(60))


def test_a_suite_sensor_on_its_own_topic_keeps_its_history_beside_it_and_is_backfilled(tmp_path):
    """A suite's sensor publishes 'measurement' remapped to its name ('lidar'): its history goes
    with the remap (/lidar/history; it went to /measurement/history, shared by both sensors of a
    fused run, so the recorder had nothing to backfill a sensor from), and the recorder, finding
    the topic in the graph, writes what it published before the match from there."""
    recorder, history = _publish_before_and_after_a_recorder(
        tmp_path, 'lidar', cli_args=['--ros-args', '-r', 'measurement:=lidar'])
    assert history == '/lidar/history'
    assert recorder.counts['/lidar'] == 60 and recorder.backfilled['/lidar'] == 40


def _truth_subscribers(node) -> set:
    return {info.node_name for info in node.get_subscriptions_info_by_topic('/truth')}


def test_the_recorder_subscribes_to_truth_only_once_the_loop_publishers_matched_it(tmp_path, capfd):
    """The plant starts on matched 'truth' subscriptions; the recorder subscribes to 'truth' only
    once it hears the estimator (CI once lost 114 estimates and their spike counts: the
    estimator matched the recorder 0.5 s after the plant had started), and, when a loop topic
    has no publisher, after match_wait with a warning naming it."""
    with ros_context() as (context, executor, nodes):
        recorder = make(RecorderNode, context, executor, nodes, 'recorder', use_sim_time=False,
                        topics=['truth', 'estimate'], output=str(tmp_path / 'bag'), match_wait=60.0)
        talker = Node('estimator', context=context)
        executor.add_node(talker)
        nodes.append(talker)
        spin_until(executor, lambda: False, timeout=1.0)
        assert not recorder.recording_truth and 'recorder' not in _truth_subscribers(talker)
        assert recorder.unmatched() == ['/estimate (no publisher)']
        estimate = talker.create_publisher(Odometry, 'estimate', qos.PUBLISHER_QOS)
        assert spin_until(executor, lambda: recorder.recording_truth)
        assert estimate.get_subscription_count() == 1 and recorder.unmatched() == []
        assert spin_until(executor, lambda: 'recorder' in _truth_subscribers(talker))
        recorder.close()

        alone = make(RecorderNode, context, executor, nodes, 'alone', use_sim_time=False,
                     topics=['truth', 'spike_count'], output=str(tmp_path / 'alone'), match_wait=0.5)
        assert spin_until(executor, lambda: alone.recording_truth, timeout=10.0)
        alone.close()
    assert re.search(r"WARN.*after 0\.\d s although not every publisher matched.*/spike_count \(no publisher\)",
                     capfd.readouterr().err)


class _DrainFails(RecorderNode):
    done = True  # run_node stops at once and goes on to drain

    def drain(self, executor, quiet: float = 0.5) -> None:
        raise RuntimeError('drain failed')


def test_the_bag_is_closed_even_when_draining_fails_and_the_error_is_raised(tmp_path):
    handlers = signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)
    try:
        with pytest.raises(RuntimeError, match='drain failed'):
            run_node(_DrainFails, ['recorder', '--ros-args', '-p', f'output:={tmp_path / "bag"}'])
    finally:
        signal.signal(signal.SIGINT, handlers[0])
        signal.signal(signal.SIGTERM, handlers[1])
    assert (tmp_path / 'bag' / 'metadata.yaml').exists()
    with Reader(tmp_path / 'bag') as reader:
        assert {c.topic for c in reader.connections} == {f'/{t}' for t in TOPICS}


def test_report_figures_exist_and_its_numbers_are_the_bags(recorded, tmp_path):
    mcap, sqlite = recorded
    report = write_report([mcap], tmp_path / 'single')
    for name in ('states_and_errors.png', 'rmse.png', 'spikes.png', 'control.png'):
        assert (tmp_path / 'single' / name).stat().st_size > 10_000, name
    # independent computation straight from the bag with rosbags
    typestore = get_typestore(Stores.ROS2_JAZZY)
    truth, estimate, spikes = {}, {}, 0
    with Reader(mcap / 'bag') as reader:
        for connection, _, raw in reader.messages():
            msg = typestore.deserialize_cdr(raw, connection.msgtype)
            if connection.topic in ('/truth', '/estimate'):
                stamp = msg.header.stamp.sec * 10 ** 9 + msg.header.stamp.nanosec
                p, v = msg.pose.pose.position, msg.twist.twist.linear
                (truth if connection.topic == '/truth' else estimate)[stamp] = [p.x, p.y, p.z, v.x, v.y, v.z]
            elif connection.topic == '/spike_count':
                spikes += msg.data
    common = sorted(set(truth) & set(estimate))
    errors = np.array([np.subtract(truth[t], estimate[t]) for t in common])
    window = np.array(common) >= common[-1] - 60 * 10 ** 9 + 1
    rmse = np.sqrt(np.mean(errors[window] ** 2, axis=0))
    final_range = np.linalg.norm(truth[max(truth)][:3])
    text = report.read_text()
    row = next(line for line in text.splitlines() if line.startswith('| SNN-EKF'))
    numbers = [float(x) for x in re.findall(r'-?\d+\.\d+e[-+]\d+|-?\d+\.\d+', row)]
    assert f'{final_range:.4f}' in row
    assert f'{rmse[0]:.3e}, {rmse[1]:.3e}, {rmse[2]:.3e}' in row
    assert f'{rmse[3]:.3e}, {rmse[4]:.3e}, {rmse[5]:.3e}' in row
    assert f'| {spikes} |' in row and numbers
    summary = json.loads((tmp_path / 'single' / 'report_summary.json').read_text())
    assert summary['SNN-EKF']['spikes_total'] == spikes
    # two runs overlay in the same figures
    write_report([mcap, sqlite], tmp_path / 'both')
    assert 'EMSIF' in (tmp_path / 'both' / 'report.md').read_text()
    assert (tmp_path / 'both' / 'states_and_errors.png').exists()


def test_moving_rms_is_the_rms_of_the_preceding_window():
    times = np.arange(0.0, 10.0, 0.1)
    errors = np.column_stack([np.sin(times), np.ones_like(times)])
    rms = moving_rms(times, errors, 2.0)
    k = 50
    window = (times > times[k] - 2.0 + 1e-9) & (times <= times[k])
    np.testing.assert_allclose(rms[k], np.sqrt(np.mean(errors[window] ** 2, axis=0)))
    np.testing.assert_allclose(rms[:, 1], 1.0)
