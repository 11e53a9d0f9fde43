"""Speed of core.icp.match on real 360-beam scans (Freiburg 101 consecutive pairs),
single-threaded, against the textbook ICP and against small_gicp, measured in one run.

Rates come from this process's CPU time (time.process_time), methods interleaved pair by pair:
wall time on the shared 2-core machine swings with other people's work. Every method gets the
same raw (N, 2) arrays and the same initial guesses (the reference
perturbed by sigma 0.10 m / 5 deg, as odometry would give) and does all of its own
preprocessing (k-d tree, normals or covariances) inside the timed region.
"""

from __future__ import annotations

import json
import math
import os
import time
from typing import Callable

import numpy as np

from sensing_nodes.bench import icp_real
from sensing_nodes.core import icp
from sensing_nodes.core.geometry.se2 import compose, inverse
from sensing_nodes.core.scan_matching import LocalMapScanMatcher, ScanMatcherSettings
from sensing_nodes.core.sim.simulator import SimParams, make_route


def textbook_icp_loops(source, target, initial=(0.0, 0.0, 0.0), iterations: int = 20):
    """The lesson's ICP: brute-force nearest neighbour written as loops over the points, the
    closed-form SVD step, a fixed number of iterations. Returns (x, y, yaw)."""
    c, s = math.cos(initial[2]), math.sin(initial[2])
    r = np.array([[c, -s], [s, c]])
    t = np.array(initial[:2], dtype=float)
    target_list = [tuple(q) for q in np.asarray(target, dtype=float)]
    for _ in range(iterations):
        moved = np.asarray(source) @ r.T + t
        pairs = []
        for px, py in moved:
            best, best_d = None, math.inf
            for qx, qy in target_list:
                d = (px - qx) ** 2 + (py - qy) ** 2
                if d < best_d:
                    best, best_d = (qx, qy), d
            pairs.append(best)
        r_step, t_step = icp.align_paired(moved, np.array(pairs))
        r, t = r_step @ r, r_step @ t + t_step
    return float(t[0]), float(t[1]), math.atan2(r[1, 0], r[0, 0])


def textbook_icp_numpy(source, target, initial=(0.0, 0.0, 0.0), iterations: int = 20):
    """The same textbook ICP with the brute-force search vectorised (full distance matrix)."""
    c, s = math.cos(initial[2]), math.sin(initial[2])
    r = np.array([[c, -s], [s, c]])
    t = np.array(initial[:2], dtype=float)
    target = np.asarray(target, dtype=float)
    for _ in range(iterations):
        moved = np.asarray(source) @ r.T + t
        d2 = ((moved[:, None, :] - target[None, :, :]) ** 2).sum(axis=2)
        r_step, t_step = icp.align_paired(moved, target[d2.argmin(axis=1)])
        r, t = r_step @ r, r_step @ t + t_step
    return float(t[0]), float(t[1]), math.atan2(r[1, 0], r[0, 0])


def _rates(methods: dict[str, Callable], pairs, guesses, repeats: int) -> dict[str, float]:
    """Matches per second of each method, from CPU time of this process (a shared machine's other
    load barely touches it), the methods interleaved pair by pair so that any remaining
    disturbance hits all of them alike; the best of `repeats` passes."""
    best = {name: math.inf for name in methods}
    for _ in range(repeats):
        spent = dict.fromkeys(methods, 0.0)
        for pair, guess in zip(pairs, guesses):
            for name, fn in methods.items():
                start = time.process_time()
                fn(pair.source, pair.target, guess)
                spent[name] += time.process_time() - start
        best = {name: min(best[name], spent[name]) for name in methods}
    return {name: len(pairs) / seconds for name, seconds in best.items()}


def _init_matrix(guess) -> np.ndarray:
    init = np.eye(4)
    c, s = math.cos(guess[2]), math.sin(guess[2])
    init[:2, :2] = [[c, -s], [s, c]]
    init[:2, 3] = guess[:2]
    return init


def _streaming_rates(points, guesses, repeats: int, options: dict,
                     registration_type: str, search: str = 'bearing') -> tuple[float, float]:
    """Scan after scan, as in the node: each scan prepared once (ours: bearing order or k-d tree,
    and normals, as the next keyframe; small_gicp: preprocess_points) and matched once as the
    source. Matches per second of ours and of small_gicp, interleaved scan by scan, CPU time,
    best of `repeats`."""
    import small_gicp

    opts = dict(icp_real.SMALL_GICP_OPTIONS)
    heights, neighbours = opts.pop('heights_m'), opts.pop('num_neighbors')
    resolution = opts.pop('downsampling_resolution')

    def preprocess(scan):
        return small_gicp.preprocess_points(icp_real.lift(scan, heights), resolution,
                                            num_neighbors=neighbours, num_threads=1)

    best_ours = best_sg = math.inf
    for _ in range(repeats):
        start = time.process_time()
        ours_previous = icp.prepare_target(points[0], search=search)
        ours_spent = time.process_time() - start
        start = time.process_time()
        sg_previous = preprocess(points[0])
        sg_spent = time.process_time() - start
        for k in range(1, len(points)):
            start = time.process_time()
            icp.match(points[k], ours_previous, guesses[k - 1], **options)
            ours_previous = icp.prepare_target(points[k], search=search)
            ours_spent += time.process_time() - start
            start = time.process_time()
            current = preprocess(points[k])
            small_gicp.align(sg_previous[0], current[0], sg_previous[1],
                             _init_matrix(guesses[k - 1]), registration_type=registration_type,
                             num_threads=1, **opts)
            sg_previous = current
            sg_spent += time.process_time() - start
        best_ours, best_sg = min(best_ours, ours_spent), min(best_sg, sg_spent)
    return (len(points) - 1) / best_ours, (len(points) - 1) / best_sg


def _local_map_streaming_rate(points, guesses, repeats: int) -> float:
    """The local-map matcher streaming over the same scans and guesses as _streaming_rates (the
    guess as the odometry's motion, the laser at base_link, scans 1 s apart): matches per
    second, CPU time, best of `repeats`."""
    settings = ScanMatcherSettings(laser_pose=(0.0, 0.0, 0.0), max_gap_s=10.0)
    best = math.inf
    for _ in range(repeats):
        matcher = LocalMapScanMatcher(settings)
        start = time.process_time()
        for k, scan in enumerate(points):
            guess = tuple(guesses[k - 1]) if k else None
            matcher.process(k * 1_000_000_000, scan, guess)
        best = min(best, time.process_time() - start)
    return (len(points) - 1) / best


def simulated_streaming(seconds: float = 60.0, repeats: int = 3) -> dict:
    """Per 360-beam scan of the simulated route (10 Hz, a 0.1 s sweep, the wheel odometry's
    guess and sweep motion, as the node runs): CPU ms per scan of each mode and of small_gicp's
    GICP on the same scans (scan to scan, the odometry's guess), interleaved pass by pass, best
    of `repeats`."""
    import small_gicp

    from sensing_nodes.bench.icp_sim import simulated_run
    from sensing_nodes.core.scan_matching import make_scan_matcher
    from sensing_nodes.core.sim.inputs import matcher_settings, scan_inputs

    run = simulated_run(seed=0, laps=seconds / make_route(SimParams()).period_s)
    inputs = scan_inputs(run)
    opts = dict(icp_real.SMALL_GICP_OPTIONS)
    heights, neighbours = opts.pop('heights_m'), opts.pop('num_neighbors')
    resolution = opts.pop('downsampling_resolution')
    laser = matcher_settings(run.params).laser_pose
    best = {'local_map': math.inf, 'keyframe': math.inf, 'small_gicp_gicp': math.inf}
    for _ in range(repeats):
        for mode in ('local_map', 'keyframe'):
            matcher = make_scan_matcher(matcher_settings(run.params, mode=mode))
            start = time.process_time()
            for args in inputs:
                matcher.process(*args)
            best[mode] = min(best[mode], time.process_time() - start)
        start = time.process_time()
        previous = None
        for stamp, scan, motion, _, _ in inputs:
            current = small_gicp.preprocess_points(icp_real.lift(scan, heights), resolution,
                                                   num_neighbors=neighbours, num_threads=1)
            if previous is not None:
                guess = compose(compose(inverse(laser), motion or (0.0, 0.0, 0.0)), laser)
                small_gicp.align(previous[0], current[0], previous[1], _init_matrix(guess),
                                 registration_type='GICP', num_threads=1, **opts)
            previous = current
        best['small_gicp_gicp'] = min(best['small_gicp_gicp'], time.process_time() - start)
    return {f'simulated_{name}_ms_per_scan': 1e3 * spent / len(inputs)
            for name, spent in best.items()} | {'simulated_scans': len(inputs)}


def run(quick: bool = False) -> dict:
    """Matches per second of each method and the ratios ours / other, from one run."""
    pairs = icp_real.scan_pairs('freiburg-101')
    if quick:
        pairs = pairs[:40]
    guesses = icp_real.initial_guesses(pairs, 'perturbed', seed=0)
    # Best of five interleaved passes: the shared machine's load swings within a run.
    repeats = 1 if quick else 5
    textbook_pairs = pairs[:3] if quick else pairs[:10]
    hypotheses = dict(icp_real.OURS_OPTIONS)
    out: dict = {'pairs': len(pairs), 'beams': 360,
                 'source_points_mean': float(np.mean([len(p.source) for p in pairs])),
                 'load_average_1min_start': os.getloadavg()[0]}
    local = {'yaw_hypotheses': ()}          # the node's setting: odometry gives the guess
    methods = {'ours': icp_real.ours(local), 'ours_hypotheses': icp_real.ours(hypotheses)}
    methods.update({name: icp_real.small_gicp_matcher(kind)
                    for name, kind in icp_real.SMALL_GICP_TYPES.items()})
    for name, rate in _rates(methods, pairs, guesses, repeats).items():
        out[f'{name}_matches_per_s'] = rate
    textbook = {'textbook_loops': textbook_icp_loops, 'textbook_numpy': textbook_icp_numpy,
                'ours_on_textbook_pairs': icp_real.ours(local)}
    for name, rate in _rates(textbook, textbook_pairs, guesses, 1).items():
        out[f'{name}_matches_per_s'] = rate
    ours = out['ours_matches_per_s']
    # Against the textbook on the same (first) pairs, measured in the same interleaved pass.
    ours_t = out['ours_on_textbook_pairs_matches_per_s']
    out['ratio_ours_vs_textbook_loops'] = ours_t / out['textbook_loops_matches_per_s']
    out['ratio_ours_vs_textbook_numpy'] = ours_t / out['textbook_numpy_matches_per_s']
    best_sg = max(out[f'{n}_matches_per_s'] for n in icp_real.SMALL_GICP_TYPES)
    out['ratio_ours_vs_small_gicp_gicp'] = ours / out['small_gicp_gicp_matches_per_s']
    out['ratio_ours_vs_fastest_small_gicp'] = ours / best_sg
    out['ratio_ours_hypotheses_vs_small_gicp_gicp'] = (out['ours_hypotheses_matches_per_s']
                                                       / out['small_gicp_gicp_matches_per_s'])
    # Streaming, as in the node: each scan preprocessed once (keyframe), matched once (source).
    points = [pairs[0].target] + [p.source for p in pairs]
    out['streaming_ours_matches_per_s'], out['streaming_small_gicp_gicp_matches_per_s'] = \
        _streaming_rates(points, guesses, repeats, {}, 'GICP')
    out['streaming_ratio_ours_vs_small_gicp_gicp'] = (
        out['streaming_ours_matches_per_s'] / out['streaming_small_gicp_gicp_matches_per_s']
    )
    # The local-map matcher over the same stream (each scan inserted: they are 1 m apart).
    out['streaming_local_map_matches_per_s'] = _local_map_streaming_rate(points, guesses,
                                                                         repeats)
    out['streaming_ratio_local_map_vs_keyframe'] = (out['streaming_local_map_matches_per_s']
                                                    / out['streaming_ours_matches_per_s'])
    out.update(simulated_streaming(20.0 if quick else 60.0, 1 if quick else 3))
    # The same with neighbours from a k-d tree (the same neighbours, found more slowly:
    # core/icp.prepare_target), against a second small_gicp pass.
    tree, sg_again = _streaming_rates(points, guesses, repeats, {}, 'GICP', search='kd_tree')
    out['streaming_ours_kd_tree_matches_per_s'] = tree
    out['streaming_ratio_ours_kd_tree_vs_small_gicp_gicp'] = tree / sg_again
    out['load_average_1min_end'] = os.getloadavg()[0]
    return out


if __name__ == '__main__':
    import sys

    print(json.dumps(run(quick='--quick' in sys.argv), indent=1))
