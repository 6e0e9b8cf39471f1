"""The package installs the ROS way (colcon) and the pip way, and `ros2 run` finds every node.

`ros2 run <pkg> <exe>` resolves ament_index_python.get_package_prefix(pkg)/lib/<pkg>/<exe> and
needs the executable bit; these tests resolve executables exactly so and start them.
"""

import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow
ROOT = Path(__file__).resolve().parents[2]
PACKAGE = 'snn_rendezvous'
NODES = ('cw_plant', 'position_sensor', 'lqr_controller', 'estimator', 'recorder')
EXECUTABLES = NODES + ('report', 'live_view')


def ros2_run_path(prefix_env: dict, executable: str) -> Path:
    """What `ros2 run` would execute, resolved through the ament index in a clean process."""
    code = ('from ament_index_python.packages import get_package_prefix;'
            f'print(get_package_prefix("{PACKAGE}"))')
    prefix = subprocess.run([sys.executable, '-c', code], env=prefix_env, check=True,
                            capture_output=True, text=True).stdout.strip()
    path = Path(prefix) / 'lib' / PACKAGE / executable
    assert path.is_file() and os.access(path, os.X_OK), path
    return path


def start_and_stop(path: Path, env: dict, log: Path, extra=()) -> tuple[int, str]:
    """Start a node with the package's parameters, let it come up, SIGINT it."""
    with open(log, 'w') as out:
        process = subprocess.Popen([str(path), '--ros-args', '--params-file', str(ROOT / 'config' / 'rendezvous.yaml'),
                                    *extra], env=env, stdout=out, stderr=subprocess.STDOUT, cwd=log.parent)
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline and process.poll() is None and '] ' not in log.read_text():
            time.sleep(0.1)
        time.sleep(0.5)
        process.send_signal(signal.SIGINT)
        code = process.wait(20)
    return code, log.read_text()


def source_files(destination: Path) -> Path:
    files = subprocess.run(['git', 'ls-files'], cwd=ROOT, capture_output=True, text=True, check=True).stdout.split()
    for name in files + [p.relative_to(ROOT).as_posix() for p in ROOT.glob('*/*.py')]:
        source = ROOT / name
        if source.is_file():
            target = destination / name
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(source, target)
    return destination


@pytest.fixture(scope='module')
def pip_prefix(tmp_path_factory):
    prefix = tmp_path_factory.mktemp('pip_prefix')
    source = source_files(tmp_path_factory.mktemp('pip_source') / PACKAGE)
    subprocess.run([sys.executable, '-m', 'pip', 'install', '--quiet', '--no-deps', '--ignore-installed',
                    '--prefix', str(prefix),
                    str(source)], check=True, capture_output=True)
    return prefix


def prefix_env(prefix: Path, site: Path) -> dict:
    env = dict(os.environ)
    env['AMENT_PREFIX_PATH'] = str(prefix)
    env['PYTHONPATH'] = str(site)
    return env


def test_pip_install_puts_ros2_run_wrappers_index_marker_and_share_files(pip_prefix, tmp_path):
    site = next(pip_prefix.glob('lib/python3*/site-packages'))
    assert (pip_prefix / 'share/ament_index/resource_index/packages' / PACKAGE).is_file()
    share = pip_prefix / 'share' / PACKAGE
    for name in ('package.xml', 'launch/rendezvous.launch.py', 'config/rendezvous.yaml',
                 'config/rendezvous_as_published.yaml', 'config/rendezvous.rviz', 'config/foxglove_layout.json',
                 'config/fastdds.xml'):
        assert (share / name).is_file(), name
    env = prefix_env(pip_prefix, site)
    for executable in EXECUTABLES:
        ros2_run_path(env, executable)
    # every node starts alone through that path and stops cleanly on SIGINT
    for node in NODES:
        extra = ('-p', f'output:={tmp_path / "bag"}') if node == 'recorder' else ()
        code, log = start_and_stop(ros2_run_path(env, node), env, tmp_path / f'{node}.log', extra)
        assert code == 0, log
        assert f'[{node}]' in log, log
    imported = subprocess.run([sys.executable, '-c', 'import scenario_nodes; print(scenario_nodes.__file__)'],
                              env=env, capture_output=True, text=True, cwd=tmp_path).stdout
    assert imported.startswith(str(site)), imported  # the installed copy, not the checkout


def test_a_node_with_an_invalid_parameter_exits_2_and_says_what_to_fix(pip_prefix):
    site = next(pip_prefix.glob('lib/python3*/site-packages'))
    env = prefix_env(pip_prefix, site)
    result = subprocess.run([str(ros2_run_path(env, 'estimator')), '--ros-args', '-p', 'neuron_count:=0'],
                            env=env, capture_output=True, text=True, timeout=60)
    assert result.returncode == 2
    assert 'neuron_count' in result.stderr


def test_colcon_build_installs_an_ament_python_package(tmp_path):
    colcon = Path(sys.executable).with_name('colcon')
    if not colcon.exists():
        pytest.skip('colcon-common-extensions is not installed in this environment')
    workspace = tmp_path / 'ws'
    source_files(workspace / 'src' / PACKAGE)
    env = dict(os.environ)
    env.pop('AMENT_PREFIX_PATH', None)
    result = subprocess.run([str(colcon), 'build', '--base-paths', 'src'], cwd=workspace, env=env,
                            capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stdout + result.stderr
    install = workspace / 'install' / PACKAGE
    assert (install / 'share/ament_index/resource_index/packages' / PACKAGE).is_file()
    for name in ('package.xml', 'launch/rendezvous.launch.py', 'config/rendezvous.yaml'):
        assert (install / 'share' / PACKAGE / name).is_file(), name
    site = next(install.glob('lib/python3*/site-packages'))
    run_env = prefix_env(install, site)
    for executable in EXECUTABLES:
        path = ros2_run_path(run_env, executable)
        assert path.read_text().startswith('#!'), path  # console scripts, not the pip wrappers
    code, log = start_and_stop(ros2_run_path(run_env, 'estimator'), run_env, tmp_path / 'estimator.log')
    assert code == 0 and '[estimator]' in log, log


def test_package_xml_declares_every_runtime_dependency():
    text = (ROOT / 'package.xml').read_text()
    assert '<build_type>ament_python</build_type>' in text and 'format="3"' in text
    for key in ('rclpy', 'nav_msgs', 'geometry_msgs', 'sensor_msgs', 'std_msgs', 'std_srvs', 'diagnostic_msgs',
                'rosgraph_msgs', 'ament_index_python', 'launch_ros', 'python3-numpy', 'python3-scipy',
                'python3-matplotlib', 'python3-control-pip', 'python3-numba-pip', 'python3-rosbags-pip'):
        assert f'<exec_depend>{key}</exec_depend>' in text, key
    rosdep = (ROOT / 'rosdep' / 'snn_rendezvous.yaml').read_text()
    for key in ('python3-control-pip', 'python3-numba-pip', 'python3-rosbags-pip'):
        assert f'{key}:' in rosdep


def test_launch_file_starts_the_nodes_with_the_arguments_and_ends_with_the_plant(monkeypatch):
    """Run generate_launch_description() against stand-ins for launch/launch_ros (not
    installable here) and check what it would start, for both scheduling choices, and that the
    launch shuts down when the plant exits unless keep_alive:=true."""
    from launch_stubs import DEFAULTS, launched_nodes, load_launch_file

    from scenario_nodes import registry

    namespace, created = load_launch_file(monkeypatch)
    namespace['generate_launch_description']()
    arguments = {a.args[0]: a.kwargs for a in created['argument']}
    assert {'estimator', 'params_file', 'mode', 'scheduling', 'plant', 'keep_alive'} <= set(arguments)
    assert all(kwargs.get('description') for kwargs in arguments.values())
    assert arguments['params_file']['default_value'] == ('join', (('share', PACKAGE), 'config', 'rendezvous.yaml'))
    assert arguments['scheduling']['choices'] == ['normal', 'batch']
    assert arguments['scheduling']['default_value'] == 'normal'
    make_nodes = created['opaque'][0].kwargs['function']
    base = dict(DEFAULTS)
    for context, prefix in (({'scheduling': 'normal'}, None),  # launch applies --launch-prefix itself
                            ({'scheduling': 'batch'}, 'chrt --batch 0'),
                            ({'scheduling': 'batch', 'launch-prefix': 'gdb -ex run --args'},
                             'chrt --batch 0 gdb -ex run --args')):
        created['node'], created['handler'] = [], []
        actions = make_nodes(dict(base, **context))
        nodes = {n.kwargs['executable']: n.kwargs for n in created['node']}
        # the registry's start order, the plant last; recorder and live view only when asked for
        assert list(nodes) == ['lqr_controller', 'estimator', 'position_sensor', 'cw_plant']
        for exe, n in nodes.items():
            assert n['package'] == PACKAGE and n['name'] == exe
            assert n['exec_name'] == exe  # log lines say [estimator-2], not [chrt-2]
            assert n.get('prefix') == prefix, (exe, context)
        # the parameter file's filter_type (only the chain's matching count is added: decisions.md, 41)
        assert nodes['estimator']['parameters'][1:] == [{'min_estimate_subscribers': 1}]
        plant = nodes['cw_plant']['parameters'][1]
        assert plant['mode'] == ('config', 'mode', None) and plant['exit_when_done'] is True
        # launch turns real_time_factor:=10 into an integer, which the DOUBLE parameter refuses
        assert plant['real_time_factor'] == ('typed', ('config', 'real_time_factor', None), float)
        # the plant's exit shuts the launch down
        (handler,) = created['handler']
        on_exit = handler.args[0]
        assert on_exit.kwargs['target_action'] is next(n for n in created['node']
                                                      if n.kwargs['executable'] == 'cw_plant')
        assert handler in actions
    # the package's Fast DDS profile unless the user points Fast DDS elsewhere (decisions.md, 38)
    monkeypatch.delenv('FASTRTPS_DEFAULT_PROFILES_FILE', raising=False)
    created['environment'] = []
    actions = make_nodes(dict(base, scheduling='normal'))
    (environment,) = created['environment']
    assert actions[0] is environment
    profile = ('join', (('share', PACKAGE), 'config', 'fastdds.xml'))
    assert environment.args == ('FASTRTPS_DEFAULT_PROFILES_FILE', profile)
    monkeypatch.setenv('FASTRTPS_DEFAULT_PROFILES_FILE', '/my/profile.xml')
    created['environment'] = []
    make_nodes(dict(base, scheduling='normal'))
    assert created['environment'] == []
    created['node'], created['handler'] = [], []
    make_nodes(dict(base, scheduling='normal', keep_alive='true', estimator='snn_emsif_weighted',
                    plant='basilisk'))
    nodes = {n.kwargs['executable']: n.kwargs for n in created['node']}
    assert created['handler'] == [] and nodes['basilisk_plant']['parameters'][1]['exit_when_done'] is False
    assert nodes['estimator']['parameters'][1]['filter_type'] == 'snn_emsif_weighted'
    assert nodes['basilisk_plant']['parameters'][1]['min_truth_subscribers'] == 1  # the sensor
    # the recorder subscribes to 'truth' last (once it hears the loop): the plant's first state
    # waits for it, and for the live view, which would otherwise fill the count before it
    for record, live_view, expected in (('true', 'false', 2), ('false', 'true', 2), ('true', 'true', 3)):
        by_name = {name: n['parameters'][1:] for name, n in
                   launched_nodes(monkeypatch, record=record, live_view=live_view).items()}
        assert ('recorder' in by_name) is (record == 'true') and ('live_view' in by_name) is (live_view == 'true')
        assert by_name['cw_plant'][0]['min_truth_subscribers'] == expected, (record, live_view)
        # each sensor waits for its estimator, controller and recorder; upstream the same
        # (decisions.md, 33 and 41): controls reach estimator, plant and the optional nodes before
        # the controller subscribes to estimates, estimates the controller and those before the
        # estimator subscribes to measurements: the counts of the pipeline description
        optional = (record == 'true') + (live_view == 'true')
        assert by_name['position_sensor'] == [{'min_measurement_subscribers': 2 + (record == 'true')}]
        assert by_name['lqr_controller'] == [{'min_control_subscribers': 2 + optional}]
        assert by_name['estimator'] == [{'min_estimate_subscribers': 1 + optional}]
        optional_nodes = [name for name, asked in (('recorder', record), ('live_view', live_view)) if asked == 'true']
        counts = registry.subscriber_counts(registry.pipeline('cw', optional_nodes))
        assert all(by_name[name][0].items() >= values.items() for name, values in counts.items())


def test_the_launch_files_scenario_and_sensor_load_their_files_after_params_file_and_start_a_node_per_sensor(
        monkeypatch):
    """scenario:=approach sensor:=by_range: config/scenario_approach.yaml, then config/sensor_by_range.yaml
    after params_file, as snn_demo layers them; relative GPS, the LIDAR and the docking camera each
    a sensor node on its own topic, counted by the estimator, controller and plant as the pipeline
    description says. The defaults load params_file alone; a choice a scenario does not fly is refused."""
    from launch_stubs import launched_nodes, load_launch_file

    from scenario_nodes import registry

    namespace, created = load_launch_file(monkeypatch)
    namespace['generate_launch_description']()
    arguments = {a.args[0]: a.kwargs for a in created['argument']}
    assert arguments['scenario']['default_value'] == 'rendezvous' and arguments['sensor']['default_value'] == 'position'
    assert set(arguments['scenario']['choices']) == {'rendezvous', 'approach'}
    assert 'by_range' in arguments['sensor']['choices']
    params = ('config', 'params_file', None)
    share = ('share', PACKAGE)
    nodes = launched_nodes(monkeypatch)
    assert all(n['parameters'][:1] == [params] and not any(isinstance(p, tuple) and p[0] == 'join'
                                                           for p in n['parameters']) for n in nodes.values())
    nodes = launched_nodes(monkeypatch, scenario='approach', sensor='by_range')
    assert list(nodes) == ['lqr_controller', 'estimator', 'relative_gps', 'lidar', 'camera', 'cw_plant']
    for name, node in nodes.items():
        assert node['parameters'][:3] == [params, ('join', (share, 'config', 'scenario_approach.yaml')),
                                          ('join', (share, 'config', 'sensor_by_range.yaml'))], name
    for name in ('relative_gps', 'lidar', 'camera'):
        assert nodes[name]['executable'] == 'position_sensor' and nodes[name]['remappings'] == [('measurement', name)]
    counts = registry.subscriber_counts(registry.pipeline('cw', (), 'by_range'))
    assert all(nodes[name]['parameters'][3].items() >= values.items() for name, values in counts.items())
    assert nodes['lidar']['parameters'][3] == {'min_measurement_subscribers': 2}  # estimator and controller
    nodes = launched_nodes(monkeypatch, scenario='approach', sensor='angles_far')  # the far camera instead
    assert list(nodes) == ['lqr_controller', 'estimator', 'far_camera', 'lidar', 'camera', 'cw_plant']
    assert nodes['lqr_controller']['parameters'][2] == ('join', (share, 'config', 'sensor_angles_far.yaml'))
    nodes = launched_nodes(monkeypatch, scenario='approach')
    assert 'position_sensor' in nodes and nodes['estimator']['parameters'][:2] == [
        params, ('join', (share, 'config', 'scenario_approach.yaml'))]
    for bad in ({'scenario': 'approach', 'sensor': 'docking'}, {'scenario': 'approach', 'plant': 'basilisk'},
                {'sensor': 'by_range'}, {'sensor': 'angles_far'}):
        with pytest.raises(ValueError, match='scenario flies plant'):
            launched_nodes(monkeypatch, **bad)


def test_the_fast_dds_profile_is_what_the_demo_points_fast_dds_at():
    """config/fastdds.xml: a default data-writer profile whose heartbeat period is 100 ms
    (docs/decisions.md, 38), set by snn_demo's environment unless the user set another."""
    import xml.etree.ElementTree as ElementTree

    from snn_tools.run.demo import pipeline_env
    namespace = {'dds': 'http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles'}
    writer = ElementTree.parse(ROOT / 'config' / 'fastdds.xml').getroot().find('dds:data_writer', namespace)
    assert writer.get('is_default_profile') == 'true'
    period = writer.find('dds:times/dds:heartbeatPeriod', namespace)
    seconds, nanoseconds = (int(period.find(f'dds:{unit}', namespace).text) for unit in ('sec', 'nanosec'))
    assert (seconds, nanoseconds) == (0, 10 ** 8)
    assert pipeline_env()['FASTRTPS_DEFAULT_PROFILES_FILE'] == os.environ['FASTRTPS_DEFAULT_PROFILES_FILE']
    saved = os.environ.pop('FASTRTPS_DEFAULT_PROFILES_FILE')
    try:
        assert pipeline_env()['FASTRTPS_DEFAULT_PROFILES_FILE'] == str(ROOT / 'config' / 'fastdds.xml')
    finally:
        os.environ['FASTRTPS_DEFAULT_PROFILES_FILE'] = saved


def test_the_install_warm_up_covers_every_kind_and_names_a_part_that_fails():
    """make's warm-up (python -m snn_tools.run.warm_cache) compiles each filter kind's kernels and loop
    on worker processes, the longest parts first; a part that fails comes back as its traceback
    (named, the others go on), not as a crash of the install."""
    from snn_estimator import FILTER_KINDS
    from snn_tools.run import warm_cache
    parts = warm_cache.parts()
    assert sorted(parts) == sorted([*FILTER_KINDS, 'basilisk truth'])
    spiking = [FILTER_KINDS[p].spiking for p in parts if p in FILTER_KINDS]
    assert spiking == sorted(spiking, reverse=True)  # the spiking kinds (the longest) first
    assert 'unknown filter kinds' in warm_cache.warm('ukf')


def test_the_install_compiles_what_the_demo_runs_and_the_estimator_node_then_compiles_nothing(tmp_path):
    """make's install warms only the demo's part (issue 37: a newcomer's first make demo must not
    wait for every kind): the default estimator's kernels, which the node's own warm-up then
    finds in numba's cache (an empty cache of its own here, so only that part fills it)."""
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path))
    program = "from snn_tools.run import warm_cache; print(warm_cache.warm('demo'))"
    warm = subprocess.run([sys.executable, '-c', program], capture_output=True, text=True, timeout=600, env=env)
    assert warm.returncode == 0 and warm.stdout.strip() == '', warm.stderr
    node = ('from snn_estimator import make_estimator; from snn_estimator.catalog import DEFAULT_FILTER\n'
            'from snn_estimator.filters import kernels\n'
            'estimator = make_estimator(DEFAULT_FILTER); estimator.warm_up()\n'
            'stats = kernels.step_kernel(*estimator.program.composition, packed=True).stats\n'
            'print(len(stats.cache_hits), len(stats.cache_misses))')
    loaded = subprocess.run([sys.executable, '-c', node], capture_output=True, text=True, timeout=300, env=env)
    assert loaded.returncode == 0, loaded.stderr
    hits, misses = map(int, loaded.stdout.split())
    assert hits >= 1 and misses == 0
