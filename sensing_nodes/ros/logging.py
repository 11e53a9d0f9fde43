"""Throttled warnings keyed by what they are about, not by the line that logs them.

rclpy throttles per call site, so one site warning about several inputs would hide all but the
first; here each key (e.g. an input's name) has its own throttle.
"""

from __future__ import annotations

import time

from rclpy.node import Node


class ThrottledWarnings:
    def __init__(self, node: Node, period_s: float = 1.0) -> None:
        self._node = node
        self._period_s = period_s
        self._last: dict[str, float] = {}
        self.suppressed: dict[str, int] = {}

    def warn(self, key: str, message: str) -> None:
        """Log message unless `key` was logged within the period; say how many were held back."""
        now = time.monotonic()
        last = self._last.get(key)
        if last is not None and now - last < self._period_s:
            self.suppressed[key] = self.suppressed.get(key, 0) + 1
            return
        held = self.suppressed.pop(key, 0)
        suffix = f' ({held} similar warnings suppressed)' if held else ''
        self._node.get_logger().warn(message + suffix)
        self._last[key] = now
