"""Layers that point one way: the core (snn_estimator) imports neither ROS nor matplotlib nor
the tools, the ROS layer (scenario_nodes) not the tools, no package has an import cycle, and the
nodes other than the estimator start without loading numba."""

import ast
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ('snn_estimator', 'scenario_nodes', 'snn_tools')
#: Top-level names each layer must not import (directly or in a function).
FORBIDDEN = {
    'snn_estimator': {'rclpy', 'rosbags', 'matplotlib', 'scenario_nodes', 'snn_tools', 'geometry_msgs',
                      'nav_msgs', 'std_msgs', 'diagnostic_msgs', 'rosgraph_msgs', 'lifecycle_msgs'},
    'scenario_nodes': {'matplotlib', 'snn_tools', 'dask', 'nir', 'brian2'},
}


def imports(path: Path, package: str, top_level_only: bool) -> set[str]:
    """Absolute names of the modules ``path`` imports (relative imports resolved)."""
    tree = ast.parse(path.read_text())
    nodes = tree.body if top_level_only else list(ast.walk(tree))
    names = set()
    for node in nodes:
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:  # from . import x / from .module import y, inside ``package``
                base = package if node.module is None else f'{package}.{node.module}'
                if node.module is None:
                    names.update(f'{package}.{alias.name}' for alias in node.names)
                else:
                    names.add(base)
            else:
                names.add(node.module)
    return names


def modules(package: str) -> dict[str, Path]:
    """Module name -> file, for ``package`` and its sub-packages (snn_estimator.gains)."""
    found = {}
    for path in sorted((ROOT / package.replace('.', '/')).rglob('*.py')):
        parts = path.relative_to(ROOT).with_suffix('').parts
        found['.'.join(parts[:-1] if parts[-1] == '__init__' else parts)] = path
    return {name: path for name, path in found.items() if name != package}


def package_of(name: str, path: Path) -> str:
    """The package a module's relative imports resolve in."""
    return name if path.stem == '__init__' else name.rpartition('.')[0]


@pytest.mark.parametrize('package', sorted(FORBIDDEN))
def test_a_layer_imports_nothing_of_the_layers_above_it(package):
    offending = {name: sorted(n for n in imports(path, package_of(name, path), top_level_only=False)
                              if n.split('.')[0] in FORBIDDEN[package])
                 for name, path in modules(package).items()}
    assert {name: found for name, found in offending.items() if found} == {}


@pytest.mark.parametrize('package', PACKAGES)
def test_no_package_has_an_import_cycle(package):
    own = modules(package)
    graph = {name: {n for n in imports(path, package_of(name, path), top_level_only=True) if n in own}
             for name, path in own.items()}
    state = {}

    def visit(name, trail):
        if state.get(name) == 'done':
            return
        assert state.get(name) != 'open', f"import cycle: {' -> '.join(trail + [name])}"
        state[name] = 'open'
        for target in sorted(graph[name]):
            visit(target, trail + [name])
        state[name] = 'done'

    for name in sorted(graph):
        visit(name, [])


#: What each folder of the core may import at module level (its ``__init__`` says the same):
#: the foundation (models, schema, config, defaults, validation, catalog) sits at the bottom;
#: the runners the nodes wrap (loop) never load the offline simulator.
FOLDER_IMPORTS = {
    'foundation': {'foundation', 'gains'},
    'gains': {'gains'},
    'measurements': {'foundation', 'measurements'},
    'spiking': {'foundation', 'gains', 'spiking'},
    'filters': {'foundation', 'gains', 'measurements', 'spiking', 'filters'},
    'loop': {'foundation', 'gains', 'measurements', 'spiking', 'filters', 'loop'},
    'offline': {'foundation', 'gains', 'measurements', 'spiking', 'filters', 'offline'},
}


def folder_of(module: str) -> str:
    parts = module.split('.')
    return parts[1] if len(parts) > 2 or parts[1] in FOLDER_IMPORTS else 'foundation'


def test_each_folder_of_the_core_imports_only_the_folders_below_it():
    core = modules('snn_estimator')
    assert {folder_of(name) for name in core} == set(FOLDER_IMPORTS)
    offending = {}
    for name, path in core.items():
        allowed = FOLDER_IMPORTS[folder_of(name)]
        found = {n for n in imports(path, package_of(name, path), top_level_only=True)
                 if n.startswith('snn_estimator.') and n in core and folder_of(n) not in allowed}
        if found:
            offending[name] = sorted(found)
    assert offending == {}
    for package in FOLDER_IMPORTS.keys() - {'foundation'}:
        assert (ROOT / 'snn_estimator' / package / '__init__.py').read_text().startswith('"""'), package


def test_the_gain_laws_import_only_numpy_scipy_and_each_other():
    """snn_estimator/gains/__init__.py: a law never imports numba (the kernels compile its
    piece), the filters, the models or anything outside the core."""
    allowed = {'numpy', 'scipy', 'math', 'importlib', 'pkgutil', 'functools', 'typing', '__future__'}
    laws = modules('snn_estimator.gains')
    assert {'snn_estimator.gains.kalman', 'snn_estimator.gains.msif', 'snn_estimator.gains.fixed'} <= set(laws)
    for name, path in laws.items():
        for imported in imports(path, package_of(name, path), top_level_only=False):
            assert imported.split('.')[0] in allowed or imported.startswith('snn_estimator.gains'), (name, imported)


def loaded_by(statement: str) -> set[str]:
    """Top-level packages a fresh interpreter has loaded after ``statement``."""
    code = f'import sys; {statement}; print(" ".join(sorted({{m.split(".")[0] for m in sys.modules}})))'
    result = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True, cwd=ROOT,
                            timeout=120)
    assert result.returncode == 0, result.stderr
    return set(result.stdout.split())


def test_importing_the_core_loads_no_ros_no_plotting_and_no_compiler():
    assert loaded_by('import snn_estimator') & {'rclpy', 'matplotlib', 'numba', 'control', 'scipy'} == set()
    assert 'numba' not in loaded_by('from snn_estimator import gains, catalog; gains.laws()')


@pytest.mark.parametrize('node', ['recorder_node', 'sensor_node', 'controller_node', 'plant_node'])
def test_the_nodes_around_the_estimator_start_without_numba_or_plotting(node):
    pytest.importorskip('rclpy')
    loaded = loaded_by(f'import scenario_nodes.{node}')
    assert 'rclpy' in loaded and loaded & {'numba', 'matplotlib', 'control', 'snn_tools'} == set()


def test_no_function_over_60_lines_no_class_over_300_and_short_kernel_argument_lists():
    """Issue 21's limits, in the core and the nodes: a function fits a screen, a class is one
    idea, and a compiled kernel takes packed tuples (about ten arguments at most)."""
    too_long = []
    for package in ('snn_estimator', 'scenario_nodes'):
        for name, path in modules(package).items():
            for node in ast.walk(ast.parse(path.read_text())):
                size = getattr(node, 'end_lineno', 0) - getattr(node, 'lineno', 0) + 1
                if isinstance(node, ast.FunctionDef):
                    arguments = len(node.args.args) + len(node.args.kwonlyargs)
                    kernel = package == 'snn_estimator' and node.name.endswith('_template')
                    if size > 60 or kernel and arguments > 10:
                        too_long.append((name, node.name, size, arguments))
                elif isinstance(node, ast.ClassDef) and size > 300:
                    too_long.append((name, node.name, size))
    assert too_long == []


def test_the_fire_kernel_takes_the_step_kernels_network_tuple():
    from snn_estimator import make_estimator
    from snn_estimator.filters import kernels

    network = make_estimator('snn_ekf')._network
    assert [id(a) for a in network.kernel_tuple()] == [id(network.arrays[name]) for name, _ in kernels.NETWORK]


def test_the_tests_the_fast_tier_skips_exist_under_their_names():
    """conftest's EXHAUSTIVE and LONG name test functions; a renamed test would silently move
    back into make test-fast."""
    import conftest
    sources = ''.join(path.read_text() for path in Path(__file__).parent.glob('test_*.py'))
    missing = [name for name in conftest.EXHAUSTIVE | conftest.LONG if f'def {name}(' not in sources]
    assert not missing, missing
