"""The scan matcher on the simulated default route against the simulator's ground truth: its
drift alone (no odometry), its RMS errors with the wheel odometry's guess pooled over seeds,
each mode side by side, and what deskewing the sweep is worth on a route turning at 1 rad/s."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np

from sensing_nodes.core.evaluation.fusion import track_errors
from sensing_nodes.core.geometry.se2 import between, wrap_angle
from sensing_nodes.core.scan_matching import ScanEvent, ScanMatcherSettings, ScanStatus
from sensing_nodes.core.sim.inputs import match_scans, matcher_settings
from sensing_nodes.core.sim.simulator import SimParams, SimRun, make_route, simulate
from sensing_nodes.core.sim.world import load_world
from sensing_nodes.paths import config_file

# The default route with every turn in place at 1 rad/s (57.3 deg/s): the deskewing benchmark.
FAST_TURNS_ROUTE = ('wait 6', 'straight 2.0 0.25', 'turn 90 57.2958', 'straight 2.0 0.25',
                    'turn 180 57.2958', 'wait 2', 'turn -360 57.2958', 'straight 2.0 0.25',
                    'turn 90 57.2958', 'wait 3')


def simulated_run(seed: int = 0, laps: float = 1.0, params: SimParams | None = None) -> SimRun:
    """`laps` of the route of params (default: the default route) in the default world."""
    params = params or SimParams()
    return simulate(params, load_world(config_file('default_world.yaml')),
                    laps * make_route(params).period_s, seed)


def _loop(long_m: float, short_m: float, speed_m_s: float) -> tuple[str, ...]:
    """A rectangular loop to the left at speed_m_s, turning in place at 45 deg/s."""
    leg = ('straight {} %g' % speed_m_s, 'turn 90 45')
    return ('wait 2', *(part.format(length) for length in (long_m, short_m, long_m, short_m)
                        for part in leg), 'wait 1')


# Open spaces (docs/nodes/icp_matcher.md): a world file and the simulated robot's parameters
# there, a 40 m laser (360 beams, 1 deg apart, as the default) driving a loop at 1 m/s.
WORLDS = {
    # An 80 m x 50 m hall, walls 20-45 m from a 12 m x 8 m loop, pillars and booths.
    'hall': ('hall_world.yaml', {'start_x_m': -6.0, 'start_y_m': -4.0,
                                 'route': _loop(12.0, 8.0, 1.0), 'range_max_m': 40.0}),
    # Sparse posts, bushes and two building fronts around a 20 m x 12 m loop, 3 cm range noise.
    'outdoor': ('outdoor_world.yaml', {'start_x_m': -10.0, 'start_y_m': -6.0,
                                       'route': _loop(20.0, 12.0, 1.0), 'range_max_m': 40.0,
                                       'range_noise_std_m': 0.03}),
}


def world_run(world: str, seed: int = 0) -> SimRun:
    """One loop of a WORLDS scenario."""
    name, overrides = WORLDS[world]
    params = dataclasses.replace(SimParams(), **overrides)
    return simulate(params, load_world(config_file(name)), make_route(params).period_s, seed)


def route_drift(seed: int = 0, laps: float = 1.0, settings: ScanMatcherSettings | None = None,
                params: SimParams | None = None) -> dict:
    """The matcher alone (constant-velocity prediction and deskewing, no odometry) over `laps`
    of the route. Returns the path length (m), final and maximum position error (m), the final
    error as a fraction of the path length, the final heading error (deg) and the step counts."""
    run = simulated_run(seed, laps, params)
    stamps, steps = match_scans(run, settings or matcher_settings(run.params), odometry=False)
    truth = run.truth_at(stamps)
    estimates = np.array([step.pose for step in steps])
    statuses: dict[str, int] = {}
    for step in steps:
        statuses[step.status] = statuses.get(step.status, 0) + 1
    reference = np.array([between(tuple(truth[0]), tuple(p)) for p in truth])
    position_error = np.hypot(*(estimates[:, :2] - reference[:, :2]).T)
    path = float(np.hypot(*np.diff(truth[:, :2], axis=0).T).sum())
    return {
        'path_length_m': path,
        'final_position_error_m': float(position_error[-1]),
        'max_position_error_m': float(position_error.max()),
        'final_drift_fraction': float(position_error[-1] / path),
        'final_heading_error_deg': float(np.degrees(abs(wrap_angle(estimates[-1, 2]
                                                                   - reference[-1, 2])))),
        'scans': int(len(stamps)),
        **{f'steps_{k}': v for k, v in sorted(statuses.items())},
    }


def route_errors(run: SimRun, settings: ScanMatcherSettings, odometry: bool = True,
                 deskew: bool = True) -> dict:
    """RMS and final position (m) and heading (deg) errors of the matcher over a run (as
    core.evaluation.fusion scores each input), the failed matches and the CPU time per scan."""
    import time

    start = time.process_time()
    stamps, steps = match_scans(run, settings, odometry=odometry, deskew=deskew)
    spent = time.process_time() - start
    errors = track_errors(run.truth_t, run.truth_pose, stamps,
                          np.array([step.pose for step in steps]))
    errors['fallback'] = sum(step.status is ScanStatus.FALLBACK for step in steps)
    errors['cpu_ms_per_scan_with_odometry'] = 1e3 * spent / max(len(steps), 1)
    return errors


def pooled(rows: list[dict], key: str) -> float:
    """RMS over runs of equal length of a per-run RMS figure."""
    return math.sqrt(float(np.mean([row[key] ** 2 for row in rows])))


def seeds_table(seeds: int = 8) -> dict:
    """Each mode over `seeds` seeds of the default route, predicted and deskewed by the wheel
    odometry (as the node's config and the fusion's inputs): per-seed and pooled RMS errors."""
    out: dict = {}
    for mode in ('local_map', 'keyframe'):
        rows = []
        for seed in range(seeds):
            run = simulated_run(seed)
            rows.append(route_errors(run, matcher_settings(run.params, mode=mode)))
        out[mode] = {'seeds': rows,
                     'pooled_rms_heading_deg': pooled(rows, 'rms_heading_deg'),
                     'pooled_rms_position_m': pooled(rows, 'rms_position_m')}
    return out


def deskew_table(seeds: int = 2) -> dict:
    """The fast-turns route (1 rad/s) with a 10 Hz sweep: the local-map matcher's pooled RMS
    heading with and without deskewing, guided by the odometry and by its own velocity."""
    params = dataclasses.replace(SimParams(), route=FAST_TURNS_ROUTE)
    out: dict = {}
    for guide in ('odometry', 'own_velocity'):
        for deskew in (True, False):
            rows = []
            for seed in range(seeds):
                run = simulated_run(seed, params=params)
                rows.append(route_errors(run, matcher_settings(params),
                                         odometry=guide == 'odometry', deskew=deskew))
            name = f"{guide}_{'deskewed' if deskew else 'not_deskewed'}"
            out[name] = {'pooled_rms_heading_deg': pooled(rows, 'rms_heading_deg'),
                         'pooled_rms_position_m': pooled(rows, 'rms_position_m'),
                         'fallback': sum(row['fallback'] for row in rows)}
        out[f'{guide}_ratio'] = (out[f'{guide}_deskewed']['pooled_rms_heading_deg']
                                 / out[f'{guide}_not_deskewed']['pooled_rms_heading_deg'])
    return out


CORRIDOR_ROUTE = ('wait 3', 'straight 30 0.5', 'wait 2')


def corridor_table(seeds: int = 4) -> dict:
    """The corridor world (config/corridor_world.yaml), 30 m along it at 0.5 m/s: per seed the
    RMS and final along-corridor (x) and RMS across (y) errors (m) of the wheel odometry, the
    matcher (predicted by the wheels) and today's EKF over them (core.evaluation.fusion), the
    smallest along / across variance ratio of the matcher's relative covariances, and how many
    matches were degenerate."""
    from sensing_nodes.core.evaluation.fusion import run_ekf
    from sensing_nodes.core.evaluation.metrics import (
        express_in_reference_frame,
        interpolate_poses,
    )
    from sensing_nodes.core.sim.inputs import inputs_from_run

    params = dataclasses.replace(SimParams(), start_x_m=-20.0, start_y_m=0.0,
                                 route=CORRIDOR_ROUTE)
    world = load_world(config_file('corridor_world.yaml'))

    def errors(inputs, t, poses):
        reference = interpolate_poses(inputs.truth_t, inputs.truth_pose, t)
        keep = np.all(np.isfinite(reference), axis=1)
        error = (express_in_reference_frame(tuple(inputs.truth_pose[0]), poses)[keep]
                 - reference[keep])
        return {'along_rms_m': float(np.sqrt(np.mean(error[:, 0] ** 2))),
                'along_final_m': float(abs(error[-1, 0])),
                'across_rms_m': float(np.sqrt(np.mean(error[:, 1] ** 2)))}

    rows = []
    for seed in range(seeds):
        run = simulate(params, world, make_route(params).period_s, seed)
        inputs = inputs_from_run(run)
        track = run_ekf(inputs)
        stamps, steps = match_scans(run, matcher_settings(params))
        ratios = [step.keyframe.covariance[0, 0] / step.keyframe.covariance[1, 1]
                  for step in steps if step.keyframe is not None]
        rows.append({'seed': seed,
                     'wheels': errors(inputs, inputs.wheel_t, inputs.wheel_pose),
                     'matcher': errors(inputs, inputs.scan_t, inputs.scan_pose),
                     'fused': errors(inputs, track.t, track.pose),
                     'min_along_over_across_variance': float(min(ratios)),
                     'degenerate': sum(ScanEvent.DEGENERATE in step.events for step in steps),
                     'matches': len(ratios)})
    return {'seeds': rows}


def run(quick: bool = False) -> dict:
    """Figures for the benchmark aggregator."""
    out = {f'alone_{k}': v for k, v in route_drift(laps=1.0).items()}
    table = seeds_table(2 if quick else 8)
    for mode, figures in table.items():
        out[f'{mode}_pooled_rms_heading_deg'] = figures['pooled_rms_heading_deg']
        out[f'{mode}_pooled_rms_position_m'] = figures['pooled_rms_position_m']
    for name, figures in deskew_table(1 if quick else 2).items():
        if isinstance(figures, dict):
            for key, value in figures.items():
                out[f'fast_turns_{name}_{key}'] = value
        else:
            out[f'fast_turns_{name}'] = figures
    for row in corridor_table(1 if quick else 4)['seeds']:
        for source in ('wheels', 'matcher', 'fused'):
            for key, value in row[source].items():
                out[f"corridor_seed{row['seed']}_{source}_{key}"] = value
        out[f"corridor_seed{row['seed']}_min_variance_ratio"] = \
            row['min_along_over_across_variance']
    return out


if __name__ == '__main__':
    import sys

    print(json.dumps(run(quick='--quick' in sys.argv), indent=1))
