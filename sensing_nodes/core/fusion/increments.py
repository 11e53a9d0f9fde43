"""Covariance of the motion between two cumulative odometry poses (m, rad; 3x3 over x, y, yaw in
the increment's frame), recovered from their cumulative covariances under first-order
compounding: how both filters read a differential input."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from sensing_nodes.core.geometry import se2
from sensing_nodes.core.geometry.se2 import Pose2


def _added_covariance(
    pose_prev: Pose2, cov_prev: NDArray[np.float64], pose_now: Pose2, cov_now: NDArray[np.float64]
) -> NDArray[np.float64]:
    """cov_now minus cov_prev compounded to pose_now, in the increment's frame (unclipped)."""
    increment = se2.between(pose_prev, pose_now)
    j_a, j_b = se2.compose_jacobians(pose_prev, increment)
    added = cov_now - j_a @ cov_prev @ j_a.T
    j_b_inv = j_b.T  # j_b is a rotation about z
    q = j_b_inv @ added @ j_b_inv.T
    return 0.5 * (q + q.T)


def increment_covariance(
    pose_prev: Pose2, cov_prev: NDArray[np.float64], pose_now: Pose2, cov_now: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Covariance of the body-frame increment between two cumulative odometry poses, recovered
    from their covariances under first-order compounding (cov_now = Ja·cov_prev·Jaᵀ + Jb·Q·Jbᵀ).
    Negative parts (a source that does not propagate this way) are clipped to zero."""
    values, vectors = np.linalg.eigh(_added_covariance(pose_prev, cov_prev, pose_now, cov_now))
    return (vectors * np.clip(values, 0.0, None)) @ vectors.T


def compounded_increment_covariance(
    pose_prev: Pose2, cov_prev: NDArray[np.float64], pose_now: Pose2, cov_now: NDArray[np.float64],
    tolerance: float = 0.1,
) -> NDArray[np.float64] | None:
    """increment_covariance, or None when the source's covariance does not grow by compounding:
    the negative part the clip would remove exceeds `tolerance` times the positive part kept.
    A covariance that grows with distance alone (carmen_to_bag's) is such a source: the clip
    leaves directions of zero variance, which a filter would take as exact."""
    values, vectors = np.linalg.eigh(_added_covariance(pose_prev, cov_prev, pose_now, cov_now))
    # Three eigenvalues: plain floats (summed in numpy's order) cost less than numpy's calls.
    listed = values.tolist()
    if -sum(v for v in listed if v < 0.0) > tolerance * sum(v for v in listed if v > 0.0):
        return None
    return (vectors * np.maximum(values, 0.0)) @ vectors.T
