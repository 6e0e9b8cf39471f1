"""One pipeline description (scenario_nodes/registry.py): the nodes of a run, their start order
and the subscriber counts each waits for (docs/decisions.md, 33 and 41) come from it, and the
launch file, snn_demo and single-process mode all follow it. A node registered only here
(test/estimate_monitor.py: its file and its entry) is started and counted by each."""

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from scenario_nodes import registry

TEST_DIR = Path(__file__).resolve().parents[1]  # test/: the helpers beside conftest
CONFIG = TEST_DIR.parent / 'config' / 'rendezvous.yaml'
LOOP = ['lqr_controller', 'estimator', 'position_sensor', 'cw_plant']


def counts(plant='cw', optional=(), sensor='position', listeners=None) -> dict:
    return registry.subscriber_counts(registry.pipeline(plant, optional, sensor), listeners)


def test_a_run_starts_the_consumers_first_and_the_plant_last():
    assert [n.name for n in registry.pipeline()] == LOOP
    assert [n.name for n in registry.pipeline('basilisk', ('recorder', 'live_view'))] == [
        'recorder', 'live_view', 'lqr_controller', 'estimator', 'position_sensor', 'basilisk_plant']
    # a suite's sensors: the sensor executable under their names, each on its own topic
    sensors = [(n.entry.name, n.name, n.remaps) for n in registry.pipeline(sensor='camera+lidar')
               if n.entry.name == 'position_sensor']
    assert sensors == [('position_sensor', 'camera', ('measurement:=camera',)),
                       ('position_sensor', 'lidar', ('measurement:=lidar',))]
    assert [n.remaps for n in registry.pipeline(sensor='lidar')] == [()] * 4  # the one sensor, renamed nothing
    for wrong, match in ((dict(plant='kalman'), 'plant'), (dict(optional=('estimator',)), 'not an optional node'),
                         (dict(sensor='sonar'), 'sensor')):
        with pytest.raises(ValueError, match=match):
            registry.pipeline(**wrong)


def test_each_node_waits_for_every_subscriber_of_its_output_among_the_nodes_started():
    """By hand from the nodes' subscriptions: truth -> the sensors, the recorder, the live view;
    measurement -> estimator, controller, recorder; control -> estimator, plant, recorder, live
    view; estimate -> controller, recorder, live view (the estimator's own liveliness monitor
    not counted)."""
    assert counts() == {'cw_plant': {'min_truth_subscribers': 1}, 'position_sensor': {'min_measurement_subscribers': 2},
                        'lqr_controller': {'min_control_subscribers': 2}, 'estimator': {'min_estimate_subscribers': 1}}
    assert counts('basilisk', ('recorder', 'live_view')) == {
        'basilisk_plant': {'min_truth_subscribers': 3}, 'position_sensor': {'min_measurement_subscribers': 3},
        'lqr_controller': {'min_control_subscribers': 4}, 'estimator': {'min_estimate_subscribers': 3}}
    # two sensors: the plant waits for both, each sensor for the estimator, controller and recorder
    fused = counts(optional=('recorder',), sensor='camera+lidar')
    assert fused['cw_plant'] == {'min_truth_subscribers': 3}
    assert fused['camera'] == fused['lidar'] == {'min_measurement_subscribers': 3}
    # a probe on measurement, estimate and control is one more subscriber of each
    probe = counts(optional=('recorder',), listeners=dict.fromkeys(('measurement', 'estimate', 'control'), 1))
    assert [probe[n] for n in ('position_sensor', 'estimator', 'lqr_controller', 'cw_plant')] == [
        {'min_measurement_subscribers': 4}, {'min_estimate_subscribers': 3}, {'min_control_subscribers': 4},
        {'min_truth_subscribers': 2}]


def test_every_entry_names_its_class_and_waits_only_for_what_it_publishes():
    for entry in registry.NODES:
        path = TEST_DIR.parent / (entry.module.replace('.', '/') + '.py')
        assert f'class {entry.node_class}(' in path.read_text(), entry.name
        assert set(entry.waits_for) <= set(entry.publishes), entry.name


def test_the_sensor_choices_are_the_position_sensor_and_the_suites_whose_values_reach_their_nodes():
    pytest.importorskip('numpy')
    from scenario_nodes.parameter_tables import sensor_suites
    suites = sensor_suites()
    assert set(registry.SENSOR_NODES) == {'position', *suites}
    for suite, values in suites.items():
        started = {n.name for n in registry.pipeline(optional=('recorder',), sensor=suite)}
        assert set(values) <= started, suite  # no value for a node the suite does not start


def test_every_sensor_suite_is_flown_by_a_scenario_and_its_overlay_names_a_missing_one():
    pytest.importorskip('numpy')
    from scenario_nodes.parameter_tables import sensor_suites
    from snn_tools.run.parameter_files import sensor_overlay
    flown = {suite for entry in registry.SCENARIOS.values() for suite in entry.sensors}
    assert set(sensor_suites()) <= flown
    with pytest.raises(ValueError, match="'sonar' is flown by no scenario"):
        sensor_overlay('sonar')


def test_the_scenarios_the_launch_file_and_the_demo_offer_are_the_rendezvous_and_those_with_a_file():
    pytest.importorskip('numpy')
    from scenario_nodes.parameter_tables import scenarios
    assert list(registry.SCENARIOS) == ['rendezvous', *scenarios()]


# ---------------------------------------------------------------- a node registered only here
@pytest.fixture
def monitor(monkeypatch):
    """estimate_monitor registered (in this process only), importable by the node processes."""
    pytest.importorskip('rclpy')
    import estimate_monitor
    monkeypatch.setattr(registry, 'NODES', estimate_monitor.register())
    monkeypatch.setenv('PYTHONPATH', os.pathsep.join(filter(None, [str(TEST_DIR), os.environ.get('PYTHONPATH')])))
    return estimate_monitor


def test_a_node_registered_only_here_is_started_and_counted_by_the_launch_file(monitor, monkeypatch):
    from launch_stubs import launched_nodes
    nodes = launched_nodes(monkeypatch)
    assert list(nodes) == ['estimate_monitor', *LOOP]
    assert nodes['estimate_monitor']['executable'] == 'estimate_monitor'
    assert nodes['estimator']['parameters'][1:] == [{'min_estimate_subscribers': 2}]  # the controller and it
    assert nodes['lqr_controller']['parameters'][1:] == [{'min_control_subscribers': 2}]  # not a control subscriber


def test_a_node_registered_only_here_is_started_and_counted_by_the_demo(monitor, tmp_path):
    from snn_tools.paths import config_file
    from snn_tools.run.demo import Pipeline, pipeline_env
    overrides = {}
    pipeline = Pipeline(tmp_path, config_file(), overrides, pipeline_env())
    assert [n.name for n in pipeline.nodes] == ['recorder', 'estimate_monitor', *LOOP]
    assert overrides['estimator']['min_estimate_subscribers'] == 3  # the controller, the recorder and it
    assert overrides['lqr_controller']['min_control_subscribers'] == 3
    assert pipeline.command('estimate_monitor', 'estimate_monitor')[:3] == [sys.executable, '-m', 'estimate_monitor']


def test_a_node_registered_only_here_is_built_and_counted_by_single_process_mode(monitor):
    import rclpy

    from snn_tools.run.single_process import build_nodes
    context = rclpy.Context()
    rclpy.init(args=['--ros-args', '--params-file', str(CONFIG)], context=context)
    nodes = {}
    try:
        for name, node in build_nodes('cw', optional=(), context=context):
            nodes[name] = node
        assert list(nodes) == ['estimate_monitor', *LOOP]
        assert isinstance(nodes['estimate_monitor'], monitor.EstimateMonitorNode)
        # the counts win over the parameter file's 0
        assert nodes['estimator'].get_parameter('min_estimate_subscribers').value == 2
        assert nodes['position_sensor'].get_parameter('min_measurement_subscribers').value == 2
    finally:
        for node in nodes.values():
            node.destroy_node()
        rclpy.try_shutdown(context=context)


def matched(log: str, topic: str) -> list[int]:
    """The subscriptions a node's hold saw matched on ``topic`` when it let its input in."""
    return [int(n) for n in re.findall(rf"'(?:[\w/]*/)?{topic}' matched (\d+) subscriptions", log)]


def heard(log: str) -> int:
    return int(re.search(r'heard (\d+) estimates', log).group(1))


@pytest.mark.slow
def test_the_demo_runs_the_registered_node_and_the_estimator_waits_for_it(monitor, tmp_path):
    from snn_tools.run.demo import run_pipeline
    result = run_pipeline(tmp_path, 'ekf', duration=5.0, scheduling='normal', pin_cpus=False)
    assert result['exit_codes']['estimate_monitor'] == 0
    logs = tmp_path / 'logs'
    assert matched((logs / 'estimator.log').read_text(), 'estimate') == [3]
    assert heard((logs / 'estimate_monitor.log').read_text()) >= 45  # 50 steps


@pytest.mark.slow
def test_single_process_mode_runs_the_registered_node_and_the_estimator_waits_for_it():
    """In a process of its own that registers the node first, as this test's fixture does."""
    pytest.importorskip('rclpy')
    from snn_tools.run.demo import pipeline_env
    code = ('import estimate_monitor; from scenario_nodes import registry; '
            'registry.NODES = estimate_monitor.register(); '
            'from snn_tools.run.single_process import main; raise SystemExit(main())')
    done = subprocess.run(
        [sys.executable, '-c', code, '--no-record', '--ros-args', '--params-file', str(CONFIG),
         '-p', 'cw_plant:duration:=5.0', '-p', 'cw_plant:exit_when_done:=true', '-p', 'estimator:filter_type:=ekf'],
        env=dict(pipeline_env(), PYTHONPATH=str(TEST_DIR)), capture_output=True, text=True, timeout=240)
    log = done.stdout + done.stderr
    assert done.returncode == 0, log[-3000:]
    assert matched(log, 'estimate') == [2]  # the controller and the monitor
    assert heard(log) >= 45


def test_a_node_starting_while_the_next_is_added_reads_a_whole_overrides_file(tmp_path, monkeypatch):
    """Every node reads overrides.yaml at init while the demo goes on starting the next ones,
    each start writing the file again: a reader must never see it empty or cut (a controller once
    read it mid-write on a loaded machine and flew without its guidance)."""
    import threading
    from types import SimpleNamespace

    import yaml

    from snn_tools.paths import config_file
    from snn_tools.run import demo
    monkeypatch.setattr(demo.subprocess, 'Popen', lambda *args, **kwargs: SimpleNamespace(pid=0))  # none started
    monkeypatch.setattr(demo, 'running_policy', lambda pid: None)
    pipeline = demo.Pipeline(tmp_path, config_file(), {'lqr_controller': {'guidance': 'approach'}}, demo.pipeline_env())
    pipeline.start_node('lqr_controller', 'scenario_nodes.controller_node')
    bad, done = [], threading.Event()

    def read_all_the_time():
        while not done.is_set():
            document = yaml.safe_load(pipeline.overrides_file.read_text()) or {}
            if document.get('/**/lqr_controller', {}).get('ros__parameters', {}).get('guidance') != 'approach':
                bad.append(document)

    reader = threading.Thread(target=read_all_the_time)
    reader.start()
    try:
        for k in range(40):  # a file of ~100 kB by the end: a write in place is caught half done
            pipeline.start_node(f'sensor_{k}', 'scenario_nodes.sensor_node', overrides={'values': list(range(300))})
    finally:
        done.set()
        reader.join()
    assert not bad, f'{len(bad)} reads of a cut or empty file'
