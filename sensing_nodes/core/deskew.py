"""Deskewing a laser scan: each beam moved from where the laser was when it was taken to where
the laser was at the scan's stamp (its first beam), using the robot's motion during the sweep.

Frames and units: points (N, 2) in the laser frame (m); beam times in s after the stamp; base
motions (x, y, yaw) of base_link relative to base_link at the stamp (m, rad); the laser mounted
at `laser_pose` (x, y, yaw) in base_link.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from sensing_nodes.core.geometry.se2 import Pose2


def beam_times(beam_index: NDArray[np.intp], time_increment_s: float) -> NDArray[np.float64]:
    """Time (s after the stamp) of each point from its beam index (LaserScan.time_increment)."""
    return np.asarray(beam_index, dtype=float) * time_increment_s


def twist_motions(twist: tuple[float, float, float],
                  times_s: NDArray[np.float64]) -> NDArray[np.float64]:
    """Base motions (T, 3) after times_s (T,), s, at a constant twist (vx, vy m/s, wz rad/s in
    base_link): the exact arcs (SE(2) exponential)."""
    vx, vy, wz = twist
    theta = wz * np.asarray(times_s, dtype=float)
    # sin(θ)/ω and (1 - cos θ)/ω as t·sinc-like factors, finite as ω -> 0.
    along = times_s * np.sinc(theta / np.pi)
    half = 0.5 * theta
    across = times_s * np.sinc(half / np.pi) * np.sin(half)
    return np.column_stack((along * vx - across * vy, across * vx + along * vy, theta))


def deskew(points: NDArray[np.float64], motions: NDArray[np.float64],
           laser_pose: Pose2) -> NDArray[np.float64]:
    """Points (N, 2), laser frame, each taken after the base moved by motions[i] (N, 3) since the
    stamp -> the same points in the laser frame at the stamp (mount⁻¹ ∘ motion ∘ mount)."""
    if points.shape[0] == 0:
        return points
    lx, ly, lyaw = laser_pose
    cm, sm = np.cos(lyaw), np.sin(lyaw)
    mx, my, myaw = motions[:, 0], motions[:, 1], motions[:, 2]
    c, s = np.cos(myaw), np.sin(myaw)
    # Point in base_link at its beam's time: mount ∘ p.
    bx = lx + cm * points[:, 0] - sm * points[:, 1]
    by = ly + sm * points[:, 0] + cm * points[:, 1]
    # In base_link at the stamp: motion ∘ (that).
    sx = mx + c * bx - s * by
    sy = my + s * bx + c * by
    # Back into the laser frame: mount⁻¹ ∘ (that).
    sx -= lx
    sy -= ly
    return np.column_stack((cm * sx + sm * sy, -sm * sx + cm * sy))
