"""The package's executables, listed once: every node (name, module, parameter table, place in
the start order) and the tools. setup.py (console scripts), scenario_nodes.parameter_tables (which
table each node section of the YAML files and docs/parameters.md holds), the launch file,
snn_tools.run.demo and the ros2-run wrappers in wrappers/ (test_packaging keeps them in step) all
read this. A new node is its file plus one entry here.

Standard library only: setup.py reads this file before anything is installed.
"""

from typing import NamedTuple


class NodeEntry(NamedTuple):
    """One node executable."""

    name: str         # executable, node name and parameter-file section
    module: str       # module whose main() runs it
    parameters: str   # its table in scenario_nodes.parameter_tables.TABLES
    start: int        # start order of the demo and the launch: consumers first, the plant last
    plant: str = ''   # a truth plant: the --plant / plant:= choice that selects it
    optional: bool = False  # started only when asked (snn_demo --live-view, live_view:=true)


#: In the order the YAML files and docs/parameters.md list them.
NODES = (
    NodeEntry('cw_plant', 'scenario_nodes.plant_node', 'PLANT', 4, plant='cw'),
    NodeEntry('basilisk_plant', 'scenario_nodes.basilisk_plant_node', 'BASILISK_PLANT', 4, plant='basilisk'),
    NodeEntry('position_sensor', 'scenario_nodes.sensor_node', 'SENSOR', 3),
    NodeEntry('lqr_controller', 'scenario_nodes.controller_node', 'CONTROLLER', 1),
    NodeEntry('estimator', 'scenario_nodes.estimator_node', 'ESTIMATOR', 2),
    NodeEntry('recorder', 'scenario_nodes.recorder_node', 'RECORDER', 0),
    NodeEntry('live_view', 'scenario_nodes.live_view_node', 'LIVE_VIEW', 0, optional=True),
)

#: Console scripts that are not nodes: name -> module:function.
TOOLS = {
    'report': 'snn_tools.bags.report:main',
    'snn_demo': 'snn_tools.run.demo:main',
    'snn_experiments': 'snn_tools.experiments.tables:main',
    'snn_bench': 'snn_tools.bench.steps:main',
    'snn_loop_bench': 'snn_tools.bench.loop:main',
    'snn_latency_bench': 'snn_tools.bench.latency:main',
    'snn_export': 'snn_tools.neuromorphic.nir_export:main',
    'snn_neuromorphic': 'snn_tools.neuromorphic.tables:main',
    'snn_campaign': 'snn_tools.campaign.run:main',
    'snn_campaign_bench': 'snn_tools.bench.campaign:main',
}

#: The truth plants: choice -> node name.
PLANTS = {entry.plant: entry.name for entry in NODES if entry.plant}
#: The nodes of one closed loop (the plant chosen separately), in start order.
LOOP = tuple(entry for entry in sorted(NODES, key=lambda entry: entry.start)
             if not entry.plant and not entry.optional)
#: The nodes started only when asked for.
OPTIONAL = tuple(entry for entry in NODES if entry.optional)


def executables() -> dict:
    """Console script name -> ``module:function`` (setup.py's entry points)."""
    return {**{entry.name: f'{entry.module}:main' for entry in NODES}, **TOOLS}


def node(name: str) -> NodeEntry:
    for entry in NODES:
        if entry.name == name:
            return entry
    raise ValueError(f'unknown node {name!r}; choose one of {", ".join(e.name for e in NODES)}')

