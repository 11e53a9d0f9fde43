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
