"""Speed of line extraction: scans per second at 360, 720 and 1080 beams, for core.lines and for
two textbook implementations of the same split-and-merge (every fit from the O(n²) double sums
of the polar least-squares formula, dense O(n²) covariance propagation, plain recursion), all
measured in the same run on the same simulated scans of the default world:
- textbook_numpy: those sums and products as numpy array expressions;
- textbook_loops: as a lesson writes it, Python lists and loops, no numpy.
None uses BLAS, so all run on one core. Rates are per CPU second of this process
(time.process_time), so time the shared machine gives to other processes is not counted; the
methods are measured in alternating rounds, so that load hits them alike; the 360-beam rates
are also given on the wall clock.
"""

from __future__ import annotations

import json
import math
import time

import numpy as np

from sensing_nodes.core.lines import extract_lines
from sensing_nodes.core.reference.lines import (
    textbook_extract_lines,
    textbook_loops_extract_lines,
)
from sensing_nodes.core.sim.world import load_world, raycast
from sensing_nodes.paths import config_file

POSES = [
    (-3.0, -2.0, 0.3),
    (3.0, -2.0, 2.0),
    (-3.0, 2.5, -1.0),
    (2.5, 1.5, 0.7),
    (0.0, 2.0, 3.0),
    (0.0, -2.0, -2.5),
    (-2.0, 0.0, 1.2),
    (3.5, 0.0, -0.4),
    (-4.0, -3.0, 0.1),
    (2.0, -3.0, 1.5),
]


def simulated_scans(beams: int, sigma: float = 0.01, range_max: float = 8.0, seed: int = 0):
    """360-degree scans (ranges, angles) of the default world from POSES, Gaussian range noise."""
    world = load_world(config_file('default_world.yaml'))
    rng = np.random.default_rng(seed)
    angles = -math.pi + 2.0 * math.pi * np.arange(beams) / beams
    scans = []
    for x, y, yaw in POSES:
        true = raycast(world.segments, (x, y), angles + yaw)
        scans.append(
            (np.where(true <= range_max, true + rng.normal(0.0, sigma, beams), np.inf), angles)
        )
    return scans


# ------------------------------------------------------------------ measurement

METHODS = {'ours': extract_lines, 'textbook_numpy': textbook_extract_lines,
           'textbook_loops': textbook_loops_extract_lines}


def _rates(methods: dict, scans, min_seconds: float, rounds: int,
           clock=time.process_time) -> dict[str, float]:
    """Scans per second of each method: in each of `rounds` rounds every method in turn passes
    over the scans until it has run at least min_seconds on `clock`; the best round counts
    (the least disturbed by load)."""
    best = dict.fromkeys(methods, 0.0)
    for _ in range(rounds):
        for name, fn in methods.items():
            count, started = 0, clock()
            while True:
                for ranges, angles in scans:
                    fn(ranges, angles)
                count += len(scans)
                elapsed = clock() - started
                if elapsed >= min_seconds:
                    break
            best[name] = max(best[name], count / elapsed)
    return best


def agreement(scans, textbook) -> tuple[float, float]:
    """Largest |dr| (m) and |dalpha| (rad) between core.lines and a textbook version on the lines
    both find (full-circle scans cut at beam 0 differ by design), and how many of ours they
    found too (fraction)."""
    dr = da = 0.0
    found = total = 0
    for ranges, angles in scans:
        ours = [ln for ln in extract_lines(ranges, angles) if ln.first <= ln.last]
        pairs = {(ln.first, ln.last): ln for ln in textbook(ranges, angles)}
        for line in ours:
            total += 1
            other = pairs.get((line.first, line.last))
            if other is not None:
                found += 1
                dr = max(dr, abs(line.r - other.r))
                da = max(da, abs(math.remainder(line.alpha - other.alpha, 2 * math.pi)))
    return dr, da, found / max(total, 1)


def run(quick: bool = False) -> dict:
    """Measure and return a flat dict of figures (ratios: ours / textbook, same run)."""
    figures: dict[str, float] = {}
    min_seconds, rounds = (0.2, 1) if quick else (1.0, 3)
    for beams in (360, 720, 1080):
        scans = simulated_scans(beams)[:2] if quick else simulated_scans(beams)
        rates = _rates(METHODS, scans, min_seconds, rounds)
        figures[f'lines_scans_per_s_{beams}'] = round(rates['ours'], 1)
        for name in ('textbook_numpy', 'textbook_loops'):
            figures[f'lines_{name}_scans_per_s_{beams}'] = round(rates[name], 2)
            figures[f'lines_speedup_vs_{name}_{beams}'] = round(rates['ours'] / rates[name], 1)
        figures[f'lines_per_scan_{beams}'] = round(
            sum(len(extract_lines(r, a)) for r, a in scans) / len(scans), 2)
    # The same at 360 beams on the wall clock, which counts time lost to other load too.
    scans = simulated_scans(360)[:2] if quick else simulated_scans(360)
    for name, rate in _rates(METHODS, scans, min_seconds, rounds, time.perf_counter).items():
        figures[f'lines_{name}_scans_per_s_360_wall' if name != 'ours'
                else 'lines_scans_per_s_360_wall'] = round(rate, 2 if name != 'ours' else 1)
    for name in ('textbook_numpy', 'textbook_loops'):
        dr, da, found = agreement(scans, METHODS[name])
        figures[f'lines_{name}_max_dr_m'] = float(f'{dr:.3g}')
        figures[f'lines_{name}_max_dalpha_rad'] = float(f'{da:.3g}')
        figures[f'lines_{name}_same_lines_fraction'] = round(found, 3)
    return figures


if __name__ == '__main__':
    import sys

    print(json.dumps(run(quick='--quick' in sys.argv), indent=2))
