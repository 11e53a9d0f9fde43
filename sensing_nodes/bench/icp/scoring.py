"""How the ICP benchmark scores: pair errors and failures against a reference pose, ATE and RPE
of a trajectory as sensing_eval scores it, RMS pooled over seeds, and CPU time (this process's,
time.process_time: wall time on a shared machine swings with other people's work), best of
repeated passes."""

from __future__ import annotations

import math
import time
from typing import Callable

import numpy as np
from numpy.typing import NDArray

from sensing_nodes.core.evaluation.metrics import (
    absolute_trajectory_error,
    relations_from_trajectory,
    relative_pose_errors,
)
from sensing_nodes.core.geometry.se2 import wrap_angle

FAIL_TRANSLATION_M = 0.10
FAIL_ROTATION_RAD = math.radians(2.0)


def pair_errors(pairs: list, guesses: NDArray[np.float64], matcher: Callable
                ) -> tuple[NDArray[np.float64], NDArray[np.float64], float]:
    """Translation (m) and rotation (rad) error of each pair's match against its reference, and
    seconds spent matching (wall time)."""
    trans, rot = np.zeros(len(pairs)), np.zeros(len(pairs))
    start = time.perf_counter()
    for i, (pair, guess) in enumerate(zip(pairs, guesses)):
        est = matcher(pair.source, pair.target, guess)
        trans[i] = math.hypot(est[0] - pair.reference[0], est[1] - pair.reference[1])
        rot[i] = abs(wrap_angle(est[2] - pair.reference[2]))
    return trans, rot, time.perf_counter() - start


def pair_summary(trans: NDArray[np.float64], rot: NDArray[np.float64]) -> dict:
    """Median errors (m, deg) and failure rate (> 0.10 m or > 2 deg)."""
    failed = (trans > FAIL_TRANSLATION_M) | (rot > FAIL_ROTATION_RAD)
    return {
        'median_translation_m': float(np.median(trans)),
        'median_rotation_deg': float(np.degrees(np.median(rot))),
        'failure_rate': float(failed.mean()),
        'pairs': int(trans.size),
    }


def best_competitor(results: dict[str, dict]) -> dict:
    """Best median translation, median rotation and failure rate over the methods not ours."""
    others = [v for k, v in results.items() if not k.startswith('ours')]
    return {key: min(v[key] for v in others)
            for key in ('median_translation_m', 'median_rotation_deg', 'failure_rate')}


def scores(reference_t: NDArray[np.int64], reference_poses: NDArray[np.float64],
           relation_t: NDArray[np.int64], relation_poses: NDArray[np.float64],
           t: NDArray[np.int64], poses: NDArray[np.float64]) -> dict:
    """ATE (m) against the reference trajectory and the mean RPE (m, deg) between consecutive
    relation samples (the scans' reference poses), as sensing_eval scores them."""
    errors = relative_pose_errors(relations_from_trajectory(relation_t, relation_poses), t,
                                  poses)
    summary = errors.summary()
    return {'ate_rmse_m': absolute_trajectory_error(reference_t, reference_poses, t,
                                                    poses)['ate_rmse_m'],
            'rpe_translation_mean_m': summary['rpe_translation_mean_m'],
            'rpe_rotation_mean_deg': summary['rpe_rotation_mean_deg'],
            'relations': summary['relations']}


def pooled(rows: list[dict], key: str) -> float:
    """RMS over runs of equal length of a per-run RMS figure."""
    return math.sqrt(float(np.mean([row[key] ** 2 for row in rows])))


def pooled_rms(rows: list[dict]) -> dict:
    """The pooled RMS heading (deg) and position (m) errors of runs of equal length."""
    return {f'pooled_{key}': pooled(rows, key) for key in ('rms_heading_deg', 'rms_position_m')}


def pair_rates(methods: dict[str, Callable], pairs, guesses, repeats: int) -> dict[str, float]:
    """Matches per second of each pair method, from CPU time, the methods interleaved pair by
    pair so that any remaining disturbance hits all of them alike; the best of `repeats`
    passes."""
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


def flatten(tree: dict, skip: tuple[str, ...] = (), prefix: str = '', sep: str = '.') -> dict:
    """Nested figures as one flat dict for `make bench`, keys joined by sep (keys in skip and
    their branches left out)."""
    flat: dict = {}
    for key, value in tree.items():
        if key in skip:
            continue
        if isinstance(value, dict):
            flat.update(flatten(value, skip, f'{prefix}{key}{sep}', sep))
        else:
            flat[f'{prefix}{key}'] = value
    return flat
