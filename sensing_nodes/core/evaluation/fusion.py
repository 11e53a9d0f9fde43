"""The fusion over recorded or simulated input streams, without ROS, and its error against
ground truth: the accuracy checks of docs/fusion.md (position m, heading deg, consistency)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import yaml
from numpy.typing import NDArray

from sensing_nodes.core.evaluation.metrics import express_in_reference_frame, interpolate_poses
from sensing_nodes.core.fusion.complementary import ComplementaryFusion, FusionSettings
from sensing_nodes.core.fusion.ekf import (
    INPUT_DEFAULTS,
    EkfFusion,
    EkfSettings,
    InputConfig,
    Reading,
    input_config,
)
from sensing_nodes.core.geometry import se2
from sensing_nodes.core.sim.inputs import FusionInputs
from sensing_nodes.paths import config_file

WHEEL, GYRO, SCAN = 0, 1, 2   # processing rank at equal stamps (as the node)


def inputs_from_params(params: dict) -> tuple[InputConfig, ...]:
    """The EKF inputs a complementary_fusion parameter dict (as in its YAML file) configures,
    the IMU as gyro_integrator's heading unless imu.source says otherwise."""
    use = {'wheel_odom': params.get('use_wheel_odom', True), 'imu': params.get('use_imu', True),
           'scan_match': params.get('use_scan_match_position', True)
           or params.get('use_scan_match_heading', True)}
    max_gap_s = float(params.get('max_gap_s', 2.0))
    return tuple(
        input_config(name, {k: v for k, v in params.get(name, {}).items()
                            if k in INPUT_DEFAULTS[name]},
                     keyframes=name == 'scan_match', max_gap_s=max_gap_s,
                     gyro_bias=name == 'imu' and params.get('imu', {}).get('source') == 'rate')
        for name in ('wheel_odom', 'imu', 'scan_match') if use[name])


def default_inputs() -> tuple[InputConfig, ...]:
    """The EKF inputs of config/complementary_fusion.yaml."""
    with open(config_file('complementary_fusion.yaml')) as f:
        params = yaml.safe_load(f)['complementary_fusion']['ros__parameters']
    return inputs_from_params(params)


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


def _events(inputs: FusionInputs) -> list[tuple[int, int, int]]:
    return sorted([(int(t), WHEEL, i) for i, t in enumerate(inputs.wheel_t)]
                  + [(int(t), GYRO, i) for i, t in enumerate(inputs.gyro_t)]
                  + [(int(t), SCAN, i) for i, t in enumerate(inputs.scan_t)])


def run_ekf(inputs: FusionInputs, configs: tuple[InputConfig, ...] | None = None,
            settings: EkfSettings | None = None) -> FusedTrack:
    """The EKF over every stream in stamp order; output at each wheel and scan stamp."""
    ekf = EkfFusion(configs or default_inputs(), settings)
    ekf.follow_heading_steps()
    names = {cfg.name for cfg in ekf.inputs.values()}
    out_t, out_p, out_c, out_step = [], [], [], []
    for stamp, kind, i in _events(inputs):
        if kind == WHEEL and 'wheel_odom' in names:
            ekf.update('wheel_odom', Reading(
                stamp, tuple(inputs.wheel_pose[i]), inputs.wheel_cov[i],
                tuple(inputs.wheel_twist[i]), None))
        elif kind == GYRO and 'imu' in names:
            cfg = ekf.inputs['imu']
            rate = inputs.raw_rate[i] if cfg.gyro_bias else inputs.gyro_rate[i]
            var = np.zeros((3, 3))
            var[2, 2] = inputs.gyro_yaw_var[i]
            ekf.update('imu', Reading(
                stamp, (0.0, 0.0, float(inputs.gyro_yaw[i])), var, (0.0, 0.0, float(rate)),
                None))
            continue
        elif kind == SCAN and 'scan_match' in names:
            kf = int(inputs.scan_keyframe_t[i])
            ekf.update('scan_match', Reading(
                stamp, tuple(inputs.scan_relative[i]) if kf >= 0 else None,
                inputs.scan_relative_cov[i], keyframe_ns=kf if kf >= 0 else None,
                new_keyframe=bool(inputs.scan_new_keyframe[i])))
        else:
            continue
        state = ekf.state
        out_t.append(stamp)
        out_p.append(state.pose)
        out_c.append(state.covariance)
        step_variance = ekf.heading_step_variance()    # and the next step starts here
        out_step.append(step_variance if len(out_t) > 1 else math.nan)
    return FusedTrack(np.array(out_t, dtype=np.int64), np.array(out_p), np.array(out_c),
                      sum(ekf.gated.values()), np.array(out_step))


def run_complementary(inputs: FusionInputs, settings: FusionSettings | None = None
                      ) -> FusedTrack:
    """The seed's complementary filter over the streams (as the node feeds it)."""
    fusion = ComplementaryFusion(settings or FusionSettings(max_gap_s=2.0))
    out_t, out_p, out_c = [], [], []
    previous_scan = None
    for stamp, kind, i in _events(inputs):
        if kind == WHEEL:
            fusion.add_wheel(stamp, tuple(inputs.wheel_pose[i]), inputs.wheel_cov[i])
        elif kind == GYRO:
            fusion.add_gyro(stamp, float(inputs.gyro_yaw[i]), float(inputs.gyro_yaw_var[i]))
            continue
        else:
            # The node's increment covariance from the matcher's twist covariance: for a match,
            # the relative covariance against its keyframe.
            inc = inputs.scan_relative_cov[i] if inputs.scan_keyframe_t[i] >= 0 else None
            fusion.add_scan_match(stamp, tuple(inputs.scan_pose[i]), inputs.scan_cov[i],
                                  inc if previous_scan is not None else None)
            previous_scan = stamp
        state = fusion.state
        out_t.append(stamp)
        out_p.append(state.pose)
        out_c.append(state.covariance)
    return FusedTrack(np.array(out_t, dtype=np.int64), np.array(out_p), np.array(out_c), 0)


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


def input_errors(inputs: FusionInputs) -> dict[str, dict[str, float]]:
    """Errors of each input on its own: wheel odometry, scan matching (pose), gyro (heading)."""
    truth_t, truth_pose = inputs.truth_t, inputs.truth_pose
    gyro = np.column_stack([np.zeros((len(inputs.gyro_t), 2)), inputs.gyro_yaw])
    g = track_errors(truth_t, truth_pose, inputs.gyro_t, gyro)
    return {
        'wheel': track_errors(truth_t, truth_pose, inputs.wheel_t, inputs.wheel_pose),
        'scan': track_errors(truth_t, truth_pose, inputs.scan_t, inputs.scan_pose),
        'gyro': {k: v for k, v in g.items() if 'heading' in k},
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


def _rounded(figures: dict[str, float]) -> dict[str, float]:
    return {k: round(v, 4) if abs(v) >= 1e-3 else float(f'{v:.2e}') for k, v in figures.items()}


def main(argv: list[str] | None = None) -> int:
    """Table of fused (EKF and complementary) and per-input errors over seeds of the default
    route and of the strong_errors configuration (docs/fusion.md's figures)."""
    import argparse
    import json

    from sensing_nodes.core.sim.inputs import simulated_inputs
    from sensing_nodes.core.sim.simulator import load_params_file, params_from_dict

    parser = argparse.ArgumentParser(description=main.__doc__)
    parser.add_argument('--seeds', type=int, default=8)
    parser.add_argument('--configs', default='default,strong_errors')
    parser.add_argument('--json', help='write every figure here')
    parser.add_argument('--inputs', action='store_true',
                        help="also print how the gyro's heading increments and the scan "
                             "matches meet the noise models the filter gives them")
    args = parser.parse_args(argv)
    rows = []
    run_configs = default_inputs()
    for name in args.configs.split(','):
        params = None if name == 'default' else params_from_dict(
            load_params_file(config_file(f'bags_{name}.yaml')))
        for seed in range(args.seeds):
            inputs = simulated_inputs(seed, params)
            track = run_ekf(inputs)
            comp = run_complementary(inputs)
            row = {'config': name, 'seed': seed, **input_errors(inputs),
                   'ekf': track_errors(inputs.truth_t, inputs.truth_pose, track.t, track.pose,
                                       track.covariance, track.heading_step_variance),
                   'complementary': track_errors(inputs.truth_t, inputs.truth_pose, comp.t,
                                                 comp.pose, comp.covariance),
                   'gated': track.gated}
            rows.append(row)
            e, c = row['ekf'], row['complementary']
            print(f"{name} seed {seed}: RMS position ekf {e['rms_position_m']:.4f} "
                  f"complementary {c['rms_position_m']:.4f} wheel "
                  f"{row['wheel']['rms_position_m']:.4f} scan {row['scan']['rms_position_m']:.4f}"
                  f" | RMS heading ekf {e['rms_heading_deg']:.4f} complementary "
                  f"{c['rms_heading_deg']:.4f} gyro {row['gyro']['rms_heading_deg']:.4f} scan "
                  f"{row['scan']['rms_heading_deg']:.4f} wheel "
                  f"{row['wheel']['rms_heading_deg']:.4f} | within 3 / beyond 1: position "
                  f"{e['position_within_3']:.3f} / {e['position_beyond_1']:.3f}, heading "
                  f"{e['heading_within_3']:.3f} / {e['heading_beyond_1']:.3f} | heading steps "
                  f"beyond 3 sigma {100 * e['chatter_beyond_3']:.3f} %, largest "
                  f"{e['chatter_max_sigma']:.1f} sigma", flush=True)
            if args.inputs:
                imu = next(c for c in run_configs if c.name == 'imu')
                # As the filter reads them: delay-compensated (InputConfig.heading_delay_s).
                row['gyro_increments'] = heading_increment_consistency(
                    inputs.truth_t, inputs.truth_pose, inputs.gyro_t,
                    inputs.gyro_yaw + inputs.gyro_rate * imu.heading_delay_s,
                    imu.noise.yaw_variance_per_s)
                row['scan_matches'] = keyframe_match_consistency(
                    inputs.truth_t, inputs.truth_pose, inputs.scan_keyframe_t, inputs.scan_t,
                    inputs.scan_relative, inputs.scan_relative_cov)
                row['stop_corrections'] = stop_corrections(
                    inputs.truth_t, inputs.truth_pose, inputs.gyro_t, inputs.gyro_yaw,
                    inputs.gyro_bias, inputs.gyro_bias_var, inputs.gyro_still)
                print('  gyro 0.1 s increments:', _rounded(row['gyro_increments']),
                      '| scan matches:', _rounded(row['scan_matches']), flush=True)
                for stop in row['stop_corrections']:
                    print(f"  integrator at the stop {stop['start_s']:.1f}-{stop['end_s']:.1f} s:"
                          f" heading error {stop['heading_error_before_deg']:+.3f} -> "
                          f"{stop['heading_error_after_deg']:+.3f} deg, bias "
                          f"{stop['bias_change_rad_s']:+.1e} rad/s (std "
                          f"{stop['bias_std_before_rad_s']:.1e} -> "
                          f"{stop['bias_std_after_rad_s']:.1e})", flush=True)
    if args.json:
        with open(args.json, 'w') as f:
            json.dump(rows, f, indent=1)
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
