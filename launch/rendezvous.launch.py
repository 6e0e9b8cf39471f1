"""Closed-loop rendezvous: plant, position_sensor, lqr_controller, estimator (and a recorder).

    ros2 launch snn_rendezvous rendezvous.launch.py estimator:=snn_emsif_weighted mode:=realtime
    ros2 launch snn_rendezvous rendezvous.launch.py params_file:=/path/to/my.yaml record:=true
    ros2 launch snn_rendezvous rendezvous.launch.py plant:=basilisk   # Basilisk truth (J2)
    ros2 launch snn_rendezvous rendezvous.launch.py keep_alive:=true  # stay up after the scenario
    ros2 launch snn_rendezvous rendezvous.launch.py live_view:=true   # Foxglove: ws://localhost:8765

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
from launch.conditions import IfCondition
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
PLANTS = registry.PLANTS


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
    """The nodes, with ``scheduling``, ``--launch-prefix``, the plant and the end of the launch
    resolved: with batch each runs as ``chrt --batch 0 [launch-prefix] <executable>``."""
    params = LaunchConfiguration('params_file')
    namespace = LaunchConfiguration('namespace')
    prefix = None  # launch's own --launch-prefix handling
    if LaunchConfiguration('scheduling').perform(context) == 'batch':
        user_prefix = LaunchConfiguration('launch-prefix', default='').perform(context)
        prefix = f'chrt --batch 0 {user_prefix}'.strip()
    end_with_plant = LaunchConfiguration('keep_alive').perform(context) != 'true'
    plant_name = PLANTS[LaunchConfiguration('plant').perform(context)]
    estimator = LaunchConfiguration('estimator').perform(context)

    def node(executable, extra=None, **kwargs):
        return Node(package=PACKAGE, executable=executable, name=executable, exec_name=executable,
                    namespace=namespace, parameters=[params] + ([extra] if extra else []),
                    output='screen', prefix=prefix, **kwargs)

    plant_params = {
        'mode': LaunchConfiguration('mode'), 'exit_when_done': end_with_plant,
        # typed: launch would pass real_time_factor:=10 as an integer, which a DOUBLE refuses
        'real_time_factor': ParameterValue(LaunchConfiguration('real_time_factor'), value_type=float)}
    optional = [name for name in ('record', 'live_view')
                if LaunchConfiguration(name).perform(context).lower() in ('true', '1')]
    if optional:  # the first state waits for the sensor and each of these on 'truth' (the recorder
        # subscribes last, once it hears the loop: counted, it is sure to record the start)
        plant_params['min_truth_subscribers'] = 1 + len(optional)
    plant = node(plant_name, plant_params)
    extra = {'estimator': {'filter_type': estimator} if estimator else None}
    if 'record' in optional:  # the sensor's publisher matches estimator, controller and recorder first
        extra['position_sensor'] = {'min_measurement_subscribers': 3}  # (decisions.md, 33)
    # the controller's controls reach the estimator, the plant and the optional nodes before it
    # subscribes to estimates, and the estimates the controller and those before the estimator
    # subscribes to measurements: the plant starts with every link matched (decisions.md, 41)
    extra['lqr_controller'] = {'min_control_subscribers': 2 + len(optional)}
    extra['estimator'] = {**(extra['estimator'] or {}), 'min_estimate_subscribers': 1 + len(optional)}
    options = {'recorder': {'condition': IfCondition(LaunchConfiguration('record'))},
               'live_view': {'condition': IfCondition(LaunchConfiguration('live_view'))}}
    actions = [node(entry.name, extra.get(entry.name), **options.get(entry.name, {}))
               for entry in registry.LOOP + registry.OPTIONAL]
    if DDS_PROFILE_VARIABLE not in os.environ:  # the package's Fast DDS profile (docs/decisions.md, 38)
        actions.insert(0, SetEnvironmentVariable(DDS_PROFILE_VARIABLE, PathJoinSubstitution(
            [FindPackageShare(PACKAGE), 'config', 'fastdds.xml'])))
    actions.append(plant)  # the registry's start order: consumers first, the plant last
    if end_with_plant:
        actions.append(RegisterEventHandler(OnProcessExit(
            target_action=plant,
            on_exit=[EmitEvent(event=Shutdown(reason='the plant has flown the scenario'))])))
    return actions
