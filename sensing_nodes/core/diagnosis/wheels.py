"""Wheels: the geometry the bag shows (sensing_calibrate's estimate against scan matching)
against the declared one, encoder resolution, and whether an Odometry topic comes from these
encoders. Wheel angles rad [left, right], stamps int64 ns, lengths m, angles rad.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from sensing_nodes.core.diagnosis.check import OK, SEVERITY, SKIPPED, Check, graded
from sensing_nodes.core.evaluation.calibration import CalibrationResult, Geometry
from sensing_nodes.core.evaluation.characterization import encoder_quantisation
from sensing_nodes.core.geometry.se2 import wrap_angle
from sensing_nodes.core.wheel_odometry import body_increments

SCALE_WARN_PCT, SCALE_PROBLEM_PCT = 1.0, 2.5


def geometry_checks(result: CalibrationResult, declared: Geometry, declared_from: str
                    ) -> list[Check]:
    """Radius scale, separation scale and laser mount found against the declared geometry."""
    est = {e.name: e for e in result.estimates}
    checks = []
    left, right = est['left_radius_m'], est['right_radius_m']
    if left.excited and right.excited:
        scales = (left.value / declared.left_radius_m, right.value / declared.right_radius_m)
        pct = 100.0 * (0.5 * (scales[0] + scales[1]) - 1.0)
        std = 100.0 * 0.5 * math.hypot(left.std / declared.left_radius_m,
                                       right.std / declared.right_radius_m)
        verdict = graded(abs(pct), SCALE_WARN_PCT, SCALE_PROBLEM_PCT)
        checks.append(Check(
            'wheel_radius', 'wheels', verdict, pct, '%',
            f'radii {left.value:.5f} / {right.value:.5f} m, {pct:+.2f} +- {std:.2f} % against '
            f'the declared {declared.left_radius_m:.5f} / {declared.right_radius_m:.5f} m '
            f'({declared_from})' + ('' if verdict == OK else
                                    ': set wheel_radius_m and the multipliers (params.yaml)'),
            f'|scale - 1| < {SCALE_WARN_PCT:g} %',
            {'left_m': left.value, 'right_m': right.value, 'std_pct': std,
             'left_scale': scales[0], 'right_scale': scales[1]}))
    else:
        checks.append(Check('wheel_radius', 'wheels', SKIPPED, None, '%', left.note or right.note))
    sep = est['wheel_separation_m']
    if sep.excited:
        pct = 100.0 * (sep.value / declared.wheel_separation_m - 1.0)
        verdict = graded(abs(pct), SCALE_WARN_PCT, SCALE_PROBLEM_PCT)
        checks.append(Check(
            'wheel_separation', 'wheels', verdict, pct, '%',
            f'separation {sep.value:.4f} m, {pct:+.2f} +- '
            f'{100 * sep.std / declared.wheel_separation_m:.2f} % against the declared '
            f'{declared.wheel_separation_m:.4f} m' + (
                '' if verdict == OK else ': turns drift; set wheel_separation_m (params.yaml)'),
            f'|scale - 1| < {SCALE_WARN_PCT:g} %', {'separation_m': sep.value, 'std_m': sep.std}))
    else:
        checks.append(Check('wheel_separation', 'wheels', SKIPPED, None, '%', sep.note))
    checks.append(_laser_mount(result, declared, declared_from))
    return checks


def _laser_mount(result: CalibrationResult, declared: Geometry, declared_from: str) -> Check:
    est = {e.name: e for e in result.estimates}
    found = result.geometry()
    shift = math.hypot(found.laser_x_m - declared.laser_x_m, found.laser_y_m - declared.laser_y_m)
    turn = abs(math.degrees(float(wrap_angle(found.laser_yaw_rad - declared.laser_yaw_rad))))
    excited = [n for n in ('laser_x_m', 'laser_y_m', 'laser_yaw_rad') if est[n].excited]
    if not excited:
        return Check('laser_mount', 'laser', SKIPPED, None, 'm', est['laser_x_m'].note)
    verdict = max(graded(shift, 0.02, 0.05), graded(turn, 1.0, 3.0),
                  key=SEVERITY.__getitem__)
    shown = (f'laser at ({found.laser_x_m:.3f}, {found.laser_y_m:.3f}) m, '
             f'{math.degrees(found.laser_yaw_rad):.2f} deg in the base frame')
    return Check('laser_mount', 'laser', verdict, shift, 'm',
                 f'{shown}, {shift:.3f} m and {turn:.2f} deg from the declared ({declared_from})'
                 + ('' if verdict == OK else ': declare it (/tf_static or icp_matcher laser_*)'),
                 '< 0.02 m, < 1 deg',
                 {'x_m': found.laser_x_m, 'y_m': found.laser_y_m,
                  'yaw_deg': math.degrees(found.laser_yaw_rad), 'yaw_error_deg': turn,
                  'estimated': excited})


def encoder_resolution_check(positions: NDArray[np.float64], radius_m: float) -> Check:
    """Counts per revolution seen in the wheel angles, and the travel per count (m)."""
    q = encoder_quantisation(positions[:, 0])
    if q.step_rad is None:
        return Check('encoder_resolution', 'wheels', OK, None, 'counts/rev', q.note)
    travel = q.step_rad * radius_m
    verdict = graded(travel, 1e-3, 5e-3)
    return Check('encoder_resolution', 'wheels', verdict, q.counts_per_rev, 'counts/rev',
                 f'{q.counts_per_rev:.0f} counts per revolution: {1000 * travel:.3f} mm of travel '
                 'per count' + ('' if verdict == OK else ': coarse; slow motion quantises'),
                 '< 1 mm per count', {'travel_per_count_m': travel})


def encoders_vs_odometry(subject: str, joint_t: NDArray[np.int64], joints: NDArray[np.float64],
                         odom_t: NDArray[np.int64], odom_yaw: NDArray[np.float64],
                         window_s: float = 0.5) -> Check:
    """Whether an Odometry topic's heading comes from these encoders: its yaw increments over
    window_s windows regressed on the two wheels' angle increments (r_R/b and -r_L/b fitted, so
    any geometry fits); the heading the fit leaves unexplained, accumulated over the bag (deg)."""
    lo, hi = max(joint_t[0], odom_t[0]), min(joint_t[-1], odom_t[-1])
    edges = np.arange(lo, hi, int(window_s * 1e9))
    if edges.size < 10:
        return Check('encoders_vs_odometry', subject, SKIPPED, None, 'deg',
                     'the encoders and the odometry overlap too little')
    base = joint_t[0]
    w = np.diff(np.column_stack([np.interp((edges - base) * 1e-9, (joint_t - base) * 1e-9,
                                           joints[:, i]) for i in range(2)]), axis=0)
    yaw = np.unwrap(odom_yaw)
    o = np.diff(np.interp((edges - base) * 1e-9, (odom_t - base) * 1e-9, yaw))
    turned = float(np.abs(o).sum())
    if turned < math.radians(90.0):
        return Check('encoders_vs_odometry', subject, SKIPPED, None, 'deg',
                     f'{subject} turns {math.degrees(turned):.0f} deg: too little to compare')
    # yaw increment = (r_R dphi_R - r_L dphi_L) / b: one gain per wheel, any geometry fits
    gains, *_ = np.linalg.lstsq(w, o, rcond=None)
    residual = o - w @ gains
    drift = np.cumsum(residual)
    divergence = math.degrees(float(np.abs(drift).max()))
    unexplained = float(np.sqrt(residual @ residual / (o @ o)))
    gain = float(gains[1])
    verdict = max(graded(divergence, 5.0, 20.0), graded(100 * unexplained, 5.0, 20.0),
                  key=SEVERITY.__getitem__)
    advice = (f'{subject} turns as the encoders do (fitted r_R/b {gain:.5f})' if verdict == OK else
              f'the encoders do not explain {subject}: dead reckoning with the best-fitting '
              f'geometry ends up to {divergence:.0f} deg off it ({100 * unexplained:.0f} % of '
              'its turning unexplained): wheel slip, another source (a simulator\'s world pose, '
              'a fused estimate), or the wrong joints')
    return Check('encoders_vs_odometry', subject, verdict, divergence, 'deg', advice,
                 '< 5 deg, < 5 % unexplained',
                 {'unexplained_pct': 100 * unexplained, 'turned_deg': math.degrees(turned),
                  'gains_rad_per_rad': [float(g) for g in gains]})


def wheel_rates(joint_t: NDArray[np.int64], joints: NDArray[np.float64], geometry: Geometry
                ) -> tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.float64],
                           NDArray[np.float64]]:
    """Midpoint stamps, forward speed (m/s), yaw rate (rad/s) and cumulative yaw (rad, at
    joint_t) of the wheels with the given geometry."""
    dt = np.diff(joint_t) * 1e-9
    ds, dth = body_increments(np.diff(joints[:, 0]) * geometry.left_radius_m,
                              np.diff(joints[:, 1]) * geometry.right_radius_m,
                              geometry.wheel_separation_m)
    ok = dt > 0
    mid = joint_t[:-1] + np.diff(joint_t) // 2
    yaw = np.concatenate(([0.0], np.cumsum(dth)))
    return mid[ok], ds[ok] / dt[ok], dth[ok] / dt[ok], yaw

