"""params.yaml: a preset for this package's nodes from what the diagnosis found."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from sensing_nodes.core.diagnosis import covariance as cov_checks
from sensing_nodes.core.diagnosis import imu as imu_checks
from sensing_nodes.core.diagnosis import timing
from sensing_nodes.core.diagnosis.check import PROBLEM, SKIPPED, Check
from sensing_nodes.core.fusion.config import NODE_NAME
from sensing_nodes.core.fusion.ekf import EkfSettings
from sensing_nodes.doctor.diagnosis import (
    PROG,
    Diagnosis,
    imu_reports_orientation,
    orientation_track,
    scan_gap_s,
)
from sensing_nodes.parameters import load_parameters
from sensing_nodes.paths import config_file
from sensing_nodes.topics import FUSED, IMU, IMU_RAW, JOINT_STATES, SCAN

# The fusion on gyro_integrator's heading (the preset's route for a gyro): its settings over
# config/complementary_fusion.yaml, whose default is the raw IMU's rate.
INTEGRATED_ROUTE = 'fusion_integrated.yaml'

# --- the preset -----------------------------------------------------------------------------

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
              'wheel_separation_m': round(g.wheel_separation_m * d.wheel_yaw_scale, 6),
              'base_frame': d.base_frame}
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
        out = {**_integrated_route('imu'), 'topic': IMU, 'source': 'integrated',
               'mask': ['yaw'], 'covariance': 'model', 'heading_delay_s': 0.0,
               'delay_s': _delay(d, d.imu.topic)}
        if 'gyro_yaw_variance_per_s' in d.noise:
            out['yaw_variance_per_s'] = float(f'{d.noise["gyro_yaw_variance_per_s"]:.3g}')
        return out
    has_cov = bool(np.any(d.imu.orientation_cov[:, 2] > 0))
    return {'topic': d.imu.topic, 'source': 'orientation', 'pose_mode': 'absolute',
            'mask': ['yaw', 'vyaw'], 'covariance': 'message' if has_cov else 'model',
            'heading_delay_s': 0.0, 'delay_s': _delay(d, d.imu.topic),
            **angles}


def _integrated_route(block: str) -> dict[str, Any]:
    """complementary_fusion's parameters of one block ('imu', 'ekf') in INTEGRATED_ROUTE, by
    their names in the block."""
    params = load_parameters(NODE_NAME, config_file(INTEGRATED_ROUTE))
    return {name[len(block) + 1:]: value for name, value in params.items()
            if name.startswith(f'{block}.')}


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
            ratio = n['wheel_yaw_error_sum_sq'] / max(n['gyro_yaw_error_sum_sq'], 1e-300)
            d.distrust.setdefault('wheels', f'their heading errs {ratio ** 0.5:.0f}x the gyro\'s '
                                  'against scan matching (slip in turns): params.yaml leaves '
                                  'it out of the fusion')
        return out
    odom = d.odoms[0]
    pose, twist = (cov_checks.covariance_kind(odom.pose_var),
                   cov_checks.covariance_kind(odom.twist_var))
    # Its heading left out where its yaw rate disagrees with the gyro's (yaw_rate_gain).
    turning = odom.topic not in d.odom_yaw_distrusted or d.imu is None
    if pose == 'growing':
        return {'topic': odom.topic, 'pose_mode': 'differential', 'covariance': 'auto',
                'mask': ['x', 'y', 'yaw'][:3 if turning else 2], 'delay_s': _delay(d, odom.topic)}
    if twist not in ('zero', 'none'):
        return {'topic': odom.topic, 'mask': ['vx', 'vy', 'vyaw'][:3 if turning else 2],
                'covariance': 'message', 'delay_s': _delay(d, odom.topic)}
    return {'topic': odom.topic, 'pose_mode': 'differential', 'covariance': 'model',
            'mask': ['x', 'y', 'yaw'][:3 if turning else 2], 'delay_s': _delay(d, odom.topic)}


def _gyro_preset(d: Diagnosis) -> dict[str, Any]:
    mount = d.mount or imu_checks.MountEstimate(0.0, 0.0, 0.0, '', '')
    params = {'mount_roll_rad': round(mount.roll, 6), 'mount_pitch_rad': round(mount.pitch, 6),
              'mount_yaw_rad': round(mount.yaw or 0.0, 6), 'base_frame': d.base_frame,
              'use_wheel_odom': d.joints is not None}
    if d.gyro_bias is not None:        # not judged (never still): the node's default
        params['initial_bias_z_rad_s'] = round(d.gyro_bias, 6)
    if d.gyro_noise_density:
        params['gyro_noise_density'] = float(f'{d.gyro_noise_density:.3g}')
    return params


def _icp_preset(d: Diagnosis) -> dict[str, Any]:
    g = d.geometry
    guide = 'wheels' if d.joints is not None else (d.odoms[0].topic if d.odoms else '')
    params = {'laser_x_m': round(g.laser_x_m, 4), 'laser_y_m': round(g.laser_y_m, 4),
              'laser_yaw_rad': round(g.laser_yaw_rad, 5), 'base_frame': d.base_frame,
              'odom_topic': '/wheel/odom' if guide == 'wheels' else guide,
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
        elif not orientation_only:
            fusion['ekf'] = _integrated_route('ekf')
    slowest = max([float(np.median(np.diff(d.survey.times[t].header_ns))) * 1e-9 for t in
                   {s.topic for s in (d.joints, d.scan, d.imu) if s is not None} |
                   {o.topic for o in d.odoms}] or [0.0])
    if slowest > 0.5:       # sparse logs (a scan a metre): wait for inputs that long
        fusion.update({'max_gap_s': round(10 * slowest, 1),
                       'input_timeout_s': round(10 * slowest, 1)})
    for key, values in _motion_range(d).items():
        fusion[key] = {**fusion.get(key, {}), **values}
    return fusion


def _motion_range(d: Diagnosis) -> dict[str, dict[str, float]]:
    """The spread of the robot's speeds the fusion gates its dead reckoning against, where
    the bag shows faster motion than the default's (a hand-turned IMU, a fast robot): its
    99.9th-percentile yaw rate (the gyro's) and speed (the odometry's twist) over 3, so that
    they lie inside the gate."""
    ekf, defaults = {}, EkfSettings()
    if d.imu is not None and d.imu.gyro.size:
        fastest = float(np.percentile(np.abs(d.imu.gyro[:, 2]), 99.9))
        if fastest / 3.0 > defaults.yaw_rate_std_rad_s:
            ekf['yaw_rate_std_rad_s'] = round(fastest / 3.0, 2)
    speeds = [np.abs(o.twist[:, 0]) for o in d.odoms if o.twist.size]
    if speeds:
        fastest = float(np.percentile(np.concatenate(speeds), 99.9))
        if fastest / 3.0 > defaults.speed_std_m_s:
            ekf['speed_std_m_s'] = round(fastest / 3.0, 2)
    return {'ekf': ekf} if ekf else {}


def build_preset(d: Diagnosis) -> None:
    """params.yaml's node sections, the nodes to run and the bag topics to remap."""
    doc: dict[str, Any] = {}
    remaps: dict[str, str] = {}
    orientation_only = d.joints is None and d.scan is None and d.orientation_usable
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
    judge_fixes(d)


def _fix_of(d: Diagnosis, c: Check) -> str:
    """What params.yaml does about a problem ('' nothing: the data itself is at fault, or
    only the robot's own configuration can change it)."""
    params = {node: v['ros__parameters'] for node, v in d.preset.items()}
    fusion = params.get('complementary_fusion', {})
    if c.fix:
        return c.fix
    if c.name in ('wheel_radius', 'wheel_separation') and 'wheel_odometry' in params:
        return 'params.yaml sets the geometry calibrated against scan matching'
    if c.name == 'laser_mount' and 'icp_matcher' in params:
        return ('params.yaml sets icp_matcher\'s laser_x/y/yaw to the mount found'
                + ('' if not d.laser_on_tf_static else ' (but /tf_static, which the nodes '
                   'take first, declares another: correct it)'))
    if c.name in ('imu_mount', 'imu_gravity') and d.imu is not None:
        frame_is_base = d.imu.frame_id.lstrip('/') == d.base_frame
        if c.name == 'imu_gravity' and c.unit != 'deg':
            return ''            # no gravity in the accelerometer: the data
        if frame_is_base or d.declared.imu_mount_from == '/tf_static':
            return ''            # the nodes take the bag's declaration over params.yaml
        return 'params.yaml sets the nodes\' mount_roll/pitch/yaw_rad to the mount found'
    if c.name == 'time_offset':
        source = c.subject.split(' vs ')[0]
        inputs = {'wheels': fusion.get('wheel_odom', {}),
                  (d.imu.topic if d.imu is not None else ''): fusion.get('imu', {})}
        for odom in d.odoms:
            if fusion.get('wheel_odom', {}).get('topic') == odom.topic:
                inputs[odom.topic] = fusion['wheel_odom']
        delay = inputs.get(source, {}).get('delay_s', 0.0)
        return f'params.yaml sets its delay_s to {delay:.3f} s' if delay else ''
    if c.name == 'covariance' and c.value == 0.0:
        used = [fusion.get(k, {}) for k in ('wheel_odom', 'imu')]
        if any(u.get('topic') == c.subject and u.get('covariance') == 'model' for u in used) \
                or c.subject == '/wheel/odom':
            return 'params.yaml gives the fusion the noise model measured here (covariance: model)'
        return ''
    if c.name == 'imu_orientation':
        imu = fusion.get('imu', {})
        if imu.get('source') == 'integrated' or 'imu' not in fusion:
            return 'params.yaml integrates the gyro instead of fusing the orientation'
        if imu.get('covariance') == 'model':
            return 'params.yaml gives the orientation the noise model (covariance: model)'
        return ''
    if c.name == 'heading_agreement':
        names = c.subject.split(' vs ')
        doubted = [n for n in names if _base_name(n) in d.distrust
                   and _heading_left_out(d, _base_name(n))]
        if doubted:
            return (f'params.yaml does not fuse the heading of {doubted[0]} '
                    f'({d.distrust[_base_name(doubted[0])]})')
    return ''


def _heading_left_out(d: Diagnosis, name: str) -> bool:
    """The preset's fusion takes no heading from this source."""
    fusion = d.preset.get('complementary_fusion', {}).get('ros__parameters', {})
    wheel, imu = fusion.get('wheel_odom', {}), fusion.get('imu', {})
    if d.imu is not None and name == orientation_track(d.imu.topic):
        return imu.get('source') != 'orientation'
    if name == 'wheels':
        name = '/wheel/odom'
    if name in ('/wheel/odom',) + tuple(o.topic for o in d.odoms):
        return wheel.get('topic') != name or not {'yaw', 'vyaw'} & set(wheel.get('mask', []))
    return False


def _base_name(name: str) -> str:
    """A comparison's label without ' (gyro heading)'; the orientation's label kept."""
    return name.removesuffix(' (gyro heading)')


def judge_fixes(d: Diagnosis) -> None:
    """Each problem marked with what params.yaml does about it, and the inputs the fusion
    does not follow (d.distrust) completed from the headings that disagree."""
    from dataclasses import replace

    if d.imu is not None and d.orientation_yaw is not None and not d.orientation_usable:
        d.distrust[orientation_track(d.imu.topic)] = 'it does not move (imu_orientation)'
    if d.imu is not None and not d.orientation_usable and imu_reports_orientation(d.imu):
        d.distrust.setdefault(orientation_track(d.imu.topic),
                              'it is a placeholder (imu_orientation)')
    # A source whose heading disagrees with every other (three or more) is the odd one out;
    # of two, the one that disagrees with scan matching (the doctor's external reference).
    heading = [c for c in d.checks if c.name == 'heading_agreement' and c.verdict != SKIPPED]
    names = {n for c in heading for n in c.subject.split(' vs ')}
    for c in heading:
        pair = c.subject.split(' vs ')
        if c.verdict == PROBLEM and 'scan matching' in pair and len(names) == 2:
            other = _base_name(next(n for n in pair if n != 'scan matching'))
            d.distrust.setdefault(other, f'its heading drifts {c.value:.0f} deg from scan '
                                         'matching\'s, the reference (heading_agreement)')
    if len(names) >= 3:
        for name in names:
            pairs = [c for c in heading if name in c.subject.split(' vs ')]
            if pairs and all(c.verdict == PROBLEM for c in pairs) and \
                    _base_name(name) not in d.distrust:
                d.distrust[_base_name(name)] = (
                    'its heading drifts from every other source\'s (heading_agreement)')
    d.checks = [replace(c, fix=_fix_of(d, c)) if c.verdict == PROBLEM else c for c in d.checks]


class _PresetDumper(yaml.SafeDumper):
    """YAML for rcl's parser: strings it would read as booleans (YAML 1.1: y, n, on, ...)
    quoted."""


_PresetDumper.add_representer(str, lambda dumper, value: dumper.represent_scalar(
    'tag:yaml.org,2002:str', value,
    style="'" if value.lower() in ('y', 'n', 'yes', 'no', 'on', 'off', 'true', 'false') else None))


# robot.launch.py's arguments that name a driver's topic, by the node topic they replace.
LAUNCH_TOPIC_ARGUMENTS = {SCAN: 'scan_topic', IMU_RAW: 'imu_topic',
                          JOINT_STATES: 'joint_states_topic'}


def commands(d: Diagnosis, params: Path) -> dict[str, str]:
    """The sensing_pipeline and sensing_replay command lines that run the preset over the bag:
    remaps, and for the replay the expectation table of the nodes started (each bag input and
    the outputs that answer it; none for what the fusion takes straight from the bag); and
    those that run it on the robot, whose drivers publish the bag's topics: robot.launch.py
    and sensing_graph (the same nodes in one process)."""
    from sensing_nodes.topics import NODES, PROCESSING_NODES

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
        if topic == wheel_topic:
            # The fusion then takes the bag's odometry itself: the lockstep replay is paced by
            # its answer to each wheel input, which it gives with every input published
            # (publish_rate_hz 0; at its default rate it answers at most 30 a second).
            answers.append(FUSED)
            expect += ' --param complementary_fusion:publish_rate_hz:=0.0'
        expect += f' --expect {topic}={",".join(answers)}'
    nodes = ','.join(d.nodes)
    every = set(d.nodes) == set(PROCESSING_NODES)
    launch = ''.join(f' {LAUNCH_TOPIC_ARGUMENTS[b]}:={a}' for a, b in sorted(d.remaps.items()))
    graph = ''.join(f' --remap {n}:{b}:={a}' for a, b in sorted(d.remaps.items())
                    for n in d.nodes if b in NODES[n].inputs)
    return {'sensing_pipeline': f'sensing_pipeline {d.survey.path} OUT --nodes {nodes} '
                                f'--params-file {params}{remap}',
            'sensing_replay': f'sensing_replay {d.survey.path} OUT --launch --nodes {nodes} '
                              f'--params-file {params}{remap}{expect}',
            'ros2 launch': f'ros2 launch sensing_nodes robot.launch.py params_file:={params}'
                           + ('' if every else f' nodes:={nodes}') + launch,
            'sensing_graph': f'sensing_graph --params-file {params}'
                             + ('' if every else f' --nodes {nodes}') + graph}


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
