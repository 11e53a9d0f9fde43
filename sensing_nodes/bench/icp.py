"""Speed of core.icp.match on real 360-beam scans (Freiburg 101 consecutive pairs),
single-threaded, against the textbook ICP and against small_gicp, measured in one run.

Every method gets the same raw (N, 2) arrays and the same initial guesses (the reference
perturbed by sigma 0.10 m / 5 deg, as odometry would give) and does all of its own
preprocessing (k-d tree, normals or covariances) inside the timed region.
"""

from __future__ import annotations

import json
import math
import time
from typing import Callable

import numpy as np

from sensing_nodes.bench import icp_real
from sensing_nodes.core import icp


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


def _rate(fn: Callable, pairs, guesses, repeats: int) -> float:
    """Matches per second: the best of `repeats` passes over the pairs (a shared machine only
    ever slows a pass down)."""
    best = math.inf
    for _ in range(repeats):
        start = time.perf_counter()
        for pair, guess in zip(pairs, guesses):
            fn(pair.source, pair.target, guess)
        best = min(best, time.perf_counter() - start)
    return len(pairs) / best


def _init_matrix(guess) -> np.ndarray:
    init = np.eye(4)
    c, s = math.cos(guess[2]), math.sin(guess[2])
    init[:2, :2] = [[c, -s], [s, c]]
    init[:2, 3] = guess[:2]
    return init


def _streaming_rate_ours(points, guesses, repeats: int, options: dict) -> float:
    """Scan after scan: each scan prepared once as the next keyframe, matched once as source."""
    best = math.inf
    for _ in range(repeats):
        start = time.perf_counter()
        previous = icp.prepare_target(points[0])
        for k in range(1, len(points)):
            icp.match(points[k], previous, guesses[k - 1], **options)
            previous = icp.prepare_target(points[k])
        best = min(best, time.perf_counter() - start)
    return (len(points) - 1) / best


def _streaming_rate_small_gicp(points, guesses, repeats: int, registration_type: str) -> float:
    import small_gicp

    opts = dict(icp_real.SMALL_GICP_OPTIONS)
    heights, neighbours = opts.pop('heights_m'), opts.pop('num_neighbors')
    resolution = opts.pop('downsampling_resolution')
    best = math.inf
    for _ in range(repeats):
        start = time.perf_counter()
        previous = small_gicp.preprocess_points(icp_real.lift(points[0], heights), resolution,
                                                num_neighbors=neighbours, num_threads=1)
        for k in range(1, len(points)):
            current = small_gicp.preprocess_points(icp_real.lift(points[k], heights), resolution,
                                                   num_neighbors=neighbours, num_threads=1)
            small_gicp.align(previous[0], current[0], previous[1], _init_matrix(guesses[k - 1]),
                             registration_type=registration_type, num_threads=1, **opts)
            previous = current
        best = min(best, time.perf_counter() - start)
    return (len(points) - 1) / best


def run(quick: bool = False) -> dict:
    """Matches per second of each method and the ratios ours / other, from one run."""
    pairs = icp_real.scan_pairs('freiburg-101')
    if quick:
        pairs = pairs[:40]
    guesses = icp_real.initial_guesses(pairs, 'perturbed', seed=0)
    repeats = 1 if quick else 3
    textbook_pairs = pairs[:3] if quick else pairs[:10]
    hypotheses = {'yaw_hypotheses': (-0.5, -0.25, 0.25, 0.5)}
    out: dict = {'pairs': len(pairs), 'beams': 360,
                 'source_points_mean': float(np.mean([len(p.source) for p in pairs]))}
    out['ours_matches_per_s'] = _rate(icp_real.ours(), pairs, guesses, repeats)
    out['ours_hypotheses_matches_per_s'] = _rate(icp_real.ours(hypotheses), pairs, guesses,
                                                 repeats)
    for name, kind in icp_real.SMALL_GICP_TYPES.items():
        out[f'{name}_matches_per_s'] = _rate(icp_real.small_gicp_matcher(kind), pairs, guesses,
                                             repeats)
    out['textbook_loops_matches_per_s'] = _rate(textbook_icp_loops, textbook_pairs, guesses, 1)
    out['textbook_numpy_matches_per_s'] = _rate(textbook_icp_numpy, textbook_pairs, guesses, 1)
    ours = out['ours_matches_per_s']
    out['ratio_ours_vs_textbook_loops'] = ours / out['textbook_loops_matches_per_s']
    out['ratio_ours_vs_textbook_numpy'] = ours / out['textbook_numpy_matches_per_s']
    best_sg = max(out[f'{n}_matches_per_s'] for n in icp_real.SMALL_GICP_TYPES)
    out['ratio_ours_vs_small_gicp_gicp'] = ours / out['small_gicp_gicp_matches_per_s']
    out['ratio_ours_vs_fastest_small_gicp'] = ours / best_sg
    out['ratio_ours_hypotheses_vs_small_gicp_gicp'] = (out['ours_hypotheses_matches_per_s']
                                                       / out['small_gicp_gicp_matches_per_s'])
    # Streaming, as in the node: each scan preprocessed once (keyframe), matched once (source).
    points = [pairs[0].target] + [p.source for p in pairs]
    out['streaming_ours_matches_per_s'] = _streaming_rate_ours(points, guesses, repeats, {})
    out['streaming_small_gicp_gicp_matches_per_s'] = _streaming_rate_small_gicp(
        points, guesses, repeats, 'GICP')
    out['streaming_ratio_ours_vs_small_gicp_gicp'] = (out['streaming_ours_matches_per_s']
                                                      / out['streaming_small_gicp_gicp_matches_per_s'])
    return out


if __name__ == '__main__':
    import sys

    print(json.dumps(run(quick='--quick' in sys.argv), indent=1))
