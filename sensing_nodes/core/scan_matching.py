"""Scan-matching odometry without ROS: each scan registered against a local map of the recent
surroundings (LocalMapScanMatcher, icp_matcher's default) or against one keyframe
(KeyframeScanMatcher, the lesson's method); motion prediction, deskewing, fallback on a failed
match, physical limits and re-acquisition.

Poses are base_link in the odometry frame (x, y, yaw; m, rad). The laser is mounted at
`laser_pose` in base_link; scans are (N, 2) points in the laser frame, each point optionally
with its beam's time after the stamp (s) for deskewing.
"""

from __future__ import annotations

import math
from bisect import bisect_left, insort
from collections import deque
from dataclasses import dataclass, field, replace
from enum import StrEnum

import numpy as np
from numpy.typing import NDArray

from sensing_nodes.core import icp
from sensing_nodes.core.correlative import correlative_search
from sensing_nodes.core.deskew import deskew, twist_motion
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
from sensing_nodes.core.local_map import LocalMap, LocalMapSettings
from sensing_nodes.core.timing import StampStep, classify_step

ZERO: Pose2 = (0.0, 0.0, 0.0)


# A scan stamped closer than this to the previous one (a driver's duplicate with a nudged stamp)
# says nothing about velocity: a match residual divided by a tiny dt would make the
# constant-velocity prediction run away, so the previous twist is kept.
MIN_VELOCITY_INTERVAL_S = 1e-3


MODES = ('local_map', 'keyframe')


@dataclass(frozen=True)
class ScanMatcherSettings:
    """Mode, laser mount, keyframe or local-map policy, acceptance gates, physical limits and
    fallback noise (m, rad, s)."""

    mode: str = 'local_map'                       # local_map | keyframe (make_scan_matcher)
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
    # --- local_map mode (LocalMapScanMatcher) ---
    local_map: LocalMapSettings = LocalMapSettings()
    # Physical limits, relative to the odometry's prediction: the published step deviates from
    # the odometry's motion by at most these x the time since the previous scan (without
    # odometry, the step itself is held to them), so a match beyond them is not believed at
    # once while a sharp turn the odometry reports and the scans confirm passes.
    max_speed_m_s: float = 2.0
    max_yaw_rate_rad_s: float = 3.0
    # False where the stamps' time is assumed (rebuilt from a log's line order): a rate
    # measures nothing there, so the limits above are off.
    rate_limits: bool = True
    # The map anchor (what /scan_match/keyframe_odom is relative to) is renewed after this far.
    anchor_distance_m: float = 5.0
    # A match whose mean alignment error exceeds this many times the median of the last
    # model_error_window matches' (at least icp_options.min_residual_std) is rejected (the
    # scale-free form of max_error_m: a long-range laser in a hall aligns to 3 cm where a short
    # one in a room aligns to 6 mm).
    max_error_ratio: float = 3.0
    # Directions whose eigenvalue (yaw as arc length at the scan's radius) is below this x the
    # largest are degenerate: not updated from the prediction, their variance inflated, the
    # match still used. In a featureless corridor the map's normal noise alone leaves up to
    # 0.025 along it (simulated corridor world, 2 seeds), a room 0.2 and more; solved down to
    # 1e-3 (the keyframe mode's ratio), the match stuck to the map and lagged the truth by
    # 0.36-1.3 m over 30 m.
    map_degeneracy_ratio: float = 0.03
    # Correspondence gate: 3 x the RMS model error (prediction vs match) of the last
    # model_error_window matches, within [min_gate_m, icp max_correspondence_distance].
    min_gate_m: float = 0.1
    model_error_window: int = 100
    # A matched scan is inserted into the map once the robot moved or turned this much since
    # the last insertion (the keyframe spacing; 0, 0: every matched scan).
    insert_distance_m: float = 0.10
    insert_angle_rad: float = math.radians(10.0)
    # While matches fail the map stays where the last match left it: once the predicted pose is
    # further than this many times the scan's median range from the last matched pose, the map
    # holds little of what the scans see, and it restarts from the scan at the predicted pose,
    # in the same frame (0: never). Outdoors (freiburg-campus, 1.75 km) matches failed in a row
    # for hundreds of metres without it: 1574 of 2007 fell back to the odometry.
    map_restart_reach: float = 0.5
    # Without odometry, a failed match leaves the velocity decaying with this time constant.
    velocity_decay_s: float = 0.5
    # When a match fails and this many have failed in a row (this one included), the scan is
    # searched for over a wide window around the prediction (core/correlative.py), then matched
    # from what that finds: a bad prediction (the odometry off by tens of degrees, a long gap)
    # is caught at its first scan.
    reacquire_after: int = 1
    reacquire_window_m: float = 1.0
    reacquire_window_rad: float = math.pi
    # A match not to join the map: re-acquired, or further from its prediction than this many
    # x the recent RMS model error (0: no such test); this many doubted in a row join it. The
    # model error is heavy-tailed (straights against turns, the yaw as an arc at the scan's
    # reach): at 4 the simulated outdoor world's seed 1 kept right matches out of its young
    # map and slid 0.25 m; at 8 the 8 outdoor seeds pool to 0.035 m RMS (0.065 m without
    # the test, 0.10 m at 4).
    doubt_deviations: float = 8.0
    doubt_streak: int = 3
    # A match keeps part of its prediction's error (the correspondences are chosen from the
    # guess; in weakly constrained directions it stays near it), which its residuals do not
    # show: its covariance is the registration's plus (this x the recent RMS deviation between
    # prediction and match)² in x and y, over the scan's median range² in yaw. 0.05 puts the
    # matcher's claimed sigma at 0.7-1.4x its own error on five of the seven CARMEN logs
    # (docs/real-data.md) and halves the simulated strong_errors route's overconfidence.
    prediction_error_share: float = 0.05

    def problems(self) -> list[tuple[str, str, object]]:
        """(field, problem, value) for each setting the matcher cannot run with (its ICP
        options' and local map's as 'icp_options.method', 'local_map.cell_m', ...)."""
        out: list[tuple[str, str, object]] = []
        if self.mode not in MODES:
            out.append(('mode', f'must be one of {MODES}', self.mode))
        if self.search not in icp.SEARCHES:
            out.append(('search', f'must be one of {icp.SEARCHES}', self.search))
        if not all(math.isfinite(v) for v in self.laser_pose):
            out.append(('laser_pose', 'must be finite', self.laser_pose))
        if not self.max_gap_s > 0.0:
            out.append(('max_gap_s', 'must be > 0', self.max_gap_s))
        for name in ('doubt_deviations', 'prediction_error_share'):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0.0):
                out.append((name, 'must be finite and >= 0', value))
        if not self.doubt_streak >= 1:
            out.append(('doubt_streak', 'must be >= 1', self.doubt_streak))
        for part in ('icp_options', 'local_map'):
            out += [(f'{part}.{name}', problem, value)
                    for name, problem, value in getattr(self, part).problems()]
        return out


class ScanStatus(StrEnum):
    """What became of a scan (counted on /diagnostics under its value)."""

    FIRST = 'first'                       # the first scan: starts the keyframe or the map
    MATCHED = 'matched'
    FALLBACK = 'fallback'                 # the match failed: the prediction carried the pose
    REPEATED = 'repeated'                 # same stamp as the previous scan: nothing published
    RESET_BACKWARDS = 'reset_backwards'   # the stamp went backwards: restarted at the origin
    GAP = 'gap'                           # keyframe mode: too long since the previous scan


class ScanEvent(StrEnum):
    """What else happened during a scan, each counted on /diagnostics under its value."""

    DESKEWED_BY_ODOMETRY = 'deskewed_by_odometry'
    DESKEWED_BY_VELOCITY = 'deskewed_by_velocity'
    GAP = 'gap'                           # local_map: the velocity restarted, the map stayed
    LIMITED = 'limited'                   # the published step was held to the physical limits
    PREDICTION_LIMITED = 'prediction_limited'   # ... the constant-velocity prediction was
    REACQUIRE_ATTEMPTS = 'reacquire_attempts'
    REACQUIRED = 'reacquired'
    DEGENERATE = 'degenerate'
    MAP_PRUNED = 'map_pruned'
    MAP_RESTARTED = 'map_restarted'
    NOT_INSERTED = 'not_inserted'         # a doubted match kept out of the map


class Prediction(StrEnum):
    """Where a scan's predicted motion came from."""

    ODOMETRY = 'odometry'
    CONSTANT_VELOCITY = 'constant_velocity'


@dataclass(frozen=True)
class KeyframeMatch:
    """A match's own measurement: base_link at the scan relative to base_link at the keyframe's
    stamp (keyframe mode: the keyframe; local_map mode: the map's anchor), m and rad, with the
    match's covariance. Successive matches against one keyframe share that keyframe's error; a
    consumer that keeps its state at keyframe stamps (stochastic cloning) counts it once."""

    keyframe_stamp_ns: int
    pose: Pose2
    covariance: NDArray[np.float64]


@dataclass(frozen=True)
class MapPose:
    """local_map mode: where a scan is in its local map, what /scan_match/keyframe_odom carries
    for the fusion. The map's frame is the odom frame the map is built in, whose origin is
    base_link at the map's first scan (map_stamp_ns, which names the map). A match is base_link
    in the map at the middle of the sweep (time_ns: the stamp plus half the sweep; the stamp
    without beam times), where the registration is made, with the registration's own covariance
    (map x, y, yaw): at the stamp the pose carries half a sweep of the prediction's error besides
    (the odometry's motion over the sweep; on the simulated route that half sweep was half the
    heading error's variance, and on strong_errors a 0.1 deg bias). The scan that starts a map
    (`origin`) is stamped at its stamp, base_link there being the map's origin exactly."""

    map_stamp_ns: int
    time_ns: int
    origin: bool = False
    pose: Pose2 | None = None                     # None: not matched (origin, fallback)
    covariance: NDArray[np.float64] | None = None
    doubt: str = ''       # why a match was kept out of the map ('' when it joined or no match)


@dataclass
class ScanStep:
    """Outcome of one scan: pose of base_link (odom frame) with covariance, twist (vx, vy, wz)
    in base_link over the last interval, and what happened (`status`, `reason`, `events`); the
    match against its keyframe or the map's anchor (`keyframe`, None when nothing was matched)
    and, in local_map mode, the scan in the map (`local_map`, None in keyframe mode)."""

    stamp_ns: int
    pose: Pose2
    covariance: NDArray[np.float64]
    twist: tuple[float, float, float]
    status: ScanStatus
    reason: str = ''
    # keyframe mode: this scan is the keyframe of the next matches; local_map: the map's
    # anchor was renewed here.
    new_keyframe: bool = False
    prediction: Prediction | None = None
    result: icp.MatchResult | None = None
    twist_covariance: NDArray[np.float64] = field(default_factory=lambda: np.zeros((3, 3)))
    events: tuple[ScanEvent, ...] = ()
    keyframe: KeyframeMatch | None = None
    local_map: MapPose | None = None

    @property
    def publish(self) -> bool:
        """False only for a repeated stamp, which produces no new estimate."""
        return self.status != ScanStatus.REPEATED


def with_prediction_error(result: icp.MatchResult, model_error_rms: float, share: float,
                          reach_m: float) -> icp.MatchResult:
    """The match with the share of its prediction's error it keeps in its covariance: plus
    (share x the recent RMS deviation between prediction and match, m)² in x and y, and that
    over the scan's median range reach_m (at least 1 m), squared, in yaw
    (ScanMatcherSettings.prediction_error_share)."""
    if share <= 0.0 or not model_error_rms > 0.0:
        return result
    variance = (share * model_error_rms) ** 2
    reach = max(reach_m, 1.0)
    return replace(result, covariance=result.covariance
                   + np.diag([variance, variance, variance / reach ** 2]))


def prediction_deviation(predicted: Pose2, matched: Pose2, reach_m: float) -> float:
    """How far a match lies from its prediction (m): the translation plus the arc a yaw
    difference moves a correspondence at the scan's median range."""
    deviation = between(predicted, matched)
    return math.hypot(deviation[0], deviation[1]) + 2.0 * reach_m * abs(
        math.sin(0.5 * deviation[2]))


def scan_reach(points: NDArray[np.float64]) -> float:
    """The scan's median range (m): how far a yaw error moves a typical correspondence."""
    if points.shape[0] == 0:
        return 0.0
    squared = np.einsum('ij,ij->i', points, points)
    middle = squared.size // 2
    return math.sqrt(float(np.partition(squared, middle)[middle]))


def mount_transform(relative_base: Pose2, laser_pose: Pose2) -> Pose2:
    """Motion of base_link (in the earlier base frame) -> the same motion seen by the laser."""
    return compose(compose(inverse(laser_pose), relative_base), laser_pose)


def predicted_step(odometry_motion: Pose2 | None, twist: Pose2,
                   dt_s: float) -> tuple[Pose2, Prediction]:
    """base_link's predicted motion since the previous scan (its base frame; m, rad) and where
    it came from: the odometry's when it is given and finite, else the constant-velocity
    model's (the matcher's own twist over dt_s)."""
    if odometry_motion is not None and all(math.isfinite(v) for v in odometry_motion):
        return odometry_motion, Prediction.ODOMETRY
    return (twist[0] * dt_s, twist[1] * dt_s, twist[2] * dt_s), Prediction.CONSTANT_VELOCITY


def limit_step(step: Pose2, reference: Pose2, dt_s: float, max_speed_m_s: float,
               max_yaw_rate_rad_s: float) -> tuple[Pose2, bool]:
    """A motion (base frame, m, rad) over dt_s whose deviation from `reference` (the odometry's
    motion over the same interval, same frame; ZERO: the step itself) is held to the physical
    limits: the translation's difference scaled down to at most max_speed x dt, the rotation's
    clipped to max_yaw_rate x dt; and whether it had to be."""
    dx, dy = step[0] - reference[0], step[1] - reference[1]
    dyaw = wrap_angle(step[2] - reference[2])
    distance = math.hypot(dx, dy)
    reach, turn = max_speed_m_s * dt_s, max_yaw_rate_rad_s * dt_s
    if distance <= reach and abs(dyaw) <= turn:
        return step, False
    scale = reach / distance if distance > reach else 1.0
    yaw = max(-turn, min(turn, dyaw))
    return (reference[0] + dx * scale, reference[1] + dy * scale,
            wrap_angle(reference[2] + yaw)), True


def deskewed_by_odometry(points: NDArray[np.float64], beam_times_s: NDArray[np.float64] | None,
                         sweep_motion: Pose2 | None, laser_pose: Pose2) -> NDArray[np.float64]:
    """Points moved to the laser's pose at the stamp at the constant twist of the odometry's
    motion over the sweep (sweep_motion: base_link's motion from the stamp to the last beam's
    time); unchanged without beam times or odometry. A constant twist from the odometry's end
    points rather than the odometry at each beam: its wobble within a sweep (wheel slip) is
    noise the scan would keep."""
    if beam_times_s is None or sweep_motion is None or points.shape[0] == 0:
        return points
    duration = float(beam_times_s.max())
    if duration <= 0.0:
        return points
    twist = (sweep_motion[0] / duration, sweep_motion[1] / duration, sweep_motion[2] / duration)
    return deskew(points, twist, beam_times_s, laser_pose)


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
        self.model_errors = RecentValues(self.settings.model_error_window)

    def _set_keyframe(self, points: NDArray[np.float64], stamp_ns: int) -> None:
        self.keyframe = icp.prepare_target(points, search=self.settings.search)
        self.keyframe_stamp_ns = stamp_ns
        self.keyframe_pose = self.pose
        self.keyframe_covariance = self.covariance.copy()

    def process(self, stamp_ns: int, points: NDArray[np.float64],
                predicted_motion: Pose2 | None = None,
                beam_times_s: NDArray[np.float64] | None = None,
                sweep_motion: Pose2 | None = None) -> ScanStep:
        """One scan: points (N, 2) in the laser frame at stamp_ns; predicted_motion is base_link's
        motion since the previous scan (in the previous base frame), or None for the
        constant-velocity model; beam_times_s (N,) when each point was taken (s after the
        stamp) and sweep_motion, base_link's motion from the stamp to the last beam's time (from
        odometry; None: local_map mode deskews by its own velocity, keyframe mode not at all),
        deskew the scan."""
        s = self.settings
        # Only the odometry's motion deskews here: the matcher's own twist, deskewing to the
        # stamp, feeds back into the next twist (core/scan_matching.LocalMapScanMatcher._sweep).
        points = deskewed_by_odometry(points, beam_times_s, sweep_motion, s.laser_pose)
        step = classify_step(self.stamp_ns, stamp_ns, s.max_gap_s)
        if step is StampStep.REPEATED:
            return ScanStep(stamp_ns, self.pose, self.covariance, self.twist,
                            ScanStatus.REPEATED, 'same stamp as the previous scan: skipped')
        if step in (StampStep.FIRST, StampStep.BACKWARDS):
            status = ScanStatus.FIRST if step is StampStep.FIRST else ScanStatus.RESET_BACKWARDS
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
            return ScanStep(stamp_ns, self.pose, self.covariance, self.twist, ScanStatus.GAP,
                            f'{gap_s:.2f} s since the previous scan: keyframe restarted here',
                            new_keyframe=True)

        return self._match(stamp_ns, points, predicted_motion)

    def _match(self, stamp_ns: int, points: NDArray[np.float64],
               predicted_motion: Pose2 | None) -> ScanStep:
        """process() for a scan that follows the previous one within max_gap_s."""
        s = self.settings
        dt = (stamp_ns - self.stamp_ns) * 1e-9
        predicted_motion, source = predicted_step(predicted_motion, self.twist, dt)
        predicted = compose(self.pose, predicted_motion)
        guess_base = between(self.keyframe_pose, predicted)
        guess_laser = mount_transform(guess_base, s.laser_pose)
        result = icp.match(points, self.keyframe, guess_laser, options=s.icp_options)
        points_usable = result.source_points >= s.icp_options.correspondences.min_points
        reach = scan_reach(points)
        if result.converged:
            result = with_prediction_error(
                result, self.model_errors.rms if self.model_errors else 0.0,
                s.prediction_error_share, reach)

        reason = self._rejection(result, guess_laser)
        previous = self.pose
        match = None
        if reason:
            fallback_cov = np.diag([s.fallback_std_m ** 2, s.fallback_std_m ** 2,
                                    s.fallback_std_rad ** 2])
            self.pose, self.covariance = compose_with_covariance(
                self.pose, self.covariance, predicted_motion, fallback_cov)
            status = ScanStatus.FALLBACK
            # Restart the keyframe here (the old one did not fit), unless this scan is too
            # sparse to match against: then the old keyframe stays, at its own pose.
            new_keyframe = points_usable
            motion_cov = fallback_cov
        else:
            self.model_errors.add(prediction_deviation(guess_laser, result.pose, reach))
            relative, rel_cov = unmount_transform(result.pose, result.covariance, s.laser_pose)
            self.pose, self.covariance = compose_with_covariance(
                self.keyframe_pose, self.keyframe_covariance, relative, rel_cov)
            status = ScanStatus.MATCHED
            match = KeyframeMatch(self.keyframe_stamp_ns, relative, rel_cov)
            motion_cov = rel_cov      # the keyframe's own uncertainty is common to both poses
            new_keyframe = (math.hypot(relative[0], relative[1]) > s.keyframe_distance_m
                            or abs(relative[2]) > s.keyframe_angle_rad)
        if new_keyframe:
            self._set_keyframe(points, stamp_ns)
        motion = between(previous, self.pose)
        if dt >= MIN_VELOCITY_INTERVAL_S:
            self.twist = (motion[0] / dt, motion[1] / dt, motion[2] / dt)
        self.stamp_ns = stamp_ns
        return ScanStep(stamp_ns, self.pose, self.covariance.copy(), self.twist, status, reason,
                        new_keyframe=new_keyframe, prediction=source, result=result,
                        twist_covariance=motion_cov / (dt * dt), keyframe=match)

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


class RecentValues:
    """The last `window` values added, with their RMS and median kept as they arrive."""

    def __init__(self, window: int) -> None:
        self.values: deque[float] = deque(maxlen=window)
        self._sorted: list[float] = []
        self._square_sum = 0.0

    def add(self, value: float) -> None:
        if len(self.values) == self.values.maxlen:
            old = self.values[0]
            del self._sorted[bisect_left(self._sorted, old)]
            self._square_sum -= old * old
        self.values.append(value)
        insort(self._sorted, value)
        self._square_sum += value * value

    def __len__(self) -> int:
        return len(self.values)

    @property
    def rms(self) -> float:
        return math.sqrt(max(self._square_sum, 0.0) / len(self.values))

    @property
    def median(self) -> float:
        n = len(self._sorted)
        return 0.5 * (self._sorted[(n - 1) // 2] + self._sorted[n // 2])


class LocalMapScanMatcher:
    """Registers each (deskewed) scan against a local map of the recent surroundings in the
    odom frame (core/local_map.py) from the predicted pose, with a correspondence gate adapted
    to the recent model error; inserts each matched scan into the map. A failed match takes the
    odometry's motion, or without odometry a decaying velocity; after repeated failures a wide
    search re-acquires the pose in the map. The published pose never deviates from the
    odometry's motion (without odometry: never steps) beyond the physical limits, unless they
    are off (rate_limits). Matches are also given relative to a long-lived map anchor
    (ScanStep.keyframe)."""

    def __init__(self, settings: ScanMatcherSettings | None = None) -> None:
        self.settings = settings or ScanMatcherSettings()
        self.map = LocalMap(self.settings.local_map)
        self.reset()

    def reset(self) -> None:
        """Forget everything, the map too: the next scan starts again at the origin."""
        self.pose: Pose2 = ZERO                 # published (continuous) pose
        self.covariance = np.zeros((3, 3))
        self.map_pose: Pose2 = ZERO             # the pose in the map (== pose unless limited)
        self.mid_pose: Pose2 = ZERO             # ... at the middle of the last scan's sweep
        self.twist = (0.0, 0.0, 0.0)
        self.stamp_ns: int | None = None
        self.map.clear()
        self.anchor_pose: Pose2 = ZERO
        self.anchor_covariance = np.zeros((3, 3))
        self.anchor_stamp_ns: int | None = None
        self.map_stamp_ns: int | None = None    # the map's first scan (it names the map)
        self.model_errors = RecentValues(self.settings.model_error_window)
        self.alignment_errors = RecentValues(self.settings.model_error_window)
        self.sweep_errors = RecentValues(self.settings.model_error_window)
        self.sweep_yaw_errors = RecentValues(self.settings.model_error_window)
        self.far_ranges = RecentValues(self.settings.model_error_window)
        self.failures = 0
        self.doubts = 0                         # doubted matches in a row (not in the map)
        self._inserted_at: Pose2 | None = None
        self._matched_at: Pose2 | None = None
        self._options: dict[float, icp.IcpOptions] = {}

    @property
    def gate_m(self) -> float:
        """The correspondence gate (m): 3 x the RMS model error of the recent matches, within
        [min_gate_m, max_correspondence_distance]; the largest before any match."""
        s = self.settings
        widest = s.icp_options.correspondences.max_correspondence_distance
        if not self.model_errors:
            return widest
        return min(widest, max(s.min_gate_m, 3.0 * self.model_errors.rms))

    def process(self, stamp_ns: int, points: NDArray[np.float64],
                predicted_motion: Pose2 | None = None,
                beam_times_s: NDArray[np.float64] | None = None,
                sweep_motion: Pose2 | None = None) -> ScanStep:
        """One scan, as KeyframeScanMatcher.process."""
        s = self.settings
        step = classify_step(self.stamp_ns, stamp_ns, s.max_gap_s)
        if step is StampStep.REPEATED:
            return ScanStep(stamp_ns, self.pose, self.covariance, self.twist,
                            ScanStatus.REPEATED, 'same stamp as the previous scan: skipped')
        events: list[ScanEvent] = []
        if step in (StampStep.FIRST, StampStep.BACKWARDS):
            self.reset()
            points, half, how, _ = self._sweep(points, beam_times_s, sweep_motion)
            self.stamp_ns = stamp_ns
            self.mid_pose = self._matched_at = half
            self._insert(points, compose(half, s.laser_pose))
            self.anchor_stamp_ns = self.map_stamp_ns = stamp_ns
            status = ScanStatus.FIRST if step is StampStep.FIRST else ScanStatus.RESET_BACKWARDS
            reason = '' if step is StampStep.FIRST else \
                'stamp went backwards: map cleared, restarted at origin'
            return ScanStep(stamp_ns, self.pose, self.covariance, self.twist, status, reason,
                            new_keyframe=True, events=(how,) if how else (),
                            local_map=MapPose(stamp_ns, stamp_ns, origin=True))
        if step is StampStep.GAP:
            # The map stays (it is in the odom frame); the velocity across the gap is unknown.
            self.twist = (0.0, 0.0, 0.0)
            events.append(ScanEvent.GAP)
        return self._register(stamp_ns, points, predicted_motion, beam_times_s, sweep_motion,
                              events)

    def _sweep(self, points: NDArray[np.float64], beam_times_s: NDArray[np.float64] | None,
               sweep_motion: Pose2 | None
               ) -> tuple[NDArray[np.float64], Pose2, ScanEvent | None, float]:
        """A swept scan deskewed to the middle of its sweep, base_link's motion from the stamp
        to that middle, how (by the odometry's motion over the sweep or the matcher's own
        twist) and the middle's time after the stamp (s); unchanged, no motion, None and 0
        when the beams carry no times.

        The middle, not the stamp: a constant-twist error then shears the scan symmetrically
        and barely moves its registration, so the twist the registrations give is not fed back
        into them (deskewed to the first beam, a twist error moved the next registration by it
        times half the sweep, which made the next twist's error as large and of opposite sign:
        without odometry the simulated route ran away to 1.4 m)."""
        if beam_times_s is None or points.shape[0] == 0 or not np.any(beam_times_s):
            return points, ZERO, None, 0.0
        duration = float(beam_times_s.max())
        twist, how = self.twist, ScanEvent.DESKEWED_BY_VELOCITY
        if sweep_motion is not None:
            twist = (sweep_motion[0] / duration, sweep_motion[1] / duration,
                     sweep_motion[2] / duration)
            how = ScanEvent.DESKEWED_BY_ODOMETRY
        middle = 0.5 * duration
        moved = deskew(points, twist, beam_times_s - middle, self.settings.laser_pose)
        return moved, twist_motion(twist, middle), how, middle

    # long: one scan's whole decision (predict, deskew, register, accept or fall back,
    # re-acquire, limit, insert, anchor), kept in one place so its order is visible.
    def _register(self, stamp_ns: int, points: NDArray[np.float64],
                  predicted_motion: Pose2 | None, beam_times_s: NDArray[np.float64] | None,
                  sweep_motion: Pose2 | None, events: list[ScanEvent]) -> ScanStep:
        """process() for a scan after the first. The scan is registered at the middle of its
        sweep (mid_pose); the published pose is base_link's at the stamp."""
        s = self.settings
        dt = (stamp_ns - self.stamp_ns) * 1e-9
        predicted_motion, source = predicted_step(predicted_motion, self.twist, dt)
        # The odometry's motion is a measurement, the reference the limits are relative to; the
        # matcher's own extrapolation (constant velocity) is held to them.
        if s.rate_limits and source is Prediction.CONSTANT_VELOCITY:
            predicted_motion, limited = limit_step(predicted_motion, ZERO, dt, s.max_speed_m_s,
                                                   s.max_yaw_rate_rad_s)
            if limited:
                events.append(ScanEvent.PREDICTION_LIMITED)
        points, half, how, middle_s = self._sweep(points, beam_times_s, sweep_motion)
        if how:
            events.append(how)
        predicted = compose(self.map_pose, predicted_motion)
        predicted_mid = compose(predicted, half)
        guess = compose(predicted_mid, s.laser_pose)
        # After failed matches the pose was carried by a prediction alone: a match from there
        # can settle in a false minimum that a narrow gate cannot tell (0.5 m along a wall in
        # the default room after 2.5 s without odometry), so the wide search goes first.
        lost = self.failures >= s.reacquire_after
        result, reason = self._match(points, guess) if not lost else (None, 'lost')
        if reason and self.failures + 1 >= s.reacquire_after and len(self.map):
            events.append(ScanEvent.REACQUIRE_ATTEMPTS)
            found = correlative_search(points, self.map.target(), guess,
                                       s.reacquire_window_m, s.reacquire_window_rad)
            if found is not None:
                second, second_reason = self._match(points, found, gate=s.min_gate_m,
                                                    check_jump=False)
                if not second_reason or result is None:
                    result, reason = second, second_reason
                if not reason:
                    events.append(ScanEvent.REACQUIRED)
        if result is None:             # lost, and the wide search found nothing
            result, reason = self._match(points, guess)
        previous_mid, previous_pose = self.mid_pose, self.pose
        match = map_pose = map_cov = None
        new_anchor = False
        doubt = ''
        if reason:
            self.failures += 1
            fallback_cov = np.diag([s.fallback_std_m ** 2, s.fallback_std_m ** 2,
                                    s.fallback_std_rad ** 2])
            self.map_pose, self.mid_pose = predicted, predicted_mid
            target_pose = compose(self.pose, predicted_motion)
            status = ScanStatus.FALLBACK
            motion_cov = fallback_cov
            _, self.covariance = compose_with_covariance(self.pose, self.covariance,
                                                         predicted_motion, fallback_cov)
            if s.map_restart_reach and self._matched_at is not None \
                    and points.shape[0] >= s.icp_options.correspondences.min_points \
                    and math.hypot(
                    predicted_mid[0] - self._matched_at[0], predicted_mid[1]
                    - self._matched_at[1]) > s.map_restart_reach * scan_reach(points):
                self._restart_map(points, predicted_mid, events)
        else:
            self.failures = 0
            mid, mid_cov = remove_offset(result.pose, result.covariance, s.laser_pose)
            map_pose, map_cov = mid, mid_cov
            base, base_cov = remove_offset(mid, mid_cov, half)
            self.alignment_errors.add(result.error)
            doubt = self._doubt(predicted_mid, mid, points, events)
            if ScanEvent.REACQUIRED not in events:
                self.model_errors.add(prediction_deviation(predicted_mid, mid,
                                                           scan_reach(points)))
            self.map_pose, self.mid_pose = base, mid
            self._matched_at = mid
            target_pose = base
            status = ScanStatus.MATCHED
            if result.degenerate:
                events.append(ScanEvent.DEGENERATE)
            _, j_base = compose_jacobians(inverse(self.anchor_pose), base)
            relative = between(self.anchor_pose, base)
            if how and ScanEvent.REACQUIRED not in events:
                deviation = between(predicted_mid, mid)
                self.sweep_errors.add(math.hypot(deviation[0], deviation[1]))
                self.sweep_yaw_errors.add(abs(deviation[2]))
            if how and len(self.sweep_errors):
                # The sweep's motion comes from the prediction's source, whose error over a
                # scan interval the matches measure: half a sweep of it is in the pose at the
                # stamp (and in the scan's shape), which the registration's residuals do not see.
                share = 0.5 * float(beam_times_s.max()) / max(dt, 1e-9)
                base_cov = base_cov + np.diag([(share * self.sweep_errors.rms) ** 2] * 2
                                              + [(share * self.sweep_yaw_errors.rms) ** 2])
            rel_cov = j_base @ base_cov @ j_base.T
            rel_cov = 0.5 * (rel_cov + rel_cov.T)
            match = KeyframeMatch(self.anchor_stamp_ns, relative, rel_cov)
            _, self.covariance = compose_with_covariance(self.anchor_pose,
                                                         self.anchor_covariance, relative, rel_cov)
            motion_cov = 2.0 * rel_cov
            if doubt:
                events.append(ScanEvent.NOT_INSERTED)
            else:
                self._maybe_insert(points, mid, events)
            new_anchor = math.hypot(base[0] - self.anchor_pose[0],
                                    base[1] - self.anchor_pose[1]) > s.anchor_distance_m
        # The published pose moves towards the map pose, never further from the odometry's
        # motion (without odometry: never further) than the limits.
        step = between(previous_pose, target_pose)
        if s.rate_limits:
            step, limited = limit_step(step, predicted_motion if source is Prediction.ODOMETRY
                                       else ZERO,
                                       dt, s.max_speed_m_s, s.max_yaw_rate_rad_s)
            if limited:
                events.append(ScanEvent.LIMITED)
        self.pose = compose(previous_pose, step)
        if new_anchor:
            self.anchor_pose, self.anchor_covariance = self.map_pose, self.covariance.copy()
            self.anchor_stamp_ns = stamp_ns
        if dt >= MIN_VELOCITY_INTERVAL_S:
            if status is ScanStatus.MATCHED and ScanEvent.REACQUIRED not in events:
                # From the registered middles of the sweeps, not the stamps: those carry the
                # twist itself (half a sweep of it), which would feed back.
                motion = between(previous_mid, self.mid_pose)
                self.twist = (motion[0] / dt, motion[1] / dt, motion[2] / dt)
            elif status is ScanStatus.MATCHED or source is Prediction.CONSTANT_VELOCITY:
                # Re-acquired (the jump is no velocity) or lost without odometry: decaying.
                decay = math.exp(-dt / s.velocity_decay_s) \
                    if status is not ScanStatus.MATCHED else 0.0
                self.twist = tuple(v * decay for v in self.twist)
            else:
                self.twist = (predicted_motion[0] / dt, predicted_motion[1] / dt,
                              predicted_motion[2] / dt)
        self.stamp_ns = stamp_ns
        return ScanStep(stamp_ns, self.pose, self.covariance.copy(), self.twist, status, reason,
                        new_keyframe=new_anchor, prediction=source, result=result,
                        twist_covariance=motion_cov / (dt * dt), events=tuple(events),
                        keyframe=match, local_map=MapPose(
                            self.map_stamp_ns, stamp_ns + round(middle_s * 1e9),
                            pose=map_pose, covariance=map_cov, doubt=doubt))

    def _match(self, points: NDArray[np.float64], guess: Pose2, gate: float | None = None,
               check_jump: bool = True) -> tuple[icp.MatchResult, str]:
        """ICP of the scan (laser frame) against the map from the laser pose guess (odom), and
        why it must not be used ('' when it is fine)."""
        s = self.settings
        gate = self.gate_m if gate is None else gate
        options = self._options.get(gate)
        if options is None:
            options = replace(
                s.icp_options, degeneracy_ratio=s.map_degeneracy_ratio,
                correspondences=replace(s.icp_options.correspondences,
                                        max_correspondence_distance=gate))
            self._options = {gate: options}            # the gate changes slowly: keep one
        result = icp.match(points, self.map.target(), guess, options=options)
        if not result.converged:
            return result, f'not converged: {result.reason}'
        result = with_prediction_error(
            result, self.model_errors.rms if self.model_errors else 0.0,
            s.prediction_error_share, scan_reach(points))
        if self.alignment_errors:
            # Never below the ICP's own floor on residuals: noiseless scans align to ~0.
            typical = max(self.alignment_errors.median, s.icp_options.min_residual_std)
            if not result.error <= s.max_error_ratio * typical:
                return result, (f'mean alignment error {result.error:.3f} m > '
                                f'{s.max_error_ratio:g} x the recent median {typical:.3f} m')
        elif not math.isfinite(result.error):
            return result, 'mean alignment error is not finite'
        if check_jump:
            jump = between(guess, result.pose)
            if math.hypot(jump[0], jump[1]) > s.max_jump_m or abs(jump[2]) > s.max_jump_rad:
                return result, (f'match {math.hypot(jump[0], jump[1]):.2f} m / '
                                f'{math.degrees(abs(jump[2])):.1f} deg from the prediction')
        return result, ''

    def _doubt(self, predicted: Pose2, matched: Pose2, points: NDArray[np.float64],
               events: list[ScanEvent]) -> str:
        """Why a match should not join the map ('' when it may): a re-acquired match, or one
        further from its prediction than doubt_deviations x the recent RMS model error, waits
        until the next match agrees with it (doubt_streak doubted matches in a row join: the
        prediction, not the matches, was wrong). A wrong match in the map would be the
        reference of the next ones."""
        s = self.settings
        reason = ''
        if ScanEvent.REACQUIRED in events:
            reason = 're-acquired'
        elif self.model_errors and s.doubt_deviations > 0.0:
            deviation = prediction_deviation(predicted, matched, scan_reach(points))
            limit = max(s.doubt_deviations * self.model_errors.rms, s.min_gate_m)
            if deviation > limit:
                reason = f'{deviation:.3f} m from its prediction (> {limit:.3f} m)'
        self.doubts = self.doubts + 1 if reason else 0
        if reason and self.doubts >= s.doubt_streak:
            self.doubts = 0
            return ''
        return reason

    def _maybe_insert(self, points: NDArray[np.float64], base: Pose2,
                      events: list[ScanEvent]) -> None:
        """Insert a matched scan (laser frame) seen from base (odom; at the middle of the
        sweep) when the robot moved or turned enough since the last insertion, and prune the
        map around the robot."""
        s = self.settings
        laser = compose(base, s.laser_pose)
        if self._inserted_at is not None and (s.insert_distance_m or s.insert_angle_rad):
            moved = between(self._inserted_at, base)
            if math.hypot(moved[0], moved[1]) < s.insert_distance_m \
                    and abs(moved[2]) < s.insert_angle_rad:
                return
        self._insert(points, laser)
        self._inserted_at = base
        if self.map.prune((base[0], base[1]), self.map_radius_m):
            events.append(ScanEvent.MAP_PRUNED)

    def _restart_map(self, points: NDArray[np.float64], base: Pose2,
                     events: list[ScanEvent]) -> None:
        """Forget the map and start it again from this scan (laser frame) seen from base (odom;
        the middle of the sweep), in the same frame: matching resumes from the next scan."""
        self.map.clear()
        self._inserted_at = None
        self._matched_at = base
        self._insert(points, compose(base, self.settings.laser_pose))
        self.failures = 0
        events.append(ScanEvent.MAP_RESTARTED)

    @property
    def map_radius_m(self) -> float:
        """How far from the robot the map keeps its cells (m): radius_m, or radius_per_range x
        the median of the inserted scans' 90th-percentile ranges where that is further."""
        m = self.settings.local_map
        if not (m.radius_per_range and self.far_ranges):
            return m.radius_m
        return max(m.radius_m, m.radius_per_range * self.far_ranges.median)

    def _insert(self, points: NDArray[np.float64], laser: Pose2) -> None:
        """Add points (laser frame) seen from the laser pose (odom) to the map, each with its
        normal in this scan, and note how far the scan reaches."""
        if points.shape[0] == 0:
            return
        squared = np.einsum('ij,ij->i', points, points)
        far = int(0.9 * (squared.size - 1))
        self.far_ranges.add(math.sqrt(float(np.partition(squared, far)[far])))
        normals, planarity = icp.scan_normals(points)
        c, s_ = math.cos(laser[2]), math.sin(laser[2])
        rotation = np.array([[c, s_], [-s_, c]])             # row vectors: p @ Rᵀ
        moved = points @ rotation
        moved += laser[:2]
        self.map.insert(moved, normals @ rotation, planarity)
        if self._inserted_at is None:
            self._inserted_at = compose(laser, inverse(self.settings.laser_pose))


def remove_offset(pose: Pose2, cov: NDArray[np.float64],
                  offset: Pose2) -> tuple[Pose2, NDArray[np.float64]]:
    """pose ∘ offset⁻¹ and its covariance (over x, y, yaw in the parent frame), the offset
    exact: the laser's pose in odom -> base_link's (offset: the mount), or base_link's pose at
    the middle of a sweep -> at its stamp (offset: the motion to the middle)."""
    offset_inverse = inverse(offset)
    j_pose, _ = compose_jacobians(pose, offset_inverse)
    out = j_pose @ cov @ j_pose.T
    return compose(pose, offset_inverse), 0.5 * (out + out.T)


def make_scan_matcher(settings: ScanMatcherSettings) -> LocalMapScanMatcher | KeyframeScanMatcher:
    """The matcher of settings.mode: each scan against a local map, or against one keyframe."""
    if settings.mode == 'local_map':
        return LocalMapScanMatcher(settings)
    if settings.mode == 'keyframe':
        return KeyframeScanMatcher(settings)
    raise ValueError(f'mode must be one of {MODES}, got {settings.mode!r}')


def odometry_guidance(odometry: OdometryBuffer, previous_ns: int | None, stamp_ns: int,
                      beam_times_s: NDArray[np.float64] | None
                      ) -> tuple[Pose2 | None, Pose2 | None]:
    """What the odometry tells a matcher about a scan stamped stamp_ns: base_link's motion
    since the previous scan (None when there is none or the odometry does not reach), and its
    motion over the sweep, from the stamp to the last beam's time (None without beam times or
    odometry there)."""
    predicted = None
    if previous_ns is not None and stamp_ns > previous_ns:
        predicted = odometry.motion_between(previous_ns, stamp_ns)
    sweep = None
    if beam_times_s is not None and beam_times_s.size and beam_times_s.max() > 0.0:
        sweep = odometry.motion_between(stamp_ns,
                                        stamp_ns + int(round(float(beam_times_s.max()) * 1e9)))
    return predicted, sweep


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
