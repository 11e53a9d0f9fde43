"""sensing_doctor: diagnose a robot's bag without ground truth, and write a preset for this
package's nodes.

    sensing_doctor BAG [--out DIR] [--params-file FILE ...] [--joint-topic T] [--scan-topic T]
                       [--imu-topic T] [--odom-topic T] [--left-joint N --right-joint N]
                       [--no-fusion] [--quiet]

Finds the inputs by type (LaserScan, Imu, JointState, Odometry, /tf, /tf_static), checks each
(timing, REP 103 axes and the IMU mount, REP 117 ranges, wheel geometry and laser mount against
scan matching, covariances, time offsets, two publishers of a transform) against what the
nodes are told (--params-file: a robot preset; default the package's config/ files, and
/tf_static), and writes DIR/report.html, DIR/report.json and DIR/params.yaml (a preset
loadable by sensing_replay --launch --params-file and sensing_pipeline --params-file). The
report ends with the preset run through the nodes offline (sensing_pipeline's code) and the
fused output against each input. Checks, methods and limits: docs/doctor.md.

Exit status: 0 the bag can be used (warnings allowed), 1 problems found, 2 the bag cannot be
read (the reason named).
"""

from __future__ import annotations

import argparse
import base64
import html
import io
import json
import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from sensing_nodes.bags.sensor_streams import SensorBagError, stderr_progress
from sensing_nodes.bags.survey import ImuStream, JointStream, OdomStream, Survey, survey_bag
from sensing_nodes.core.diagnosis import covariance as cov_checks
from sensing_nodes.core.diagnosis import imu as imu_checks
from sensing_nodes.core.diagnosis import laser as laser_checks
from sensing_nodes.core.diagnosis import tf as tf_checks
from sensing_nodes.core.diagnosis import timing, wheels
from sensing_nodes.core.diagnosis.check import OK, PROBLEM, SKIPPED, WARNING, Check, worst
from sensing_nodes.core.evaluation import calibration as cal
from sensing_nodes.core.geometry import se2
from sensing_nodes.core.geometry.imu_mount import mount_rotation, quaternion_matrix
from sensing_nodes.core.geometry.quaternion import to_rpy
from sensing_nodes.core.gyro import integrate_rate
from sensing_nodes.core.scan_matching import KeyframeScanMatcher, ScanMatcherSettings
from sensing_nodes.core.wheel_odometry import integrate_path
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
    gyro_bias: float = 0.0
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
    advice = (f'inputs: {found}; base frame {d.base_frame}'
              + (f'; several candidates {several}: choose with --{"/".join(several)}-topic'
                 if several else '')
              + (f'; absent: {", ".join(missing)} (their checks are skipped)' if missing else ''))
    d.add(Check('inputs', 'bag', WARNING if several else OK, None, '', advice, '',
                {'found': found, 'candidates': d.candidates, 'base_frame': d.base_frame,
                 'duration_s': s.duration_s, 'notes': s.notes[:100]}))


def _section(data: Any, node: str) -> dict[str, Any]:
    for key in (node, '/' + node, '/**'):
        section = data.get(key) if isinstance(data, dict) else None
        if isinstance(section, dict) and isinstance(section.get('ros__parameters'), dict):
            return section['ros__parameters']
    return {}


def read_declared(d: Diagnosis) -> None:
    """The nodes' parameters (config/ defaults, then each --params-file) and /tf_static."""
    params: dict[str, dict[str, Any]] = {}
    for node in ('wheel_odometry', 'icp_matcher', 'gyro_integrator'):
        files = [config_file(f'{node}.yaml')] + list(d.args.params_file)
        params[node] = {}
        for f in files:
            try:
                params[node].update(_section(yaml.safe_load(Path(f).read_text()) or {}, node))
            except (OSError, yaml.YAMLError) as exc:
                raise SensorBagError(f'cannot read the parameters {f}: {exc}') from None
    origin = ', '.join(str(f) for f in d.args.params_file) or 'the package\'s config/'
    w, icp = params['wheel_odometry'], params['icp_matcher']
    radius = float(w.get('wheel_radius_m', 0.05))
    laser = [float(icp.get(k, 0.0)) for k in ('laser_x_m', 'laser_y_m', 'laser_yaw_rad')]
    laser_from = origin
    static = _static_transform(d, d.scan.frame_id if d.scan is not None else '')
    if static is not None:
        laser = [static[0][0], static[0][1], to_rpy(static[1])[2]]
        laser_from = '/tf_static'
    geometry = cal.Geometry(radius * float(w.get('left_radius_multiplier', 1.0)),
                            radius * float(w.get('right_radius_multiplier', 1.0)),
                            float(w.get('wheel_separation_m', 0.30)), *laser)
    g = params['gyro_integrator']
    mount = mount_rotation(*(float(g.get(f'mount_{a}_rad', 0.0)) for a in
                             ('roll', 'pitch', 'yaw')))
    mount_from = origin
    imu_frame = d.imu.frame_id.lstrip('/') if d.imu is not None else ''
    static = _static_transform(d, imu_frame)
    if static is not None:
        mount, mount_from = quaternion_matrix(static[1]), '/tf_static'
    elif imu_frame == d.base_frame:
        mount, mount_from = np.eye(3), f'the IMU\'s frame is {d.base_frame}'
    d.declared = Declared(geometry, f'{origin}; laser from {laser_from}',
                          str(w.get('left_wheel_joint', '')), str(w.get('right_wheel_joint', '')),
                          mount, mount_from, params)


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
                f'cannot tell the wheels among {list(names)}: give --left-joint/--right-joint'))
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


def _sorted_unique(t: np.ndarray, *columns: np.ndarray) -> tuple[np.ndarray, ...]:
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
    t, pos = _sorted_unique(d.joints.t, d.joints.position[:, list(d.wheel_columns)])
    return t, pos


def _scan_points(d: Diagnosis) -> tuple[np.ndarray, list[np.ndarray]]:
    from sensing_nodes.core.geometry.scan import scan_to_points

    t, idx = _sorted_unique(d.scan.t, np.arange(d.scan.t.size))
    points = [scan_to_points(d.scan.ranges[i], d.scan.angles, d.scan.range_min,
                             d.scan.range_max)[0] for i in idx]
    return t, points


def wheel_section(d: Diagnosis) -> None:
    """Calibration against scan matching (twice when the declared geometry is far off, so the
    matcher starts from a good guess), then the geometry, resolution and odometry checks."""
    d.geometry = d.declared.geometry
    if d.joints is None:
        return
    joint_t, joints = _joint_arrays(d)
    if d.scan is not None and np.ptp(joints, axis=0).max() > 1e-6:
        scan_t, points = _scan_points(d)
        nominal = d.declared.geometry
        try:
            for _ in range(2):
                intervals = cal.make_intervals(joint_t, joints, scan_t, points, nominal)
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
        t, yaw = _sorted_unique(odom.t, odom.pose[:, 2])
        d.add(wheels.encoders_vs_odometry(odom.topic, joint_t, joints, t, yaw))


def wheel_track(d: Diagnosis) -> tuple[np.ndarray, np.ndarray] | None:
    """Dead reckoning from the encoders with the geometry found: (stamps, poses (J, 3))."""
    if d.joints is None:
        return None
    t, joints = _joint_arrays(d)
    g = d.geometry
    steps = np.diff(joints, axis=0)
    poses, _ = integrate_path((0.0, 0.0, 0.0), steps[:, 0] * g.left_radius_m,
                              steps[:, 1] * g.right_radius_m, g.wheel_separation_m)
    return t, np.vstack(([0.0, 0.0, 0.0], poses))


def _pose_at(t: np.ndarray, poses: np.ndarray, query: np.ndarray) -> np.ndarray:
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
    scan_t, points = _scan_points(d)
    g = d.geometry
    matcher = KeyframeScanMatcher(ScanMatcherSettings(
        laser_pose=(g.laser_x_m, g.laser_y_m, g.laser_yaw_rad), max_gap_s=scan_gap_s(d)))
    guide = d.pose_tracks.get('wheels') or next(
        (d.pose_tracks[o.topic] for o in d.odoms if o.topic in d.pose_tracks), None)
    guess = _pose_at(*guide, scan_t) if guide is not None else None
    poses, variances, status = [], [], {}
    for i, (stamp, pts) in enumerate(zip(scan_t, points)):
        motion = None
        if guess is not None and i and np.isfinite(guess[i]).all() and \
                np.isfinite(guess[i - 1]).all():
            motion = se2.between(tuple(guess[i - 1]), tuple(guess[i]))
        step = matcher.process(int(stamp), pts, motion)
        status[step.status] = status.get(step.status, 0) + 1
        poses.append(step.pose)
        # The match's own variance against its keyframe (NaN where nothing was matched).
        variances.append(np.diag(step.relative_covariance) if step.relative_covariance
                         is not None else np.full(3, np.nan))
    d.scan_track = (scan_t, np.array(poses, dtype=float))
    d.scan_variance = np.array(variances)
    d.pose_tracks['scan matching'] = d.scan_track
    d.scan_track_status = status
    d.tracks['scan matching'] = (scan_t, np.unwrap(np.array(poses)[:, 2]))
    matched = status.get('matched', 0) / max(len(points) - 1, 1)
    d.add(Check('scan_matching', d.scan.topic, OK if matched >= 0.8 else WARNING,
                100.0 * matched, '% matched',
                f'{100 * matched:.0f} % of scans matched their keyframe ({status}): the '
                'reference for the time offsets, noise and covariance checks' if matched >= 0.8
                else f'only {100 * matched:.0f} % of scans matched ({status}): a sparse or '
                'moving scene; the checks against scan matching are weak', '>= 80 %'))


def motion_tracks(d: Diagnosis) -> None:
    """Pose and yaw tracks of the wheels and every Odometry (stamps sorted, unique)."""
    track = wheel_track(d)
    if track is not None:
        d.pose_tracks['wheels'] = track
        d.tracks['wheels'] = (track[0], np.unwrap(track[1][:, 2]))
    for odom in d.odoms:
        t, pose = _sorted_unique(odom.t, odom.pose)
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
        t, twist = _sorted_unique(odom.t, odom.twist)
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


def _mount_section(d: Diagnosis, t: np.ndarray, accel: np.ndarray, up, axis, ref
                   ) -> np.ndarray:
    """The mount from the up axis (gravity's, else the rate axis) and the accelerations'
    yaw, checked against the declared one; the rotation the gyro is read through (the
    declared yaw kept where none was found)."""
    imu = d.imu
    direction = up if up is not None else axis
    if direction is None:
        d.add(Check('imu_mount', imu.topic, SKIPPED, None, 'deg',
                    'neither gravity nor a reference yaw rate shows the IMU\'s axes'))
        return d.declared.imu_mount
    roll, pitch = imu_checks.roll_pitch_of(direction)
    yaw, note = None, 'no reference motion'
    if up is not None and ref is not None:
        found = imu_checks.horizontal_yaw(t, accel, roll, pitch, ref[1], ref[2], ref[3])
        yaw, note = (found[0], f'from accelerations, {found[1]:.2f} m/s^2 RMS') \
            if found else (None, 'the robot hardly accelerates')
    elif up is None:
        note = 'no gravity in the accelerometer'
    d.mount = imu_checks.MountEstimate(roll, pitch, yaw,
                                       'gravity' if up is not None else 'rotation', note)
    d.add(imu_checks.mount_check(imu.topic, d.mount, d.declared.imu_mount,
                                 d.declared.imu_mount_from,
                                 imu.frame_id.lstrip('/') == d.base_frame))
    if yaw is None:     # keep the declared yaw about the vertical
        declared_yaw = math.atan2(d.declared.imu_mount[1, 0], d.declared.imu_mount[0, 0])
        d.mount = imu_checks.MountEstimate(roll, pitch, declared_yaw, d.mount.up_from, note)
    return d.mount.rotation()


def imu_section(d: Diagnosis) -> None:
    """Gravity (REP 103/145), the rate axis, the mount found against the declared one, gyro
    bias and noise; the gyro's yaw track about base_link's z."""
    if d.imu is None:
        return
    imu = d.imu
    t, gyro, accel = _sorted_unique(imu.t, imu.gyro, imu.accel)
    ref = _reference_motion(d)
    moving = None
    if ref is not None:
        name, rt, v, w = ref
        at = (t - rt[0]) * 1e-9
        moving = (np.abs(np.interp(at, (rt - rt[0]) * 1e-9, v)) > 1e-3) | \
            (np.abs(np.interp(at, (rt - rt[0]) * 1e-9, w)) > 1e-3)
    still = imu_checks.stillness(t, gyro, accel, moving)
    gravity, up = imu_checks.gravity_check(imu.topic, accel, still, d.declared.imu_mount)
    d.add(gravity)
    axis = None
    if ref is not None:
        fit = imu_checks.rate_axis(t, gyro, ref[1], ref[3])
        if fit is not None:
            axis = fit[0]
            d.add(imu_checks.rate_axis_check(imu.topic, ref[0], fit[0], fit[1], up))
    rotation = _mount_section(d, t, accel, up, axis, ref)
    rate_z = gyro @ rotation[2]
    noise = imu_checks.gyro_noise_checks(imu.topic, t, rate_z, still)
    d.add(noise)
    d.gyro_bias = next((c.details['bias_rad_s'] for c in noise
                        if c.name == 'gyro_bias' and c.verdict != SKIPPED), 0.0)
    d.gyro_noise_density = next((c.value for c in noise
                                 if c.name == 'gyro_noise' and c.verdict != SKIPPED), None)
    d.tracks[imu.topic] = (t, integrate_rate(t, rate_z, bias=d.gyro_bias))
    d.imu_still = still
    if not np.all(imu.orientation_cov[:, 0] == -1.0) and np.any(imu.orientation[:, 3] != 0):
        tilt = [math.degrees(math.acos(min(1.0, abs(float(
            (quaternion_matrix(q) @ rotation.T)[2, 2]))))) for q in
            imu.orientation[::max(1, len(imu.orientation) // 2000)]]
        d.imu_tilt_deg = float(max(tilt))


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
                        f'not measured: {refused}'))
            continue
        d.add(timing.offset_check(name, reference, solved[name], pairs))
    d.offsets = solved
    d.offset_reference = reference


def _increments(t: np.ndarray, poses: np.ndarray, t0: np.ndarray, t1: np.ndarray) -> np.ndarray:
    """Motion (x, y, yaw) of a pose track from t0 to t1 in the frame at t0 (NaN outside)."""
    a, b = _pose_at(t, poses, t0), _pose_at(t, poses, t1)
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
            _, var = _sorted_unique(odom.t, odom.pose_var)
            grown = np.column_stack([np.interp(t1, t, var[:, i]) - np.interp(t0, t, var[:, i])
                                     for i in range(3)])
        else:
            _, tv = _sorted_unique(odom.t, odom.twist_var)
            dt = (t1 - t0) * 1e-9
            grown = np.column_stack([np.interp(t0, t, tv[:, i]) for i in range(3)]) * \
                (dt ** 2)[:, None]
        d.add(cov_checks.nees_check(odom.topic, err, grown + ref_var))


def _wheel_noise(d: Diagnosis, t0, t1, motion, moving) -> None:
    """The wheels' variance per metre along the path and across, per radian turned, and the
    tail of their normalised errors (the scan-match gate)."""
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
    # How far the wheels' increments stray from scan matching in units of that model, over
    # intervals that drive at least 0.1 m/s (in place, the matcher's own noise, which does
    # not shrink with the distance, would dominate).
    dist = np.abs(motion[moving, 0])[ok]
    driving = dist >= 0.1 * (t1 - t0)[moving][ok] * 1e-9
    if driving.sum() >= 20:
        normalised = (err[ok, 0] ** 2 + err[ok, 1] ** 2)[driving] / (
            d.noise['wheel_variance_per_m'] * dist[driving])
        d.noise['wheel_error_chi2_p99'] = float(np.percentile(normalised, 99))


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


# --- the preset -----------------------------------------------------------------------------

def _imu_has_orientation(imu: ImuStream | None) -> bool:
    return imu is not None and not np.all(imu.orientation_cov[:, 0] == -1.0) and \
        bool(np.all(np.linalg.norm(imu.orientation, axis=1) > 0.5))


def _delay(d: Diagnosis, name: str) -> float:
    """A track's time offset for the fusion's delay_s: 0 within the check's tolerance, and 0
    without a laser: between proprioceptive sources alone (wheels, odometry, gyro) the offset
    says which is late only relative to the other, not which stamps to correct."""
    if d.offset_reference != 'scan matching':
        return 0.0
    offset = d.offsets.get(name, 0.0)
    return round(offset, 4) if abs(offset) >= timing.OFFSET_WARN_S else 0.0


def _wheel_preset(d: Diagnosis) -> dict[str, Any]:
    g = d.geometry
    names = d.joints.names
    params = {'left_wheel_joint': names[d.wheel_columns[0]],
              'right_wheel_joint': names[d.wheel_columns[1]],
              'wheel_radius_m': round(g.left_radius_m, 6), 'left_radius_multiplier': 1.0,
              'right_radius_multiplier': round(g.right_radius_m / g.left_radius_m, 6),
              'wheel_separation_m': round(g.wheel_separation_m, 6), 'base_frame': d.base_frame}
    if 'wheel_variance_per_m' in d.noise:
        # wheel_odometry's k is per metre of each wheel's travel: along the path, both wheels
        # travel the distance, and the path's variance is k / 2 per metre.
        params['wheel_variance_per_m'] = float(f'{2.0 * d.noise["wheel_variance_per_m"]:.3g}')
    return params


def _imu_fusion_preset(d: Diagnosis, integrated: bool) -> dict[str, Any]:
    mount = d.mount or imu_checks.MountEstimate(0.0, 0.0, 0.0, '', '')
    angles = {f'mount_{a}_rad': round(float(v), 6) for a, v in
              zip(('roll', 'pitch', 'yaw'), (mount.roll, mount.pitch, mount.yaw or 0.0))}
    if integrated:
        out = {'topic': IMU, 'source': 'integrated', 'mask': ['yaw'], 'covariance': 'model',
               'heading_delay_s': 0.0, 'delay_s': _delay(d, d.imu.topic)}
        if 'gyro_yaw_variance_per_s' in d.noise:
            out['yaw_variance_per_s'] = float(f'{d.noise["gyro_yaw_variance_per_s"]:.3g}')
        return out
    has_cov = bool(np.any(d.imu.orientation_cov[:, 2] > 0))
    return {'topic': d.imu.topic, 'source': 'orientation', 'pose_mode': 'absolute',
            'mask': ['yaw', 'vyaw'], 'covariance': 'message' if has_cov else 'model',
            'gate_chi2': 0.0, 'heading_delay_s': 0.0, 'delay_s': _delay(d, d.imu.topic),
            **angles}


def _odom_fusion_preset(d: Diagnosis) -> dict[str, Any]:
    """The wheels' input to the fusion: /wheel/odom with the measured noise model, or the bag's
    Odometry as its covariance allows."""
    if d.joints is not None:
        out = {'topic': '/wheel/odom', 'pose_mode': 'differential', 'covariance': 'model',
               'covariance_scale': 1.0, 'mask': ['x', 'y', 'yaw'],
               'delay_s': _delay(d, 'wheels')}
        n = d.noise
        if 'wheel_variance_per_m' in n:
            out['variance_per_m'] = float(f'{max(n["wheel_variance_per_m"], 1e-6):.3g}')
        if 'wheel_yaw_variance_per_rad' in n:
            out['variance_per_rad'] = float(f'{max(n["wheel_yaw_variance_per_rad"], 1e-6):.3g}')
        # The wheels' heading is left out where its errors against scan matching are ten
        # times the gyro's over the same intervals (slip in turns).
        if n.get('wheel_yaw_error_sum_sq', 0.0) > 10.0 * n.get('gyro_yaw_error_sum_sq', np.inf):
            out['mask'] = ['x', 'y']
        return out
    odom = d.odoms[0]
    pose, twist = (cov_checks.covariance_kind(odom.pose_var),
                   cov_checks.covariance_kind(odom.twist_var))
    if pose == 'growing':
        return {'topic': odom.topic, 'pose_mode': 'differential', 'covariance': 'auto',
                'mask': ['x', 'y', 'yaw'], 'delay_s': _delay(d, odom.topic)}
    if twist not in ('zero', 'none'):
        return {'topic': odom.topic, 'mask': ['vx', 'vy', 'vyaw'], 'covariance': 'message',
                'delay_s': _delay(d, odom.topic)}
    return {'topic': odom.topic, 'pose_mode': 'differential', 'covariance': 'model',
            'mask': ['x', 'y', 'yaw'], 'delay_s': _delay(d, odom.topic)}


def _gyro_preset(d: Diagnosis) -> dict[str, Any]:
    mount = d.mount or imu_checks.MountEstimate(0.0, 0.0, 0.0, '', '')
    params = {'mount_roll_rad': round(mount.roll, 6), 'mount_pitch_rad': round(mount.pitch, 6),
              'mount_yaw_rad': round(mount.yaw or 0.0, 6), 'base_frame': d.base_frame,
              'initial_bias_z_rad_s': round(d.gyro_bias, 6),
              'use_wheel_odom': d.joints is not None}
    if d.gyro_noise_density:
        params['gyro_noise_density'] = float(f'{d.gyro_noise_density:.3g}')
    return params


def _icp_preset(d: Diagnosis) -> dict[str, Any]:
    g = d.geometry
    guide = 'wheels' if d.joints is not None else (d.odoms[0].topic if d.odoms else '')
    params = {'laser_x_m': round(g.laser_x_m, 4), 'laser_y_m': round(g.laser_y_m, 4),
              'laser_yaw_rad': round(g.laser_yaw_rad, 5), 'base_frame': d.base_frame,
              'odom_topic': '/wheel/odom' if guide in ('wheels', '') else guide,
              'odom_delay_s': _delay(d, guide)}
    if scan_gap_s(d) > 1.0:        # a keyframe log: bridge its gaps, extrapolate its odometry
        params['max_gap_s'] = scan_gap_s(d)
        if guide not in ('wheels', '') and d.odoms[0].t.size > 1:
            period = float(np.median(np.diff(np.sort(d.odoms[0].t)))) * 1e-9
            params['odom_max_extrapolation_s'] = round(min(1.0, max(0.1, 5 * period)), 2)
    return params


def _fusion_preset(d: Diagnosis, orientation_only: bool) -> dict[str, Any]:
    odom_source = d.joints is not None or bool(d.odoms)
    fusion: dict[str, Any] = {
        'method': 'ekf', 'base_frame': d.base_frame, 'use_wheel_odom': odom_source,
        'use_imu': d.imu is not None, 'use_scan_match_position': d.scan is not None,
        'use_scan_match_heading': d.scan is not None}
    if odom_source:
        fusion['wheel_odom'] = _odom_fusion_preset(d)
    if d.imu is not None:
        fusion['imu'] = _imu_fusion_preset(d, not orientation_only)
        if orientation_only and (d.imu_tilt_deg or 0.0) > 2.0:
            fusion['level_with_imu_tilt'] = True
    slowest = max([float(np.median(np.diff(d.survey.times[t].header_ns))) * 1e-9 for t in
                   {s.topic for s in (d.joints, d.scan, d.imu) if s is not None} |
                   {o.topic for o in d.odoms}] or [0.0])
    if slowest > 0.5:       # sparse logs (a scan a metre): wait for inputs that long
        fusion.update({'max_gap_s': round(10 * slowest, 1),
                       'input_timeout_s': round(10 * slowest, 1)})
    if d.scan is not None and 'wheel_error_chi2_p99' in d.noise:
        # The default gate (25) holds for Gaussian wheel errors, whose normalised squared
        # error over two axes stays below 9.21 in 99 % of intervals; heavier tails (slip)
        # widen it by as much, or it refuses the right matches after each slip.
        tail = d.noise['wheel_error_chi2_p99'] / 9.21
        fusion['scan_match'] = {'gate_chi2': float(round(min(400.0, 25.0 * max(1.0, tail))))}
    return fusion


def build_preset(d: Diagnosis) -> None:
    """params.yaml's node sections, the nodes to run and the bag topics to remap."""
    doc: dict[str, Any] = {}
    remaps: dict[str, str] = {}
    orientation_only = d.joints is None and d.scan is None and _imu_has_orientation(d.imu)
    if d.joints is not None:
        doc['wheel_odometry'] = _wheel_preset(d)
        if d.joints.topic != JOINT_STATES:
            remaps[d.joints.topic] = JOINT_STATES
    if d.imu is not None and not orientation_only:
        doc['gyro_integrator'] = _gyro_preset(d)
        if d.imu.topic != IMU_RAW:
            remaps[d.imu.topic] = IMU_RAW
    if d.scan is not None:
        doc['icp_matcher'] = _icp_preset(d)
        if d.scan.topic != SCAN:
            remaps[d.scan.topic] = SCAN
    doc['complementary_fusion'] = _fusion_preset(d, orientation_only)
    d.preset = {node: {'ros__parameters': params} for node, params in doc.items()}
    d.nodes, d.remaps = tuple(doc), remaps


class _PresetDumper(yaml.SafeDumper):
    """YAML for rcl's parser: strings it would read as booleans (YAML 1.1: y, n, on, ...)
    quoted."""


_PresetDumper.add_representer(str, lambda dumper, value: dumper.represent_scalar(
    'tag:yaml.org,2002:str', value,
    style="'" if value.lower() in ('y', 'n', 'yes', 'no', 'on', 'off', 'true', 'false') else None))


def commands(d: Diagnosis, params: Path) -> dict[str, str]:
    """The sensing_pipeline and sensing_replay command lines that run the preset: remaps,
    and for the replay the expectation table of the nodes started (each bag input and the
    outputs that answer it; none for what the fusion takes straight from the bag)."""
    from sensing_nodes.topics import NODES

    remap = ''.join(f' --remap {a}:={b}' for a, b in sorted(d.remaps.items()))
    fed = {s.topic for s in (d.joints, d.scan, d.imu) if s is not None}
    fusion = d.preset.get('complementary_fusion', {}).get('ros__parameters', {})
    fed |= {fusion[i]['topic'] for i in ('wheel_odom', 'imu') if i in fusion
            and fusion[i].get('topic') not in ('/wheel/odom', IMU)}
    wheel_topic = fusion.get('wheel_odom', {}).get('topic')
    expect = ''
    for topic in sorted(fed):
        name = d.remaps.get(topic, topic)
        answers = [o for n in d.nodes if NODES[n].answers == name for o in NODES[n].answered_with]
        if topic == wheel_topic:     # the fusion answers each wheel input (once all spoke)
            answers.append(FUSED)
        expect += f' --expect {topic}={",".join(answers)}'
    nodes = ','.join(d.nodes)
    return {'sensing_pipeline': f'sensing_pipeline {d.survey.path} OUT --nodes {nodes} '
                                f'--params-file {params}{remap}',
            'sensing_replay': f'sensing_replay {d.survey.path} OUT --launch --nodes {nodes} '
                              f'--params-file {params}{remap}{expect}'}


def preset_text(d: Diagnosis, out: Path) -> str:
    """params.yaml: the command that loads it, then the node sections."""
    run = commands(d, out / 'params.yaml')
    head = [f'# {PROG} {d.survey.path}: a preset for this package\'s nodes, measured on the bag',
            f'# (report: {out / "report.html"}). Run it with:',
            f'#   {run["sensing_pipeline"]}', f'#   {run["sensing_replay"]}',
            f'# remap (bag topic -> node topic): {json.dumps(d.remaps)}']
    if d.offset_reference and d.offset_reference != 'scan matching' and any(
            abs(v) >= timing.OFFSET_WARN_S for v in d.offsets.values()):
        head.append(f'# Time offsets against {d.offset_reference} are in report.json; without '
                    'a laser they say which source is late relative to the other, not which '
                    'to correct: no delay_s is set.')
    if d.imu is not None and d.imu.frame_id.lstrip('/') == d.base_frame:
        head.append(f'# The Imu\'s frame_id is {d.base_frame}: the nodes take it as aligned '
                    'and ignore the mount_*_rad below (they record what was found).')
    elif d.imu is not None and d.declared.imu_mount_from == '/tf_static':
        head.append('# /tf_static declares the IMU mount: the nodes take it over the '
                    'mount_*_rad below (what was found); correct /tf_static where they differ.')
    return '\n'.join(head) + '\n' + yaml.dump(d.preset, Dumper=_PresetDumper, sort_keys=False)


# --- the preset over the bag ----------------------------------------------------------------

def load_odometry(bag: Path, topic: str) -> tuple[np.ndarray, np.ndarray]:
    """(stamps ns, poses (N, 3)) of an Odometry topic, sorted, one per stamp."""
    from sensing_nodes.bags.storage import read_messages
    from sensing_nodes.ros.conversions import odometry_pose, stamp_to_ns

    rows = {stamp_to_ns(m.header.stamp): odometry_pose(m)[0]
            for _, _, m in read_messages(bag, [topic])}
    t = np.array(sorted(rows), dtype=np.int64)
    return t, np.array([rows[k] for k in t.tolist()], dtype=float).reshape(-1, 3)


def compare_fused(d: Diagnosis, t: np.ndarray, poses: np.ndarray) -> None:
    """The fused output against each pose track, the bag's ground truth where it has one,
    and the IMU's headings (its gyro's integral, its own orientation)."""
    from sensing_nodes.core.evaluation.metrics import trajectory_errors

    def heading_only(stamps: np.ndarray, yaw: np.ndarray) -> dict[str, float] | None:
        errors = trajectory_errors(stamps, np.column_stack((np.zeros((len(stamps), 2)), yaw)),
                                   t, np.column_stack((np.zeros((len(t), 2)), poses[:, 2])))
        return errors.summary(False) if errors.t.size else None

    references = {n: track for n, track in d.pose_tracks.items() if n != 'fused'}
    truth = d.survey.odoms.get(GROUND_TRUTH)
    if truth is not None:      # a simulator's or a log's reference: compared, never an input
        references[f'ground truth ({GROUND_TRUTH})'] = _sorted_unique(truth.t, truth.pose)
    compared = d.fused['compared']
    for name, (rt, rp) in references.items():
        errors = trajectory_errors(rt, rp, t, poses)
        if errors.t.size:
            compared[name] = errors.summary()
    if d.imu is not None and d.imu.topic in d.tracks:
        compared[d.imu.topic + ' (gyro heading)'] = heading_only(*d.tracks[d.imu.topic])
    if _imu_has_orientation(d.imu):
        rotation = d.mount.rotation() if d.mount is not None else d.declared.imu_mount
        it, q = _sorted_unique(d.imu.t, d.imu.orientation)
        yaw = np.unwrap([math.atan2(b[1, 0], b[0, 0]) for b in
                         (quaternion_matrix(row) @ rotation.T for row in q)])
        compared[d.imu.topic + ' (its orientation)'] = heading_only(it, yaw)
    d.fused['compared'] = {n: v for n, v in compared.items() if v is not None}


def fused_section(d: Diagnosis, out: Path) -> None:
    """The preset through the nodes offline (sensing_pipeline's code) over the bag, and the
    fused output against each input, anchored at the fused output's second stamp."""
    from sensing_nodes.graph.pipeline import PipelineError, run

    if 'complementary_fusion' not in d.nodes:
        d.add(Check('fused', 'preset', SKIPPED, None, 'm', 'nothing to fuse'))
        return
    fused_bag = out / 'fused_bag'
    try:
        counts = run(d.survey.path, fused_bag, d.nodes, params_files=[out / 'params.yaml'],
                     remaps=d.remaps, progress=False)
    except PipelineError as exc:
        d.add(Check('fused', 'preset', PROBLEM, None, 'm',
                    f'the preset does not run through the nodes: {exc}'))
        return
    except Exception as exc:  # rcl refuses a parameter file with its own exception types
        d.add(Check('fused', 'preset', PROBLEM, None, 'm',
                    f'the preset does not load ({type(exc).__name__}: {exc})'))
        return
    t, poses = load_odometry(fused_bag, FUSED)
    d.fused = {'outputs': counts, 'final_pose': poses[-1].tolist() if len(poses) else None,
               'compared': {}, 'bag': str(fused_bag)}
    d.pose_tracks['fused'] = (t, poses)
    if len(t) < 2:
        d.add(Check('fused', 'preset', PROBLEM, float(len(t)), 'outputs',
                    f'the fusion published {len(t)} estimates over the bag ({counts})'))
        return
    # The first output is the filter's initial state (with an absolute IMU yaw: before the
    # first orientation reached it): the comparisons anchor at the second.
    compare_fused(d, t[1:], poses[1:])
    shown = '; '.join(f'{n}: {v.get("rms_position_error_m", float("nan")):.3f} m / '
                      f'{v["rms_heading_error_deg"]:.2f} deg RMS'
                      for n, v in d.fused['compared'].items())
    d.add(Check('fused', 'preset', OK, float(len(t)), 'outputs',
                f'the preset\'s fused output ({len(t)} estimates) against each input: {shown}',
                '', d.fused))


# --- the report -----------------------------------------------------------------------------

def _png(fig) -> str:
    buffer = io.BytesIO()
    fig.savefig(buffer, format='png', dpi=90)
    return base64.b64encode(buffer.getvalue()).decode('ascii')


def _anchored(track: tuple[np.ndarray, np.ndarray], anchor: tuple[np.ndarray, np.ndarray]
              ) -> np.ndarray | None:
    """A pose track expressed in the anchor track's frame, coinciding at its first stamp."""
    from sensing_nodes.core.evaluation.metrics import express_in_reference_frame

    t, p = track
    at = _pose_at(t, p, anchor[0][:1])[0]
    if not np.isfinite(at).all():
        return None
    origin = se2.compose(tuple(anchor[1][0]), se2.inverse(tuple(at)))
    return express_in_reference_frame(origin, p)


def make_plots(d: Diagnosis) -> None:
    """Trajectories of every input and the fused output, yaw rates, Allan deviation."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    if d.pose_tracks:
        anchor = d.pose_tracks.get('fused') or d.pose_tracks.get('scan matching') or \
            next(iter(d.pose_tracks.values()))
        fig, ax = plt.subplots(figsize=(7, 6))
        for name, track in d.pose_tracks.items():
            p = _anchored(track, anchor)
            if p is not None:
                ax.plot(p[:, 0], p[:, 1], lw=2.0 if name == 'fused' else 1.0, label=name)
        ax.set_aspect('equal', adjustable='datalim')
        ax.set_xlabel('x (m)')
        ax.set_ylabel('y (m)')
        ax.grid(alpha=0.3)
        ax.legend(loc='best', fontsize=8)
        ax.set_title('Each input and the fused output, anchored at the fused output\'s start')
        fig.tight_layout()
        d.plots['trajectories'] = _png(fig)
        plt.close(fig)
    if len(d.tracks) > 1:
        fig, ax = plt.subplots(figsize=(9, 3.5))
        for name, (t, yaw) in d.tracks.items():
            edges = np.arange(t[0], t[-1], 100_000_000)
            if edges.size < 3:
                continue
            y = np.interp(edges - t[0], t - t[0], yaw)
            ax.plot((edges[1:] - d.survey.times[next(iter(d.survey.times))].record_ns[0]) * 1e-9,
                    np.degrees(np.diff(y) / 0.1), lw=0.8, label=name)
        ax.set_xlabel('bag time (s)')
        ax.set_ylabel('yaw rate (deg/s)')
        ax.grid(alpha=0.3)
        ax.legend(loc='best', fontsize=8)
        ax.set_title('Yaw rate of each source (0.1 s means): time offsets show as shifts')
        fig.tight_layout()
        d.plots['yaw rates'] = _png(fig)
        plt.close(fig)
    noise = next((c for c in d.checks if c.name == 'gyro_noise' and c.verdict != SKIPPED), None)
    if noise is not None:
        fig, ax = plt.subplots(figsize=(6, 4))
        ax.loglog(noise.details['allan_tau_s'], noise.details['allan_dev_rad_s'], 'o-', ms=3)
        ax.set_xlabel('cluster time tau (s)')
        ax.set_ylabel('Allan deviation (rad/s)')
        ax.grid(alpha=0.3, which='both')
        ax.set_title(f'Gyro z (base_link) Allan deviation while still: {noise.subject}')
        fig.tight_layout()
        d.plots['gyro Allan deviation'] = _png(fig)
        plt.close(fig)


def report_json(d: Diagnosis, status: int) -> dict[str, Any]:
    """Every check, verdict and number, the inputs, the preset and the fused comparison."""
    counts = {v: sum(c.verdict == v for c in d.checks) for v in (OK, WARNING, PROBLEM, SKIPPED)}
    return {'tool': PROG, 'bag': d.survey.path, 'duration_s': d.survey.duration_s,
            'exit_status': status, 'verdict': worst(d.checks), 'counts': counts,
            'topics': {t: {'type': ty, 'count': n} for t, (ty, n) in d.survey.topics.items()},
            'base_frame': d.base_frame, 'checks': [c.as_dict() for c in d.checks],
            'preset': {'nodes': list(d.nodes), 'remaps': d.remaps, 'parameters': d.preset,
                       'commands': commands(d, Path('params.yaml'))},
            'time_offsets_s': d.offsets, 'offset_reference': d.offset_reference,
            'noise': d.noise, 'fused': d.fused, 'timings_s': d.timings}


COLOURS = {OK: '#d9f2d9', WARNING: '#fff0c2', PROBLEM: '#f8d0d0', SKIPPED: '#eeeeee'}


def _number(c: Check) -> str:
    if c.value is None:
        return ''
    v = c.value
    shown = f'{v:.4g}' if isinstance(v, float) else str(v)
    return f'{shown} {html.escape(c.unit)}'


def report_html(d: Diagnosis, report: dict[str, Any]) -> str:
    """One self-contained page: the verdicts, the checks, the plots (inline PNG), the preset
    and the fused output against each input."""
    e = html.escape
    rows = ''.join(
        f'<tr style="background:{COLOURS[c.verdict]}"><td>{e(c.subject)}</td><td>{e(c.name)}'
        f'</td><td><b>{e(c.verdict)}</b></td><td>{_number(c)}</td><td>{e(c.limit)}</td>'
        f'<td>{e(c.advice)}</td></tr>' for c in d.checks)
    topics = ''.join(f'<tr><td>{e(t)}</td><td>{e(v["type"])}</td><td>{v["count"]}</td></tr>'
                     for t, v in sorted(report['topics'].items()))
    compared = ''.join(
        f'<tr><td>{e(n)}</td><td>{v.get("rms_position_error_m", float("nan")):.4f}</td>'
        f'<td>{v.get("final_position_error_m", float("nan")):.4f}</td>'
        f'<td>{v["rms_heading_error_deg"]:.3f}</td><td>{v["final_heading_error_deg"]:.3f}</td>'
        '</tr>' for n, v in d.fused.get('compared', {}).items())
    findings = ''.join(
        f'<li style="background:{COLOURS[c.verdict]}"><b>{e(c.verdict)}</b> {e(c.subject)} '
        f'({e(c.name)}, {_number(c)}): {e(c.advice)}</li>'
        for verdict in (PROBLEM, WARNING) for c in d.checks if c.verdict == verdict) or \
        '<li>nothing to change</li>'
    plots = ''.join(f'<h3>{e(title)}</h3><img alt="{e(title)}" src="data:image/png;base64,'
                    f'{data}">' for title, data in d.plots.items())
    counts = report['counts']
    return f"""<!DOCTYPE html>
<html><head><meta charset="utf-8"><title>{PROG}: {e(d.survey.path)}</title>
<style>body{{font-family:sans-serif;max-width:1200px;margin:1em auto;padding:0 1em}}
table{{border-collapse:collapse;width:100%;font-size:90%}}td,th{{border:1px solid #bbb;
padding:3px 6px;vertical-align:top;text-align:left}}pre{{background:#f4f4f4;padding:8px;
overflow-x:auto}}img{{max-width:100%}}</style></head><body>
<h1>{PROG}: {e(Path(d.survey.path).name)}</h1>
<p>{e(d.survey.path)}, {d.survey.duration_s:.1f} s; base frame <code>{e(d.base_frame)}</code>.
<b>Verdict: {e(report['verdict'])}</b> (exit status {report['exit_status']}):
{counts[PROBLEM]} problems, {counts[WARNING]} warnings, {counts[OK]} ok, {counts[SKIPPED]} not
judged.</p>
<h2>What to change</h2><ul>{findings}</ul>
<h2>Every check</h2><table><tr><th>input</th><th>check</th><th>verdict</th><th>value</th>
<th>limit</th><th>what it means, what to change</th></tr>{rows}</table>
<h2>Plots</h2>{plots}
<h2>Topics</h2><table><tr><th>topic</th><th>type</th><th>messages</th></tr>{topics}</table>
<h2>The preset (params.yaml)</h2><pre>{e(d.preset_text)}</pre>
<h2>The preset over the bag: fused output against each input</h2>
<p>The nodes {e(', '.join(d.nodes))} run offline over the bag with the preset
(sensing_pipeline's code); the fused output against each input, anchored at the fused output's
second stamp (the first is the filter's initial state). Without ground truth this is
self-consistency: where inputs disagree, the fused
output sits between them, nearer to the one with less noise.</p>
<table><tr><th>input</th><th>RMS position (m)</th><th>final position (m)</th>
<th>RMS heading (deg)</th><th>final heading (deg)</th></tr>{compared}</table>
<p>Fused final pose: {e(str(d.fused.get('final_pose')))}</p>
</body></html>
"""


# --- the command ----------------------------------------------------------------------------

SECTIONS = (('inputs', find_inputs), ('parameters', read_declared), ('refusals', refusal_section),
            ('timing', timing_section), ('wheels', wheel_section), ('tracks', motion_tracks),
            ('scan matching', scan_section), ('imu', imu_section), ('offsets', offset_section),
            ('noise', noise_section), ('tf', tf_section), ('preset', build_preset))


def diagnose(bag: Path, args: argparse.Namespace,
             progress=None) -> Diagnosis:
    """Read the bag and run every check; SensorBagError when the bag cannot be read."""
    started = time.monotonic()
    d = Diagnosis(survey_bag(bag, progress), args)
    d.timings['read'] = time.monotonic() - started
    for name, section in SECTIONS:
        if name == 'wheels' and d.joints is not None:
            wheel_columns(d)
        started = time.monotonic()
        if progress is not None:
            progress(name)
        section(d)
        d.timings[name] = time.monotonic() - started
    return d


def write_outputs(d: Diagnosis, out: Path, fuse: bool) -> int:
    """params.yaml, the fused comparison, plots, report.json and report.html; the exit status."""
    out.mkdir(parents=True, exist_ok=True)
    d.preset_text = preset_text(d, out)
    (out / 'params.yaml').write_text(d.preset_text)
    if fuse:
        started = time.monotonic()
        fused_bag = out / 'fused_bag'
        if fused_bag.exists():
            import shutil
            shutil.rmtree(fused_bag)
        fused_section(d, out)
        d.timings['fused'] = time.monotonic() - started
    started = time.monotonic()
    make_plots(d)
    d.timings['plots'] = time.monotonic() - started
    status = EXIT_PROBLEMS if worst(d.checks) == PROBLEM else EXIT_OK
    report = report_json(d, status)
    (out / 'report.json').write_text(json.dumps(report, indent=1))
    (out / 'report.html').write_text(report_html(d, report))
    return status


def print_summary(d: Diagnosis, out: Path, status: int) -> None:
    for c in d.checks:
        if c.verdict in (WARNING, PROBLEM):
            print(f'{c.verdict.upper():8} {c.subject}: {c.name}: {c.advice}')
    counts = {v: sum(c.verdict == v for c in d.checks) for v in (PROBLEM, WARNING, OK, SKIPPED)}
    print(f'{PROG}: {counts[PROBLEM]} problems, {counts[WARNING]} warnings, {counts[OK]} ok, '
          f'{counts[SKIPPED]} not judged; wrote {out / "report.html"}, {out / "report.json"}, '
          f'{out / "params.yaml"} (exit {status})')


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog=PROG, description=__doc__.split('\n\n')[0])
    parser.add_argument('bag', type=Path, help='rosbag2 folder (MCAP or sqlite3) or ROS 1 .bag')
    parser.add_argument('--out', type=Path, help='folder for report.html, report.json, '
                        'params.yaml (default: doctor_<bag name>)')
    parser.add_argument('--params-file', action='append', default=[], type=Path,
                        help='what the nodes are told today (a robot preset); repeatable; '
                        'default: the package\'s config/ files')
    for kind in ('joint', 'scan', 'imu', 'odom'):
        parser.add_argument(f'--{kind}-topic', help=f'the {kind} topic, where the bag has '
                            'several candidates')
    parser.add_argument('--left-joint', help='left wheel joint name')
    parser.add_argument('--right-joint', help='right wheel joint name')
    parser.add_argument('--no-fusion', action='store_true',
                        help='skip running the preset through the nodes')
    parser.add_argument('--quiet', action='store_true', help='no progress on stderr')
    args = parser.parse_args(argv)
    for i, f in enumerate(args.params_file):
        if not f.is_file():
            named = config_file(f'robots/{f}.yaml')
            if not named.is_file():
                parser.error(f'--params-file {f}: no such file or robot preset')
            args.params_file[i] = named
    out = args.out or Path(f'doctor_{args.bag.name.removesuffix(".bag")}')
    progress = None if args.quiet else stderr_progress(PROG)
    try:
        d = diagnose(args.bag, args, progress)
    except SensorBagError as exc:
        print(f'{PROG}: error: cannot use the bag: {exc}', file=sys.stderr)
        return EXIT_BAD_INPUT
    status = write_outputs(d, out, not args.no_fusion)
    print_summary(d, out, status)
    return status


if __name__ == '__main__':
    sys.exit(main())
