"""The inputs a bag holds, what the nodes are told about them, and the checks of each
(core/diagnosis does the numbers; this gathers them into one Diagnosis)."""

from __future__ import annotations

import argparse
import math
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from sensing_nodes.bags.sensor_streams import SensorBagError
from sensing_nodes.bags.survey import ImuStream, JointStream, OdomStream, Survey
from sensing_nodes.core.config.gyro_integrator import GYRO_INTEGRATOR_PARAMETERS
from sensing_nodes.core.config.icp_matcher import ICP_MATCHER_PARAMETERS
from sensing_nodes.core.config.wheel_odometry import WHEEL_ODOMETRY_PARAMETERS
from sensing_nodes.core.diagnosis import covariance as cov_checks
from sensing_nodes.core.diagnosis import cross, timing, wheels
from sensing_nodes.core.diagnosis import imu as imu_checks
from sensing_nodes.core.diagnosis import laser as laser_checks
from sensing_nodes.core.diagnosis import tf as tf_checks
from sensing_nodes.core.diagnosis.check import OK, PROBLEM, SKIPPED, WARNING, Check, graded
from sensing_nodes.core.evaluation import calibration as cal
from sensing_nodes.core.geometry import se2
from sensing_nodes.core.geometry.imu_mount import mount_rotation, mount_rpy, quaternion_matrix
from sensing_nodes.core.geometry.quaternion import to_rpy
from sensing_nodes.core.gyro import integrate_rate
from sensing_nodes.core.scan_matching import KeyframeScanMatcher, ScanMatcherSettings
from sensing_nodes.core.wheel_odometry import integrate_path
from sensing_nodes.parameters import ParameterError, load_parameters
from sensing_nodes.paths import config_file
from sensing_nodes.topics import FUSED, GROUND_TRUTH, IMU, IMU_RAW, JOINT_STATES, SCAN

PROG = 'sensing_doctor'
EXIT_OK, EXIT_PROBLEMS, EXIT_BAD_INPUT = 0, 1, 2
# Outputs of this package's nodes: in a bag they are results, not the robot's inputs.
PACKAGE_OUTPUTS = ('/wheel/odom', '/scan_match/odom', '/scan_match/keyframe_odom', FUSED, IMU)
IMU_PREFERRED = (IMU_RAW, '/imu', '/imu/data')


@dataclass
class Declared:
    """What the nodes are told: wheel geometry and laser mount, joints, the IMU mount and
    where each came from."""

    geometry: cal.Geometry
    geometry_from: str
    left_joint: str
    right_joint: str
    imu_mount: np.ndarray
    imu_mount_from: str
    parameters: dict[str, dict[str, Any]]


@dataclass
class Diagnosis:
    """Everything found in one bag: inputs, checks, estimates, plots."""

    survey: Survey
    args: argparse.Namespace
    base_frame: str = 'base_link'
    joints: JointStream | None = None
    wheel_columns: tuple[int, int] = (0, 1)
    scan: Any = None
    imu: ImuStream | None = None
    odoms: list[OdomStream] = field(default_factory=list)
    candidates: dict[str, list[str]] = field(default_factory=dict)
    declared: Declared | None = None
    checks: list[Check] = field(default_factory=list)
    calibration: cal.CalibrationResult | None = None
    geometry: cal.Geometry | None = None          # found (calibrated) or declared
    scan_track: tuple[np.ndarray, np.ndarray] | None = None   # (t, poses) of scan matching
    scan_track_status: dict[str, int] = field(default_factory=dict)
    mount: imu_checks.MountEstimate | None = None
    gyro_bias: float | None = None            # rad/s while still; None: never still
    gyro_noise_density: float | None = None
    offsets: dict[str, float] = field(default_factory=dict)   # track -> s vs the reference
    noise: dict[str, float] = field(default_factory=dict)
    tracks: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)  # yaw
    pose_tracks: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    fused: dict[str, Any] = field(default_factory=dict)
    plots: dict[str, str] = field(default_factory=dict)       # title -> base64 PNG
    preset: dict[str, Any] = field(default_factory=dict)
    remaps: dict[str, str] = field(default_factory=dict)
    nodes: tuple[str, ...] = ()
    timings: dict[str, float] = field(default_factory=dict)
    imu_still: Any = None
    offset_reference: str = ''
    scan_variance: Any = None                 # (S, 3) each match's variance (x, y, yaw)
    preset_text: str = ''
    imu_tilt_deg: float | None = None         # largest base tilt the IMU's orientation shows
    orientation_usable: bool = False          # the IMU's own orientation can be fused
    imu_rate_z: tuple[np.ndarray, np.ndarray] | None = None   # gyro about base_link's z
    orientation_yaw: tuple[np.ndarray, np.ndarray] | None = None   # its yaw in base_link
    wheel_yaw_scale: float = 1.0              # the preset's separation over the found one
    odom_yaw_distrusted: set[str] = field(default_factory=set)   # Odometry topics
    distrust: dict[str, str] = field(default_factory=dict)   # input -> why the fusion doubts it
    laser_on_tf_static: bool = False

    def add(self, checks: Check | list[Check]) -> None:
        self.checks.extend([checks] if isinstance(checks, Check) else checks)


# --- inputs ---------------------------------------------------------------------------------

def _choose(d: Diagnosis, kind: str, streams: dict, wanted: str | None,
            preferred: tuple[str, ...] = ()) -> Any:
    """The stream of a kind to check: the one asked for, a preferred name, else the busiest."""
    names = [t for t in streams if t not in PACKAGE_OUTPUTS or t == wanted] or list(streams)
    d.candidates[kind] = sorted(streams)
    if wanted:
        if wanted not in streams:
            raise SensorBagError(f'{d.survey.path}: no {kind} topic {wanted} (candidates: '
                                 f'{", ".join(sorted(streams)) or "none"})')
        return streams[wanted]
    for name in preferred:
        if name in names:
            return streams[name]
    return max((streams[t] for t in names), key=lambda s: len(s.t), default=None)


def find_inputs(d: Diagnosis) -> None:
    """The inputs by type, the base frame, and a check listing them."""
    s, a = d.survey, d.args
    d.joints = _choose(d, 'joints', s.joints, a.joint_topic, (JOINT_STATES,))
    d.scan = _choose(d, 'scan', s.scans, a.scan_topic, (SCAN,))
    d.imu = _choose(d, 'imu', s.imus, a.imu_topic, IMU_PREFERRED)
    odoms = {t: o for t, o in s.odoms.items() if t != GROUND_TRUTH}
    d.candidates['odom'] = sorted(odoms)
    if a.odom_topic:
        if a.odom_topic not in odoms:
            raise SensorBagError(f'{s.path}: no Odometry topic {a.odom_topic}')
        d.odoms = [odoms[a.odom_topic]]
    else:
        d.odoms = [o for t, o in sorted(odoms.items()) if t not in PACKAGE_OUTPUTS] or \
            list(odoms.values())
    if not (d.joints or d.scan or d.imu or d.odoms):
        raise SensorBagError(f'{s.path} holds no input the doctor can check (JointState, '
                             'LaserScan, Imu or Odometry); topics: ' + '; '.join(
                                 f'{t} ({ty}, {n})' for t, (ty, n) in sorted(s.topics.items())))
    children = [o.child_frame_id for o in d.odoms if o.child_frame_id]
    parents = [tr.parent for tr in s.transforms if tr.static]
    d.base_frame = (children[0] if children else parents[0] if parents else 'base_link')
    found = {'joints': d.joints.topic if d.joints else None,
             'scan': d.scan.topic if d.scan else None, 'imu': d.imu.topic if d.imu else None,
             'odometry': [o.topic for o in d.odoms]}
    several = {k: v for k, v in d.candidates.items() if len(v) > 1}
    missing = [k for k in ('joints', 'scan', 'imu') if found[k] is None]
    listed = '; '.join(f'{kind} {", ".join(v) if isinstance(v, list) else v}'
                       for kind, v in found.items() if v)
    advice = (f'inputs: {listed}; base frame {d.base_frame}'
              + ('; several candidates: ' + '; '.join(f'{k} {", ".join(v)}' for k, v in
                                                     several.items())
                 + f' (choose with --{"/".join(several)}-topic)'
                 if several else '')
              + (f'; absent: {", ".join(missing)} (their checks are skipped)' if missing else ''))
    d.add(Check('inputs', 'bag', WARNING if several else OK, None, '', advice, '',
                {'found': found, 'candidates': d.candidates, 'base_frame': d.base_frame,
                 'duration_s': s.duration_s, 'notes': s.notes[:100]}))


def read_declared(d: Diagnosis) -> None:
    """The nodes' parameters (config/ defaults, then each --params-file) and /tf_static."""
    try:
        params = {node: load_parameters(node, config_file(f'{node}.yaml'), *d.args.params_file)
                  for node in ('wheel_odometry', 'icp_matcher', 'gyro_integrator')}
        wheel = WHEEL_ODOMETRY_PARAMETERS.config(params['wheel_odometry'])
        icp = ICP_MATCHER_PARAMETERS.config(params['icp_matcher'])
        gyro = GYRO_INTEGRATOR_PARAMETERS.config(params['gyro_integrator'])
    except ParameterError as exc:
        raise SensorBagError(f'cannot use the parameters: {exc}') from None
    origin = ', '.join(str(f) for f in d.args.params_file) or 'the package\'s config/'
    laser = list(icp.matcher.laser_pose)
    laser_from = origin
    static = _static_transform(d, d.scan.frame_id if d.scan is not None else '')
    if static is not None:
        laser = [static[0][0], static[0][1], to_rpy(static[1])[2]]
        laser_from = '/tf_static'
        d.laser_on_tf_static = True
    odometry = wheel.odometry
    geometry = cal.Geometry(*odometry.radii, odometry.wheel_separation_m, *laser)
    mount = mount_rotation(*gyro.mount_rpy)
    mount_from = origin
    imu_frame = d.imu.frame_id.lstrip('/') if d.imu is not None else ''
    static = _static_transform(d, imu_frame)
    if static is not None:
        mount, mount_from = quaternion_matrix(static[1]), '/tf_static'
    elif imu_frame == d.base_frame:
        mount, mount_from = np.eye(3), f'the IMU\'s frame is {d.base_frame}'
    d.declared = Declared(geometry, f'{origin}; laser from {laser_from}',
                          wheel.left_wheel_joint, wheel.right_wheel_joint, mount, mount_from,
                          params)


def _static_transform(d: Diagnosis, child: str):
    """(translation, rotation) of base frame -> child on /tf_static, else None."""
    for tr in d.survey.transforms:
        if tr.static and tr.child == child.lstrip('/') and tr.parent == d.base_frame:
            return tr.translation, tr.rotation
    return None


def wheel_columns(d: Diagnosis) -> None:
    """Columns of the left and right wheel: the declared names, else the one 'left' and one
    'right' among the joint names."""
    names = d.joints.names
    left, right = d.args.left_joint or d.declared.left_joint, \
        d.args.right_joint or d.declared.right_joint
    if left in names and right in names:
        d.wheel_columns = (names.index(left), names.index(right))
        return
    lefts = [i for i, n in enumerate(names) if 'left' in n.lower()]
    rights = [i for i, n in enumerate(names) if 'right' in n.lower()]
    if len(lefts) == 1 and len(rights) == 1:
        d.wheel_columns = (lefts[0], rights[0])
        return
    d.add(Check('wheel_joints', 'wheels', PROBLEM, None, '',
                f'cannot tell the wheels among the joints {", ".join(names)}: give '
                '--left-joint/--right-joint'))
    d.joints = None


# --- checks ---------------------------------------------------------------------------------

def timing_section(d: Diagnosis) -> None:
    """Every input topic's stamps (the kinds the nodes take, and every Odometry)."""
    wanted = {s.topic for s in (d.joints, d.scan, d.imu) if s is not None}
    wanted |= {o.topic for o in d.odoms}
    for topic in sorted(wanted):
        times = d.survey.times[topic]
        d.add(timing.stream_checks(topic, times.kind, times.header_ns, times.record_ns,
                                   times.has_header))


def sorted_unique(t: np.ndarray, *columns: np.ndarray) -> tuple[np.ndarray, ...]:
    """Stamps sorted with repeats dropped, and the columns in the same order."""
    order = np.argsort(t, kind='stable')
    t = t[order]
    keep = np.concatenate(([True], np.diff(t) > 0))
    return (t[keep],) + tuple(c[order][keep] for c in columns)


def refusal_section(d: Diagnosis) -> None:
    """What the package's tools refuse: non-finite encoder and IMU values."""
    for name, stream, values in (
            ('joints', d.joints, None if d.joints is None else d.joints.position),
            ('imu', d.imu, None if d.imu is None else np.hstack((d.imu.gyro, d.imu.accel)))):
        if stream is None:
            continue
        bad = int((~np.isfinite(values).all(axis=1)).sum())
        d.add(Check('finite_values', stream.topic, PROBLEM if bad else OK, float(bad),
                    'messages', f'{bad} messages hold NaN or inf: sensing_calibrate refuses the '
                    'bag and the nodes drop them (counted on /diagnostics); fix the driver'
                    if bad else 'every value finite', '0'))
        if bad:
            keep = np.isfinite(values).all(axis=1)
            if name == 'joints':
                d.joints = JointStream(stream.topic, stream.names, stream.t[keep],
                                       stream.position[keep])
            else:
                s = stream
                d.imu = ImuStream(s.topic, s.frame_id, s.t[keep], s.gyro[keep], s.accel[keep],
                                  s.orientation[keep], s.orientation_cov[keep],
                                  s.gyro_cov[keep], s.accel_cov[keep])
    if d.survey.notes:      # messages the survey left out: a node or tool would skip them too
        d.add(Check('left_out', 'bag', WARNING, float(len(d.survey.notes)), 'messages',
                    f'{len(d.survey.notes)} messages left out: '
                    + '; '.join(d.survey.notes[:3]) + ('; ...' if len(d.survey.notes) > 3 else ''),
                    '0', {'notes': d.survey.notes[:100]}))
    if d.scan is not None:
        d.add(laser_checks.range_checks(d.scan.topic, d.scan.ranges, d.scan.range_min,
                                        d.scan.range_max))


def _joint_arrays(d: Diagnosis) -> tuple[np.ndarray, np.ndarray]:
    """Encoder stamps (sorted, unique) and [left, right] wheel angles."""
    t, pos = sorted_unique(d.joints.t, d.joints.position[:, list(d.wheel_columns)])
    return t, pos


def _scan_points(d: Diagnosis) -> tuple[np.ndarray, list[np.ndarray], list | None]:
    """Scan stamps (sorted, unique), each scan's points (laser frame) and, for a sweeping
    scanner (time_increment set), when each point was taken (s after the stamp)."""
    from sensing_nodes.core.geometry.scan import scan_to_points

    t, idx = sorted_unique(d.scan.t, np.arange(d.scan.t.size))
    converted = [scan_to_points(d.scan.ranges[i], d.scan.angles, d.scan.range_min,
                                d.scan.range_max) for i in idx]
    times = None if d.scan.beam_times(np.zeros(1, np.intp)) is None else \
        [d.scan.beam_times(beams) for _, beams in converted]
    return t, [points for points, _ in converted], times


def wheel_section(d: Diagnosis) -> None:
    """Calibration against scan matching (twice when the declared geometry is far off, so the
    matcher starts from a good guess), then the geometry, resolution and odometry checks."""
    d.geometry = d.declared.geometry
    if d.joints is None:
        return
    joint_t, joints = _joint_arrays(d)
    if d.scan is not None and np.ptp(joints, axis=0).max() > 1e-6:
        scan_t, points, beam_times = _scan_points(d)
        nominal = _gyro_scaled_geometry(d, joint_t, joints)
        try:
            for _ in range(2):
                intervals = cal.make_intervals(joint_t, joints, scan_t, points, nominal,
                                               beam_times=beam_times)
                result = cal.calibrate(intervals, nominal)
                found = result.geometry()
                if abs(found.wheel_separation_m / nominal.wheel_separation_m - 1) < 0.03 and \
                        abs(found.left_radius_m / nominal.left_radius_m - 1) < 0.03:
                    break
                nominal = found
            d.calibration, d.geometry = result, result.geometry()
            d.add(wheels.geometry_checks(result, d.declared.geometry, d.declared.geometry_from))
        except cal.CalibrationError as exc:
            d.add(Check('wheel_radius', 'wheels', SKIPPED, None, '%',
                        f'not calibrated: {exc}'))
    d.add(wheels.encoder_resolution_check(joints, d.geometry.left_radius_m))
    for odom in d.odoms:
        t, yaw = sorted_unique(odom.t, odom.pose[:, 2])
        d.add(wheels.encoders_vs_odometry(odom.topic, joint_t, joints, t, yaw))


def _gyro_scaled_geometry(d: Diagnosis, joint_t: np.ndarray, joints: np.ndarray
                          ) -> cal.Geometry:
    """The declared geometry as the calibration's starting guess, its separation scaled to
    turn as the gyro does where the wheels turn more than twice (or less than half) as much
    (a skid-steer base, a track width far off): scan matching guided by such wheels fails."""
    g = d.declared.geometry
    if d.imu is None:
        return g
    t, gyro = sorted_unique(d.imu.t, d.imu.gyro)
    mid, _, w, _ = wheels.wheel_rates(joint_t, joints, g)
    fit = imu_checks.rate_axis(t, gyro, mid, w)
    if fit is None or 0.5 <= fit[1] <= 2.0:
        return g
    return replace(g, wheel_separation_m=g.wheel_separation_m / fit[1])


def wheel_track(d: Diagnosis, geometry: cal.Geometry | None = None
                ) -> tuple[np.ndarray, np.ndarray] | None:
    """Dead reckoning from the encoders with the geometry found (or the one given): (stamps,
    poses (J, 3))."""
    if d.joints is None:
        return None
    t, joints = _joint_arrays(d)
    g = geometry or d.geometry
    steps = np.diff(joints, axis=0)
    poses, _ = integrate_path((0.0, 0.0, 0.0), steps[:, 0] * g.left_radius_m,
                              steps[:, 1] * g.right_radius_m, g.wheel_separation_m)
    return t, np.vstack(([0.0, 0.0, 0.0], poses))


def pose_at(t: np.ndarray, poses: np.ndarray, query: np.ndarray) -> np.ndarray:
    from sensing_nodes.core.evaluation.metrics import interpolate_poses

    return interpolate_poses(t, poses, query)


def scan_gap_s(d: Diagnosis) -> float:
    """The gap between scans the matcher bridges: icp_matcher's 1 s, or for a sparse log (a
    keyframe log: a scan a metre) 1.5 times its longest gap."""
    longest = float(np.diff(np.sort(d.scan.t)).max()) * 1e-9 if d.scan.t.size > 1 else 0.0
    return 1.0 if longest <= 1.0 else round(min(1.5 * longest, 300.0), 1)


def scan_section(d: Diagnosis) -> None:
    """Scan matching over every scan (icp_matcher's keyframe matcher, the motion predicted
    from the wheels or the odometry): the external reference of the other checks."""
    if d.scan is None:
        return
    scan_t, points, beam_times = _scan_points(d)
    g = d.geometry
    matcher = KeyframeScanMatcher(ScanMatcherSettings(
        laser_pose=(g.laser_x_m, g.laser_y_m, g.laser_yaw_rad), max_gap_s=scan_gap_s(d)))
    guide = d.pose_tracks.get('wheels') or next(
        (d.pose_tracks[o.topic] for o in d.odoms if o.topic in d.pose_tracks), None)
    guess = pose_at(*guide, scan_t) if guide is not None else None
    # A sweeping scanner: each scan deskewed to its stamp by the guide's motion over the sweep.
    sweep_ns = 0 if beam_times is None else round(max(
        (float(b.max()) for b in beam_times if b.size), default=0.0) * 1e9)
    sweep_end = pose_at(*guide, scan_t + sweep_ns) if guide is not None and sweep_ns else None
    poses, variances, status = [], [], {}
    for i, (stamp, pts) in enumerate(zip(scan_t, points)):
        motion = sweep = None
        if guess is not None and i and np.isfinite(guess[i]).all() and \
                np.isfinite(guess[i - 1]).all():
            motion = se2.between(tuple(guess[i - 1]), tuple(guess[i]))
        if sweep_end is not None and np.isfinite(guess[i]).all() and \
                np.isfinite(sweep_end[i]).all():
            sweep = se2.between(tuple(guess[i]), tuple(sweep_end[i]))
        step = matcher.process(int(stamp), pts, motion,
                               beam_times[i] if beam_times is not None else None, sweep)
        status[step.status] = status.get(step.status, 0) + 1
        poses.append(step.pose)
        # The match's own variance against its keyframe (NaN where nothing was matched).
        variances.append(np.diag(step.keyframe.covariance) if step.keyframe is not None
                         else np.full(3, np.nan))
    d.scan_track = (scan_t, np.array(poses, dtype=float))
    d.scan_variance = np.array(variances)
    d.pose_tracks['scan matching'] = d.scan_track
    d.scan_track_status = status
    d.tracks['scan matching'] = (scan_t, np.unwrap(np.array(poses)[:, 2]))
    matched = status.get('matched', 0) / max(len(points) - 1, 1)
    shown = ', '.join(f'{n} {k}' for k, n in sorted(status.items()))
    d.add(Check('scan_matching', d.scan.topic, OK if matched >= 0.8 else WARNING,
                100.0 * matched, '% matched',
                f'{100 * matched:.0f} % of scans matched their keyframe ({shown}): the '
                'reference for the time offsets, noise and covariance checks' if matched >= 0.8
                else f'only {100 * matched:.0f} % of scans matched ({shown}): a sparse or '
                'moving scene; the checks against scan matching are weak', '>= 80 %'))


def motion_tracks(d: Diagnosis) -> None:
    """Pose and yaw tracks of the wheels and every Odometry (stamps sorted, unique)."""
    track = wheel_track(d)
    if track is not None:
        d.pose_tracks['wheels'] = track
        d.tracks['wheels'] = (track[0], np.unwrap(track[1][:, 2]))
    for odom in d.odoms:
        t, pose = sorted_unique(odom.t, odom.pose)
        d.pose_tracks[odom.topic] = (t, pose)
        d.tracks[odom.topic] = (t, np.unwrap(pose[:, 2]))


def _reference_motion(d: Diagnosis) -> tuple[str, np.ndarray, np.ndarray, np.ndarray] | None:
    """base_link's forward speed and yaw rate from the wheels, else an Odometry's twist, else
    scan matching: (name, midpoint stamps, v m/s, w rad/s)."""
    if d.joints is not None:
        t, joints = _joint_arrays(d)
        mid, v, w, _ = wheels.wheel_rates(t, joints, d.geometry)
        return 'the wheels', mid, v, w
    for odom in d.odoms:         # an Odometry's own twist, where it publishes one
        t, twist = sorted_unique(odom.t, odom.twist)
        if t.size > 10 and np.abs(twist[:, [0, 2]]).max() > 0.0:
            return odom.topic, t, twist[:, 0], twist[:, 2]
    for name in [o.topic for o in d.odoms] + ['scan matching']:
        if name in d.pose_tracks:
            t, p = d.pose_tracks[name]
            dt = np.diff(t) * 1e-9
            inc = np.array([se2.between(tuple(a), tuple(b)) for a, b in zip(p[:-1], p[1:])])
            if inc.size and np.abs(inc).sum() > 0:
                return name, t[:-1] + np.diff(t) // 2, inc[:, 0] / dt, inc[:, 2] / dt
    return None


def _declared_mount(d: Diagnosis, note: str) -> imu_checks.MountEstimate:
    """The declared mount as the preset's (not judged: nothing measured replaces it)."""
    return imu_checks.MountEstimate(*mount_rpy(d.declared.imu_mount), 'declared', note)


def _mount_section(d: Diagnosis, t: np.ndarray, accel: np.ndarray, up, up_std, rate_fit, ref
                   ) -> np.ndarray:
    """The mount from the up axis (gravity's, else the rate axis) and the accelerations'
    yaw, each angle with its standard deviation and snapped to a right angle within 2 sigma,
    checked against the declared one; the rotation the gyro is read through (the declared
    mount where the data shows none, the declared yaw where the accelerations show none)."""
    imu = d.imu
    if up is None and rate_fit is not None:
        up, up_std = rate_fit[0], rate_fit[2]
        up_from = 'rotation'
    else:
        up_from = 'gravity'
    if up is None:
        still = d.imu_still is not None and d.imu_still.still.sum() >= 20
        reason = ('neither gravity (the IMU never stands still) nor a reference that turns '
                  'shows its axes' if not still else 'no gravity reading and no reference that '
                  'turns shows its axes')
        d.add(Check('imu_mount', imu.topic, SKIPPED, None, 'deg',
                    f'not judged: {reason}; params.yaml keeps the declared mount '
                    f'({d.declared.imu_mount_from})'))
        d.mount = _declared_mount(d, reason)
        return d.declared.imu_mount
    roll, pitch = imu_checks.roll_pitch_of(up)
    roll_std = up_std / max(abs(math.cos(pitch)), 0.1)
    yaw = yaw_std = None
    note = 'no reference motion'
    if up_from == 'gravity' and ref is not None:
        found = imu_checks.horizontal_yaw(t, accel, roll, pitch, ref[1], ref[2], ref[3])
        if found:
            yaw, yaw_std = found[0], found[2]
            note = f'from accelerations against {ref[0]} ({found[1]:.2f} m/s^2 RMS)'
        else:
            note = 'the robot hardly accelerates'
    elif up_from == 'rotation':
        note = 'no gravity reading to level the accelerations'
    d.mount = imu_checks.MountEstimate.snapped(roll, pitch, yaw, (roll_std, up_std, yaw_std),
                                               up_from, note)
    d.add(imu_checks.mount_check(imu.topic, d.mount, d.declared.imu_mount,
                                 d.declared.imu_mount_from,
                                 imu.frame_id.lstrip('/') == d.base_frame))
    if yaw is None:     # keep the declared yaw about the vertical
        declared_yaw = math.atan2(d.declared.imu_mount[1, 0], d.declared.imu_mount[0, 0])
        d.mount = imu_checks.MountEstimate(d.mount.roll, d.mount.pitch, declared_yaw,
                                           d.mount.up_from, note, d.mount.measured, d.mount.std)
    return d.mount.rotation()


def imu_section(d: Diagnosis) -> None:
    """Gravity (REP 103/145), the rate axis, the mount found against the declared one, gyro
    bias and noise; the gyro's yaw track about base_link's z; the IMU's own orientation."""
    if d.imu is None:
        return
    imu = d.imu
    t, gyro, accel = sorted_unique(imu.t, imu.gyro, imu.accel)
    ref = _reference_motion(d)
    moving = None
    if ref is not None:
        name, rt, v, w = ref
        at = (t - rt[0]) * 1e-9
        moving = (np.abs(np.interp(at, (rt - rt[0]) * 1e-9, v)) > 1e-3) | \
            (np.abs(np.interp(at, (rt - rt[0]) * 1e-9, w)) > 1e-3)
    still = imu_checks.stillness(t, gyro, accel, moving)
    d.imu_still = still
    gravity, up, up_std = imu_checks.gravity_check(imu.topic, accel, still,
                                                   d.declared.imu_mount)
    d.add(gravity)
    rate_fit = None
    if ref is not None:
        rate_fit = imu_checks.rate_axis(t, gyro, ref[1], ref[3])
        if rate_fit is not None:
            d.add(imu_checks.rate_axis_check(imu.topic, ref[0], rate_fit[0], rate_fit[1], up))
    rotation = _mount_section(d, t, accel, up, up_std, rate_fit, ref)
    rate_z = gyro @ rotation[2]
    noise = imu_checks.gyro_noise_checks(imu.topic, t, rate_z, still)
    d.add(noise)
    bias = next((c for c in noise if c.name == 'gyro_bias' and c.verdict != SKIPPED), None)
    d.gyro_bias = bias.details['bias_rad_s'] if bias is not None else None
    d.gyro_noise_density = next((c.value for c in noise
                                 if c.name == 'gyro_noise' and c.verdict != SKIPPED), None)
    d.tracks[imu.topic] = (t, integrate_rate(t, rate_z, bias=d.gyro_bias or 0.0))
    d.imu_rate_z = (t, rate_z)
    if imu_reports_orientation(imu):
        turned = float(np.abs(np.diff(d.tracks[imu.topic][1])).sum())
        check = cross.orientation_check(imu.topic, imu.orientation, imu.orientation_cov, turned)
        d.add(check)
        d.orientation_usable = not (check.details['identity'] or (
            check.details['constant'] and turned > math.radians(5.0)))
        ot, q = sorted_unique(imu.t, imu.orientation)
        yaw = np.unwrap([math.atan2(b[1, 0], b[0, 0]) for b in
                         (quaternion_matrix(row) @ rotation.T for row in q)])
        d.orientation_yaw = (ot, yaw)
        if d.orientation_usable:
            tilt = [math.degrees(math.acos(min(1.0, abs(float(
                (quaternion_matrix(q) @ rotation.T)[2, 2]))))) for q in
                imu.orientation[::max(1, len(imu.orientation) // 2000)]]
            d.imu_tilt_deg = float(max(tilt))


def imu_reports_orientation(imu: ImuStream | None) -> bool:
    """The Imu messages fill their orientation (REP 145: covariance[0] -1 says they do not)."""
    return imu is not None and not np.all(imu.orientation_cov[:, 0] == -1.0) and \
        bool(np.all(np.linalg.norm(imu.orientation, axis=1) > 0.5))


def orientation_track(topic: str) -> str:
    """The name of the yaw track of an IMU's own orientation."""
    return f'{topic} (its orientation)'


def offset_section(d: Diagnosis) -> None:
    """Time offsets of every yaw track against the reference (scan matching, else the wheels,
    else the first Odometry), solved from every pair of tracks weighted by the increments
    each pair compares (the high-rate pairs, wheels and gyro, pin the relative offsets; the
    laser's few increments the common one): the fusion's <input>.delay_s."""
    names = list(d.tracks)
    reference = next((n for n in ('scan matching', 'wheels') if n in d.tracks),
                     names[0] if names else '')
    if len(names) < 2:
        d.add(Check('time_offset', 'bag', SKIPPED, None, 's',
                    'fewer than two motion sources: no time offset to measure'))
        return
    pairs: dict[tuple[str, str], tuple[float, float]] = {}
    refused: dict[str, str] = {}
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            try:
                pairs[a, b] = timing.pairwise_offset(*d.tracks[a], *d.tracks[b])
            except ValueError as exc:
                refused[f'{a} vs {b}'] = str(exc)
    solved = timing.solve_offsets(names, reference, pairs)
    for name in names:
        if name == reference:
            continue
        if name not in solved:
            d.add(Check('time_offset', f'{name} vs {reference}', SKIPPED, None, 's',
                        'not measured: ' + '; '.join(f'{pair}: {why}'
                                                     for pair, why in refused.items())))
            continue
        fused = {'wheels' if d.joints is not None else (d.odoms[0].topic if d.odoms else ''),
                 d.imu.topic if d.imu is not None else ''}
        d.add(timing.offset_check(name, reference, solved[name], pairs,
                                  reference == 'scan matching' and name in fused))
    d.offsets = solved
    d.offset_reference = reference


def _shifted(d: Diagnosis, name: str) -> tuple[np.ndarray, np.ndarray]:
    """A yaw track with its time offset against the reference taken out."""
    t, yaw = d.tracks[name]
    return t - int(round(d.offsets.get(name, 0.0) * 1e9)), yaw


def _gain(check: Check) -> float | None:
    return check.details.get('gain') if check.verdict != SKIPPED else None


def _bias_from_wheels(d: Diagnosis, bias: float) -> None:
    """A gyro never still: its bias from the yaw-rate offset against the wheels (which agree
    with it in gain), in place of the still reading it lacks; its yaw track integrated
    again."""
    d.gyro_bias = bias
    t, rate_z = d.imu_rate_z
    d.tracks[d.imu.topic] = (t, integrate_rate(t, rate_z, bias=bias))
    d.checks = [c for c in d.checks if not (c.name == 'gyro_bias' and c.verdict == SKIPPED)]
    verdict = graded(abs(bias), math.radians(1.0), 0.05)
    d.add(Check('gyro_bias', d.imu.topic, verdict, math.degrees(bias), 'deg/s',
                f'bias {math.degrees(bias):+.3f} deg/s, read against the wheels\' yaw rate while '
                'moving (the IMU never stands still): initial_bias_z_rad_s in params.yaml',
                '< 1 deg/s', {'bias_rad_s': bias, 'from': 'wheels'}))


def cross_section(d: Diagnosis) -> None:
    """Each source against the others: the wheels' and each odometry's yaw rate against the
    gyro's, their distance against scan matching's, every pair's heading over the run (time
    offsets taken out)."""
    gyro = d.imu.topic if d.imu is not None and d.imu.topic in d.tracks else None
    if gyro is not None:
        gt, gy = _shifted(d, gyro)
        if d.joints is not None:
            jt, joints = _joint_arrays(d)
            jt = jt - int(round(d.offsets.get('wheels', 0.0) * 1e9))
            found = cross.yaw_rate_gain('wheels', gyro, jt, wheels.wheel_rates(
                jt, joints, d.geometry)[3], gt, gy, '')
            gain = _gain(found)
            if d.gyro_bias is None and gain is not None and \
                    cross.GAIN_LOW <= gain <= cross.GAIN_HIGH:
                _bias_from_wheels(d, -found.details['offset_rad_s'] / gain)
                gt, gy = _shifted(d, gyro)
            d.wheel_yaw_scale = 1.0 if gain is None or \
                cross.GAIN_LOW <= gain <= cross.GAIN_HIGH else gain
            separation = d.geometry.wheel_separation_m * d.wheel_yaw_scale
            fix = (f'params.yaml\'s wheel_separation_m ({separation:.4f} m, '
                   + ('calibrated against scan matching' if d.calibration is not None else
                      'the declared one') + ') ' + (
                       f'scaled by {d.wheel_yaw_scale:.2f} so that the wheels turn as the gyro '
                       'does' if d.wheel_yaw_scale != 1.0 else
                       f'brings the gain to {gain:.2f}' if gain is not None else 'is kept'))
            check = cross.yaw_rate_gain('wheels', gyro, jt, wheels.wheel_rates(
                jt, joints, d.declared.geometry)[3], gt, gy, fix)
            if check.verdict != SKIPPED:
                check.details['gain_with_preset_geometry'] = gain
                check.details['preset_separation_m'] = separation
            if check.verdict == PROBLEM:
                check = replace(check, fix=fix)
                if d.wheel_yaw_scale != 1.0:
                    d.distrust['wheels'] = (f'its yaw rate is {check.value:.2f}x the gyro\'s '
                                            '(yaw_rate_gain)')
            d.add(check)
        for odom in d.odoms:
            ot, oy = _shifted(d, odom.topic)
            fix = ('params.yaml leaves its yaw rate out of the fusion (wheel_odom.mask without '
                   'yaw and vyaw): the IMU gives the heading')
            check = cross.yaw_rate_gain(odom.topic, gyro, ot, oy, gt, gy, fix)
            if check.verdict == PROBLEM:
                check = replace(check, fix=fix)
                d.odom_yaw_distrusted.add(odom.topic)
                d.distrust[odom.topic] = (f'its yaw rate is {check.value:.2f}x the gyro\'s '
                                          '(yaw_rate_gain: skid steer)')
            d.add(check)
    ref = _reference_intervals(d)
    if ref is not None:
        t0, t1, motion, _ = ref
        sources = ([('wheels', wheel_track(d, d.declared.geometry))] if d.joints is not None
                   else []) + [(o.topic, d.pose_tracks[o.topic]) for o in d.odoms]
        for name, (t, pose) in sources:
            inc = _increments(t, pose, t0, t1)
            travel = np.copysign(np.hypot(inc[:, 0], inc[:, 1]), inc[:, 0])
            along = np.copysign(np.hypot(motion[:, 0], motion[:, 1]), motion[:, 0])
            if name == 'wheels':
                fix = ('params.yaml\'s wheel_radius_m is calibrated against scan matching'
                       if d.calibration is not None else 'set wheel_radius_m')
            else:
                fix = 'correct the wheel radius in the driver (the fusion takes its speed as is)'
            check = cross.speed_scale(name, travel, along, fix)
            if check.verdict == PROBLEM and name == 'wheels' and d.calibration is not None:
                check = replace(check, fix=fix)
            d.add(check)
    headings = {(f'{n} (gyro heading)' if d.imu is not None and n == d.imu.topic else n):
                _shifted(d, n) for n in d.tracks}
    if d.orientation_yaw is not None:
        headings[orientation_track(d.imu.topic)] = d.orientation_yaw
    names = list(headings)
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            d.add(cross.heading_agreement(a, b, *headings[a], *headings[b]))


def _increments(t: np.ndarray, poses: np.ndarray, t0: np.ndarray, t1: np.ndarray) -> np.ndarray:
    """Motion (x, y, yaw) of a pose track from t0 to t1 in the frame at t0 (NaN outside)."""
    a, b = pose_at(t, poses, t0), pose_at(t, poses, t1)
    out = np.full((len(t0), 3), np.nan)
    ok = np.isfinite(a).all(axis=1) & np.isfinite(b).all(axis=1)
    c, s = np.cos(a[ok, 2]), np.sin(a[ok, 2])
    dx, dy = b[ok, 0] - a[ok, 0], b[ok, 1] - a[ok, 1]
    out[ok] = np.column_stack((c * dx + s * dy, -s * dx + c * dy,
                               np.angle(np.exp(1j * (b[ok, 2] - a[ok, 2])))))
    return out


def _reference_intervals(d: Diagnosis, span_s: float = 0.5) -> tuple[np.ndarray, ...] | None:
    """Intervals of about span_s between matched scans: (t0, t1, scan-matched base motion)."""
    if d.scan_track is None:
        return None
    t, poses = d.scan_track
    step = max(1, int(round(span_s / max(np.median(np.diff(t)) * 1e-9, 1e-3))))
    i0 = np.arange(0, len(t) - step, step)
    if i0.size < 5:
        return None
    t0, t1 = t[i0], t[i0 + step]
    # The reference's own variance: each end's match against its keyframe (a floor: 1 mm,
    # 0.05 deg, as ICP's covariance is optimistic).
    var = d.scan_variance[i0] + d.scan_variance[i0 + step] + \
        np.array([1e-6, 1e-6, math.radians(0.05) ** 2])
    return t0, t1, _increments(t, poses, t0, t1), var


def _odometry_noise(d: Diagnosis, ref) -> None:
    """Each Odometry's covariance, and its increments' errors against scan matching in units
    of the variance it claims (NEES)."""
    for odom in d.odoms:
        t, pose = d.pose_tracks[odom.topic]
        d.add(cov_checks.odometry_covariance_check(odom.topic, odom.pose_var, odom.twist_var))
        if ref is None:
            continue
        t0, t1, motion, ref_var = ref
        err = _increments(t, pose, t0, t1) - motion
        err[:, 2] = np.angle(np.exp(1j * err[:, 2]))
        if cov_checks.covariance_kind(odom.pose_var) == 'growing':
            _, var = sorted_unique(odom.t, odom.pose_var)
            grown = np.column_stack([np.interp(t1, t, var[:, i]) - np.interp(t0, t, var[:, i])
                                     for i in range(3)])
        else:
            _, tv = sorted_unique(odom.t, odom.twist_var)
            dt = (t1 - t0) * 1e-9
            grown = np.column_stack([np.interp(t0, t, tv[:, i]) for i in range(3)]) * \
                (dt ** 2)[:, None]
        d.add(cov_checks.nees_check(odom.topic, err, grown + ref_var))


def _wheel_noise(d: Diagnosis, t0, t1, motion, moving) -> None:
    """The wheels' variance per metre along the path and across, and per radian turned."""
    path = np.abs(motion[moving, 0]).sum()
    turned = np.abs(motion[moving, 2]).sum()
    if 'wheels' not in d.pose_tracks or path <= 1.0:
        return
    err = _increments(*d.pose_tracks['wheels'], t0, t1)[moving] - motion[moving]
    err[:, 2] = np.angle(np.exp(1j * err[:, 2]))
    ok = np.isfinite(err).all(axis=1)
    d.noise['wheel_variance_per_m'] = float((err[ok, 0] ** 2).sum() / path)
    d.noise['wheel_lateral_variance_per_m'] = float((err[ok, 1] ** 2).sum() / path)
    if turned > 1.0:
        d.noise['wheel_yaw_variance_per_rad'] = float((err[ok, 2] ** 2).sum() / turned)
    d.noise['wheel_yaw_error_sum_sq'] = float((err[ok, 2] ** 2).sum())


def noise_section(d: Diagnosis) -> None:
    """Each input's errors against scan matching over short intervals: the Odometry's
    covariances, the wheels' variance per metre and per radian turned, the gyro's heading
    variance per second."""
    ref = _reference_intervals(d)
    _odometry_noise(d, ref)
    if d.imu is not None:
        d.add(cov_checks.imu_covariance_check(d.imu.topic, d.imu.orientation_cov,
                                              d.imu.gyro_cov))
    if ref is None:
        return
    t0, t1, motion, _ = ref
    moving = np.isfinite(motion).all(axis=1)
    _wheel_noise(d, t0, t1, motion, moving)
    if d.imu is not None and d.imu.topic in d.tracks:
        t, yaw = d.tracks[d.imu.topic]
        base = t[0]
        inc = np.interp((t1 - base) * 1e-9, (t - base) * 1e-9, yaw) - \
            np.interp((t0 - base) * 1e-9, (t - base) * 1e-9, yaw)
        inside = moving & (t0 >= t[0]) & (t1 <= t[-1])
        e = inc[inside] - motion[inside, 2]
        if e.size > 5:
            d.noise['gyro_yaw_variance_per_s'] = float((e ** 2).sum() / (
                (t1[inside] - t0[inside]).sum() * 1e-9))
            d.noise['gyro_yaw_error_sum_sq'] = float((e ** 2).sum())


def tf_section(d: Diagnosis) -> None:
    """Two publishers of one transform on /tf; one /tf_static transform declared twice,
    differently."""
    pairs: dict[str, list] = {}
    statics: dict[str, list] = {}
    for tr in d.survey.transforms:
        (statics if tr.static else pairs).setdefault(f'{tr.parent} -> {tr.child}', []).append(tr)
    for pair, samples in sorted(statics.items()):
        d.add(tf_checks.static_check(pair, np.array([s.translation for s in samples]),
                                     np.array([s.rotation for s in samples])))
    for pair, samples in sorted(pairs.items()):
        stamps = np.array([s.stamp_ns for s in samples], dtype=np.int64)
        xyyaw = np.array([(s.translation[0], s.translation[1],
                           math.atan2(2 * (s.rotation[3] * s.rotation[2]
                                           + s.rotation[0] * s.rotation[1]),
                                      1 - 2 * (s.rotation[1] ** 2 + s.rotation[2] ** 2)))
                          for s in samples])
        d.add(tf_checks.publishers_check(pair, stamps, xyyaw))
