"""Wheel odometry written the way a lesson writes it (3x3 matrix products, one step at a
time): one dead-reckoning step of the pose and the classic EKF covariance step
P' = F P F^T + G diag(k |ds_l|, k |ds_r|) G^T. Production (core.wheel_odometry's
dead_reckoning_step) runs the same recursion in plain floats; the tests compare the two."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from sensing_nodes.core.geometry.se2 import wrap_angle
from sensing_nodes.core.wheel_odometry import arc_displacement


def integrate_step(pose: ArrayLike, ds: ArrayLike, dtheta: ArrayLike, method: str = 'exact_arc'):
    """Pose(s) (x, y, yaw) in odom after travelling ds (m) and turning dtheta (rad) in one step.

    pose (3,) or (..., 3) with matching ds/dtheta; a tuple of floats returns a tuple.
    method 'exact_arc' follows the arc; 'euler' moves straight along the heading at the start
    of the step (the textbook update).
    """
    if isinstance(pose, tuple) and isinstance(ds, float) and isinstance(dtheta, float):
        dx, dy, _, _ = arc_displacement(float(pose[2]), ds, dtheta, method)
        return (pose[0] + dx, pose[1] + dy, float(wrap_angle(pose[2] + dtheta)))
    p = np.asarray(pose, dtype=float)
    dx, dy, _, _ = arc_displacement(p[..., 2], np.asarray(ds, float), np.asarray(dtheta, float),
                                 method)
    return np.stack([p[..., 0] + dx, p[..., 1] + dy, wrap_angle(p[..., 2] + dtheta)], axis=-1)


def step_jacobians(
    yaw: float, ds: float, dtheta: float, wheel_separation_m: float, method: str = 'exact_arc'
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Jacobians of one step w.r.t. the pose (3x3) and the wheel distances [dsL, dsR] (3x2)."""
    dx, dy, d_ds, d_dth = arc_displacement(float(yaw), float(ds), float(dtheta), method)
    j_pose = np.array([[1.0, 0.0, -dy], [0.0, 1.0, dx], [0.0, 0.0, 1.0]])
    j_body = np.array([[d_ds[0], d_dth[0]], [d_ds[1], d_dth[1]], [0.0, 1.0]])
    to_body = np.array([[0.5, 0.5], [-1.0 / wheel_separation_m, 1.0 / wheel_separation_m]])
    return j_pose, j_body @ to_body


def propagate_covariance(
    covariance: ArrayLike,
    yaw: float,
    ds_left: float,
    ds_right: float,
    wheel_separation_m: float,
    variance_per_m: tuple[float, float],
    method: str = 'exact_arc',
) -> NDArray[np.float64]:
    """Pose covariance (3x3, x/y/yaw in odom) after one step from heading yaw, wheel distances in
    m.

    Wheel distance variance is variance_per_m[i] * |ds_i| (m^2), independent per wheel.
    """
    ds, dtheta = 0.5 * (ds_right + ds_left), (ds_right - ds_left) / wheel_separation_m
    j_pose, j_wheels = step_jacobians(yaw, ds, dtheta, wheel_separation_m, method)
    wheel_var = np.diag([variance_per_m[0] * abs(ds_left), variance_per_m[1] * abs(ds_right)])
    cov = j_pose @ np.asarray(covariance, float) @ j_pose.T + j_wheels @ wheel_var @ j_wheels.T
    return 0.5 * (cov + cov.T)
