"""Counters every node keeps and reports on `diagnostics` (diagnostic_msgs/DiagnosticArray)."""

from __future__ import annotations

from collections import Counter

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus

from . import qos
from .conversions import diagnostic_status, ns_to_stamp


class Rejections(Counter):
    """Rejected inputs by reason, e.g. {'non_finite': 2, 'stale': 1}."""

    @property
    def total(self) -> int:
        return sum(self.values())

    def as_values(self, prefix: str) -> dict:
        values = {f'{prefix}_rejected': self.total}
        values.update({f'{prefix}_rejected.{reason}': count for reason, count in sorted(self.items())})
        return values


def diagnostic_array(stamp_ns: int, name: str, node_name: str, values: dict,
                     problems: list[str] | None = None, level: int = 0) -> DiagnosticArray:
    """One status named ``name``; WARN with the problems listed when there are any, or
    ``level`` (0 OK, 1 WARN, 2 ERROR: a peer gone) if higher."""
    level = max(int(level), 1 if problems else 0)
    level = (DiagnosticStatus.OK, DiagnosticStatus.WARN, DiagnosticStatus.ERROR)[min(level, 2)]
    message = '; '.join(problems) if problems else 'OK'
    array = DiagnosticArray()
    array.header.stamp = ns_to_stamp(stamp_ns)
    array.status = [diagnostic_status(name, node_name, level, message, values)]
    return array


class DiagnosticsPublisher:
    """Publishes one node's status on `diagnostics` at most every ``period`` simulated seconds.
    The node's incompatible-QoS counts (``events``) go into every status."""

    def __init__(self, node, name: str, period: float, events: qos.QosEvents, lifecycle: bool = False,
                 peers=None):
        self._node = node
        self.peers = peers  # a snn_estimator.runners.peers.PeerWatch: its levels go into every status
        self._name = name
        self._events = events
        self._period_ns = int(round(period * 1e9))
        self._last_ns = None
        self.publisher = qos.publisher(node, events, DiagnosticArray, qos.DIAGNOSTICS, lifecycle=lifecycle)

    def due(self, stamp_ns: int) -> bool:
        """True for the first message, then once per period (every time for period 0)."""
        return (self._last_ns is None or self._period_ns <= 0
                or stamp_ns - self._last_ns >= self._period_ns)

    def publish(self, stamp_ns: int, values: dict, problems: list[str] | None = None) -> None:
        self._last_ns = stamp_ns
        values = dict(values, **self._events.values())
        problems = list(problems or [])
        level = 0
        if self.peers is not None:
            values.update(self.peers.values())
            problems += self.peers.problems()
            level = self.peers.level
        if self._events.incompatible:
            problems.append(f"incompatible QoS on {', '.join(sorted(self._events.incompatible))}")
        self.publisher.publish(diagnostic_array(
            stamp_ns, self._name, self._node.get_fully_qualified_name(), values, problems, level))

    def flush(self, timeout: float = 1.0) -> None:
        """Wait until subscribers acknowledged what was published (before the process exits)."""
        from rclpy.duration import Duration
        self.publisher.wait_for_all_acked(Duration(seconds=timeout))
