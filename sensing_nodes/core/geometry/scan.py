"""Laser scans as arrays: validity per REP 117 and conversion to points in the scan frame."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray


def beam_angles(angle_min: float, angle_increment: float, count: int) -> NDArray[np.float64]:
    """Angle (rad, scan frame) of each of `count` beams."""
    return angle_min + angle_increment * np.arange(count, dtype=float)


def valid_ranges(
    ranges: ArrayLike, range_min: float = 0.0, range_max: float = np.inf
) -> NDArray[np.bool_]:
    """True where a range is a finite measurement inside [range_min, range_max] (m)."""
    r = np.asarray(ranges, dtype=float)
    with np.errstate(invalid='ignore'):
        return np.isfinite(r) & (r >= range_min) & (r <= range_max)


def scan_to_points(
    ranges: ArrayLike, angles: ArrayLike, range_min: float = 0.0, range_max: float = np.inf
) -> tuple[NDArray[np.float64], NDArray[np.intp]]:
    """Valid beams as (N, 2) points (m, scan frame) and the beam index of each point.

    Raises ValueError when ranges and angles differ in length: that is a malformed call.
    """
    r = np.asarray(ranges, dtype=float).ravel()
    a = np.asarray(angles, dtype=float).ravel()
    if r.shape != a.shape:
        raise ValueError(f'ranges ({r.size}) and angles ({a.size}) differ in length')
    index = np.flatnonzero(valid_ranges(r, range_min, range_max) & np.isfinite(a))
    points = np.column_stack((r[index] * np.cos(a[index]), r[index] * np.sin(a[index])))
    return points, index
