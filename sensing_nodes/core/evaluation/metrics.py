"""Comparing estimated trajectories with a reference (ground truth), all planar, SI units."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from sensing_nodes.core.geometry import se2


def interpolate_poses(
    t_ref: NDArray[np.int64], poses_ref: NDArray[np.float64], t_query: NDArray[np.int64]
) -> NDArray[np.float64]:
    """Reference poses (N, 3) at the query stamps (ns), linear in x, y and unwrapped yaw.
    Queries outside the reference's time span are NaN."""
    t_ref = np.asarray(t_ref, dtype=np.int64)
    t_query = np.asarray(t_query, dtype=np.int64)
    base = t_ref[0]
    tr, tq = (t_ref - base).astype(float), (t_query - base).astype(float)
    yaw = np.unwrap(poses_ref[:, 2])
    out = np.column_stack([np.interp(tq, tr, poses_ref[:, 0]), np.interp(tq, tr, poses_ref[:, 1]),
                           se2.wrap_angle(np.interp(tq, tr, yaw))])
    out[(t_query < t_ref[0]) | (t_query > t_ref[-1])] = np.nan
    return out


def express_in_reference_frame(
    origin: se2.Pose2, poses: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Poses of an estimate whose frame starts at `origin` (a reference-frame pose) -> reference
    frame."""
    xy = se2.transform_points(origin, poses[:, :2])
    return np.column_stack([xy, se2.wrap_angle(poses[:, 2] + origin[2])])


@dataclass
class TrajectoryErrors:
    """Per-sample errors of an estimate against the reference at the estimate's stamps."""

    t: NDArray[np.int64]
    position_m: NDArray[np.float64]
    heading_rad: NDArray[np.float64]
    xy_in_estimate_frame: NDArray[np.float64]  # (N, 2) error vectors, estimate's frame
    kept: NDArray[np.bool_]                    # which input samples had a reference

    def summary(self, with_position: bool = True) -> dict[str, float]:
        out = {}
        if with_position:
            out['final_position_error_m'] = float(self.position_m[-1])
            out['rms_position_error_m'] = float(np.sqrt(np.mean(self.position_m ** 2)))
        out['final_heading_error_deg'] = float(np.degrees(abs(self.heading_rad[-1])))
        out['rms_heading_error_deg'] = float(np.degrees(np.sqrt(np.mean(self.heading_rad ** 2))))
        return out


def trajectory_errors(
    t_ref: NDArray[np.int64], poses_ref: NDArray[np.float64],
    t_est: NDArray[np.int64], poses_est: NDArray[np.float64],
) -> TrajectoryErrors:
    """Errors of an estimate that starts at identity in its own frame, anchored at the
    reference pose of its first stamp (how odometry frames are defined, REP 105)."""
    reference = interpolate_poses(t_ref, poses_ref, t_est)
    keep = np.all(np.isfinite(reference), axis=1)
    t_est, poses_est, reference = np.asarray(t_est)[keep], poses_est[keep], reference[keep]
    origin = se2.compose(tuple(reference[0]), se2.inverse(tuple(poses_est[0])))
    aligned = express_in_reference_frame(origin, poses_est)
    error_map = aligned[:, :2] - reference[:, :2]
    heading = se2.wrap_angle(aligned[:, 2] - reference[:, 2])
    # The same error in the estimate's own frame, where its covariance is expressed.
    error_est = error_map @ se2.rotation(origin[2])
    return TrajectoryErrors(t_est, np.hypot(*error_map.T), np.asarray(heading), error_est, keep)


def aligned_trajectory_errors(
    t_ref: NDArray[np.int64], poses_ref: NDArray[np.float64],
    t_est: NDArray[np.int64], poses_est: NDArray[np.float64],
) -> TrajectoryErrors:
    """Errors of an estimate in a frame of its own after the rigid transform that best maps its
    positions onto the reference's at its stamps (align_rigid_2d): how far the two tracks depart,
    whatever the moment each started (anchored at one stamp, a start-up transient of a few
    degrees turns the whole track)."""
    reference = interpolate_poses(t_ref, poses_ref, t_est)
    keep = np.all(np.isfinite(reference), axis=1)
    t_est, poses_est, reference = np.asarray(t_est)[keep], poses_est[keep], reference[keep]
    if len(t_est) < 2:
        return trajectory_errors(t_ref, poses_ref, t_est, poses_est)
    origin = align_rigid_2d(reference[:, :2], poses_est[:, :2])
    aligned = express_in_reference_frame(origin, poses_est)
    error_map = aligned[:, :2] - reference[:, :2]
    heading = se2.wrap_angle(aligned[:, 2] - reference[:, 2])
    error_est = error_map @ se2.rotation(origin[2])
    return TrajectoryErrors(t_est, np.hypot(*error_map.T), np.asarray(heading), error_est, keep)


def path_length(poses: NDArray[np.float64]) -> float:
    """Distance travelled along a sampled trajectory (m)."""
    return float(np.sum(np.hypot(np.diff(poses[:, 0]), np.diff(poses[:, 1]))))


def sigma_consistency(
    errors_xy: NDArray[np.float64], covariances: NDArray[np.float64]
) -> dict[str, float]:
    """Share of samples whose position error lies within 1 and 3 sigma of the covariance's
    x/y block (Mahalanobis distance, 2 degrees of freedom)."""
    d2 = np.full(len(errors_xy), np.inf)
    for i, (e, c) in enumerate(zip(errors_xy, covariances[:, :2, :2])):
        if np.linalg.det(c) > 0:
            d2[i] = float(e @ np.linalg.solve(c, e))
    d = np.sqrt(d2)
    return {'within_3_sigma': float(np.mean(d <= 3.0)), 'beyond_1_sigma': float(np.mean(d > 1.0))}


# -- relative pose error (Kümmerle et al. 2009) and absolute trajectory error -----------------
@dataclass
class Relations:
    """Reference relative poses: the pose at t2 (ns) in the frame of the pose at t1 (x, y, yaw)."""

    t1: NDArray[np.int64]
    t2: NDArray[np.int64]
    motion: NDArray[np.float64]  # (N, 3)


def relations_from_trajectory(
    t_ref: NDArray[np.int64], poses_ref: NDArray[np.float64], delta_s: float = 0.0
) -> Relations:
    """Relations between reference samples: each sample to the first one at least delta_s later
    (delta_s = 0: to the next sample)."""
    t_ref = np.asarray(t_ref, dtype=np.int64)
    if delta_s > 0.0:
        j = np.searchsorted(t_ref, t_ref + int(round(delta_s * 1e9)), side='left')
    else:
        j = np.arange(1, len(t_ref) + 1)
    i = np.flatnonzero(j < len(t_ref))
    j = j[i]
    motion = np.array(
        [se2.between(tuple(poses_ref[a]), tuple(poses_ref[b])) for a, b in zip(i, j)]
    )
    return Relations(t_ref[i], t_ref[j], motion.reshape(-1, 3))


def read_relations(path: str, time_offset_ns: int = 0) -> Relations:
    """A relations file of the SLAM benchmark (`t1 t2 x y z roll pitch yaw` per line, times in
    seconds, the pose of t2 in the frame of t1); planar part kept. ValueError names the line."""
    rows = []
    with open(path) as handle:
        for number, line in enumerate(handle, start=1):
            words = line.split()
            if not words or words[0].startswith('#'):
                continue
            try:
                values = [float(w) for w in words]
                if len(values) != 8 or not all(np.isfinite(values)):
                    raise ValueError
            except ValueError:
                raise ValueError(f'{path}:{number}: expected 8 numbers '
                                 f'"t1 t2 x y z roll pitch yaw", got {line.strip()!r}') from None
            rows.append(values)
    if not rows:
        raise ValueError(f'{path}: no relations')
    data = np.array(rows)
    t1 = np.round(data[:, 0] * 1e9).astype(np.int64) + time_offset_ns
    t2 = np.round(data[:, 1] * 1e9).astype(np.int64) + time_offset_ns
    return Relations(t1, t2, data[:, [2, 3, 7]].copy())


@dataclass
class RelativeErrors:
    """Per-relation errors of an estimate: translation (m) and rotation (rad, absolute)."""

    t1: NDArray[np.int64]
    t2: NDArray[np.int64]
    translation_m: NDArray[np.float64]
    rotation_rad: NDArray[np.float64]
    skipped: int  # relations outside the estimate's time span

    def summary(self) -> dict[str, float]:
        tr, rot = self.translation_m, np.degrees(self.rotation_rad)
        return {
            'relations': int(tr.size),
            'skipped_relations': int(self.skipped),
            'rpe_translation_mean_m': float(tr.mean()),
            'rpe_translation_std_m': float(tr.std()),
            'rpe_rotation_mean_deg': float(rot.mean()),
            'rpe_rotation_std_deg': float(rot.std()),
            'rpe_translation_median_m': float(np.median(tr)),
            'rpe_rotation_median_deg': float(np.median(rot)),
        }


def relative_pose_errors(
    relations: Relations, t_est: NDArray[np.int64], poses_est: NDArray[np.float64]
) -> RelativeErrors:
    """Kümmerle et al.'s relative error: the estimate's motion from t1 to t2 (poses interpolated
    at both) against the reference motion; translation = norm of the error motion's x, y,
    rotation = |its yaw|. Relations outside the estimate's time span are skipped."""
    at1 = interpolate_poses(t_est, poses_est, relations.t1)
    at2 = interpolate_poses(t_est, poses_est, relations.t2)
    ok = np.all(np.isfinite(at1), axis=1) & np.all(np.isfinite(at2), axis=1)
    trans, rot = [], []
    for a, b, ref in zip(at1[ok], at2[ok], relations.motion[ok]):
        error = se2.between(tuple(ref), se2.between(tuple(a), tuple(b)))
        trans.append(np.hypot(error[0], error[1]))
        rot.append(abs(float(se2.wrap_angle(error[2]))))
    return RelativeErrors(relations.t1[ok], relations.t2[ok], np.array(trans), np.array(rot),
                          int((~ok).sum()))


def align_rigid_2d(
    reference_xy: NDArray[np.float64], estimate_xy: NDArray[np.float64]
) -> tuple[float, float, float]:
    """The rigid transform (x, y, yaw) that best maps estimate points onto reference points in
    the least-squares sense (Horn/Umeyama without scale)."""
    mu_r, mu_e = reference_xy.mean(axis=0), estimate_xy.mean(axis=0)
    h = (estimate_xy - mu_e).T @ (reference_xy - mu_r)
    yaw = float(np.arctan2(h[0, 1] - h[1, 0], h[0, 0] + h[1, 1]))
    t = mu_r - se2.rotation(yaw) @ mu_e
    return float(t[0]), float(t[1]), yaw


def absolute_trajectory_error(
    t_ref: NDArray[np.int64], poses_ref: NDArray[np.float64],
    t_est: NDArray[np.int64], poses_est: NDArray[np.float64],
) -> dict[str, float]:
    """ATE: position error of the estimate at the reference's stamps within the estimate's span
    (the estimate interpolated, as for RPE) after the best rigid alignment of its positions onto
    the reference's; RMSE, mean and max (m).

    Scored at the reference's stamps, estimates of different rates are scored on the same
    samples. (At the estimate's own stamps, an odometry-rate estimate was scored against the
    reference interpolated between scans up to 38 s apart on the CARMEN logs, and lost to the
    scan-rate matcher by that interpolation alone: 0.316 against 0.281 m on Freiburg 101.)"""
    estimate = interpolate_poses(t_est, np.asarray(poses_est, dtype=float), t_ref)
    keep = np.all(np.isfinite(estimate), axis=1)
    if keep.sum() < 2:
        raise ValueError('fewer than 2 reference samples lie within the estimate\'s time span')
    ref, est = np.asarray(poses_ref, dtype=float)[keep, :2], estimate[keep, :2]
    transform = align_rigid_2d(ref, est)
    error = np.hypot(*(se2.transform_points(transform, est) - ref).T)
    return {'ate_rmse_m': float(np.sqrt(np.mean(error ** 2))), 'ate_mean_m': float(error.mean()),
            'ate_max_m': float(error.max()), 'ate_samples': int(keep.sum())}
