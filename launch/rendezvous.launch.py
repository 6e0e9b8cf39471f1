"""Closed-loop rendezvous: cw_plant, position_sensor, lqr_controller, estimator (and a recorder).

    ros2 launch snn_rendezvous rendezvous.launch.py estimator:=snn_ekf mode:=realtime
    ros2 launch snn_rendezvous rendezvous.launch.py params_file:=/path/to/my.yaml record:=true
    ros2 launch snn_rendezvous rendezvous.launch.py scheduling:=batch   # as snn_demo runs them

Each node is its own process; swapping the estimator is only the `estimator` argument.
"""

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.conditions import IfCondition
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution
from launch_ros.actions import Node
from launch_ros.parameter_descriptions import ParameterValue
from launch_ros.substitutions import FindPackageShare

PACKAGE = 'snn_rendezvous'


def generate_launch_description():
    arguments = [
        DeclareLaunchArgument(
            'estimator', default_value='snn_emsif',
            description='filter_type of the estimator: snn_emsif | snn_ekf | snn_emsif_star | emsif | ekf | esif'),
        DeclareLaunchArgument(
            'params_file',
            default_value=PathJoinSubstitution([FindPackageShare(PACKAGE), 'config', 'rendezvous.yaml']),
            description='Parameter file for all nodes (default: the paper scenario, Table 6)'),
        DeclareLaunchArgument(
            'mode', default_value='lockstep',
            description='cw_plant mode: lockstep (as fast as the loop allows) | realtime'),
        DeclareLaunchArgument(
            'real_time_factor', default_value='1.0',
            description='realtime mode: simulated seconds per wall-clock second'),
        DeclareLaunchArgument('namespace', default_value='', description='Namespace of all nodes'),
        DeclareLaunchArgument(
            'record', default_value='false',
            description='Also start the recorder (rosbag2 MCAP in ./bag_<date-time>)'),
        DeclareLaunchArgument(
            'scheduling', default_value='normal', choices=['normal', 'batch'],
            description='batch: start every node under SCHED_BATCH (chrt --batch 0, Linux; a node '
                        'fails to start where the kernel refuses it), as snn_demo does: no wakeup '
                        'preemption, a faster lockstep loop on few cores'),
    ]
    return LaunchDescription(arguments + [OpaqueFunction(function=_nodes)])


def _nodes(context):
    """The nodes, with ``scheduling`` and ``--launch-prefix`` resolved: with batch each runs as
    ``chrt --batch 0 [launch-prefix] <executable>``; otherwise launch applies its prefix as usual."""
    params = LaunchConfiguration('params_file')
    namespace = LaunchConfiguration('namespace')
    prefix = None  # launch's own --launch-prefix handling
    if LaunchConfiguration('scheduling').perform(context) == 'batch':
        user_prefix = LaunchConfiguration('launch-prefix', default='').perform(context)
        prefix = f'chrt --batch 0 {user_prefix}'.strip()

    def node(executable, extra=None, **kwargs):
        return Node(package=PACKAGE, executable=executable, name=executable, exec_name=executable,
                    namespace=namespace, parameters=[params] + ([extra] if extra else []),
                    output='screen', prefix=prefix, **kwargs)

    return [
        node('lqr_controller'),
        node('estimator', {'filter_type': LaunchConfiguration('estimator')}),
        node('position_sensor'),
        node('cw_plant', {'mode': LaunchConfiguration('mode'),
                          # typed: launch would pass real_time_factor:=10 as an integer,
                          # which a DOUBLE parameter refuses
                          'real_time_factor': ParameterValue(LaunchConfiguration('real_time_factor'),
                                                             value_type=float)}),
        node('recorder', condition=IfCondition(LaunchConfiguration('record'))),
    ]
