"""Line extraction from a laser scan by split-and-merge, lines in polar form (laser frame, m, rad).

A line is x·cos(alpha) + y·sin(alpha) = r with r >= 0 and alpha in (-pi, pi]; a point's signed
distance to it is x·cos(alpha) + y·sin(alpha) - r (for a beam (rho, theta): rho·cos(theta - alpha) - r).

Every least-squares fit during splitting and merging is O(1) from prefix sums of
(x, y, x², y², xy) prepared once per scan, and the splitting works on all segments of a scan at once
(one numpy pass per level of the split tree), so a scan costs O(n log n) array work and a few
dozen numpy calls per level, with no Python recursion. The (r, alpha) covariance of each line
propagates every point's distance variance sigma_r²·cos²(theta_i - alpha) (range noise seen along
the normal, the noise model of Pfister et al. 2003) through the least-squares fit. (A fit weighted
by the inverse of those variances, as Pfister et al. propose, was tried: on the real CARMEN logs it
pulled lines up to 7 cm off their own end points, as the noise there is not range-only.)
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from sensing_nodes.core.scan import scan_to_points

# cos²(incidence) is floored here: at grazing incidence the real error is dominated by beam width
# and mixed returns, not by the range noise (which would give a vanishing distance variance).
_MIN_COS2 = 0.05
# An end point farther than this many standard deviations of its distance from the fit is dropped:
# a split point found a beam or two off a corner lies on the other wall, within split_distance
# of this one. A split point within noise of both walls stays in both lines.
_END_SIGMAS = 3.0
_SMALLEST_RANGE = 1e-9


@dataclass(slots=True)
class Line:
    """A fitted line in the laser frame: x·cos(alpha) + y·sin(alpha) = r (m, rad).

    covariance is 2x2 over (r, alpha); start and end are the first and last fitted points
    projected onto the line (m); first and last are the beam indices of those points (for a scan
    covering the full circle a line may run through beam 0, then first > last); point_count is
    the number of beams fitted.
    """

    r: float
    alpha: float
    covariance: NDArray[np.float64]
    start: tuple[float, float]
    end: tuple[float, float]
    first: int
    last: int
    point_count: int

    @property
    def length(self) -> float:
        """Distance between the endpoints (m)."""
        return math.hypot(self.end[0] - self.start[0], self.end[1] - self.start[1])


@dataclass(frozen=True)
class PolarFit:
    """Least-squares line fit of points (laser frame): alpha (rad), r (m), residual sum of squares (m²)."""

    alpha: float
    r: float
    residual: float


def fit_line(points: ArrayLike) -> PolarFit:
    """Perpendicular (total) least-squares line through (N, 2) points (m), N >= 2, from O(N) sums."""
    p = np.asarray(points, dtype=float).reshape(-1, 2)
    if len(p) < 2:
        raise ValueError(f'a line needs at least 2 points, got {len(p)}')
    sums = np.concatenate(([len(p)], p.sum(axis=0), (p * p).sum(axis=0), [p[:, 0] @ p[:, 1]]))
    fit = _PolarFits(sums[None, :])
    spread = math.hypot(fit.sxx[0] - fit.syy[0], 2.0 * fit.sxy[0])
    residual = max(0.5 * (fit.sxx[0] + fit.syy[0] - spread), 0.0)  # smaller scatter eigenvalue
    return PolarFit(float(fit.alpha[0]), float(fit.r[0]), residual)


class _PolarFits:
    """Least-squares lines from rows of point sums (n, Σx, Σy, Σx², Σy², Σxy), with r >= 0 and
    alpha in (-pi, pi]; covariance() is that of (r, alpha) for unit distance variance per point."""

    def __init__(self, sums: NDArray[np.float64]) -> None:
        w = self.w = sums[:, 0]
        xm, ym = self.xm, self.ym = sums[:, 1] / w, sums[:, 2] / w
        self.sxx = sums[:, 3] - xm * sums[:, 1]
        self.syy = sums[:, 4] - ym * sums[:, 2]
        self.sxy = sums[:, 5] - xm * sums[:, 2]
        alpha = 0.5 * np.arctan2(-2.0 * self.sxy, self.syy - self.sxx)   # in [-pi/2, pi/2]
        c, s = np.cos(alpha), np.sin(alpha)
        r = xm * c + ym * s
        flip = r < 0.0
        # Turning the normal by pi keeps the line and makes r positive.
        alpha = np.where(flip, np.where(alpha > 0.0, alpha - np.pi, alpha + np.pi), alpha)
        self.alpha = np.where(alpha <= -np.pi, alpha + 2.0 * np.pi, alpha)   # -pi rounds to pi
        self.c, self.s = np.where(flip, -c, c), np.where(flip, -s, s)
        self.r = np.abs(r)

    def covariance(self):
        """(var r, cov r-alpha, var alpha), each (k,), for unit distance variance per point."""
        c, s = self.c, self.s
        # Along-line coordinate t = p·(-sin, cos): its spread about the centroid and the centroid's t.
        # Floored so that a degenerate fit (one point) gives a huge but finite covariance.
        stt = np.maximum(s * s * self.sxx + c * c * self.syy - 2.0 * s * c * self.sxy, 1e-12)
        tm = c * self.ym - s * self.xm
        return 1.0 / self.w + tm * tm / stt, tm / stt, 1.0 / stt


def _ranges_within(lengths: NDArray[np.intp], starts: NDArray[np.intp]):
    """Concatenated index ranges [starts[k], starts[k] + lengths[k]) and the owner k of each."""
    offsets = np.cumsum(lengths) - lengths
    owner = np.repeat(np.arange(len(lengths)), lengths)
    index = np.arange(int(lengths.sum())) - np.repeat(offsets - starts, lengths)
    return index, owner, offsets


class _Scan:
    """Valid points of one scan in processing order, with prefix sums for O(1) segment fits."""

    def __init__(self, points: NDArray[np.float64], beams: NDArray[np.intp]) -> None:
        self.x = np.ascontiguousarray(points[:, 0])
        self.y = np.ascontiguousarray(points[:, 1])
        self.beams = beams
        prefix = np.empty((len(self.x) + 1, 6))
        prefix[0] = 0.0
        terms = prefix[1:]
        terms[:, 0] = 1.0
        terms[:, 1] = self.x
        terms[:, 2] = self.y
        np.multiply(self.x, self.x, out=terms[:, 3])
        np.multiply(self.y, self.y, out=terms[:, 4])
        np.multiply(self.x, self.y, out=terms[:, 5])
        np.cumsum(terms, axis=0, out=terms)
        self.prefix = prefix

    def fit(self, s: NDArray[np.intp], e: NDArray[np.intp]):
        """Unweighted fits of the inclusive point ranges [s, e] as (cos alpha, sin alpha, r);
        r may be negative here (only the final lines are normalised to r >= 0)."""
        d = self.prefix[e + 1] - self.prefix[s]
        w = d[:, 0]
        xm, ym = d[:, 1] / w, d[:, 2] / w
        alpha = 0.5 * np.arctan2(-2.0 * (d[:, 5] - xm * d[:, 2]),
                                 (d[:, 4] - ym * d[:, 2]) - (d[:, 3] - xm * d[:, 1]))
        c, sn = np.cos(alpha), np.sin(alpha)
        return c, sn, xm * c + ym * sn

    def distances(self, index, c, sn, r):
        """Signed distances (m) of points `index` to lines (cos alpha, sin alpha, r) given per point."""
        return self.x[index] * c + self.y[index] * sn - r


def _split(scan: _Scan, s: NDArray[np.intp], e: NDArray[np.intp], split_distance: float,
           min_points: int) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """Split every range [s, e] until its fit's farthest point is within split_distance.

    A range that must split is cut at its point farthest from the chord between its end points
    (robust to a corner near one end, where the farthest point from the fit is the end itself);
    that point goes to both halves (_trim_ends later drops it where it does not fit).
    """
    done_s, done_e = [], []
    smallest = max(min_points, 3)
    while len(s):
        n = e - s + 1
        small = n < smallest
        if small.any():
            done_s.append(s[small])
            done_e.append(e[small])
            s, e, n = s[~small], e[~small], n[~small]
            if not len(s):
                break
        c, sn, r = scan.fit(s, e)
        index, owner, offsets = _ranges_within(n, s)
        xi, yi = scan.x[index], scan.y[index]
        far = np.maximum.reduceat(np.abs(xi * c[owner] + yi * sn[owner] - r[owner]), offsets)
        final = far <= split_distance
        done_s.append(s[final])
        done_e.append(e[final])
        if final.all():
            break
        # Distance to the chord through each range's first and last point, times the chord's
        # length (which does not move the argmax); computed for every range, used for the others.
        x0, y0 = scan.x[s], scan.y[s]
        dx, dy = scan.x[e] - x0, scan.y[e] - y0
        chord = np.abs(xi * dy[owner] - yi * dx[owner] - (x0 * dy - y0 * dx)[owner])
        hits = np.flatnonzero(chord == np.maximum.reduceat(chord, offsets)[owner])
        hit_owner = owner[hits]
        first = np.ones(len(hits), dtype=bool)
        np.not_equal(hit_owner[1:], hit_owner[:-1], out=first[1:])
        split = ~final
        at = np.clip(index[hits[first]], s + 1, e - 1)[split]
        s, e = np.concatenate((s[split], at)), np.concatenate((at, e[split]))
    s, e = np.concatenate(done_s), np.concatenate(done_e)
    order = np.lexsort((e, s))
    return s[order], e[order]


def _merge(scan: _Scan, s, e, sigma2: float, merge_chi2: float, split_distance: float,
           max_gap: float, min_points: int):
    """Merge neighbouring ranges whose lines agree within their summed covariance (chi-square on
    (dr, dalpha), 2 dof) when the gap between them is at most max_gap and the merged fit still has
    every point within split_distance. A range of fewer than min_points points (a piece of wall
    between invalid beams, or an outlier) needs only the gap and the merged fit to pass.
    Also returns the ranges' fits (cos, sin, r) when they were computed and nothing merged."""
    if len(s) < 2:
        return s, e, None
    gap = np.hypot(scan.x[s[1:]] - scan.x[e[:-1]], scan.y[s[1:]] - scan.y[e[:-1]])
    near = (gap <= max_gap) & (s[1:] >= e[:-1])
    if not near.any():
        return s, e, None
    fit = _PolarFits(scan.prefix[e + 1] - scan.prefix[s])
    rr, ra, aa = fit.covariance()
    # Unweighted fits: information scaled by 1 / sigma² (the distance noise is at most sigma).
    rr, ra, aa = (rr[1:] + rr[:-1]) * sigma2, (ra[1:] + ra[:-1]) * sigma2, (aa[1:] + aa[:-1]) * sigma2
    dr = fit.r[1:] - fit.r[:-1]
    da = fit.alpha[1:] - fit.alpha[:-1]
    da = np.where(da > np.pi, da - 2.0 * np.pi, np.where(da <= -np.pi, da + 2.0 * np.pi, da))
    chi2 = (aa * dr * dr - 2.0 * ra * dr * da + rr * da * da) / (rr * aa - ra * ra)
    small = e - s + 1 < min_points
    small_l, small_r = small[:-1], small[1:]
    # A small range joins a neighbour only when its far end is within split_distance of the
    # neighbour's line (the merged fit is checked below); two small ones are checked directly.
    x, y, c, sn, r = scan.x, scan.y, fit.c, fit.s, fit.r
    right_fits_left = np.abs(x[e[1:]] * c[:-1] + y[e[1:]] * sn[:-1] - r[:-1]) <= split_distance
    left_fits_right = np.abs(x[s[:-1]] * c[1:] + y[s[:-1]] * sn[1:] - r[1:]) <= split_distance
    candidate = near & np.where(
        small_l | small_r,
        (small_l & small_r) | (small_r & right_fits_left) | (small_l & left_fits_right),
        chi2 <= merge_chi2)
    if not candidate.any():
        return s, e, (fit.c, fit.s, fit.r)
    out_s, out_e = [int(s[0])], [int(e[0])]
    for k in range(1, len(s)):
        if candidate[k - 1] and out_e[-1] == e[k - 1]:
            ms, me = np.array([out_s[-1]]), np.array([int(e[k])])
            cm, sm, rm = scan.fit(ms, me)
            index = np.arange(ms[0], me[0] + 1)
            if np.abs(scan.distances(index, cm[0], sm[0], rm[0])).max() <= split_distance:
                out_e[-1] = int(e[k])
                continue
        out_s.append(int(s[k]))
        out_e.append(int(e[k]))
    return np.array(out_s), np.array(out_e), None


def _is_full_circle(angles: NDArray[np.float64]) -> bool:
    """True when the beam after the last would be the first (a 360-degree scan)."""
    if angles.size < 3:
        return False
    first, last = float(angles[0]), float(angles[-1])
    step = (last - first) / (angles.size - 1)
    return math.isfinite(step) and step != 0.0 \
        and abs(math.remainder(first - last - step, 2.0 * math.pi)) < 0.5 * abs(step)


def _breaks(x, y, beams, beam_count: int, circular: bool, max_gap: float) -> NDArray[np.bool_]:
    """brk[i]: no line may run from point i to point i+1 (the last entry: from the last point
    back to the first, only possible on a full-circle scan)."""
    brk = np.empty(len(x), dtype=bool)
    brk[:-1] = (np.diff(beams) != 1) | (np.hypot(np.diff(x), np.diff(y)) > max_gap)
    brk[-1] = not (circular and beams[0] == 0 and beams[-1] == beam_count - 1
                   and math.hypot(x[0] - x[-1], y[0] - y[-1]) <= max_gap)
    return brk


def extract_lines(
    ranges: ArrayLike,
    angles: ArrayLike,
    *,
    split_distance: float = 0.05,
    max_line_gap: float = 0.5,
    min_line_points: int = 6,
    min_line_length: float = 0.2,
    min_range: float = 0.0,
    max_range: float = np.inf,
    range_sigma: float = 0.01,
    merge_chi2: float = 9.21,
) -> list[Line]:
    """Lines (laser frame) in a scan given as ranges (m, REP 117 values allowed) and beam angles (rad).

    split_distance: a segment is split while a point is farther than this from its fit (m);
    max_line_gap: no line spans two consecutive points farther apart than this (m);
    min_line_points, min_line_length (m): smaller lines are dropped;
    min_range, max_range (m): beams outside are invalid, like NaN and ±inf (and a range of 0);
    range_sigma: standard deviation of the range noise (m), scales the covariances;
    merge_chi2: neighbouring segments merge when chi-square of (dr, dalpha) is at most this
    (2 degrees of freedom; 9.21 is the 99 % quantile).
    Lines are sorted by first beam. Raises ValueError for ranges and angles of different lengths
    and for option values that make no sense; otherwise returns what it finds (possibly nothing).
    """
    _check_options(split_distance, max_line_gap, min_line_points, min_line_length,
                   min_range, max_range, range_sigma, merge_chi2)
    r_in = np.asarray(ranges, dtype=float).ravel()
    a_in = np.asarray(angles, dtype=float).ravel()
    # A zero range is no point on a surface, whatever min_range says.
    points, beams = scan_to_points(r_in, a_in, max(min_range, _SMALLEST_RANGE), max_range)
    min_points = max(int(min_line_points), 2)
    if len(points) < min_points:
        return []
    circular = _is_full_circle(a_in)
    x, y = points[:, 0], points[:, 1]
    brk = _breaks(x, y, beams, r_in.size, circular, max_line_gap)
    if circular and not brk[-1]:
        if brk.any():
            # Start just after a break so that no wall is cut in two by where the list starts.
            shift = int(np.flatnonzero(brk)[0]) + 1
            points, beams, brk = (np.concatenate((a[shift:], a[:shift])) for a in (points, beams, brk))
        else:
            # A closed ring of points: start at a split point found on a first pass.
            scan = _Scan(points, beams)
            s, _ = _split(scan, np.array([0]), np.array([len(points) - 1]), split_distance, min_points)
            if len(s) > 1:
                shift = int(s[1])
                points, beams = (np.concatenate((a[shift:], a[:shift])) for a in (points, beams))
            brk = np.zeros(len(points), dtype=bool)
            brk[-1] = True
    scan = _Scan(points, beams)
    ends = np.flatnonzero(brk)
    starts = np.concatenate(([0], ends[:-1] + 1))
    s, e = _split(scan, starts, ends, split_distance, min_points)
    sigma2 = range_sigma * range_sigma
    s, e, fits = _merge(scan, s, e, sigma2, merge_chi2, split_distance, max_line_gap, min_points)
    keep = e - s + 1 >= min_points
    if not keep.all():
        s, e, fits = s[keep], e[keep], None
    s, e = _trim_ends(scan, s, e, range_sigma, min_points, fits)
    return _final_lines(scan, s, e, sigma2, min_line_length)


def _trim_ends(scan: _Scan, s, e, range_sigma: float, min_points: int, fits=None):
    """Drop end points farther than _END_SIGMAS standard deviations (range noise seen along the
    normal) from their range's refitted line until none is; ranges left with fewer than
    min_points points are dropped.
    fits, if given, are the ranges' unweighted fits (cos alpha, sin alpha, r)."""
    # Each pass removes at least one point, so this ends; on a straight wall it takes one or two.
    while len(s):
        c, sn, r = fits if fits is not None else scan.fit(s, e)
        fits = None
        ends = np.stack((s, e), axis=1)
        x, y = scan.x[ends], scan.y[ends]
        d = x * c[:, None] + y * sn[:, None] - r[:, None]
        # cos of the incidence angle: (beam direction . normal), beam direction = point / range.
        cos2 = np.maximum((x * c[:, None] + y * sn[:, None]) ** 2 / (x * x + y * y), _MIN_COS2)
        bad = d * d > (_END_SIGMAS * range_sigma) ** 2 * cos2
        if not bad.any():
            break
        s = s + bad[:, 0]
        e = e - bad[:, 1]
        keep = e - s + 1 >= min_points
        s, e = s[keep], e[keep]
    return s, e


def _final_lines(scan: _Scan, s, e, sigma2: float, min_length: float) -> list[Line]:
    """Fit each range (unweighted least squares) and build the Line objects; the covariance
    propagates each point's distance variance sigma²·cos²(incidence) through that fit."""
    if not len(s):
        return []
    sums = scan.prefix[e + 1] - scan.prefix[s]
    fit = _PolarFits(sums)
    c, sn, n = fit.c, fit.s, sums[:, 0]
    index, owner, offsets = _ranges_within(e - s + 1, s)
    x, y = scan.x[index], scan.y[index]
    co, so = c[owner], sn[owner]
    # Only the range is noisy, so a point's distance noise is sigma·|cos(incidence)|.
    v = sigma2 * np.maximum((x * co + y * so) ** 2 / (x * x + y * y), _MIN_COS2)
    tm = c * fit.ym - sn * fit.xm                       # centroid's along-line coordinate
    u = y * co - x * so - tm[owner]                     # along-line coordinate about it
    vu = v * u
    terms = np.column_stack((v, vu, vu * u))
    sv, svu, svuu = np.add.reduceat(terms, offsets, axis=0).T
    suu = np.maximum(sn * sn * fit.sxx + c * c * fit.syy - 2.0 * sn * c * fit.sxy, 1e-12)
    # Covariance of (offset at the centroid q, alpha), then r = q + tm·alpha to first order.
    qq, qa, aa = sv / (n * n), -svu / (n * suu), svuu / (suu * suu)
    rr, ra = qq + 2.0 * tm * qa + tm * tm * aa, qa + tm * aa
    ends = np.stack((s, e), axis=1)
    px, py = scan.x[ends], scan.y[ends]
    c2, s2, r2 = c[:, None], sn[:, None], fit.r[:, None]
    dist = px * c2 + py * s2 - r2
    qx, qy = px - dist * c2, py - dist * s2
    keep = np.hypot(qx[:, 1] - qx[:, 0], qy[:, 1] - qy[:, 0]) >= min_length
    if not keep.any():
        return []
    rows = np.column_stack((fit.r, fit.alpha, rr, ra, aa, qx, qy))[keep].tolist()
    beams = np.column_stack((scan.beams[ends], e - s + 1))[keep].tolist()
    lines = [
        Line(r=row[0], alpha=row[1], covariance=np.array([[row[2], row[3]], [row[3], row[4]]]),
             start=(row[5], row[7]), end=(row[6], row[8]),
             first=b[0], last=b[1], point_count=b[2])
        for row, b in zip(rows, beams)
    ]
    # A 360-degree scan was processed from a break, not from beam 0.
    lines.sort(key=lambda line: line.first)
    return lines


def _check_options(split_distance, max_line_gap, min_line_points, min_line_length,
                   min_range, max_range, range_sigma, merge_chi2) -> None:
    positive = {'split_distance': split_distance, 'max_line_gap': max_line_gap,
                'range_sigma': range_sigma, 'merge_chi2': merge_chi2}
    for name, value in positive.items():
        if not (math.isfinite(value) and value > 0.0):
            raise ValueError(f'{name} must be a finite number > 0, got {value!r}')
    if not (math.isfinite(min_line_length) and min_line_length >= 0.0):
        raise ValueError(f'min_line_length must be a finite number >= 0, got {min_line_length!r}')
    if int(min_line_points) != min_line_points or min_line_points < 2:
        raise ValueError(f'min_line_points must be an integer >= 2, got {min_line_points!r}')
    if not (math.isfinite(min_range) and min_range >= 0.0 and max_range > min_range):
        raise ValueError(f'need 0 <= min_range < max_range, got {min_range!r} and {max_range!r}')
