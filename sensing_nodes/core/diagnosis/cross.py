"""Each source judged against the others: the wheels' (or an odometry's) yaw rate against the
gyro's (gain and offset), a source's speed against scan matching's (scale), the IMU's own
orientation (constant, identity, zero covariance), and each source's heading against each
other's over the run. Stamps int64 ns (sorted, unique), yaw rad (cumulative, unwrapped),
rates rad/s, distances m.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from sensing_nodes.core.diagnosis.check import OK, PROBLEM, SKIPPED, WARNING, Check

# The wheels' yaw rate over the gyro's: beyond 10 % the wheels turn another amount than the
# robot does (a skid-steer base's wheels slip sideways in every turn, or the track width is
# wrong), far more than a gyro's scale error (< 1 %) explains.
GAIN_LOW, GAIN_HIGH = 0.9, 1.1
MIN_TURN_RAD = math.radians(90.0)          # turning a yaw-rate or heading comparison needs
SPEED_WARN_PCT, SPEED_PROBLEM_PCT = 1.0, 2.5
# Heading disagreement over the run: both the angle and its share of the turning (a long bag
# that turns a lot lets a gyro drift a few degrees; noise adds to a jittery source's turning).
HEADING_WARN_DEG, HEADING_PROBLEM_DEG = 10.0, 30.0
HEADING_WARN_SHARE, HEADING_PROBLEM_SHARE = 0.02, 0.03


def _named(subject: str, verb: str) -> str:
    """'the wheels turn', '/odom turns'."""
    return f'the wheels {verb}' if subject == 'wheels' else f'{subject} {verb}s'


def _binned_rates(t: NDArray[np.int64], yaw: NDArray[np.float64], edges: NDArray[np.int64],
                  base: int) -> NDArray[np.float64]:
    """Mean yaw rate (rad/s) of a cumulative yaw track over each bin between edges."""
    y = np.interp((edges - base) * 1e-9, (t - base) * 1e-9, yaw)
    return np.diff(y) / (np.diff(edges) * 1e-9)


def yaw_rate_gain(subject: str, gyro_name: str, t_ref: NDArray[np.int64],
                  yaw_ref: NDArray[np.float64], t_gyro: NDArray[np.int64],
                  yaw_gyro: NDArray[np.float64], what_fixes: str, bin_s: float = 0.2
                  ) -> Check:
    """subject's yaw rate = gain x the gyro's + offset (reduced major axis over bin_s means
    where either turns), and their correlation; problem outside 0.9-1.1.
    what_fixes: what params.yaml does about a gain outside the range."""
    lo, hi = max(t_ref[0], t_gyro[0]), min(t_ref[-1], t_gyro[-1])
    edges = np.arange(lo, hi, int(bin_s * 1e9), dtype=np.int64)
    name = 'yaw_rate_gain'
    label = f'{subject} vs {gyro_name}'
    if edges.size < 20:
        return Check(name, label, SKIPPED, None, '',
                     f'not judged: {subject} and {gyro_name} overlap {max(0, hi - lo) * 1e-9:.1f}'
                     ' s only')
    w_ref = _binned_rates(t_ref, yaw_ref, edges, lo)
    w_gyro = _binned_rates(t_gyro, yaw_gyro, edges, lo)
    turned = float(np.abs(w_gyro).sum() * bin_s)
    turning = (np.abs(w_gyro) > 0.05) | (np.abs(w_ref) > 0.05)
    if turned < MIN_TURN_RAD or turning.sum() < 20:
        return Check(name, label, SKIPPED, None, '',
                     f'not judged: the robot turns {math.degrees(turned):.0f} deg by the gyro '
                     f'(a gain needs {math.degrees(MIN_TURN_RAD):.0f} deg)')
    # Reduced major axis: symmetric in the two sources (a regression of either on the other
    # shrinks the gain by their correlation, and a slipping base's yaw rate hardly
    # correlates with the gyro's).
    x, y = w_gyro[turning], w_ref[turning]
    r = float(np.corrcoef(x, y)[0, 1])
    gain = math.copysign(float(np.std(y) / np.std(x)), r)
    offset = float(np.mean(y) - gain * np.mean(x))
    gain_std = abs(gain) * math.sqrt(max(1.0 - r * r, 0.0) / x.size)
    verdict = OK if GAIN_LOW <= gain <= GAIN_HIGH else PROBLEM
    shown = (f'{_named(subject, "turn")} {gain:.2f} +- {gain_std:.2f} times as fast as '
             f'{gyro_name}\'s '
             f'gyro (offset {math.degrees(offset):+.2f} deg/s, correlation {r:.2f}) over '
             f'{math.degrees(turned):.0f} deg of turning')
    advice = (f'{shown}: they agree' if verdict == OK else
              f'{shown}: skid steer or wrong track width; {what_fixes}')
    return Check(name, label, verdict, gain, 'x the gyro', advice,
                 f'{GAIN_LOW:g} - {GAIN_HIGH:g}',
                 {'gain': gain, 'gain_std': gain_std, 'offset_rad_s': offset,
                  'correlation': r, 'turned_deg': math.degrees(turned), 'bins': int(x.size)})


def speed_scale(subject: str, distances: NDArray[np.float64],
                reference: NDArray[np.float64], what_fixes: str) -> Check:
    """A source's distance over intervals against scan matching's (m, forward component of
    each interval): the scale that fits them through the origin, over intervals that drive
    at least 5 cm; problem beyond 2.5 %."""
    ok = np.isfinite(distances) & np.isfinite(reference) & (np.abs(reference) >= 0.05)
    path = float(np.abs(reference[ok]).sum())
    if ok.sum() < 10 or path < 2.0:
        return Check('speed_scale', f'{subject} vs scan matching', SKIPPED, None, '%',
                     f'not judged: {path:.1f} m of driving between matched scans (a scale '
                     'needs 2 m)')
    x, y = reference[ok], distances[ok]
    scale = float((x * y).sum() / (x * x).sum())
    residual = y - scale * x
    std = math.sqrt(float((residual ** 2).sum()) / max(x.size - 1, 1) / float((x * x).sum()))
    pct = 100.0 * (scale - 1.0)
    verdict = OK if abs(pct) < SPEED_WARN_PCT else (
        WARNING if abs(pct) < SPEED_PROBLEM_PCT else PROBLEM)
    shown = (f'{_named(subject, "travel")} {scale:.4f} +- {std:.4f} times the distance '
             f'scan matching does ({pct:+.2f} %, over {path:.1f} m)')
    return Check('speed_scale', f'{subject} vs scan matching', verdict, pct, '%',
                 shown if verdict == OK else f'{shown}: a wheel radius scale; {what_fixes}',
                 f'|scale - 1| < {SPEED_WARN_PCT:g} %',
                 {'scale': scale, 'scale_std': std, 'path_m': path, 'intervals': int(ok.sum())})


def orientation_check(subject: str, orientation: NDArray[np.float64],
                      orientation_var: NDArray[np.float64], gyro_turned_rad: float
                      ) -> Check:
    """The IMU's own orientation (K, 4) x y z w and its covariance diagonal (K, 3): constant
    while the gyro turns, identity throughout, or with zero covariance, a filter cannot use
    it (problem); the preset integrates the gyro instead."""
    q = np.asarray(orientation, dtype=float)
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    # The largest rotation from the first orientation (deg).
    spread_deg = math.degrees(2.0 * math.acos(min(1.0, float(np.min(np.abs(q @ q[0]))))))
    identity = bool(np.allclose(q, [0.0, 0.0, 0.0, 1.0], atol=1e-9))
    constant = spread_deg < 1e-3
    zero_cov = bool(np.all(np.asarray(orientation_var) == 0.0))
    faults = []
    if identity:
        faults.append('is the identity (0, 0, 0, 1) in every message')
    elif constant and gyro_turned_rad > math.radians(5.0):
        faults.append(f'is the same quaternion in every message while the gyro turns '
                      f'{math.degrees(gyro_turned_rad):.0f} deg')
    if zero_cov:
        faults.append('has a covariance of all zeros (REP 145: unknown)')
    details = {'spread_deg': spread_deg, 'identity': identity, 'constant': constant,
               'zero_covariance': zero_cov, 'gyro_turned_deg': math.degrees(gyro_turned_rad)}
    if not faults:
        return Check('imu_orientation', subject, OK, spread_deg, 'deg',
                     f'the orientation moves ({spread_deg:.0f} deg over the bag) and carries a '
                     'covariance', 'not constant, covariance set', details)
    unusable = identity or (constant and gyro_turned_rad > math.radians(5.0))
    return Check('imu_orientation', subject, PROBLEM, spread_deg, 'deg',
                 f'the orientation {" and ".join(faults)}: '
                 + ('no orientation was estimated (a driver that fills the field with a '
                    'placeholder): params.yaml integrates the gyro instead'
                    if unusable else 'a filter takes it as exact or rejects the rest: '
                    'params.yaml gives it the noise model instead (covariance: model)'),
                 'not constant, covariance set', details)


def heading_agreement(a: str, b: str, t_a: NDArray[np.int64], yaw_a: NDArray[np.float64],
                      t_b: NDArray[np.int64], yaw_b: NDArray[np.float64], step_s: float = 0.5
                      ) -> Check:
    """Two sources' headings over the run, both anchored at their common start: the largest
    and the final difference (deg), against the turning (deg) the pair saw."""
    lo, hi = max(t_a[0], t_b[0]), min(t_a[-1], t_b[-1])
    name, label = 'heading_agreement', f'{a} vs {b}'
    edges = np.arange(lo, hi, int(step_s * 1e9), dtype=np.int64)
    if edges.size < 10:
        return Check(name, label, SKIPPED, None, 'deg',
                     f'not judged: they overlap {max(0, hi - lo) * 1e-9:.1f} s only')
    ya = np.interp((edges - lo) * 1e-9, (t_a - lo) * 1e-9, yaw_a)
    yb = np.interp((edges - lo) * 1e-9, (t_b - lo) * 1e-9, yaw_b)
    turned = max(float(np.abs(np.diff(ya)).sum()), float(np.abs(np.diff(yb)).sum()))
    if turned < MIN_TURN_RAD:
        return Check(name, label, SKIPPED, None, 'deg',
                     f'not judged: they turn {math.degrees(turned):.0f} deg (a comparison needs '
                     f'{math.degrees(MIN_TURN_RAD):.0f} deg)')
    diff = np.degrees((ya - ya[0]) - (yb - yb[0]))
    largest = float(np.abs(diff).max())
    share = math.radians(largest) / turned
    final = float(diff[-1])
    verdict = PROBLEM if largest >= HEADING_PROBLEM_DEG and share >= HEADING_PROBLEM_SHARE else (
        WARNING if largest >= HEADING_WARN_DEG and share >= HEADING_WARN_SHARE else OK)
    shown = (f'{a} and {b} drift up to {largest:.1f} deg apart ({100 * share:.1f} % of '
             f'{math.degrees(turned):.0f} deg turned; {final:+.1f} deg at the end)')
    return Check(name, label, verdict, largest, 'deg',
                 shown if verdict == OK else
                 f'{shown}: one of them turns another amount than the robot does',
                 f'< {HEADING_WARN_DEG:g} deg or < {100 * HEADING_WARN_SHARE:g} % of the turning',
                 {'largest_deg': largest, 'final_deg': final, 'turned_deg': math.degrees(turned),
                  'share': share})
