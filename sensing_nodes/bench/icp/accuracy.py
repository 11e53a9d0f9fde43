"""The scan matchers' accuracy against each dataset's reference: CARMEN pairs (ours against
small_gicp, two initial-guess regimes), the simulated route and worlds against the simulator's
ground truth (drift alone, each mode's RMS errors pooled over seeds, deskewing on a route turning
at 1 rad/s, the corridor), and the local map beside KISS-ICP on the CARMEN logs and simulated
runs (`make bench` area icp_kiss)."""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import numpy as np

from sensing_nodes.bench.icp import comparators as cmp
from sensing_nodes.bench.icp import datasets, scoring
from sensing_nodes.core.evaluation.fusion import run_ekf, track_errors
from sensing_nodes.core.evaluation.metrics import express_in_reference_frame, interpolate_poses
from sensing_nodes.core.geometry.se2 import between, wrap_angle
from sensing_nodes.core.scan_matching import ScanEvent, ScanMatcherSettings, ScanStatus
from sensing_nodes.core.sim.inputs import (
    inputs_from_run,
    match_scans,
    matcher_settings,
    scan_inputs,
)
from sensing_nodes.core.sim.simulator import SimParams, SimRun

# --- carmen-pairs -----------------------------------------------------------------------------


def evaluate(logs: tuple[str, ...] = datasets.PAIR_LOGS, stride: int = 1, seed: int = 0,
             directory: Path | None = None,
             methods: dict | None = None) -> dict[str, dict[str, dict[str, dict]]]:
    """{log: {regime: {method: summary}}} over every stride-th consecutive pair of each log."""
    methods = methods or cmp.pair_matchers()
    table: dict = {}
    for name in logs:
        pairs = datasets.scan_pairs(name, directory, stride)
        table[name] = {}
        for regime in datasets.REGIMES:
            guesses = datasets.initial_guesses(pairs, regime, seed)
            table[name][regime] = {}
            for method, matcher in methods.items():
                trans, rot, seconds = scoring.pair_errors(pairs, guesses, matcher)
                table[name][regime][method] = {**scoring.pair_summary(trans, rot),
                                               'seconds': seconds}
    return table


def pairs_table(table: dict) -> str:
    """Markdown table of evaluate()'s output."""
    lines = [
        '| log | regime | method | median trans (m) | median rot (deg) | failure rate | pairs |',
        '|---|---|---|---|---|---|---|',
    ]
    for name, regimes in table.items():
        for regime, methods in regimes.items():
            for method, s in methods.items():
                lines.append(f"| {name} | {regime} | {method} | {s['median_translation_m']:.4f} | "
                             f"{s['median_rotation_deg']:.3f} | {s['failure_rate']:.3f} | "
                             f"{s['pairs']} |")
    return '\n'.join(lines)


# --- sim --------------------------------------------------------------------------------------

def route_drift(seed: int = 0, laps: float = 1.0, settings: ScanMatcherSettings | None = None,
                params: SimParams | None = None) -> dict:
    """The matcher alone (constant-velocity prediction and deskewing, no odometry) over `laps`
    of the route. Returns the path length (m), final and maximum position error (m), the final
    error as a fraction of the path length, the final heading error (deg) and the step counts."""
    run = datasets.simulated_run(seed, laps, params)
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
    start = time.process_time()
    stamps, steps = match_scans(run, settings, odometry=odometry, deskew=deskew)
    spent = time.process_time() - start
    errors = track_errors(run.truth_t, run.truth_pose, stamps,
                          np.array([step.pose for step in steps]))
    errors['fallback'] = sum(step.status is ScanStatus.FALLBACK for step in steps)
    errors['cpu_ms_per_scan_with_odometry'] = 1e3 * spent / max(len(steps), 1)
    return errors


def seeds_table(seeds: int = 8) -> dict:
    """Each mode over `seeds` seeds of the default route, predicted and deskewed by the wheel
    odometry (as the node's config and the fusion's inputs): per-seed and pooled RMS errors."""
    out: dict = {}
    for mode in ('local_map', 'keyframe'):
        rows = []
        for seed in range(seeds):
            run = datasets.simulated_run(seed)
            rows.append(route_errors(run, matcher_settings(run.params, mode=mode)))
        out[mode] = {'seeds': rows, **scoring.pooled_rms(rows)}
    return out


def deskew_table(seeds: int = 2) -> dict:
    """The fast-turns route (1 rad/s) with a 10 Hz sweep: the local-map matcher's pooled RMS
    heading with and without deskewing, guided by the odometry and by its own velocity."""
    params = dataclasses.replace(SimParams(), route=datasets.FAST_TURNS_ROUTE)
    out: dict = {}
    for guide in ('odometry', 'own_velocity'):
        for deskew in (True, False):
            rows = []
            for seed in range(seeds):
                run = datasets.simulated_run(seed, params=params)
                rows.append(route_errors(run, matcher_settings(params),
                                         odometry=guide == 'odometry', deskew=deskew))
            name = f"{guide}_{'deskewed' if deskew else 'not_deskewed'}"
            out[name] = {**scoring.pooled_rms(rows),
                         'fallback': sum(row['fallback'] for row in rows)}
        out[f'{guide}_ratio'] = (out[f'{guide}_deskewed']['pooled_rms_heading_deg']
                                 / out[f'{guide}_not_deskewed']['pooled_rms_heading_deg'])
    return out


def corridor_table(seeds: int = 4) -> dict:
    """The corridor world (config/corridor_world.yaml), 30 m along it at 0.5 m/s: per seed the
    RMS and final along-corridor (x) and RMS across (y) errors (m) of the wheel odometry, the
    matcher (predicted by the wheels) and today's EKF over them (core.evaluation.fusion), the
    smallest along / across variance ratio of the matcher's relative covariances, and how many
    matches were degenerate."""
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
        run = datasets.world_run('corridor', seed)
        inputs = inputs_from_run(run)
        track = run_ekf(inputs)
        stamps, steps = match_scans(run, matcher_settings(run.params))
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


def sim(quick: bool = False) -> dict:
    """The simulated route's tables: the matcher alone, each mode, deskewing, the corridor."""
    return {'alone': route_drift(laps=1.0), 'modes': seeds_table(2 if quick else 8),
            'fast_turns': deskew_table(1 if quick else 2),
            'corridor': corridor_table(1 if quick else 4)}


# --- the local map beside KISS-ICP ------------------------------------------------------------

def kiss_log_figures(bag: Path | None, settings: ScanMatcherSettings = datasets.CARMEN_SETTINGS,
                     voxels: tuple[float, ...] = cmp.KISS_VOXELS_M) -> dict:
    """{estimator: figures} of one CARMEN log's bag (datasets.carmen_bag), scored at the
    reference's stamps, or {'error': why}."""
    from sensing_nodes.tools.eval import load_trajectories

    if bag is None:
        return dict(datasets.NOT_CONVERTED)
    tracks = load_trajectories(bag, ['/ground_truth/odom', '/odom'])
    ref_t, ref_poses = tracks['/ground_truth/odom']
    inputs = datasets.bag_inputs(datasets.bag_messages(bag), settings)
    figures = {'odometry': scoring.scores(ref_t, ref_poses, ref_t, ref_poses, *tracks['/odom'])}
    for estimator, (t, poses, ms) in cmp.estimators(inputs, settings, voxels).items():
        figures[estimator] = scoring.scores(ref_t, ref_poses, ref_t, ref_poses, t, poses) | {
            'ms_per_scan': ms}
    figures['scans'] = len(inputs)
    return figures


def kiss_sim_figures(seeds: int = 2, world: str = '',
                     voxels: tuple[float, ...] = cmp.KISS_VOXELS_M) -> dict:
    """{estimator: figures} on the simulated default route (one lap, the wheel odometry's
    guess), or one loop of an open-space world (datasets.WORLDS), pooled over seeds: ATE and
    heading RMS as RMS over seeds, RPE and ms as means."""
    rows: dict[str, list[dict]] = {}
    for seed in range(seeds):
        run = datasets.world_run(world, seed) if world else datasets.simulated_run(seed)
        inputs = scan_inputs(run)
        scan_t = np.array([i[0] for i in inputs], dtype=np.int64)
        truth = run.truth_at(scan_t)
        for estimator, (t, poses, ms) in cmp.estimators(inputs, matcher_settings(run.params),
                                                        voxels).items():
            row = scoring.scores(run.truth_t, run.truth_pose, scan_t, truth, t, poses)
            row['rms_heading_deg'] = track_errors(run.truth_t, run.truth_pose, t,
                                                  poses)['rms_heading_deg']
            rows.setdefault(estimator, []).append(row | {'ms_per_scan': ms})
    out: dict = {}
    for estimator, per_seed in rows.items():
        out[estimator] = {key: (scoring.pooled(per_seed, key)
                                if key in ('ate_rmse_m', 'rms_heading_deg')
                                else float(np.mean([r[key] for r in per_seed])))
                          for key in per_seed[0]}
    out['seeds'] = seeds
    return out


def kiss_table(results: dict) -> str:
    """One row per log: ATE, consecutive RPE mean and ms per scan of each estimator run."""
    ran = [e for e in cmp.ESTIMATORS if any(e in figures for figures in results.values())]
    head = ' | '.join(f'{e} ATE (m) | {e} RPE (m / deg) | {e} ms' for e in ran)
    lines = [f'| log | odometry ATE (m) | {head} |', '|---|---|' + '---|---|---|' * len(ran)]
    for log, figures in results.items():
        if 'error' in figures:
            lines.append(f"| {log} | cannot be scored: {figures['error']} |")
            continue
        odometry = figures.get('odometry', {}).get('ate_rmse_m')
        cells = [f'{odometry:.3f}' if odometry is not None else '']
        for e in ran:
            f = figures[e]
            cells += [f"{f['ate_rmse_m']:.3f}",
                      f"{f['rpe_translation_mean_m']:.4f} / {f['rpe_rotation_mean_deg']:.3f}",
                      f"{f['ms_per_scan']:.2f}"]
        lines.append(f"| {log} | {' | '.join(cells)} |")
    return '\n'.join(lines)


def run_kiss_area(quick: bool = False) -> dict:
    """`make bench` area icp_kiss (ACES, Freiburg 101 and one seed when quick)."""
    import tempfile

    logs = datasets.CARMEN_LOGS[:2] if quick else datasets.CARMEN_LOGS
    with tempfile.TemporaryDirectory() as out:
        results = {name: kiss_log_figures(datasets.carmen_bag(name, Path(out))) for name in logs}
    results['sim'] = kiss_sim_figures(1 if quick else 2)
    for world in ('hall', 'outdoor'):
        results[f'sim_{world}'] = kiss_sim_figures(1 if quick else 2, world)
    return scoring.flatten(results, skip=('relations', 'scans', 'seeds'))
