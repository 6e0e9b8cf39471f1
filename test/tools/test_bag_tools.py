"""bag_tools on small bags written here with rosbags: bags the pipeline can produce besides the
demo's (a hot swap, publish_spikes false, ``ros2 bag record -a`` with custom types)."""

from pathlib import Path

import numpy as np
import pytest

pytest.importorskip('rclpy')

from rclpy.serialization import serialize_message  # noqa: E402
from rosbags.rosbag2 import Writer  # noqa: E402
from rosbags.typesys import Stores, get_types_from_msg, get_typestore  # noqa: E402

from scenario_nodes.codec import encode_odometry, encode_spikes, encode_uint32  # noqa: E402
from scenario_nodes.diagnostics import diagnostic_array  # noqa: E402
from scenario_nodes.recorder_node import KNOWN_TYPES  # noqa: E402
from snn_tools.bags.data import read_bag, summarize  # noqa: E402
from snn_tools.bags.report import default_output, write_report  # noqa: E402

NS = 1_000_000_000
STEP_NS = NS // 10


def write_bag(path, messages, typestore=None):
    """A rosbag2 (MCAP) of ``messages``: (topic, type, CDR bytes) received one step apart."""
    typestore = typestore or get_typestore(Stores.ROS2_JAZZY)
    connections = {}
    with Writer(path, version=9) as writer:
        for k, (topic, msgtype, raw) in enumerate(messages):
            if topic not in connections:
                connections[topic] = writer.add_connection(topic, msgtype, typestore=typestore)
            writer.write(connections[topic], (k + 1) * STEP_NS, raw)
    return path


def steps(count, spikes=None):
    """``count`` estimator steps: truth, estimate, spike_count and, if given, spikes[k]."""
    messages = []
    for k in range(count):
        x = np.arange(6.0) + k
        messages.append(('/truth', KNOWN_TYPES['truth'], encode_odometry(x, None, k * STEP_NS, 'lvlh', 'chaser')))
        messages.append(('/estimate', KNOWN_TYPES['estimate'],
                         encode_odometry(x + 0.5, np.eye(6), k * STEP_NS, 'lvlh', 'chaser')))
        messages.append(('/spike_count', KNOWN_TYPES['spike_count'], encode_uint32(0)))
        if spikes is not None:
            messages.append(('/spikes', KNOWN_TYPES['spikes'], encode_spikes(spikes[k])))
    return messages


def diagnostics(name, **values):
    return ('/diagnostics', KNOWN_TYPES['diagnostics'],
            serialize_message(diagnostic_array(10 * NS, name, name, values)))


def test_spike_arrays_of_different_lengths_are_padded_with_zeros_and_reported(tmp_path):
    # snn_ekf with 3 neurons, hot swap to emsif (empty arrays), then a 5-neuron network
    spikes = [[1, 0, 2], [], [0, 3, 0, 0, 1]]
    bag = write_bag(tmp_path / 'bag', steps(3, spikes))
    run = read_bag(bag)
    np.testing.assert_array_equal(run.spikes, [[1, 0, 2, 0, 0], [0, 0, 0, 0, 0], [0, 3, 0, 0, 1]])
    write_report([bag], tmp_path / 'report')
    assert (tmp_path / 'report' / 'spikes.png').stat().st_size > 10_000


def test_a_resent_sample_is_on_record_once_per_stamp_and_counted(tmp_path):
    # a lockstep plant resends x0 while the loop warms up, the estimator resends its answer
    messages = steps(3)
    resent = messages[:2] * 3  # truth and estimate of step 0, twice more
    bag = write_bag(tmp_path / 'bag', messages[:3] + resent[2:] + messages[3:])
    run = read_bag(bag)
    assert run.counts['/truth'] == 5 and run.truth.shape == (3, 6)
    np.testing.assert_array_equal(run.truth_t, [0.0, 0.1, 0.2])
    np.testing.assert_array_equal(run.estimate[:, 0], [0.5, 1.5, 2.5])
    assert run.repeats == {'truth': 2, 'estimate': 2, 'measurement': 0, 'control': 0}


def test_the_report_goes_beside_a_bare_bag_into_a_run_folder_and_to_report_for_several(tmp_path):
    bare = tmp_path / 'flights' / 'my_bag'
    (bare).mkdir(parents=True)
    run = tmp_path / 'runs' / 'demo'
    (run / 'bag').mkdir(parents=True)
    assert default_output([bare]) == tmp_path / 'flights' / 'my_bag_report'  # never inside the bag
    assert default_output([run]) == run
    assert default_output([bare, run]) == Path('report')


def test_a_topic_of_a_type_the_typestore_does_not_know_is_counted_not_decoded(tmp_path):
    # e.g. `ros2 bag record -a` with a user's own message on the graph
    typestore = get_typestore(Stores.ROS2_JAZZY)
    typestore.register(get_types_from_msg('float64 value\n', 'my_msgs/msg/Thing'))
    thing = typestore.serialize_cdr(typestore.types['my_msgs/msg/Thing'](value=1.0), 'my_msgs/msg/Thing')
    messages = steps(2)
    messages.insert(1, ('/thing', 'my_msgs/msg/Thing', thing))
    run = read_bag(write_bag(tmp_path / 'bag', messages, typestore))
    assert run.counts['/thing'] == 1 and run.types['/thing'] == 'my_msgs/msg/Thing'
    np.testing.assert_array_equal(run.truth, [np.arange(6.0), np.arange(6.0) + 1])
    np.testing.assert_array_equal(run.estimate_t, [0.0, 0.1])
    only_others = read_bag(write_bag(tmp_path / 'others', [messages[1]], typestore))
    assert only_others.counts == {'/thing': 1} and only_others.truth.size == 0


@pytest.mark.parametrize('spikes_published, spikes_recorded', [
    (0, 0),     # publish_spikes false: the estimator reports that it published none
    (None, 3),  # an estimator without the spikes_published key: one array per estimate
])
def test_spikes_expected_are_the_ones_the_estimator_published(tmp_path, spikes_published, spikes_recorded):
    estimator = {'filter': 'snn_ekf', 'estimates_published': 3}
    if spikes_published is not None:
        estimator['spikes_published'] = spikes_published
    messages = steps(3, [[1, 0]] * 3 if spikes_recorded else None)
    messages += [diagnostics('cw_plant', truth_published=3), diagnostics('estimator', **estimator)]
    summary = summarize(read_bag(write_bag(tmp_path / 'bag', messages)))
    assert summary['messages']['spikes'] == {'published': spikes_recorded, 'recorded': spikes_recorded}
    assert summary['recording_complete']


def test_a_bag_with_two_estimators_a_restarted_plant_and_a_gap_is_reported_per_stamp(tmp_path):
    """What the fault matrix records: an estimate per stamp from two estimators at once (each
    with its spikes), a plant whose counters restart from zero, measurements missing for 0.3 s."""
    from scenario_nodes.codec import encode_point
    messages = []
    for k in range(20):
        x = np.arange(6.0) + k
        messages.append(('/truth', KNOWN_TYPES['truth'], encode_odometry(x, None, k * STEP_NS, 'lvlh', 'chaser')))
        if not 5 <= k <= 7:
            messages.append(('/measurement', KNOWN_TYPES['measurement'],
                             encode_point(x[:3], (0, 1, 2), k * STEP_NS, 'lvlh')))
        for _ in range(2 if k >= 10 else 1):  # a second estimator from step 10
            messages.append(('/estimate', KNOWN_TYPES['estimate'],
                             encode_odometry(x + 0.5, np.eye(6), k * STEP_NS, 'lvlh', 'chaser')))
            messages.append(('/spike_count', KNOWN_TYPES['spike_count'], encode_uint32(2)))
            messages.append(('/spikes', KNOWN_TYPES['spikes'], encode_spikes([1, 1, 0, 0])))
    messages += [diagnostics('cw_plant', truth_published=15), diagnostics('cw_plant', truth_published=5),
                 diagnostics('estimator', filter='snn_ekf', neurons=4, steps=10, estimates_published=10)]
    run = read_bag(write_bag(tmp_path / 'bag', messages))
    summary = summarize(run)
    assert summary['restarts'] == {'cw_plant': 1, 'estimator': 0}
    assert summary['duplicate_estimates'] == 10
    assert summary['gaps'] == {'measurement': [[0.5, 0.7]], 'estimate': []}
    assert not summary['recording_complete']  # the gap, not the restarted plant's totals
    # 60 spikes over 30 recorded steps of 4 neurons: 0.5, not 60 / (4 x 10 steps of the last estimator)
    assert summary['spike_fraction'] == pytest.approx(0.5)
    report = write_report([tmp_path / 'bag'], tmp_path / 'report')  # no crash on the longer spike record
    text = report.read_text()
    assert 'cw_plant restarted 1x' in text and 'measurement missing 0.5-0.7 s' in text
    assert (tmp_path / 'report' / 'spikes.png').exists()


def test_a_complete_bag_without_restarts_is_complete(tmp_path):
    messages = steps(5) + [diagnostics('cw_plant', truth_published=5),
                           diagnostics('estimator', filter='ekf', estimates_published=5, spikes_published=0)]
    summary = summarize(read_bag(write_bag(tmp_path / 'bag', messages)))
    assert summary['recording_complete'] and summary['gaps'] == {'estimate': []}


def test_a_corrected_estimate_replaces_the_first_in_the_series_and_the_bag_is_still_complete(tmp_path):
    """The estimator published stamp 0.2 s again, taken with the control the plant applied
    (estimates_corrected): the series holds the corrected one, the spike counts one per step,
    and nothing counts as a duplicate."""
    corrected = ('/estimate', KNOWN_TYPES['estimate'], encode_odometry(np.full(6, 9.0), np.eye(6), 2 * STEP_NS,
                                                                       'lvlh', 'chaser'))
    messages = steps(5) + [corrected] + [
        diagnostics('cw_plant', truth_published=5),
        diagnostics('estimator', filter='ekf', estimates_published=6, estimates_corrected=1, spikes_published=0)]
    run = read_bag(write_bag(tmp_path / 'bag', messages))
    np.testing.assert_array_equal(run.estimate[:, 0], [0.5, 1.5, 9.0, 3.5, 4.5])
    assert run.repeats['estimate'] == 1 and run.counts['/estimate'] == 6
    summary = summarize(run)
    assert summary['messages']['spike_count'] == {'published': 5, 'recorded': 5}
    assert summary['recording_complete'] and summary['duplicate_estimates'] == 0


def test_a_series_reads_in_stamp_order_with_the_first_copy_of_each_stamp_and_an_estimates_last():
    """A recorder writes backfilled samples after newer live ones; a resend repeats a stamp; a
    corrected estimate comes after the provisional one under its stamp (the estimator's answer)."""
    from snn_tools.bags.data import _one_per_stamp

    samples = [(3, 'live'), (4, 'live'), (1, 'history'), (3, 'again'), (2, 'history')]
    kept, dropped = _one_per_stamp(samples)
    assert kept == [(1, 'history'), (2, 'history'), (3, 'live'), (4, 'live')] and dropped == 1
    kept, dropped = _one_per_stamp(samples, last=True)
    assert kept == [(1, 'history'), (2, 'history'), (3, 'again'), (4, 'live')] and dropped == 1


def sensor_diagnostics(name, published, period, every_truth=True, unpublished=0):
    """What a sensor node reports about its schedule (scenario_nodes/sensor_node.py)."""
    return diagnostics(name, measurements_published=published, topic=f'/{name}', sample_period=period,
                       reports_every_truth=every_truth, samples_unpublished=unpublished)


def test_each_sensor_is_checked_against_its_own_rate_and_a_gap_in_one_is_counted(tmp_path):
    """Camera at every truth (10 Hz, nothing measured once too close), LIDAR sampling at 5 Hz
    within range and saying "nothing measured" at every other truth: three LIDAR reports lost
    (1.2-1.4 s) are a gap of the LIDAR, while its "nothing measured" stamps are not."""
    from scenario_nodes.codec import encode_vector3
    from snn_tools.run.demo import sensor_lines
    vector = 'geometry_msgs/msg/Vector3Stamped'
    messages = steps(30)
    for k in range(30):
        camera = [0.1, 0.2] if k < 20 else []  # too close from 2 s: nothing measured
        messages.append(('/camera', vector, encode_vector3(camera, k * STEP_NS, 'camera')))
        if k in (12, 13, 14):
            continue  # lost: neither sample nor "nothing measured"
        lidar = [5.0, 0.1, 0.2] if k % 2 == 0 and k >= 6 else []  # out of range before 0.6 s
        messages.append(('/lidar', vector, encode_vector3(lidar, k * STEP_NS, 'lidar')))
    messages += [diagnostics('cw_plant', truth_published=30),
                 diagnostics('estimator', filter='ekf', estimates_published=30, spikes_published=0,
                             sensors='camera,lidar'),
                 sensor_diagnostics('camera', 30, 0.0), sensor_diagnostics('lidar', 27, 0.2)]
    run = read_bag(write_bag(tmp_path / 'bag', messages))
    summary = summarize(run)
    camera, lidar = summary['sensors']['camera'], summary['sensors']['lidar']
    assert camera == {'node': 'camera', 'period_s': pytest.approx(0.1), 'every_truth': True, 'expected': 30,
                      'recorded': 30, 'measured': 20, 'not_measured': 10, 'off_schedule': 0, 'missing': 0,
                      'gaps': [], 'not_published': 0, 'lost': 0}
    # samples at 0.6, 0.8, 1.0, then 1.6 ... 2.8 s (1.2 and 1.4 lost with the truth between them)
    assert (lidar['expected'], lidar['recorded'], lidar['measured'], lidar['not_measured']) == (30, 27, 10, 17)
    assert lidar['period_s'] == 0.2 and lidar['gaps'] == [[1.2, 1.4]] and (lidar['missing'], lidar['lost']) == (3, 3)
    assert summary['gaps'] == {'camera': [], 'lidar': [[1.2, 1.4]], 'estimate': []}
    # both streams were recorded whole as published: only the per-sensor check sees the gap
    assert summary['messages']['lidar'] == {'published': 27, 'recorded': 27}
    assert not summary['recording_complete']
    lines = sensor_lines(summary['sensors'])
    assert lines[0] == 'camera 30/30 reports (20 measured, 10 nothing measured; a sample every 0.1 s): no gap'
    assert lines[1] == ('lidar 27/30 reports (10 measured, 17 nothing measured; a sample every 0.2 s): '
                        '3 missing in 1 gap(s) at 1.2-1.4 s (0 not published by the sensor, 3 lost)')


def test_a_sensor_sampling_every_half_second_is_complete_and_its_own_dropout_is_explained(tmp_path):
    """A position sensor with measurement_period 0.5 s says nothing between samples (no limits):
    on a 0.1 s truth grid it is due at 0, 0.5, 1.0, 1.5 s; it dropped the 1.0 s sample itself
    (dropout, counted), so the bag is complete with that gap reported."""
    from scenario_nodes.codec import encode_point
    messages = steps(20)
    for k in (0, 5, 15):
        messages.append(('/measurement', KNOWN_TYPES['measurement'],
                         encode_point(np.ones(3), (0, 1, 2), k * STEP_NS, 'lvlh')))
    messages += [diagnostics('cw_plant', truth_published=20),
                 diagnostics('estimator', filter='ekf', estimates_published=20, spikes_published=0),
                 diagnostics('position_sensor', measurements_published=3, topic='/measurement',
                             sample_period=0.5, reports_every_truth=False, samples_unpublished=1)]
    summary = summarize(read_bag(write_bag(tmp_path / 'bag', messages)))
    sensor = summary['sensors']['measurement']
    assert (sensor['expected'], sensor['recorded'], sensor['missing'], sensor['lost']) == (4, 3, 1, 0)
    assert sensor['gaps'] == [[1.0, 1.0]] and sensor['period_s'] == 0.5 and sensor['node'] == 'position_sensor'
    assert summary['recording_complete']


def test_the_summary_and_report_give_the_contact_conditions_within_the_last_metre(tmp_path):
    """A recorded approach along -x at 1 m/s from (3, 0, 0.5) m: it first comes within 1 m at
    the truth of 2.2 s (x = 0.8 m), closing at 1 m/s x 0.8 / hypot(0.8, 0.5), 0.5 m off the axis."""
    messages = []
    for k in range(30):
        x = np.array([3.0 - 0.1 * k, 0.0, 0.5, -1.0, 0.0, 0.0])
        messages.append(('/truth', KNOWN_TYPES['truth'], encode_odometry(x, None, k * STEP_NS, 'lvlh', 'chaser')))
        messages.append(('/estimate', KNOWN_TYPES['estimate'], encode_odometry(x, np.eye(6), k * STEP_NS, 'lvlh',
                                                                               'chaser')))
    bag = write_bag(tmp_path / 'bag', messages)
    contact = summarize(read_bag(bag))['contact']
    assert contact['t_s'] == pytest.approx(2.2)
    assert contact['closing_speed_m_s'] == pytest.approx(0.8 / np.hypot(0.8, 0.5), rel=1e-9)
    assert contact['axis_offset_m'] == pytest.approx(0.5)
    write_report([bag], tmp_path / 'report')
    assert '| 2.2 | 0.848 | 0.500 |' in (tmp_path / 'report' / 'report.md').read_text()
