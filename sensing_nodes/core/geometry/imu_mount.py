"""An IMU mounted rotated in base_link: its readings expressed about base_link's axes.

The mount is the IMU frame's orientation in base_link as roll, pitch, yaw (rad, ZYX: R =
Rz(yaw)·Ry(pitch)·Rx(roll)); upside down is roll = pi. A vector measured in the IMU frame is
R·v in base_link; an IMU orientation q (IMU frame in its world frame) gives base_link's
orientation q·R⁻¹ in that world frame. Quaternions are (x, y, z, w).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray


def mount_rotation(roll: float, pitch: float, yaw: float) -> NDArray[np.float64]:
    """3x3 rotation of the IMU frame in base_link from roll, pitch, yaw (rad, ZYX)."""
    cr, sr = math.cos(roll), math.sin(roll)
    cp, sp = math.cos(pitch), math.sin(pitch)
    cy, sy = math.cos(yaw), math.sin(yaw)
    return np.array([
        [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
        [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
        [-sp, cp * sr, cp * cr],
    ])


def mount_rpy(rotation: NDArray[np.float64]) -> tuple[float, float, float]:
    """Roll, pitch, yaw (rad, ZYX) of a 3x3 rotation: mount_rotation's inverse (pitch within
    [-pi/2, pi/2])."""
    r = rotation
    return (math.atan2(r[2, 1], r[2, 2]), -math.asin(max(-1.0, min(1.0, float(r[2, 0])))),
            math.atan2(r[1, 0], r[0, 0]))


def quaternion_matrix(q: ArrayLike) -> NDArray[np.float64]:
    """3x3 rotation of a unit quaternion (x, y, z, w); normalised first."""
    x, y, z, w = (float(v) for v in q)
    n = math.sqrt(x * x + y * y + z * z + w * w)
    x, y, z, w = x / n, y / n, z / n, w / n
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def base_orientation(q_imu: ArrayLike, mount: NDArray[np.float64]) -> NDArray[np.float64]:
    """3x3 orientation of base_link in the IMU's world frame from the IMU's quaternion."""
    return quaternion_matrix(q_imu) @ mount.T


def to_base(vector: ArrayLike, mount: NDArray[np.float64]) -> NDArray[np.float64]:
    """A rate or acceleration measured about the IMU's axes -> about base_link's axes."""
    return mount @ np.asarray(vector, dtype=float)


def is_identity(mount: NDArray[np.float64]) -> bool:
    """True when the mount does not rotate anything (the IMU is aligned with base_link)."""
    return bool(np.allclose(mount, np.eye(3), atol=1e-12))
