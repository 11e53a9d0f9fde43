"""A node's health on /diagnostics: counters of what it processed and what it rejected."""

from __future__ import annotations

from collections import Counter
from typing import Callable

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.node import Node

from sensing_nodes.ros.conversions import ns_to_stamp


class Diagnostics:
    """Counts named events and publishes them with a level and message on /diagnostics.

    The stamp is the newest input stamp seen, so a replayed bag yields the same diagnostics.
    """

    def __init__(
        self, node: Node, period_s: float = 1.0,
        update: Callable[[Diagnostics], None] | None = None,
    ) -> None:
        self._node = node
        self._update = update  # refreshes values, level and message just before each publish
        self.counts: Counter[str] = Counter()
        self.values: dict[str, str] = {}
        self.level = DiagnosticStatus.OK
        self.message = 'ok'
        self.last_stamp_ns = 0
        self._publisher = node.create_publisher(DiagnosticArray, '/diagnostics', 10)
        self._timer = node.create_timer(period_s, self.publish)

    def count(self, key: str, amount: int = 1) -> None:
        self.counts[key] += amount

    def publish(self) -> None:
        if self._update is not None:
            self._update(self)
        status = DiagnosticStatus(
            level=self.level,
            name=f'{self._node.get_name()}',
            message=self.message,
            hardware_id=self._node.get_fully_qualified_name(),
        )
        values = {**{k: str(v) for k, v in sorted(self.counts.items())}, **self.values}
        status.values = [KeyValue(key=k, value=v) for k, v in values.items()]
        msg = DiagnosticArray(status=[status])
        msg.header.stamp = ns_to_stamp(self.last_stamp_ns)
        self._publisher.publish(msg)
