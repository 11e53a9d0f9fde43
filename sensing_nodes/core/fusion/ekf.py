"""Planar EKF with stochastic cloning: fuses odometry, IMU and keyframe scan matches.

State (odom frame, SI units): pose x, y (m), yaw (rad); body velocities vx, vy (m/s), yaw rate
wz (rad/s); gyro z bias bg (rad/s); followed by clones of the pose (3 each). A clone is the pose
at an earlier stamp, kept jointly with the current state, so that a measurement of the motion
since that stamp ("differential": consecutive odometry messages; a scan match relative to its
keyframe) is fused exactly once, with its correlation to the current pose, instead of being
turned into a velocity or counted again at every scan (the keyframe's error is shared by every
match against it).

Process model: constant body velocity (white acceleration noise), random-walk gyro bias.

Errors of the pose and of every clone are kept in that pose's own body frame (true pose =
estimate ⊕ error, a right perturbation on SE(2)); velocities and bias are additive. Then the
Jacobians of motion and of every relative measurement depend on relative quantities only, never
on the absolute heading: with no absolute input, the odom-frame uncertainty grows without bound
and, with errors in the odom frame, first-order errors of the lever arms times that large
uncertainty corrupted the cross-covariances (a match against a keyframe then moved the keyframe
and the pose by decimetres on the CARMEN logs, docs/fusion.md). The published covariance is
turned into the odom frame.
Measurement kinds, each with a per-input mask over (x, y, yaw, vx, vy, vyaw):
  - pose, absolute (in the source's frame, which is the fused frame), relative to the source's
    first message, or differential (the motion between consecutive messages, via a clone);
  - twist (vx, vy, vyaw) in base_link; a raw gyro rate measures wz + bg;
  - keyframe-relative pose (scan matcher), via a clone at the keyframe's stamp.
Every measurement passes a Mahalanobis gate (squared distance against a per-input chi-square
threshold) before it is fused.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from sensing_nodes.core.fusion.filter import FusedState
from sensing_nodes.core.fusion.increments import (
    compounded_increment_covariance,
    increment_covariance,
)
from sensing_nodes.core.fusion.inputs import RANK, InputConfig, Reading
from sensing_nodes.core.fusion.integrity import InputHealth, gate_threshold, tail_probability
from sensing_nodes.core.geometry import se2
from sensing_nodes.core.geometry.se2 import Pose2

BASE = 7                      # x, y, yaw, vx, vy, wz, bg
X, Y, YAW, VX, VY, WZ, BG = range(BASE)
# Smallest variance a measurement component may claim: an exactly known increment would make
# the innovation covariance singular.
MIN_VARIANCE = 1e-12
# The share of a dead-reckoning increment's variance that is its own noise from one increment
# to the next; the rest is drift (EkfFusion._differential). Translation only: the heading
# increments of wheels are noisy from one to the next (encoder steps, slip in turns), and a
# gyro's are white.
SHORT_TERM_SHARE = 0.01
_SHORT_TERM = np.array([[SHORT_TERM_SHARE, SHORT_TERM_SHARE, 1.0],
                        [SHORT_TERM_SHARE, SHORT_TERM_SHARE, 1.0],
                        [1.0, 1.0, 1.0]])
_DIAG3 = (np.arange(3), np.arange(3))        # the diagonal of a 3x3 (fancy index, made once)


@dataclass(frozen=True)
class EkfSettings:
    """Process noise (white-noise densities) and the initial uncertainty of what no input has
    told yet (velocities, bias)."""

    pose_noise_density: float = 1e-4       # m/sqrt(s) and rad/sqrt(s) on the pose itself
    accel_noise_density: float = 1.0       # m/s^2/sqrt(Hz): how fast vx, vy may change
    angular_accel_noise_density: float = 2.0   # rad/s^2/sqrt(Hz)
    # The velocities' uncertainty grows as the densities above say up to these standard
    # deviations, not beyond (the robot's speeds are bounded). Unbounded, a silence of the
    # inputs left the yaw rate so uncertain that a wrong increment after it was taken as a
    # 9 rad/s turn (CARMEN seattle), and every right one after it refused. (Their means are not
    # pulled towards zero: with noisy increments, as the CARMEN logs' odometry, that lost a
    # third of the motion between scans.)
    speed_std_m_s: float = 1.0
    yaw_rate_std_rad_s: float = 1.5
    bias_random_walk: float = 1e-5         # rad/s/sqrt(s)
    initial_velocity_std: float = 1.0      # m/s, rad/s
    initial_bias_std: float = 0.01         # rad/s
    # A refused scan match is checked against the state replayed without each other input
    # since the last fused match: an input whose readings the match and the motion model both
    # contradict is blamed instead (EkfFusion._isolate).
    fault_isolation: bool = True
    # A scan input refused for this long (stamp time, and at least reacquire_after_matches
    # matches in a row) is taken back: the state's pose is doubted as far as it disagrees with
    # the current match, which is then fused (the pose moves to the matcher's).
    reacquire_after_s: float = 1.0
    reacquire_after_matches: int = 3
    # Readings kept since the last fused match for fault isolation, at most.
    isolation_log: int = 20000
    # A blamed input's next readings are held back until the next match vouches for them
    # where matches come at most this far apart (s).
    hold_back_max_s: float = 0.5
    # The dead reckoning's noise (every input but the scan matches) scaled by what the scan
    # matches' innovations show of it: the scale follows the mean of the last adaptive_window
    # matches' squared Mahalanobis distances per row (each capped at ten times the gate),
    # within [1, adaptive_max_scale], published on /diagnostics. The matches' own covariance
    # is taken as honest (the matcher calibrates it).
    adaptive_noise: bool = False
    adaptive_window: int = 50
    adaptive_max_scale: float = 100.0


@dataclass(frozen=True)
class Outcome:
    """What the filter did with a reading: fused, gated (rejected by the Mahalanobis test, with
    its squared distance), or neither (first message of a differential input, unknown
    keyframe...), with a note."""

    fused: bool = False
    gated: bool = False
    distance2: float = 0.0
    note: str = ''
    blamed: str = ''      # the input blamed for the disagreement (the reading then fused)
    dof: int = 0          # rows of the tested innovation


_HELD = Outcome(fused=True, note='increment held until the next output')


def _symmetric(m: NDArray[np.float64]) -> NDArray[np.float64]:
    return 0.5 * (m + m.T)


def _wrap(angle: float) -> float:
    """Scalar angle wrapped into [-pi, pi] (rad); math.remainder, much cheaper than arrays."""
    return math.remainder(angle, 2.0 * math.pi)


def body_to_odom(yaw: float) -> NDArray[np.float64]:
    """3x3 map of a body-frame pose error (x, y, yaw) to the odom frame at heading yaw (rad)."""
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def adjoint(motion: Pose2) -> NDArray[np.float64]:
    """3x3 adjoint of an SE(2) motion (m, rad): a body-frame error e at its end is the error
    adjoint(motion) @ e at its start (motion ⊕ e = e' ⊕ motion)."""
    c, s = math.cos(motion[2]), math.sin(motion[2])
    return np.array([[c, -s, motion[1]], [s, c, -motion[0]], [0.0, 0.0, 1.0]])


def relative_jacobian(clone: Pose2, pose: Pose2) -> tuple[Pose2, NDArray[np.float64],
                                                          NDArray[np.float64]]:
    """between(clone, pose) and its Jacobians with respect to the body-frame errors of pose and
    of clone (3x3 each; true = estimate ⊕ error): functions of the relative pose only."""
    c, s = math.cos(clone[2]), math.sin(clone[2])
    dx, dy = pose[0] - clone[0], pose[1] - clone[1]
    h = (c * dx + s * dy, -s * dx + c * dy, _wrap(pose[2] - clone[2]))
    j_pose = body_to_odom(h[2])
    j_clone = np.array([[-1.0, 0.0, h[1]], [0.0, -1.0, -h[0]], [0.0, 0.0, -1.0]])
    return h, j_pose, j_clone


def _selection(mask: tuple[bool, ...]) -> tuple[NDArray, tuple[NDArray, NDArray]] | None:
    """Rows a mask over three quantities selects, and the matching (rows, columns) index of a
    3x3 noise; None when it selects all three."""
    if all(mask):
        return None
    rows = np.array([i for i, used in enumerate(mask) if used], dtype=np.intp)
    return rows, np.ix_(rows, rows)



def _behind_match(match: Pose2, noise: NDArray) -> tuple[NDArray, NDArray]:
    """For the frame a match is taken in (pose ⊕ match⁻¹): adjoint(match), which turns errors
    into that frame's body-frame error, and the match's coordinate noise in its body frame."""
    to_body = body_to_odom(match[2]).T
    return adjoint(match), to_body @ noise @ to_body.T

@dataclass
class _Clone:
    """A slot of the state holding the pose at `stamp_ns` (None: empty), and for a
    differential input the reading taken then; for the scan matcher's input either the pose at
    its keyframe (key: the keyframe's stamp) or, with `map` set, the pose of a local map's
    origin in the odom frame (key: the map's stamp)."""

    offset: int
    stamp_ns: int | None = None
    key: object = None
    reading: Reading | None = None
    map: bool = False


@dataclass
class _Saved:
    """Everything EkfFusion.update changes, copied (fault isolation's checkpoint)."""

    x: NDArray[np.float64]
    p: NDArray[np.float64]
    stamp_ns: int | None
    slots: list[tuple]
    pending: dict
    last_seen: dict
    origin: dict
    initialized: bool
    refusals: dict
    held: set
    updates: int
    step_cross: NDArray[np.float64] | None
    step_variance: float


class EkfFusion:
    """Stamp-ordered EKF over the inputs in `inputs`; feed readings with update(name, reading)
    in stamp order and read `state`.

    A differential input with a pose mask only is coalesced: its newest reading waits until
    another kind of reading or a read of `state`, and the increment since its clone is fused
    once (the same increment, with the same summed covariance, as fusing every message, for a
    fraction of the work).
    """

    def __init__(self, inputs: tuple[InputConfig, ...], settings: EkfSettings | None = None
                 ) -> None:
        self.settings = settings or EkfSettings()
        self.inputs = {cfg.name: cfg for cfg in inputs}
        # One clone slot per differential or keyframe input, at fixed offsets.
        self._slots: dict[str, _Clone] = {}
        offset = BASE
        for cfg in inputs:
            if cfg.keyframes or (cfg.pose_mode == 'differential' and any(cfg.mask[:3])):
                self._slots[cfg.name] = _Clone(offset)
                offset += 3
        self._size = offset
        self._keyframe_slots = [self._slots[cfg.name] for cfg in inputs if cfg.keyframes]
        # A local map's offset random-walks with the distance travelled: (slot, x and y
        # variance per metre, yaw variance per metre).
        self._map_drift = [(self._slots[cfg.name],
                            np.array([cfg.map_variance_per_m, cfg.map_variance_per_m,
                                      cfg.map_yaw_variance_per_m]))
                           for cfg in inputs if cfg.keyframes and (cfg.map_variance_per_m
                                                                   or cfg.map_yaw_variance_per_m)]
        # Per input, the rows of its pose and twist measurements that its mask selects (None:
        # all three), as index arrays made once.
        self._rows = {cfg.name: (_selection(cfg.mask[:3]), _selection(cfg.mask[3:]))
                      for cfg in inputs}
        # Per input, its gate's threshold per number of measured rows (1 to 3).
        self._gates = {cfg.name: {dof: gate_threshold(cfg.gate_probability, dof)
                                  for dof in (1, 2, 3)} for cfg in inputs}
        self._diagonal = (np.arange(BASE), np.arange(BASE))
        self._velocity_diagonal = (np.arange(VX, WZ + 1), np.arange(VX, WZ + 1))
        # The rows of F (predict) that differ from the identity's: x, y and yaw.
        self._f = np.zeros((3, BASE))
        self._f[YAW, YAW] = 1.0
        # follow_heading_steps: covariance of the state's error with the heading error at the
        # last heading_step_variance() (n,), and that heading's variance; None: not followed.
        self._step_cross: NDArray[np.float64] | None = None
        self._step_variance = 0.0
        st = self.settings
        self._q_diagonal = np.array([st.pose_noise_density ** 2] * 3
                                    + [st.accel_noise_density ** 2] * 2
                                    + [st.angular_accel_noise_density ** 2,
                                       st.bias_random_walk ** 2])
        # The velocities' largest variances (their growth stops there).
        self._velocity_variance = np.array([st.speed_std_m_s ** 2] * 2
                                           + [st.yaw_rate_std_rad_s ** 2])
        self.reset()

    # -- state management --------------------------------------------------------------------
    def reset(self, pose: Pose2 = (0.0, 0.0, 0.0), covariance: NDArray | None = None) -> None:
        """Start again at pose (odom) with the given 3x3 covariance (zero: exactly known)."""
        s = self.settings
        self.x = np.zeros(self._size)
        self.x[:3] = pose
        self.p = np.zeros((self._size, self._size))
        if covariance is not None:
            to_body = body_to_odom(pose[2]).T
            self.p[:3, :3] = to_body @ np.asarray(covariance, dtype=float) @ to_body.T
        self.p[VX, VX] = self.p[VY, VY] = self.p[WZ, WZ] = s.initial_velocity_std ** 2
        self.p[BG, BG] = s.initial_bias_std ** 2
        self.stamp_ns: int | None = None
        for slot in self._slots.values():
            slot.stamp_ns, slot.key, slot.reading, slot.map = None, None, None, False
        self._pending: dict[str, Reading] = {}   # coalesced differential readings
        self._last_seen: dict[str, int] = {}     # stamp of each input's newest reading
        self._origin: dict[str, Pose2] = {}      # relative mode: source pose -> fused pose
        self._initialized = False                # an absolute reading has set the state
        self._refusals: dict[str, int] = {}      # each dead-reckoning input's refusals in a row
        self._held: set[str] = set()             # inputs blamed at the last match, held back
        self.updates = 0
        self.health = {name: InputHealth() for name in self.inputs}
        # Each input's noise scale (adaptive_noise: the dead reckoning's, from the matches).
        self.noise_scale = {name: 1.0 for name in self.inputs}
        self._ratios: deque[float] = deque(maxlen=self.settings.adaptive_window)
        # The state after the last fused scan match and every reading since (fault isolation).
        self._checkpoint: tuple[_Saved, list[tuple[str, Reading]]] | None = None
        self._replaying = False
        if self._step_cross is not None:
            self.follow_heading_steps()              # a new start: no step across it

    @property
    def gated(self) -> dict[str, int]:
        """Readings refused by each input's gate (inputs with none left out)."""
        return {name: h.refused for name, h in self.health.items() if h.refused}

    def set_pose(self, pose: Pose2, covariance: NDArray[np.float64]) -> None:
        """Put the robot at pose with the given covariance; velocities and bias are kept, every
        differential and keyframe input starts again from its next message."""
        self._flush()
        keep_x, keep_p = self.x[3:BASE].copy(), self.p[3:BASE, 3:BASE].copy()
        stamp = self.stamp_ns
        self.reset(pose, covariance)
        self.x[3:BASE], self.p[3:BASE, 3:BASE] = keep_x, keep_p
        self.stamp_ns = stamp

    def restart(self, name: str) -> None:
        """Input `name` starts again from its next message (its increments and its relative
        origin): what it measures has changed (a new sensor mount)."""
        self._flush()
        if name in self._slots:
            self._empty(self._slots[name])
        self._origin.pop(name, None)
        self._checkpoint = None

    # -- evaluation: the fused heading's steps (fusion_eval's chatter measure) -----------------
    def follow_heading_steps(self) -> None:
        """Follow the error of the heading's change from now on (heading_step_variance); off
        by default: it costs a vector update per prediction and correction."""
        self._step_cross = self.p[:, YAW].copy()
        self._step_variance = float(self.p[YAW, YAW])

    def heading_step_variance(self) -> float:
        """Variance (rad²) of the error of the heading's change since the previous call (or
        follow_heading_steps), the error of both ends and their correlation included:
        P_now + P_then - 2·Cov(e_now, e_then); then starts again from the current heading."""
        if self._step_cross is None:
            raise RuntimeError('follow_heading_steps() first')
        variance = float(self.p[YAW, YAW]) + self._step_variance \
            - 2.0 * float(self._step_cross[YAW])
        self.follow_heading_steps()
        return variance

    def _clone(self, slot: _Clone, key: object = None, reading: Reading | None = None) -> None:
        """Copy the current pose (and its correlations) into the slot."""
        at = slot.offset
        # Every entry of the slot's rows and columns is written below: nothing to empty first.
        self.x[at:at + 3] = self.x[:3]
        self.p[at:at + 3, :] = self.p[:3, :]
        self.p[:, at:at + 3] = self.p[:, :3]
        self.p[at:at + 3, at:at + 3] = self.p[:3, :3]
        if self._step_cross is not None:
            self._step_cross[at:at + 3] = self._step_cross[:3]
        slot.stamp_ns, slot.key, slot.reading, slot.map = self.stamp_ns, key, reading, False

    def _place_map(self, slot: _Clone, key: int, origin: Pose2,
                   covariance: NDArray | None = None) -> None:
        """A local map's origin in the odom frame, as a frame defined by the fused estimate
        (exact: no variance, no correlation with the pose). A copy of the pose with its
        correlations would carry the odom frame's whole heading uncertainty twice, and an EKF
        linearised at moving estimates then turns that unobservable common heading into a
        rotation of the map (CARMEN freiburg-101: the map turned 10 deg against the matcher's
        own headings in a minute, the fused ATE 3.0 m against the matcher's 0.24 m). Placed by
        a match instead of at its first scan, it carries that match's noise (`covariance`). Its
        drift afterwards is the random walk map_variance_per_m adds."""
        self._empty(slot)
        at = slot.offset
        self.x[at:at + 3] = (origin[0], origin[1], _wrap(origin[2]))
        if covariance is not None:
            self.p[at:at + 3, at:at + 3] = covariance
        slot.stamp_ns, slot.key, slot.map = self.stamp_ns, key, True

    def _empty(self, slot: _Clone) -> None:
        at = slot.offset
        self.x[at:at + 3] = 0.0
        self.p[at:at + 3, :] = 0.0
        self.p[:, at:at + 3] = 0.0
        if self._step_cross is not None:
            self._step_cross[at:at + 3] = 0.0
        slot.stamp_ns, slot.key, slot.reading, slot.map = None, None, None, False

    @property
    def pose(self) -> Pose2:
        return (float(self.x[X]), float(self.x[Y]), float(self.x[YAW]))

    @property
    def state(self) -> FusedState | None:
        """The fused estimate after every reading so far (None before the first)."""
        self._flush()
        if self.stamp_ns is None:
            return None
        p = self.p
        to_odom = body_to_odom(float(self.x[YAW]))
        return FusedState(self.stamp_ns, self.pose, _symmetric(to_odom @ p[:3, :3] @ to_odom.T),
                          (float(self.x[VX]), float(self.x[VY]), float(self.x[WZ])),
                          _symmetric(p[3:6, 3:6]), float(self.x[BG]), float(p[BG, BG]))

    # -- filter steps ------------------------------------------------------------------------
    def predict(self, stamp_ns: int) -> None:
        """Constant-velocity prediction of the current state to stamp_ns (clones stay)."""
        if self.stamp_ns is None:
            self.stamp_ns = stamp_ns
            return
        dt = (stamp_ns - self.stamp_ns) * 1e-9
        if dt <= 0.0:
            return
        yaw, vx, vy, wz = float(self.x[YAW]), float(self.x[VX]), float(self.x[VY]), \
            float(self.x[WZ])
        c, si = math.cos(yaw), math.sin(yaw)
        # The pose moves by the body motion u = (vx, vy, wz) dt; its body-frame error is carried
        # to the new pose by adjoint(u)⁻¹, a velocity error adds (u's end frame) dt.
        a, b, turn = vx * dt, vy * dt, wz * dt
        ct, st = math.cos(turn), math.sin(turn)
        # F is the identity but for its rows x, y, yaw (f): only those rows and columns of P
        # change.
        f = self._f
        f[X, X], f[X, Y], f[Y, X], f[Y, Y] = ct, st, -st, ct
        f[X, YAW], f[Y, YAW] = -ct * b + st * a, st * b + ct * a
        f[X, VX], f[X, VY], f[Y, VX], f[Y, VY] = ct * dt, st * dt, -st * dt, ct * dt
        f[YAW, WZ] = dt
        self.x[X] += (vx * c - vy * si) * dt
        self.x[Y] += (vx * si + vy * c) * dt
        self.x[YAW] = _wrap(yaw + wz * dt)
        p = self.p
        p[:3, :] = f @ p[:BASE, :]
        p[:, :3] = p[:, :BASE] @ f.T
        q = self._q_diagonal * dt
        # The velocities' growth stops at their largest variances (q >= 0: P stays PSD).
        room = 1.0 - p[self._velocity_diagonal] / self._velocity_variance
        q[VX:WZ + 1] *= np.clip(room, 0.0, 1.0)
        p[self._diagonal] += q
        if self._map_drift and (vx or vy):
            self._drift_maps(math.hypot(vx, vy) * dt)
        if self._step_cross is not None:
            self._step_cross[:3] = f @ self._step_cross[:BASE]
        self.stamp_ns = stamp_ns

    def _drift_maps(self, distance: float) -> None:
        """A local map's error where the robot is changes as it travels (m): a random walk of
        the map's pose seen from the robot (x, y and yaw variance per metre), turned into its
        origin's body-frame error (rel ⊕ w = (Ad(rel)·w) ⊕ rel, rel = between(origin, pose)):
        a heading drift turns the map about the robot, not about its far origin."""
        x = self.x.tolist()
        for slot, variance_per_m in self._map_drift:
            if not slot.map:
                continue
            at = slot.offset
            rel = se2.between((x[at], x[at + 1], x[at + 2]), (x[X], x[Y], x[YAW]))
            a = adjoint(rel)
            self.p[at:at + 3, at:at + 3] += (a * (variance_per_m * distance)) @ a.T

    def _correct(self, residual: NDArray, h: NDArray, r: NDArray, cfg: InputConfig,
                 dry: bool = False, partial: bool = False) -> Outcome:
        """EKF update with innovation `residual` (angle rows already wrapped), Jacobian h over
        the whole state and noise r; refused when the squared Mahalanobis distance exceeds the
        input's gate (the chi-square quantile of its gate_probability for these rows). With
        `partial` (velocities: independent quantities), a reading refused as a whole is fused
        without its worst rows where the rest passes (_partial). dry: only the distance,
        nothing changed."""
        scale = self.noise_scale[cfg.name]
        if scale != 1.0:
            r = r * scale
        ph = self.p @ h.T
        s = h @ ph + r
        try:
            s_inv = np.linalg.inv(s)
        except np.linalg.LinAlgError:
            return Outcome(note='singular innovation covariance')
        d2 = float(residual @ s_inv @ residual)
        dof = residual.size
        gate = self._gates[cfg.name][dof]
        if dry:
            return Outcome(gated=not d2 <= gate, distance2=d2, dof=dof, note='tested only')
        if self.settings.adaptive_noise and cfg.keyframes and not self._replaying:
            self._adapt(min(d2, 10.0 * gate) / dof)
        if not d2 <= gate:
            refused = Outcome(gated=True, distance2=d2, dof=dof,
                              note=f'squared Mahalanobis distance {d2:.1f} > {gate:.1f} (gate at '
                                   f'{cfg.gate_probability:g} for {dof} rows)')
            if partial and dof > 1:
                return self._partial(residual, h, r, cfg, s, refused)
            return refused
        k = ph @ s_inv
        if cfg.keyframes:
            # A scan match corrects where the robot is, not how fast it moves: taken as
            # velocity, a correction right after a propagation became a velocity of the
            # correction over that short step (CARMEN aces: a 37 deg correction 0.16 s after
            # the last odometry made a 6 rad/s turn, and the next odometry was refused). The
            # velocities come from the dead reckoning.
            k[VX:WZ + 1] = 0.0
        self._keep_keyframes(k)
        self._inject(k @ residual)
        # P - K H P - (K H P)' + K S K': the covariance of any gain, not only the optimal one.
        khp = k @ ph.T
        self.p = _symmetric(self.p - khp - khp.T + k @ s @ k.T)
        if self._step_cross is not None:
            self._step_cross -= k @ (h @ self._step_cross)     # (I - KH)·c, any gain
        self.updates += 1
        return Outcome(fused=True, distance2=d2, dof=dof)

    def _partial(self, residual: NDArray, h: NDArray, r: NDArray, cfg: InputConfig,
                 s: NDArray, refused: Outcome) -> Outcome:
        """A dead-reckoning reading without the row that strays furthest (its residual over
        its standard deviation), fused when the rest passes the gate (a skid-steer base's yaw
        rate against the gyro's, its speeds right), else the refusal."""
        worst = int(np.argmax(residual * residual / np.diag(s)))
        keep = np.array([i for i in range(residual.size) if i != worst])
        outcome = self._correct(residual[keep], h[keep], r[np.ix_(keep, keep)], cfg,
                                partial=True)
        if outcome.gated:
            return refused
        return replace(outcome, note=f'row {worst} of {residual.size} refused ({refused.note})')

    def _adapt(self, ratio: float) -> None:
        """Move the dead reckoning's noise scale towards what the matches' innovations show:
        by the window's mean distance per row (1 when consistent) to the power 1/window per
        match."""
        window = self._ratios
        window.append(ratio)
        mean = sum(window) / len(window)
        if mean <= 0.0:
            return
        st = self.settings
        for name, cfg in self.inputs.items():
            if not cfg.keyframes:
                self.noise_scale[name] = min(max(
                    self.noise_scale[name] * mean ** (1.0 / st.adaptive_window), 1.0),
                    st.adaptive_max_scale)

    def _keep_keyframes(self, gain: NDArray[np.float64]) -> None:
        """A keyframe's clone is not revised: it is the pose published at the keyframe's scan,
        onto which every later match is composed. The correction the optimal gain gives it goes
        to the pose through the motion since it (pose = keyframe ⊕ motion: the motion keeps
        its optimal correction), so the published motion from scan to scan is the fused one.
        Revising the keyframe instead moved the whole chain on the real logs: the wheels'
        increment across a keyframe and the velocities tie it to the motion after it. The
        clones taken since the keyframe move with the pose: left behind, the next increment
        from one would see the shift as motion and take most of it back."""
        for slot in self._keyframe_slots:
            if slot.key is None or slot.stamp_ns is None or slot.map:
                continue   # a map's offset is a state like any other: revised by the gain
            at = slot.offset
            x = self.x.tolist()       # plain floats: this runs at every correction
            keyframe = (x[at], x[at + 1], x[at + 2])
            undone = gain[at:at + 3]
            # A clone since the keyframe is keyframe ⊕ (motion to it) as the pose is: moved with
            # it, an increment from it to the pose keeps its optimal correction.
            moved = [0] + [other.offset for other in self._slots.values()
                           if other is not slot and other.stamp_ns is not None
                           and other.stamp_ns >= slot.stamp_ns]
            for to in moved:
                motion = se2.between(keyframe, (x[to], x[to + 1], x[to + 2]))
                gain[to:to + 3] -= adjoint(se2.inverse(motion)) @ undone
            gain[at:at + 3] = 0.0

    def _inject(self, error: NDArray[np.float64]) -> None:
        """Apply a correction: pose and clones composed with their body-frame errors, the
        rest added."""
        x, e = self.x.tolist(), error.tolist()   # plain floats: a dozen scalars per update
        for at in [0] + [slot.offset for slot in self._slots.values()
                         if slot.stamp_ns is not None]:
            if e[at] == 0.0 and e[at + 1] == 0.0 and e[at + 2] == 0.0:
                continue   # not corrected (a keyframe: _keep_keyframes)
            moved = se2.compose((x[at], x[at + 1], x[at + 2]), (e[at], e[at + 1], e[at + 2]))
            x[at:at + 3] = (moved[0], moved[1], _wrap(moved[2]))
        for i in range(3, BASE):
            x[i] += e[i]
        self.x[:] = x

    # -- measurements --------------------------------------------------------------------------
    def _coalesced(self, cfg: InputConfig) -> bool:
        return cfg.pose_mode == 'differential' and not cfg.keyframes and not any(cfg.mask[3:])

    def update(self, name: str, reading: Reading) -> Outcome:
        """Fuse one reading of input `name` (stamps must not go backwards: FusionSession
        orders them); every input's reading meets its gate, a refused scan match goes through
        fault isolation (_isolate) and, refused long enough, re-acquisition (_reacquire)."""
        cfg = self.inputs[name]
        if cfg.keyframes:
            return self._scan_update(cfg, reading)
        if self._checkpoint is not None:
            log = self._checkpoint[1]
            if len(log) < self.settings.isolation_log:
                log.append((name, reading))
            else:
                self._checkpoint = None           # too long since the last match to replay
                self._held.clear()
        if name in self._held:
            # Blamed at the last match: held back until the next one vouches for it (_vouch).
            if self._checkpoint is not None:
                self.health[name].refused_at(reading.stamp_ns, 'held back: blamed at the last '
                                                               'scan match')
                return Outcome(gated=True, note='held back until the next scan match')
            self._held.discard(name)
        outcome = self._update(cfg, reading)
        if outcome is not _HELD:
            self._record(name, outcome, reading.stamp_ns)
        return outcome

    def _update(self, cfg: InputConfig, reading: Reading) -> Outcome:
        """update() without the bookkeeping (fault isolation replays readings through it)."""
        name = cfg.name
        previous_stamp = self._last_seen.get(name)
        self._last_seen[name] = reading.stamp_ns
        if self._coalesced(cfg):
            slot = self._slots[name]
            gap = previous_stamp is not None and \
                reading.stamp_ns - previous_stamp > cfg.max_gap_s * 1e9
            if slot.stamp_ns is not None and not gap:
                # As it came: most held readings are replaced before they are fused, so the
                # heading delay is applied when one is (_flush).
                self._pending[name] = reading
                return _HELD
            reading = _with_heading_delay(cfg, reading)
            self._flush()
            self.predict(reading.stamp_ns)
            self._clone(slot, reading=reading)
            return Outcome(note='first message of this differential input (or after a gap)')
        reading = _with_heading_delay(cfg, reading)
        self._flush()
        self.predict(reading.stamp_ns)
        outcomes = []
        if cfg.keyframes:
            outcomes.append(self._keyframe(cfg, reading))
        elif reading.pose is not None and any(cfg.mask[:3]):
            outcomes.append(self._pose(cfg, reading))
        if reading.twist is not None and any(cfg.mask[3:]):
            outcomes.append(self._twist(cfg, reading))
        if not outcomes:
            return Outcome(note="nothing in this reading is in the input's mask")
        gated = [o for o in outcomes if o.gated]
        if gated:
            return gated[0]
        fused = [o for o in outcomes if o.fused]
        return fused[0] if fused else outcomes[0]

    def _record(self, name: str, outcome: Outcome, stamp_ns: int) -> None:
        """The input's health after a reading's outcome (not while replaying)."""
        if self._replaying:
            return
        if outcome.gated:
            self.health[name].refused_at(stamp_ns, outcome.note)
        elif outcome.fused:
            self.health[name].accepted(stamp_ns)

    def _flush(self) -> Outcome | None:
        """Fuse the held differential readings, oldest first; the outcome of a gated one."""
        gated = None
        while self._pending:
            # Oldest first; at equal stamps in RANK's order (the wheels' increment before the
            # IMU's: the wheels' pin the heading where they see no motion, and an integrator's
            # own corrections while standing still then meet the gate).
            name = min(self._pending, key=lambda n: (self._pending[n].stamp_ns, RANK.get(n, 0)))
            cfg = self.inputs[name]
            reading = _with_heading_delay(cfg, self._pending.pop(name))
            self.predict(reading.stamp_ns)
            outcome = self._differential(cfg, reading)
            self._record(name, outcome, reading.stamp_ns)
            if outcome.gated:
                gated = outcome
        return gated

    # -- integrity: fault isolation and re-acquisition of the scan input ------------------------
    def _scan_update(self, cfg: InputConfig, reading: Reading) -> Outcome:
        """A scan match (or a map's or keyframe's start) through its gate; refused, the
        readings of the other inputs since the last fused match are checked (_isolate), and a
        source refused long enough is taken back (_reacquire)."""
        if self._held and self._checkpoint is not None:
            self._vouch(cfg, reading)
        outcome = self._update(cfg, reading)
        if outcome.gated and self.settings.fault_isolation and self._checkpoint is not None:
            outcome = self._isolate(cfg, reading, outcome)
        health = self.health[cfg.name]
        if outcome.gated:
            health.refused_at(reading.stamp_ns, outcome.note)
            if health.streak >= self.settings.reacquire_after_matches and \
                    reading.stamp_ns - health.streak_start_ns \
                    >= self.settings.reacquire_after_s * 1e9:
                outcome = self._reacquire(cfg, reading, health.streak)
                health.reacquired += 1
                health.streak, health.streak_start_ns = 0, None
        elif outcome.fused:
            health.accepted(reading.stamp_ns)
        if not outcome.gated:
            self._checkpoint = (self._save(), [])
        return outcome

    def _isolate(self, cfg: InputConfig, reading: Reading, refused: Outcome) -> Outcome:
        """A scan match the state refused, tested against the state replayed from the last
        fused match without each other input in turn. An input is blamed when, without it, the
        match passes its gate and that input's latest reading is less consistent with the
        replayed state (the motion model and the other inputs) than the match is: its readings
        since the last match are dropped, the match is fused. Otherwise the refusal stands."""
        saved, log = self._checkpoint
        after = self._save()
        best: tuple[float, str, _Saved, int] | None = None
        for name in {n for n, _ in log}:
            last = max(i for i, (n, _) in enumerate(log) if n == name)
            self._restore(saved)
            self._replaying = True
            try:
                tested = None
                for i, (n, r) in enumerate(log):
                    if n != name:
                        self._update(self.inputs[n], r)
                    elif i == last:
                        tested = self._restart_from(self.inputs[n], r)
                match = self._dry(cfg, reading)
            finally:
                self._replaying = False
            if tested is None or match is None:
                continue
            gate = self._gates[cfg.name][match[1]]
            p_input, p_match = tail_probability(*tested), tail_probability(*match)
            if match[0] <= gate and p_input < p_match and (best is None or p_input < best[0]):
                best = (p_input, name, self._save(), sum(n == name for n, _ in log))
        if best is None:
            self._restore(after)
            return refused
        _, name, replayed, count = best
        self._restore(replayed)
        outcome = self._update(cfg, reading)
        if not outcome.fused:              # cannot happen: the dry test passed
            self._restore(after)
            return refused
        self._velocity_from_matches(saved)
        problem = (f'{count} readings since the last fused scan match disagreed with the match '
                   'and the motion model: dropped')
        # Held back until the next match vouches for it where that match is near: between
        # matches seconds apart (a CARMEN log's) the motion model alone cannot carry the pose.
        if saved.stamp_ns is not None and \
                (reading.stamp_ns - saved.stamp_ns) * 1e-9 <= self.settings.hold_back_max_s:
            self._held.add(name)
            problem += ', the next held back until a match vouches for them'
        self.health[name].blamed_for(count, reading.stamp_ns, problem)
        return replace(outcome, blamed=name, note=f'{name} blamed: {problem}')

    def _vouch(self, cfg: InputConfig, reading: Reading) -> None:
        """Before a scan match: the readings held back since the last one (inputs blamed
        there) replayed in; kept, and their inputs used again, where the match then passes its
        gate and agrees with them at least as well as without them, else dropped (their inputs
        restart from their latest reading, still held back when the match is fused)."""
        saved, log = self._checkpoint
        current = self._save()
        self._replaying = True
        try:
            without = self._dry(cfg, reading)
            self._restore(saved)
            for n, r in log:
                self._update(self.inputs[n], r)
            match = self._dry(cfg, reading)
        finally:
            self._replaying = False
        # A slip still going on moves the state by little over one match interval: passing
        # the gate alone vouched for it (a 0.5 s wheel slip in the fault catalogue was taken
        # back after 0.1 s, and the matches then refused for a second).
        if match is not None and match[0] <= self._gates[cfg.name][match[1]] and (
                without is None or match[0] <= without[0]):
            self._held.clear()             # vouched for: in use again
            return
        self._restore(current)
        self._replaying = True
        try:
            for name in list(self._held):
                latest = [r for n, r in log if n == name]
                if latest:
                    self._restart_from(self.inputs[name], latest[-1])
        finally:
            self._replaying = False

    def _velocity_from_matches(self, saved: _Saved) -> None:
        """After a blame: the velocities from the pose's motion since the last fused match
        (the blamed input had driven them), as uncertain as the robot's speeds allow."""
        dt = (self.stamp_ns - saved.stamp_ns) * 1e-9 if saved.stamp_ns is not None else 0.0
        if dt <= 0.0:
            return
        motion = se2.between((float(saved.x[X]), float(saved.x[Y]), float(saved.x[YAW])),
                             self.pose)
        self.x[VX:WZ + 1] = (motion[0] / dt, motion[1] / dt, motion[2] / dt)
        self.p[VX:WZ + 1, :] = 0.0
        self.p[:, VX:WZ + 1] = 0.0
        self.p[VX:WZ + 1, VX:WZ + 1] = np.diag(self._velocity_variance) * 0.01
        if self._step_cross is not None:
            self._step_cross[VX:WZ + 1] = 0.0

    def _restart_from(self, cfg: InputConfig, reading: Reading) -> tuple[float, int] | None:
        """Fault isolation: how far the input's latest reading (its increment since its clone,
        or its twist) lies from the replayed state (squared Mahalanobis distance, rows), and
        the input restarted from it (its next increment starts there); None when it measures
        nothing testable."""
        reading = _with_heading_delay(cfg, reading)
        self._flush()
        self.predict(reading.stamp_ns)
        tested = None
        slot = self._slots.get(cfg.name)
        if slot is not None and slot.reading is not None and reading.pose is not None:
            tested = self._differential(cfg, reading, dry=True)
        elif reading.twist is not None and any(cfg.mask[3:]):
            tested = self._twist(cfg, reading, dry=True)
        if slot is not None:
            self._clone(slot, reading=reading)
        self._last_seen[cfg.name] = reading.stamp_ns
        if tested is None or not tested.dof:
            return None
        return tested.distance2, tested.dof

    def _dry(self, cfg: InputConfig, reading: Reading) -> tuple[float, int] | None:
        """The scan match's squared Mahalanobis distance and rows against the current state,
        nothing fused; None when it would not be tested (a map or keyframe not yet placed)."""
        self._flush()
        self.predict(reading.stamp_ns)
        slot = self._slots[cfg.name]
        if reading.pose is None or slot.stamp_ns is None:
            return None
        if reading.map_ns is not None:
            if not slot.map or slot.key != reading.map_ns:
                return None
        elif slot.map or slot.key != reading.keyframe_ns:
            return None
        noise = self._pose_noise(cfg, reading.pose_covariance, reading.pose, False)
        outcome = self._relative_update(cfg, slot, reading.pose, noise, dry=True)
        return (outcome.distance2, outcome.dof) if outcome.dof else None

    def _reacquire(self, cfg: InputConfig, reading: Reading, streak: int) -> Outcome:
        """Take a scan input back after `streak` refused matches: a disagreement that lasted
        this long is the state's (its dead reckoning erred while the matches were refused), so
        the pose's body-frame uncertainty grows by the disagreement and the match is fused. A
        map or keyframe not yet placed is placed from this match."""
        slot = self._slots[cfg.name]
        noise = self._pose_noise(cfg, reading.pose_covariance, reading.pose, False)
        in_frame = slot.stamp_ns is not None and (
            (reading.map_ns is not None and slot.map and slot.key == reading.map_ns)
            or (reading.map_ns is None and not slot.map and slot.key == reading.keyframe_ns))
        note = f'{streak} matches refused in a row: taken back'
        if not in_frame:
            return self._update(cfg, reading)
        at = slot.offset
        frame = (float(self.x[at]), float(self.x[at + 1]), float(self.x[at + 2]))
        predicted = se2.between(frame, self.pose)
        # The disagreement in the pose's body frame: pose ⊕ e = frame ⊕ match.
        error = se2.between(self.pose, se2.compose(frame, reading.pose))
        self.p[_DIAG3] += np.square(error) + 1e-12
        outcome = self._relative_update(cfg, slot, reading.pose, noise)
        del predicted
        return replace(outcome, note=f'{note}; {outcome.note}' if outcome.note else note)

    def _save(self) -> _Saved:
        """A copy of everything update() changes (fault isolation's checkpoint)."""
        return _Saved(self.x.copy(), self.p.copy(), self.stamp_ns,
                      [(c.stamp_ns, c.key, c.reading, c.map) for c in self._slots.values()],
                      dict(self._pending), dict(self._last_seen), dict(self._origin),
                      self._initialized, dict(self._refusals), set(self._held), self.updates,
                      None if self._step_cross is None else self._step_cross.copy(),
                      self._step_variance)

    def _restore(self, saved: _Saved) -> None:
        self.x, self.p, self.stamp_ns = saved.x.copy(), saved.p.copy(), saved.stamp_ns
        for slot, (stamp, key, reading, is_map) in zip(self._slots.values(), saved.slots):
            slot.stamp_ns, slot.key, slot.reading, slot.map = stamp, key, reading, is_map
        self._pending, self._last_seen = dict(saved.pending), dict(saved.last_seen)
        self._origin, self._initialized = dict(saved.origin), saved.initialized
        self._refusals = dict(saved.refusals)
        self._held = set(saved.held)
        self.updates = saved.updates
        self._step_cross = None if saved.step_cross is None else saved.step_cross.copy()
        self._step_variance = saved.step_variance

    @staticmethod
    def _masked(selection, residual, h, r) -> tuple:
        """The rows of residual, h and r that an input's mask selects (_selection)."""
        if selection is None:
            return residual, h, r
        rows, block = selection
        return residual[rows], h[rows], r[block]

    @staticmethod
    def _pose_noise(cfg: InputConfig, covariance, increment: Pose2 | None,
                    static: bool, dt: float = 0.0) -> NDArray[np.float64]:
        use_model = cfg.covariance == 'model' or (
            cfg.covariance == 'auto' and (covariance is None or static or not np.any(covariance)))
        if use_model:
            if increment is None:
                return np.diag([max(cfg.noise.min_variance, MIN_VARIANCE)] * 3)
            return cfg.noise.increment_covariance(increment, dt)
        cov = _symmetric(np.asarray(covariance, dtype=float)) * cfg.covariance_scale
        cov[_DIAG3] += MIN_VARIANCE
        return cov

    def _pose(self, cfg: InputConfig, reading: Reading) -> Outcome:
        if cfg.pose_mode == 'differential':
            return self._differential(cfg, reading)
        pose = reading.pose
        cov = self._pose_noise(cfg, reading.pose_covariance, None, False)
        if cfg.pose_mode == 'relative':
            if cfg.name not in self._origin:
                # The source's first pose is where we are now: later ones are relative to it.
                self._origin[cfg.name] = se2.compose(self.pose, se2.inverse(pose))
                return Outcome(note='first message: origin of the relative input')
            _, j = se2.compose_jacobians(self._origin[cfg.name], pose)
            pose = se2.compose(self._origin[cfg.name], pose)
            cov = j @ cov @ j.T
        if cfg.pose_mode == 'absolute' and not self._initialized:
            # As robot_localization: the filter's first absolute reading sets what it measures
            # (an IMU's heading in its world frame is where the fused frame's heading starts).
            # Done in the odom frame, where the reading's quantities are.
            self._initialized = True
            rows = [i for i in range(3) if cfg.mask[i]]
            to_odom = np.eye(self._size)
            to_odom[:3, :3] = body_to_odom(float(self.x[YAW]))
            p = to_odom @ self.p @ to_odom.T
            for i in rows:
                self.x[i] = pose[i]
                p[i, :] = 0.0
                p[:, i] = 0.0
            p[np.ix_(rows, rows)] = cov[np.ix_(rows, rows)]
            to_body = np.eye(self._size)
            to_body[:3, :3] = body_to_odom(float(self.x[YAW])).T
            self.p = _symmetric(to_body @ p @ to_body.T)
            if self._step_cross is not None:
                self.follow_heading_steps()      # a new start: no step across it
            return Outcome(note='first absolute reading: state set to it')
        residual = np.array([pose[0] - self.x[X], pose[1] - self.x[Y],
                             _wrap(pose[2] - float(self.x[YAW]))])
        h = np.zeros((3, self._size))
        h[:, :3] = body_to_odom(float(self.x[YAW]))
        return self._correct(*self._masked(self._rows[cfg.name][0], residual, h, cov),
                             cfg)

    def _differential(self, cfg: InputConfig, reading: Reading, dry: bool = False) -> Outcome:
        """The motion from the slot's reading to this one, fused against the clone (dry: only
        tested, the clone left as it is)."""
        slot = self._slots[cfg.name]
        previous = slot.reading
        if previous is None:
            self._clone(slot, reading=reading)
            return Outcome(note='first message of this differential input (or after a gap)')
        increment = se2.between(previous.pose, reading.pose)
        static = False
        cov = None
        # 'model' never reads the message's covariance (an eigendecomposition per message).
        if cfg.covariance != 'model' and reading.pose_covariance is not None \
                and previous.pose_covariance is not None:
            static = bool(np.array_equal(reading.pose_covariance, previous.pose_covariance))
            if not static and cfg.covariance == 'auto':
                # None (then the noise model) when the source's covariance does not compound.
                cov = compounded_increment_covariance(
                    previous.pose, previous.pose_covariance, reading.pose,
                    reading.pose_covariance)
            elif not static:
                cov = increment_covariance(previous.pose, previous.pose_covariance,
                                           reading.pose, reading.pose_covariance)
        dt = (reading.stamp_ns - previous.stamp_ns) * 1e-9
        noise = self._pose_noise(cfg, cov, increment, static, dt)
        # A dead-reckoning increment's error is mostly the slow drift its noise describes,
        # which the motion model cannot see from one increment to the next: SHORT_TERM_SHARE
        # of it is the increment's own noise, the rest grows the pose's uncertainty once the
        # increment is in (as a motion input's noise). All of it as the increment's noise, the
        # constant-velocity model took a third of the motion of the CARMEN Edmonton log's
        # odometry away (jittered stamps: 6.3 m fused of 9.3 m travelled in 20 s).
        short = noise * _SHORT_TERM
        outcome = self._relative_update(cfg, slot, increment, short, dt, dry)
        if not dry:
            outcome, restart = self._after_refusal(
                cfg, outcome, (reading.stamp_ns - slot.stamp_ns) * 1e-9,
                lambda: self._relative_update(cfg, slot, increment, short, dt))
            if outcome.fused:
                self._drift(increment, (noise - short) * self.noise_scale[cfg.name])
            if not outcome.gated or restart or dt > cfg.max_gap_s:
                self._clone(slot, reading=reading)
        return outcome

    def _drift(self, increment: Pose2, covariance: NDArray[np.float64]) -> None:
        """The pose's uncertainty grown by an increment's drift (its covariance in the frame
        the increment started from, turned into the pose's body frame)."""
        turn = body_to_odom(increment[2]).T
        self.p[:3, :3] += turn @ covariance @ turn.T

    def _after_refusal(self, cfg: InputConfig, outcome: Outcome, span_s: float,
                       retry) -> tuple[Outcome, bool]:
        """What follows a dead-reckoning reading's outcome, and whether the input restarts from
        it. Refused once, the next reading is measured from the last accepted one (a reading
        whose pose or stamp is off drops out, its motion does not). Refused again, that span
        contradicts the state: where every dead-reckoning input is refused, it is the velocity
        the motion model extrapolates (a burst taken as velocity by an earlier correction),
        which is forgotten (zero, as uncertain as the robot's speeds, the motion over the span
        span_s as uncertain as that makes it) and the reading tried again (refused still, the
        span goes on until the input's max_gap_s); where another one is accepted, it is this
        input (a gyro integrator's drift before its calibration), which restarts from this
        reading."""
        name = cfg.name
        if not outcome.gated:
            self._refusals[name] = 0
            return outcome, False
        self._refusals[name] = self._refusals.get(name, 0) + 1
        if self._refusals[name] < 2:
            return outcome, False
        self._refusals[name] = 0
        others = [n for n, c in self.inputs.items() if n != name and not c.keyframes
                  and n in self._last_seen]
        if others and not all(self._refusals.get(n, 0) for n in others):
            note = '; refused twice in a row while the other dead reckoning is not: restarted'
            return replace(outcome, note=outcome.note + note), True
        self.x[VX:WZ + 1] = 0.0
        self.p[VX:WZ + 1, :] = 0.0
        self.p[:, VX:WZ + 1] = 0.0
        self.p[VX:WZ + 1, VX:WZ + 1] = np.diag(self._velocity_variance)
        self.p[_DIAG3] += self._velocity_variance * span_s ** 2
        if self._step_cross is not None:
            self._step_cross[VX:WZ + 1] = 0.0
        again = retry()
        note = 'refused twice in a row: the velocity forgotten'
        return replace(again, note=f'{again.note}; {note}' if again.note else note), False

    def _relative_update(self, cfg: InputConfig, slot: _Clone, measured: Pose2,
                         noise: NDArray, dt: float = 0.0, dry: bool = False) -> Outcome:
        at = slot.offset
        clone = (float(self.x[at]), float(self.x[at + 1]), float(self.x[at + 2]))
        predicted, j_pose, j_clone = relative_jacobian(clone, self.pose)
        h = np.zeros((3, self._size))
        h[:, :3] = j_pose
        h[:, at:at + 3] = j_clone
        yaw = predicted[2]
        if cfg.gyro_bias:
            # Heading increments of a gyro carry its remaining bias times the interval.
            h[2, BG] = dt
            yaw += float(self.x[BG]) * dt
        residual = np.array([measured[0] - predicted[0], measured[1] - predicted[1],
                             _wrap(measured[2] - yaw)])
        selection = self._rows[cfg.name][0]
        if not cfg.keyframes and not dry:
            implausible = self._implausible(cfg, measured, dt, selection)
            if implausible is not None:
                return implausible
        return self._correct(*self._masked(selection, residual, h, noise), cfg, dry)

    def _implausible(self, cfg: InputConfig, measured: Pose2, dt: float,
                     selection) -> Outcome | None:
        """A refusal when an increment (m, rad) over dt (s) is beyond the motion the robot
        can make (its velocities' spread, zero-mean, at the input's gate), else None."""
        if dt <= 0.0:
            return None
        motion = np.asarray(measured) / dt
        z2 = motion * motion / self._velocity_variance
        if selection is not None:
            z2 = z2[selection[0]]
        d2 = float(z2.sum())
        gate = self._gates[cfg.name][z2.size]
        if d2 <= gate:
            return None
        return Outcome(gated=True, distance2=d2, dof=z2.size, note=(
            f'an increment the robot cannot make: {math.hypot(measured[0], measured[1]):.3f} m '
            f'and {math.degrees(abs(measured[2])):.1f} deg in {dt:.3f} s'))

    def _map(self, cfg: InputConfig, reading: Reading) -> Outcome:
        """A match in a local map's frame: it measures between(map origin, pose), the map's
        origin a state (its slot) that every match against the map refines, and that drifts
        with the distance travelled. The first match of a map only places its origin."""
        slot = self._slots[cfg.name]
        noise = self._pose_noise(cfg, reading.pose_covariance, reading.pose, False)
        if not slot.map or slot.key != reading.map_ns:
            # Its origin was not fused (dropped as late, or before the filter started).
            # pose ⊕ match⁻¹, uncertain by the match's noise (e_o = adjoint(match) e_m, e_m
            # in the match's body frame).
            j, match_noise = _behind_match(reading.pose, noise)
            self._place_map(slot, reading.map_ns,
                            se2.compose(self.pose, se2.inverse(reading.pose)),
                            j @ match_noise @ j.T)
            return Outcome(note="map adopted: its origin placed by this match")
        return self._relative_update(cfg, slot, reading.pose, noise)

    def _keyframe(self, cfg: InputConfig, reading: Reading) -> Outcome:
        slot = self._slots[cfg.name]
        if reading.map_ns is not None and reading.pose is None:
            # A map starts at this reading: its origin is the pose now, exactly.
            self._place_map(slot, reading.map_ns, self.pose)
            return Outcome(note="a map's origin")
        if reading.map_ns is not None:
            return self._map(cfg, reading)
        outcome = Outcome(note='no match in this reading')
        if reading.pose is not None and reading.keyframe_ns is not None:
            noise = self._pose_noise(cfg, reading.pose_covariance, reading.pose, False)
            if slot.key == reading.keyframe_ns and not slot.map:
                outcome = self._relative_update(cfg, slot, reading.pose, noise)
            else:
                # The message that started this keyframe was never fused (dropped as late,
                # or before the filter started): adopt the keyframe from this match, so the
                # later matches against it measure the motion since this one.
                self._adopt_keyframe(slot, reading.keyframe_ns, reading.pose, noise)
                outcome = Outcome(note='keyframe adopted from its first fused match')
        if reading.new_keyframe:
            self._clone(slot, key=reading.stamp_ns)
        return outcome

    def _adopt_keyframe(self, slot: _Clone, key: int, match: Pose2, noise: NDArray) -> None:
        """Fill the slot with the keyframe's pose implied by the current pose and a match
        against it (pose ⊕ match⁻¹), its covariance and correlations carried from the pose
        plus the match's noise: that match then tells nothing about the current pose, and
        only the motion between later matches and it is fused."""
        # keyframe ⊕ e_k = pose ⊕ e_p ⊕ (match ⊕ e_m)⁻¹  gives  e_k = adjoint(match)(e_p - e_m),
        # with e_m the match's coordinate noise turned into its body frame.
        j, match_noise = _behind_match(match, noise)
        self._empty(slot)
        at = slot.offset
        keyframe = se2.compose(self.pose, se2.inverse(match))
        self.x[at:at + 3] = (keyframe[0], keyframe[1], _wrap(keyframe[2]))
        row = j @ self.p[:3, :]
        self.p[at:at + 3, :] = row
        self.p[:, at:at + 3] = row.T
        self.p[at:at + 3, at:at + 3] = j @ (self.p[:3, :3] + match_noise) @ j.T
        if self._step_cross is not None:
            self._step_cross[at:at + 3] = j @ self._step_cross[:3]
        slot.stamp_ns, slot.key, slot.reading = self.stamp_ns, key, None

    def _twist(self, cfg: InputConfig, reading: Reading, dry: bool = False) -> Outcome:
        cov = reading.twist_covariance
        if cfg.covariance == 'model' or cov is None or not np.all(np.diag(cov) > 0.0):
            cov = np.diag(cfg.twist_variance)
        cov = _symmetric(np.asarray(cov, dtype=float))
        cov[_DIAG3] += MIN_VARIANCE
        h = np.zeros((3, self._size))
        h[0, VX] = h[1, VY] = h[2, WZ] = 1.0
        if cfg.gyro_bias:
            h[2, BG] = 1.0
        residual = np.asarray(reading.twist, dtype=float) - h @ self.x
        outcome = self._correct(*self._masked(self._rows[cfg.name][1], residual, h, cov),
                                cfg, dry, partial=True)
        if dry:
            return outcome
        return self._after_refusal(cfg, outcome, 0.0, lambda: self._correct(
            *self._masked(self._rows[cfg.name][1], np.asarray(reading.twist, dtype=float)
                          - h @ self.x, h, cov), cfg, partial=True))[0]


def _with_heading_delay(cfg: InputConfig, reading: Reading) -> Reading:
    """The reading with its yaw read as yaw + yaw rate x cfg.heading_delay_s (a heading that
    lags its stamp)."""
    if cfg.heading_delay_s and reading.pose is not None and reading.twist is not None:
        pose = reading.pose
        return replace(reading, pose=(pose[0], pose[1],
                                      pose[2] + reading.twist[2] * cfg.heading_delay_s))
    return reading
