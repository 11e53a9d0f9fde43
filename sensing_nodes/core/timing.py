"""Classifying the step between two message stamps (ns): what every integrating node must check."""

from __future__ import annotations

import enum
from dataclasses import dataclass


class StampStep(enum.Enum):
    FIRST = 'first'          # no previous stamp: initialise, integrate nothing
    OK = 'ok'                # 0 < dt <= max_gap: integrate
    REPEATED = 'repeated'    # dt == 0: duplicate stamp, nothing to integrate
    BACKWARDS = 'backwards'  # dt < 0: a bag looped or a clock was reset; reset the estimate
    GAP = 'gap'              # dt > max_gap: do not integrate across; restart from here


def classify_step(previous_ns: int | None, current_ns: int, max_gap_s: float) -> StampStep:
    """Classify the step from previous_ns to current_ns against a maximum gap (s)."""
    if previous_ns is None:
        return StampStep.FIRST
    dt_ns = current_ns - previous_ns
    if dt_ns == 0:
        return StampStep.REPEATED
    if dt_ns < 0:
        return StampStep.BACKWARDS
    if dt_ns > max_gap_s * 1e9:
        return StampStep.GAP
    return StampStep.OK


@dataclass
class SampleOutcome:
    """Outcome of one sample of an integrating core: whether to publish, the stamp step, why
    the sample was rejected (the core's own enum; None when it was used) and anything to report."""
    publish: bool
    step: StampStep | None = None
    rejection: enum.Enum | None = None
    note: str = ''


class StampRate:
    """Thins a stream of stamps (ns, non-decreasing) to rate_hz: a stamp is due when it is the
    first in a new period, periods of round(1e9 / rate_hz) ns counted from stamp 0, so what is
    let through depends on the stamps alone (a replay gives the same); rate_hz 0: every stamp."""

    def __init__(self, rate_hz: float) -> None:
        self.period_ns = round(1e9 / rate_hz) if rate_hz > 0.0 else 0
        self.reset()

    def reset(self) -> None:
        """Start again (a new timeline): the next stamp is due."""
        self._period: int | None = None

    def due(self, stamp_ns: int) -> bool:
        """Whether stamp_ns starts a new period (and then it is the period's)."""
        if not self.period_ns:
            return True
        period = stamp_ns // self.period_ns
        if self._period is not None and period <= self._period:
            return False
        self._period = period
        return True
