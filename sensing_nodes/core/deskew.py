"""Deskewing a laser scan: each beam moved from where the laser was when it was taken to where
the laser was at the scan's stamp (its first beam), using the robot's motion during the sweep.

Frames and units: points (N, 2) in the laser frame (m); beam times in s after the stamp; base
motions (x, y, yaw) of base_link relative to base_link at the stamp (m, rad); the laser mounted
at `laser_pose` (x, y, yaw) in base_link.
"""

from __future__ import annotations

import math

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
    translation, theta = _arcs(twist, np.asarray(times_s, dtype=float))
    return np.column_stack((translation.real, translation.imag, theta))


def twist_motion(twist: tuple[float, float, float], time_s: float) -> Pose2:
    """twist_motions for one time (plain floats)."""
    vx, vy, wz = twist
    theta = wz * time_s
    if abs(theta) < 1e-9:
        along, across = time_s, 0.5 * theta * time_s
    else:
        along, across = math.sin(theta) / wz, (1.0 - math.cos(theta)) / wz
    return (along * vx - across * vy, across * vx + along * vy, theta)


def _arcs(twist: tuple[float, float, float], times_s: NDArray[np.float64]
          ) -> tuple[NDArray[np.complex128], NDArray[np.float64]]:
    """Translation (x + iy) and rotation (rad) of the constant-twist motion after each time."""
    vx, vy, wz = twist
    theta = wz * times_s
    # sin(θ)/ω and (1 - cos θ)/ω as t·sinc-like factors, finite as ω -> 0.
    half = 0.5 * theta
    arc = np.sinc(theta * (1.0 / np.pi)) + 1j * (np.sinc(half * (1.0 / np.pi)) * np.sin(half))
    arc *= times_s
    arc *= complex(vx, vy)
    return arc, theta


def deskew(points: NDArray[np.float64], twist: tuple[float, float, float],
           times_s: NDArray[np.float64], laser_pose: Pose2) -> NDArray[np.float64]:
    """Points (N, 2), laser frame, each taken times_s[i] after the stamp while the base moved at
    a constant twist (vx, vy, wz in base_link) -> the same points in the laser frame at the
    stamp: mount⁻¹ ∘ motion(t) ∘ mount applied to each (as x + iy: rotations are products)."""
    if points.shape[0] == 0:
        return points
    lx, ly, lyaw = laser_pose
    mount = complex(math.cos(lyaw), math.sin(lyaw))
    lever = complex(lx, ly)
    translation, theta = _arcs(twist, np.asarray(times_s, dtype=float))
    rotation = np.cos(theta) + 1j * np.sin(theta)
    moved = np.ascontiguousarray(points, dtype=float).view(np.complex128).ravel() * mount
    moved += lever                                  # in base_link at the beam's time
    moved *= rotation
    moved += translation                            # in base_link at the stamp
    moved -= lever
    moved *= mount.conjugate()                      # in the laser frame at the stamp
    return moved.view(np.float64).reshape(-1, 2)
