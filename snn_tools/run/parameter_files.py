"""The files generated from the parameter tables and the node registry: the commented parameter
files in config/ (the scenario, the as-published variant, one overlay per sensor suite),
docs/parameters.md and the ros2-run wrappers of a pip install (wrappers/). A test keeps them in
step with the tables.

    python -m snn_tools.run.parameter_files            # print the parameter tables (markdown)
    python -m snn_tools.run.parameter_files --write    # write the files that changed
"""

from __future__ import annotations

import argparse
import textwrap
from pathlib import Path

from scenario_nodes import parameter_tables as tables
from scenario_nodes import registry
from scenario_nodes.parameter_tables import (
    BASILISK_PLANT,
    ESTIMATOR,
    MODEL,
    PLANT,
    SENSOR,
    SENSOR_INPUT,
    Spec,
    scenarios,
    sensor_input_specs,
    sensor_suites,
    show,
)
from snn_tools.paths import SOURCE_ROOT

#: wrappers/<name>: what `ros2 run` finds in lib/<package> after a pip install (setup.py).
WRAPPER = '''#!/bin/sh
# ros2 run entry point for a pip install: run the console script installed in <prefix>/bin.
exec "$(dirname "$0")/../../bin/{name}" "$@"
'''


def markdown() -> str:
    """The parameter reference tables of docs/parameters.md."""
    shared = {spec.name for spec in MODEL}
    lines = []
    for title, specs in (('all pipeline nodes', MODEL), *tables.NODES.items()):
        if specs is BASILISK_PLANT:  # only what it adds to cw_plant's
            lines += ['**basilisk_plant** (cw_plant\'s parameters and these)', '',
                      '| parameter | default | meaning |', '|---|---|---|']
            lines += [_row(spec) for spec in BASILISK_PLANT[len(PLANT):]] + ['']
            continue
        lines += [f'**{title}**', '', '| parameter | default | meaning |', '|---|---|---|']
        for spec in specs:
            if specs is not MODEL and spec.name in shared:
                continue
            lines.append(_row(spec))
        lines.append('')
    lines += ['**estimator, each sensor of `sensors`** (declared as `<name>.<parameter>`, e.g. `lidar.model`)', '',
              '| parameter | default | meaning |', '|---|---|---|']
    lines += [_row(spec) for spec in SENSOR_INPUT] + ['']
    return '\n'.join(lines)


def _row(spec: Spec) -> str:
    choices = ' (' + ' \\| '.join(spec.choices) + ')' if spec.choices else ''
    runtime = '' if spec.read_only else ' **[runtime]**'
    return f'| `{spec.name}` | `{show(spec.default)}` | {spec.description}{choices}{runtime} |'


def _yaml_float(value: float) -> str:
    """Shortest exact text of ``value`` that YAML 1.1 (PyYAML, rcl) reads as a float: always
    with a decimal point, large values in scientific notation."""
    text = repr(value)
    if abs(value) >= 1e7 and 'e' not in text:
        mantissa, exponent = f'{value:.15e}'.split('e')
        text = f"{mantissa.rstrip('0')}e{exponent}"
    if 'e' in text:
        mantissa, exponent = text.split('e')
        text = f"{mantissa if '.' in mantissa else mantissa + '.0'}e{exponent}"
        if mantissa.endswith('.'):
            text = f'{mantissa}0e{exponent}'
    return text


def _yaml_value(value) -> str:
    if isinstance(value, bool):
        return 'true' if value else 'false'
    if isinstance(value, float):
        return _yaml_float(value)
    if isinstance(value, list):
        return '[' + ', '.join(_yaml_value(v) for v in value) + ']'
    if isinstance(value, str):
        return f"'{value}'" if value == '' else value
    return str(value)


#: The files in config/: name -> (header, estimator overrides).
CONFIG_FILES = {
    'rendezvous.yaml': (
        "the paper's rendezvous scenario (Sec. 3.2, Table 6) with this package's numerical "
        'defaults and a filter that does not know the truth (dispersed start).',
        {'initial_state_dispersion': True}),
    'rendezvous_as_published.yaml': (
        'the rendezvous scenario with the network exactly as Table 6 gives it: no state scaling, '
        'forward-Euler steps, the estimate starting at the truth. Expect ~0.1 m of spike quantisation.',
        {'state_scale': [1.0] * 6, 'discretization': 'euler', 'initial_state_dispersion': False}),
}


def sensor_overlay(name: str) -> str:
    """config/sensor_<name>.yaml: the suite's values, to load after config/rendezvous.yaml and,
    for a suite of another scenario (registry.SCENARIOS), that scenario's file."""
    scenario = next((s for s, entry in registry.SCENARIOS.items() if name in entry.sensors), None)
    if scenario is None:
        raise ValueError(f'sensor suite {name!r} is flown by no scenario of registry.SCENARIOS; add it to one')
    after = () if scenario == 'rendezvous' else (f'scenario_{scenario}.yaml',)
    return _overlay(f'the {name} sensor suite instead of the position sensor (docs/sensors.md)', 'sensor_suites',
                    f'sensor_{name}.yaml', sensor_suites()[name], after)


def scenario_overlay(name: str) -> str:
    """config/scenario_<name>.yaml: the scenario's values, to load after config/rendezvous.yaml."""
    return _overlay(f'the {name} scenario (snn_demo --scenario {name}; docs/decisions.md, 67-69)', 'scenarios',
                    f'scenario_{name}.yaml', scenarios()[name])


def _overlay(title: str, source: str, file_name: str, nodes: dict, after=()) -> str:
    files = ' '.join(f'--params-file config/{name}' for name in ('rendezvous.yaml', *after, file_name))
    out = [f'# snn_rendezvous: {title}.',
           f"# Generated from scenario_nodes/parameter_tables.py ({source}). Load it after the scenario "
           f"file{'s' if after else ''}:",
           f'#   --ros-args {files}',
           '']
    for node, values in nodes.items():
        out.extend([f'/**/{node}:', '  ros__parameters:'])
        specs = {spec.name: spec for spec in tables.NODES.get(node, SENSOR)}  # a renamed sensor: SENSOR's
        for key, value in values.items():
            spec = specs.get(key) or {s.name: s for s in sensor_input_specs(key.rpartition('.')[0])}[key]
            out.extend(f'    # {line}' for line in textwrap.wrap(spec.description, 92))
            out.append(f'    {key}: {_yaml_value(value)}')
        out.append('')
    return '\n'.join(out)


def yaml_document(header: str, estimator_overrides: dict) -> str:
    """A parameter file for all nodes, every parameter commented (generated from the tables)."""
    out = [f'# snn_rendezvous: {header}',
           '# Generated from scenario_nodes/parameter_tables.py (python -m snn_tools.run.parameter_files --write).',
           '# Use with: ros2 run snn_rendezvous <node> --ros-args --params-file <this file>',
           '# Matrices are flat lists: 1 value = scalar x identity, n values = diagonal, n*n = row-major.',
           '# [runtime] parameters can be changed while running (ros2 param set); the others are read',
           '# at start-up.', '']

    def block(section: str, specs, extra: dict, skip=()):
        if not extra and all(spec.name in skip for spec in specs):
            return  # nothing of its own: an empty ros__parameters is a parse error for rcl
        out.extend([f'{section}:', '  ros__parameters:'])
        for name, (comment, value) in extra.items():
            out.append(f'    # {comment}')
            out.append(f'    {name}: {_yaml_value(value)}')
        for spec in specs:
            if spec.name in skip:
                continue
            runtime = ' [runtime]' if not spec.read_only else ''
            choices = f" ({' | '.join(spec.choices)})" if spec.choices else ''
            for line in textwrap.wrap(spec.description + choices + runtime, 92):
                out.append(f'    # {line}')
            value = estimator_overrides.get(spec.name, spec.default) if specs is ESTIMATOR else spec.default
            if value != spec.default:
                out.append(f'    # (this file; the default is {_yaml_value(spec.default)})')
            prefix = '# ' if value is None else ''
            out.append(f'    {prefix}{spec.name}: {_yaml_value(value if value is not None else [])}')
        out.append('')

    block('/**', MODEL, {'use_sim_time': ('stamps from /clock, which the plant publishes', True)})
    shared = {spec.name for spec in MODEL}
    for node, specs in tables.NODES.items():
        extra = ({'use_sim_time': ('the plant is the clock: it must not follow /clock itself', False)}
                 if node.endswith('_plant') else {})
        block(f'/**/{node}', specs, extra, skip=shared)
    return '\n'.join(out)


PARAMETERS_DOC = """\
# Parameters

Generated from `scenario_nodes/parameter_tables.py` (`python -m snn_tools.run.parameter_files
--write`; a test fails when this file, config/rendezvous.yaml or
config/rendezvous_as_published.yaml is stale). Every parameter is declared with a descriptor
carrying this text and its range (`ros2 param describe /estimator leak_rate`). Matrices are flat
lists: 1 value = scalar x I, n values = diagonal, n x n values = row-major. **[runtime]**
parameters may be changed while running (`ros2 param set`): they are validated and applied
between two steps, or refused with a reason and nothing changes. The others are read at start-up
(the estimator: at configure); an invalid value makes the node exit with code 2 (the estimator:
fails `configure`) with a message that names the parameter and the fix.

"""


def generated_files() -> dict[Path, str]:
    """Every file generated from the tables, with its content."""
    files = {SOURCE_ROOT / 'config' / name: yaml_document(*spec) for name, spec in CONFIG_FILES.items()}
    files.update({SOURCE_ROOT / 'config' / f'sensor_{name}.yaml': sensor_overlay(name) for name in sensor_suites()})
    files.update({SOURCE_ROOT / 'config' / f'scenario_{name}.yaml': scenario_overlay(name) for name in scenarios()})
    files[SOURCE_ROOT / 'docs' / 'parameters.md'] = PARAMETERS_DOC + markdown()
    for name in registry.executables():  # ros2 run entry points of a pip install (setup.py)
        files[SOURCE_ROOT / 'wrappers' / name] = WRAPPER.format(name=name)
    return files



def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description='Print the parameter tables, or --write the generated '
                                                 'files (config/*.yaml, docs/parameters.md, wrappers/).')
    parser.add_argument('--write', action='store_true')
    args = parser.parse_args(argv)
    if not args.write:
        print(markdown())
        return 0
    for path, content in generated_files().items():
        if not path.exists() or path.read_text() != content:
            path.write_text(content)
            if path.parent.name == 'wrappers':
                path.chmod(0o755)
            print(f'wrote {path}')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
