"""A node registered only in the tests (test_pipeline_description.py): one more subscriber of
`estimate`, so the estimator must wait for it however the pipeline is started. Its file plus
:data:`ENTRY` is all there is of it.

    python -m estimate_monitor --ros-args ...   (test/ on PYTHONPATH)
"""

from nav_msgs.msg import Odometry
from rclpy.node import Node

from scenario_nodes import qos, registry
from scenario_nodes.runtime import ProcessHooks, run_node
from scenario_nodes.topics import ESTIMATE

#: Its registry entry: a consumer, started before the loop; the shared parameters only.
ENTRY = registry.NodeEntry('estimate_monitor', 'estimate_monitor', 'EstimateMonitorNode', 'MODEL', 0,
                           subscribes=(ESTIMATE,))


def register() -> tuple:
    """The registry's nodes with this one (to set as ``registry.NODES``)."""
    return registry.NODES + (ENTRY,)


class EstimateMonitorNode(ProcessHooks, Node):
    """Counts the estimates it hears and says how many when it closes."""

    def __init__(self, **kwargs):
        super().__init__(ENTRY.name, **kwargs)
        self.heard = 0
        self.create_subscription(Odometry, ESTIMATE, self._on_estimate, qos.SUBSCRIPTION_QOS)

    def _on_estimate(self, msg: Odometry) -> None:
        self.heard += 1

    def close(self) -> None:
        self.get_logger().info(f'heard {self.heard} estimates')


def main(args=None) -> int:
    return run_node(EstimateMonitorNode, args, ENTRY.name)


if __name__ == '__main__':
    raise SystemExit(main())
