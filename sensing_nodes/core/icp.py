"""2-D ICP scan matching: point-to-point (closed-form SVD) and point-to-line (Gauss-Newton).

Frame convention: the result (x, y, yaw) maps source points into the target frame,
target ≈ R(yaw)·source + (x, y). Matching scan k+1 (source) against scan k (target) therefore
gives the pose of scan k+1 in the frame of scan k. Units: metres and radians.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree


# Variance (m², rad²) put on the diagonal of a failed match's covariance: large enough that any
# fusion ignores it, finite so arithmetic stays sane.
FAILED_VARIANCE = 1.0e6
# Variance (m², yaw as arc length at the scan radius) added along an unconstrained direction:
# far above any motion between scans, yet small enough that the slight tilt of that direction
# does not leak into the constrained ones.
DEGENERATE_VARIANCE = 100.0

_METHODS = ('point_to_line', 'point_to_point')
_ROBUST = ('trim', 'adaptive', 'none')


@dataclass(frozen=True)
class Target:
    """A target scan prepared once for many matches: points (N, 2) in its frame (m), a k-d tree,
    unit normals (N, 2) from the neighbouring points, how line-like each neighbourhood is
    (`planarity` in [0, 1]: 1 = points exactly on a line), and the 2x2 information matrix each
    point gives a residual, as (N, 3) rows (m00, m01, m11): n·nᵀ + tangent_weight·I on a line
    (point-to-line), I elsewhere (corners and isolated points act point-to-point)."""

    points: NDArray[np.float64]
    tree: cKDTree
    normals: NDArray[np.float64]
    planarity: NDArray[np.float64]
    information: NDArray[np.float64]
    dropped: int = 0          # non-finite rows removed from the input


@dataclass
class MatchResult:
    """Transform of the source into the target frame (m, rad) with its 3x3 covariance over
    (x, y, yaw). `error` is the mean residual (m) of the inlier correspondences: along the
    target's normal where the target is line-like (point-to-line), the point-to-point distance
    at corners and isolated points and with method='point_to_point'. `iterations` counts the
    full-resolution iterations (a yaw-hypothesis stage runs before them). `converged` is True only when
    the increment fell below the tolerance before `max_iterations`; `reason` says why not.
    `degenerate` flags a direction the geometry does not constrain (a corridor's axis), along which
    the covariance is inflated; `degenerate_direction` is that unit vector over (x, y, yaw·L)."""

    x: float
    y: float
    yaw: float
    covariance: NDArray[np.float64]
    iterations: int
    converged: bool
    error: float
    reason: str = ''
    degenerate: bool = False
    degenerate_direction: NDArray[np.float64] | None = None
    inliers: int = 0
    source_points: int = 0
    dropped_points: int = 0
    condition: float = math.inf            # smallest/largest eigenvalue ratio of the normal matrix
    history: list[float] = field(default_factory=list)   # mean error per iteration

    @property
    def pose(self) -> tuple[float, float, float]:
        return (self.x, self.y, self.yaw)

    @property
    def ok(self) -> bool:
        """Converged and not degenerate: safe to use as a measurement."""
        return self.converged and not self.degenerate


def _as_points(points: ArrayLike, name: str) -> tuple[NDArray[np.float64], int]:
    """(N, 2) finite float array and the number of non-finite rows dropped; ValueError on a
    wrong shape (that is a malformed call, not bad data)."""
    try:
        array = np.asarray(points, dtype=float)
    except (TypeError, ValueError) as exc:
        raise ValueError(f'{name} must be an (N, 2) array of numbers: {exc}') from exc
    if array.ndim != 2 or array.shape[1] != 2:
        raise ValueError(f'{name} must have shape (N, 2), got {array.shape}')
    finite = np.isfinite(array).all(axis=1)
    if finite.all():
        return array, 0
    return array[finite], int(array.shape[0] - finite.sum())


def cross_covariance(
    source: ArrayLike, target: ArrayLike, weights: ArrayLike | None = None
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Centroids p̄, q̄ (m) of index-paired source and target points and H = Σ wᵢ·p'ᵢ·q'ᵢᵀ over
    the centred points p' = p - p̄, q' = q - q̄."""
    p = np.asarray(source, dtype=float).reshape(-1, 2)
    q = np.asarray(target, dtype=float).reshape(-1, 2)
    if p.shape != q.shape or p.shape[0] == 0:
        raise ValueError(f'paired point sets must be non-empty and equal in shape: {p.shape} vs {q.shape}')
    w = np.ones(p.shape[0]) if weights is None else np.asarray(weights, dtype=float).ravel()
    if w.shape != (p.shape[0],) or not np.all(w >= 0) or w.sum() <= 0:
        raise ValueError('weights must be one non-negative number per pair, not all zero')
    p_mean = w @ p / w.sum()
    q_mean = w @ q / w.sum()
    return p_mean, q_mean, (p - p_mean).T @ ((q - q_mean) * w[:, None])


def align_paired(
    source: ArrayLike, target: ArrayLike, weights: ArrayLike | None = None
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Closed-form least-squares rigid transform (R 2x2, t 2) with target_i ≈ R·source_i + t for
    points paired by index: centroids, H = Σ p'·q'ᵀ, SVD H = U·S·Vᵀ, R = V·Uᵀ, with the sign of the
    last singular vector flipped when det(V·Uᵀ) < 0 so a reflection is never returned;
    t = q̄ - R·p̄."""
    p_mean, q_mean, h = cross_covariance(source, target, weights)
    u, _, vt = np.linalg.svd(h)
    d = 1.0 if np.linalg.det(vt.T @ u.T) >= 0 else -1.0
    r = vt.T @ np.diag([1.0, d]) @ u.T
    return r, q_mean - r @ p_mean


def _line_normals(points: NDArray[np.float64], tree: cKDTree, neighbours: int,
                  radius: float) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Unit normal and planarity (1 - λmin/λmax of the neighbourhood scatter) per point."""
    n = points.shape[0]
    k = min(neighbours, n)
    distance, index = tree.query(points, k=k, distance_upper_bound=radius)
    if k == 1:
        distance, index = distance[:, None], index[:, None]
    present = np.isfinite(distance)
    index = np.where(present, index, np.arange(n)[:, None])
    neighbourhood = points[index]                                   # (N, k, 2)
    count = present.sum(axis=1)
    weights = present.astype(float)
    mean = (neighbourhood * weights[..., None]).sum(axis=1) / count[:, None]
    d = (neighbourhood - mean[:, None, :]) * weights[..., None]
    sxx = (d[..., 0] ** 2).sum(axis=1)
    syy = (d[..., 1] ** 2).sum(axis=1)
    sxy = (d[..., 0] * d[..., 1]).sum(axis=1)
    # Principal axis of a 2x2 scatter in closed form; the normal is perpendicular to it.
    theta = 0.5 * np.arctan2(2.0 * sxy, sxx - syy)
    normals = np.column_stack((-np.sin(theta), np.cos(theta)))
    half_trace = 0.5 * (sxx + syy)
    spread = np.sqrt((0.5 * (sxx - syy)) ** 2 + sxy ** 2)
    with np.errstate(invalid='ignore', divide='ignore'):
        planarity = np.where(half_trace > 0, spread / half_trace, 0.0)   # (λ1-λ2)/(λ1+λ2)
    planarity[count < 3] = 0.0
    return normals, np.clip(planarity, 0.0, 1.0)


def prepare_target(points: ArrayLike, normal_neighbours: int = 7, normal_radius: float = 1.0,
                   min_planarity: float = 0.5, tangent_weight: float = 0.0) -> Target:
    """Build the k-d tree, normals and per-point information of a target point set (N, 2), m,
    in its own frame; a point is line-like when its planarity >= min_planarity. Non-finite rows
    are dropped (counted in `dropped`); ValueError on a wrong shape or bad settings."""
    if not (normal_neighbours >= 2 and normal_radius > 0 and 0 <= min_planarity <= 1
            and 0 <= tangent_weight <= 1):
        raise ValueError('normal_neighbours >= 2, normal_radius > 0, 0 <= min_planarity <= 1 and '
                         '0 <= tangent_weight <= 1 required')
    array, dropped = _as_points(points, 'target')
    if array.shape[0] == 0:
        return Target(array, cKDTree(np.zeros((0, 2))), np.zeros((0, 2)), np.zeros(0),
                      np.zeros((0, 3)), dropped)
    tree = cKDTree(array)
    normals, planarity = _line_normals(array, tree, normal_neighbours, normal_radius)
    line = planarity >= min_planarity
    information = np.column_stack((
        np.where(line, normals[:, 0] ** 2 + tangent_weight, 1.0),
        np.where(line, normals[:, 0] * normals[:, 1], 0.0),
        np.where(line, normals[:, 1] ** 2 + tangent_weight, 1.0),
    ))
    return Target(array, tree, normals, planarity, information, dropped)


def voxel_downsample(points: ArrayLike, voxel_size: float) -> NDArray[np.float64]:
    """Centroid of the points in each square voxel of side voxel_size (m); order follows voxel keys."""
    pts = np.asarray(points, dtype=float).reshape(-1, 2)
    if voxel_size <= 0 or pts.shape[0] == 0:
        return pts
    keys = np.floor(pts / voxel_size).astype(np.int64)
    _, inverse, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.ravel()
    sums = np.zeros((counts.size, 2))
    np.add.at(sums, inverse, pts)
    return sums / counts[:, None]


def _failed(initial, reason: str, source_n: int = 0, dropped: int = 0) -> MatchResult:
    return MatchResult(
        x=float(initial[0]), y=float(initial[1]), yaw=float(initial[2]),
        covariance=np.eye(3) * FAILED_VARIANCE, iterations=0, converged=False,
        error=math.nan, reason=reason, source_points=source_n, dropped_points=dropped)


@dataclass
class _Loop:
    """State at the end of an ICP loop (internal)."""

    x: float
    y: float
    yaw: float
    iterations: int = 0
    converged: bool = False
    reason: str = ''
    error: float = math.nan
    inliers: int = 0
    history: list[float] = field(default_factory=list)
    p: NDArray[np.float64] | None = None          # moved inlier source points (last iteration)
    matched: NDArray[np.intp] | None = None       # index of each one's target neighbour


def _median(values: NDArray[np.float64]) -> float:
    k = values.size // 2
    return float(np.partition(values, k)[k])


def _icp_loop(src, tgt: Target, pose, *, point_to_line: bool, max_iterations: int, gate: float,
              min_gate: float, tolerance: float, robust: str, trim_fraction: float,
              adaptive_factor: float, min_inliers: int, radius: float,
              solve_ratio: float, error_tolerance: float, stall_iterations: int) -> _Loop:
    """Iterate correspondences and closed-form / Gauss-Newton steps from pose (x, y, yaw)."""
    state = _Loop(*pose, reason=f'max_iterations ({max_iterations}) reached')
    x, y, yaw = pose
    previous: NDArray[np.intp] | None = None
    best_error, stalled = math.inf, 0
    scale = np.array([1.0, 1.0, 1.0 / radius])
    outer = scale[:, None] * scale[None, :]
    floor_sq = (0.25 * min_gate) ** 2
    for iteration in range(1, max_iterations + 1):
        state.iterations = iteration
        c, s = math.cos(yaw), math.sin(yaw)
        moved = src @ np.array([[c, s], [-s, c]])
        moved += (x, y)
        distance, index = tgt.tree.query(moved, k=1, distance_upper_bound=gate)
        keep = distance < gate
        count = int(np.count_nonzero(keep))
        if count < min_inliers:
            state.reason = f'too few correspondences ({count} < {min_inliers}) within {gate:.3f} m'
            state.converged = False
            state.inliers = count
            break
        if count < keep.size:
            p, matched = moved[keep], index[keep]
        else:
            p, matched = moved, index
        e = p - tgt.points[matched]
        ex, ey = e[:, 0], e[:, 1]
        if point_to_line:
            info = tgt.information[matched]
            m00, m01, m11 = info[:, 0], info[:, 1], info[:, 2]
            me0 = m00 * ex + m01 * ey
            me1 = m01 * ex + m11 * ey
            size_sq = ex * me0 + ey * me1          # squared Mahalanobis-like residual (m²)
        else:
            size_sq = distance[keep] ** 2
        # Robust rule: which of the gated pairs enter the estimate.
        median_sq = _median(size_sq)
        chosen: NDArray[np.bool_] | NDArray[np.intp] | None
        if robust == 'trim' and count > min_inliers:
            n_keep = max(min_inliers, int(trim_fraction * count))
            chosen = np.argpartition(size_sq, n_keep - 1)[:n_keep]
        elif robust == 'adaptive':
            threshold_sq = max((adaptive_factor * 1.4826) ** 2 * median_sq, floor_sq)
            chosen = size_sq <= threshold_sq
            if np.count_nonzero(chosen) < min_inliers:
                chosen = np.argpartition(size_sq, min_inliers - 1)[:min_inliers]
        else:
            chosen = None
        if chosen is not None:
            p, matched, size_sq = p[chosen], matched[chosen], size_sq[chosen]
            ex, ey = ex[chosen], ey[chosen]
        state.inliers = p.shape[0]
        state.error = float(np.sqrt(size_sq).mean())
        state.history.append(state.error)
        state.p, state.matched = p, matched
        if point_to_line:
            if chosen is not None:
                m00, m01, m11, me0, me1 = m00[chosen], m01[chosen], m11[chosen], me0[chosen], \
                    me1[chosen]
            c0 = y - p[:, 1]                     # J·(p - t), J = 90° rotation
            c1 = p[:, 0] - x
            mc0 = m00 * c0 + m01 * c1
            mc1 = m01 * c0 + m11 * c1
            h02, h12 = mc0.sum(), mc1.sum()
            s01 = m01.sum()
            hessian = np.array([[m00.sum(), s01, h02], [s01, m11.sum(), h12],
                                [h02, h12, c0 @ mc0 + c1 @ mc1]])
            gradient = np.array([me0.sum(), me1.sum(), c0 @ me0 + c1 @ me1])
            values, vectors = np.linalg.eigh(hessian * outer)
            if values[-1] <= 0:
                dx = dy = dyaw = 0.0
            else:
                strong = values > solve_ratio * values[-1]
                g = vectors.T @ (gradient * scale)
                g[strong] /= values[strong]
                g[~strong] = 0.0
                dx, dy, dyaw = -(vectors @ g) * scale
        else:
            r_step, t_step = align_paired(p, tgt.points[matched])
            dyaw = math.atan2(r_step[1, 0], r_step[0, 0])
            # The SVD step is exact for these pairs; compose it with the current transform.
            new_xy = r_step @ np.array([x, y]) + t_step
            dx, dy = new_xy[0] - x, new_xy[1] - y
        x, y = x + dx, y + dy
        yaw = math.remainder(yaw + dyaw, 2.0 * math.pi)
        state.x, state.y, state.yaw = x, y, yaw
        if robust == 'adaptive':
            gate = max(min_gate, min(gate, 2.0 * adaptive_factor * 1.4826 * math.sqrt(median_sq)))
        same_pairs = previous is not None and previous.size == matched.size \
            and np.array_equal(previous, matched)
        previous = matched
        step = math.hypot(dx, dy) + abs(dyaw) * radius
        settled = len(state.history) >= 2 and \
            abs(state.history[-2] - state.history[-1]) <= error_tolerance * state.history[-1]
        # Correspondences that flip back and forth keep the step from vanishing; when the error
        # has not improved on its best for `stall_iterations`, it has stopped changing.
        if state.error < best_error * (1.0 - error_tolerance):
            best_error, stalled = state.error, 0
        else:
            stalled += 1
        if step < tolerance or (same_pairs and step < 10.0 * tolerance) or settled \
                or stalled >= stall_iterations:
            state.converged = True
            state.reason = ''
            break
    return state


def _normal_equations(lever, info, me0, me1):
    """Σ Gᵢᵀ Mᵢ Gᵢ and Σ Gᵢᵀ Mᵢ eᵢ over pairs, with Gᵢ = [I | J·leverᵢ] the Jacobian of the
    moved point over (x, y, yaw) and Mᵢ the 2x2 information (rows m00, m01, m11)."""
    c0, c1 = -lever[:, 1], lever[:, 0]                   # J·lever, J = 90° rotation
    mc0 = info[:, 0] * c0 + info[:, 1] * c1
    mc1 = info[:, 1] * c0 + info[:, 2] * c1
    s00, s01, s11 = info.sum(axis=0)
    h02, h12, h22 = mc0.sum(), mc1.sum(), float(c0 @ mc0 + c1 @ mc1)
    hessian = np.array([[s00, s01, h02], [s01, s11, h12], [h02, h12, h22]])
    gradient = np.array([me0.sum(), me1.sum(), float(c0 @ me0 + c1 @ me1)])
    return hessian, gradient


def _score(src, tgt: Target, pose, inlier_distance: float) -> float:
    """Fraction of source points within inlier_distance (m) of a target point at pose."""
    c, s = math.cos(pose[2]), math.sin(pose[2])
    moved = src @ np.array([[c, s], [-s, c]]) + (pose[0], pose[1])
    distance, _ = tgt.tree.query(moved, k=1, distance_upper_bound=inlier_distance)
    return float(np.isfinite(distance).mean())


def match(
    source: ArrayLike,
    target: ArrayLike | Target,
    initial: ArrayLike = (0.0, 0.0, 0.0),
    *,
    method: str = 'point_to_line',
    max_iterations: int = 50,
    max_correspondence_distance: float = 1.0,
    min_correspondence_distance: float = 0.1,
    tolerance: float = 1e-4,
    error_tolerance: float = 0.001,
    stall_iterations: int = 5,
    robust: str = 'adaptive',
    trim_fraction: float = 0.9,
    adaptive_factor: float = 3.0,
    voxel_size: float = 0.0,
    yaw_hypotheses: tuple[float, ...] = (),
    coarse_voxel_size: float = 0.25,
    coarse_iterations: int = 10,
    score_distance: float = 0.1,
    hypothesis_margin: float = 0.05,
    min_points: int = 3,
    min_inlier_fraction: float = 0.2,
    degeneracy_ratio: float = 1e-3,
    min_residual_std: float = 0.005,
) -> MatchResult:
    """Align source (N, 2) to target ((M, 2) or a prepared Target), both in their own frames (m),
    starting from `initial` (x, y, yaw). See MatchResult for the output.

    Correspondences are nearest neighbours within a gate that starts at
    max_correspondence_distance and, with robust='adaptive', shrinks each iteration to
    2 × adaptive_factor × 1.4826 × the median residual (never below min_correspondence_distance),
    keeping pairs within adaptive_factor × 1.4826 × median; robust='trim' keeps the
    trim_fraction best pairs; 'none' keeps every pair inside the gate. Fewer pairs than
    min_inlier_fraction of the source: failure. Iteration stops (converged) when the increment
    (m, with yaw as arc length at the source's RMS radius) is below `tolerance`, when the mean
    error changes by less than error_tolerance (relative) or has not improved on its best for
    stall_iterations (correspondences flipping back and forth), else at max_iterations
    (not converged). voxel_size > 0 downsamples the source first. With yaw_hypotheses (yaw offsets, rad) a coarse match from the initial guess
    and from each offset is scored by the fraction of source points within score_distance of the
    target, and the best seeds the fine match. Malformed arrays or options raise ValueError;
    valid but unusable input (too few points, all points identical, a non-finite guess) returns
    converged=False with a reason.
    """
    if method not in _METHODS:
        raise ValueError(f'method must be one of {_METHODS}, got {method!r}')
    if robust not in _ROBUST:
        raise ValueError(f'robust must be one of {_ROBUST}, got {robust!r}')
    if not (max_iterations >= 1 and max_correspondence_distance > 0 and tolerance > 0
            and 0 < trim_fraction <= 1 and adaptive_factor > 0 and min_points >= 3):
        raise ValueError('max_iterations >= 1, max_correspondence_distance > 0, tolerance > 0, '
                         '0 < trim_fraction <= 1, adaptive_factor > 0 and min_points >= 3 required')
    guess = np.asarray(initial, dtype=float).ravel()
    if guess.shape != (3,):
        raise ValueError(f'initial must be (x, y, yaw), got shape {guess.shape}')
    src, dropped = _as_points(source, 'source')
    tgt = target if isinstance(target, Target) else prepare_target(target)
    dropped += tgt.dropped
    if not np.all(np.isfinite(guess)):
        return _failed(guess, 'initial guess is not finite', src.shape[0], dropped)
    if voxel_size > 0:
        src = voxel_downsample(src, voxel_size)
    if src.shape[0] < min_points or tgt.points.shape[0] < min_points:
        return _failed(guess, f'too few valid points (source {src.shape[0]}, target '
                       f'{tgt.points.shape[0]}, need {min_points})', src.shape[0], dropped)
    centred = src - src.mean(axis=0)
    radius = float(np.sqrt((centred ** 2).sum(axis=1).mean()))
    if radius < 1e-9 or np.ptp(tgt.points, axis=0).max() < 1e-9:
        return _failed(guess, 'all points identical: rotation undefined', src.shape[0], dropped)

    point_to_line = method == 'point_to_line'
    min_inliers = max(min_points, int(math.ceil(min_inlier_fraction * src.shape[0])))
    settings = dict(
        point_to_line=point_to_line, min_gate=min(min_correspondence_distance,
                                                  max_correspondence_distance),
        tolerance=tolerance, robust=robust, trim_fraction=trim_fraction,
        adaptive_factor=adaptive_factor, radius=radius,
        solve_ratio=degeneracy_ratio, error_tolerance=error_tolerance,
        stall_iterations=stall_iterations)
    start = (float(guess[0]), float(guess[1]), float(guess[2]))
    if yaw_hypotheses:
        coarse = voxel_downsample(src, coarse_voxel_size) if coarse_voxel_size > 0 else src
        if coarse.shape[0] < max(min_points, 20):
            coarse = src            # too few points left to be worth a coarse stage
        coarse_min = max(min_points, int(math.ceil(min_inlier_fraction * coarse.shape[0])))
        best, best_score = start, -1.0
        for offset in (0.0, *yaw_hypotheses):
            seed = (start[0], start[1], start[2] + float(offset))
            state = _icp_loop(coarse, tgt, seed, max_iterations=coarse_iterations,
                              gate=max_correspondence_distance, min_inliers=coarse_min, **settings)
            candidate = (state.x, state.y, state.yaw) if state.p is not None else seed
            score = _score(coarse, tgt, candidate, score_distance)
            # The guess's own result wins unless a hypothesis explains clearly more points.
            if score > best_score + (hypothesis_margin if offset else 0.0):
                best, best_score = candidate, score
        start = best
    state = _icp_loop(src, tgt, start, max_iterations=max_iterations,
                      gate=max_correspondence_distance, min_inliers=min_inliers, **settings)
    x, y, yaw = state.x, state.y, state.yaw
    if state.p is None or state.inliers < min_inliers:
        return MatchResult(x, y, yaw, np.eye(3) * FAILED_VARIANCE, state.iterations, False,
                           state.error, state.reason, source_points=src.shape[0],
                           dropped_points=dropped, history=state.history, inliers=state.inliers)

    # Final linearised system over the last iteration's inlier pairs (converged: a tiny step).
    p = state.p
    q = tgt.points[state.matched]
    lever = p - (x, y)
    e = p - q
    info = tgt.information[state.matched] if point_to_line else np.tile((1.0, 0.0, 1.0), (len(p), 1))
    me0 = info[:, 0] * e[:, 0] + info[:, 1] * e[:, 1]
    me1 = info[:, 1] * e[:, 0] + info[:, 2] * e[:, 1]
    hessian, _ = _normal_equations(lever, info, me0, me1)
    # Each pair gives rank(Mᵢ) residuals: 1 on a line (tangent weight aside), 2 point-to-point.
    residual_count = float((info[:, 0] + info[:, 2]).sum())
    dof = max(1.0, residual_count - 3.0)
    variance = max(float(e[:, 0] @ me0 + e[:, 1] @ me1) / dof, min_residual_std ** 2)
    covariance, degenerate, direction, condition = _covariance(
        hessian, variance, radius, degeneracy_ratio)
    reason = state.reason
    if degenerate and state.converged:
        reason = 'degenerate: geometry leaves one direction unconstrained'
    return MatchResult(
        x=x, y=y, yaw=yaw, covariance=covariance, iterations=state.iterations,
        converged=state.converged, error=state.error, reason=reason, degenerate=degenerate,
        degenerate_direction=direction, inliers=state.inliers, source_points=src.shape[0],
        dropped_points=dropped, condition=condition, history=state.history)


def _scaled(info: NDArray[np.float64], radius: float) -> NDArray[np.float64]:
    """The normal matrix with yaw expressed as arc length at the scan radius, so its eigenvalues
    compare metres with metres."""
    scale = np.array([1.0, 1.0, 1.0 / radius])
    return info * scale[:, None] * scale[None, :]


def _covariance(info, variance, radius, degeneracy_ratio):
    """variance · info⁻¹ over (x, y, yaw); an unconstrained direction gets DEGENERATE_VARIANCE."""
    scaled = _scaled(info, radius)
    values, vectors = np.linalg.eigh(scaled)
    top = max(values[-1], 1e-300)
    condition = float(max(values[0], 0.0) / top)
    weak = values <= degeneracy_ratio * top
    inverse_values = np.where(weak, 0.0, 1.0 / np.where(weak, 1.0, values))
    cov_scaled = variance * (vectors * inverse_values) @ vectors.T
    cov_scaled += DEGENERATE_VARIANCE * (vectors[:, weak] @ vectors[:, weak].T)
    scale = np.array([1.0, 1.0, 1.0 / radius])
    cov = cov_scaled * scale[:, None] * scale[None, :]
    direction = vectors[:, 0].copy() if weak.any() else None
    return 0.5 * (cov + cov.T), bool(weak.any()), direction, condition
