"""Closed-loop rendezvous: plant, position_sensor, lqr_controller, estimator (and a recorder, a
live view): the nodes, their start order and subscriber counts of scenario_nodes.registry.

    ros2 launch snn_rendezvous rendezvous.launch.py estimator:=snn_emsif_weighted mode:=realtime
    ros2 launch snn_rendezvous rendezvous.launch.py params_file:=/path/to/my.yaml record:=true
    ros2 launch snn_rendezvous rendezvous.launch.py plant:=basilisk   # Basilisk truth (J2)
    ros2 launch snn_rendezvous rendezvous.launch.py keep_alive:=true  # stay up after the scenario
    ros2 launch snn_rendezvous rendezvous.launch.py live_view:=true   # Foxglove: ws://localhost:8765
    ros2 launch snn_rendezvous rendezvous.launch.py sensor:=docking   # a sensor node per sensor
    ros2 launch snn_rendezvous rendezvous.launch.py scenario:=approach sensor:=by_range  # 5 km to contact
    ros2 launch snn_rendezvous rendezvous.launch.py scenario:=approach sensor:=angles_far  # angles only far out

Each node is its own process; swapping the estimator is only the `estimator` argument. When
the plant has flown the scenario it exits and the launch shuts the others down (the recorder
closes its bag on the way), unless keep_alive:=true.
"""

import os

from launch.actions import (
    DeclareLaunchArgument,
    EmitEvent,
    OpaqueFunction,
    RegisterEventHandler,
    SetEnvironmentVariable,
)
from launch.event_handlers import OnProcessExit
from launch.events import Shutdown
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution
from launch_ros.actions import Node
from launch_ros.parameter_descriptions import ParameterValue
from launch_ros.substitutions import FindPackageShare

from launch import LaunchDescription
from scenario_nodes import registry
from snn_estimator.catalog import FILTER_KINDS

PACKAGE = 'snn_rendezvous'
DDS_PROFILE_VARIABLE = 'FASTRTPS_DEFAULT_PROFILES_FILE'
FILTERS = ' | '.join(FILTER_KINDS)
PLANTS = registry.plants()
#: Launch arguments that start an optional node: argument -> node.
OPTIONAL_ARGUMENTS = {'record': 'recorder', 'live_view': 'live_view'}


def generate_launch_description():
    arguments = [
        DeclareLaunchArgument(
            'estimator', default_value='',
            description=f'filter_type of the estimator: {FILTERS} (empty: the parameter file\'s)'),
        DeclareLaunchArgument(
            'params_file',
            default_value=PathJoinSubstitution([FindPackageShare(PACKAGE), 'config', 'rendezvous.yaml']),
            description='Parameter file for all nodes (default: the paper scenario, Table 6)'),
        DeclareLaunchArgument(
            'scenario', default_value='rendezvous', choices=list(registry.SCENARIOS),
            description='rendezvous (Table 6: params_file alone) | approach (5 km behind on V-bar to contact '
                        'through the holds, the cw plant on the nonlinear truth: config/scenario_approach.yaml '
                        'after params_file, as snn_demo --scenario approach; docs/decisions.md, 67)'),
        DeclareLaunchArgument(
            'sensor', default_value='position', choices=list(registry.SENSOR_NODES),
            description="position (Table 6's sensor) | a sensor suite, one node per sensor, each on its own "
                        'topic: config/sensor_<suite>.yaml after the scenario\'s files (docs/sensors.md). '
                        'The rendezvous flies lidar, camera+lidar, docking; the approach by_range (relative '
                        'GPS, the LIDAR, the docking camera) and angles_far (a far camera measuring angles '
                        'only, the LIDAR, the docking camera; the guidance flies an out-of-plane hop)'),
        DeclareLaunchArgument(
            'plant', default_value='cw', choices=list(PLANTS),
            description='Truth: cw (the Clohessy-Wiltshire model the filters use) | basilisk '
                        '(Basilisk orbits with J2 and thrust limits; needs the basilisk extra)'),
        DeclareLaunchArgument(
            'mode', default_value='lockstep',
            description='plant mode: lockstep (as fast as the loop allows) | realtime'),
        DeclareLaunchArgument(
            'real_time_factor', default_value='1.0',
            description='realtime mode: simulated seconds per wall-clock second'),
        DeclareLaunchArgument('namespace', default_value='', description='Namespace of all nodes'),
        DeclareLaunchArgument(
            'record', default_value='false',
            description='Also start the recorder (rosbag2 MCAP in ./bag_<date-time>)'),
        DeclareLaunchArgument(
            'live_view', default_value='false', choices=['true', 'false'],
            description='Also start live_view: the scene and plots over Foxglove\'s WebSocket protocol '
                        '(ws://localhost:8765; needs the live extra) and a MarkerArray on markers (RViz)'),
        DeclareLaunchArgument(
            'keep_alive', default_value='false', choices=['true', 'false'],
            description='true: keep every node up after the plant has flown the scenario; false: the '
                        'plant exits and the launch shuts down'),
        DeclareLaunchArgument(
            'scheduling', default_value='normal', choices=['normal', 'batch'],
            description='batch: start every node under SCHED_BATCH (chrt --batch 0, Linux; a node '
                        'fails to start where the kernel refuses it), as snn_demo does: no wakeup '
                        'preemption, a faster lockstep loop on few cores'),
    ]
    return LaunchDescription(arguments + [OpaqueFunction(function=_nodes)])


def _nodes(context):
    """The nodes of the pipeline description (scenario_nodes.registry) for the plant, the sensor
    choice and the optional nodes asked for, in its start order (the plant last), each with
    the parameter files of the scenario and the sensor choice (:func:`_parameter_files`) and the subscriber
    counts it waits for (decisions.md, 33 and 41), with ``scheduling``, ``--launch-prefix`` and
    the end of the launch resolved: with batch each runs as ``chrt --batch 0 [launch-prefix]
    <executable>``."""
    params = LaunchConfiguration('params_file')
    namespace = LaunchConfiguration('namespace')
    prefix = None  # launch's own --launch-prefix handling
    if LaunchConfiguration('scheduling').perform(context) == 'batch':
        user_prefix = LaunchConfiguration('launch-prefix', default='').perform(context)
        prefix = f'chrt --batch 0 {user_prefix}'.strip()
    end_with_plant = LaunchConfiguration('keep_alive').perform(context) != 'true'
    plant = LaunchConfiguration('plant').perform(context)
    plant_name = registry.plant_node(plant)
    scenario, sensor = (LaunchConfiguration(name).perform(context) for name in ('scenario', 'sensor'))
    registry.check_scenario(scenario, plant, sensor)
    estimator = LaunchConfiguration('estimator').perform(context)
    optional = [node for argument, node in OPTIONAL_ARGUMENTS.items()
                if LaunchConfiguration(argument).perform(context).lower() in ('true', '1')]
    started = registry.pipeline(plant, optional, sensor)
    files = _parameter_files(params, scenario, sensor)
    extra = registry.subscriber_counts(started)
    extra[plant_name].update({
        'mode': LaunchConfiguration('mode'), 'exit_when_done': end_with_plant,
        # typed: launch would pass real_time_factor:=10 as an integer, which a DOUBLE refuses
        'real_time_factor': ParameterValue(LaunchConfiguration('real_time_factor'), value_type=float)})
    if estimator:
        extra.setdefault('estimator', {})['filter_type'] = estimator
    actions = [Node(package=PACKAGE, executable=node.entry.name, name=node.name, exec_name=node.name,
                    namespace=namespace, parameters=files + ([extra[node.name]] if node.name in extra else []),
                    remappings=[tuple(rule.split(':=')) for rule in node.remaps], output='screen', prefix=prefix)
               for node in started]
    plant_action = next(action for action, node in zip(actions, started) if node.name == plant_name)
    if DDS_PROFILE_VARIABLE not in os.environ:  # the package's Fast DDS profile (docs/decisions.md, 38)
        actions.insert(0, SetEnvironmentVariable(DDS_PROFILE_VARIABLE, PathJoinSubstitution(
            [FindPackageShare(PACKAGE), 'config', 'fastdds.xml'])))
    if end_with_plant:
        actions.append(RegisterEventHandler(OnProcessExit(
            target_action=plant_action,
            on_exit=[EmitEvent(event=Shutdown(reason='the plant has flown the scenario'))])))
    return actions


def _parameter_files(params, scenario: str, sensor: str) -> list:
    """params_file, then the package's config/scenario_<scenario>.yaml (not for the rendezvous,
    which is params_file's own), then config/sensor_<sensor>.yaml (not for position): each
    file's values win over the ones before, as snn_demo layers them."""
    extra = ([f'scenario_{scenario}.yaml'] if scenario != 'rendezvous' else []) + (
        [f'sensor_{sensor}.yaml'] if sensor != 'position' else [])
    return [params] + [PathJoinSubstitution([FindPackageShare(PACKAGE), 'config', name]) for name in extra]
