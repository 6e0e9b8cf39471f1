"""In-process ROS helpers: isolated contexts, parameters from config/, bounded spinning."""

from __future__ import annotations

import contextlib
import time
from pathlib import Path

import rclpy
import yaml
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter

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


def make(node_class, context, executor, nodes, name: str, start: bool = True, **changes):
    """Build a node as run_node does: parameters from config/ with ``changes``, added to the
    executor, then ``start()`` (a managed node configures and activates itself)."""
    node = node_class(context=context, parameter_overrides=overrides(name, **changes))
    executor.add_node(node)
    nodes.append(node)
    if start:
        node.start()
    return node


def spin_until(executor, predicate, timeout: float = 20.0) -> bool:
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            return False
        executor.spin_once(timeout_sec=0.02)
    return True
