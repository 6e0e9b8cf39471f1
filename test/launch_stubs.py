"""The launch file run against stand-ins for launch/launch_ros (not installable from PyPI): what
it would start, readable as plain data."""

import sys
import types
from pathlib import Path

LAUNCH_FILE = Path(__file__).resolve().parents[1] / 'launch' / 'rendezvous.launch.py'


class Config(tuple):
    """LaunchConfiguration stand-in: compares as ('config', name, default), performs from a dict."""

    def perform(self, context):
        return context.get(self[1], self[2])


def load_launch_file(monkeypatch) -> tuple[dict, dict]:
    """Execute the launch file with the stand-ins in ``sys.modules``; return its namespace and
    ``created``: kind ('node', 'argument', 'handler', ...) -> the stand-in actions made so far,
    each with the ``args`` and ``kwargs`` it was made with."""
    created = {}

    def recorder(kind):
        class Action:
            def __init__(self, *args, **kwargs):
                self.args, self.kwargs = args, kwargs
                created.setdefault(kind, []).append(self)
        return Action

    stubs = {
        'launch': {'LaunchDescription': lambda actions: actions},
        'launch.actions': {'DeclareLaunchArgument': recorder('argument'),
                           'OpaqueFunction': recorder('opaque'), 'EmitEvent': recorder('emit'),
                           'RegisterEventHandler': recorder('handler'),
                           'SetEnvironmentVariable': recorder('environment')},
        'launch.event_handlers': {'OnProcessExit': recorder('on_exit')},
        'launch.events': {'Shutdown': recorder('shutdown')},
        'launch.substitutions': {'LaunchConfiguration': lambda name, default=None: Config(('config', name, default)),
                                 'PathJoinSubstitution': lambda parts: ('join', tuple(parts))},
        'launch_ros.actions': {'Node': recorder('node')},
        'launch_ros.substitutions': {'FindPackageShare': lambda name: ('share', name)},
        'launch_ros.parameter_descriptions': {
            'ParameterValue': lambda value, value_type=None: ('typed', value, value_type)},
    }
    for name, members in stubs.items():
        module = types.ModuleType(name)
        module.__dict__.update(members)
        monkeypatch.setitem(sys.modules, name, module)
    namespace = {}
    exec(compile(LAUNCH_FILE.read_text(), str(LAUNCH_FILE), 'exec'), namespace)
    return namespace, created


#: The launch arguments' values of a plain `ros2 launch snn_rendezvous rendezvous.launch.py`.
DEFAULTS = {'keep_alive': 'false', 'plant': 'cw', 'estimator': '', 'record': 'false', 'live_view': 'false',
            'scheduling': 'normal', 'scenario': 'rendezvous', 'sensor': 'position'}


def launched_nodes(monkeypatch, **arguments) -> dict[str, dict]:
    """Node name -> the keyword arguments of its launch_ros Node, in the order the launch
    starts them, for the launch ``arguments`` (over :data:`DEFAULTS`)."""
    namespace, created = load_launch_file(monkeypatch)
    namespace['generate_launch_description']()
    created['node'] = []
    created['opaque'][0].kwargs['function'](dict(DEFAULTS, **arguments))
    return {node.kwargs['name']: node.kwargs for node in created['node']}
