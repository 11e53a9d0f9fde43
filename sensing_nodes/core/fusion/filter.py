"""What a fusion filter offers the session (core/fusion/session.py): the interface the EKF and
the complementary filter both implement, and the fused estimate they give."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from sensing_nodes.core.fusion.inputs import Reading
from sensing_nodes.core.fusion.integrity import InputHealth
from sensing_nodes.core.geometry.se2 import Pose2


@dataclass(frozen=True)
class FusedState:
    """Fused estimate at stamp_ns: pose (odom, m and rad) and its 3x3 covariance, body twist
    (vx, vy, wz in base_link) and its 3x3 covariance (None: the filter does not estimate it),
    gyro z bias (rad/s) and its variance (None where the filter has no bias)."""

    stamp_ns: int
    pose: Pose2
    covariance: NDArray[np.float64]
    twist: tuple[float, float, float] = (0.0, 0.0, 0.0)
    twist_covariance: NDArray[np.float64] | None = None
    bias: float | None = None
    bias_variance: float | None = None


class FusionFilter(Protocol):
    """A stamp-ordered filter over the inputs named in core/fusion/inputs.py: readings in, in
    stamp order; the fused state out."""

    updates: int                 # measurements fused so far
    gated: dict[str, int]        # readings refused by the filter's gate, per input
    health: dict[str, InputHealth]   # per input, what the filter refused and blamed (may be
                                     # empty: a filter without gates)
    noise_scale: dict[str, float]    # per input, its noise's adaptive scale (1: none)

    def update(self, name: str, reading: Reading) -> object:
        """Fuse one reading of input `name` (stamps never go backwards)."""

    @property
    def state(self) -> FusedState | None:
        """The fused estimate after every reading so far (None before the first)."""

    def reset(self) -> None:
        """Start again, as new."""

    def set_pose(self, pose: Pose2, covariance: NDArray[np.float64]) -> None:
        """Put the robot at pose (odom) with this 3x3 covariance; later inputs go on from it."""

    def restart(self, name: str) -> None:
        """Input `name` starts again from its next reading (what it measures has changed)."""
