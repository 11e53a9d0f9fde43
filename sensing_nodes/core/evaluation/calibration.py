"""Odometry, laser-mount and gyro calibration against scan-matched motion (no ground truth).

Method (Censi, Franchi, Marchionni, Oriolo, "Simultaneous calibration of odometry and sensor
parameters for mobile robots", IEEE T-RO 29(2), 2013): the bag is cut into intervals between
two scans; over each, the encoders give the wheel angle increments and the package's ICP gives
the laser's motion s_k (laser frame). A differential drive with wheel radii r_L, r_R and
separation b moves base_link by o_k(r_L, r_R, b); the laser mounted at l = (l_x, l_y, l_yaw) in
base_link then moves by s_k = (-l) (+) o_k (+) l. The closed form solves first the rotation
(s_yaw = J21 dphi_L + J22 dphi_R, J21 = -r_L/b, J22 = r_R/b, linear least squares), then b and
l from the translations (a quadratic form constrained to cos^2 + sin^2 = 1, solved through a
2x2 eigenproblem). A weighted nonlinear least squares (scipy) over all six parameters, with
intervals integrated encoder sample by encoder sample and outliers rejected, refines it and
gives the covariance. The gyro's bias and scale factor follow from the integrated yaw rate
against the scan-matched rotation over the same intervals.

Units: m, rad, s; times int64 ns; wheel angles rad [left, right]; scan points (N, 2) m in the
laser frame; parameters [left radius m, right radius m, separation m, laser x m, laser y m,
laser yaw rad]; poses (x, y, yaw) as in core/geometry/se2.py.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares

from sensing_nodes.core import icp
from sensing_nodes.core.geometry.se2 import Pose2, wrap_angle
from sensing_nodes.core.scan_matching import mount_transform
from sensing_nodes.core.wheel_odometry import body_increments, integrate_path, step_columns

PARAMETERS = ('left_radius_m', 'right_radius_m', 'wheel_separation_m', 'laser_x_m',
              'laser_y_m', 'laser_yaw_rad')
# A parameter whose share of a near-null direction of the (scaled) information matrix exceeds
# this is not excited by the motion in the bag.
_NULL_SHARE = 0.1
_NULL_EIGEN_RATIO = 1e-9


class CalibrationError(ValueError):
    """The data cannot support a calibration; the message says why."""


@dataclass(frozen=True)
class Geometry:
    """Differential-drive geometry and laser mount: radii and separation (m), laser pose in
    base_link (m, m, rad)."""

    left_radius_m: float
    right_radius_m: float
    wheel_separation_m: float
    laser_x_m: float
    laser_y_m: float
    laser_yaw_rad: float

    def vector(self) -> NDArray[np.float64]:
        """The six numbers in PARAMETERS order."""
        return np.array([getattr(self, name) for name in PARAMETERS], dtype=float)

    @classmethod
    def from_vector(cls, values: Sequence[float]) -> Geometry:
        """Geometry from six numbers in PARAMETERS order."""
        return cls(*(float(v) for v in values))

    @property
    def laser_pose(self) -> Pose2:
        return (self.laser_x_m, self.laser_y_m, self.laser_yaw_rad)


@dataclass(frozen=True)
class IntervalOptions:
    """How the bag is cut: an interval ends at the first scan after the nominal odometry moved
    `distance_m` along its path or turned `angle_rad`, or after `max_duration_s`; scans or
    encoder samples further apart than `max_gap_s` break the chain. Intervals that moved less
    than `still_distance_m` and `still_angle_rad` are still (they only serve the gyro)."""

    distance_m: float = 0.5
    angle_rad: float = math.radians(45.0)
    max_duration_s: float = 2.0
    max_gap_s: float = 0.5
    still_distance_m: float = 1e-3
    still_angle_rad: float = math.radians(0.1)
    # ICP acceptance: error and inlier gates as icp_matcher's defaults; tighter jump gates
    # (the guess is one interval of odometry, a few mm and tenths of a degree off).
    max_error_m: float = 0.05
    max_jump_m: float = 0.3
    max_jump_rad: float = math.radians(15.0)
    min_inlier_fraction: float = 0.3
    min_points: int = 20


@dataclass(frozen=True)
class Intervals:
    """Synchronised intervals: scan-matched laser motion and the encoder increments inside.

    t0_ns, t1_ns (K,): interval ends (scan stamps); laser_motion (K, 3) ICP result (laser frame
    at t0); laser_covariance (K, 3, 3); wheel_steps (M, 2) encoder angle increments (rad) of
    every encoder step inside the intervals, interval by interval, starting at step_start (K,)
    (step counts step_count (K,)); still (K,) bool; rejected: reason -> count of intervals
    whose match was refused.
    """

    t0_ns: NDArray[np.int64]
    t1_ns: NDArray[np.int64]
    laser_motion: NDArray[np.float64]
    laser_covariance: NDArray[np.float64]
    wheel_steps: NDArray[np.float64]
    step_start: NDArray[np.intp]
    step_count: NDArray[np.intp]
    still: NDArray[np.bool_]
    rejected: dict[str, int] = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.t0_ns.size)

    def select(self, keep: NDArray[np.bool_]) -> Intervals:
        """The intervals where keep is True (encoder steps re-packed)."""
        keep = np.asarray(keep, dtype=bool)
        idx = np.flatnonzero(keep)
        steps = [self.wheel_steps[self.step_start[i]:self.step_start[i] + self.step_count[i]]
                 for i in idx]
        counts = self.step_count[idx]
        starts = np.concatenate(([0], np.cumsum(counts)[:-1])).astype(np.intp) if idx.size \
            else np.zeros(0, np.intp)
        return Intervals(self.t0_ns[idx], self.t1_ns[idx], self.laser_motion[idx],
                         self.laser_covariance[idx],
                         np.concatenate(steps) if steps else np.zeros((0, 2)),
                         starts, counts, self.still[idx], dict(self.rejected))


@dataclass(frozen=True)
class Estimate:
    """One calibrated number: value and standard deviation (unit in `unit`), or not excited
    (value None) with the reason in `note`."""

    name: str
    value: float | None
    std: float | None
    unit: str
    note: str = ''

    @property
    def excited(self) -> bool:
        return self.value is not None


@dataclass(frozen=True)
class GyroCalibration:
    """Gyro z bias (rad/s) and scale factor error (reads (1 + scale) x true rate), each an
    Estimate, from `intervals` intervals; residual_std_rad is the scatter of the fit (rad)."""

    bias: Estimate
    scale: Estimate
    intervals: int
    residual_std_rad: float


@dataclass(frozen=True)
class CalibrationResult:
    """Estimates in PARAMETERS order, the 6x6 covariance and correlation over the excited ones
    (NaN rows/columns for the rest), the closed-form solution, what the bag's motion covered,
    how many intervals were used, rejected as outliers, or refused by the matcher, and the
    random wheel error the residuals show (variance per metre of wheel travel, the model of
    core/wheel_odometry.py)."""

    nominal: Geometry
    estimates: tuple[Estimate, ...]
    covariance: NDArray[np.float64]
    correlation: NDArray[np.float64]
    closed_form: Geometry | None
    intervals_used: int
    outliers: int
    refused: dict[str, int]
    distance_m: float
    turned_rad: float
    residual_std: tuple[float, float, float]
    notes: tuple[str, ...]
    wheel_variance_per_m: float = float('nan')    # fitted random wheel error (m^2 per m)
    gyro: GyroCalibration | None = None

    def geometry(self) -> Geometry:
        """The calibrated geometry, nominal values where a parameter was not excited."""
        values = [e.value if e.excited else getattr(self.nominal, e.name)
                  for e in self.estimates]
        return Geometry.from_vector(values)

    def estimate(self, name: str) -> Estimate:
        return self.estimates[PARAMETERS.index(name)]


# --- synchronisation ------------------------------------------------------------------------

def _interp_angles(joint_t: NDArray[np.int64], joint_pos: NDArray[np.float64],
                   t: NDArray[np.int64]) -> NDArray[np.float64]:
    """Wheel angles (rad) linearly interpolated at stamps t (ns)."""
    base = joint_t[0]
    x = (joint_t - base).astype(float)
    q = (np.asarray(t) - base).astype(float)
    return np.column_stack([np.interp(q, x, joint_pos[:, i]) for i in range(2)])


def nominal_motion(steps: NDArray[np.float64], geometry: Geometry) -> Pose2:
    """base_link motion (x, y, yaw) from encoder increments (M, 2) with the given geometry."""
    out = integrate_intervals(steps, np.array([0]), np.array([len(steps)]),
                              geometry.vector()[:3])
    return tuple(float(v) for v in out[0])


def integrate_intervals(steps: NDArray[np.float64], starts: NDArray[np.intp],
                        counts: NDArray[np.intp], wheels: Sequence[float]) -> NDArray[np.float64]:
    """base_link motion (K, 3) over each interval (frame at its start) from encoder increments
    (M, 2) rad, interval k being steps[starts[k]:starts[k] + counts[k]]; wheels = (r_L, r_R, b)."""
    r_l, r_r, b = (float(w) for w in wheels)
    k = len(starts)
    out = np.zeros((k, 3))
    if steps.shape[0] == 0:
        return out
    ds_left, ds_right = steps[:, 0] * r_l, steps[:, 1] * r_r
    _, dtheta = body_increments(ds_left, ds_right, b)
    owner = np.repeat(np.arange(k), counts)
    turned = np.cumsum(dtheta)
    offset = np.zeros(k)
    nonempty = counts > 0
    offset[nonempty] = turned[starts[nonempty]] - dtheta[starts[nonempty]]
    yaw_before = turned - dtheta - offset[owner]
    dx, dy = step_columns(yaw_before, ds_left, ds_right, b)[:2]
    out[:, 0] = np.bincount(owner, dx, minlength=k)
    out[:, 1] = np.bincount(owner, dy, minlength=k)
    out[:, 2] = np.bincount(owner, dtheta, minlength=k)
    return out


def laser_motion_of(base_motion: NDArray[np.float64], laser: Sequence[float]
                    ) -> NDArray[np.float64]:
    """Laser motion (K, 3) in its own frame for base_link motions (K, 3): (-l) (+) o (+) l."""
    lx, ly, lyaw = (float(v) for v in laser)
    o = np.asarray(base_motion, dtype=float)
    c, s = np.cos(o[:, 2]), np.sin(o[:, 2])
    tx = o[:, 0] + c * lx - s * ly - lx
    ty = o[:, 1] + s * lx + c * ly - ly
    cl, sl = math.cos(lyaw), math.sin(lyaw)
    return np.column_stack((cl * tx + sl * ty, -sl * tx + cl * ty, o[:, 2]))


def _interval_ends(st: NDArray[np.int64], path: NDArray[np.float64], turn: NDArray[np.float64],
                   gaps_t: NDArray[np.int64], gap_ns: int,
                   options: IntervalOptions) -> list[tuple[int, int]]:
    """(first, last) scan indices of each interval: consecutive scans until the nominal path
    length, turning or duration reaches the options' limit; a gap in the scans or the encoder
    samples (gaps_t: encoder stamps followed by one) ends an interval unused."""
    ends: list[tuple[int, int]] = []
    i = 0
    max_ns = int(options.max_duration_s * 1e9)
    while i < st.size - 1:
        j = i + 1
        broken = False
        while j < st.size:
            if st[j] - st[j - 1] > gap_ns or np.any((gaps_t >= st[j - 1]) & (gaps_t < st[j])):
                broken = True
                break
            if (path[j] - path[i] >= options.distance_m or turn[j] - turn[i] >= options.angle_rad
                    or st[j] - st[i] >= max_ns):
                break
            j += 1
        if broken:
            i = j
            continue
        if j >= st.size:
            break
        ends.append((i, j))
        i = j
    return ends


def _refusal(result, guess: NDArray[np.float64], options: IntervalOptions) -> str:
    """Why an interval's scan match is not used ('' when it is): not converged, degenerate,
    a large alignment error, or far (m, rad) from the odometry guess."""
    if not result.converged:
        return 'not converged'
    if result.degenerate:
        return 'degenerate geometry'
    if not result.error <= options.max_error_m:
        return 'alignment error too large'
    dx, dy = result.x - guess[0], result.y - guess[1]
    if (math.hypot(dx, dy) > options.max_jump_m
            or abs(float(wrap_angle(result.yaw - guess[2]))) > options.max_jump_rad):
        return 'far from the odometry guess'
    return ''


def _encoder_steps(joint_t: NDArray[np.int64], joint_pos: NDArray[np.float64], t0: int,
                   t1: int) -> NDArray[np.float64]:
    """Encoder increments (rad) from t0 to t1: interpolated ends, recorded samples between."""
    lo = np.searchsorted(joint_t, t0, side='right')
    hi = np.searchsorted(joint_t, t1, side='left')
    ends = _interp_angles(joint_t, joint_pos, np.array([t0, t1]))
    angles = np.vstack((ends[:1], joint_pos[lo:hi], ends[1:]))
    return np.diff(angles, axis=0)


def sweep_motion(joint_t: NDArray[np.int64], joint_pos: NDArray[np.float64], stamp_ns: int,
                 sweep_s: float, geometry: Geometry) -> Pose2:
    """base_link's motion (m, rad) over a scan's sweep, from its stamp to sweep_s later, as the
    encoders show it through `geometry` (the stamp's base frame)."""
    return nominal_motion(_encoder_steps(joint_t, joint_pos, int(stamp_ns),
                                         int(stamp_ns + round(sweep_s * 1e9))), geometry)


def deskew_scans(joint_t: NDArray[np.int64], joint_pos: NDArray[np.float64],
                 scan_t: NDArray[np.int64], scan_points: Sequence[NDArray[np.float64]],
                 beam_times: Sequence[NDArray[np.float64]], geometry: Geometry
                 ) -> list[NDArray[np.float64]]:
    """Each scan's points (laser frame, m) moved to where the laser was at the scan's stamp,
    beam_times[i] (s after the stamp) giving when each point was taken and the encoders the
    base's motion over the sweep (its mean twist, through `geometry`'s wheels and laser mount).
    Scans outside the encoder recording are kept as they are."""
    from sensing_nodes.core.deskew import deskew

    out = []
    for stamp, points, times in zip(scan_t, scan_points, beam_times):
        sweep = float(times.max()) if times.size else 0.0
        end = int(stamp) + round(sweep * 1e9)
        if sweep <= 0.0 or stamp < joint_t[0] or end > joint_t[-1]:
            out.append(points)
            continue
        dx, dy, dyaw = sweep_motion(joint_t, joint_pos, int(stamp), sweep, geometry)
        out.append(deskew(points, (dx / sweep, dy / sweep, dyaw / sweep), times,
                          geometry.laser_pose))
    return out


def _packed(t0s: list, t1s: list, motions: list, covs: list, step_list: list, stills: list,
            rejected: dict[str, int]) -> Intervals:
    """The matched intervals' lists as one Intervals (encoder steps concatenated)."""
    counts = np.array([len(s) for s in step_list], dtype=np.intp)
    starts = np.concatenate(([0], np.cumsum(counts)[:-1])).astype(np.intp) if counts.size \
        else np.zeros(0, np.intp)
    return Intervals(np.array(t0s, dtype=np.int64), np.array(t1s, dtype=np.int64),
                     np.array(motions, dtype=float).reshape(-1, 3),
                     np.array(covs, dtype=float).reshape(-1, 3, 3),
                     np.concatenate(step_list) if step_list else np.zeros((0, 2)),
                     starts, counts, np.array(stills, dtype=bool), rejected)


# long: one pass in its order (cut at scans, guess from the encoders, match, refuse or keep).
def make_intervals(joint_t: NDArray[np.int64], joint_pos: NDArray[np.float64],
                   scan_t: NDArray[np.int64], scan_points: Sequence[NDArray[np.float64]],
                   nominal: Geometry, options: IntervalOptions = IntervalOptions(),
                   progress: Callable[[int, int], None] | None = None,
                   beam_times: Sequence[NDArray[np.float64]] | None = None) -> Intervals:
    """Cut the bag into intervals between scans and scan-match each (see IntervalOptions).

    joint_t (J,) ns sorted, joint_pos (J, 2) rad [left, right]; scan_t (S,) ns sorted with
    scan_points[i] (N_i, 2) in the laser frame, taken beam_times[i] (s after the stamp) when
    the scanner sweeps (deskewed by the nominal odometry first; None: every beam at the
    stamp). The ICP starts from the nominal odometry seen through the nominal mount.
    progress(done, total) is called now and then.
    """
    joint_t = np.asarray(joint_t, dtype=np.int64)
    joint_pos = np.asarray(joint_pos, dtype=float)
    scan_t = np.asarray(scan_t, dtype=np.int64)
    if beam_times is not None:
        scan_points = deskew_scans(joint_t, joint_pos, scan_t, scan_points, beam_times, nominal)
    inside = (scan_t >= joint_t[0]) & (scan_t <= joint_t[-1])
    scan_idx = np.flatnonzero(inside)
    if scan_idx.size < 2:
        raise CalibrationError('fewer than two scans fall inside the encoder recording')
    at_scans = _interp_angles(joint_t, joint_pos, scan_t[scan_idx])
    gap_ns = int(options.max_gap_s * 1e9)
    joint_gaps = np.flatnonzero(np.diff(joint_t) > gap_ns)
    r_l, r_r, b = nominal.left_radius_m, nominal.right_radius_m, nominal.wheel_separation_m

    # Path length and turning of the nominal odometry at each scan, for cutting.
    ds_scan, dth_scan = body_increments(np.diff(at_scans[:, 0]) * r_l,
                                        np.diff(at_scans[:, 1]) * r_r, b)
    path = np.concatenate(([0.0], np.cumsum(np.abs(ds_scan))))
    turn = np.concatenate(([0.0], np.cumsum(np.abs(dth_scan))))
    st = scan_t[scan_idx]
    ends = _interval_ends(st, path, turn, joint_t[joint_gaps], gap_ns, options)

    t0s, t1s, motions, covs, step_list, stills = [], [], [], [], [], []
    rejected: dict[str, int] = {}
    match_options = dict(min_inlier_fraction=options.min_inlier_fraction,
                         min_points=options.min_points)
    laser_nominal = nominal.laser_pose
    for n, (i, j) in enumerate(ends):
        if progress is not None and n % 20 == 0:
            progress(n, len(ends))
        a, bidx = scan_idx[i], scan_idx[j]
        steps = _encoder_steps(joint_t, joint_pos, int(st[i]), int(st[j]))
        guess_base = nominal_motion(steps, nominal)
        still = (path[j] - path[i] < options.still_distance_m
                 and turn[j] - turn[i] < options.still_angle_rad)
        target_pts, source_pts = scan_points[a], scan_points[bidx]
        if len(target_pts) < options.min_points or len(source_pts) < options.min_points:
            rejected['too few points'] = rejected.get('too few points', 0) + 1
            continue
        guess = mount_transform(guess_base, laser_nominal)
        result = icp.match(source_pts, icp.prepare_target(target_pts), guess, **match_options)
        reason = _refusal(result, guess, options)
        if reason:
            rejected[reason] = rejected.get(reason, 0) + 1
            continue
        t0s.append(st[i])
        t1s.append(st[j])
        motions.append(result.pose)
        covs.append(result.covariance)
        step_list.append(steps)
        stills.append(still)
    if progress is not None:
        progress(len(ends), len(ends))
    return _packed(t0s, t1s, motions, covs, step_list, stills, rejected)


# --- closed form ----------------------------------------------------------------------------

def _robust_std(x: NDArray[np.float64]) -> float:
    """Standard deviation from the median absolute deviation (robust to outliers)."""
    if x.size == 0:
        return float('nan')
    return float(1.4826 * np.median(np.abs(x - np.median(x))))


def closed_form(intervals: Intervals, reject_sigma: float = 4.0) -> tuple[Geometry, NDArray]:
    """Censi et al.'s closed-form solution over the moving intervals, and the mask of intervals
    kept (the rotation fit rejects outliers beyond reject_sigma robust std). Raises
    CalibrationError when the system is singular (no turning or no straight driving)."""
    totals = np.add.reduceat(intervals.wheel_steps, intervals.step_start, axis=0) \
        if len(intervals) else np.zeros((0, 2))
    totals[intervals.step_count == 0] = 0.0
    s = intervals.laser_motion
    keep = ~intervals.still
    for _ in range(3):
        a = totals[keep]
        if a.shape[0] < 4 or np.linalg.matrix_rank(a) < 2:
            raise CalibrationError('the motion does not excite both wheels independently')
        j, *_ = np.linalg.lstsq(a, s[keep, 2], rcond=None)
        res = s[:, 2] - totals @ j
        sigma = max(_robust_std(res[keep]), 1e-9)
        keep = ~intervals.still & (np.abs(res) <= reject_sigma * sigma)
    j21, j22 = float(j[0]), float(j[1])
    unit = integrate_intervals(intervals.wheel_steps, intervals.step_start,
                               intervals.step_count, (-j21, j22, 1.0))
    idx = np.flatnonzero(keep)
    m = np.zeros((5, 5))
    for k in idx:
        th = s[k, 2]
        c, sn = math.cos(th), math.sin(th)
        rows = np.array([
            [-unit[k, 0], 1.0 - c, sn, s[k, 0], -s[k, 1]],
            [-unit[k, 1], -sn, 1.0 - c, s[k, 1], s[k, 0]],
        ])
        m += rows.T @ rows
    a_blk, b_blk, d_blk = m[:3, :3], m[:3, 3:], m[3:, 3:]
    if np.linalg.cond(a_blk) > 1e12:
        raise CalibrationError('the translations do not determine separation and laser '
                               'position (no turns?)')
    schur = d_blk - b_blk.T @ np.linalg.solve(a_blk, b_blk)
    w, v = np.linalg.eigh(0.5 * (schur + schur.T))
    m2 = v[:, 0] / np.linalg.norm(v[:, 0])
    m1 = -np.linalg.solve(a_blk, b_blk @ m2)
    if m1[0] < 0:
        m1, m2 = -m1, -m2
    b = float(m1[0])
    geometry = Geometry(-j21 * b, j22 * b, b, float(m1[1]), float(m1[2]),
                        math.atan2(m2[1], m2[0]))
    return geometry, keep


# --- nonlinear refinement -------------------------------------------------------------------

def interval_residuals(intervals: Intervals, values: NDArray[np.float64]) -> NDArray[np.float64]:
    """Scan-matched minus predicted laser motion (K, 3) per interval for the six parameters
    `values` (PARAMETERS order); yaw wrapped (m, m, rad)."""
    base = integrate_intervals(intervals.wheel_steps, intervals.step_start,
                               intervals.step_count, values[:3])
    predicted = laser_motion_of(base, values[3:])
    res = intervals.laser_motion - predicted
    res[:, 2] = wrap_angle(res[:, 2])
    return res


def wheel_noise_shapes(intervals: Intervals, geometry: Geometry) -> NDArray[np.float64]:
    """(K, 3, 3) covariance of each interval's laser motion for a wheel travel variance of
    1 m^2 per m (the per-wheel random model of core/wheel_odometry.py), through the mount."""
    values = geometry.vector()
    out = np.zeros((len(intervals), 3, 3))
    base = integrate_intervals(intervals.wheel_steps, intervals.step_start, intervals.step_count,
                               values[:3])
    lx, ly, lyaw = values[3:]
    rot = np.array([[math.cos(lyaw), math.sin(lyaw)], [-math.sin(lyaw), math.cos(lyaw)]])
    for k in range(len(intervals)):
        steps = intervals.wheel_steps[intervals.step_start[k]:
                                      intervals.step_start[k] + intervals.step_count[k]]
        if steps.shape[0] == 0:
            continue
        _, covs = integrate_path((0.0, 0.0, 0.0), steps[:, 0] * values[0], steps[:, 1] * values[1],
                                 values[2], variance_per_m=(1.0, 1.0))
        c, s_ = math.cos(base[k, 2]), math.sin(base[k, 2])
        jac = np.zeros((3, 3))
        jac[:2, :2] = rot
        jac[:2, 2] = rot @ np.array([-s_ * lx - c * ly, c * lx - s_ * ly])
        jac[2, 2] = 1.0
        out[k] = jac @ covs[-1] @ jac.T
    return out


def _noise_model(res: NDArray[np.float64], wheel: NDArray[np.float64],
                 matcher: NDArray[np.float64]) -> tuple[float, float]:
    """(k_wheel m^2/m, matcher scale) of residual covariance k_wheel W_k + scale C_k + floor,
    by least squares on the residual outer products (method of moments), both >= tiny."""
    iu = np.triu_indices(3)
    outer = (res[:, :, None] * res[:, None, :])[:, iu[0], iu[1]].ravel()
    design = np.column_stack((wheel[:, iu[0], iu[1]].ravel(), matcher[:, iu[0], iu[1]].ravel()))
    norm = np.sqrt((design ** 2).sum(axis=0))
    norm[norm == 0] = 1.0
    from scipy.optimize import nnls

    coef, _ = nnls(design / norm, outer)
    coef = coef / norm
    return max(float(coef[0]), 1e-12), max(float(coef[1]), 1e-6)


def _whitener(cov: NDArray[np.float64]) -> NDArray[np.float64]:
    """(K, 3, 3) matrices L_k^-1 with L_k L_k^T = cov_k: L^-1 r has unit covariance."""
    chol = np.linalg.cholesky(cov)
    return np.linalg.inv(chol)


# Scales that make the parameters comparable when judging excitation: 1 mm of radius or
# separation, 1 cm of laser offset, 1 degree of laser yaw.
_SCALES = np.array([1e-3, 1e-3, 1e-3, 1e-2, 1e-2, math.radians(1.0)])


def _unexcited(jac: NDArray[np.float64], free: NDArray[np.bool_]) -> NDArray[np.bool_]:
    """Free parameters that lie in a near-null direction of the scaled information matrix."""
    if not free.any():            # nothing left free (a short bag: every parameter held)
        return np.zeros(free.size, dtype=bool)
    scaled = jac[:, free] * _SCALES[free]
    info = scaled.T @ scaled
    w, v = np.linalg.eigh(info)
    null = w <= _NULL_EIGEN_RATIO * max(w[-1], 1e-300)
    share = (v[:, null] ** 2).sum(axis=1)
    out = np.zeros(free.size, dtype=bool)
    out[np.flatnonzero(free)] = share > _NULL_SHARE
    return out


def _starting_geometry(intervals: Intervals, nominal: Geometry, reject_sigma: float,
                       notes: list[str]) -> tuple[Geometry | None, NDArray[np.float64]]:
    """The closed form and its parameter vector when it is solvable and physical, else (None,
    the nominal vector) with a note saying why."""
    try:
        closed, _ = closed_form(intervals, reject_sigma)
        start = closed.vector()
        if not np.all(np.isfinite(start)) or start[2] <= 0 or min(start[:2]) <= 0:
            raise CalibrationError('closed form gave a non-physical geometry')
    except (CalibrationError, np.linalg.LinAlgError) as exc:
        closed, start = None, nominal.vector()
        notes.append(f'closed form not solvable ({exc}); started from the nominal geometry')
    return closed, start


def _estimates(values: NDArray[np.float64], std: NDArray[np.float64], free: NDArray[np.bool_],
               limits: NDArray[np.float64]) -> list[Estimate]:
    """Each parameter's estimate, or why there is none: held (not excited) or its std over the
    limit (weakly excited); m, and rad for the laser yaw."""
    units = ('m', 'm', 'm', 'm', 'm', 'rad')
    estimates = []
    for i, name in enumerate(PARAMETERS):
        if not free[i]:
            estimates.append(Estimate(name, None, None, units[i],
                                      'not excited by the motion in the bag'))
        elif not std[i] <= limits[i]:
            estimates.append(Estimate(name, None, None, units[i],
                                      f'weakly excited: std {std[i]:.3g} {units[i]} exceeds '
                                      f'{limits[i]:.3g} {units[i]}'))
        else:
            estimates.append(Estimate(name, float(values[i]), float(std[i]), units[i]))
    return estimates


def _fit(sub: Intervals, covariance: NDArray[np.float64], values: NDArray[np.float64],
         free: NDArray[np.bool_]) -> NDArray[np.float64]:
    """Whitened least squares (interval covariances (K, 3, 3)) of the free parameters over the
    intervals; updates `values` in place, returns the (rows, 6) Jacobian (zero columns for held
    parameters)."""
    whiten = _whitener(covariance)

    def fun(p_free: NDArray[np.float64]) -> NDArray[np.float64]:
        p = values.copy()
        p[free] = p_free
        return np.einsum('kij,kj->ki', whiten, interval_residuals(sub, p)).ravel()

    result = least_squares(fun, values[free], x_scale=_SCALES[free], method='lm'
                           if free.sum() <= sub.t0_ns.size * 3 else 'trf')
    values[free] = result.x
    jac = np.zeros((result.fun.size, 6))
    jac[:, free] = result.jac
    return jac


def _parameter_covariance(
    jac: NDArray[np.float64],
    free: NDArray[np.bool_],
    res: NDArray[np.float64],
    cov: NDArray[np.float64],
) -> NDArray[np.float64]:
    """(6, 6) covariance of the parameters from the fit's Jacobian, scaled by the reduced
    chi-square of the residuals (K, 3) under their covariances (K, 3, 3) when above 1; NaN rows
    and columns for held parameters."""
    dof = max(res.size - int(free.sum()), 1)
    chi2 = max(float(np.einsum('ki,kij,kj->', res, np.linalg.inv(cov), res)) / dof, 1.0)
    jac_free = jac[:, free]
    covariance = np.full((6, 6), np.nan)
    covariance[np.ix_(free, free)] = np.linalg.pinv(jac_free.T @ jac_free) * chi2
    return covariance


# long: the estimation in its order (start, reweighted fit rejecting outliers, covariance,
# report), each step a helper above; cut further it would hand eight arrays around.
def calibrate(intervals: Intervals, nominal: Geometry, reject_sigma: float = 4.0,
              max_relative_std: float = 0.01, max_laser_std_m: float = 0.02,
              max_laser_yaw_std_rad: float = math.radians(1.0)) -> CalibrationResult:
    """Joint estimate of the six parameters from the moving intervals (see the module doc).

    Starts from the closed form when it is solvable, else from the nominal geometry; residuals
    are weighted per component by their robust standard deviation, intervals beyond
    reject_sigma are outliers; parameters the motion leaves in a null direction are held at
    nominal and reported as not excited, as are those whose std exceeds the given limits.
    """
    moving = ~intervals.still
    if moving.sum() < 6:
        raise CalibrationError(f'only {int(moving.sum())} intervals with motion were matched '
                               '(need at least 6): the robot must drive and turn')
    notes: list[str] = []
    base_nominal = integrate_intervals(intervals.wheel_steps, intervals.step_start,
                                       intervals.step_count, nominal.vector()[:3])
    distance = float(np.hypot(base_nominal[moving, 0], base_nominal[moving, 1]).sum())
    turned = float(np.abs(intervals.laser_motion[moving, 2]).sum())
    closed, start = _starting_geometry(intervals, nominal, reject_sigma, notes)

    data = intervals.select(moving)
    free = np.ones(6, dtype=bool)
    keep = np.ones(len(data), dtype=bool)
    values = start.copy()
    wheel_shape = wheel_noise_shapes(data, Geometry.from_vector(values))
    # A floor: the matcher's covariance alone can be optimistic (1 mm, 0.01 deg).
    matcher = data.laser_covariance + np.diag([1e-6, 1e-6, math.radians(0.01) ** 2])
    noise = (4e-6, 1.0)          # (wheel m^2/m as wheel_odometry's default, matcher scale)

    def fit(keep: NDArray[np.bool_], noise: tuple[float, float]) -> NDArray[np.float64]:
        sub = data.select(keep)
        return _fit(sub, noise[0] * wheel_shape[keep] + noise[1] * matcher[keep], values, free)

    for _round in range(8):
        if _round:
            noise = _noise_model(interval_residuals(data.select(keep), values), wheel_shape[keep],
                                 matcher[keep])
        jac = fit(keep, noise)
        unexcited = _unexcited(jac, free)
        if unexcited.any():
            names = ', '.join(PARAMETERS[i] for i in np.flatnonzero(unexcited))
            notes.append(f'not excited by the motion in the bag: {names} (held at nominal)')
            free &= ~unexcited
            values[~free] = nominal.vector()[~free]
            continue
        res = interval_residuals(data, values)
        cov_all = noise[0] * wheel_shape + noise[1] * matcher
        mahalanobis = np.einsum('ki,kij,kj->k', res, np.linalg.inv(cov_all), res)
        # Chi-square with 3 dof: 16 + 6 = 22 is about as rare as a 4-sigma normal residual.
        new_keep = mahalanobis <= reject_sigma ** 2 + 6.0
        if np.array_equal(new_keep, keep) and _round >= 2:
            break
        keep = new_keep
    if not free.any():
        raise CalibrationError('the motion in the bag excites none of the parameters')
    # The reported figures come from one consistent fit: the final intervals and noise model.
    jac = fit(keep, noise)
    sub = data.select(keep)
    res = interval_residuals(sub, values)
    cov_sub = noise[0] * wheel_shape[keep] + noise[1] * matcher[keep]
    sigma = np.array([_robust_std(res[:, c]) for c in range(3)])
    covariance = _parameter_covariance(jac, free, res, cov_sub)
    std = np.sqrt(np.diag(covariance))
    correlation = covariance / np.outer(std, std)
    limits = np.array([max_relative_std * nominal.left_radius_m,
                       max_relative_std * nominal.right_radius_m,
                       max_relative_std * nominal.wheel_separation_m,
                       max_laser_std_m, max_laser_std_m, max_laser_yaw_std_rad])
    estimates = _estimates(values, std, free, limits)
    if turned < math.radians(90.0):
        notes.append(f'the robot turned only {math.degrees(turned):.0f} deg in matched '
                     'intervals: separation and laser position need turns')
    return CalibrationResult(
        nominal=nominal, estimates=tuple(estimates), covariance=covariance,
        correlation=correlation, closed_form=closed, intervals_used=int(keep.sum()),
        outliers=int((~keep).sum()), refused=dict(intervals.rejected), distance_m=distance,
        turned_rad=turned, residual_std=tuple(float(v) for v in sigma), notes=tuple(notes),
        wheel_variance_per_m=float(noise[0]))


def calibrate_gyro(intervals: Intervals, imu_t: NDArray[np.int64], gyro_z: NDArray[np.float64],
                   reject_sigma: float = 4.0, min_turn_rad: float = math.radians(90.0)
                   ) -> GyroCalibration:
    """Gyro z bias (rad/s) and scale factor error from every matched interval inside the IMU
    recording: integral of the rate = (1 + scale) x scan-matched rotation + bias x duration."""
    from sensing_nodes.core.gyro import integrate_rate

    imu_t = np.asarray(imu_t, dtype=np.int64)
    heading = integrate_rate(imu_t, np.asarray(gyro_z, dtype=float))
    inside = (intervals.t0_ns >= imu_t[0]) & (intervals.t1_ns <= imu_t[-1])
    if inside.sum() < 3:
        raise CalibrationError('fewer than three matched intervals fall inside the IMU recording')
    base = float(imu_t[0])
    h0 = np.interp(intervals.t0_ns[inside] - base, imu_t - base, heading)
    h1 = np.interp(intervals.t1_ns[inside] - base, imu_t - base, heading)
    measured = h1 - h0
    rotation = intervals.laser_motion[inside, 2]
    duration = (intervals.t1_ns[inside] - intervals.t0_ns[inside]) * 1e-9
    turned = float(np.abs(rotation).sum())
    fit_scale = turned >= min_turn_rad
    a = np.column_stack((rotation, duration)) if fit_scale else duration[:, None]
    y = measured - (0.0 if fit_scale else rotation)
    keep = np.ones(y.size, dtype=bool)
    for _ in range(4):
        coef, *_ = np.linalg.lstsq(a[keep], y[keep], rcond=None)
        res = y - a @ coef
        sigma = max(_robust_std(res[keep]), 1e-9)
        new_keep = np.abs(res) <= reject_sigma * sigma
        if np.array_equal(new_keep, keep):
            break
        keep = new_keep
    res = (y - a @ coef)[keep]
    dof = max(int(keep.sum()) - a.shape[1], 1)
    s2 = float(res @ res) / dof
    cov = np.linalg.inv(a[keep].T @ a[keep]) * s2
    if fit_scale:
        scale = Estimate('gyro_scale_error', float(coef[0] - 1.0), float(math.sqrt(cov[0, 0])), '')
        bias = Estimate('gyro_bias_rad_s', float(coef[1]), float(math.sqrt(cov[1, 1])), 'rad/s')
    else:
        scale = Estimate('gyro_scale_error', None, None, '',
                         f'not excited: only {math.degrees(turned):.0f} deg turned while the IMU '
                         f'recorded (need {math.degrees(min_turn_rad):.0f})')
        bias = Estimate('gyro_bias_rad_s', float(coef[0]), float(math.sqrt(cov[0, 0])), 'rad/s',
                        'scale assumed 1')
    return GyroCalibration(bias, scale, int(keep.sum()), float(math.sqrt(s2)))


# --- odometry time offset -----------------------------------------------------------------------

@dataclass(frozen=True)
class TimeOffset:
    """How far an odometry stream's stamps lag the scan matches': odometry stamped t describes
    the robot at t - delay_s (s; < 0: stamps early), with its bootstrap std (s). cost_rad[i] is
    the disagreement of yaw increments at grid_s[i] (rad, RMS of the best 1 - trim share)."""

    delay_s: float
    std_s: float
    grid_s: NDArray[np.float64]
    cost_rad: NDArray[np.float64]
    intervals: int
    turned_rad: float

    @property
    def cost_at_zero_rad(self) -> float:
        """The disagreement with no offset (rad)."""
        return float(np.interp(0.0, self.grid_s, self.cost_rad))

    @property
    def two_sided(self) -> bool:
        """The disagreement also falls well below its value at 0 on the other side of 0: no
        single delay explains it (e.g. odometry re-anchored at the scans, docs/calibration.md)."""
        at_zero = self.cost_at_zero_rad
        other = self.cost_rad[self.grid_s * self.delay_s < 0.0]
        drop = at_zero - float(self.cost_rad.min())
        return other.size > 0 and drop > 0.0 and at_zero - float(other.min()) > 0.5 * drop


def _trimmed_rms(residual: NDArray[np.float64], keep: int) -> NDArray[np.float64]:
    """Per row: RMS of the `keep` smallest absolute residuals (rad)."""
    part = np.partition(residual * residual, keep - 1, axis=-1)[..., :keep]
    return np.sqrt(part.mean(axis=-1))


def grid_minimum(grid: NDArray[np.float64], cost: NDArray[np.float64]) -> float:
    """Minimum of a sampled cost, refined by the parabola through it and its neighbours (s)."""
    i = int(np.argmin(cost))
    if i == 0 or i == len(grid) - 1:
        return float(grid[i])
    c0, c1, c2 = cost[i - 1], cost[i], cost[i + 1]
    curvature = c0 - 2.0 * c1 + c2
    shift = 0.5 * (c0 - c2) / curvature if curvature > 0.0 else 0.0
    return float(grid[i] + shift * (grid[1] - grid[0]))


def odometry_delay(odom_t: NDArray[np.int64], odom_yaw: NDArray[np.float64],
                   match_t: NDArray[np.int64], match_yaw: NDArray[np.float64],
                   max_delay_s: float = 0.5, step_s: float = 0.005, trim: float = 0.1,
                   min_turn_rad: float = math.radians(90.0), bootstrap: int = 200
                   ) -> TimeOffset:
    """Delay of odometry (stamps ns, yaw rad) against scan matches (cumulative poses' stamps ns
    and yaw rad): the offset d on a grid over +-max_delay_s at which the odometry's yaw
    increments read at (match stamps + d) agree best with the matches' own increments.

    The worst `trim` share of intervals is left out at every d (failed matches fall back on
    the odometry itself); the minimum is refined by a parabola; the std is the spread of that
    minimum over `bootstrap` resamplings of the intervals (fixed seed: reproducible)."""
    odom_t = np.asarray(odom_t, dtype=np.int64)
    match_t = np.asarray(match_t, dtype=np.int64)
    if len(odom_t) < 2 or np.any(np.diff(odom_t) <= 0):
        raise CalibrationError('odometry needs at least two samples with increasing stamps')
    if not (math.isfinite(max_delay_s) and max_delay_s > 0 and 0 < step_s <= max_delay_s):
        raise CalibrationError('max_delay_s and step_s must be > 0, step_s <= max_delay_s')
    base = odom_t[0]
    t = (odom_t - base) * 1e-9
    yaw = np.unwrap(np.asarray(odom_yaw, dtype=float))
    margin = max_delay_s + step_s
    m = (match_t - base) * 1e-9
    inside = (m - margin >= t[0]) & (m + margin <= t[-1])
    pairs = np.flatnonzero(inside[:-1] & inside[1:])
    if len(pairs) < 10:
        raise CalibrationError(f'only {len(pairs)} consecutive scan matches lie inside the '
                               'odometry recording (need 10)')
    matched = wrap_angle(np.asarray(match_yaw, dtype=float)[pairs + 1]
                         - np.asarray(match_yaw, dtype=float)[pairs])
    turned = float(np.abs(matched).sum())
    if turned < min_turn_rad:
        raise CalibrationError(f'the matches turn {math.degrees(turned):.0f} deg in all: a time '
                               f'offset needs turning (>= {math.degrees(min_turn_rad):.0f} deg)')
    n_steps = int(round(max_delay_s / step_s))
    grid = np.arange(-n_steps, n_steps + 1) * step_s
    at = m[None, :] + grid[:, None]                           # (grid, matches)
    odom_at = np.interp(at.ravel(), t, yaw).reshape(at.shape)
    residual = (odom_at[:, pairs + 1] - odom_at[:, pairs]) - matched[None, :]
    keep = max(1, int(math.floor((1.0 - trim) * len(pairs))))
    cost = _trimmed_rms(residual, keep)
    delay = grid_minimum(grid, cost)
    if abs(delay) >= max_delay_s:
        raise CalibrationError(f'the best agreement lies at the edge of the searched offsets '
                               f'(+-{max_delay_s:g} s): widen the search')
    rng = np.random.default_rng(0)
    draws = []
    for _ in range(bootstrap):
        sample = residual[:, rng.integers(0, len(pairs), len(pairs))]
        draws.append(grid_minimum(grid, _trimmed_rms(sample, keep)))
    std = float(np.std(draws)) if draws else float('nan')
    return TimeOffset(delay, std, grid, cost, len(pairs), turned)
