"""sensing_fusion_eval: the fusion's accuracy on the simulated robot, without ROS (docs/fusion.md's
figures): for each seed of each simulator configuration, the package's wheel odometry, gyro
integrator and scan matcher (icp_matcher's default, the local map; --matcher-mode keyframe for
the lesson's) over core-simulated sensors (core/sim/inputs.py), then the fusion session as the
node runs it (the EKF and the seed's complementary filter; every output, publish_rate_hz 0),
scored against the ground truth (core/evaluation/fusion.py): RMS and final errors (m, deg),
consistency shares, heading-step chatter and each input's own errors, per seed and pooled over
the seeds of each configuration (RMS over every sample of every run; the fused RMS against the
best single input's; the consistency shares over every sample).

    sensing_fusion_eval [--seeds 8] [--configs default,strong_errors] [--params-file FILE]
                        [--matcher-mode local_map] [--inputs] [--json OUT]
    sensing_fusion_eval --faults [--seeds 1] [--params-file FILE]

With --faults, the fault catalogue instead (core/evaluation/faults.py: each fault injected into
the default route's first 40 s, seed 0 and up; docs/fusion.md "Integrity").
"""

from __future__ import annotations

import argparse
import json
import sys

from sensing_nodes.core.evaluation.fusion import (
    EVERY_OUTPUT,
    heading_increment_consistency,
    input_errors,
    keyframe_match_consistency,
    map_match_consistency,
    pooled,
    run_complementary,
    run_ekf,
    stop_corrections,
    track_errors,
)
from sensing_nodes.core.fusion.config import SessionConfig, default_config
from sensing_nodes.core.fusion.inputs import IMU
from sensing_nodes.core.sim.inputs import FusionInputs, simulated_inputs
from sensing_nodes.core.sim.simulator import params_from_dict
from sensing_nodes.parameters import ParameterError, load_parameters
from sensing_nodes.paths import config_file

EXIT_BAD_INPUT = 2


def _rounded(figures: dict[str, float]) -> dict[str, float]:
    return {k: round(v, 4) if abs(v) >= 1e-3 else float(f'{v:.2e}') for k, v in figures.items()}


def score(inputs: FusionInputs, ekf: SessionConfig, complementary: SessionConfig) -> dict:
    """Each input's errors, the EKF's and the complementary filter's, and the EKF's gate
    refusals, on one simulated run."""
    track = run_ekf(inputs, ekf)
    comp = run_complementary(inputs, complementary)
    return {**input_errors(inputs),
            'ekf': track_errors(inputs.truth_t, inputs.truth_pose, track.t, track.pose,
                                track.covariance, track.heading_step_variance),
            'complementary': track_errors(inputs.truth_t, inputs.truth_pose, comp.t, comp.pose,
                                          comp.covariance),
            'gated': track.gated}


def input_figures(inputs: FusionInputs, ekf: SessionConfig) -> dict:
    """How the gyro's heading increments and the scan matches meet the noise models the EKF
    gives them, and what gyro_integrator's bias re-estimates at stops did to its heading."""
    imu = ekf.input_map[IMU]
    in_map = inputs.scan_map_t.size and inputs.scan_map_t[0] >= 0
    return {
        # As the filter reads them: delay-compensated (InputConfig.heading_delay_s).
        'gyro_increments': heading_increment_consistency(
            inputs.truth_t, inputs.truth_pose, inputs.gyro_t,
            inputs.gyro_yaw + inputs.gyro_rate * imu.heading_delay_s,
            imu.noise.yaw_variance_per_s),
        'scan_matches': map_match_consistency(
            inputs.truth_t, inputs.truth_pose, inputs.scan_map_t, inputs.scan_map_id,
            inputs.scan_map_pose, inputs.scan_map_cov) if in_map else keyframe_match_consistency(
            inputs.truth_t, inputs.truth_pose, inputs.scan_keyframe_t, inputs.scan_t,
            inputs.scan_relative, inputs.scan_relative_cov),
        'stop_corrections': stop_corrections(
            inputs.truth_t, inputs.truth_pose, inputs.gyro_t, inputs.gyro_yaw,
            inputs.gyro_bias, inputs.gyro_bias_var, inputs.gyro_still),
    }


def _print_row(row: dict) -> None:
    e, c = row['ekf'], row['complementary']
    print(f"{row['config']} seed {row['seed']}: RMS position ekf {e['rms_position_m']:.4f} "
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
    if 'gyro_increments' in row:
        print('  gyro 0.1 s increments:', _rounded(row['gyro_increments']),
              '| scan matches:', _rounded(row['scan_matches']), flush=True)
        for stop in row['stop_corrections']:
            print(f"  integrator at the stop {stop['start_s']:.1f}-{stop['end_s']:.1f} s:"
                  f" heading error {stop['heading_error_before_deg']:+.3f} -> "
                  f"{stop['heading_error_after_deg']:+.3f} deg, bias "
                  f"{stop['bias_change_rad_s']:+.1e} rad/s (std "
                  f"{stop['bias_std_before_rad_s']:.1e} -> "
                  f"{stop['bias_std_after_rad_s']:.1e})", flush=True)


def _print_pooled(name: str, figures: dict) -> None:
    e = figures['ekf']
    best = {k: figures[k] for k in ('wheel', 'scan', 'gyro') if k in figures}
    print(f"{name} pooled over {e['samples']} fused samples: RMS position ekf "
          f"{e['rms_position_m']:.5f} m ({e['ratio_position']:.2f}x the best input; wheel "
          f"{best['wheel']['rms_position_m']:.5f}, scan {best['scan']['rms_position_m']:.5f}) "
          f"| RMS heading ekf {e['rms_heading_deg']:.4f} deg ({e['ratio_heading']:.2f}x; gyro "
          f"{best['gyro']['rms_heading_deg']:.4f}, scan {best['scan']['rms_heading_deg']:.4f}, "
          f"wheel {best['wheel']['rms_heading_deg']:.4f}) | within 3 / beyond 1: position "
          f"{e['position_within_3']:.3f} / {e['position_beyond_1']:.3f}, heading "
          f"{e['heading_within_3']:.3f} / {e['heading_beyond_1']:.3f}", flush=True)


def _faults(config, seeds: int, json_path: str | None) -> int:
    """Print (and with json_path write) the fault catalogue's figures per seed."""
    from sensing_nodes.core.evaluation.faults import CATALOGUE, CATALOGUE_SECONDS, fault_figures
    from sensing_nodes.core.sim.simulator import SimParams, simulate
    from sensing_nodes.core.sim.world import load_world

    world = load_world(config_file('default_world.yaml'))
    out = {}
    for seed in range(seeds):
        figures = fault_figures(simulate(SimParams(), world, CATALOGUE_SECONDS, seed), config,
                                list(CATALOGUE))
        out[seed] = figures
        clean = figures['none']
        print(f"seed {seed}, no fault: RMS position {clean['rms_position_m'] * 1e3:.2f} mm, "
              f"heading {clean['rms_heading_deg']:.4f} deg")
        for kind, f in figures.items():
            if kind == 'none':
                continue
            refused = '' if f['wrong_matches'] == 0 else \
                f", wrong matches refused {f['wrong_refused']:.0%} of {f['wrong_matches']}"
            print(f"  {kind:14s} RMS position {f['position_ratio']:.2f}x, heading "
                  f"{f['heading_ratio']:.2f}x the fault-free run's; named after "
                  f"{f['named_after_s']:.2f} s, in use again after "
                  f"{f['in_use_again_after_s']:.2f} s{refused}; largest heading step "
                  f"{f['step_max_sigma']:.1f} sigma, position {f['position_max_sigma']:.1f} sigma")
    if json_path:
        with open(json_path, 'w') as f:
            json.dump(out, f, indent=1, default=float)
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog='sensing_fusion_eval', description=__doc__.split('\n\n')[0],
        formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('--seeds', type=int, default=8)
    parser.add_argument('--configs', default='default,strong_errors',
                        help='simulator configurations: default, or NAME for '
                             'config/bags_NAME.yaml (comma separated)')
    parser.add_argument('--params-file', action='append', default=[],
                        help="complementary_fusion parameters over its config/ file's "
                             '(repeatable; the EKF with them, and the complementary filter)')
    parser.add_argument('--matcher-mode', default='local_map', choices=('local_map', 'keyframe'),
                        help="icp_matcher's mode for the scan matches (default: its default)")
    parser.add_argument('--json', help='write every figure here')
    parser.add_argument('--faults', action='store_true',
                        help="the fault catalogue (docs/fusion.md's Integrity) instead, on the "
                             "default route's first 40 s, for --seeds seeds")
    parser.add_argument('--inputs', action='store_true',
                        help="also print how the gyro's heading increments and the scan "
                             "matches meet the noise models the filter gives them")
    args = parser.parse_args(argv)
    try:
        ekf = default_config(*args.params_file, overrides={'method': 'ekf', **EVERY_OUTPUT})
        complementary = default_config(*args.params_file,
                                       overrides={'method': 'complementary', **EVERY_OUTPUT})
    except ParameterError as error:
        print(f'sensing_fusion_eval: {error}', file=sys.stderr)
        return EXIT_BAD_INPUT
    if args.faults:
        return _faults(ekf, args.seeds, args.json)
    rows, summary = [], {}
    for name in args.configs.split(','):
        params = None if name == 'default' else params_from_dict(
            load_parameters('sensor_sim', config_file(f'bags_{name}.yaml')))
        runs = []
        for seed in range(args.seeds):
            inputs = simulated_inputs(seed, params, matcher_mode=args.matcher_mode)
            row = {'config': name, 'seed': seed, **score(inputs, ekf, complementary)}
            if args.inputs:
                row.update(input_figures(inputs, ekf))
            rows.append(row)
            runs.append(row)
            _print_row(row)
        summary[name] = pooled(runs)
        _print_pooled(name, summary[name])
    if args.json:
        with open(args.json, 'w') as f:
            json.dump({'runs': rows, 'pooled': summary}, f, indent=1)
    return 0


if __name__ == '__main__':
    sys.exit(main())
