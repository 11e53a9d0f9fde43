"""Speed of line extraction: scans per second at 360, 720 and 1080 beams, for core.lines and for
a textbook implementation of the same split-and-merge (every fit from the O(n²) double sums of
the polar least-squares formula, dense O(n²) covariance propagation, plain recursion), measured
in the same run on the same simulated scans of the default world. Neither uses BLAS, so both run
on one core. Rates are per CPU second of this process (time.process_time), so time the shared
machine gives to other processes is not counted; the 360-beam rates are also given on the wall
clock.
"""

from __future__ import annotations

import json
import math
import time

import numpy as np

from sensing_nodes.core.lines import Line, extract_lines
from sensing_nodes.core.world import load_world, raycast
from sensing_nodes.paths import config_file

POSES = [(-3.0, -2.0, 0.3), (3.0, -2.0, 2.0), (-3.0, 2.5, -1.0), (2.5, 1.5, 0.7), (0.0, 2.0, 3.0),
         (0.0, -2.0, -2.5), (-2.0, 0.0, 1.2), (3.5, 0.0, -0.4), (-4.0, -3.0, 0.1), (2.0, -3.0, 1.5)]


def simulated_scans(beams: int, sigma: float = 0.01, range_max: float = 8.0, seed: int = 0):
    """360-degree scans (ranges, angles) of the default world from POSES, Gaussian range noise."""
    world = load_world(config_file('default_world.yaml'))
    rng = np.random.default_rng(seed)
    angles = -math.pi + 2.0 * math.pi * np.arange(beams) / beams
    scans = []
    for x, y, yaw in POSES:
        true = raycast(world.segments, (x, y), angles + yaw)
        scans.append((np.where(true <= range_max, true + rng.normal(0.0, sigma, beams), np.inf), angles))
    return scans


# ------------------------------------------------------------------ textbook implementation

def _textbook_fit(rho, theta):
    """alpha, r of the polar least-squares line (Siegwart & Nourbakhsh's formula, double sums)."""
    n = len(rho)
    rr = np.outer(rho, rho)
    num = np.sum(rho * rho * np.sin(2 * theta)) - 2.0 / n * np.sum(rr * np.outer(np.cos(theta), np.sin(theta)))
    den = np.sum(rho * rho * np.cos(2 * theta)) - 1.0 / n * np.sum(rr * np.cos(np.add.outer(theta, theta)))
    alpha = 0.5 * math.atan2(num, den) + math.pi / 2
    r = float(np.sum(rho * np.cos(theta - alpha)) / n)
    if r < 0:
        r, alpha = -r, alpha + math.pi
    return math.remainder(alpha, 2 * math.pi), r


def _textbook_covariance(rho, theta, alpha, sigma):
    """Dense first-order propagation F·C·Fᵀ with C = sigma²·I (n×n), F = d(r, alpha)/d(rho)."""
    c, s = math.cos(alpha), math.sin(alpha)
    x, y = rho * np.cos(theta), rho * np.sin(theta)
    t = y * c - x * s
    a = np.column_stack((-np.ones_like(t), t))
    info = np.einsum('ki,kj->ij', a, a)
    d = np.diag(np.maximum(np.cos(theta - alpha) ** 2, 0.05) ** 0.5)
    f = np.linalg.inv(info) @ np.einsum('ki,kj->ij', a, d)              # (2, n)
    cov = np.einsum('ij,jk,lk->il', f, sigma * sigma * np.eye(len(rho)), f)
    return cov


def _distances(rho, theta, alpha, r):
    return rho * np.cos(theta - alpha) - r


def _textbook_split(rho, theta, lo, hi, split_distance, min_points, out):
    """Recursive split of the inclusive index range [lo, hi]."""
    if hi - lo + 1 < max(min_points, 3):
        out.append((lo, hi))
        return
    alpha, r = _textbook_fit(rho[lo:hi + 1], theta[lo:hi + 1])
    if np.abs(_distances(rho[lo:hi + 1], theta[lo:hi + 1], alpha, r)).max() <= split_distance:
        out.append((lo, hi))
        return
    x, y = rho[lo:hi + 1] * np.cos(theta[lo:hi + 1]), rho[lo:hi + 1] * np.sin(theta[lo:hi + 1])
    chord = np.abs((x - x[0]) * (y[-1] - y[0]) - (y - y[0]) * (x[-1] - x[0]))
    k = min(max(lo + int(np.argmax(chord)), lo + 1), hi - 1)
    _textbook_split(rho, theta, lo, k, split_distance, min_points, out)
    _textbook_split(rho, theta, k, hi, split_distance, min_points, out)


def textbook_extract_lines(ranges, angles, split_distance=0.05, max_line_gap=0.5, min_line_points=6,
                           min_line_length=0.2, range_sigma=0.01, merge_chi2=9.21):
    """The same split-and-merge as core.lines, written the textbook way (non-circular scans:
    a full-circle scan is cut at beam 0)."""
    ranges, angles = np.asarray(ranges, float), np.asarray(angles, float)
    valid = np.flatnonzero(np.isfinite(ranges))
    rho, theta = ranges[valid], angles[valid]
    x, y = rho * np.cos(theta), rho * np.sin(theta)
    ranges_out: list[tuple[int, int]] = []
    start = 0
    for i in range(1, len(rho) + 1):
        if i == len(rho) or valid[i] != valid[i - 1] + 1 or math.hypot(x[i] - x[i - 1], y[i] - y[i - 1]) > max_line_gap:
            _textbook_split(rho, theta, start, i - 1, split_distance, min_line_points, ranges_out)
            start = i
    ranges_out.sort()
    merged: list[tuple[int, int]] = []
    for lo, hi in ranges_out:
        if merged:
            plo, phi = merged[-1]
            near = lo >= phi and math.hypot(x[lo] - x[phi], y[lo] - y[phi]) <= max_line_gap
            small = (hi - lo + 1 < min_line_points) or (phi - plo + 1 < min_line_points)
            if near:
                ok = small
                if not small:
                    a1, r1 = _textbook_fit(rho[plo:phi + 1], theta[plo:phi + 1])
                    a2, r2 = _textbook_fit(rho[lo:hi + 1], theta[lo:hi + 1])
                    c = _textbook_covariance(rho[plo:phi + 1], theta[plo:phi + 1], a1, 1.0) * range_sigma ** 2 \
                        + _textbook_covariance(rho[lo:hi + 1], theta[lo:hi + 1], a2, 1.0) * range_sigma ** 2
                    d = np.array([r2 - r1, math.remainder(a2 - a1, 2 * math.pi)])
                    ok = d @ np.linalg.solve(c, d) <= merge_chi2
                if ok:
                    am, rm = _textbook_fit(rho[plo:hi + 1], theta[plo:hi + 1])
                    if np.abs(_distances(rho[plo:hi + 1], theta[plo:hi + 1], am, rm)).max() <= split_distance:
                        merged[-1] = (plo, hi)
                        continue
        merged.append((lo, hi))
    lines = []
    for lo, hi in merged:
        while hi - lo + 1 >= min_line_points:
            alpha, r = _textbook_fit(rho[lo:hi + 1], theta[lo:hi + 1])
            d = _distances(rho[[lo, hi]], theta[[lo, hi]], alpha, r)
            sd = 3.0 * range_sigma * np.maximum(np.abs(np.cos(theta[[lo, hi]] - alpha)), math.sqrt(0.05))
            if abs(d[0]) <= sd[0] and abs(d[1]) <= sd[1]:
                break
            lo, hi = lo + int(abs(d[0]) > sd[0]), hi - int(abs(d[1]) > sd[1])
        if hi - lo + 1 < min_line_points:
            continue
        alpha, r = _textbook_fit(rho[lo:hi + 1], theta[lo:hi + 1])
        n = np.array([math.cos(alpha), math.sin(alpha)])
        p0 = np.array([x[lo], y[lo]])
        p1 = np.array([x[hi], y[hi]])
        q0, q1 = p0 - (p0 @ n - r) * n, p1 - (p1 @ n - r) * n
        if np.linalg.norm(q1 - q0) < min_line_length:
            continue
        cov = _textbook_covariance(rho[lo:hi + 1], theta[lo:hi + 1], alpha, range_sigma)
        lines.append(Line(r, alpha, cov, tuple(q0), tuple(q1), int(valid[lo]), int(valid[hi]), hi - lo + 1))
    return lines


# ------------------------------------------------------------------ measurement

def _rate(fn, scans, min_seconds: float, repeats: int, clock=time.process_time) -> float:
    """Scans per second: the best of `repeats` passes over the scans (least disturbed by load),
    each pass repeated until it lasts at least min_seconds on `clock`."""
    best = 0.0
    for _ in range(repeats):
        count, started = 0, clock()
        while True:
            for ranges, angles in scans:
                fn(ranges, angles)
            count += len(scans)
            elapsed = clock() - started
            if elapsed >= min_seconds:
                break
        best = max(best, count / elapsed)
    return best


def _agreement(scans) -> tuple[float, float]:
    """Largest |dr| (m) and |dalpha| (rad) between the two implementations' lines on scans
    where both find the same lines (full-circle scans cut at beam 0 differ by design)."""
    dr = da = 0.0
    for ranges, angles in scans:
        ours = [ln for ln in extract_lines(ranges, angles) if ln.first <= ln.last]
        theirs = textbook_extract_lines(ranges, angles)
        pairs = {(ln.first, ln.last): ln for ln in theirs}
        for line in ours:
            other = pairs.get((line.first, line.last))
            if other is not None:
                dr = max(dr, abs(line.r - other.r))
                da = max(da, abs(math.remainder(line.alpha - other.alpha, 2 * math.pi)))
    return dr, da


def run(quick: bool = False) -> dict:
    """Measure and return a flat dict of figures."""
    figures: dict[str, float] = {}
    min_seconds, repeats = (0.3, 1) if quick else (1.0, 3)
    for beams in (360, 720, 1080):
        scans = simulated_scans(beams)
        ours = _rate(extract_lines, scans, min_seconds, repeats)
        textbook = _rate(textbook_extract_lines, scans, min_seconds, repeats)
        figures[f'lines_scans_per_s_{beams}'] = round(ours, 1)
        figures[f'lines_textbook_scans_per_s_{beams}'] = round(textbook, 2)
        figures[f'lines_speedup_{beams}'] = round(ours / textbook, 1)
        figures[f'lines_per_scan_{beams}'] = round(
            sum(len(extract_lines(r, a)) for r, a in scans) / len(scans), 2)
    # The same at 360 beams on the wall clock, which counts time lost to other load too.
    scans = simulated_scans(360)
    figures['lines_scans_per_s_360_wall'] = round(
        _rate(extract_lines, scans, min_seconds, repeats, time.perf_counter), 1)
    figures['lines_textbook_scans_per_s_360_wall'] = round(
        _rate(textbook_extract_lines, scans, min_seconds, repeats, time.perf_counter), 2)
    dr, da = _agreement(scans)
    figures['lines_textbook_max_dr_m'] = float(f'{dr:.3g}')
    figures['lines_textbook_max_dalpha_rad'] = float(f'{da:.3g}')
    return figures


if __name__ == '__main__':
    print(json.dumps(run(), indent=2))
