"""The preset run over the bag through the nodes offline (sensing_pipeline's code), and the
fused output against each input."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from sensing_nodes.core.diagnosis.check import OK, PROBLEM, SKIPPED, WARNING, Check, plural
from sensing_nodes.core.geometry.imu_mount import quaternion_matrix
from sensing_nodes.doctor.diagnosis import (
    Diagnosis,
    imu_reports_orientation,
    orientation_track,
    sorted_unique,
)
from sensing_nodes.topics import FUSED, GROUND_TRUTH, IMU

# --- the preset over the bag ----------------------------------------------------------------

def load_odometry(bag: Path, topic: str) -> tuple[np.ndarray, np.ndarray]:
    """(stamps ns, poses (N, 3)) of an Odometry topic, sorted, one per stamp."""
    from sensing_nodes.bags.storage import read_messages
    from sensing_nodes.ros.conversions import odometry_pose, stamp_to_ns

    rows = {stamp_to_ns(m.header.stamp): odometry_pose(m)[0]
            for _, _, m in read_messages(bag, [topic])}
    t = np.array(sorted(rows), dtype=np.int64)
    return t, np.array([rows[k] for k in t.tolist()], dtype=float).reshape(-1, 3)


def load_headings(bag: Path, topic: str) -> tuple[np.ndarray, np.ndarray] | None:
    """(stamps ns, unwrapped yaw rad) of an Imu topic's orientation (gyro_integrator's
    output), None when the bag has none."""
    from sensing_nodes.bags.storage import read_messages
    from sensing_nodes.core.geometry.quaternion import yaw
    from sensing_nodes.ros.conversions import stamp_to_ns

    rows = {stamp_to_ns(m.header.stamp): yaw((m.orientation.x, m.orientation.y,
                                              m.orientation.z, m.orientation.w))
            for _, _, m in read_messages(bag, [topic])}
    if len(rows) < 2:
        return None
    t = np.array(sorted(rows), dtype=np.int64)
    return t, np.unwrap([rows[k] for k in t.tolist()])


def compare_fused(d: Diagnosis, t: np.ndarray, poses: np.ndarray,
                  integrated: tuple[np.ndarray, np.ndarray] | None = None) -> None:
    """The fused output against each pose track, the bag's ground truth where it has one,
    and the IMU's headings (the doctor's integral of its gyro, gyro_integrator's output where
    the preset runs it, its own orientation)."""
    from sensing_nodes.core.evaluation.metrics import aligned_trajectory_errors, trajectory_errors

    def heading_only(stamps: np.ndarray, yaw: np.ndarray) -> dict[str, float] | None:
        errors = trajectory_errors(stamps, np.column_stack((np.zeros((len(stamps), 2)), yaw)),
                                   t, np.column_stack((np.zeros((len(t), 2)), poses[:, 2])))
        return errors.summary(False) if errors.t.size else None

    references = {n: track for n, track in d.pose_tracks.items() if n != 'fused'}
    truth = d.survey.odoms.get(GROUND_TRUTH)
    if truth is not None:      # a simulator's or a log's reference: compared, never an input
        references[f'ground truth ({GROUND_TRUTH})'] = sorted_unique(truth.t, truth.pose)
    compared = d.fused['compared']
    for name, (rt, rp) in references.items():
        # Rigidly aligned: anchored at one stamp, the first second's transient (a differential
        # input's first message only sets where its increments start) turned Freiburg 101's
        # whole fused track by 3 deg, 1.1 m RMS from a scan matching it follows to 1 mm (ATE).
        errors = aligned_trajectory_errors(rt, rp, t, poses)
        if errors.t.size:
            compared[name] = errors.summary()
    if d.imu is not None and d.imu.topic in d.tracks:
        compared[d.imu.topic + ' (gyro heading)'] = heading_only(*d.tracks[d.imu.topic])
    if integrated is not None:
        compared[f'{d.imu.topic} (gyro_integrator\'s heading)'] = heading_only(*integrated)
    if imu_reports_orientation(d.imu):
        rotation = d.mount.rotation() if d.mount is not None else d.declared.imu_mount
        it, q = sorted_unique(d.imu.t, d.imu.orientation)
        yaw = np.unwrap([math.atan2(b[1, 0], b[0, 0]) for b in
                         (quaternion_matrix(row) @ rotation.T for row in q)])
        compared[orientation_track(d.imu.topic)] = heading_only(it, yaw)
    d.fused['compared'] = {n: v for n, v in compared.items() if v is not None}


def _quietly(quiet: bool, call):
    """call() with the nodes' INFO and WARN logs silenced when quiet (rcutils' default level, put
    back afterwards: a caller's own nodes keep theirs)."""
    if not quiet:
        return call()
    import rclpy.logging

    previous = rclpy.logging.get_logger_level('')
    rclpy.logging.set_logger_level('', rclpy.logging.LoggingSeverity.ERROR)
    try:
        return call()
    finally:
        rclpy.logging.set_logger_level('', previous)


def fused_section(d: Diagnosis, out: Path) -> None:
    """The preset through the nodes offline (sensing_pipeline's code) over the bag, and the
    fused output against each input: pose tracks after the best rigid alignment, headings
    anchored at the fused output's second stamp."""
    from sensing_nodes.bags.storage import failure_reason
    from sensing_nodes.graph.pipeline import PipelineError, run

    if 'complementary_fusion' not in d.nodes:
        d.add(Check('fused', 'preset', SKIPPED, None, 'm', 'nothing to fuse'))
        return
    fused_bag = out / 'fused_bag'
    try:
        counts = _quietly(getattr(d.args, 'quiet', False), lambda: run(
            d.survey.path, fused_bag, d.nodes, params_files=[out / 'params.yaml'],
            remaps=d.remaps, progress=False))
    except PipelineError as exc:
        d.add(Check('fused', 'preset', PROBLEM, None, 'm',
                    f'the preset does not run through the nodes: {exc}'))
        return
    except Exception as exc:  # rcl refuses a parameter file with its own exception types
        d.add(Check('fused', 'preset', PROBLEM, None, 'm',
                    f'the preset does not load ({failure_reason(exc)})'))
        return
    t, poses = load_odometry(fused_bag, FUSED)
    d.fused = {'outputs': counts, 'final_pose': None if not len(poses) else {
                   'x_m': round(float(poses[-1][0]), 4), 'y_m': round(float(poses[-1][1]), 4),
                   'yaw_deg': round(math.degrees(float(poses[-1][2])), 2)},
               'compared': {}, 'bag': str(fused_bag)}
    d.pose_tracks['fused'] = (t, poses)
    if len(t) < 2:
        d.add(Check('fused', 'preset', PROBLEM, float(len(t)), 'outputs',
                    f'the fusion published {plural(len(t), "estimate")} over the bag ('
                    + ', '.join(f'{topic} {n}' for topic, n in counts.items()) + ')'))
        return
    # The first output is the filter's initial state (with an absolute IMU yaw: before the
    # first orientation reached it): the comparisons anchor at the second.
    integrated = load_headings(fused_bag, IMU) if 'gyro_integrator' in d.nodes else None
    compare_fused(d, t[1:], poses[1:], integrated)
    d.add(fused_check(d, len(t)))


# The fused output this far from an input needs a reason: metres, tens of degrees (RMS).
FAR_M, FAR_DEG = 1.0, 10.0


def figures(v: dict) -> str:
    """'0.014 m / 0.30 deg RMS' (heading only: '0.30 deg RMS')."""
    position = v.get('rms_position_error_m')
    return (f'{position:.3f} m / ' if position is not None else '') + \
        f'{v["rms_heading_error_deg"]:.2f} deg RMS'


def fused_check(d: Diagnosis, outputs: int) -> Check:
    """The fused output against each input: ok where it follows them, or where it departs
    from one the report names a reason to distrust (d.distrust); a warning where it departs
    from an input and nothing says why."""
    far, explained = {}, {}
    # Where gyro_integrator runs, its heading is the gyro as the fusion gets it: the doctor's
    # own integral (one bias, read while still) is shown, not held against the output.
    nodes_gyro = any(n.endswith('(gyro_integrator\'s heading)') for n in d.fused['compared'])
    for name, v in d.fused['compared'].items():
        if name.startswith('ground truth') or (nodes_gyro and name.endswith('(gyro heading)')):
            continue
        if (v.get('rms_position_error_m') or 0.0) >= FAR_M or \
                v['rms_heading_error_deg'] >= FAR_DEG:
            base = name.removesuffix(' (gyro heading)')
            (explained if base in d.distrust else far)[name] = v
    near = '; '.join(f'{n}: {figures(v)}' for n, v in d.fused['compared'].items()
                     if n not in far and n not in explained)
    parts = [f'the preset\'s fused output ({outputs} estimates) against each input: '
             + (near or 'none close')]
    for name, v in explained.items():
        base = name.removesuffix(' (gyro heading)')
        parts.append(f'it departs from {name} ({figures(v)}) by design: {d.distrust[base]}')
    fusion = d.preset.get('complementary_fusion', {}).get('ros__parameters', {})
    imu_alone = 'imu' in fusion and not fusion.get('use_wheel_odom') and \
        not fusion.get('use_scan_match_heading')
    for name, v in far.items():
        if imu_alone and name.endswith('(gyro_integrator\'s heading)'):
            parts.append(f'it departs from {name} ({figures(v)}), the only heading it fuses: the '
                         'fusion refuses part of that input (its outlier gate, '
                         'imu.gate_probability; the refusals are counted on its /diagnostics)')
        else:
            parts.append(f'it departs from {name} ({figures(v)}) and no check says why: the '
                         'inputs disagree; compare them in the plots before trusting either')
    d.fused['distrusted'] = {n: d.distrust[n.removesuffix(' (gyro heading)')] for n in explained}
    d.fused['unexplained'] = list(far)
    return Check('fused', 'preset', WARNING if far else OK, float(outputs), 'outputs',
                 '; '.join(parts), f'within {FAR_M:g} m and {FAR_DEG:g} deg RMS of each input, '
                 'or a reason named', d.fused)
