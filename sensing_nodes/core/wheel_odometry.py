"""Differential-drive dead reckoning from wheel encoder angles, with propagated covariance.

Poses are (x, y, yaw) of base_link in the odom frame (m, rad); twists are (vx, vy, wz) in
base_link (m/s, rad/s). Wheel order is always [left, right]. Covariance follows the classic
per-wheel model: each wheel's travelled distance has variance k * |ds_wheel| (k in m^2 per m),
independent between wheels and between steps, so the uncertainty grows with distance driven.
Optionally a systematic part is added: each wheel's effective radius is off by a constant
relative error of standard deviation `radius_multiplier_std` (what calibration leaves); its effect
is carried as the Jacobian of the pose w.r.t. the two radius errors, so it correlates over the
path.

Encoder wrap: some drivers publish positions wrapped into (-pi, pi]. An increment whose size is
impossible for the wheel in dt (|dphi| > max_wheel_speed * dt) but becomes possible with one
turn (2 pi) taken off is a wrapped reading and is folded back. This is only unambiguous while the
wheel turns less than pi per sample, which holds at usual rates (50 rad/s at 100 Hz is 0.5 rad).
An increment that is implausible even after folding is rejected by WheelOdometry.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from sensing_nodes.core.geometry.se2 import Pose2, wrap_angle
from sensing_nodes.core.timing import SampleOutcome, StampStep, classify_step

METHODS = ('exact_arc', 'euler')

# Variance of the base-frame lateral velocity: zero for a non-holonomic base, kept tiny but
# positive so that consumers which invert the twist covariance do not meet a singular matrix.
LATERAL_VELOCITY_VARIANCE = 1e-9


def unwrap_increments(delta_rad, max_step_rad):
    """Encoder angle increments (rad; a float or an array) with wrap jumps folded back.

    Folds by one turn (a wrapped reading cannot jump further) only where |delta| > max_step_rad
    and the folded value is within max_step_rad; elsewhere the increment is returned as it is.
    """
    if isinstance(delta_rad, float):
        delta, copysign, select = delta_rad, math.copysign, _select
    else:
        delta, copysign, select = np.asarray(delta_rad, dtype=float), np.copysign, np.where
    # A wrapping driver's reading jumps by exactly one turn: true step -+ 2 pi.
    wrapped = delta - copysign(2.0 * math.pi, delta)
    fold = (abs(delta) > max_step_rad) & (abs(wrapped) <= max_step_rad)
    return select(fold, wrapped, delta)


def _select(condition: bool, if_true: float, if_false: float) -> float:
    """np.where for one float."""
    return if_true if condition else if_false


def wheel_increments(
    positions_prev: ArrayLike,
    positions_now: ArrayLike,
    radii: ArrayLike,
    max_step_rad: ArrayLike = np.inf,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Distances (m) rolled by the left and right wheels between two (..., 2) angle readings (rad).

    radii: effective (2,) wheel radii (m), multipliers already applied. max_step_rad: largest
    plausible angle change per wheel (rad), used only to fold encoder wrap jumps.
    """
    delta = np.asarray(positions_now, dtype=float) - np.asarray(positions_prev, dtype=float)
    delta = unwrap_increments(delta, np.asarray(max_step_rad, dtype=float)[..., None])
    ds = delta * np.asarray(radii, dtype=float)
    return ds[..., 0], ds[..., 1]


def body_increments(ds_left, ds_right, wheel_separation_m: float):
    """Wheel distances (m; floats or arrays) -> base travel (dsR + dsL)/2 (m) and heading change
    (dsR - dsL)/L (rad)."""
    return 0.5 * (ds_right + ds_left), (ds_right - ds_left) * (1.0 / wheel_separation_m)


def _sincos(angle):
    if isinstance(angle, float):
        return math.sin(angle), math.cos(angle)
    return np.sin(angle), np.cos(angle)


def _arc_factors(half_turn):
    """sin(a)/a and its derivative, with their series near a = 0 (the straight-line limit)."""
    if isinstance(half_turn, float):
        if abs(half_turn) < 1e-4:
            a2 = half_turn * half_turn
            return 1.0 - a2 / 6.0, -half_turn / 3.0 + half_turn * a2 / 30.0
        s, c = math.sin(half_turn), math.cos(half_turn)
        return s / half_turn, (half_turn * c - s) / (half_turn * half_turn)
    a = np.asarray(half_turn, dtype=float)
    small = np.abs(a) < 1e-4
    safe = np.where(small, 1.0, a)
    a2 = a * a
    f = np.where(small, 1.0 - a2 / 6.0, np.sin(safe) / safe)
    df = np.where(small, -a / 3.0 + a * a2 / 30.0,
                  (safe * np.cos(safe) - np.sin(safe)) / (safe * safe))
    return f, df


def arc_displacement(yaw, ds, dtheta, method: str):
    """Odom-frame step (dx, dy) (m) and d(dx, dy)/d(ds, dtheta) for a step of ds (m) and dtheta
    (rad) starting at heading yaw (rad): along the arc, or straight ahead for 'euler'."""
    if method == 'exact_arc':
        # Exact arc: (dx, dy) = ds * sin(a)/a * (cos, sin)(yaw + a), a = dtheta/2; at a -> 0 this
        # is the midpoint straight-line form.
        half = 0.5 * dtheta
        f, df = _arc_factors(half)
        s, c = _sincos(yaw + half)
        dx, dy = ds * f * c, ds * f * s
        d_dtheta = (ds * (0.5 * df * c - 0.5 * f * s), ds * (0.5 * df * s + 0.5 * f * c))
        return dx, dy, (f * c, f * s), d_dtheta
    if method == 'euler':
        s, c = _sincos(yaw)
        return ds * c, ds * s, (c, s), (0.0 * c, 0.0 * s)
    raise ValueError(f"unknown integration method {method!r}; expected one of {METHODS}")


def step_columns(yaw, ds_left, ds_right, wheel_separation_m: float, method: str = 'exact_arc'):
    """One step from heading yaw (rad) over wheel distances ds_left, ds_right (m; floats or
    arrays): the odom-frame displacement (dx, dy) (m), the base travel ds (m) and heading change
    dtheta (rad), and the columns (x, y) of d(dx, dy)/d(ds_left) and d(dx, dy)/d(ds_right).
    d(dtheta)/d(ds_left, ds_right) is (-1/L, 1/L).

    The step's pose Jacobian is the shear I + u e3^T with u = (-dy, dx, 0), so with these
    columns G = [[gl_x, gr_x], [gl_y, gr_y], [-1/L, 1/L]] the covariance step is
    P' = F P F^T + G diag(var_l, var_r) G^T; the per-message (WheelOdometry) and the batch
    (integrate_path) propagation both build on this, and core.reference writes it as 3x3 products.
    """
    ds, dtheta = body_increments(ds_left, ds_right, wheel_separation_m)
    inv_l = 1.0 / wheel_separation_m
    dx, dy, (fx, fy), (gx, gy) = arc_displacement(yaw, ds, dtheta, method)
    return (dx, dy, ds, dtheta, (0.5 * fx - inv_l * gx, 0.5 * fy - inv_l * gy),
            (0.5 * fx + inv_l * gx, 0.5 * fy + inv_l * gy))


class Rejection(enum.Enum):
    """Why a JointState sample was not integrated (None when it was)."""
    MISSING_JOINT = 'missing_joint'
    LENGTH_MISMATCH = 'length_mismatch'
    NON_FINITE = 'non_finite'
    NO_DATA = 'no_position_or_velocity'
    REPEATED_STAMP = 'repeated_stamp'
    IMPLAUSIBLE = 'implausible_increment'


@dataclass
class WheelOdometryConfig:
    """Robot geometry and error model; lengths in m, angles in rad."""
    wheel_radius_m: float = 0.05
    wheel_separation_m: float = 0.30
    left_radius_multiplier: float = 1.0
    right_radius_multiplier: float = 1.0
    method: str = 'exact_arc'
    variance_per_m: tuple[float, float] = (4e-6, 4e-6)
    max_gap_s: float = 0.5
    max_wheel_speed_rad_s: float = 50.0
    radius_multiplier_std: float = 0.0

    def problems(self) -> list[tuple[str, str, object]]:
        """(field, problem, value) for every value the odometry cannot run with."""
        out: list[tuple[str, str, object]] = []
        for name in ('wheel_radius_m', 'wheel_separation_m', 'left_radius_multiplier',
                     'right_radius_multiplier', 'max_gap_s', 'max_wheel_speed_rad_s'):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                out.append((name, 'must be a finite number > 0', value))
        if self.method not in METHODS:
            out.append(('method', f'must be one of {list(METHODS)}', self.method))
        if any(not (math.isfinite(k) and k >= 0) for k in self.variance_per_m):
            out.append(('variance_per_m', 'must be finite and >= 0', self.variance_per_m))
        std = self.radius_multiplier_std
        if not (math.isfinite(std) and 0 <= std < 0.5):
            out.append(('radius_multiplier_std', 'must be in [0, 0.5)', std))
        return out

    @property
    def radii(self) -> tuple[float, float]:
        return (self.wheel_radius_m * self.left_radius_multiplier,
                self.wheel_radius_m * self.right_radius_multiplier)


def dead_reckoning_step(pose: Pose2, covariance: tuple[float, ...],
                        radius_jacobian: tuple[float, ...], ds_left: float, ds_right: float,
                        config: WheelOdometryConfig) -> tuple[Pose2, tuple[float, ...],
                                                                tuple[float, ...]]:
    """One dead-reckoning step over wheel distances ds_left, ds_right (m): the new pose (x, y,
    yaw in odom; m, rad), its covariance from the random wheel errors as (xx, xy, xt, yy, yt, tt)
    and its Jacobian w.r.t. the two relative radius errors as (x_l, x_r, y_l, y_r, yaw_l, yaw_r).

    P' = F P F^T + G diag(k|ds_l|, k|ds_r|) G^T and J' = F J + G diag(ds_l, ds_r) with the
    columns of step_columns (F = I + u e3^T, u = (-dy, dx, 0)), written out in plain floats:
    this runs once per JointState message, where 3x3 numpy products cost more than the
    arithmetic (core.reference writes the same step as matrix products; the tests compare)."""
    inv_l = 1.0 / config.wheel_separation_m
    x, y, yaw = pose
    dx, dy, _, dtheta, (lx, ly), (rx, ry) = step_columns(yaw, ds_left, ds_right,
                                                          config.wheel_separation_m, config.method)
    a, b = -dy, dx
    var_l = config.variance_per_m[0] * abs(ds_left)
    var_r = config.variance_per_m[1] * abs(ds_right)
    xx, xy, xt, yy, yt, tt = covariance
    covariance = (xx + 2.0 * a * xt + a * a * tt + var_l * lx * lx + var_r * rx * rx,
                  xy + a * yt + b * xt + a * b * tt + var_l * lx * ly + var_r * rx * ry,
                  xt + a * tt + inv_l * (var_r * rx - var_l * lx),
                  yy + 2.0 * b * yt + b * b * tt + var_l * ly * ly + var_r * ry * ry,
                  yt + b * tt + inv_l * (var_r * ry - var_l * ly),
                  tt + inv_l * inv_l * (var_l + var_r))
    if config.radius_multiplier_std > 0.0:
        jx0, jx1, jy0, jy1, jt0, jt1 = radius_jacobian
        radius_jacobian = (jx0 + a * jt0 + lx * ds_left, jx1 + a * jt1 + rx * ds_right,
                           jy0 + b * jt0 + ly * ds_left, jy1 + b * jt1 + ry * ds_right,
                           jt0 - inv_l * ds_left, jt1 + inv_l * ds_right)
    yaw2 = yaw + dtheta
    if yaw2 > math.pi or yaw2 <= -math.pi:
        yaw2 = float(wrap_angle(yaw2))
    return (x + dx, y + dy, yaw2), covariance, radius_jacobian


def covariance_matrix(covariance: tuple[float, ...], radius_jacobian: tuple[float, ...],
                      radius_multiplier_std: float) -> NDArray[np.float64]:
    """The 3x3 pose covariance (x/y/yaw) from dead_reckoning_step's random part and radius
    Jacobian: random + std^2 J J^T."""
    xx, xy, xt, yy, yt, tt = covariance
    out = np.array([[xx, xy, xt], [xy, yy, yt], [xt, yt, tt]])
    if radius_multiplier_std > 0.0:
        j = np.array(radius_jacobian).reshape(3, 2)
        out += radius_multiplier_std * radius_multiplier_std * (j @ j.T)
    return out


ZERO_COVARIANCE = (0.0,) * 6


def integrate_path(
    pose0: Pose2,
    ds_left: ArrayLike,
    ds_right: ArrayLike,
    wheel_separation_m: float,
    variance_per_m: tuple[float, float] = (0.0, 0.0),
    covariance0: ArrayLike | None = None,
    method: str = 'exact_arc',
    radius_multiplier_std: float = 0.0,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Dead reckoning over N steps of wheel distances (m): poses (N, 3) in odom and covariances
    (N, 3, 3) after each step, by dead_reckoning_step (the recursion WheelOdometry runs)."""
    ds_l = np.asarray(ds_left, dtype=float).ravel()
    ds_r = np.asarray(ds_right, dtype=float).ravel()
    if ds_l.shape != ds_r.shape:
        raise ValueError(f'ds_left and ds_right differ in length ({ds_l.size} vs {ds_r.size})')
    config = WheelOdometryConfig(wheel_separation_m=wheel_separation_m, method=method,
                                 variance_per_m=tuple(variance_per_m),
                                 radius_multiplier_std=radius_multiplier_std)
    c0 = np.zeros((3, 3)) if covariance0 is None else np.asarray(covariance0, dtype=float)
    pose = (float(pose0[0]), float(pose0[1]), float(pose0[2]))
    cov = (c0[0, 0], c0[0, 1], c0[0, 2], c0[1, 1], c0[1, 2], c0[2, 2])
    cov = tuple(float(v) for v in cov)
    jac = ZERO_COVARIANCE
    poses, covs = np.empty((ds_l.size, 3)), np.empty((ds_l.size, 3, 3))
    for k, (left, right) in enumerate(zip(ds_l.tolist(), ds_r.tolist())):
        pose, cov, jac = dead_reckoning_step(pose, cov, jac, left, right, config)
        poses[k] = pose
        covs[k] = covariance_matrix(cov, jac, radius_multiplier_std)
    return poses, covs


@dataclass
class OdometryUpdate(SampleOutcome):
    """Outcome of one JointState sample (rejection: a Rejection); wrapped: an encoder wrap was
    folded back."""
    wrapped: bool = False


class _NotIntegrated(Exception):
    """A sample that integrates nothing; `outcome` says why (a rejection or a restart)."""

    def __init__(self, outcome: OdometryUpdate) -> None:
        super().__init__(outcome.note)
        self.outcome = outcome


def _wheel_pair(names, values, il: int, ir: int, kind: str) -> tuple[float, float]:
    """(left, right) floats of one JointState field; _NotIntegrated for a malformed one."""
    if len(values) != len(names):
        raise _NotIntegrated(OdometryUpdate(False, rejection=Rejection.LENGTH_MISMATCH,
                                            note=f'{len(names)} names but {len(values)} {kind}'))
    pair = (float(values[il]), float(values[ir]))
    if not (math.isfinite(pair[0]) and math.isfinite(pair[1])):
        raise _NotIntegrated(OdometryUpdate(False, rejection=Rejection.NON_FINITE,
                                            note=f'wheel {kind} {pair}'))
    return pair


@dataclass
class WheelOdometry:
    """Dead reckoning over JointState samples, one at a time, with every bad-input rule.

    A rejected sample leaves the state untouched: positions are absolute, so the next good sample
    integrates the whole increment from the last accepted reading and no distance is lost.
    """
    config: WheelOdometryConfig
    pose: Pose2 = (0.0, 0.0, 0.0)
    twist: tuple[float, float, float] = (0.0, 0.0, 0.0)
    twist_covariance: NDArray[np.float64] = field(default_factory=lambda: np.zeros((3, 3)))
    stamp_ns: int | None = None
    # dead_reckoning_step's state: the random part of the pose covariance and the radius Jacobian
    _random: tuple[float, ...] = ZERO_COVARIANCE
    _radius: tuple[float, ...] = ZERO_COVARIANCE
    _positions: tuple[float, float] | None = None
    _velocities: tuple[float, float] | None = None

    @property
    def covariance(self) -> NDArray[np.float64]:
        """Pose covariance (3x3, x/y/yaw in odom): random wheel errors plus radius errors."""
        return covariance_matrix(self._random, self._radius, self.config.radius_multiplier_std)

    def reset(self, pose: Pose2 = (0.0, 0.0, 0.0), covariance: ArrayLike | None = None) -> None:
        """Put the robot at pose with `covariance` (3x3, default zero: exactly known); keep the
        encoder reference."""
        self.pose = (float(pose[0]), float(pose[1]), float(wrap_angle(pose[2])))
        c = np.zeros((3, 3)) if covariance is None else np.asarray(covariance, dtype=float)
        self._random = tuple(float(v) for v in c[np.triu_indices(3)])
        self._radius = ZERO_COVARIANCE
        self.twist = (0.0, 0.0, 0.0)
        self.twist_covariance = np.zeros((3, 3))

    def _restart(self, stamp_ns: int, positions, velocities) -> None:
        self.stamp_ns = stamp_ns
        self._positions = positions
        self._velocities = velocities

    def update(
        self,
        stamp_ns: int,
        names: Sequence[str],
        positions: Sequence[float],
        velocities: Sequence[float],
        joints: tuple[str, str],
    ) -> OdometryUpdate:
        """Take one JointState sample (stamp ns, names, positions rad, velocities rad/s)."""
        try:
            return self._update(stamp_ns, names, positions, velocities, joints)
        except _NotIntegrated as skipped:
            return skipped.outcome

    def _update(self, stamp_ns, names, positions, velocities, joints) -> OdometryUpdate:
        pos, vel = self._read(names, positions, velocities, joints)
        step = classify_step(self.stamp_ns, stamp_ns, self.config.max_gap_s)
        if step is StampStep.REPEATED:
            return OdometryUpdate(False, step, Rejection.REPEATED_STAMP,
                                  note=f'duplicate stamp {stamp_ns} ns; waiting for the next one')
        if step is StampStep.FIRST:
            self._restart(stamp_ns, pos, vel)
            return OdometryUpdate(True, step)
        if step is StampStep.BACKWARDS:
            note = (f'time went backwards by {(self.stamp_ns - stamp_ns) / 1e9:.3f} s '
                    '(looping bag?): pose reset to the origin')
            self.reset()
            self._restart(stamp_ns, pos, vel)
            return OdometryUpdate(True, step, note=note)

        dt = (stamp_ns - self.stamp_ns) * 1e-9
        ds_l, ds_r, wrapped = self._wheel_distances(stamp_ns, step, dt, pos, vel)
        if step is StampStep.GAP:
            self._inflate_for_gap(ds_l, ds_r)
            note = (
                f'{dt:.3f} s gap (> max_gap_s {self.config.max_gap_s}): not integrated across; '
                f'wheels rolled {ds_l:.3f} / {ds_r:.3f} m, pose covariance widened'
            )
            self.twist = (0.0, 0.0, 0.0)
            self._restart(stamp_ns, pos, vel)
            return OdometryUpdate(True, step, note=note, wrapped=wrapped)

        self._integrate(ds_l, ds_r, dt)
        self._restart(stamp_ns, pos, vel)
        return OdometryUpdate(True, step, wrapped=wrapped,
                              note='encoder position wrapped; unwrapped' if wrapped else '')

    def _read(self, names, positions, velocities, joints):
        """(positions, None) or (None, velocities) of the [left, right] wheels; _NotIntegrated
        for a sample that cannot be used."""
        try:
            il, ir = names.index(joints[0]), names.index(joints[1])
        except ValueError:
            missing = [j for j in joints if j not in names]
            raise _NotIntegrated(OdometryUpdate(
                False, rejection=Rejection.MISSING_JOINT,
                note=f'wheel joint(s) {missing} not in {list(names)}')) from None
        if len(positions):
            return _wheel_pair(names, positions, il, ir, 'positions'), None
        if not len(velocities):
            raise _NotIntegrated(OdometryUpdate(False, rejection=Rejection.NO_DATA,
                                                note='no positions and no velocities'))
        vel = _wheel_pair(names, velocities, il, ir, 'velocities')
        if max(abs(vel[0]), abs(vel[1])) > self.config.max_wheel_speed_rad_s:
            raise _NotIntegrated(OdometryUpdate(False, rejection=Rejection.IMPLAUSIBLE, note=(
                f'wheel velocities {vel} rad/s beyond max_wheel_speed_rad_s '
                f'{self.config.max_wheel_speed_rad_s}')))
        return None, vel

    def _wheel_distances(self, stamp_ns: int, step: StampStep, dt: float, pos, vel
                         ) -> tuple[float, float, bool]:
        """(ds_left, ds_right, wrapped): the distances (m) the wheels rolled since the last
        sample; _NotIntegrated when there is nothing to integrate (restarted)."""
        radii = self.config.radii
        if pos is not None and self._positions is not None:
            max_step = self.config.max_wheel_speed_rad_s * dt
            dphi, wrapped = [], False
            for now, prev in zip(pos, self._positions):
                d = now - prev
                if abs(d) > max_step and step is StampStep.OK:
                    folded = unwrap_increments(d, max_step)
                    if abs(folded) > max_step:
                        self._restart(stamp_ns, pos, vel)
                        raise _NotIntegrated(OdometryUpdate(
                            False, step, Rejection.IMPLAUSIBLE, note=(
                                f'wheel angle jumped {d:.3f} rad in {dt:.4f} s (max '
                                f'{max_step:.3f} rad); restarted from this reading')))
                    d, wrapped = folded, True
                dphi.append(d)
            return dphi[0] * radii[0], dphi[1] * radii[1], wrapped
        if vel is not None and self._velocities is not None:
            # Velocity-only drivers: trapezoidal rule over the interval.
            return (0.5 * (vel[0] + self._velocities[0]) * dt * radii[0],
                    0.5 * (vel[1] + self._velocities[1]) * dt * radii[1], False)
        if vel is not None:
            return vel[0] * dt * radii[0], vel[1] * dt * radii[1], False
        # Positions appear after velocity-only samples: anchor on them.
        self._restart(stamp_ns, pos, vel)
        raise _NotIntegrated(OdometryUpdate(True, step,
                                            note='positions appeared; anchored on them'))

    def _integrate(self, ds_l: float, ds_r: float, dt: float) -> None:
        """One step of the pose and its covariance (dead_reckoning_step), and the twist over
        the interval with its covariance from the same wheel variances."""
        cfg = self.config
        self.pose, self._random, self._radius = dead_reckoning_step(
            self.pose, self._random, self._radius, ds_l, ds_r, cfg)
        inv_l = 1.0 / cfg.wheel_separation_m
        ds, dtheta = body_increments(ds_l, ds_r, cfg.wheel_separation_m)
        self.twist = (ds / dt, 0.0, dtheta / dt)
        var_l = cfg.variance_per_m[0] * abs(ds_l)
        var_r = cfg.variance_per_m[1] * abs(ds_r)
        inv_dt2 = 1.0 / (dt * dt)
        var_v = 0.25 * (var_l + var_r) * inv_dt2
        var_w = inv_l * inv_l * (var_l + var_r) * inv_dt2
        cov_vw = 0.5 * inv_l * (var_r - var_l) * inv_dt2
        self.twist_covariance = np.array([
            [var_v, 0.0, cov_vw], [0.0, LATERAL_VELOCITY_VARIANCE, 0.0], [cov_vw, 0.0, var_w]])

    def _inflate_for_gap(self, ds_l: float, ds_r: float) -> None:
        # The path across a gap is unknown, but its length bounds the displacement and the wheel
        # difference bounds the turn; add both as variance rather than pretend to know the pose.
        path = 0.5 * (abs(ds_l) + abs(ds_r))
        turn = (abs(ds_l) + abs(ds_r)) / self.config.wheel_separation_m
        xx, xy, xt, yy, yt, tt = self._random
        self._random = (xx + path * path, xy, xt, yy + path * path, yt, tt + turn * turn)
