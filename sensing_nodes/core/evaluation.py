"""Comparing estimated trajectories with a reference (ground truth), all planar, SI units."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from sensing_nodes.core import se2


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
    """Poses of an estimate whose frame starts at `origin` (a reference-frame pose) -> reference frame."""
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
