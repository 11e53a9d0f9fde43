"""Covariances of Odometry and Imu sources: zero, static or growing, and how they compare with
the source's actual errors against scan matching (NEES). Variances of x, y, yaw (m^2, rad^2)
per message, in bag order."""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from sensing_nodes.core.diagnosis.check import OK, PROBLEM, SKIPPED, WARNING, Check

# Variances this large mean "not measured" (robot_localization's 1e6, TurtleBot3's 1e12).
UNUSED_VARIANCE = 1e3


def covariance_kind(var: NDArray[np.float64]) -> str:
    """'zero' (no variance on any used axis), 'static' (the same in every message),
    'growing' (rises over the bag), 'varying' (changes, but does not grow), 'none' (no
    messages)."""
    v = np.asarray(var, dtype=float)
    if v.size == 0:
        return 'none'
    used = v[:, (v < UNUSED_VARIANCE).any(axis=0)] if (v < UNUSED_VARIANCE).any() else v
    if not np.any(used > 0.0):
        return 'zero'
    if np.allclose(used, used[0], rtol=1e-9, atol=0.0):
        return 'static'
    total = used.sum(axis=1)
    rises = np.diff(total) >= -1e-15 * np.abs(total[:-1])
    return 'growing' if total[-1] > total[0] and rises.mean() > 0.9 else 'varying'


def odometry_covariance_check(topic: str, pose_var: NDArray[np.float64],
                              twist_var: NDArray[np.float64]) -> Check:
    """What a filter can take from an Odometry's covariance."""
    pose, twist = covariance_kind(pose_var), covariance_kind(twist_var)
    details = {'pose': pose, 'twist': twist, 'pose_var_first': pose_var[0],
               'pose_var_last': pose_var[-1], 'twist_var_first': twist_var[0]}
    if pose == 'zero' and twist == 'zero':
        return Check('covariance', topic, PROBLEM, 0.0, 'm^2',
                     'zero covariance on pose and twist: a filter takes the source as exact '
                     '(robot_localization and this fusion follow it blindly or reject the '
                     'rest); publish a real covariance, or let the fusion use its noise model '
                     '(covariance: model in params.yaml)', 'non-zero', details)
    if pose == 'growing':
        return Check('covariance', topic, OK, float(pose_var[-1, :2].sum()), 'm^2',
                     'the pose covariance grows with the motion, as dead reckoning\'s does',
                     '', details)
    note = {'zero': 'zero', 'static': 'static (it never grows)',
            'varying': 'varying but not growing'}[pose]
    return Check('covariance', topic, WARNING, float(pose_var[-1, :2].sum()), 'm^2',
                 f'the pose covariance is {note} and the twist covariance {twist}: a static '
                 'pose covariance says nothing of how far the estimate has drifted; fuse its '
                 'velocities or its increments, not its pose (params.yaml does, where it fuses '
                 'this odometry)',
                 'growing', details)


def imu_covariance_check(topic: str, orientation_var: NDArray[np.float64],
                         gyro_var: NDArray[np.float64]) -> Check:
    """REP 145: orientation_covariance[0] = -1 for no orientation; all zeros: unknown."""
    has_orientation = not np.all(orientation_var[:, 0] == -1.0)
    gyro = covariance_kind(gyro_var)
    details = {'orientation': has_orientation, 'gyro': gyro, 'gyro_var_first': gyro_var[0]}
    if gyro == 'zero':
        return Check('covariance', topic, WARNING, 0.0, '(rad/s)^2',
                     'angular velocity covariance all zero: REP 145 reads that as unknown; the '
                     'nodes use their own noise figures (gyro_noise_density: params.yaml carries '
                     'the one measured where the IMU stands still 10 s)',
                     'non-zero', details)
    return Check('covariance', topic, OK, float(gyro_var[0, 2]), '(rad/s)^2',
                 f'angular velocity covariance {gyro}' + (
                     ', orientation given' if has_orientation else ', no orientation (-1)'),
                 '', details)


def nees_check(topic: str, errors: NDArray[np.float64], variances: NDArray[np.float64]
               ) -> Check:
    """Normalised estimation error squared of increments (K, 3) against their predicted
    variances (K, 3): mean e^2 / var per axis; 1 is honest, above it over-confident."""
    e = np.asarray(errors, dtype=float)
    v = np.asarray(variances, dtype=float)
    use = (v > 0).all(axis=1) & np.isfinite(e).all(axis=1)
    if use.sum() < 5:
        return Check('covariance_nees', topic, SKIPPED, None, '',
                     'too few increments with a covariance to compare')
    ratio = (e[use] ** 2 / v[use]).mean(axis=0)
    nees = float(ratio.mean())
    verdict = OK if 0.1 <= nees <= 10.0 else WARNING
    word = 'honest' if verdict == OK else ('over-confident' if nees > 10 else 'pessimistic')
    return Check('covariance_nees', topic, verdict, nees, 'per axis',
                 f'its increments err {math.sqrt(nees):.2g}x the sigma its covariance gives '
                 f'(x {ratio[0]:.2g}, y {ratio[1]:.2g}, yaw {ratio[2]:.2g} in variance) against '
                 f'scan matching: {word}', '0.1 - 10', {'per_axis': ratio, 'increments':
                                                         int(use.sum())})
