"""Scan-matching odometry without ROS: keyframes, motion prediction, fallback on a failed match.

Poses are base_link in the odometry frame (x, y, yaw; m, rad). The laser is mounted at
`laser_pose` in base_link; scans are (N, 2) points in the laser frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from sensing_nodes.core import icp
from sensing_nodes.core.geometry.se2 import (
    Pose2,
    between,
    compose,
    compose_jacobians,
    compose_with_covariance,
    interpolate,
    inverse,
    wrap_angle,
)
from sensing_nodes.core.timing import StampStep, classify_step

ZERO: Pose2 = (0.0, 0.0, 0.0)


# A scan stamped closer than this to the previous one (a driver's duplicate with a nudged stamp)
# says nothing about velocity: a match residual divided by a tiny dt would make the
# constant-velocity prediction run away, so the previous twist is kept.
MIN_VELOCITY_INTERVAL_S = 1e-3


@dataclass(frozen=True)
class ScanMatcherSettings:
    """Keyframe policy, laser mount, acceptance gates and fallback noise (m, rad, s)."""

    laser_pose: Pose2 = (0.0, 0.0, 0.0)          # laser in base_link
    keyframe_distance_m: float = 0.10
    keyframe_angle_rad: float = math.radians(10.0)
    max_error_m: float = 0.05                     # mean alignment error above this: failed
    max_jump_m: float = 0.5                       # match further than this from the prediction
    max_jump_rad: float = math.radians(30.0)      #   ... is rejected as a false minimum
    fallback_std_m: float = 0.05                  # std added per fallback step, translation
    fallback_std_rad: float = math.radians(3.0)   # ... and yaw
    max_gap_s: float = 1.0                        # scans further apart: restart the keyframe
    # keyframe's neighbour search (icp.prepare_target)
    search: str = 'bearing'
    icp_options: icp.IcpOptions = icp.IcpOptions()   # how each scan is matched


@dataclass
class ScanStep:
    """Outcome of one scan: pose of base_link (odom frame) with covariance, twist (vx, vy, wz)
    in base_link over the last interval, and what happened (`status`, `reason`)."""

    stamp_ns: int
    pose: Pose2
    covariance: NDArray[np.float64]
    twist: tuple[float, float, float]
    status: str                 # first | matched | fallback | repeated | reset_backwards | gap
    reason: str = ''
    new_keyframe: bool = False
    prediction: str = ''        # odometry | constant_velocity
    result: icp.MatchResult | None = None
    twist_covariance: NDArray[np.float64] = field(default_factory=lambda: np.zeros((3, 3)))
    # A match's own measurement: base_link at stamp_ns relative to base_link at the keyframe's
    # stamp (keyframe_stamp_ns), with the match's covariance. Successive matches against one
    # keyframe share that keyframe's error; a consumer that keeps its state at keyframe stamps
    # (stochastic cloning) counts it once. None when nothing was matched (first, gap, fallback).
    keyframe_stamp_ns: int | None = None
    relative: Pose2 | None = None
    relative_covariance: NDArray[np.float64] | None = None

    @property
    def publish(self) -> bool:
        """False only for a repeated stamp, which produces no new estimate."""
        return self.status != 'repeated'


def mount_transform(relative_base: Pose2, laser_pose: Pose2) -> Pose2:
    """Motion of base_link (in the earlier base frame) -> the same motion seen by the laser."""
    return compose(compose(inverse(laser_pose), relative_base), laser_pose)


def unmount_transform(relative_laser: Pose2, cov_laser: NDArray[np.float64],
                      laser_pose: Pose2) -> tuple[Pose2, NDArray[np.float64]]:
    """Laser motion (laser frame) and its covariance -> base_link motion and covariance."""
    first = compose(laser_pose, relative_laser)
    base = compose(first, inverse(laser_pose))
    _, j_inner = compose_jacobians(laser_pose, relative_laser)
    j_outer, _ = compose_jacobians(first, inverse(laser_pose))
    jac = j_outer @ j_inner
    cov = jac @ cov_laser @ jac.T
    return base, 0.5 * (cov + cov.T)


class KeyframeScanMatcher:
    """Matches each scan against the current keyframe from a predicted pose; publishes the
    accumulated base_link pose. A failed match falls back to the prediction (with inflated
    covariance) and restarts the keyframe there, so the pose never jumps."""

    def __init__(self, settings: ScanMatcherSettings | None = None) -> None:
        self.settings = settings or ScanMatcherSettings()
        self.reset()

    def reset(self) -> None:
        """Forget everything: the next scan starts again at the origin."""
        self.pose: Pose2 = ZERO
        self.covariance = np.zeros((3, 3))
        self.twist = (0.0, 0.0, 0.0)
        self.stamp_ns: int | None = None
        self.keyframe: icp.Target | None = None
        self.keyframe_pose: Pose2 = ZERO
        self.keyframe_covariance = np.zeros((3, 3))
        self.keyframe_stamp_ns: int | None = None

    def _set_keyframe(self, points: NDArray[np.float64], stamp_ns: int) -> None:
        self.keyframe = icp.prepare_target(points, search=self.settings.search)
        self.keyframe_stamp_ns = stamp_ns
        self.keyframe_pose = self.pose
        self.keyframe_covariance = self.covariance.copy()

    def process(self, stamp_ns: int, points: NDArray[np.float64],
                predicted_motion: Pose2 | None = None) -> ScanStep:
        """One scan: points (N, 2) in the laser frame at stamp_ns; predicted_motion is base_link's
        motion since the previous scan (in the previous base frame), or None for the
        constant-velocity model."""
        s = self.settings
        step = classify_step(self.stamp_ns, stamp_ns, s.max_gap_s)
        if step is StampStep.REPEATED:
            return ScanStep(stamp_ns, self.pose, self.covariance, self.twist, 'repeated',
                            'same stamp as the previous scan: skipped')
        if step in (StampStep.FIRST, StampStep.BACKWARDS):
            status = 'first' if step is StampStep.FIRST else 'reset_backwards'
            self.reset()
            self.stamp_ns = stamp_ns
            self._set_keyframe(points, stamp_ns)
            reason = '' if step is StampStep.FIRST else 'stamp went backwards: restarted at origin'
            return ScanStep(stamp_ns, self.pose, self.covariance, self.twist, status, reason,
                            new_keyframe=True)
        if step is StampStep.GAP:
            gap_s = (stamp_ns - self.stamp_ns) * 1e-9
            self.stamp_ns = stamp_ns
            self.twist = (0.0, 0.0, 0.0)
            self._set_keyframe(points, stamp_ns)
            return ScanStep(stamp_ns, self.pose, self.covariance, self.twist, 'gap',
                            f'{gap_s:.2f} s since the previous scan: keyframe restarted here',
                            new_keyframe=True)

        return self._match(stamp_ns, points, predicted_motion)

    def _match(self, stamp_ns: int, points: NDArray[np.float64],
               predicted_motion: Pose2 | None) -> ScanStep:
        """process() for a scan that follows the previous one within max_gap_s."""
        s = self.settings
        dt = (stamp_ns - self.stamp_ns) * 1e-9
        source = 'odometry'
        if predicted_motion is None or not all(math.isfinite(v) for v in predicted_motion):
            source = 'constant_velocity'
            predicted_motion = (self.twist[0] * dt, self.twist[1] * dt, self.twist[2] * dt)
        predicted = compose(self.pose, predicted_motion)
        guess_base = between(self.keyframe_pose, predicted)
        guess_laser = mount_transform(guess_base, s.laser_pose)
        result = icp.match(points, self.keyframe, guess_laser, options=s.icp_options)
        points_usable = result.source_points >= s.icp_options.correspondences.min_points

        reason = self._rejection(result, guess_laser)
        previous = self.pose
        keyframe_stamp, relative, rel_cov = self.keyframe_stamp_ns, None, None
        if reason:
            fallback_cov = np.diag([s.fallback_std_m ** 2, s.fallback_std_m ** 2,
                                    s.fallback_std_rad ** 2])
            self.pose, self.covariance = compose_with_covariance(
                self.pose, self.covariance, predicted_motion, fallback_cov)
            status = 'fallback'
            # Restart the keyframe here (the old one did not fit), unless this scan is too
            # sparse to match against: then the old keyframe stays, at its own pose.
            new_keyframe = points_usable
            motion_cov = fallback_cov
        else:
            relative, rel_cov = unmount_transform(result.pose, result.covariance, s.laser_pose)
            self.pose, self.covariance = compose_with_covariance(
                self.keyframe_pose, self.keyframe_covariance, relative, rel_cov)
            status = 'matched'
            motion_cov = rel_cov      # the keyframe's own uncertainty is common to both poses
            new_keyframe = (math.hypot(relative[0], relative[1]) > s.keyframe_distance_m
                            or abs(relative[2]) > s.keyframe_angle_rad)
        if new_keyframe:
            self._set_keyframe(points, stamp_ns)
        if status != 'matched':
            keyframe_stamp = None
        motion = between(previous, self.pose)
        if dt >= MIN_VELOCITY_INTERVAL_S:
            self.twist = (motion[0] / dt, motion[1] / dt, motion[2] / dt)
        self.stamp_ns = stamp_ns
        return ScanStep(stamp_ns, self.pose, self.covariance.copy(), self.twist, status, reason,
                        new_keyframe=new_keyframe, prediction=source, result=result,
                        twist_covariance=motion_cov / (dt * dt),
                        keyframe_stamp_ns=keyframe_stamp, relative=relative,
                        relative_covariance=rel_cov)

    def _rejection(self, result: icp.MatchResult, guess: Pose2) -> str:
        """Why a match must not be used ('' when it is fine)."""
        s = self.settings
        if not result.converged:
            return f'not converged: {result.reason}'
        if result.degenerate:
            return result.reason
        if not result.error <= s.max_error_m:
            return f'mean alignment error {result.error:.3f} m > {s.max_error_m} m'
        jump = between(guess, result.pose)
        if math.hypot(jump[0], jump[1]) > s.max_jump_m or abs(jump[2]) > s.max_jump_rad:
            return (f'match {math.hypot(jump[0], jump[1]):.2f} m / '
                    f'{math.degrees(abs(jump[2])):.1f} deg from the prediction')
        return ''


class OdometryBuffer:
    """Recent odometry poses (odom frame, by stamp) for the motion between two scan stamps."""

    def __init__(self, max_age_s: float = 10.0, max_extrapolation_s: float = 0.1) -> None:
        self.max_age_ns = int(max_age_s * 1e9)
        self.max_extrapolation_ns = int(max_extrapolation_s * 1e9)
        self.stamps: list[int] = []
        self.poses: list[Pose2] = []

    def add(self, stamp_ns: int, pose: Pose2) -> bool:
        """Append a pose; a stamp older than the newest clears the buffer (returns False)."""
        if self.stamps and stamp_ns < self.stamps[-1]:
            self.clear()
            self.stamps.append(stamp_ns)
            self.poses.append(pose)
            return False
        if self.stamps and stamp_ns == self.stamps[-1]:
            self.poses[-1] = pose
            return True
        self.stamps.append(stamp_ns)
        self.poses.append(pose)
        cut = 0
        while cut < len(self.stamps) - 2 and self.stamps[cut] < stamp_ns - self.max_age_ns:
            cut += 1
        if cut:
            del self.stamps[:cut], self.poses[:cut]
        return True

    def clear(self) -> None:
        self.stamps.clear()
        self.poses.clear()

    def pose_at(self, stamp_ns: int) -> Pose2 | None:
        """Pose interpolated at stamp_ns; linearly extrapolated up to max_extrapolation_s past
        the newest sample; None when outside that range."""
        if not self.stamps or stamp_ns < self.stamps[0]:
            return None
        i = int(np.searchsorted(self.stamps, stamp_ns))
        if i < len(self.stamps) and self.stamps[i] == stamp_ns:
            return self.poses[i]
        if i == len(self.stamps):
            if stamp_ns - self.stamps[-1] > self.max_extrapolation_ns:
                return None
            if len(self.stamps) < 2:
                return self.poses[-1]
            i = len(self.stamps) - 1          # extrapolate along the last interval
        t0, t1 = self.stamps[i - 1], self.stamps[i]
        return interpolate(self.poses[i - 1], self.poses[i], (stamp_ns - t0) / (t1 - t0))

    def motion_between(self, start_ns: int, end_ns: int) -> Pose2 | None:
        """base_link motion from start_ns to end_ns in the base frame at start_ns, or None."""
        a, b = self.pose_at(start_ns), self.pose_at(end_ns)
        if a is None or b is None:
            return None
        motion = between(a, b)
        return (motion[0], motion[1], float(wrap_angle(motion[2])))
