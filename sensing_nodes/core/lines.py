"""Line extraction from a laser scan by split-and-merge, lines in polar form (laser frame, m, rad).

A line is x·cos(alpha) + y·sin(alpha) = r with r >= 0 and alpha in (-pi, pi]; a point's signed
distance to it is x·cos(alpha) + y·sin(alpha) - r (for a beam (rho, theta): rho·cos(theta - alpha)
- r).

Every least-squares fit during splitting and merging is O(1) from prefix sums of
(x, y, x², y², xy) prepared once per scan, and the splitting works on all segments of a scan at
once
(one numpy pass per level of the split tree) while there are many, then range by range on array
slices, so a scan costs O(n log n) array work. As numpy's cost per call (about a microsecond)
dominates at a few hundred beams, work whose size is the number of segments or lines (a dozen or
so) and the split of short ranges run on plain floats with the same arithmetic, and the cos and
sin of the beam angles are cached across scans with the same angles. The (r, alpha) covariance
of each line propagates every point's distance variance sigma_r²·cos²(theta_i - alpha) (range
noise seen along the normal, the noise model of Pfister et al. 2003) through the least-squares
fit. (A fit weighted by the inverse of those variances, as Pfister et al. propose, was tried: on
the real CARMEN logs it pulled lines up to 7 cm off their own end points, as the noise there is
not range-only.)
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import ArrayLike, NDArray

from sensing_nodes.parameters import CheckedAtConstruction

# cos²(incidence) is floored here: at grazing incidence the real error is dominated by beam width
# and mixed returns, not by the range noise (which would give a vanishing distance variance).
_MIN_COS2 = 0.05
# An end point farther than this many standard deviations of its distance from the fit is dropped:
# a split point found a beam or two off a corner lies on the other wall, within split_distance
# of this one. A split point within noise of both walls stays in both lines.
_END_SIGMAS = 3.0
_SMALLEST_RANGE = 1e-9
# numpy costs about a microsecond per call here: the split works on all ranges at once (sixty
# calls or so per level) while there are more than this many, then range by range (a dozen
# calls per range on array slices), a range of fewer than this many points on plain floats.
_BATCH_SPLIT_RANGES = 8
_FLOAT_SPLIT_POINTS = 16


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
    """Least-squares line fit of points (laser frame): alpha (rad), r (m), residual sum of squares
    (m²)."""

    alpha: float
    r: float
    residual: float


def fit_line(points: ArrayLike) -> PolarFit:
    """Perpendicular (total) least-squares line through (N, 2) points (m), N >= 2, from O(N)
    sums."""
    p = np.asarray(points, dtype=float).reshape(-1, 2)
    if len(p) < 2:
        raise ValueError(f'a line needs at least 2 points, got {len(p)}')
    sums = np.concatenate(([len(p)], p.sum(axis=0), (p * p).sum(axis=0), [p[:, 0] @ p[:, 1]]))
    fit = _Fits(sums[None, :])
    alpha, _, _, r = fit.normalised()
    spread = math.hypot(fit.sxx[0] - fit.syy[0], 2.0 * fit.sxy[0])
    residual = max(0.5 * (fit.sxx[0] + fit.syy[0] - spread), 0.0)  # smaller scatter eigenvalue
    return PolarFit(float(alpha[0]), float(r[0]), residual)


class _Fits:
    """Least-squares lines from rows of point sums (n, Σx, Σy, Σx², Σy², Σxy): the centroid
    (xm, ym), the centred scatter (sxx, syy, sxy) and the normal (c, s) = (cos, sin)(alpha) with
    offset r = (xm, ym)·(c, s), which may be negative here (see normalised()). A negative r
    flips the signs of c, s and every signed distance, never their size, so the split, merge
    and trim rules use the fits as they come. _fit_floats is the same fit on plain floats."""

    def __init__(self, sums: NDArray[np.float64]) -> None:
        w = self.w = sums[:, 0]
        xm, ym = self.xm, self.ym = sums[:, 1] / w, sums[:, 2] / w
        self.sxx = sums[:, 3] - xm * sums[:, 1]
        self.syy = sums[:, 4] - ym * sums[:, 2]
        self.sxy = sums[:, 5] - xm * sums[:, 2]
        self.alpha = 0.5 * np.arctan2(-2.0 * self.sxy, self.syy - self.sxx)   # in [-pi/2, pi/2]
        self.c, self.s = np.cos(self.alpha), np.sin(self.alpha)
        self.r = xm * self.c + ym * self.s

    def normalised(self):
        """(alpha, cos alpha, sin alpha, r) with r >= 0 and alpha in (-pi, pi]."""
        flip = self.r < 0.0
        alpha = self.alpha
        # Turning the normal by pi keeps the line and makes r positive.
        alpha = np.where(flip, np.where(alpha > 0.0, alpha - np.pi, alpha + np.pi), alpha)
        alpha = np.where(alpha <= -np.pi, alpha + 2.0 * np.pi, alpha)   # -pi rounds to pi
        return (alpha, np.where(flip, -self.c, self.c), np.where(flip, -self.s, self.s),
                np.abs(self.r))


class _Scan:
    """Valid points of one scan in processing order, with prefix sums for O(1) segment fits."""

    def __init__(
        self, x: NDArray[np.float64], y: NDArray[np.float64], beams: NDArray[np.intp]
    ) -> None:
        self.x, self.y, self.beams = x, y, beams
        prefix = np.empty((len(self.x) + 1, 6))
        prefix[0] = 0.0
        terms = prefix[1:]
        terms[:, 0] = 1.0
        terms[:, 1] = self.x
        terms[:, 2] = self.y
        np.multiply(self.x, self.x, out=terms[:, 3])
        np.multiply(self.y, self.y, out=terms[:, 4])
        np.multiply(self.x, self.y, out=terms[:, 5])
        self.rho2 = terms[:, 3] + terms[:, 4]           # squared range of each point (m²)
        np.cumsum(terms, axis=0, out=terms)
        self.prefix = prefix
        self.counter = np.arange(2 * len(self.x) + 1)   # indices: a range list holds < 2n points

    def ranges(self, s: NDArray[np.intp], counts: NDArray[np.intp]):
        """Point indices of the ranges [s, s + counts) one after another, the range each comes
        from, and where each range begins in that list."""
        offsets = np.add.accumulate(counts)
        total = int(offsets[-1])
        offsets -= counts
        owner = self.counter[:len(counts)].repeat(counts)
        index = (s - offsets).repeat(counts)
        index += self.counter[:total]
        return index, owner, offsets

    def fit(self, s: NDArray[np.intp], e: NDArray[np.intp]) -> _Fits:
        """Fits of the inclusive point ranges [s, e]."""
        return _Fits(self.prefix[e + 1] - self.prefix[s])


def _split(scan: _Scan, s: NDArray[np.intp], e: NDArray[np.intp], split_distance: float,
           min_points: int) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """Split every range [s, e] until its fit's farthest point is within split_distance.

    A range that must split is cut at its point farthest from the chord between its end points
    (robust to a corner near one end, where the farthest point from the fit is the end itself);
    that point goes to both halves (_trim_ends later drops it where it does not fit).
    """
    done_s, done_e = [], []
    smallest = max(min_points, 3)
    x, y = scan.x, scan.y
    while True:
        if len(s) <= _BATCH_SPLIT_RANGES:
            _split_ranges(scan, s.tolist(), e.tolist(), split_distance, smallest, done_s, done_e)
            break
        n = e - s + 1
        fit = scan.fit(s, e)
        c, sn, r = fit.c, fit.s, fit.r
        index, owner, offsets = scan.ranges(s, n)
        xi, yi = x[index], y[index]
        # Fewer points than `smallest` are never split (their fit is computed but not used).
        final = n < smallest
        dist = xi * c[owner]
        dist += yi * sn[owner]
        dist -= r[owner]
        final |= np.maximum.reduceat(np.abs(dist, out=dist), offsets) <= split_distance
        done_s.append(s[final])
        done_e.append(e[final])
        if np.count_nonzero(final) == len(final):
            break
        # Distance to the chord through each range's first and last point, times the chord's
        # length (which does not move the argmax); computed for every range, used for the others.
        x0, y0 = x[s], y[s]
        dx, dy = x[e] - x0, y[e] - y0
        chord = xi * dy[owner]
        chord -= yi * dx[owner]
        chord -= (x0 * dy - y0 * dx)[owner]
        np.abs(chord, out=chord)
        top = np.maximum.reduceat(chord, offsets)[owner]
        # The first point of each range at its maximum (index grows within a range).
        at = np.minimum.reduceat(np.where(chord == top, index, len(scan.counter)), offsets)
        split = ~final
        s, e, at = s[split], e[split], at[split]
        np.maximum(at, s + 1, out=at)
        np.minimum(at, e - 1, out=at)
        s, e = np.concatenate((s, at)), np.concatenate((at, e))
    s, e = np.concatenate(done_s), np.concatenate(done_e)
    order = np.lexsort((e, s))
    return s[order], e[order]


def _split_ranges(scan: _Scan, s: list[int], e: list[int], split_distance: float, smallest: int,
                  done_s: list, done_e: list) -> None:
    """_split range by range, for a few ranges: a short range on plain floats, a longer one on
    array slices (no gathers). Same arithmetic and the same first farthest point as _split;
    appends the final ranges as arrays to done_s and done_e."""
    x, y, prefix = scan.x, scan.y, scan.prefix
    todo = list(zip(s, e))
    out_s, out_e = [], []
    while todo:
        lo, hi = todo.pop()
        at = None                                   # where to split, from lo, if it must
        if hi - lo + 1 >= smallest:
            c, sn, r = _fit_floats((prefix[hi + 1] - prefix[lo]).tolist())[:3]
            if hi - lo < _FLOAT_SPLIT_POINTS:
                xs, ys = x[lo:hi + 1].tolist(), y[lo:hi + 1].tolist()
                if max(abs(px * c + py * sn - r) for px, py in zip(xs, ys)) > split_distance:
                    x0, y0 = xs[0], ys[0]
                    dx, dy = xs[-1] - x0, ys[-1] - y0
                    k0 = x0 * dy - y0 * dx
                    top, at = -1.0, 0
                    for i, (px, py) in enumerate(zip(xs, ys)):
                        chord = abs(px * dy - py * dx - k0)
                        if chord > top:
                            top, at = chord, i
            else:
                xs, ys = x[lo:hi + 1], y[lo:hi + 1]
                along = xs * c
                along += ys * sn
                # max |along - r|: rounding is monotonic, so it is at one of the two extremes
                # (argmax and argmin cost less than max and min here).
                if max(float(along[along.argmax()]) - r,
                       r - float(along[along.argmin()])) > split_distance:
                    x0, y0 = float(xs[0]), float(ys[0])
                    dx, dy = float(xs[-1]) - x0, float(ys[-1]) - y0
                    chord = xs * dy
                    chord -= ys * dx
                    chord -= x0 * dy - y0 * dx
                    at = int(np.abs(chord, out=chord).argmax())
        if at is not None:
            at = min(max(lo + at, lo + 1), hi - 1)
            todo.append((lo, at))
            todo.append((at, hi))
            continue
        out_s.append(lo)
        out_e.append(hi)
    done_s.append(np.array(out_s, dtype=np.intp))
    done_e.append(np.array(out_e, dtype=np.intp))


def _merge(scan: _Scan, s, e, options: LineOptions, min_points: int):
    """Merge neighbouring ranges whose lines agree within their summed covariance (chi-square on
    (dr, dalpha), 2 dof) when the gap between them is at most max_line_gap and the merged fit
    still has every point within split_distance. A range of fewer than min_points points (a
    piece of wall between invalid beams, or an outlier) needs only the gap and the merged fit to
    pass. Also returns the ranges' fits (cos, sin, r) when they were computed and nothing
    merged."""
    if len(s) < 2:
        return s, e, None
    xs, ys, xe, ye = scan.x[s], scan.y[s], scan.x[e], scan.y[e]
    near = np.hypot(xs[1:] - xe[:-1], ys[1:] - ye[:-1]) <= options.max_line_gap
    near &= s[1:] >= e[:-1]
    if not np.count_nonzero(near):
        return s, e, None
    # A scan has a dozen ranges or so: per range and per pair, plain floats cost less than
    # numpy calls.
    fits = [_polar_fit_floats(row) for row in (scan.prefix[e + 1] - scan.prefix[s]).tolist()]
    s_l, e_l = s.tolist(), e.tolist()
    ends = (xs.tolist(), ys.tolist(), xe.tolist(), ye.tolist())
    candidate = _merge_candidates(fits, s_l, e_l, near.tolist(), ends, options, min_points)
    if not any(candidate):
        return s, e, tuple(np.array([f[j] for f in fits]) for j in range(3))
    split_distance = options.split_distance
    out_s, out_e = [s_l[0]], [e_l[0]]
    for k in range(1, len(s_l)):
        if candidate[k - 1] and out_e[-1] == e_l[k - 1]:
            lo, hi = out_s[-1], e_l[k]
            cm, sm, rm = _fit_floats((scan.prefix[hi + 1] - scan.prefix[lo]).tolist())[:3]
            if (
                np.abs(scan.x[lo : hi + 1] * cm + scan.y[lo : hi + 1] * sm - rm).max()
                <= split_distance
            ):
                out_e[-1] = hi
                continue
        out_s.append(s_l[k])
        out_e.append(e_l[k])
    return np.array(out_s), np.array(out_e), None


def _merge_candidates(fits, s_l, e_l, near_l, ends, options: LineOptions,
                      min_points: int) -> list[bool]:
    """Per neighbouring pair of ranges, whether _merge should try the merged fit: fits from
    _polar_fit_floats, ends = the ranges' first and last points (xs, ys, xe, ye) as lists."""
    xs_l, ys_l, xe_l, ye_l = ends
    split_distance, sigma2 = options.split_distance, options.range_sigma * options.range_sigma
    candidate = [False] * (len(s_l) - 1)
    for k in range(1, len(s_l)):
        if not near_l[k - 1]:
            continue
        left, right = fits[k - 1], fits[k]
        small_l, small_r = (
            e_l[k - 1] - s_l[k - 1] + 1 < min_points,
            e_l[k] - s_l[k] + 1 < min_points,
        )
        if small_l or small_r:
            # A small range joins a neighbour only when its far end is within split_distance of
            # the neighbour's line (the merged fit is checked below); two small ones directly.
            candidate[k - 1] = (small_l and small_r) or (
                small_r and abs(xe_l[k] * left[0] + ye_l[k] * left[1] - left[2]) <= split_distance
            ) or (
                small_l and abs(xs_l[k - 1] * right[0] + ys_l[k - 1] * right[1] - right[2])
                <= split_distance)
            continue
        # Unweighted fits: information scaled by 1 / sigma² (the distance noise is at most sigma).
        rr, ra, aa = ((right[j] + left[j]) * sigma2 for j in (4, 5, 6))
        dr = right[2] - left[2]
        da = right[3] - left[3]
        if da > math.pi:
            da -= 2.0 * math.pi
        elif da <= -math.pi:
            da += 2.0 * math.pi
        candidate[k - 1] = _divide(aa * dr * dr - 2.0 * ra * dr * da + rr * da * da,
                                   rr * aa - ra * ra) <= options.merge_chi2
    return candidate


def _fit_floats(d: list[float]) -> tuple[float, ...]:
    """_Fits of one row of sums (n, Σx, Σy, Σx², Σy², Σxy) on plain floats (a dozen ranges per
    scan: numpy calls cost more than the arithmetic): (cos alpha, sin alpha, r) as _Fits has
    them (r may be negative), then alpha, the centroid and the centred scatter."""
    w, sx, sy, sxx, syy, sxy = d
    xm, ym = sx / w, sy / w
    sxx, syy, sxy = sxx - xm * sx, syy - ym * sy, sxy - xm * sy
    alpha = 0.5 * math.atan2(-2.0 * sxy, syy - sxx)
    c, sn = math.cos(alpha), math.sin(alpha)
    return c, sn, xm * c + ym * sn, alpha, w, xm, ym, sxx, syy, sxy


def _polar_fit_floats(d: list[float]) -> tuple[float, ...]:
    """_fit_floats normalised as _Fits.normalised: (cos alpha, sin alpha, r, alpha), then
    (var r, cov r-alpha, var alpha) for unit distance variance per point."""
    c, sn, r, alpha, w, xm, ym, sxx, syy, sxy = _fit_floats(d)
    if r < 0.0:
        alpha = alpha - math.pi if alpha > 0.0 else alpha + math.pi
        c, sn, r = -c, -sn, -r
    if alpha <= -math.pi:
        alpha += 2.0 * math.pi
    # Along-line coordinate t = p·(-sin, cos): its spread about the centroid and the centroid's t.
    # Floored so that a degenerate fit (one point) gives a huge but finite covariance.
    stt = max(sn * sn * sxx + c * c * syy - 2.0 * sn * c * sxy, 1e-12)
    tm = c * ym - sn * xm
    return c, sn, r, alpha, 1.0 / w + tm * tm / stt, tm / stt, 1.0 / stt


def _divide(a: float, b: float) -> float:
    """a / b with numpy's result for b == 0 (±inf, or nan for 0 / 0)."""
    if b != 0.0:
        return a / b
    if a == 0.0 or math.isnan(a):
        return math.nan
    return math.copysign(math.inf, a) * math.copysign(1.0, b)


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
    np.not_equal(beams[1:] - beams[:-1], 1, out=brk[:-1])
    brk[:-1] |= np.hypot(x[1:] - x[:-1], y[1:] - y[:-1]) > max_gap
    brk[-1] = not (circular and beams[0] == 0 and beams[-1] == beam_count - 1
                   and math.hypot(x[0] - x[-1], y[0] - y[-1]) <= max_gap)
    return brk


@dataclass(frozen=True, slots=True)
class _Beams:
    """What depends only on a scan's beam angles: cos and sin of each, which are finite (None
    when all are), and whether the scan covers the full circle."""

    cos: NDArray[np.float64]
    sin: NDArray[np.float64]
    finite: NDArray[np.bool_] | None
    circular: bool


# A scan stream repeats the same angles scan after scan: computing their cos and sin once saves
# two of the per-scan array passes. Keyed by the angles' bytes, a few angle sets at most.
_BEAMS_CACHE: dict[bytes, _Beams] = {}
_BEAMS_CACHE_SIZE = 8


def _beams(angles: NDArray[np.float64]) -> _Beams:
    """The _Beams of these angles (rad), from the cache when seen recently."""
    key = angles.tobytes()
    beams = _BEAMS_CACHE.get(key)
    if beams is None:
        finite = np.isfinite(angles)
        beams = _Beams(np.cos(angles), np.sin(angles), None if finite.all() else finite,
                       _is_full_circle(angles))
        if len(_BEAMS_CACHE) >= _BEAMS_CACHE_SIZE:
            del _BEAMS_CACHE[next(iter(_BEAMS_CACHE))]
        _BEAMS_CACHE[key] = beams
    return beams


@dataclass(frozen=True)
class LineOptions(CheckedAtConstruction):
    """Settings of extract_lines, checked once (ValueError for values that make no sense).

    split_distance: a segment is split while a point is farther than this from its fit (m);
    max_line_gap: no line spans two consecutive points farther apart than this (m);
    min_line_points, min_line_length (m): smaller lines are dropped;
    min_range, max_range (m): beams outside are invalid, like NaN and ±inf (and a range of 0);
    range_sigma: standard deviation of the range noise (m), scales the covariances;
    merge_chi2: neighbouring segments merge when chi-square of (dr, dalpha) is at most this
    (2 degrees of freedom; 9.21 is the 99 % quantile).
    """

    split_distance: float = 0.05
    max_line_gap: float = 0.5
    min_line_points: int = 6
    min_line_length: float = 0.2
    min_range: float = 0.0
    max_range: float = np.inf
    range_sigma: float = 0.01
    merge_chi2: float = 9.21

    def problems(self) -> list[tuple[str, str, object]]:
        """(field, problem, value) for each setting that makes no sense."""
        out: list[tuple[str, str, object]] = []
        for name in ('split_distance', 'max_line_gap', 'range_sigma', 'merge_chi2'):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0.0):
                out.append((name, 'must be a finite number > 0', value))
        if not (math.isfinite(self.min_line_length) and self.min_line_length >= 0.0):
            out.append(('min_line_length', 'must be a finite number >= 0',
                        self.min_line_length))
        if int(self.min_line_points) != self.min_line_points or self.min_line_points < 2:
            out.append(('min_line_points', 'must be an integer >= 2', self.min_line_points))
        if not (math.isfinite(self.min_range) and self.min_range >= 0.0):
            out.append(('min_range', 'must be a finite number >= 0', self.min_range))
        elif not self.max_range > self.min_range:
            out.append(('max_range', 'must be greater than min_range', self.max_range))
        return out


_DEFAULT_OPTIONS = LineOptions()


def extract_lines(ranges: ArrayLike, angles: ArrayLike, *, options: LineOptions | None = None,
                  **keywords) -> list[Line]:
    """Lines (laser frame) in a scan given as ranges (m, REP 117 values allowed) and beam angles
    (rad).

    Settings: `options=LineOptions(...)` or its fields as keywords (set on top of `options`).
    Lines are sorted by first beam. Raises ValueError for ranges and angles of different lengths
    and for option values that make no sense (TypeError for an unknown name); otherwise returns
    what it finds (possibly nothing).
    """
    if options is None:
        options = LineOptions(**keywords) if keywords else _DEFAULT_OPTIONS
    elif keywords:
        options = replace(options, **keywords)
    r_in = np.asarray(ranges, dtype=float).ravel()
    a_in = np.asarray(angles, dtype=float).ravel()
    if r_in.shape != a_in.shape:
        raise ValueError(f'ranges ({r_in.size}) and angles ({a_in.size}) differ in length')
    table = _beams(a_in)
    beams = _valid_beams(r_in, table, options)
    min_points = max(int(options.min_line_points), 2)
    if len(beams) < min_points:
        return []
    rho = r_in[beams]
    x, y = rho * table.cos[beams], rho * table.sin[beams]
    scan, brk = _ordered_scan(x, y, beams, r_in.size, table.circular, options, min_points)
    ends = brk.nonzero()[0]
    starts = np.concatenate(([0], ends[:-1] + 1))
    s, e = _split(scan, starts, ends, options.split_distance, min_points)
    s, e, fits = _merge(scan, s, e, options, min_points)
    keep = e - s + 1 >= min_points
    if np.count_nonzero(keep) < len(keep):
        s, e, fits = s[keep], e[keep], None
    s, e = _trim_ends(scan, s, e, options.range_sigma, min_points, fits)
    return _final_lines(scan, s, e, options.range_sigma * options.range_sigma,
                        options.min_line_length)


def _valid_beams(r_in: NDArray[np.float64], table: _Beams,
                 options: LineOptions) -> NDArray[np.intp]:
    """Indices of the valid beams, as in core.scan.valid_ranges (REP 117); a zero range is no
    point on a surface, whatever min_range says. NaN fails every comparison; +inf the second."""
    valid = r_in >= max(options.min_range, _SMALLEST_RANGE)
    max_range = options.max_range
    valid &= r_in <= max_range if math.isfinite(max_range) else r_in < math.inf
    if table.finite is not None:
        valid &= table.finite
    return valid.nonzero()[0]


def _ordered_scan(x, y, beams, beam_count: int, circular: bool, options: LineOptions,
                  min_points: int) -> tuple[_Scan, NDArray[np.bool_]]:
    """The _Scan of the valid points and its breaks (see _breaks); a full-circle scan is
    rotated to start where no wall is cut in two."""
    brk = _breaks(x, y, beams, beam_count, circular, options.max_line_gap)
    if circular and not brk[-1]:
        ends = brk.nonzero()[0]
        if len(ends):
            # Start just after a break so that no wall is cut in two by where the list starts.
            shift = int(ends[0]) + 1
            x, y, beams, brk = (np.concatenate((a[shift:], a[:shift])) for a in (x, y, beams, brk))
        else:
            # A closed ring of points: start at a split point found on a first pass.
            scan = _Scan(x, y, beams)
            s, _ = _split(scan, np.array([0]), np.array([len(x) - 1]), options.split_distance,
                          min_points)
            if len(s) > 1:
                shift = int(s[1])
                x, y, beams = (np.concatenate((a[shift:], a[:shift])) for a in (x, y, beams))
            brk = np.zeros(len(x), dtype=bool)
            brk[-1] = True
    return _Scan(x, y, beams), brk


def _trim_ends(scan: _Scan, s, e, range_sigma: float, min_points: int, fits=None):
    """Drop end points farther than _END_SIGMAS standard deviations (range noise seen along the
    normal) from their range's refitted line until none is; ranges left with fewer than
    min_points points are dropped.
    fits, if given, are the ranges' unweighted fits (cos alpha, sin alpha, r)."""
    if not len(s):
        return s, e
    if fits is None:
        fit = scan.fit(s, e)
        fits = fit.c, fit.s, fit.r
    c, sn, r = fits
    ends = np.stack((s, e), axis=1)
    x, y = scan.x[ends], scan.y[ends]
    c2, s2 = c[:, None], sn[:, None]
    along = x * c2 + y * s2
    d = along - r[:, None]
    # cos of the incidence angle: (beam direction . normal), beam direction = point / range.
    limit2 = (_END_SIGMAS * range_sigma) ** 2
    bad = d * d > limit2 * np.maximum(along * along / scan.rho2[ends], _MIN_COS2)
    if not np.count_nonzero(bad):
        return s, e
    # A range whose ends all fit keeps its fit; the few others are trimmed one at a time, on
    # plain floats (each step removes at least one point, so this ends; a wall takes one or two).
    s_out, e_out = s.tolist(), e.tolist()
    kept = [True] * len(s_out)
    x, y, rho2, prefix = scan.x, scan.y, scan.rho2, scan.prefix
    for k in np.flatnonzero(bad.any(axis=1)).tolist():
        lo, hi = s_out[k], e_out[k]
        bad_lo, bad_hi = bool(bad[k, 0]), bool(bad[k, 1])
        while True:
            lo, hi = lo + bad_lo, hi - bad_hi
            if hi - lo + 1 < min_points:
                kept[k] = False
                break
            ck, sk, rk = _fit_floats((prefix[hi + 1] - prefix[lo]).tolist())[:3]
            bad_lo = bad_hi = False
            for end in (lo, hi):
                xe, ye = float(x[end]), float(y[end])
                along_e = xe * ck + ye * sk
                de = along_e - rk
                if de * de > limit2 * max(along_e * along_e / float(rho2[end]), _MIN_COS2):
                    if end == lo:
                        bad_lo = True
                    else:
                        bad_hi = True
            if not (bad_lo or bad_hi):
                break
        s_out[k], e_out[k] = lo, hi
    keep = np.array(kept)
    return np.array(s_out)[keep], np.array(e_out)[keep]


def _final_lines(scan: _Scan, s, e, sigma2: float, min_length: float) -> list[Line]:
    """Fit each range (unweighted least squares) and build the Line objects; the covariance
    propagates each point's distance variance sigma²·cos²(incidence) through that fit."""
    if not len(s):
        return []
    fit = scan.fit(s, e)
    alpha, c, sn, r = fit.normalised()
    n = fit.w
    counts = e - s + 1
    index, owner, offsets = scan.ranges(s, counts)
    x, y = scan.x[index], scan.y[index]
    co, so = c[owner], sn[owner]
    # Only the range is noisy, so a point's distance noise is sigma·|cos(incidence)|.
    along = x * co + y * so
    terms = np.empty((len(index), 3))
    v = np.multiply(
        sigma2, np.maximum(along * along / scan.rho2[index], _MIN_COS2), out=terms[:, 0]
    )
    tm = c * fit.ym - sn * fit.xm                       # centroid's along-line coordinate
    u = y * co - x * so - tm[owner]                     # along-line coordinate about it
    vu = np.multiply(v, u, out=terms[:, 1])
    np.multiply(vu, u, out=terms[:, 2])
    sums_v = np.add.reduceat(terms, offsets, axis=0)
    # A dozen lines or so: the rest is per line, on plain floats (the same arithmetic).
    per_line = np.array((n, c, sn, r, alpha, tm, fit.sxx, fit.syy, fit.sxy,
                         scan.x[s], scan.y[s], scan.x[e], scan.y[e])).T.tolist()
    first, last, counts = scan.beams[s].tolist(), scan.beams[e].tolist(), counts.tolist()
    lines = []
    for k, ((w, ck, sk, rk, ak, tk, sxx, syy, sxy, x0, y0, x1, y1), (sv, svu, svuu)) in enumerate(
            zip(per_line, sums_v.tolist())):
        # End points projected onto the line.
        d0, d1 = x0 * ck + y0 * sk - rk, x1 * ck + y1 * sk - rk
        start, end = (x0 - d0 * ck, y0 - d0 * sk), (x1 - d1 * ck, y1 - d1 * sk)
        if not math.hypot(end[0] - start[0], end[1] - start[1]) >= min_length:
            continue
        suu = max(sk * sk * sxx + ck * ck * syy - 2.0 * sk * ck * sxy, 1e-12)
        # Covariance of (offset at the centroid q, alpha), then r = q + tm·alpha to first order.
        qq, qa, aa = sv / (w * w), -svu / (w * suu), svuu / (suu * suu)
        rr, ra = qq + 2.0 * tk * qa + tk * tk * aa, qa + tk * aa
        lines.append(Line(r=rk, alpha=ak, covariance=np.array(((rr, ra), (ra, aa))), start=start,
                          end=end, first=first[k], last=last[k], point_count=counts[k]))
    # A 360-degree scan was processed from a break, not from beam 0.
    lines.sort(key=lambda line: line.first)
    return lines
