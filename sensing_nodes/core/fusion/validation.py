"""Acceptance rules of the fusion's input values: why a 3x3 covariance, or an odometry pose with
its covariance, cannot be used ('' when it can). Poses in m and rad."""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike

from sensing_nodes.core.geometry.se2 import Pose2


def covariance_problem(cov: ArrayLike) -> str:
    """Why a covariance cannot be used ('' when it can): not finite, not symmetric, or not
    positive semi-definite (beyond rounding)."""
    c = np.asarray(cov, dtype=float)
    if c.shape == (3, 3) and _plainly_positive_definite(c.tolist()):
        return ''
    if not np.all(np.isfinite(c)):
        return 'covariance is not finite'
    scale = max(float(np.max(np.abs(c))), 1e-300)
    if np.max(np.abs(c - c.T)) > 1e-9 * scale:
        return 'covariance is not symmetric'
    if float(np.min(np.linalg.eigvalsh(0.5 * (c + c.T)))) < -1e-9 * scale:
        return 'covariance is not positive semi-definite'
    return ''


def _plainly_positive_definite(rows: list[list[float]]) -> bool:
    """True when a 3x3 covariance (nested lists) is finite, symmetric within covariance_problem's
    tolerance and positive definite (its LDLt pivots > 0, which rounding cannot fake beyond
    ~1e-15 of its scale): what covariance_problem accepts, decided in plain floats for the
    common case (a 3x3 eigendecomposition per message cost more than the rest of a reading).
    False: covariance_problem decides with numpy."""
    (a, b, c), (d, e, f), (g, h, i) = rows
    values = (a, b, c, d, e, f, g, h, i)
    if not all(math.isfinite(v) for v in values):
        return False
    scale = max(max(abs(v) for v in values), 1e-300)
    if max(abs(b - d), abs(c - g), abs(f - h)) > 1e-9 * scale:
        return False
    b, c, f = 0.5 * (b + d), 0.5 * (c + g), 0.5 * (f + h)   # the symmetric part
    if not a > 0.0:
        return False
    l1, l2 = b / a, c / a
    d2 = e - l1 * b
    if not d2 > 0.0:
        return False
    l3 = (f - l1 * c) / d2
    return i - l2 * c - l3 * l3 * d2 > 0.0


def pose_problem(pose: Pose2, cov: ArrayLike, origin: Pose2 | None, zero_allowed: bool) -> str:
    """Why an odometry pose and its 3x3 covariance cannot be used ('' when they can). An exactly
    known (zero) covariance is only believable at the source's starting pose, unless the input
    replaces the covariance by its noise model anyway (zero_allowed)."""
    if not all(math.isfinite(v) for v in pose):
        return 'pose is not finite'
    reason = covariance_problem(cov)
    if reason:
        return reason
    diagonal = np.diag(np.asarray(cov, dtype=float)).tolist()
    if any(v < 0.0 for v in diagonal):
        return 'covariance has a negative variance'
    at_origin = origin is None or tuple(pose) == tuple(origin)
    if not zero_allowed and not all(v > 0.0 for v in diagonal) and \
            not (all(v == 0.0 for v in diagonal) and at_origin):
        return 'covariance is zero after moving (only a starting pose may be exactly known)'
    return ''
