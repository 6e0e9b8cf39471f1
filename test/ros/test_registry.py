"""One node registry (scenario_nodes/registry.py): setup.py's console scripts, the ros2-run
wrappers, the parameter tables, the demo and the launch file all list the same nodes."""

import importlib
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from scenario_nodes import registry

ROOT = Path(__file__).resolve().parents[2]


def test_the_wrappers_are_exactly_the_registrys_executables_and_can_run():
    from snn_tools.run.parameter_files import WRAPPER
    wrappers = {path.name: path for path in (ROOT / 'wrappers').iterdir()}
    assert set(wrappers) == set(registry.executables())
    for name, path in wrappers.items():
        assert path.read_text() == WRAPPER.format(name=name), f'{name}: run parameter_files --write'
        assert os.access(path, os.X_OK), name


def test_setup_reads_its_console_scripts_from_the_registry():
    text = (ROOT / 'setup.py').read_text()
    assert 'from scenario_nodes.registry import executables' in text and "'scenario_nodes.plant_node:main'" not in text
    # the registry needs nothing installed: setup.py reads it from the source tree before numpy
    # exists (here: an interpreter without site-packages)
    code = (f'import json, sys; sys.path.insert(0, {str(ROOT)!r}); '
            'from scenario_nodes.registry import executables; print(json.dumps(executables()))')
    done = subprocess.run([sys.executable, '-S', '-c', code], capture_output=True, text=True, cwd='/')
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout) == registry.executables()


def test_every_registered_executable_has_its_main_and_every_node_its_parameter_table():
    for name, target in registry.executables().items():
        module, _, function = target.partition(':')
        spec = importlib.util.find_spec(module)
        assert spec is not None, name
        assert f'def {function}(' in Path(spec.origin).read_text(), name
    pytest.importorskip('rclpy')
    from scenario_nodes import parameter_tables
    assert list(parameter_tables.NODES) == [entry.name for entry in registry.NODES]
    assert all(parameter_tables.NODES[entry.name] is getattr(parameter_tables, entry.parameters)
               for entry in registry.NODES)


def test_the_demo_starts_the_registrys_loop_in_its_order(tmp_path):
    pytest.importorskip('rclpy')
    from snn_tools.paths import config_file
    from snn_tools.run.demo import Pipeline, pipeline_env
    for plant, name in registry.plants().items():
        pipeline = Pipeline(tmp_path, config_file(), {}, pipeline_env(), plant=plant)
        assert [node.name for node in pipeline.nodes] == ['recorder', 'lqr_controller', 'estimator',
                                                          'position_sensor', name]
        assert pipeline.plant == name
    with pytest.raises(ValueError, match='unknown node'):
        registry.node('kalman_node')
