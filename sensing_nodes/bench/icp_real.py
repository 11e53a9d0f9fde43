"""Accuracy of scan matching on real CARMEN logs: ours against small_gicp, in one run.

Consecutive scan pairs: source = scan k+1, target = scan k, reference = between(pose_k, pose_k+1)
of the logs' corrected laser poses. Two initial-guess regimes: identity, and the reference
perturbed by seeded Gaussian noise (sigma 0.10 m per axis, 5 deg). A pair fails when its
translation error exceeds 0.10 m or its rotation error 2 deg.
"""

from __future__ import annotations

import json
import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
from numpy.typing import NDArray

from sensing_nodes.bags.carmen import read_carmen
from sensing_nodes.core import icp
from sensing_nodes.core.geometry.scan import scan_to_points
from sensing_nodes.core.geometry.se2 import Pose2, between, wrap_angle

# Range reported for "no return" in each log (see the dataset README); ranges at or above it are
# invalid, not walls 50 m away.
NO_RETURN_M = {'aces': 50.0, 'freiburg-101': 81.91}
LOGS = ('aces', 'freiburg-101')
FAIL_TRANSLATION_M = 0.10
FAIL_ROTATION_RAD = math.radians(2.0)
GUESS_SIGMA_M = 0.10
GUESS_SIGMA_RAD = math.radians(5.0)
REGIMES = ('identity', 'perturbed')

# Our matcher's settings for real keyframe pairs (about 1 m and 10-20 deg apart): a coarse match
# from the guess and from four yaw offsets (+-14, +-29 deg), the best-scoring one refined.
# 'ours_local' is the plain local match (the node's setting, where odometry gives the guess).
OURS_OPTIONS: dict = {'yaw_hypotheses': (-0.5, -0.25, 0.25, 0.5)}
# small_gicp settings: the best of a grid tried on these logs (see docs/nodes/icp_matcher.md).
SMALL_GICP_OPTIONS = {
    'downsampling_resolution': 0.05,
    'max_correspondence_distance': 1.0,
    'max_iterations': 50,
    'heights_m': (-0.1, 0.0, 0.1),
    'num_neighbors': 10,
}
SMALL_GICP_TYPES = {'small_gicp_icp': 'ICP', 'small_gicp_plane_icp': 'PLANE_ICP',
                    'small_gicp_gicp': 'GICP'}


def carmen_dir(repo: str | Path | None = None) -> Path:
    """The shared CARMEN directory, located as <repo>/../shared/datasets/carmen."""
    root = Path(repo) if repo is not None else Path(__file__).resolve().parents[2]
    return (root / '..' / 'shared' / 'datasets' / 'carmen').resolve()


@dataclass
class ScanPair:
    """Source = scan k+1, target = scan k, as (N, 2) laser-frame points (m); reference pose of
    the source in the target frame (m, rad)."""

    source: NDArray[np.float64]
    target: NDArray[np.float64]
    reference: Pose2


def log_points(path: Path, no_return_m: float) -> tuple[list[NDArray[np.float64]], list[Pose2]]:
    """Every FLASER scan of a log as laser-frame points, with the laser pose of each."""
    log = read_carmen(path)
    points, poses = [], []
    for scan in log.scans:
        angles = log.scan_angles(scan.ranges.size)
        ranges = np.where(scan.ranges >= no_return_m, np.inf, scan.ranges)
        points.append(scan_to_points(ranges, angles, 0.01, no_return_m)[0])
        poses.append(scan.pose)
    return points, poses


def scan_pairs(name: str, directory: Path | None = None, stride: int = 1) -> list[ScanPair]:
    """Consecutive pairs (k, k+1) of a log, every `stride`-th pair."""
    directory = directory or carmen_dir()
    points, poses = log_points(directory / f'{name}-corrected.log.gz', NO_RETURN_M[name])
    return [ScanPair(points[k + 1], points[k], between(poses[k], poses[k + 1]))
            for k in range(0, len(points) - 1, stride)]


def initial_guesses(pairs: list[ScanPair], regime: str, seed: int = 0) -> NDArray[np.float64]:
    """(P, 3) initial guesses: zeros, or each reference plus seeded Gaussian noise."""
    if regime == 'identity':
        return np.zeros((len(pairs), 3))
    rng = np.random.default_rng(seed)
    reference = np.array([p.reference for p in pairs])
    noise = rng.normal(size=(len(pairs), 3)) * (GUESS_SIGMA_M, GUESS_SIGMA_M, GUESS_SIGMA_RAD)
    return reference + noise


Matcher = Callable[[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]], Pose2]


def ours(options: dict | None = None) -> Matcher:
    """core.icp.match with the given options, as a matcher function."""
    opts = {**OURS_OPTIONS, **(options or {})}
    target_keys = {'normal_neighbours', 'normal_radius', 'min_planarity', 'tangent_weight',
                   'search'}
    target_opts = {k: opts.pop(k) for k in list(opts) if k in target_keys}

    def run(source, target, guess):
        r = icp.match(source, icp.prepare_target(target, **target_opts), guess, **opts)
        return (r.x, r.y, r.yaw)
    return run


def lift(points: NDArray[np.float64], heights: tuple[float, ...]) -> NDArray[np.float64]:
    """2-D points copied at each height as (N·H, 3), so 3-D normals and covariances exist."""
    return np.vstack([np.column_stack((points, np.full(len(points), h))) for h in heights])


def small_gicp_matcher(registration_type: str, options: dict | None = None) -> Matcher:
    """small_gicp.align on lifted points; its 4x4 result is projected to (x, y, yaw)."""
    import small_gicp

    opts = {**SMALL_GICP_OPTIONS, **(options or {})}
    heights = tuple(opts.pop('heights_m'))
    neighbours = int(opts.pop('num_neighbors'))
    resolution = float(opts.pop('downsampling_resolution'))

    def run(source, target, guess):
        tgt, tree = small_gicp.preprocess_points(lift(target, heights), resolution,
                                                 num_neighbors=neighbours, num_threads=1)
        src, _ = small_gicp.preprocess_points(lift(source, heights), resolution,
                                              num_neighbors=neighbours, num_threads=1)
        init = np.eye(4)
        c, s = math.cos(guess[2]), math.sin(guess[2])
        init[:2, :2] = [[c, -s], [s, c]]
        init[:2, 3] = guess[:2]
        result = small_gicp.align(tgt, src, tree, init, registration_type=registration_type,
                                  num_threads=1, **opts)
        t = result.T_target_source
        return (float(t[0, 3]), float(t[1, 3]), math.atan2(t[1, 0], t[0, 0]))
    return run


def errors(pairs: list[ScanPair], guesses: NDArray[np.float64],
           matcher: Matcher) -> tuple[NDArray[np.float64], NDArray[np.float64], float]:
    """Translation (m) and rotation (rad) error of each pair, and seconds spent matching."""
    trans, rot = np.zeros(len(pairs)), np.zeros(len(pairs))
    start = time.perf_counter()
    for i, (pair, guess) in enumerate(zip(pairs, guesses)):
        est = matcher(pair.source, pair.target, guess)
        trans[i] = math.hypot(est[0] - pair.reference[0], est[1] - pair.reference[1])
        rot[i] = abs(wrap_angle(est[2] - pair.reference[2]))
    return trans, rot, time.perf_counter() - start


def summary(trans: NDArray[np.float64], rot: NDArray[np.float64]) -> dict:
    """Median errors (m, deg) and failure rate (> 0.10 m or > 2 deg)."""
    failed = (trans > FAIL_TRANSLATION_M) | (rot > FAIL_ROTATION_RAD)
    return {
        'median_translation_m': float(np.median(trans)),
        'median_rotation_deg': float(np.degrees(np.median(rot))),
        'failure_rate': float(failed.mean()),
        'pairs': int(trans.size),
    }


def matchers(include_small_gicp: bool = True) -> dict[str, Matcher]:
    """The methods compared: ours, ours without yaw hypotheses (the node's setting) with
    neighbours from the scans' bearing order (the default) and from a k-d tree (the same
    neighbours: a check), and small_gicp's ICP, plane-ICP and GICP."""
    out = {'ours': ours(), 'ours_local': ours({'yaw_hypotheses': ()}),
           'ours_local_kd_tree': ours({'yaw_hypotheses': (), 'search': 'kd_tree'})}
    if include_small_gicp:
        out.update({name: small_gicp_matcher(kind) for name, kind in SMALL_GICP_TYPES.items()})
    return out


def evaluate(logs: tuple[str, ...] = LOGS, stride: int = 1, seed: int = 0,
             directory: Path | None = None,
             methods: dict[str, Matcher] | None = None) -> dict[str, dict[str, dict[str, dict]]]:
    """{log: {regime: {method: summary}}} over every stride-th consecutive pair of each log."""
    methods = methods or matchers()
    table: dict = {}
    for name in logs:
        pairs = scan_pairs(name, directory, stride)
        table[name] = {}
        for regime in REGIMES:
            guesses = initial_guesses(pairs, regime, seed)
            table[name][regime] = {}
            for method, matcher in methods.items():
                trans, rot, seconds = errors(pairs, guesses, matcher)
                table[name][regime][method] = {**summary(trans, rot), 'seconds': seconds}
    return table


def best_competitor(results: dict[str, dict]) -> dict:
    """Best median translation, median rotation and failure rate over small_gicp's methods."""
    others = [v for k, v in results.items() if not k.startswith('ours')]
    return {key: min(v[key] for v in others)
            for key in ('median_translation_m', 'median_rotation_deg', 'failure_rate')}


def format_table(table: dict) -> str:
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


def run(quick: bool = False) -> dict:
    """Flat figures for the benchmark aggregator: every log x regime x method summary."""
    table = evaluate(stride=5 if quick else 1)
    flat = {}
    for name, regimes in table.items():
        for regime, methods in regimes.items():
            for method, s in methods.items():
                for key, value in s.items():
                    flat[f'{name}.{regime}.{method}.{key}'] = value
    return flat


if __name__ == '__main__':
    stride = int(sys.argv[1]) if len(sys.argv) > 1 else 1
    result = evaluate(stride=stride)
    print(format_table(result))
    print(json.dumps(result))
