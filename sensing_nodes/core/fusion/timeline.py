"""The fusion's timeline pieces: the stamp-ordered reorder buffer, what is kept per input
(InputRecord) and the watermark every live input has reached (stamps in ns). FusionSession
(core/fusion/session.py) owns them."""

from __future__ import annotations

import bisect
import math
from dataclasses import dataclass


class StampOrderedBuffer:
    """Releases items in stamp order once they are `window_ns` older than the newest stamp seen
    (or once every live input is past them), so the order of processing depends on stamps only,
    not on arrival timing.

    Ties are broken by `rank` (an input's fixed priority), then by arrival. An item whose stamp is
    older than what was already released is late: refused (push returns False) and counted.
    """

    def __init__(self, window_ns: int) -> None:
        self.window_ns = int(window_ns)
        self.clear()
        self.late = 0

    def clear(self) -> None:
        self._items: list[tuple[int, int, int, object]] = []
        self._arrivals = 0
        self.newest_ns: int | None = None
        self.released_ns: int | None = None

    def push(self, stamp_ns: int, rank: int, item: object) -> bool:
        if self.released_ns is not None and stamp_ns < self.released_ns:
            self.late += 1
            return False
        self._arrivals += 1
        # Kept sorted (arrival numbers are unique, so items themselves are never compared).
        bisect.insort(self._items, (stamp_ns, rank, self._arrivals, item))
        self.newest_ns = stamp_ns if self.newest_ns is None else max(self.newest_ns, stamp_ns)
        return True

    def pop_ready(self, watermark_ns: int | None = None) -> list[tuple[int, object]]:
        """(stamp, item) of every item at least window_ns older than the newest, or not newer
        than `watermark_ns` (a stamp every live input has already reached), in order."""
        if self.newest_ns is None:
            return []
        up_to = self.newest_ns - self.window_ns
        if watermark_ns is not None:
            up_to = max(up_to, watermark_ns)
        return self._release(up_to)

    def flush(self) -> list[tuple[int, object]]:
        """Everything still held, in order (end of a stream)."""
        return self._release(None)

    def __len__(self) -> int:
        return len(self._items)

    def _release(self, up_to_ns: int | None) -> list[tuple[int, object]]:
        count = len(self._items) if up_to_ns is None else \
            bisect.bisect_right(self._items, up_to_ns, key=_stamp_of)
        ready, self._items = self._items[:count], self._items[count:]
        if ready:
            self.released_ns = ready[-1][0]
        return [(stamp, item) for stamp, _, _, item in ready]


def _stamp_of(entry: tuple) -> int:
    return entry[0]

@dataclass
class InputRecord:
    """Bookkeeping of one fusion input (stamps ns): what arrived, what was processed, and the
    reference an exactly-known covariance is allowed at (its first accepted value)."""

    name: str
    enabled: bool = True
    received: int = 0
    processed: int = 0
    arrived_ns: int | None = None    # newest stamp accepted into the reorder buffer
    first_ns: int | None = None      # first and last processed stamps
    last_ns: int | None = None
    origin: object = None            # first accepted pose or yaw

    def clear(self) -> None:
        """Forget the timeline (time went backwards): keep the counts of received messages."""
        self.processed = 0
        self.arrived_ns = self.first_ns = self.last_ns = None
        self.origin = None

    def processed_at(self, stamp_ns: int) -> None:
        self.processed += 1
        self.last_ns = stamp_ns
        if self.first_ns is None:
            self.first_ns = stamp_ns

    def rate_hz(self) -> float:
        """Processed messages per second of stamp time (0 before two)."""
        if self.first_ns is None or self.last_ns is None or self.last_ns <= self.first_ns:
            return 0.0
        return (self.processed - 1) / ((self.last_ns - self.first_ns) * 1e-9)

    def age_s(self, newest_ns: int | None) -> float:
        """Stamp time since this input's last processed message (inf before any)."""
        if self.last_ns is None or newest_ns is None:
            return math.inf
        return (newest_ns - self.last_ns) * 1e-9


def watermark(records: list[InputRecord], newest_ns: int | None, start_ns: int | None,
              timeout_s: float, startup_timeout_s: float | None = None) -> int | None:
    """The stamp every live input has reached: nothing at or before it can still arrive (each
    input arrives in order), so it can be processed without waiting for the reorder window.
    An enabled input not heard from for timeout_s (stamp time) is not waited for; one not heard
    yet, for startup_timeout_s (default timeout_s) since start_ns."""
    if newest_ns is None:
        return None
    timeout_ns = timeout_s * 1e9
    startup_ns = timeout_ns if startup_timeout_s is None else startup_timeout_s * 1e9
    reached = []
    for record in records:
        if not record.enabled:
            continue
        if record.arrived_ns is None:
            if start_ns is None or newest_ns - start_ns <= startup_ns:
                return None  # not heard from yet, but may still be starting up
            continue
        if newest_ns - record.arrived_ns <= timeout_ns:
            reached.append(record.arrived_ns)
    return min(reached) if reached else None
