"""Parameter tables, descriptors and the commented YAML files in config/ stay in step."""

import re
import shlex
from pathlib import Path

import numpy as np
import pytest
import yaml

pytest.importorskip('rclpy')

from scenario_nodes.core_objects import estimator_config  # noqa: E402
from scenario_nodes.parameter_tables import (  # noqa: E402
    CONTROLLER,
    ESTIMATOR,
    ESTIMATOR_RUNTIME,
    PLANT,
    RECORDER,
    SENSOR,
    sensor_input_specs,
    sensor_suites,
)
from scenario_nodes.ros_parameters import descriptor  # noqa: E402
from snn_estimator import EstimatorConfig, make_estimator, rendezvous_scenario, schema  # noqa: E402
from snn_estimator.filters.estimators import Estimator  # noqa: E402
from snn_tools.run.parameter_files import CONFIG_FILES  # noqa: E402

CONFIG = Path(__file__).resolve().parents[2] / 'config'
NODES = {'cw_plant': PLANT, 'position_sensor': SENSOR, 'lqr_controller': CONTROLLER, 'estimator': ESTIMATOR,
         'recorder': RECORDER}


def node_values(document: dict, node: str) -> dict:
    values = dict(document.get('/**', {}).get('ros__parameters', {}))
    values.update(document.get(f'/**/{node}', {}).get('ros__parameters', {}))
    return values


def test_the_generated_files_are_current():
    """config/*.yaml and docs/parameters.md are generated from the parameter tables."""
    from snn_tools.run.parameter_files import generated_files
    for path, content in generated_files().items():
        assert path.read_text() == content, f'{path.name} is stale: run python -m snn_tools.run.parameter_files --write'


def test_default_yaml_repeats_every_default_of_the_parameter_tables():
    document = yaml.safe_load((CONFIG / 'rendezvous.yaml').read_text())
    text = (CONFIG / 'rendezvous.yaml').read_text()
    for node, specs in NODES.items():
        values = node_values(document, node)
        for spec in specs:
            if spec.default is None:  # arrays without a default are documented as comments
                assert re.search(rf'#\s*{spec.name}:', text), (node, spec.name)
                continue
            assert spec.name in values, (node, spec.name)
            expected, actual = spec.default, values[spec.name]
            if specs is ESTIMATOR:  # the file's own choices, said in its header
                expected = CONFIG_FILES['rendezvous.yaml'][1].get(spec.name, expected)
            assert actual == expected and type(actual) is type(expected), (node, spec.name, actual)


def test_every_yaml_parameter_is_preceded_by_its_comment():
    for path in CONFIG.glob('*.yaml'):
        lines = path.read_text().splitlines()
        for number, line in enumerate(lines):
            if re.match(r'^\s{4}\w+:', line):
                assert lines[number - 1].strip().startswith('#'), f'{path.name}: {line.strip()} has no comment'


def test_as_published_yaml_differs_only_in_the_network_numerics_and_the_start():
    default = yaml.safe_load((CONFIG / 'rendezvous.yaml').read_text())
    literal = yaml.safe_load((CONFIG / 'rendezvous_as_published.yaml').read_text())
    differences = {(node, key) for node in default for key in default[node]['ros__parameters']
                   if default[node]['ros__parameters'][key] != literal[node]['ros__parameters'][key]}
    assert differences == {('/**/estimator', 'state_scale'), ('/**/estimator', 'discretization'),
                           ('/**/estimator', 'initial_state_dispersion')}
    assert literal['/**/estimator']['ros__parameters']['state_scale'] == [1.0] * 6


def test_descriptors_carry_descriptions_ranges_and_read_only_flags():
    for specs in NODES.values():
        for spec in specs:
            described = descriptor(spec)
            assert len(described.description) > 15, spec.name
            if spec.low is not None and isinstance(spec.default, float):
                assert described.floating_point_range[0].from_value == spec.low
    by_name = {s.name: s for s in ESTIMATOR}
    assert by_name['filter_type'].read_only and by_name['neuron_count'].read_only
    assert 'Eq.' in by_name['boundary_layer'].description


def test_the_runtime_parameters_are_exactly_what_the_core_can_change_between_steps():
    """read_only=False on a schema field's ROS parameter iff Estimator.retune takes it; each such
    field is accepted by a running filter and every other one refused (test_robustness covers
    the same over the parameter services)."""
    by_name = {s.name: s for s in ESTIMATOR}
    assert not by_name['leak_rate'].read_only and 'leak_rate' in Estimator.RETUNABLE
    estimator = make_estimator('snn_ekf')
    estimator.prepare(0.1)
    for field in schema.FIELDS:
        assert by_name[field.name].read_only is (field.name not in Estimator.RETUNABLE), field.name
        if field.runtime:
            estimator.retune(**{field.name: field.default})
        else:
            with pytest.raises(ValueError, match='cannot change'):
                estimator.retune(**{field.name: field.default})
    assert {s.name for s in ESTIMATOR if not s.read_only} == set(ESTIMATOR_RUNTIME)


def test_the_schema_repeats_the_choices_of_the_models():
    from snn_estimator.models import DISCRETIZATIONS, DYNAMICS_MODELS
    assert schema.BY_NAME['discretization'].choices == DISCRETIZATIONS
    assert schema.BY_NAME['dynamics_model'].choices == DYNAMICS_MODELS


def test_yaml_estimator_parameters_build_the_core_default_configuration():
    document = yaml.safe_load((CONFIG / 'rendezvous.yaml').read_text())
    values = node_values(document, 'estimator')
    values.setdefault('silenced_neurons', None)
    config = estimator_config(values)
    core = rendezvous_scenario().estimator
    for field in ('neuron_count', 'leak_rate', 'decoder_variance', 'process_noise_scale',
                  'measurement_noise_scale', 'spike_rule', 'discretization'):
        assert getattr(config, field) == pytest.approx(getattr(core, field)) if isinstance(
            getattr(core, field), float) else getattr(config, field) == getattr(core, field)
    np.testing.assert_allclose(config.state_scale, core.state_scale)
    np.testing.assert_allclose(config.initial_covariance, core.initial_covariance)
    np.testing.assert_allclose(config.initial_state, EstimatorConfig().initial_state)


def test_the_readme_ros2_run_lines_set_what_they_say():
    """Each `-p` of the README's `ros2 run` lines reaches its node over the package's parameter
    file (a bare `-p name:=value` would lose to the file's node section), renamed nodes included."""
    import rclpy
    from rclpy.node import Node

    from scenario_nodes.ros_parameters import declare

    readme = (CONFIG.parent / 'README.md').read_text().replace('\\\n', ' ')
    lines = re.findall(r'^ros2 run snn_rendezvous (\w+)\s+--ros-args (.*?)(?:\s+#.*)?$', readme, re.M)
    assert len(lines) >= 5
    checked = 0
    for executable, arguments in lines:
        overlays = {'$L': 'lidar', '$F': 'camera+lidar'}
        arguments = arguments.replace('$P', str(CONFIG / 'rendezvous.yaml'))
        for variable, suite in overlays.items():
            arguments = arguments.replace(variable, str(CONFIG / f'sensor_{suite}.yaml'))
        arguments = shlex.split(arguments)
        context = rclpy.Context()
        rclpy.init(args=['readme', '--ros-args', *arguments], context=context)
        try:
            node = Node(executable, context=context)
            values = declare(node, NODES[executable])
            for suite in overlays.values():
                if str(CONFIG / f'sensor_{suite}.yaml') not in arguments:
                    continue
                for name in values.get('sensors') or ():  # an estimator's sensors, declared at configure
                    values.update(declare(node, sensor_input_specs(name)))
                # the overlay's values won over the file's, a renamed sensor node's too
                for name, value in sensor_suites()[suite][node.get_name()].items():
                    assert values[name] == value, (executable, name)
                    checked += 1
            for flag, rule in zip(arguments, arguments[1:]):
                if flag == '-p':
                    name, _, value = rule.partition(':=')
                    if name.startswith('qos_overrides.'):  # declared by the endpoint (test_ros_citizen)
                        continue
                    target, _, name = name.rpartition(':')
                    assert target in ('', node.get_name()), rule
                    assert values[name] == yaml.safe_load(value), (executable, rule)
                    checked += 1
            node.destroy_node()
        finally:
            rclpy.try_shutdown(context=context)
    assert checked >= 7


def test_a_node_with_only_the_shared_parameters_gets_no_empty_section(monkeypatch):
    """A new node whose table is the shared MODEL one (issue 21's throwaway node found it):
    every section of the generated file holds a ros__parameters mapping, which rcl requires
    (an empty one is a parse error: 'Cannot have a value before ros__parameters')."""
    from scenario_nodes import parameter_tables
    from snn_tools.run.parameter_files import yaml_document

    monkeypatch.setattr(parameter_tables, 'NODES', {**parameter_tables.NODES, 'range_monitor': parameter_tables.MODEL})
    document = yaml.safe_load(yaml_document('test', {}))
    assert '/**/range_monitor' not in document
    assert all(isinstance(section.get('ros__parameters'), dict) for section in document.values())
