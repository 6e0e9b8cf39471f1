"""The pipeline, described once: every executable, and for each node its module and class, its
parameter table, its place in the start order, the topics it publishes and subscribes to, and
the subscriber counts it waits for at start-up. setup.py (console scripts), the parameter
tables, the generated files (YAML, docs/parameters.md, the ros2-run wrappers), the launch file,
snn_demo and its single-process mode all read this. A new node is its file plus one entry here.

Standard library only (and the topic names beside it): setup.py reads this file before
anything is installed.
"""

from __future__ import annotations

from typing import Mapping, NamedTuple

from scenario_nodes.topics import (
    APPLIED_CONTROL,
    CLOCK,
    CONTROL,
    DIAGNOSTICS,
    ESTIMATE,
    GUIDANCE,
    MARKERS,
    MEASUREMENT,
    PIPELINE_TOPICS,
    SET_STATE,
    SPIKE_COUNT,
    SPIKES,
    TRUTH,
)


class NodeEntry(NamedTuple):
    """One node executable and its place in the pipeline. Topics are the relative names of
    scenario_nodes.topics (/clock, which every node but the plant follows, is not listed)."""

    name: str          # executable, node name and parameter-file section
    module: str        # module whose main() runs it
    node_class: str    # its Node class in that module (single-process mode builds it)
    parameters: str    # its table in scenario_nodes.parameter_tables.TABLES
    start: int         # start order: consumers first, the plant last
    publishes: tuple[str, ...] = ()
    subscribes: tuple[str, ...] = ()
    #: topics it publishes whose subscriptions it waits for before it starts (its input, or for
    #: the plant the scenario): parameter ``min_<topic>_subscribers`` (docs/decisions.md, 33 and 41)
    waits_for: tuple[str, ...] = ()
    plant: str = ''    # a truth plant: the --plant / plant:= choice that selects it
    optional: bool = False     # started only when asked (snn_demo --no-record / record:=true, live view)
    own_process: bool = False  # single-process mode still runs it as a process of its own


# `guidance` only with end_on_guidance (the approach)
_PLANT_TOPICS = dict(publishes=(TRUTH, APPLIED_CONTROL, CLOCK, DIAGNOSTICS), subscribes=(CONTROL, GUIDANCE),
                     waits_for=(TRUTH,))
#: In the order the YAML files and docs/parameters.md list them.
NODES = (
    NodeEntry('cw_plant', 'scenario_nodes.plant_node', 'PlantNode', 'PLANT', 4, plant='cw', **_PLANT_TOPICS),
    NodeEntry('basilisk_plant', 'scenario_nodes.basilisk_plant_node', 'BasiliskPlantNode', 'BASILISK_PLANT', 4,
              plant='basilisk', **_PLANT_TOPICS),
    NodeEntry('position_sensor', 'scenario_nodes.sensor_node', 'SensorNode', 'SENSOR', 3,
              publishes=(MEASUREMENT, DIAGNOSTICS), subscribes=(TRUTH,), waits_for=(MEASUREMENT,)),
    # the controller watches the measurements' stamps (safe mode when no sensor speaks); `guidance`
    # only with guidance approach
    NodeEntry('lqr_controller', 'scenario_nodes.controller_node', 'ControllerNode', 'CONTROLLER', 1,
              publishes=(CONTROL, DIAGNOSTICS, GUIDANCE), subscribes=(ESTIMATE, MEASUREMENT), waits_for=(CONTROL,)),
    # its liveliness monitor and history reader on `estimate` watch other estimators: not counted
    NodeEntry('estimator', 'scenario_nodes.estimator_node', 'EstimatorNode', 'ESTIMATOR', 2,
              publishes=(ESTIMATE, SPIKE_COUNT, SPIKES, DIAGNOSTICS),
              subscribes=(MEASUREMENT, CONTROL, APPLIED_CONTROL, SET_STATE), waits_for=(ESTIMATE,)),
    # subscribes to 'truth' last, once it hears the loop: counted, the plant waits for it
    NodeEntry('recorder', 'scenario_nodes.recorder_node', 'RecorderNode', 'RECORDER', 0,
              subscribes=PIPELINE_TOPICS, optional=True),
    NodeEntry('live_view', 'scenario_nodes.live_view_node', 'LiveViewNode', 'LIVE_VIEW', 0,
              publishes=(MARKERS,), subscribes=(TRUTH, ESTIMATE, CONTROL, SPIKE_COUNT, SPIKES),
              optional=True, own_process=True),
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

#: The sensor nodes of each sensor choice (snn_demo --sensor; the suites' parameter values are
#: scenario_nodes.parameter_tables.sensor_suites): the sensor node renamed, and its
#: `measurement` remapped to its name, when it is not the one sensor on `measurement`.
SENSOR_NODES = {'position': ('position_sensor',), 'lidar': ('position_sensor',), 'camera+lidar': ('camera', 'lidar'),
                'docking': ('lidar', 'camera'), 'by_range': ('relative_gps', 'lidar', 'camera'),
                'angles_far': ('far_camera', 'lidar', 'camera')}


class Scenario(NamedTuple):
    """What a scenario flies: its truth plants and sensor choices (a suite's values are for one
    scenario's time step and geometry). The values of scenarios other than the rendezvous are
    scenario_nodes.parameter_tables.scenarios, config/scenario_<name>.yaml."""

    plants: tuple[str, ...]
    sensors: tuple[str, ...]


#: The scenarios (snn_demo --scenario, the launch file's scenario:=): the rendezvous of Table 6 on
#: either plant and its suites; the approach on the cw plant node (its dynamics_model set), on the
#: position sensor, the approach's sensors by range or its angles-only far suite (docs/decisions.md,
#: 67, 80 and 81).
SCENARIOS = {'rendezvous': Scenario(('cw', 'basilisk'), ('position', 'lidar', 'camera+lidar', 'docking')),
             'approach': Scenario(('cw',), ('position', 'by_range', 'angles_far'))}


def check_scenario(scenario: str, plant: str, sensor: str) -> None:
    """ValueError naming the choices when ``scenario`` does not fly ``plant`` or ``sensor``."""
    if scenario not in SCENARIOS:
        raise ValueError(f"scenario must be one of {', '.join(SCENARIOS)}; got {scenario!r}")
    plants, sensors = SCENARIOS[scenario]
    if plant not in plants or sensor not in sensors:
        raise ValueError(f"the {scenario} scenario flies plant {' | '.join(plants)} and sensor "
                         f"{' | '.join(sensors)}; got plant {plant!r}, sensor {sensor!r}")


def executables() -> dict:
    """Console script name -> ``module:function`` (setup.py's entry points)."""
    return {**{entry.name: f'{entry.module}:main' for entry in NODES}, **TOOLS}


def node(name: str) -> NodeEntry:
    for entry in NODES:
        if entry.name == name:
            return entry
    raise ValueError(f'unknown node {name!r}; choose one of {", ".join(e.name for e in NODES)}')


def plants() -> dict[str, str]:
    """The truth plants: choice (--plant, plant:=) -> node name."""
    return {entry.plant: entry.name for entry in NODES if entry.plant}


def plant_node(choice: str) -> str:
    """The node name of the truth plant ``choice``."""
    choices = plants()
    if choice not in choices:
        raise ValueError(f'plant {choice!r}: expected one of {", ".join(choices)}')
    return choices[choice]


def optional_nodes() -> tuple[str, ...]:
    """The nodes started only when asked for."""
    return tuple(entry.name for entry in NODES if entry.optional)


class Started(NamedTuple):
    """One node of a run: its entry, its node name (a suite's sensors run the sensor executable
    under their own names) and its topic remappings."""

    entry: NodeEntry
    name: str
    remaps: tuple[str, ...] = ()


def pipeline(plant: str = 'cw', optional=(), sensor: str = 'position') -> tuple[Started, ...]:
    """The nodes of one run in start order (consumers first, the plant last): every node that is
    neither a plant nor optional, the ``plant`` chosen, the ``optional`` nodes named, and the
    sensor nodes of ``sensor`` (:data:`SENSOR_NODES`) in place of the sensor."""
    plant_name = plant_node(plant)
    unknown = set(optional) - set(optional_nodes())
    if unknown:
        raise ValueError(f'{", ".join(sorted(unknown))}: not an optional node; choose from '
                         f'{", ".join(optional_nodes())}')
    if sensor not in SENSOR_NODES:
        raise ValueError(f'sensor {sensor!r}: expected one of {", ".join(SENSOR_NODES)}')
    chosen = [entry for entry in NODES if entry.name == plant_name
              or not entry.plant and (not entry.optional or entry.name in optional)]
    started = []
    for entry in sorted(chosen, key=lambda entry: entry.start):
        if MEASUREMENT not in entry.publishes:
            started.append(Started(entry, entry.name))
            continue
        for name in SENSOR_NODES[sensor]:  # each on its own topic, named after it
            started.append(Started(entry, name, () if name == entry.name else (f'{MEASUREMENT}:={name}',)))
    return tuple(started)


def count_parameter(topic: str) -> str:
    """The parameter that holds a node until ``topic`` has that many subscriptions."""
    return f'min_{topic}_subscribers'


def subscriber_counts(started, listeners: Mapping[str, int] | None = None) -> dict[str, dict[str, int]]:
    """Node name -> {``min_<topic>_subscribers``: count} for every topic it waits for: the other
    nodes of ``started`` that subscribe to that topic, plus ``listeners`` (topic -> subscribers
    outside the pipeline, e.g. a latency probe, so that they cannot stand in for a node of the
    loop). A suite's sensors publish on their own topics, to which every node subscribing to
    `measurement` subscribes (its ``sensors`` or ``measurement_topics``), so counts go by the
    topic the entries name."""
    listeners = listeners or {}
    return {node.name: {count_parameter(topic): listeners.get(topic, 0) + sum(
        topic in other.entry.subscribes for other in started if other is not node)
        for topic in node.entry.waits_for} for node in started if node.entry.waits_for}
