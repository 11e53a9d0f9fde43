"""Line extraction written the way a lesson writes it: split-and-merge where every fit comes from
the O(n^2) double sums of the polar least-squares formula (Siegwart & Nourbakhsh), dense O(n^2)
covariance propagation and plain recursion. Two forms: textbook_extract_lines writes the sums as
numpy array expressions, textbook_loops_extract_lines as Python lists and loops. core.lines is
the production version; test_lines checks it against these and bench/lines races them."""

from __future__ import annotations

import math

import numpy as np

from sensing_nodes.core.lines import Line


def _textbook_fit(rho, theta):
    """alpha, r of the polar least-squares line (Siegwart & Nourbakhsh's formula, double sums)."""
    n = len(rho)
    rr = np.outer(rho, rho)
    num = np.sum(rho * rho * np.sin(2 * theta)) - 2.0 / n * np.sum(
        rr * np.outer(np.cos(theta), np.sin(theta))
    )
    den = np.sum(rho * rho * np.cos(2 * theta)) - 1.0 / n * np.sum(
        rr * np.cos(np.add.outer(theta, theta))
    )
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


# long: the lesson's form on purpose, one function from scan to lines as a lesson writes it.
def textbook_extract_lines(
    ranges,
    angles,
    split_distance=0.05,
    max_line_gap=0.5,
    min_line_points=6,
    min_line_length=0.2,
    range_sigma=0.01,
    merge_chi2=9.21,
):
    """The same split-and-merge as core.lines, written the textbook way (non-circular scans:
    a full-circle scan is cut at beam 0)."""
    ranges, angles = np.asarray(ranges, float), np.asarray(angles, float)
    valid = np.flatnonzero(np.isfinite(ranges))
    rho, theta = ranges[valid], angles[valid]
    x, y = rho * np.cos(theta), rho * np.sin(theta)
    ranges_out: list[tuple[int, int]] = []
    start = 0
    for i in range(1, len(rho) + 1):
        if (
            i == len(rho)
            or valid[i] != valid[i - 1] + 1
            or math.hypot(x[i] - x[i - 1], y[i] - y[i - 1]) > max_line_gap
        ):
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
                    c = (
                        _textbook_covariance(rho[plo : phi + 1], theta[plo : phi + 1], a1, 1.0)
                        * range_sigma**2
                        + _textbook_covariance(rho[lo : hi + 1], theta[lo : hi + 1], a2, 1.0)
                        * range_sigma**2
                    )
                    d = np.array([r2 - r1, math.remainder(a2 - a1, 2 * math.pi)])
                    ok = d @ np.linalg.solve(c, d) <= merge_chi2
                if ok:
                    am, rm = _textbook_fit(rho[plo:hi + 1], theta[plo:hi + 1])
                    if (
                        np.abs(_distances(rho[plo : hi + 1], theta[plo : hi + 1], am, rm)).max()
                        <= split_distance
                    ):
                        merged[-1] = (plo, hi)
                        continue
        merged.append((lo, hi))
    lines = []
    for lo, hi in merged:
        while hi - lo + 1 >= min_line_points:
            alpha, r = _textbook_fit(rho[lo:hi + 1], theta[lo:hi + 1])
            d = _distances(rho[[lo, hi]], theta[[lo, hi]], alpha, r)
            sd = (
                3.0
                * range_sigma
                * np.maximum(np.abs(np.cos(theta[[lo, hi]] - alpha)), math.sqrt(0.05))
            )
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
        lines.append(
            Line(r, alpha, cov, tuple(q0), tuple(q1), int(valid[lo]), int(valid[hi]), hi - lo + 1)
        )
    return lines


# ------------------------------------------------------------------ the lesson's version

def _lesson_fit(rho, theta):
    """alpha, r of the polar least-squares line, the same formula with its sums written as the
    lesson writes them: loops, the double sums as two nested loops."""
    n = len(rho)
    sin2 = cos2 = cross = pair = 0.0
    for i in range(n):
        sin2 += rho[i] * rho[i] * math.sin(2 * theta[i])
        cos2 += rho[i] * rho[i] * math.cos(2 * theta[i])
        for j in range(n):
            cross += rho[i] * rho[j] * math.cos(theta[i]) * math.sin(theta[j])
            pair += rho[i] * rho[j] * math.cos(theta[i] + theta[j])
    alpha = 0.5 * math.atan2(sin2 - 2.0 / n * cross, cos2 - 1.0 / n * pair) + math.pi / 2
    r = 0.0
    for i in range(n):
        r += rho[i] * math.cos(theta[i] - alpha)
    r /= n
    if r < 0:
        r, alpha = -r, alpha + math.pi
    return math.remainder(alpha, 2 * math.pi), r


def _lesson_covariance(rho, theta, alpha, sigma):
    """F·C·Fᵀ with the dense n×n C = sigma²·I, F = d(r, alpha)/d(rho), in loops (2×2 list)."""
    n = len(rho)
    c, s = math.cos(alpha), math.sin(alpha)
    a = [
        (-1.0, rho[k] * math.sin(theta[k]) * c - rho[k] * math.cos(theta[k]) * s) for k in range(n)
    ]
    info = [[sum(a[k][i] * a[k][j] for k in range(n)) for j in range(2)] for i in range(2)]
    det = info[0][0] * info[1][1] - info[0][1] * info[1][0]
    inv = [[info[1][1] / det, -info[0][1] / det], [-info[1][0] / det, info[0][0] / det]]
    d = [math.sqrt(max(math.cos(theta[k] - alpha) ** 2, 0.05)) for k in range(n)]
    f = [[(inv[i][0] * a[k][0] + inv[i][1] * a[k][1]) * d[k] for k in range(n)] for i in range(2)]
    cov_c = [[sigma * sigma if j == k else 0.0 for k in range(n)] for j in range(n)]
    cov = [[0.0, 0.0], [0.0, 0.0]]
    for i in range(2):
        for m in range(2):
            total = 0.0
            for j in range(n):
                for k in range(n):
                    total += f[i][j] * cov_c[j][k] * f[m][k]
            cov[i][m] = total
    return cov


def _lesson_max_distance(rho, theta, alpha, r):
    worst = 0.0
    for i in range(len(rho)):
        worst = max(worst, abs(rho[i] * math.cos(theta[i] - alpha) - r))
    return worst


def _lesson_split(rho, theta, x, y, lo, hi, split_distance, min_points, out):
    """Recursive split of the inclusive index range [lo, hi]."""
    if hi - lo + 1 < max(min_points, 3):
        out.append((lo, hi))
        return
    alpha, r = _lesson_fit(rho[lo:hi + 1], theta[lo:hi + 1])
    if _lesson_max_distance(rho[lo:hi + 1], theta[lo:hi + 1], alpha, r) <= split_distance:
        out.append((lo, hi))
        return
    far, k = -1.0, lo
    for i in range(lo, hi + 1):
        chord = abs((x[i] - x[lo]) * (y[hi] - y[lo]) - (y[i] - y[lo]) * (x[hi] - x[lo]))
        if chord > far:
            far, k = chord, i
    k = min(max(k, lo + 1), hi - 1)
    _lesson_split(rho, theta, x, y, lo, k, split_distance, min_points, out)
    _lesson_split(rho, theta, x, y, k, hi, split_distance, min_points, out)


# long: the lesson's form on purpose, one function from scan to lines as a lesson writes it.
def textbook_loops_extract_lines(ranges, angles, split_distance=0.05, max_line_gap=0.5,
                                 min_line_points=6, min_line_length=0.2, range_sigma=0.01,
                                 merge_chi2=9.21):
    """textbook_extract_lines as a lesson writes it: Python lists and loops, no numpy (the O(n²)
    fit sums and the dense covariance as nested loops), plain recursion."""
    valid = [i for i in range(len(ranges)) if math.isfinite(ranges[i])]
    rho = [float(ranges[i]) for i in valid]
    theta = [float(angles[i]) for i in valid]
    x = [rho[i] * math.cos(theta[i]) for i in range(len(rho))]
    y = [rho[i] * math.sin(theta[i]) for i in range(len(rho))]
    pieces: list[tuple[int, int]] = []
    start = 0
    for i in range(1, len(rho) + 1):
        if i == len(rho) or valid[i] != valid[i - 1] + 1 \
                or math.hypot(x[i] - x[i - 1], y[i] - y[i - 1]) > max_line_gap:
            _lesson_split(rho, theta, x, y, start, i - 1, split_distance, min_line_points, pieces)
            start = i
    pieces.sort()
    merged: list[tuple[int, int]] = []
    for lo, hi in pieces:
        if merged:
            plo, phi = merged[-1]
            near = lo >= phi and math.hypot(x[lo] - x[phi], y[lo] - y[phi]) <= max_line_gap
            small = (hi - lo + 1 < min_line_points) or (phi - plo + 1 < min_line_points)
            if near:
                ok = small
                if not small:
                    a1, r1 = _lesson_fit(rho[plo:phi + 1], theta[plo:phi + 1])
                    a2, r2 = _lesson_fit(rho[lo:hi + 1], theta[lo:hi + 1])
                    c1 = _lesson_covariance(rho[plo:phi + 1], theta[plo:phi + 1], a1, range_sigma)
                    c2 = _lesson_covariance(rho[lo:hi + 1], theta[lo:hi + 1], a2, range_sigma)
                    c = [[c1[i][j] + c2[i][j] for j in range(2)] for i in range(2)]
                    dr, da = r2 - r1, math.remainder(a2 - a1, 2 * math.pi)
                    det = c[0][0] * c[1][1] - c[0][1] * c[1][0]
                    chi2 = (
                        c[1][1] * dr * dr - (c[0][1] + c[1][0]) * dr * da + c[0][0] * da * da
                    ) / det
                    ok = chi2 <= merge_chi2
                if ok:
                    am, rm = _lesson_fit(rho[plo:hi + 1], theta[plo:hi + 1])
                    if (
                        _lesson_max_distance(rho[plo : hi + 1], theta[plo : hi + 1], am, rm)
                        <= split_distance
                    ):
                        merged[-1] = (plo, hi)
                        continue
        merged.append((lo, hi))
    lines = []
    for lo, hi in merged:
        while hi - lo + 1 >= min_line_points:
            alpha, r = _lesson_fit(rho[lo:hi + 1], theta[lo:hi + 1])
            bad = []
            for i in (lo, hi):
                d = rho[i] * math.cos(theta[i] - alpha) - r
                bad.append(
                    abs(d)
                    > 3.0 * range_sigma * max(abs(math.cos(theta[i] - alpha)), math.sqrt(0.05))
                )
            if not (bad[0] or bad[1]):
                break
            lo, hi = lo + int(bad[0]), hi - int(bad[1])
        if hi - lo + 1 < min_line_points:
            continue
        alpha, r = _lesson_fit(rho[lo:hi + 1], theta[lo:hi + 1])
        c, s = math.cos(alpha), math.sin(alpha)
        d0, d1 = x[lo] * c + y[lo] * s - r, x[hi] * c + y[hi] * s - r
        q0, q1 = (x[lo] - d0 * c, y[lo] - d0 * s), (x[hi] - d1 * c, y[hi] - d1 * s)
        if math.hypot(q1[0] - q0[0], q1[1] - q0[1]) < min_line_length:
            continue
        cov = _lesson_covariance(rho[lo:hi + 1], theta[lo:hi + 1], alpha, range_sigma)
        lines.append(Line(r, alpha, np.array(cov), q0, q1, valid[lo], valid[hi], hi - lo + 1))
    return lines
