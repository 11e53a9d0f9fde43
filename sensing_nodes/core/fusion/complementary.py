"""Complementary fusion of fast-but-drifting dead reckoning with slow-but-absolute scan matching.

All poses are planar (x, y, yaw) in metres and radians; covariances are 3x3 over (x, y, yaw).
The fused pose lives in its own `odom` frame, which starts where the first input starts.
"""

from __future__ import annotations

import bisect
import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

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


def _added_covariance(
    pose_prev: Pose2, cov_prev: NDArray[np.float64], pose_now: Pose2, cov_now: NDArray[np.float64]
) -> NDArray[np.float64]:
    """cov_now minus cov_prev compounded to pose_now, in the increment's frame (unclipped)."""
    increment = se2.between(pose_prev, pose_now)
    j_a, j_b = se2.compose_jacobians(pose_prev, increment)
    added = cov_now - j_a @ cov_prev @ j_a.T
    j_b_inv = j_b.T  # j_b is a rotation about z
    q = j_b_inv @ added @ j_b_inv.T
    return 0.5 * (q + q.T)


def increment_covariance(
    pose_prev: Pose2, cov_prev: NDArray[np.float64], pose_now: Pose2, cov_now: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Covariance of the body-frame increment between two cumulative odometry poses, recovered
    from their covariances under first-order compounding (cov_now = Ja·cov_prev·Jaᵀ + Jb·Q·Jbᵀ).
    Negative parts (a source that does not propagate this way) are clipped to zero."""
    values, vectors = np.linalg.eigh(_added_covariance(pose_prev, cov_prev, pose_now, cov_now))
    return (vectors * np.clip(values, 0.0, None)) @ vectors.T


def compounded_increment_covariance(
    pose_prev: Pose2, cov_prev: NDArray[np.float64], pose_now: Pose2, cov_now: NDArray[np.float64],
    tolerance: float = 0.1,
) -> NDArray[np.float64] | None:
    """increment_covariance, or None when the source's covariance does not grow by compounding:
    the negative part the clip would remove exceeds `tolerance` times the positive part kept.
    A covariance that grows with distance alone (carmen_to_bag's) is such a source: the clip
    leaves directions of zero variance, which a filter would take as exact."""
    values, vectors = np.linalg.eigh(_added_covariance(pose_prev, cov_prev, pose_now, cov_now))
    # Three eigenvalues: plain floats (summed in numpy's order) cost less than numpy's calls.
    listed = values.tolist()
    if -sum(v for v in listed if v < 0.0) > tolerance * sum(v for v in listed if v > 0.0):
        return None
    return (vectors * np.maximum(values, 0.0)) @ vectors.T


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


class StampOrderedBuffer:
    """Releases items in stamp order once they are `window_ns` older than the newest stamp seen
    (or once every live input is past them), so the order of processing depends on stamps only,
    not on arrival timing.

    Ties are broken by `rank` (an input's fixed priority), then by arrival. An item whose stamp is
    older than what was already released is late: refused (push returns False) and counted.
    """

    def __init__(self, window_ns: int) -> None:
        self.window_ns = int(window_ns)
        self.clear()
        self.late = 0

    def clear(self) -> None:
        self._items: list[tuple[int, int, int, object]] = []
        self._arrivals = 0
        self.newest_ns: int | None = None
        self.released_ns: int | None = None

    def push(self, stamp_ns: int, rank: int, item: object) -> bool:
        if self.released_ns is not None and stamp_ns < self.released_ns:
            self.late += 1
            return False
        self._arrivals += 1
        # Kept sorted (arrival numbers are unique, so items themselves are never compared).
        bisect.insort(self._items, (stamp_ns, rank, self._arrivals, item))
        self.newest_ns = stamp_ns if self.newest_ns is None else max(self.newest_ns, stamp_ns)
        return True

    def pop_ready(self, watermark_ns: int | None = None) -> list[tuple[int, object]]:
        """(stamp, item) of every item at least window_ns older than the newest, or not newer
        than `watermark_ns` (a stamp every live input has already reached), in order."""
        if self.newest_ns is None:
            return []
        up_to = self.newest_ns - self.window_ns
        if watermark_ns is not None:
            up_to = max(up_to, watermark_ns)
        return self._release(up_to)

    def flush(self) -> list[tuple[int, object]]:
        """Everything still held, in order (end of a stream)."""
        return self._release(None)

    def __len__(self) -> int:
        return len(self._items)

    def _release(self, up_to_ns: int | None) -> list[tuple[int, object]]:
        count = len(self._items) if up_to_ns is None else \
            bisect.bisect_right(self._items, up_to_ns, key=_stamp_of)
        ready, self._items = self._items[:count], self._items[count:]
        if ready:
            self.released_ns = ready[-1][0]
        return [(stamp, item) for stamp, _, _, item in ready]


def _stamp_of(entry: tuple) -> int:
    return entry[0]


# -- what the fusion node keeps per input, and the acceptance rules of its messages ----------
@dataclass
class InputRecord:
    """Bookkeeping of one fusion input (stamps ns): what arrived, what was processed, and the
    reference an exactly-known covariance is allowed at (its first accepted value)."""

    name: str
    enabled: bool = True
    received: int = 0
    processed: int = 0
    arrived_ns: int | None = None    # newest stamp accepted into the reorder buffer
    first_ns: int | None = None      # first and last processed stamps
    last_ns: int | None = None
    origin: object = None            # first accepted pose or yaw

    def clear(self) -> None:
        """Forget the timeline (time went backwards): keep the counts of received messages."""
        self.processed = 0
        self.arrived_ns = self.first_ns = self.last_ns = None
        self.origin = None

    def processed_at(self, stamp_ns: int) -> None:
        self.processed += 1
        self.last_ns = stamp_ns
        if self.first_ns is None:
            self.first_ns = stamp_ns

    def rate_hz(self) -> float:
        """Processed messages per second of stamp time (0 before two)."""
        if self.first_ns is None or self.last_ns is None or self.last_ns <= self.first_ns:
            return 0.0
        return (self.processed - 1) / ((self.last_ns - self.first_ns) * 1e-9)

    def age_s(self, newest_ns: int | None) -> float:
        """Stamp time since this input's last processed message (inf before any)."""
        if self.last_ns is None or newest_ns is None:
            return math.inf
        return (newest_ns - self.last_ns) * 1e-9


def watermark(records: list[InputRecord], newest_ns: int | None, start_ns: int | None,
              timeout_s: float) -> int | None:
    """The stamp every live input has reached: nothing at or before it can still arrive (each
    input arrives in order), so it can be processed without waiting for the reorder window.
    An enabled input not heard from for timeout_s (stamp time) is not waited for."""
    if newest_ns is None:
        return None
    timeout_ns = timeout_s * 1e9
    reached = []
    for record in records:
        if not record.enabled:
            continue
        if record.arrived_ns is None:
            if start_ns is None or newest_ns - start_ns <= timeout_ns:
                return None  # not heard from yet, but may still be starting up
            continue
        if newest_ns - record.arrived_ns <= timeout_ns:
            reached.append(record.arrived_ns)
    return min(reached) if reached else None


def covariance_problem(cov: ArrayLike) -> str:
    """Why a covariance cannot be used ('' when it can): not finite, not symmetric, or not
    positive semi-definite (beyond rounding)."""
    c = np.asarray(cov, dtype=float)
    if c.shape == (3, 3) and _plainly_positive_definite(c.tolist()):
        return ''
    if not np.all(np.isfinite(c)):
        return 'covariance is not finite'
    scale = max(float(np.max(np.abs(c))), 1e-300)
    if np.max(np.abs(c - c.T)) > 1e-9 * scale:
        return 'covariance is not symmetric'
    if float(np.min(np.linalg.eigvalsh(0.5 * (c + c.T)))) < -1e-9 * scale:
        return 'covariance is not positive semi-definite'
    return ''


def _plainly_positive_definite(rows: list[list[float]]) -> bool:
    """True when a 3x3 covariance (nested lists) is finite, symmetric within covariance_problem's
    tolerance and positive definite (its LDLt pivots > 0, which rounding cannot fake beyond
    ~1e-15 of its scale): what covariance_problem accepts, decided in plain floats for the
    common case (a 3x3 eigendecomposition per message cost more than the rest of a reading).
    False: covariance_problem decides with numpy."""
    (a, b, c), (d, e, f), (g, h, i) = rows
    values = (a, b, c, d, e, f, g, h, i)
    if not all(math.isfinite(v) for v in values):
        return False
    scale = max(max(abs(v) for v in values), 1e-300)
    if max(abs(b - d), abs(c - g), abs(f - h)) > 1e-9 * scale:
        return False
    b, c, f = 0.5 * (b + d), 0.5 * (c + g), 0.5 * (f + h)   # the symmetric part
    if not a > 0.0:
        return False
    l1, l2 = b / a, c / a
    d2 = e - l1 * b
    if not d2 > 0.0:
        return False
    l3 = (f - l1 * c) / d2
    return i - l2 * c - l3 * l3 * d2 > 0.0


def pose_problem(pose: Pose2, cov: ArrayLike, origin: Pose2 | None, zero_allowed: bool) -> str:
    """Why an odometry pose and its 3x3 covariance cannot be used ('' when they can). An exactly
    known (zero) covariance is only believable at the source's starting pose, unless the input
    replaces the covariance by its noise model anyway (zero_allowed)."""
    if not all(math.isfinite(v) for v in pose):
        return 'pose is not finite'
    reason = covariance_problem(cov)
    if reason:
        return reason
    diagonal = np.diag(np.asarray(cov, dtype=float)).tolist()
    if any(v < 0.0 for v in diagonal):
        return 'covariance has a negative variance'
    at_origin = origin is None or tuple(pose) == tuple(origin)
    if not zero_allowed and not all(v > 0.0 for v in diagonal) and \
            not (all(v == 0.0 for v in diagonal) and at_origin):
        return 'covariance is zero after moving (only a starting pose may be exactly known)'
    return ''


class ComplementaryMethod:
    """The seed's complementary filter behind the EKF's interface (update(name, Reading),
    state, reset, set_pose, gated), fed by the inputs named wheel_odom, imu, scan_match."""

    def __init__(self, settings: FusionSettings) -> None:
        self._filter = ComplementaryFusion(settings)
        self.gated: dict[str, int] = {}

    def reset(self) -> None:
        self._filter.reset()

    @property
    def updates(self) -> int:
        return self._filter.updates

    def set_pose(self, pose: Pose2, covariance: NDArray[np.float64]) -> None:
        """Restart at pose: the filter restarts and later inputs continue from there."""
        self._filter.reset(pose, covariance)

    def update(self, name: str, reading) -> None:
        """One Reading of wheel_odom (pose, covariance), imu (pose[2] = yaw, covariance[2, 2])
        or scan_match (pose, covariance; twist covariance x dt^2 as increment covariance)."""
        if name == 'wheel_odom':
            self._filter.add_wheel(reading.stamp_ns, reading.pose, reading.pose_covariance)
        elif name == 'imu':
            self._filter.add_gyro(reading.stamp_ns, reading.pose[2],
                                  float(reading.pose_covariance[2, 2]))
        else:
            self._filter.add_scan_match(reading.stamp_ns, reading.pose, reading.pose_covariance,
                                        reading.twist_covariance)

    @property
    def state(self) -> FusionState | None:
        return self._filter.state
