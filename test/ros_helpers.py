"""In-process ROS helpers: isolated contexts, parameters from config/, bounded spinning."""

from __future__ import annotations

import contextlib
import time
from pathlib import Path

import rclpy
import yaml
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import AccelStamped, PointStamped
from nav_msgs.msg import Odometry
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from std_msgs.msg import UInt32, UInt32MultiArray

from scenario_nodes import qos

CONFIG = Path(__file__).resolve().parents[1] / 'config' / 'rendezvous.yaml'


@contextlib.contextmanager
def ros_context():
    """A fresh rclpy context with its own executor; always shut down."""
    context = Context()
    rclpy.init(context=context)
    executor = SingleThreadedExecutor(context=context)
    nodes = []
    try:
        yield context, executor, nodes
    finally:
        for node in nodes:
            executor.remove_node(node)
            node.destroy_node()
        executor.shutdown()
        rclpy.try_shutdown(context=context)


def overrides(node: str, **changes) -> list[Parameter]:
    """The node's parameters from config/rendezvous.yaml with ``changes`` applied."""
    document = yaml.safe_load(CONFIG.read_text())
    values = dict(document['/**']['ros__parameters'])
    values.update(document.get(f'/**/{node}', {}).get('ros__parameters', {}))
    values.update(changes)
    return [Parameter(name, value=value) for name, value in values.items()]


def make(node_class, context, executor, nodes, name: str, start: bool = True, cli_args=None, **changes):
    """Build a node as run_node does: parameters from config/ with ``changes`` (and ``cli_args``,
    e.g. remappings), added to the executor, then ``start()`` (a managed node configures and
    activates itself)."""
    node = node_class(context=context, parameter_overrides=overrides(name, **changes), cli_args=cli_args)
    executor.add_node(node)
    nodes.append(node)
    if start:
        node.start()
    return node


def latest_status(arrays, name: str) -> dict:
    """The values of the newest status called ``name`` among received DiagnosticArrays."""
    for array in reversed(arrays):
        for status in array.status:
            if status.name == name:
                return {kv.key: kv.value for kv in status.values}
    return {}


def spin_until(executor, predicate, timeout: float = 20.0) -> bool:
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            return False
        executor.spin_once(timeout_sec=0.02)
    return True


class Probe:
    """A test node that publishes inputs and collects outputs of the pipeline topics."""

    def __init__(self, context, executor, nodes, publish=True, skip=()):
        from rclpy.node import Node
        self.node = Node('probe', context=context)
        executor.add_node(self.node)
        nodes.append(self.node)
        self.received = {name: [] for name in qos.PIPELINE_TOPICS}
        types = {qos.TRUTH: Odometry, qos.MEASUREMENT: PointStamped, qos.CONTROL: AccelStamped,
                 qos.ESTIMATE: Odometry, qos.SPIKE_COUNT: UInt32, qos.SPIKES: UInt32MultiArray,
                 qos.DIAGNOSTICS: DiagnosticArray}
        self.publishers = {}
        for topic, kind in types.items():
            if topic in skip:  # another type there (a sensor model's message): one process, one type
                continue
            self.node.create_subscription(kind, topic, self.received[topic].append, qos.LISTENER_QOS)
            if publish:
                self.publishers[topic] = self.node.create_publisher(kind, topic, qos.PUBLISHER_QOS)

    def publish(self, topic, msg):
        self.publishers[topic].publish(msg)

    def diagnostics(self, name):
        return latest_status(self.received[qos.DIAGNOSTICS], name)
