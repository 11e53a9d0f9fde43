"""What the fusion knows about each input's integrity: the chi-square gate at a stated
probability, and each input's record of fused, refused and blamed readings, its current
streak of refusals and the share refused recently (what /diagnostics says of it).

A reading is *refused* when its innovation fails the input's gate; it is *blamed* when a scan
match that disagreed with the state was explained by leaving this input's readings since the
last fused match out (EkfFusion's fault isolation): the input, not the match, was wrong. Stamps
in ns.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from functools import lru_cache

# scipy.special's chi-square functions, not scipy.stats': the same values, and the fusion node
# (every process that fuses) no longer pays scipy.stats' import, 34 MB of RSS and 0.35 s.
from scipy.special import chdtrc, chdtri

# How long (s of stamp time) an input stays reported as distrusted after its last refused or
# blamed reading.
DISTRUST_HOLD_S = 1.0
# Readings over which the recent refused share is counted.
RECENT_READINGS = 200


@lru_cache(maxsize=64)
def gate_threshold(probability: float, dof: int) -> float:
    """Squared Mahalanobis distance below which a Gaussian innovation of dof dimensions falls
    with the given probability (the chi-square quantile)."""
    return float(chdtri(dof, 1.0 - probability))


def tail_probability(distance2: float, dof: int) -> float:
    """Probability that a consistent innovation of dof dimensions lies further than
    distance2 (squared Mahalanobis distance)."""
    return float(chdtrc(dof, distance2))


@dataclass
class InputHealth:
    """One input's record: readings fused, refused by its gate and blamed by fault isolation,
    the current streak of refusals (and the stamp it began), the share refused among the last
    RECENT_READINGS, and the last problem with its stamp."""

    fused: int = 0
    refused: int = 0
    blamed: int = 0
    reacquired: int = 0
    streak: int = 0
    streak_start_ns: int | None = None
    last_problem: str = ''
    last_problem_ns: int | None = None
    last_ns: int | None = None
    recent: deque = field(default_factory=lambda: deque(maxlen=RECENT_READINGS))

    def accepted(self, stamp_ns: int) -> None:
        self.fused += 1
        self.streak, self.streak_start_ns = 0, None
        self.recent.append(False)
        self.last_ns = stamp_ns

    def refused_at(self, stamp_ns: int, problem: str) -> None:
        self.refused += 1
        if self.streak == 0:
            self.streak_start_ns = stamp_ns
        self.streak += 1
        self.recent.append(True)
        self._problem(stamp_ns, problem)

    def blamed_for(self, count: int, stamp_ns: int, problem: str) -> None:
        """`count` readings already fused are taken back: they were wrong."""
        self.blamed += count
        for _ in range(min(count, RECENT_READINGS)):
            self.recent.append(True)
        self._problem(stamp_ns, problem)

    def _problem(self, stamp_ns: int, problem: str) -> None:
        self.last_problem, self.last_problem_ns = problem, stamp_ns
        self.last_ns = stamp_ns

    @property
    def refused_share(self) -> float:
        """Share of the last RECENT_READINGS readings refused or blamed (0 before any)."""
        return sum(self.recent) / len(self.recent) if self.recent else 0.0

    def distrusted(self, now_ns: int) -> bool:
        """Whether a reading of this input was refused or blamed within DISTRUST_HOLD_S."""
        return self.last_problem_ns is not None and \
            now_ns - self.last_problem_ns <= DISTRUST_HOLD_S * 1e9
