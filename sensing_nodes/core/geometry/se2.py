"""SE(2) poses (x, y, yaw) in metres and radians, and angle wrapping: the one place for both."""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

Pose2 = tuple[float, float, float]


_TWO_PI = 2.0 * math.pi


def wrap_angle(angle: ArrayLike) -> NDArray[np.float64] | float:
    """Wrap angles (rad) into (-pi, pi]; scalars stay Python floats."""
    if isinstance(angle, (float, int)) and math.isfinite(angle):
        # One float: math.remainder (exact) instead of numpy's per-call overhead, which cost
        # more than the rest of a per-message update.
        wrapped = math.remainder(angle, _TWO_PI)
        return float(wrapped) if wrapped > -math.pi else wrapped + _TWO_PI
    wrapped = np.pi - np.mod(np.pi - np.asarray(angle, dtype=float), 2.0 * np.pi)
    return float(wrapped) if np.ndim(wrapped) == 0 else wrapped


def rotation(yaw: float) -> NDArray[np.float64]:
    """2x2 rotation matrix for yaw (rad)."""
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s], [s, c]])


def compose(a: Pose2, b: Pose2) -> Pose2:
    """a ⊕ b: pose b, given in frame a, expressed in a's parent frame."""
    c, s = math.cos(a[2]), math.sin(a[2])
    return (
        a[0] + c * b[0] - s * b[1],
        a[1] + s * b[0] + c * b[1],
        float(wrap_angle(a[2] + b[2])),
    )


def inverse(a: Pose2) -> Pose2:
    """⊖a: the parent frame's origin expressed in frame a."""
    c, s = math.cos(a[2]), math.sin(a[2])
    return (-c * a[0] - s * a[1], s * a[0] - c * a[1], float(wrap_angle(-a[2])))


def between(a: Pose2, b: Pose2) -> Pose2:
    """⊖a ⊕ b: pose b expressed in frame a (both given in the same parent frame)."""
    return compose(inverse(a), b)


def transform_points(pose: Pose2, points: ArrayLike) -> NDArray[np.float64]:
    """Map (N, 2) points from the frame of `pose` into its parent frame."""
    pts = np.asarray(points, dtype=float).reshape(-1, 2)
    return pts @ rotation(pose[2]).T + np.array([pose[0], pose[1]])


def compose_jacobians(a: Pose2, b: Pose2) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Jacobians of compose(a, b) with respect to a and to b (3x3 each), for covariance
    propagation."""
    c, s = math.cos(a[2]), math.sin(a[2])
    j_a = np.array([
        [1.0, 0.0, -s * b[0] - c * b[1]],
        [0.0, 1.0, c * b[0] - s * b[1]],
        [0.0, 0.0, 1.0],
    ])
    j_b = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return j_a, j_b


def compose_with_covariance(
    a: Pose2, cov_a: NDArray[np.float64], b: Pose2, cov_b: NDArray[np.float64]
) -> tuple[Pose2, NDArray[np.float64]]:
    """compose(a, b) with first-order covariance, a and b independent (3x3 over x, y, yaw)."""
    j_a, j_b = compose_jacobians(a, b)
    cov = j_a @ cov_a @ j_a.T + j_b @ cov_b @ j_b.T
    return compose(a, b), 0.5 * (cov + cov.T)


def interpolate(a: Pose2, b: Pose2, fraction: float) -> Pose2:
    """Pose a fraction of the way from a to b (linear in x, y; shortest way round in yaw)."""
    dyaw = float(wrap_angle(b[2] - a[2]))
    return (
        a[0] + fraction * (b[0] - a[0]),
        a[1] + fraction * (b[1] - a[1]),
        float(wrap_angle(a[2] + fraction * dyaw)),
    )
