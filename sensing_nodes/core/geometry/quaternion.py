"""Unit quaternions (x, y, z, w), ROS's order, as plain float tuples.

Rotations of sensor mounts and transforms: a handful per message at most, so plain floats (a
4-vector
through numpy costs more in call overhead than the arithmetic).
"""

from __future__ import annotations

import math

Quat = tuple[float, float, float, float]
Vec3 = tuple[float, float, float]

IDENTITY: Quat = (0.0, 0.0, 0.0, 1.0)

# How far |q| may be from 1 before a quaternion is refused rather than normalised: drivers and
# hand-written URDFs print 4-6 digits, which leaves |q| within ~1e-4 of 1.
UNIT_TOLERANCE = 1e-3


def norm(q: Quat) -> float:
    """Euclidean norm of q."""
    return math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])


def is_unit(q: Quat, tolerance: float = UNIT_TOLERANCE) -> bool:
    """True when every component is finite and |q| is within tolerance of 1."""
    return all(math.isfinite(c) for c in q) and abs(norm(q) - 1.0) <= tolerance


def normalized(q: Quat) -> Quat:
    """q / |q|."""
    n = norm(q)
    return (q[0] / n, q[1] / n, q[2] / n, q[3] / n)


def multiply(a: Quat, b: Quat) -> Quat:
    """Hamilton product a * b: rotate by b, then by a."""
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return (aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
            aw * bw - ax * bx - ay * by - az * bz)


def conjugate(q: Quat) -> Quat:
    """Inverse rotation of a unit quaternion."""
    return (-q[0], -q[1], -q[2], q[3])


def rotate(q: Quat, v: Vec3) -> Vec3:
    """Vector v rotated by unit quaternion q (v' = q v q*)."""
    x, y, z, w = q
    # t = 2 (q_xyz x v); v' = v + w t + q_xyz x t: the cross-product form, no matrix.
    tx = 2.0 * (y * v[2] - z * v[1])
    ty = 2.0 * (z * v[0] - x * v[2])
    tz = 2.0 * (x * v[1] - y * v[0])
    return (v[0] + w * tx + (y * tz - z * ty),
            v[1] + w * ty + (z * tx - x * tz),
            v[2] + w * tz + (x * ty - y * tx))


def from_yaw(yaw: float) -> Quat:
    """Rotation about z by yaw (rad)."""
    return (0.0, 0.0, math.sin(yaw / 2.0), math.cos(yaw / 2.0))


def from_rpy(roll: float, pitch: float, yaw: float) -> Quat:
    """Fixed-axis roll (x), pitch (y), yaw (z) in rad -> q = qz(yaw) qy(pitch) qx(roll) (REP
    103)."""
    cr, sr = math.cos(roll / 2.0), math.sin(roll / 2.0)
    cp, sp = math.cos(pitch / 2.0), math.sin(pitch / 2.0)
    cy, sy = math.cos(yaw / 2.0), math.sin(yaw / 2.0)
    return (sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy,
            cr * cp * cy + sr * sp * sy)


def to_rpy(q: Quat) -> Vec3:
    """Unit quaternion -> fixed-axis (roll, pitch, yaw) in rad, pitch in [-pi/2, pi/2]."""
    x, y, z, w = q
    roll = math.atan2(2.0 * (w * x + y * z), 1.0 - 2.0 * (x * x + y * y))
    pitch = math.asin(max(-1.0, min(1.0, 2.0 * (w * y - z * x))))
    yaw = math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
    return roll, pitch, yaw


def yaw(q: Quat) -> float:
    """Yaw (rad) of a quaternion: the z part of its fixed-axis roll-pitch-yaw."""
    x, y, z, w = q
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def angle_between(a: Quat, b: Quat) -> float:
    """Angle (rad, [0, pi]) of the rotation taking a to b."""
    d = abs(a[0] * b[0] + a[1] * b[1] + a[2] * b[2] + a[3] * b[3])
    return 2.0 * math.acos(min(1.0, d))
