"""The fusion over recorded or simulated input streams, without ROS, and its error against
ground truth: the accuracy checks of docs/fusion.md (position m, heading deg, consistency)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from sensing_nodes.core.evaluation.metrics import express_in_reference_frame, interpolate_poses
from sensing_nodes.core.events import time_ordered
from sensing_nodes.core.fusion.config import SessionConfig, default_config
from sensing_nodes.core.fusion.ekf import EkfFusion, Outcome
from sensing_nodes.core.fusion.filter import FusedState
from sensing_nodes.core.fusion.inputs import IMU, RANK, SCAN, WHEEL, DeltaAngles, Reading
from sensing_nodes.core.fusion.session import FusionSession
from sensing_nodes.core.geometry import se2
from sensing_nodes.core.sim.inputs import FusionInputs


@dataclass(frozen=True)
class FusedTrack:
    """Fused output at each published stamp: poses (N, 3), covariances (N, 3, 3), and where
    known the variance of the heading step's error from the previous output to each (N,), rad²
    (EkfFusion.heading_step_variance; NaN at the first)."""

    t: NDArray[np.int64]
    pose: NDArray[np.float64]
    covariance: NDArray[np.float64]
    gated: int
    heading_step_variance: NDArray[np.float64] | None = None


def _yaw_only(variance: float) -> NDArray[np.float64]:
    out = np.zeros((3, 3))
    out[2, 2] = variance
    return out


def input_readings(inputs: FusionInputs, config: SessionConfig) -> list[tuple[str, Reading]]:
    """The simulated streams as the fusion's readings of its enabled inputs, in the one event
    order (core/events.py; ties: wheel, IMU, scan match), as the node reads the messages: wheel
    odometry poses, the gyro's integrated heading with its rate (imu.source rate: the IMU's raw
    rate and those summed, as ros/fusion_readings.py sums them), and scan matches as
    /scan_match/keyframe_odom carries them (EKF: in the local map's frame at the sweep's
    middle, or keyframe-relative) or cumulative with the increment covariance (complementary
    filter)."""
    raw_rate = config.method == 'ekf' and config.imu_source == 'rate'
    imu = config.input_map.get(IMU)
    delta_angles = DeltaAngles(imu.max_gap_s if imu is not None else 0.5)
    # The EKF's matches in a local map's frame are stamped at their sweep's middle.
    in_map = config.method == 'ekf' and inputs.scan_map_t.size and inputs.scan_map_t[0] >= 0
    stamps = {WHEEL: inputs.wheel_t, IMU: inputs.gyro_t,
              SCAN: inputs.scan_map_t if in_map else inputs.scan_t}
    readings = []
    previous_scan = None
    for event in time_ordered({name: stamps[name] for name in sorted(RANK, key=RANK.get)
                               if config.enabled[name]}):
        stamp, name, i = event.stamp_ns, event.source, event.index
        if name == WHEEL:
            reading = Reading(stamp, tuple(inputs.wheel_pose[i]), inputs.wheel_cov[i],
                              tuple(inputs.wheel_twist[i]), None)
        elif name == IMU and raw_rate:
            # The IMU's own rate (imu.source rate), and the rates summed (the converter's).
            rate, variance = float(inputs.raw_rate[i]), inputs.raw_rate_variance
            delta_angles.add(stamp, rate, variance)
            reading = Reading(stamp, (0.0, 0.0, delta_angles.yaw),
                              _yaw_only(delta_angles.variance), (0.0, 0.0, rate),
                              _yaw_only(variance))
        elif name == IMU:
            reading = Reading(stamp, (0.0, 0.0, float(inputs.gyro_yaw[i])),
                              _yaw_only(inputs.gyro_yaw_var[i]),
                              (0.0, 0.0, float(inputs.gyro_rate[i])), None)
        elif config.method == 'ekf' and in_map:
            local_map = int(inputs.scan_map_id[i])
            if local_map == stamp:       # the scan that starts the map: its origin
                reading = Reading(stamp, new_keyframe=True, map_ns=local_map)
            else:
                reading = Reading(stamp, tuple(inputs.scan_map_pose[i]) if local_map >= 0
                                  else None, inputs.scan_map_cov[i],
                                  map_ns=local_map if local_map >= 0 else None)
        elif config.method == 'ekf':
            kf = int(inputs.scan_keyframe_t[i])
            reading = Reading(stamp, tuple(inputs.scan_relative[i]) if kf >= 0 else None,
                              inputs.scan_relative_cov[i], keyframe_ns=kf if kf >= 0 else None,
                              new_keyframe=bool(inputs.scan_new_keyframe[i]))
        else:
            # The node's increment covariance from the matcher's twist covariance: for a match,
            # the relative covariance against its keyframe.
            increment = inputs.scan_relative_cov[i] \
                if inputs.scan_keyframe_t[i] >= 0 and previous_scan is not None else None
            reading = Reading(stamp, tuple(inputs.scan_pose[i]), inputs.scan_cov[i],
                              twist_covariance=increment)
            previous_scan = stamp
        readings.append((name, reading))
    return readings


def run_session(config: SessionConfig, readings, follow_heading_steps: bool = False
                ) -> FusedTrack:
    """The fusion session (as the node runs it) over (input name, Reading) pairs in arrival
    order, flushed at the end: every output. follow_heading_steps (EKF): with the variance of
    each output's heading step (FusedTrack.heading_step_variance)."""
    steps: list[float] = []
    out_t, out_p, out_c = [], [], []

    def on_output(stamp: int, state: FusedState) -> None:
        out_t.append(stamp)
        out_p.append(state.pose)
        out_c.append(state.covariance)
        if follow_heading_steps:
            variance = session.fusion.heading_step_variance()   # and the next step starts here
            steps.append(variance if len(out_t) > 1 else math.nan)

    session = FusionSession(config, on_output=on_output)
    if follow_heading_steps:
        assert isinstance(session.fusion, EkfFusion), 'heading steps: the EKF only'
        session.fusion.follow_heading_steps()
    for name, reading in readings:
        session.feed(name, reading)
    session.flush()
    return FusedTrack(np.array(out_t, dtype=np.int64), np.array(out_p), np.array(out_c),
                      sum(session.fusion.gated.values()),
                      np.array(steps) if follow_heading_steps else None)


class _Recording(EkfFusion):
    """The EKF, recording each reading's outcome (input, stamp ns, outcome) as it is fused."""

    def __init__(self, *args, **kwargs) -> None:
        self.outcomes: list[tuple[str, int, Outcome]] = []
        super().__init__(*args, **kwargs)

    def update(self, name, reading):
        outcome = super().update(name, reading)
        self.outcomes.append((name, reading.stamp_ns, outcome))
        return outcome


@dataclass
class RecordedRun:
    """The fused track of one EKF run (every output, its heading steps' variances), each
    reading's outcome (input, stamp ns, Outcome) and each problem the filter recorded (input,
    stamp of a refused or blamed reading)."""

    t: np.ndarray
    pose: np.ndarray
    covariance: np.ndarray
    heading_step_variance: np.ndarray
    outcomes: list = field(repr=False)
    problems: list = field(repr=False)   # (input, stamp of a refused or blamed reading)


def run_recorded(config: SessionConfig, readings) -> RecordedRun:
    """The fusion session over (input, Reading) pairs in arrival order, flushed: every output
    (the heading steps' variances followed), each reading's outcome and every problem the
    filter recorded (refused or blamed readings, by the stamp it recorded them at)."""
    fusion = _Recording(config.inputs, config.ekf)
    fusion.follow_heading_steps()
    out_t, out_p, out_c, steps = [], [], [], []
    problems: list[tuple[str, int]] = []
    seen = {name: None for name in fusion.health}

    def on_output(stamp, state) -> None:
        out_t.append(stamp)
        out_p.append(state.pose)
        out_c.append(state.covariance)
        steps.append(fusion.heading_step_variance() if len(out_t) > 1 else math.nan)

    session = FusionSession(config, fusion=fusion, on_output=on_output)
    for name, reading in readings:
        session.feed(name, reading)
        for n, health in fusion.health.items():
            if health.last_problem_ns != seen[n]:
                seen[n] = health.last_problem_ns
                problems.append((n, health.last_problem_ns))
    session.flush()
    return RecordedRun(np.array(out_t, dtype=np.int64), np.array(out_p), np.array(out_c),
                       np.array(steps), fusion.outcomes, problems)


# The evaluation scores the filter at every wheel and scan-match input: the node's output rate
# (publish_rate_hz) only thins what it publishes.
EVERY_OUTPUT = {'publish_rate_hz': 0.0}


def run_ekf(inputs: FusionInputs, config: SessionConfig | None = None) -> FusedTrack:
    """The EKF over every stream, as config (default: config/complementary_fusion.yaml with
    every output) sets it; output at each wheel and scan stamp, with the heading steps'
    variances."""
    config = config or default_config(overrides=EVERY_OUTPUT)
    assert config.method == 'ekf', config.method
    return run_session(config, input_readings(inputs, config), follow_heading_steps=True)


def run_complementary(inputs: FusionInputs, config: SessionConfig | None = None
                      ) -> FusedTrack:
    """The seed's complementary filter over the streams, as the node runs it with
    `method: complementary` (default: config/complementary_fusion.yaml with that method and
    every output)."""
    config = config or default_config(overrides={'method': 'complementary', **EVERY_OUTPUT})
    assert config.method == 'complementary', config.method
    return run_session(config, input_readings(inputs, config))


def track_errors(truth_t, truth_pose, t, poses, covariances=None,
                 heading_step_variance=None) -> dict[str, float]:
    """RMS and final position (m) and heading (deg) errors of a track whose frame starts at the
    truth's first pose; with covariances, the consistency shares; with the variance of each
    heading step's error too (FusedTrack), how far the steps depart from the truth's in units of
    the step's sigma (chatter: the largest, and the share beyond 3)."""
    reference = interpolate_poses(truth_t, truth_pose, t)
    keep = np.all(np.isfinite(reference), axis=1)
    reference, poses, t = reference[keep], poses[keep], t[keep]
    origin = tuple(truth_pose[0])
    estimate = express_in_reference_frame(origin, poses)
    error_xy = estimate[:, :2] - reference[:, :2]
    position = np.hypot(error_xy[:, 0], error_xy[:, 1])
    heading = se2.wrap_angle(estimate[:, 2] - reference[:, 2])
    out = {
        'rms_position_m': float(np.sqrt(np.mean(position ** 2))),
        'final_position_m': float(position[-1]),
        'rms_heading_deg': float(np.degrees(np.sqrt(np.mean(heading ** 2)))),
        'final_heading_deg': float(np.degrees(abs(heading[-1]))),
        'samples': int(heading.size),
    }
    if covariances is not None:
        cov = covariances[keep]
        # Covariance is in the estimate's frame (odom); errors rotated into it.
        rot = se2.rotation(-origin[2])
        e = error_xy @ rot.T
        cxy = cov[:, :2, :2] + np.eye(2) * 1e-18
        d2 = np.einsum('ni,nij,nj->n', e, np.linalg.inv(cxy), e)
        d = np.sqrt(d2)
        sigma_yaw = np.sqrt(np.maximum(cov[:, 2, 2], 1e-30))
        z = np.abs(heading) / sigma_yaw
        out.update({
            'position_within_3': float(np.mean(d <= 3.0)),
            'position_beyond_1': float(np.mean(d > 1.0)),
            'heading_within_3': float(np.mean(z <= 3.0)),
            'heading_beyond_1': float(np.mean(z > 1.0)),
        })
    if covariances is not None and heading_step_variance is not None and len(t) > 1:
        # Not from the change of the heading variance between two outputs: a prediction's
        # growth and a correction's reduction cancel in it (a step at a scan update came out at
        # thousands of its "sigma"); nor their sum: a gyro increment's update takes back most of
        # what the prediction added, and the two errors cancel too.
        est_step = se2.wrap_angle(np.diff(estimate[:, 2]))
        true_step = se2.wrap_angle(np.diff(reference[:, 2]))
        # (Outputs outside the truth's span are dropped above; the route's truth covers every
        # output, so consecutive kept outputs are consecutive outputs.)
        step_variance = heading_step_variance[keep][1:]
        step_sigma = np.sqrt(np.maximum(step_variance, 0.0) + 1e-30)
        z_step = np.abs(est_step - true_step) / step_sigma
        out['chatter_max_sigma'] = float(np.max(z_step))
        out['chatter_beyond_3'] = float(np.mean(z_step > 3.0))
    return out


POOLED_SHARES = ('position_within_3', 'position_beyond_1', 'heading_within_3',
                 'heading_beyond_1')


def pooled(runs: list[dict[str, dict[str, float]]]) -> dict[str, dict[str, float]]:
    """Figures pooled over runs (each {estimate: track_errors(...)}, e.g. 'ekf', 'scan',
    'wheel', 'gyro'): RMS position (m) and heading (deg) over every sample of every run, the
    consistency shares over every sample, and the fused RMS against the best single input's
    (position: wheel, scan; heading: gyro, scan, wheel) as `ratio_*`."""
    out: dict[str, dict[str, float]] = {}
    for name in runs[0]:
        figures = [run[name] for run in runs if isinstance(run.get(name), dict)
                   and 'samples' in run[name]]
        if not figures:
            continue
        count = sum(f['samples'] for f in figures)
        entry = {'samples': count}
        for key in ('rms_position_m', 'rms_heading_deg'):
            if key in figures[0]:
                entry[key] = math.sqrt(sum(f['samples'] * f[key] ** 2 for f in figures) / count)
        for key in POOLED_SHARES:
            if key in figures[0]:
                entry[key] = sum(f['samples'] * f[key] for f in figures) / count
        out[name] = entry
    if 'ekf' in out:
        best_position = min(out[k]['rms_position_m'] for k in ('wheel', 'scan') if k in out)
        best_heading = min(out[k]['rms_heading_deg'] for k in ('gyro', 'scan', 'wheel')
                           if k in out)
        out['ekf']['ratio_position'] = out['ekf']['rms_position_m'] / best_position
        out['ekf']['ratio_heading'] = out['ekf']['rms_heading_deg'] / best_heading
    return out


def input_errors(inputs: FusionInputs) -> dict[str, dict[str, float]]:
    """Errors of each input on its own: wheel odometry, scan matching (pose), gyro (heading)."""
    truth_t, truth_pose = inputs.truth_t, inputs.truth_pose
    gyro = np.column_stack([np.zeros((len(inputs.gyro_t), 2)), inputs.gyro_yaw])
    g = track_errors(truth_t, truth_pose, inputs.gyro_t, gyro)
    return {
        'wheel': track_errors(truth_t, truth_pose, inputs.wheel_t, inputs.wheel_pose),
        'scan': track_errors(truth_t, truth_pose, inputs.scan_t, inputs.scan_pose),
        'gyro': {k: v for k, v in g.items() if 'heading' in k or k == 'samples'},
    }



def keyframe_match_consistency(truth_t, truth_pose, keyframe_t, stamps, relative,
                               relative_cov) -> dict[str, float]:
    """How the scan matcher's keyframe-relative matches (m, rad; keyframe_t -1: no match) meet
    their covariances against ground truth: mean squared Mahalanobis distance (3 when
    consistent), RMS heading z, and the correlation of the heading errors of consecutive
    matches against the same keyframe (0 when independent, as the filter takes them)."""
    ok = np.asarray(keyframe_t) >= 0
    kf_t, t = np.asarray(keyframe_t)[ok], np.asarray(stamps)[ok]
    at_kf = interpolate_poses(truth_t, truth_pose, kf_t)
    at_scan = interpolate_poses(truth_t, truth_pose, t)
    truth_rel = np.array([se2.between(tuple(a), tuple(b)) for a, b in zip(at_kf, at_scan)])
    err = np.asarray(relative)[ok] - truth_rel
    err[:, 2] = se2.wrap_angle(err[:, 2])
    cov = np.asarray(relative_cov)[ok]
    d2 = np.einsum('ni,nij,nj->n', err, np.linalg.inv(cov), err)
    same = kf_t[1:] == kf_t[:-1]
    corr = float(np.corrcoef(err[:-1, 2][same], err[1:, 2][same])[0, 1]) \
        if np.count_nonzero(same) > 2 else float('nan')
    return {'mean_distance2': float(np.mean(d2)),
            'heading_z_rms': float(np.sqrt(np.mean(err[:, 2] ** 2 / cov[:, 2, 2]))),
            'heading_error_correlation': corr,
            'matches_per_keyframe': float(len(kf_t) / max(len(np.unique(kf_t)), 1))}


def map_match_consistency(truth_t, truth_pose, stamps, map_id, pose, covariance,
                          window: int = 10, distances_m=(1.0, 2.0, 3.0, 4.0, 6.0)
                          ) -> dict[str, float]:
    """How the scan matcher's poses in its local map (m, rad, at stamps ns; map_id -1: no
    match, equal to the stamp: the map's origin) meet their covariances against ground truth
    (the map's frame is base_link at its origin's stamp): mean squared Mahalanobis distance (3
    when consistent; /3 is the covariance's scale), RMS heading z, the correlation of
    consecutive heading errors, and the part of the error that varies slowly with the
    distance travelled: the means of `window` consecutive matches, half the variance of their
    differences per axis against the distance between them (bins at distances_m, m) fitted
    with a line, whose slope is a random walk per metre (x and y m^2/m, yaw rad^2/m) and whose
    intercept the window means' own noise."""
    stamps, map_id = np.asarray(stamps), np.asarray(map_id)
    ok = (map_id >= 0) & (map_id != stamps)
    at = interpolate_poses(truth_t, truth_pose, stamps[ok])
    origin = interpolate_poses(truth_t, truth_pose, map_id[ok])
    keep = np.all(np.isfinite(at), axis=1) & np.all(np.isfinite(origin), axis=1)
    at, origin = at[keep], origin[keep]
    truth_rel = np.array([se2.between(tuple(a), tuple(b)) for a, b in zip(origin, at)])
    err = np.asarray(pose)[ok][keep] - truth_rel
    err[:, 2] = se2.wrap_angle(err[:, 2])
    cov = np.asarray(covariance)[ok][keep]
    d2 = np.einsum('ni,nij,nj->n', err, np.linalg.inv(cov), err)
    out = {'mean_distance2': float(np.mean(d2)),
           'heading_z_rms': float(np.sqrt(np.mean(err[:, 2] ** 2 / cov[:, 2, 2]))),
           'heading_error_correlation': float(np.corrcoef(err[:-1, 2], err[1:, 2])[0, 1])}
    # Slowly varying part: window means against the distance along the true path.
    path = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(at[:, :2], axis=0).T))])
    n = err.shape[0] // window
    means = err[:n * window].reshape(n, window, 3).mean(axis=1)
    where = path[:n * window].reshape(n, window).mean(axis=1)
    i, j = np.triu_indices(n, 1)
    apart = where[j] - where[i]
    half = 0.5 * (means[j] - means[i]) ** 2
    edges = np.asarray(distances_m)
    centres, xy, yaw = [], [], []
    for low, high in zip(edges[:-1], edges[1:]):
        in_bin = (apart >= low) & (apart < high)
        if np.count_nonzero(in_bin) < 10:
            continue
        centres.append(float(np.mean(apart[in_bin])))
        xy.append(float(np.mean(half[in_bin, :2])))
        yaw.append(float(np.mean(half[in_bin, 2])))
    if len(centres) >= 2:
        slope_xy, intercept_xy = np.polyfit(centres, xy, 1)
        slope_yaw, _ = np.polyfit(centres, yaw, 1)
        out.update({'drift_xy_m2_per_m': float(slope_xy),
                    'drift_yaw_rad2_per_m': float(slope_yaw),
                    'window_mean_xy_m2': float(intercept_xy)})
    return out


def heading_increment_consistency(truth_t, truth_pose, t, yaw, variance_per_s: float,
                                  every: int = 20) -> dict[str, float]:
    """How the heading increments of a differential yaw input (rad, every `every`-th sample)
    meet a white-noise model of variance_per_s (rad^2/s) against ground truth: RMS z (1 when
    consistent), share beyond 3 sigma, largest error (rad)."""
    t, yaw = np.asarray(t)[::every], np.asarray(yaw)[::every]
    reference = interpolate_poses(truth_t, truth_pose, t)
    err = se2.wrap_angle(np.diff(yaw) - np.diff(reference[:, 2]))
    z = err / np.sqrt(variance_per_s * np.diff(t) * 1e-9)
    return {'z_rms': float(np.sqrt(np.mean(z ** 2))), 'beyond_3': float(np.mean(np.abs(z) > 3)),
            'max_error_rad': float(np.max(np.abs(err)))}



def stop_corrections(truth_t, truth_pose, t, yaw, bias, bias_variance, still,
                     lead_s: float = 0.6) -> list[dict[str, float]]:
    """What an integrating gyro's re-estimates at stops did to its heading (rad, stamps ns,
    bias rad/s): for every still period after the first (the first calibration), its start and
    end (s after the truth's first stamp), the heading error (deg, against ground truth) lead_s
    before it (ahead of the stillness window's step back) and at its end, the change of the
    bias estimate (rad/s) and its standard deviation before and at the end (rad/s)."""
    t, still = np.asarray(t), np.asarray(still, dtype=bool)
    origin = tuple(truth_pose[0])
    reference = interpolate_poses(truth_t, truth_pose, t)
    estimate = express_in_reference_frame(
        origin, np.column_stack([np.zeros((t.size, 2)), np.asarray(yaw)]))
    error = np.degrees(se2.wrap_angle(estimate[:, 2] - reference[:, 2]))
    edges = np.diff(np.concatenate([[0], still.astype(np.int8), [0]]))
    starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1) - 1
    out = []
    for first, last in list(zip(starts, ends))[1:]:
        before = int(np.searchsorted(t, t[first] - int(lead_s * 1e9)))
        out.append({'start_s': float((t[first] - truth_t[0]) * 1e-9),
                    'end_s': float((t[last] - truth_t[0]) * 1e-9),
                    'heading_error_before_deg': float(error[before]),
                    'heading_error_after_deg': float(error[last]),
                    'bias_change_rad_s': float(bias[last] - bias[before]),
                    'bias_std_before_rad_s': float(math.sqrt(bias_variance[before])),
                    'bias_std_after_rad_s': float(math.sqrt(bias_variance[last]))})
    return out
