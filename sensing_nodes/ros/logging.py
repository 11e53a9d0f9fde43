"""Throttled warnings keyed by what they are about, not by the line that logs them.

rclpy throttles per call site, so one site warning about several inputs would hide all but the
first; here each key (e.g. an input's name) has its own throttle. The period is measured on the
node's clock, so with use_sim_time it follows /clock (a replay at 10x throttles per simulated
second, as the messages' stamps do).
"""

from __future__ import annotations

from rclpy.node import Node


class ThrottledWarnings:
    def __init__(self, node: Node, period_s: float = 1.0) -> None:
        self._node = node
        self._period_s = period_s
        self._last: dict[str, float] = {}
        self.suppressed: dict[str, int] = {}

    def warn(self, key: str, message: str) -> None:
        """Log message unless `key` was logged within the period; say how many were held back."""
        now = self._node.get_clock().now().nanoseconds * 1e-9
        last = self._last.get(key)
        # A clock that went back (a replayed bag looping) restarts the throttle.
        if last is not None and 0.0 <= now - last < self._period_s:
            self.suppressed[key] = self.suppressed.get(key, 0) + 1
            return
        held = self.suppressed.pop(key, 0)
        suffix = f' ({held} similar warnings suppressed)' if held else ''
        self._node.get_logger().warn(message + suffix)
        self._last[key] = now
