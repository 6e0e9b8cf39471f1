"""One node registry (scenario_nodes/registry.py): setup.py's console scripts, the ros2-run
wrappers, the parameter tables, the demo and the launch file all list the same nodes."""

import importlib
import os
import runpy
from pathlib import Path

import pytest

from scenario_nodes import registry

ROOT = Path(__file__).resolve().parents[1]


def test_the_wrappers_are_exactly_the_registrys_executables_and_can_run():
    from snn_tools.run.parameter_files import WRAPPER
    wrappers = {path.name: path for path in (ROOT / 'wrappers').iterdir()}
    assert set(wrappers) == set(registry.executables())
    for name, path in wrappers.items():
        assert path.read_text() == WRAPPER.format(name=name), f'{name}: run parameter_files --write'
        assert os.access(path, os.X_OK), name


def test_setup_reads_its_console_scripts_from_the_registry():
    text = (ROOT / 'setup.py').read_text()
    assert "'registry.py'))['executables']()" in text and "'scenario_nodes.plant_node:main'" not in text
    # the registry needs nothing installed: setup.py runs it before numpy exists
    assert runpy.run_path(str(ROOT / 'scenario_nodes' / 'registry.py'))['executables']() == registry.executables()


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


def test_the_demo_starts_the_registrys_loop_in_its_order():
    pytest.importorskip('rclpy')
    from snn_tools.run import demo
    assert [name for name, _ in demo.NODES] == ['recorder', 'lqr_controller', 'estimator', 'position_sensor',
                                                'cw_plant']
    assert {plant: name for plant, (name, _) in demo.PLANTS.items()} == registry.PLANTS
    with pytest.raises(ValueError, match='unknown node'):
        registry.node('kalman_node')
