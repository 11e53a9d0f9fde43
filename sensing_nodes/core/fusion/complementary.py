"""Complementary fusion of fast-but-drifting dead reckoning with slow-but-absolute scan matching
(the lesson's filter, `method: complementary`), and its worked-number helpers.

All poses are planar (x, y, yaw) in metres and radians; covariances are 3x3 over (x, y, yaw).
The fused pose lives in its own `odom` frame, which starts where the first input starts.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from sensing_nodes.core.fusion.filter import FusedState
from sensing_nodes.core.fusion.increments import increment_covariance
from sensing_nodes.core.fusion.inputs import IMU, SCAN, WHEEL, Reading
from sensing_nodes.core.geometry import se2
from sensing_nodes.core.geometry.se2 import Pose2

# Smallest variance an input may claim: keeps information matrices finite when a source
# reports an exactly known (static, zero) covariance for an increment.
VARIANCE_FLOOR = 1e-12


def inverse_variance(m1: ArrayLike, var1: ArrayLike, m2: ArrayLike, var2: ArrayLike):
    """Inverse-variance weighted mean of two independent estimates and its variance
    (elementwise)."""
    m1, var1, m2, var2 = (np.asarray(v, dtype=float) for v in (m1, var1, m2, var2))
    fused = (var2 * m1 + var1 * m2) / (var1 + var2)
    variance = var1 * var2 / (var1 + var2)
    return (float(fused), float(variance)) if fused.ndim == 0 else (fused, variance)


def fuse_information(
    m1: NDArray[np.float64],
    cov1: NDArray[np.float64],
    m2: NDArray[np.float64],
    cov2: NDArray[np.float64],
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Inverse-variance fusion of two independent vector estimates with full covariances
    (the matrix form of inverse_variance: information matrices add)."""
    info1, info2 = np.linalg.inv(cov1), np.linalg.inv(cov2)
    cov = np.linalg.inv(info1 + info2)
    return cov @ (info1 @ m1 + info2 @ m2), 0.5 * (cov + cov.T)


def complementary_heading(
    heading_prev: float, rate: float, dt: float, heading_abs: float, alpha: float
) -> float:
    """θ̂ = α·(θ̂_prev + ω·dt) + (1 − α)·θ_abs, computed on the wrapped difference so that
    headings on either side of ±π blend correctly (rad, rad/s, s)."""
    predicted = heading_prev + rate * dt
    return float(
        se2.wrap_angle(predicted + (1.0 - alpha) * se2.wrap_angle(heading_abs - predicted))
    )


def auto_alpha(var_predicted: float, var_absolute: float) -> float:
    """The α that weights prediction and absolute heading by inverse variance."""
    return var_absolute / (var_predicted + var_absolute)


@dataclass
class FusionSettings:
    """What the filter uses from each input, and how it weights them."""

    use_wheel: bool = True            # position increments (and heading when no gyro) from wheels
    use_gyro: bool = True             # heading increments from the integrated gyro
    use_scan_position: bool = True    # position increments from scan matching
    use_scan_heading: bool = True     # absolute heading from scan matching
    alpha: float | None = 0.98        # None: derive α each update from the two variances
    max_gap_s: float = 1.0            # an input silent for longer restarts its increments
    # After a silence, a scan matcher whose motion disagrees with dead reckoning by more than
    # this has restarted (its frame is new) and is tied to the current estimate again.
    restart_distance_m: float = 0.5
    restart_angle_rad: float = math.radians(20.0)


@dataclass
class _Source:
    """The last message of one odometry-like input, for forming increments."""

    stamp_ns: int | None = None
    pose: Pose2 = (0.0, 0.0, 0.0)
    cov: NDArray[np.float64] = field(default_factory=lambda: np.zeros((3, 3)))


@dataclass
class FusionState:
    stamp_ns: int
    pose: Pose2
    covariance: NDArray[np.float64]


class ComplementaryFusion:
    """Stamp-ordered complementary filter. Feed it messages in stamp order; read `state`.

    Between scan matches the pose is propagated by wheel increments with heading from the gyro.
    At each scan match the motion since the previous one is fused: wheel and scan increments by
    inverse variance (x, y), heading by the complementary filter against the scan heading.
    """

    def __init__(self, settings: FusionSettings) -> None:
        self.settings = settings
        self.reset()

    def reset(self, pose: Pose2 = (0.0, 0.0, 0.0),
              covariance: NDArray[np.float64] | None = None) -> None:
        """Start again; the first input starts the fused pose at `pose` with `covariance`."""
        self._start = (tuple(pose), np.zeros((3, 3)) if covariance is None
                       else np.asarray(covariance, dtype=float).copy())
        self.state: FusionState | None = None
        self._wheel = _Source()
        self._gyro_stamp: int | None = None
        self._gyro_yaw = 0.0
        self._gyro_var = 0.0
        self._scan = _Source()
        # Anchor: fused state at the last scan match, and what each source said since then.
        self._anchor: FusionState | None = None
        self._wheel_since = self._zero_increment()
        self._gyro_since = (0.0, 0.0)  # (yaw change, its variance)
        self._wheel_steps = self._gyro_steps = 0  # increments since the anchor
        self._scan_offset: Pose2 | None = None  # scan frame -> fused frame
        self._tie_variance = 0.0            # fused heading variance when the frames were tied
        self._scan_variance_at_tie = 0.0    # the matcher's own heading variance then
        self.updates = 0

    @staticmethod
    def _zero_increment() -> tuple[Pose2, NDArray[np.float64]]:
        return (0.0, 0.0, 0.0), np.zeros((3, 3))

    def _ensure_started(self, stamp_ns: int) -> None:
        if self.state is None:
            self.state = FusionState(stamp_ns, self._start[0], self._start[1].copy())
            self._anchor = FusionState(stamp_ns, self.state.pose, self.state.covariance.copy())

    def _propagated(self) -> tuple[Pose2, NDArray[np.float64]]:
        """Anchor ⊕ wheel motion since, with the gyro's heading change when it is used."""
        assert self._anchor is not None
        motion, motion_cov = self._wheel_since
        if self._gyro_steps:
            motion = (motion[0], motion[1], self._gyro_since[0])
            motion_cov = motion_cov.copy()
            motion_cov[2, :] = motion_cov[:, 2] = 0.0
            motion_cov[2, 2] = self._gyro_since[1]
        return se2.compose_with_covariance(
            self._anchor.pose, self._anchor.covariance, motion, motion_cov)

    def _publishable(self, stamp_ns: int) -> None:
        pose, cov = self._propagated()
        assert self.state is not None
        self.state = FusionState(max(stamp_ns, self.state.stamp_ns), pose, cov)

    def add_wheel(self, stamp_ns: int, pose: Pose2, cov: NDArray[np.float64]) -> None:
        """A wheel-odometry pose (its own odom frame) with its cumulative covariance."""
        if not self.settings.use_wheel:
            return
        self._ensure_started(stamp_ns)
        src = self._wheel
        if (
            src.stamp_ns is not None
            and 0 < stamp_ns - src.stamp_ns <= self.settings.max_gap_s * 1e9
        ):
            step = se2.between(src.pose, pose)
            step_cov = increment_covariance(src.pose, src.cov, pose, cov)
            self._wheel_since = se2.compose_with_covariance(*self._wheel_since, step, step_cov)
            self._wheel_steps += 1
        src.stamp_ns, src.pose, src.cov = stamp_ns, pose, np.asarray(cov, dtype=float)
        self._publishable(stamp_ns)

    def add_gyro(self, stamp_ns: int, yaw: float, yaw_variance: float) -> None:
        """An integrated gyro heading (rad) with its cumulative variance."""
        if not self.settings.use_gyro:
            return
        self._ensure_started(stamp_ns)
        if self._gyro_stamp is not None and \
                0 < stamp_ns - self._gyro_stamp <= self.settings.max_gap_s * 1e9:
            change, var = self._gyro_since
            self._gyro_since = (
                change + float(se2.wrap_angle(yaw - self._gyro_yaw)),
                var + max(yaw_variance - self._gyro_var, 0.0),
            )
            self._gyro_steps += 1
        self._gyro_stamp, self._gyro_yaw, self._gyro_var = stamp_ns, yaw, yaw_variance

    def add_scan_match(self, stamp_ns: int, pose: Pose2, cov: NDArray[np.float64],
                       increment_cov: NDArray[np.float64] | None = None) -> None:
        """A scan-matching pose (its own frame) with cumulative covariance; `increment_cov`, when
        the source provides it, is the covariance of the motion since its previous pose."""
        if not (self.settings.use_scan_position or self.settings.use_scan_heading):
            return
        self._ensure_started(stamp_ns)
        src = self._scan
        predicted, predicted_cov = self._propagated()
        if src.stamp_ns is None or self._scan_offset is None or \
                self._restarted(stamp_ns, pose, predicted):
            # First match, or the matcher restarted: tie its frame to ours, fuse nothing yet.
            self._scan_offset = se2.compose(predicted, se2.inverse(pose))
            self._tie_variance = float(predicted_cov[2, 2])
            self._scan_variance_at_tie = float(np.asarray(cov)[2, 2])
            fused, fused_cov = predicted, predicted_cov
        else:
            fused, fused_cov = self._fuse(
                stamp_ns, pose, cov, increment_cov, predicted, predicted_cov)
        src.stamp_ns, src.pose, src.cov = stamp_ns, pose, np.asarray(cov, dtype=float)
        self._anchor = FusionState(stamp_ns, fused, fused_cov)
        self.state = FusionState(stamp_ns, fused, fused_cov)
        self._wheel_since = self._zero_increment()
        self._gyro_since = (0.0, 0.0)
        self._wheel_steps = self._gyro_steps = 0
        self.updates += 1

    def restart(self, name: str) -> None:
        """Input `name` (wheel_odom, imu, scan_match) starts again from its next message: no
        increment spans the restart, and the scan matcher's frame is tied to ours again."""
        if name == WHEEL:
            self._wheel.stamp_ns = None
        elif name == IMU:
            self._gyro_stamp = None
        elif name == SCAN:
            self._scan_offset = None

    def _restarted(self, stamp_ns: int, pose: Pose2, predicted: Pose2) -> bool:
        """After a silence longer than max_gap_s, did the matcher start over in a new frame?
        Judged by whether its motion over the silence disagrees with dead reckoning's."""
        if stamp_ns - self._scan.stamp_ns <= self.settings.max_gap_s * 1e9:
            return False
        assert self._anchor is not None
        scan_motion = se2.between(self._scan.pose, pose)
        dr_motion = se2.between(self._anchor.pose, predicted)
        mismatch = se2.between(dr_motion, scan_motion)
        return (math.hypot(mismatch[0], mismatch[1]) > self.settings.restart_distance_m
                or abs(mismatch[2]) > self.settings.restart_angle_rad)

    # long: the complementary filter's scan update in the lesson's order (increment, position
    # by inverse variance, heading by alpha, covariance, anchor), kept as one worked-number unit.
    def _fuse(self, stamp_ns, pose, cov, increment_cov, predicted, predicted_cov):
        assert self._anchor is not None and self._scan_offset is not None
        anchor = self._anchor
        scan_step = se2.between(self._scan.pose, pose)
        if increment_cov is None or not np.any(increment_cov):
            increment_cov = increment_covariance(self._scan.pose, self._scan.cov, pose, cov)
        scan_step_cov = increment_cov + np.eye(3) * VARIANCE_FLOOR

        # Dead-reckoned motion over the same interval, in the anchor frame. A source that sent
        # nothing in the interval knows nothing about it (it does not say "no motion").
        dr_step = se2.between(anchor.pose, predicted)
        _, motion_cov = self._wheel_since
        dr_cov = motion_cov + np.eye(3) * VARIANCE_FLOOR
        if self._gyro_steps:
            dr_cov = dr_cov.copy()
            dr_cov[2, :] = dr_cov[:, 2] = 0.0
            dr_cov[2, 2] = self._gyro_since[1] + VARIANCE_FLOOR
        elif not self._wheel_steps:
            # No dead reckoning at all: the scan match's own heading change stands in for it.
            predicted = (predicted[0], predicted[1],
                         float(se2.wrap_angle(anchor.pose[2] + scan_step[2])))
            predicted_cov = predicted_cov.copy()
            predicted_cov[2, 2] = anchor.covariance[2, 2] + scan_step_cov[2, 2]
            dr_step = (dr_step[0], dr_step[1], scan_step[2])
            dr_cov[2, 2] = scan_step_cov[2, 2]

        step = np.array(dr_step, dtype=float)
        step_cov = dr_cov.copy()
        if self.settings.use_scan_position and self._wheel_steps:
            xy, xy_cov = fuse_information(
                step[:2], dr_cov[:2, :2], np.array(scan_step[:2]), scan_step_cov[:2, :2])
            step[:2], step_cov[:2, :2] = xy, xy_cov
            step_cov[:2, 2] = step_cov[2, :2] = 0.0
        elif self.settings.use_scan_position:
            step[:2], step_cov[:2, :2] = scan_step[:2], scan_step_cov[:2, :2]
            step_cov[:2, 2] = step_cov[2, :2] = 0.0
        fused, fused_cov = se2.compose_with_covariance(
            anchor.pose, anchor.covariance, tuple(step), step_cov)

        if self.settings.use_scan_heading:
            heading_abs = se2.compose(self._scan_offset, pose)[2]
            var_pred = float(predicted_cov[2, 2])
            # The matcher's heading is as uncertain as it says, relative to where it was tied.
            var_abs = max(self._tie_variance + float(cov[2, 2]) - self._scan_variance_at_tie,
                          float(scan_step_cov[2, 2]))
            alpha = self.settings.alpha
            if alpha is None:
                alpha = auto_alpha(var_pred, var_abs)
            heading = complementary_heading(predicted[2], 0.0, 0.0, heading_abs, alpha)
            fused = (fused[0], fused[1], heading)
            fused_cov = fused_cov.copy()
            # The prediction's error is mostly the earlier absolute headings' error (the filter
            # tracks them), so the two are combined as fully correlated: the fused heading is
            # never claimed to be better than the reference it follows.
            sigma = alpha * math.sqrt(var_pred) + (1.0 - alpha) * math.sqrt(var_abs)
            var_heading = sigma * sigma
            scale = math.sqrt(var_heading / fused_cov[2, 2]) if fused_cov[2, 2] > 0 else 0.0
            fused_cov[2, :2] *= scale
            fused_cov[:2, 2] *= scale
            fused_cov[2, 2] = var_heading
        return fused, fused_cov


class ComplementaryMethod:
    """The complementary filter behind the fusion's filter interface (filter.FusionFilter), fed
    by the inputs named wheel_odom, imu and scan_match."""

    def __init__(self, settings: FusionSettings) -> None:
        self._filter = ComplementaryFusion(settings)
        self.gated: dict[str, int] = {}   # (this filter has no gate)
        self.health: dict = {}
        self.noise_scale: dict = {}

    def reset(self) -> None:
        self._filter.reset()

    @property
    def updates(self) -> int:
        return self._filter.updates

    def set_pose(self, pose: Pose2, covariance: NDArray[np.float64]) -> None:
        """Restart at pose: the filter restarts and later inputs continue from there."""
        self._filter.reset(pose, covariance)

    def restart(self, name: str) -> None:
        self._filter.restart(name)

    def update(self, name: str, reading: Reading) -> None:
        """One Reading of wheel_odom (pose, covariance), imu (pose[2] = yaw, covariance[2, 2])
        or scan_match (pose, covariance; twist covariance x dt^2 as increment covariance)."""
        if name == WHEEL:
            self._filter.add_wheel(reading.stamp_ns, reading.pose, reading.pose_covariance)
        elif name == IMU:
            self._filter.add_gyro(reading.stamp_ns, reading.pose[2],
                                  float(reading.pose_covariance[2, 2]))
        else:
            self._filter.add_scan_match(reading.stamp_ns, reading.pose, reading.pose_covariance,
                                        reading.twist_covariance)

    @property
    def state(self) -> FusedState | None:
        """The filter's state as the fusion's output (no twist estimated: zero)."""
        state = self._filter.state
        if state is None:
            return None
        return FusedState(state.stamp_ns, state.pose, state.covariance)
