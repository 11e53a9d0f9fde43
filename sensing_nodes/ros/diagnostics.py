"""A node's health on /diagnostics: counters of what it processed and what it rejected."""

from __future__ import annotations

from collections import Counter
from typing import Callable

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.clock import Clock, ClockType
from rclpy.node import Node

from sensing_nodes.ros.conversions import ns_to_stamp

_CATCH_UP_PERIODS = 30  # a node clock further ahead of its due time than this has leapt


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
        # Once per period of the node's clock; under use_sim_time (/clock time) checked by a
        # steady-clock timer polling ten times a period: the EventsExecutor's timers on /clock
        # time fire in bursts on a loaded machine (a 1 Hz timer 32-110 times over a 22 s
        # replay at 3x, 4 runs of 4; rclcpp#2457, #2771 describe its timer manager's sim-time
        # and overrun limits).
        self._period_ns = int(period_s * 1e9)
        self._due_ns: int | None = None
        steady = Clock(clock_type=ClockType.STEADY_TIME)
        if node.get_parameter('use_sim_time').value:
            self._timer = node.create_timer(period_s / 10.0, self._on_poll, clock=steady)
        else:
            # The node's clock is the system clock: a timer of the period itself, a tenth of
            # the poll's wake-ups (the five nodes in one process with no input: 1.1 -> 0.47 %
            # of a core, `graph_cpu --idle --one-process`).
            self._timer = node.create_timer(period_s, self.publish, clock=steady)

    def _on_poll(self) -> None:
        """Publish when the node's clock has reached the due time (it starts a period after the
        first reading; a clock gone backwards, a looping bag, restarts it)."""
        now = self._node.get_clock().now().nanoseconds
        if now == 0:            # use_sim_time before the first /clock
            return
        if self._due_ns is None or now < self._due_ns - self._period_ns:
            self._due_ns = now + self._period_ns
            return
        if now >= self._due_ns:
            # The next one a period on: after a stall of a few periods (a busy executor also
            # takes /clock late) one status per poll catches up; after a leap, no catching up.
            self._due_ns += self._period_ns
            if now - self._due_ns > _CATCH_UP_PERIODS * self._period_ns:
                self._due_ns = now + self._period_ns
            self.publish()

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
