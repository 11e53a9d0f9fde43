"""2-D ICP scan matching: point-to-point (closed-form SVD) and point-to-line (Gauss-Newton).

Frame convention: the result (x, y, yaw) maps source points into the target frame,
target ≈ R(yaw)·source + (x, y). Matching scan k+1 (source) against scan k (target) therefore
gives the pose of scan k+1 in the frame of scan k. Units: metres and radians.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields, replace
from functools import cached_property, lru_cache

import numpy as np
from numpy.lib.stride_tricks import as_strided
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree

from sensing_nodes.parameters import CheckedAtConstruction

# Variance (m², rad²) put on the diagonal of a failed match's covariance: large enough that any
# fusion ignores it, finite so arithmetic stays sane.
FAILED_VARIANCE = 1.0e6
# Variance (m², yaw as arc length at the scan radius) added along an unconstrained direction:
# far above any motion between scans, yet small enough that the slight tilt of that direction
# does not leak into the constrained ones.
DEGENERATE_VARIANCE = 100.0

# Target points each side of a query's bearing among which its nearest neighbour is sought first
# (a scan's points are ordered by bearing, so the nearest one is usually among them; the bearing
# gap to the window's edges certifies it, else it is sought among all points).
ANGULAR_WINDOW = 10
# A GridIndex cell without a point: far enough that no query ever takes it for a neighbour.
EMPTY_CELL = complex(1e15, 1e15)
# Queries the bearing window cannot certify are answered by computing every distance while
# they are fewer than this many query-target pairs (a k-d tree's call costs more: ~40 us), else
# by the target's k-d tree.
BRUTE_FORCE_PAIRS = 8000
# Neighbouring points each side of a target point among which its normal_neighbours nearest are
# taken (a scan's neighbouring beams).
NORMAL_WINDOW = 8

_METHODS = ('point_to_line', 'point_to_point')
SEARCHES = ('bearing', 'kd_tree')
_ROBUST = ('trim', 'adaptive', 'none')




@dataclass(frozen=True)
class Convergence(CheckedAtConstruction):
    """When the ICP loop stops. Converged: the increment (m, yaw as arc length at the source's RMS
    radius) fell below `tolerance`, or the mean error changed by less than `error_tolerance`
    (relative), or it has not improved on its best for `stall_iterations` (correspondences
    flipping back and forth). Not converged: `max_iterations` reached."""

    max_iterations: int = 50
    tolerance: float = 1e-4
    error_tolerance: float = 0.001
    stall_iterations: int = 5

    def problems(self) -> list[tuple[str, str, object]]:
        """(field, problem, value) for each setting the loop cannot run with."""
        out: list[tuple[str, str, object]] = []
        if not self.max_iterations >= 1:
            out.append(('max_iterations', 'must be >= 1', self.max_iterations))
        if not self.tolerance > 0:
            out.append(('tolerance', 'must be > 0', self.tolerance))
        return out


@dataclass(frozen=True)
class Correspondences(CheckedAtConstruction):
    """Which nearest-neighbour pairs enter the estimate (distances in m).

    The gate starts at max_correspondence_distance and, with robust='adaptive', shrinks each
    iteration to 2 × adaptive_factor × 1.4826 × the median residual (never below
    min_correspondence_distance), keeping pairs within adaptive_factor × 1.4826 × median;
    robust='trim' keeps the trim_fraction best pairs; 'none' keeps every pair inside the gate.
    Fewer pairs than min_inlier_fraction of the source (or min_points): failure."""

    max_correspondence_distance: float = 1.0
    min_correspondence_distance: float = 0.1
    robust: str = 'adaptive'
    trim_fraction: float = 0.9
    adaptive_factor: float = 3.0
    min_points: int = 3
    min_inlier_fraction: float = 0.2

    def problems(self) -> list[tuple[str, str, object]]:
        """(field, problem, value) for each setting the pairing cannot run with."""
        checks = (('robust', self.robust in _ROBUST, f'must be one of {_ROBUST}'),
                  ('max_correspondence_distance', self.max_correspondence_distance > 0,
                   'must be > 0'),
                  ('trim_fraction', 0 < self.trim_fraction <= 1, 'must be in (0, 1]'),
                  ('adaptive_factor', self.adaptive_factor > 0, 'must be > 0'),
                  ('min_points', self.min_points >= 3, 'must be >= 3'))
        return [(name, problem, getattr(self, name)) for name, ok, problem in checks if not ok]


@dataclass(frozen=True)
class YawSearch:
    """Coarse matches from the initial guess and from each yaw offset in yaw_hypotheses (rad),
    on the source downsampled to coarse_voxel_size (m); each is scored by the fraction of source
    points within score_distance (m) of the target, and the best seeds the fine match (a
    hypothesis must beat the guess's own result by hypothesis_margin). No offsets: no search."""

    yaw_hypotheses: tuple[float, ...] = ()
    coarse_voxel_size: float = 0.25
    coarse_iterations: int = 10
    score_distance: float = 0.1
    hypothesis_margin: float = 0.05

    def __post_init__(self) -> None:
        object.__setattr__(self, 'yaw_hypotheses', tuple(self.yaw_hypotheses))


@dataclass(frozen=True)
class IcpOptions(CheckedAtConstruction):
    """Everything match() can be told, validated once: the residual (`method`), source
    downsampling (voxel_size, m; 0 = off), the degeneracy test (eigenvalue ratio) and the floor
    of the residual standard deviation (m) used for the covariance, and one part per concern."""

    method: str = 'point_to_line'
    voxel_size: float = 0.0
    degeneracy_ratio: float = 1e-3
    min_residual_std: float = 0.005
    convergence: Convergence = Convergence()
    correspondences: Correspondences = Correspondences()
    yaw_search: YawSearch = YawSearch()

    def problems(self) -> list[tuple[str, str, object]]:
        """(field, problem, value) for each option match() cannot run with (its parts' as
        'convergence.max_iterations', ...)."""
        out: list[tuple[str, str, object]] = []
        if self.method not in _METHODS:
            out.append(('method', f'must be one of {_METHODS}', self.method))
        for part in ('convergence', 'correspondences'):
            out += [(f'{part}.{name}', problem, value)
                    for name, problem, value in getattr(self, part).problems()]
        return out

    def updated(self, **keywords) -> IcpOptions:
        """A copy with flat keywords (match's call form) set in the part that holds each name;
        TypeError on a name no part has."""
        parts = {}
        for part in ('convergence', 'correspondences', 'yaw_search'):
            current = getattr(self, part)
            names = {f.name for f in fields(current)} & keywords.keys()
            if names:
                parts[part] = replace(current, **{n: keywords.pop(n) for n in names})
        return replace(self, **keywords, **parts)


_DEFAULT_OPTIONS = IcpOptions()


@dataclass(frozen=True)
class BearingIndex:
    """A target's points sorted by bearing from its origin (rad), padded circularly by `pad`
    entries at each end (bearings shifted by ∓2π) so that a window of up to `pad` entries each
    side of any bearing in [-π, π] stays inside the arrays: bearing, point as x + iy (m) and
    point index per entry. A query sorted at c (bearings[c-1] < its bearing <= bearings[c]) is
    searched among the `half` entries each side, windows[c - half] (entries c - half ..
    c + half - 1; a strided view of `points`, no copy); `edge_sin_sq[c]` is sin² of the
    smallest bearing gap (capped at π/2) between it and the nearest entry outside that window:
    a query at range ρ is at least ρ·√edge_sin_sq[c] from every point outside, which certifies
    the window's nearest point as the nearest of all. `slot`: each point's entry in the padded
    arrays."""

    bearings: NDArray[np.float64]
    points: NDArray[np.complex128]
    index: NDArray[np.intp]
    pad: int
    half: int
    # (size - 2·half + 1, 2·half)
    windows: NDArray[np.complex128] = field(repr=False, compare=False)
    edge_sin_sq: NDArray[np.float64] = field(repr=False, compare=False)
    slot: NDArray[np.intp] = field(repr=False, compare=False)


@dataclass(frozen=True)
class GridIndex:
    """Points binned in square cells of side `cell` (m), at most one point per cell (a local
    map's cell means): `table[(ix - ix0) · height + (iy - iy0)]` is the index of the point in
    cell (ix, iy), or -1. An empty ring of cells surrounds the points, so a query's 3x3 block of
    cells stays inside the table. Every point within `cell` of a query lies in the query's 3x3
    block, which certifies the block's nearest point as the nearest of all up to that distance.
    """

    cell: float
    ix0: int
    iy0: int
    width: int
    height: int
    table: NDArray[np.int32] = field(repr=False, compare=False)
    # Each cell's point as x + iy (m), EMPTY_CELL where none: one take per query block.
    points: NDArray[np.complex128] = field(repr=False, compare=False)
    block: NDArray[np.intp] = field(repr=False, compare=False)     # the 3x3 block's offsets

    @cached_property
    def low(self) -> NDArray[np.float64]:
        """(ix0, iy0) as floats: a cell index minus this is its table row and column."""
        return np.array([self.ix0, self.iy0], dtype=float)

    @cached_property
    def high(self) -> NDArray[np.float64]:
        """The last row and column a query's block may be centred on."""
        return np.array([self.width - 2, self.height - 2], dtype=float)

    @cached_property
    def strides(self) -> NDArray[np.float64]:
        """(height, 1): a cell's row and column -> its flat index in the table."""
        return np.array([self.height, 1.0])


@dataclass(frozen=True)
class Target:
    """A target scan prepared once for many matches: points (N, 2) in its frame (m), how its
    neighbours are found (`search`: 'bearing' = `bearing_index`, its points sorted by bearing,
    None below 2·ANGULAR_WINDOW + 1 points, with `tree` for what a bearing window cannot
    certify; else `tree`, a k-d tree built when first needed),
    unit normals (N, 2) from the neighbouring points,
    how line-like each neighbourhood is (`planarity` in [0, 1]: 1 = points exactly on a line),
    and the 2x2 information matrix each point gives a residual, as (N, 3) rows (m00, m01, m11):
    n·nᵀ + tangent_weight·I on a line (point-to-line), I elsewhere (corners and isolated points
    act point-to-point)."""

    points: NDArray[np.float64]
    normals: NDArray[np.float64]
    planarity: NDArray[np.float64]
    information: NDArray[np.float64]
    dropped: int = 0          # non-finite rows removed from the input
    # Residual rows [U | 0 | -U·q] per point q with UᵀU = its information (2x2 U: the residual
    # of a pair is U·(p - q), its Jacobian rows follow from U) as (4, 2, N): U's first column,
    # its second column, a slot for the yaw column and -(U·q), each over U's two rows, points
    # last so that every per-iteration operation runs over contiguous rows of pairs; None =
    # derived when first matched.
    rows: NDArray[np.float64] | None = field(default=None, repr=False, compare=False)
    bearing_index: BearingIndex | None = field(default=None, repr=False, compare=False)
    search: str = 'bearing'
    # search='grid' (map_target): the points' cells, one point each.
    grid: GridIndex | None = field(default=None, repr=False, compare=False)

    @cached_property
    def tree(self) -> cKDTree:
        """k-d tree over the points: the neighbour search with search='kd_tree' or without a
        bearing index."""
        return cKDTree(self.points)


@dataclass
class MatchResult:
    """Transform of the source into the target frame (m, rad) with its 3x3 covariance over
    (x, y, yaw). `error` is the mean residual (m) of the inlier correspondences: along the
    target's normal where the target is line-like (point-to-line), the point-to-point distance
    at corners and isolated points and with method='point_to_point'. `iterations` counts the
    full-resolution iterations (a yaw-hypothesis stage runs before them). `converged` is True only
    when
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
    residual_variance: float = math.nan     # the residuals' variance behind the covariance (m²)

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
    if math.isfinite(float(array.sum())):         # one pass for the usual all-finite case
        return array, 0
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
        raise ValueError(
            f'paired point sets must be non-empty and equal in shape: {p.shape} vs {q.shape}'
        )
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


def _neighbourhoods(points: NDArray[np.float64], bearing_index: BearingIndex | None,
                    neighbours: int, radius: float
                    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_],
                               cKDTree | None]:
    """Offsets dx, dy (rows, n), m, from each point to its k nearest points (itself included)
    and which of them are present (closer than radius, m; an absent one has offset 0), and the
    k-d tree if one was built. With a bearing index, the k nearest among the NORMAL_WINDOW
    points each side of the point's bearing (its neighbouring beams in a scan) where the window
    certifies them as the k nearest of all, the k-d tree's elsewhere; else the k-d tree's for
    all."""
    n = points.shape[0]
    k = min(neighbours, n)
    half = min(NORMAL_WINDOW, bearing_index.pad - 1) if bearing_index is not None else 0
    tree = None
    if bearing_index is None or k > 2 * half + 1:
        tree = cKDTree(points)
        dx, dy, present = _tree_neighbourhoods(points, tree, k, radius, points)
        return dx, dy, present, tree
    position = bearing_index.slot
    # (2·half + 1, n): each operation runs over contiguous rows of points.
    offset = bearing_index.points.take(np.arange(-half, half + 1)[:, None] + position)
    centred = _complex(points)
    offset -= centred
    size = np.abs(offset)                           # distances
    present = size < radius
    kth = np.partition(size, k - 1, axis=0)[k - 1] if k < size.shape[0] else size.max(axis=0)
    present &= size <= kth
    # Every point outside the window is at least ρ·sin(gap) away (gap: the bearing gap to the
    # window's outer neighbours, capped at π/2); beyond that the tree decides.
    bearings = bearing_index.bearings
    gap = np.minimum(bearings.take(position) - bearings.take(position - half - 1),
                     bearings.take(position + half + 1) - bearings.take(position))
    bound = np.abs(centred) * np.sin(np.minimum(gap, 0.5 * math.pi))
    offset[~present] = 0.0
    dx, dy = offset.real.copy(), offset.imag.copy()
    uncertain = np.flatnonzero(np.minimum(kth, radius) > bound)
    if uncertain.size:
        tree = cKDTree(points)           # also answers the matches' uncertain queries
        sub_dx, sub_dy, sub_present = _tree_neighbourhoods(points, tree, k, radius,
                                                           points.take(uncertain, axis=0))
        dx[:, uncertain] = 0.0
        dy[:, uncertain] = 0.0
        present[:, uncertain] = False
        dx[:k, uncertain], dy[:k, uncertain], present[:k, uncertain] = sub_dx, sub_dy, sub_present
    return dx, dy, present, tree


def _tree_neighbourhoods(points: NDArray[np.float64], tree: cKDTree, k: int, radius: float,
                         queries: NDArray[np.float64]) -> tuple[NDArray[np.float64],
                                                                NDArray[np.float64],
                                                                NDArray[np.bool_]]:
    """Offsets dx, dy (k, q), m, from each query (q, 2) to its k nearest points (tree over
    points) within radius, m, and which are present (absent: offset 0)."""
    distance, index = tree.query(queries, k=k, distance_upper_bound=radius)
    if k == 1:
        distance, index = distance[:, None], index[:, None]
    present = distance.T <= radius
    index = np.where(present, index.T, 0)
    dx = points[:, 0].take(index)
    dx -= queries[:, 0]
    dy = points[:, 1].take(index)
    dy -= queries[:, 1]
    dx[~present] = 0.0
    dy[~present] = 0.0
    return dx, dy, present


def _line_normals(dx: NDArray[np.float64], dy: NDArray[np.float64],
                  present: NDArray[np.bool_]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Unit normal and planarity (1 - λmin/λmax of the neighbourhood scatter) per point, from
    the offsets (k, n), m, to its neighbours and which of them are present (absent: offset 0).
    The offsets are small numbers, so the one-pass scatter Σ d·dᵀ - (Σ d)(Σ d)ᵀ / count loses
    no precision."""
    k, n = dx.shape
    count = present.sum(axis=0, dtype=float)                      # exact: a sum of 0s and 1s
    sx, sy = dx.sum(axis=0), dy.sum(axis=0)
    sxx = np.einsum('ij,ij->j', dx, dx) - sx * sx / count
    syy = np.einsum('ij,ij->j', dy, dy) - sy * sy / count
    sxy = np.einsum('ij,ij->j', dx, dy) - sx * sy / count
    # Principal axis of a 2x2 scatter in closed form; the normal is perpendicular to it.
    half_difference = 0.5 * (sxx - syy)
    theta = 0.5 * np.arctan2(sxy, half_difference)
    normals = np.empty((n, 2))
    np.sin(theta, out=normals[:, 0])
    np.negative(normals[:, 0], out=normals[:, 0])
    np.cos(theta, out=normals[:, 1])
    half_trace = 0.5 * (sxx + syy)
    spread = np.hypot(half_difference, sxy)
    with np.errstate(invalid='ignore', divide='ignore'):
        planarity = spread / half_trace                           # (λ1-λ2)/(λ1+λ2)
    planarity[(count < 3) | ~(half_trace > 0)] = 0.0
    return normals, np.clip(planarity, 0.0, 1.0, out=planarity)


def _residual_rows(points: NDArray[np.float64],
                   information: NDArray[np.float64]) -> NDArray[np.float64]:
    """Residual rows [U | U·q] with UᵀU = M for each point q and information M (rows m00, m01,
    m11), as Target.rows lays them out: U = diag(√λ)·Vᵀ from M's eigen-decomposition."""
    n = points.shape[0]
    m = np.empty((n, 2, 2))
    m[:, 0, 0], m[:, 0, 1], m[:, 1, 0], m[:, 1, 1] = (information[:, 0], information[:, 1],
                                                      information[:, 1], information[:, 2])
    values, vectors = np.linalg.eigh(m)
    u = np.sqrt(np.clip(values, 0.0, None))[:, :, None] * vectors.transpose(0, 2, 1)
    return _residual_table(u[:, :, 0], u[:, :, 1], np.einsum('nij,nj->ni', u, points))


def _residual_table(u0: NDArray[np.float64], u1: NDArray[np.float64],
                    uq: NDArray[np.float64]) -> NDArray[np.float64]:
    """Target.rows (4, 2, N) from U's first and second columns and U·q, each (N, 2) over U's
    two rows: one take per iteration fetches the pairs' rows [U | 0 | -U·q]."""
    table = np.zeros((4, 2, u0.shape[0]))
    table[0], table[1] = u0.T, u1.T
    np.negative(uq.T, out=table[3])
    return table


def prepare_target(points: ArrayLike, normal_neighbours: int = 7, normal_radius: float = 1.0,
                   min_planarity: float = 0.5, tangent_weight: float = 0.0,
                   search: str = 'bearing') -> Target:
    """Normals and per-point information of a target point set (N, 2), m, in its own frame,
    and the index its neighbours are found with (`search`: 'bearing', the points' order by
    bearing from the origin, fastest for a scan, or 'kd_tree'; both give the exact nearest
    neighbours, equal up to ties); a point is line-like when its planarity >= min_planarity.
    Non-finite rows are dropped (counted in `dropped`); ValueError on a wrong shape or bad
    settings."""
    if not (normal_neighbours >= 2 and normal_radius > 0 and 0 <= min_planarity <= 1
            and 0 <= tangent_weight <= 1 and search in SEARCHES):
        raise ValueError('normal_neighbours >= 2, normal_radius > 0, 0 <= min_planarity <= 1, '
                         f'0 <= tangent_weight <= 1 and search in {SEARCHES} required')
    array, dropped = _as_points(points, 'target')
    if array.shape[0] == 0:
        return Target(array, np.zeros((0, 2)), np.zeros(0), np.zeros((0, 3)), dropped,
                      search=search)
    array = np.ascontiguousarray(array)
    bearing_index, normals, planarity, tree = _normals_of(array, search, normal_neighbours,
                                                          normal_radius)
    target = _target_with_normals(array, normals, planarity, min_planarity, tangent_weight,
                                  dropped=dropped, bearing_index=bearing_index, search=search)
    if tree is not None:
        target.__dict__['tree'] = tree        # the cached_property's slot: built once
    return target


def scan_normals(points: ArrayLike, normal_neighbours: int = 7,
                 normal_radius: float = 1.0) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Unit normal (N, 2) and planarity (N,) of each point of a scan (N, 2), m, in its own
    frame, as prepare_target finds them: from its normal_neighbours nearest points within
    normal_radius (m). ValueError on a wrong shape or non-finite points."""
    array = np.ascontiguousarray(points, dtype=float)
    if array.ndim != 2 or array.shape[1] != 2 or not np.isfinite(array).all():
        raise ValueError('scan_normals needs finite points (N, 2)')
    if array.shape[0] == 0:
        return np.zeros((0, 2)), np.zeros(0)
    _, normals, planarity, _ = _normals_of(array, 'bearing', normal_neighbours, normal_radius)
    return normals, planarity


def _normals_of(array: NDArray[np.float64], search: str, neighbours: int, radius: float):
    """(bearing index or None, normals, planarity, k-d tree or None) of finite points."""
    bearing_index = _bearing_index(array, max(ANGULAR_WINDOW, NORMAL_WINDOW + 1),
                                   ANGULAR_WINDOW) if search == 'bearing' else None
    dx, dy, present, tree = _neighbourhoods(array, bearing_index, neighbours, radius)
    normals, planarity = _line_normals(dx, dy, present)
    return bearing_index, normals, planarity, tree


def map_target(points: ArrayLike, normals: ArrayLike, planarity: ArrayLike, grid: GridIndex,
               min_planarity: float = 0.5, tangent_weight: float = 0.0) -> Target:
    """A target from points (N, 2), m, with their unit normals (N, 2) and planarity (N,) given
    (a local map's cells: core/local_map.py), point i alone in cell i of `grid`
    (grid_index(cells, ...)), found through those cells (the k-d tree for what a cell's
    neighbours cannot certify). A point is line-like when its planarity >= min_planarity.
    ValueError on mismatched shapes or non-finite values."""
    array = np.ascontiguousarray(points, dtype=float)
    normals = np.ascontiguousarray(normals, dtype=float)
    planarity = np.asarray(planarity, dtype=float)
    n = array.shape[0] if array.ndim == 2 else -1
    if not (array.shape == (n, 2) and normals.shape == (n, 2) and planarity.shape == (n,)
            and np.isfinite(array).all() and np.isfinite(normals).all()):
        raise ValueError('map_target needs finite points (N, 2), normals (N, 2) and '
                         'planarity (N,)')
    return _target_with_normals(array, normals, planarity, min_planarity, tangent_weight,
                                search='grid', grid=grid)


def grid_index(points: NDArray[np.float64], cells: NDArray[np.int64], cell: float) -> GridIndex:
    """The GridIndex of points (N, 2), m, each alone in its cell: cells (N, 2) are their integer
    cell indices (floor(x / cell), floor(y / cell)), cell the side (m). ValueError when two
    points share a cell."""
    cells = np.asarray(cells, dtype=np.int64).reshape(-1, 2)
    points = _complex(points)
    if cells.shape[0] == 0:
        return GridIndex(cell, 0, 0, 3, 3, np.full(9, -1, dtype=np.int32),
                         np.full(9, EMPTY_CELL), _block_offsets(3))
    low = cells.min(axis=0) - 1
    width, height = (cells.max(axis=0) - low + 2).tolist()
    flat = (cells[:, 0] - low[0]) * height + (cells[:, 1] - low[1])
    table = np.full(width * height, -1, dtype=np.int32)
    table[flat] = np.arange(cells.shape[0], dtype=np.int32)
    if np.count_nonzero(table >= 0) != cells.shape[0]:
        raise ValueError(f'grid_index: two points share a cell of {cell} m')
    located = np.full(width * height, EMPTY_CELL)
    located[flat] = points
    return GridIndex(cell, int(low[0]), int(low[1]), width, height, table, located,
                     _block_offsets(height))


def _block_offsets(height: int) -> NDArray[np.intp]:
    """Flat offsets of a cell's 3x3 block in a table of columns `height` long (dx major)."""
    return (np.arange(-1, 2)[:, None] * height + np.arange(-1, 2)[None, :]).ravel()


def _target_with_normals(array: NDArray[np.float64], normals: NDArray[np.float64],
                         planarity: NDArray[np.float64], min_planarity: float,
                         tangent_weight: float, dropped: int = 0,
                         bearing_index: BearingIndex | None = None, search: str = 'bearing',
                         grid: GridIndex | None = None) -> Target:
    """A Target from points with their normals and planarity: per-point information and the
    residual rows."""
    corner = planarity < min_planarity
    n = array.shape[0]
    # Information n·nᵀ + w·I on a line, I elsewhere, as rows (m00, m01, m11).
    nx, ny = normals[:, 0], normals[:, 1]
    information = np.empty((n, 3))
    np.multiply(nx, nx, out=information[:, 0])
    np.multiply(nx, ny, out=information[:, 1])
    np.multiply(ny, ny, out=information[:, 2])
    if tangent_weight:
        information[:, 0::2] += tangent_weight
    information[corner] = (1.0, 0.0, 1.0)
    # Residual rows [U | U·q] with UᵀU = information: √(1+w)·n and √w·tangent on a line, the
    # unit axes elsewhere.
    rows = np.zeros((3, n, 2))
    if tangent_weight:
        rows[0, :, 0] = math.sqrt(1.0 + tangent_weight) * nx
        rows[1, :, 0] = math.sqrt(1.0 + tangent_weight) * ny
        rows[0, :, 1] = math.sqrt(tangent_weight) * ny
        rows[1, :, 1] = -math.sqrt(tangent_weight) * nx
    else:
        rows[0, :, 0] = nx
        rows[1, :, 0] = ny
    rows[0, corner] = (1.0, 0.0)
    rows[1, corner] = (0.0, 1.0)
    np.multiply(rows[0], array[:, 0, None], out=rows[2])
    rows[2] += rows[1] * array[:, 1, None]
    return Target(array, normals, planarity, information, dropped, _residual_table(*rows),
                  bearing_index, search, grid)


def _bearing_index(points: NDArray[np.float64], pad: int, window: int) -> BearingIndex | None:
    """The BearingIndex of points (N, 2) in their own frame (m), padded by pad entries each
    side, searched window entries each side (window <= pad); None below 2·pad + 1 points."""
    n = points.shape[0]
    if n < 2 * pad + 1:
        return None
    bearing = np.arctan2(points[:, 1], points[:, 0])
    order = np.argsort(bearing, kind='stable')
    extended = np.concatenate((order[n - pad:], order, order[:pad]))
    bearings = bearing.take(extended)
    bearings[:pad] -= 2.0 * math.pi
    bearings[n + pad:] += 2.0 * math.pi
    # One more entry each side (circularly) for the window edges of the first and last centres.
    outer = np.concatenate(([bearing[order[n - pad - 1]] - 2.0 * math.pi], bearings,
                            [bearing[order[pad % n]] + 2.0 * math.pi]))
    size = bearings.shape[0]
    centre = np.arange(size + 1) + 1              # searchsorted's range, as outer's index
    gap = np.minimum(outer.take(centre - 1) - outer.take(np.maximum(centre - window - 1, 0)),
                     outer.take(np.minimum(centre + window, size + 1)) - outer.take(
                         np.minimum(centre, size + 1)))
    edge_sin_sq = np.square(np.sin(np.minimum(np.maximum(gap, 0.0), 0.5 * math.pi)))
    slot = np.empty(n, dtype=np.intp)
    slot[order] = np.arange(pad, n + pad)
    padded = _complex(points).take(extended)
    windows = as_strided(padded, (size - 2 * window + 1, 2 * window), 2 * padded.strides,
                         writeable=False)
    return BearingIndex(bearings, padded, extended, pad, window, windows, edge_sin_sq, slot)


def _complex(points: NDArray[np.float64]) -> NDArray[np.complex128]:
    """(N,) x + iy of points (N, 2), m."""
    return np.ascontiguousarray(points, dtype=np.float64).view(np.complex128).ravel()


def _nearest(target: Target, points: NDArray[np.complex128],
             gate: float) -> tuple[NDArray[np.bool_], NDArray[np.intp]]:
    """For each query point (x + iy, target frame, m): whether a target point lies closer than
    gate, and the index of the nearest one (any index when none). Exact with either search:
    with 'bearing', the nearest in the query's bearing window (_bearing_nearest) where the
    window certifies it, elsewhere from every distance (few such queries) or the k-d tree."""
    if target.grid is not None:
        return _grid_nearest(target, points, gate)
    bearing_index = target.bearing_index
    if bearing_index is None:
        distance, index = target.tree.query(np.column_stack((points.real, points.imag)), k=1,
                                            distance_upper_bound=gate)
        return distance < gate, index
    gate_sq = gate * gate
    distance_sq, index, certain_sq = _bearing_nearest(bearing_index, points)
    # A query whose window's nearest point (or the gate) is further than the window certifies
    # may have a nearer point outside the window: every distance, or the tree, answers those.
    uncertain = np.flatnonzero(np.minimum(distance_sq, gate_sq) > certain_sq)
    if uncertain.size:
        query = points.take(uncertain)
        count = bearing_index.index.shape[0] - 2 * bearing_index.pad
        if uncertain.size * count <= BRUTE_FORCE_PAIRS:
            every = np.abs(bearing_index.points[bearing_index.pad:count + bearing_index.pad]
                           - query[:, None])
            nearest = every.argmin(axis=1)
            index[uncertain] = bearing_index.index.take(nearest + bearing_index.pad)
            distance_sq[uncertain] = np.square(every.take(nearest
                                                          + _row_starts(*every.shape)))
        else:
            _tree_nearest(target, query, uncertain, gate, index, distance_sq)
    return distance_sq < gate_sq, index


def _tree_nearest(target: Target, query: NDArray[np.complex128], rows: NDArray[np.intp],
                  gate: float, index: NDArray[np.intp], distance_sq: NDArray[np.float64]) -> None:
    """The k-d tree's answer for the queries (x + iy) at `rows` of index and distance_sq,
    written where a target point lies within gate (the rest keep what they had)."""
    distance, found = target.tree.query(np.column_stack((query.real, query.imag)), k=1,
                                        distance_upper_bound=gate)
    inside = distance < gate
    where = rows[inside]
    index[where] = found[inside]
    distance_sq[where] = np.square(distance[inside])


def _grid_nearest(target: Target, points: NDArray[np.complex128],
                  gate: float) -> tuple[NDArray[np.bool_], NDArray[np.intp]]:
    """_nearest through the target's cells: each query's nearest point in its 3x3 block of
    cells. Every point within one cell of a query is in its block, so with a gate up to a cell
    the block's answer is exact; with a wider gate a query is certified up to the distance to
    its block's edge, and the rest (nothing that close, or a query off the table) are answered
    by the k-d tree."""
    grid = target.grid
    cells = points.view(np.float64).reshape(-1, 2) * (1.0 / grid.cell)
    wide = gate > grid.cell
    if wide:
        # The block's edge lies a cell beyond the nearest edge of the query's own cell.
        fraction = cells - np.floor(cells)
        margin = np.minimum(fraction, 1.0 - fraction).min(axis=1)
    np.floor(cells, out=cells)
    cells -= grid.low
    if wide:
        inside = ((cells >= 1.0) & (cells <= grid.high)).all(axis=1)
    # Far queries are pulled onto the table's edge (its ring of empty cells: nothing within a
    # cell of them).
    np.clip(cells, 1.0, grid.high, out=cells)
    block = (cells @ grid.strides).astype(np.intp)[:, None] + grid.block       # (n, 9)
    offset = grid.points.take(block)
    offset -= points[:, None]
    parts = offset.view(np.float64)
    np.square(parts, out=parts)
    distance_sq = parts[:, 0::2] + parts[:, 1::2]
    best = distance_sq.argmin(axis=1)
    best += _row_starts(*distance_sq.shape)
    distance_sq = distance_sq.take(best)
    index = grid.table.take(block.take(best)).astype(np.intp)   # -1 (none): never kept
    gate_sq = gate * gate
    if wide:
        certain = (1.0 + margin) * grid.cell
        certain[~inside] = 0.0
        uncertain = np.flatnonzero(np.minimum(distance_sq, gate_sq) > certain * certain)
        if uncertain.size and target.points.shape[0]:
            _tree_nearest(target, points.take(uncertain), uncertain, gate, index, distance_sq)
    return distance_sq < gate_sq, index


def _bearing_nearest(bearing_index: BearingIndex, points: NDArray[np.complex128]
                     ) -> tuple[NDArray[np.float64], NDArray[np.intp], NDArray[np.float64]]:
    """For each query point (x + iy, target frame): the squared distance (m²) to and the index
    of the nearest target point among the window's entries each side of its bearing, and the
    squared distance (m²) within which that point is certainly the nearest of all (every point
    outside the window is at least that far)."""
    start = np.searchsorted(bearing_index.bearings, np.arctan2(points.imag, points.real))
    # A finite bearing's window lies between the pads; a NaN one sorts past the end and is
    # pulled back into the arrays (its distance is NaN: no correspondence).
    np.minimum(start, bearing_index.points.shape[0] - bearing_index.pad, out=start)
    certain_sq = points.real * points.real
    certain_sq += points.imag * points.imag
    certain_sq *= bearing_index.edge_sin_sq.take(start)
    start -= bearing_index.half
    # (count, window): one fancy index copies each query's window out of the strided view.
    offset = bearing_index.windows[start]
    offset -= points[:, None]
    parts = offset.view(np.float64)
    np.square(parts, out=parts)
    distance_sq = parts[:, 0::2] + parts[:, 1::2]
    best = distance_sq.argmin(axis=1)
    start += best
    best += _row_starts(*distance_sq.shape)
    return distance_sq.take(best), bearing_index.index.take(start), certain_sq


@lru_cache(maxsize=16)
def _row_starts(rows: int, columns: int) -> NDArray[np.intp]:
    """Flat index of each row's first entry in a C-ordered (rows, columns) array (read-only)."""
    starts = np.arange(0, rows * columns, columns)
    starts.flags.writeable = False
    return starts


def voxel_downsample(points: ArrayLike, voxel_size: float) -> NDArray[np.float64]:
    """Centroid of the points in each square voxel of side voxel_size (m); order follows voxel
    keys."""
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
    # The last iteration's 4x4 [[H, g], [gᵀ, Σr²]] over its inlier pairs, with the levers taken
    # about `origin` (the translation it started from); None before any iteration ran.
    normal: NDArray[np.float64] | None = None
    origin: tuple[float, float] = (0.0, 0.0)


def _identity_rows(points: NDArray[np.float64]) -> NDArray[np.float64]:
    """Residual rows of plain point-to-point pairs (information I): [[1, 0, qx], [0, 1, qy]]."""
    n = points.shape[0]
    return _residual_table(np.broadcast_to([1.0, 0.0], (n, 2)),
                           np.broadcast_to([0.0, 1.0], (n, 2)), points)


def _solve_step(normal: NDArray[np.float64], radius: float,
                solve_ratio: float) -> tuple[float, float, float]:
    """Gauss-Newton increment (dx, dy, dyaw) = -H⁻¹·g from the 4x4 [[H, g], [gᵀ, Σr²]], truncated
    to the directions whose eigenvalue (yaw as arc length at radius) exceeds solve_ratio × the
    largest: the others get no step."""
    (h00, h01, h02, g0), (_, h11, h12, g1), (_, _, h22, g2), _ = normal.tolist()
    k = 1.0 / radius
    s02, s12, s22, b2 = h02 * k, h12 * k, h22 * k * k, g2 * k     # S = D·H·D, D = diag(1, 1, k)
    c00 = h11 * s22 - s12 * s12
    c01 = s02 * s12 - h01 * s22
    c02 = h01 * s12 - h11 * s02
    det = h00 * c00 + h01 * c01 + s02 * c02
    trace = h00 + h11 + s22
    # λmin ≥ det / (trace/2)² and λmax ≤ trace for a positive semi-definite 3x3: when this bound
    # already clears the ratio every direction is strong and the plain solve is the answer.
    if det > 0.0 and 4.0 * det > solve_ratio * trace ** 3:
        c11 = h00 * s22 - s02 * s02
        c12 = h01 * s02 - h00 * s12
        c22 = h00 * h11 - h01 * h01
        return (-(c00 * g0 + c01 * g1 + c02 * b2) / det,
                -(c01 * g0 + c11 * g1 + c12 * b2) / det,
                -(c02 * g0 + c12 * g1 + c22 * b2) / det * k)
    scale = np.array([1.0, 1.0, k])
    values, vectors = np.linalg.eigh(normal[:3, :3] * scale[:, None] * scale[None, :])
    if values[-1] <= 0:
        return 0.0, 0.0, 0.0
    strong = values > solve_ratio * values[-1]
    g = vectors.T @ (normal[:3, 3] * scale)
    g[strong] /= values[strong]
    g[~strong] = 0.0
    dx, dy, dyaw = -(vectors @ g) * scale
    return float(dx), float(dy), float(dyaw)


def _same_pairs(a: tuple, b: tuple) -> bool:
    """Whether two iterations chose the same (source point, target point) pairs."""
    (index_a, chosen_a), (index_b, chosen_b) = a, b
    matched_a = index_a if chosen_a is None else index_a[chosen_a]
    matched_b = index_b if chosen_b is None else index_b[chosen_b]
    return matched_a.size == matched_b.size and np.array_equal(matched_a, matched_b)


def _choose_pairs(size_sq, keep, count: int, corr: Correspondences, min_inliers: int,
                  floor_sq: float) -> tuple[NDArray[np.intp] | None, float]:
    """The robust rule: indices of the gated pairs that enter the estimate (None = all of them)
    and the median squared residual. size_sq is infinite for pairs outside the gate."""
    k = count // 2
    median_sq = float(np.partition(size_sq, k)[k])
    gated = count < keep.size and corr.robust != 'adaptive'      # adaptive chooses its own
    chosen: NDArray[np.intp] | None = np.flatnonzero(keep) if gated else None
    if corr.robust == 'trim' and count > min_inliers:
        n_keep = max(min_inliers, int(corr.trim_fraction * count))
        chosen = np.argpartition(size_sq, n_keep - 1)[:n_keep]
    elif corr.robust == 'adaptive':
        robust_sq = (corr.adaptive_factor * 1.4826) ** 2
        chosen = np.flatnonzero(size_sq <= max(robust_sq * median_sq, floor_sq))
        if chosen.size < min_inliers:
            chosen = np.argpartition(size_sq, min_inliers - 1)[:min_inliers]
        elif chosen.size == keep.size:
            chosen = None
    return chosen, median_sq


def _point_to_point_step(moved, index, chosen, tgt: Target, x: float, y: float):
    """Closed-form (SVD) increment (dx, dy, dyaw) for the chosen pairs of moved source points
    (N, 2) at translation (x, y)."""
    matched = index if chosen is None else index[chosen]
    p = moved if chosen is None else moved[chosen]
    r_step, t_step = align_paired(p, tgt.points.take(matched, axis=0))
    dyaw = math.atan2(r_step[1, 0], r_step[0, 0])
    # The SVD step is exact for these pairs; compose it with the current transform.
    new_xy = r_step @ np.array([x, y]) + t_step
    return float(new_xy[0]) - x, float(new_xy[1]) - y, dyaw


class _Stop:
    """The convergence rules of Convergence, fed one iteration at a time."""

    def __init__(self, rules: Convergence) -> None:
        self.rules = rules
        self.previous: tuple | None = None
        self.best_error, self.stalled = math.inf, 0

    def converged(self, step: float, pairs: tuple, history: list[float]) -> bool:
        rules = self.rules
        # The pairs (target index per chosen source point) are compared only when it matters.
        same_pairs = step < 10.0 * rules.tolerance and self.previous is not None \
            and _same_pairs(self.previous, pairs)
        self.previous = pairs
        error = history[-1]
        settled = len(history) >= 2 and \
            abs(history[-2] - error) <= rules.error_tolerance * error
        # Correspondences that flip back and forth keep the step from vanishing; when the error
        # has not improved on its best for `stall_iterations`, it has stopped changing.
        if error < self.best_error * (1.0 - rules.error_tolerance):
            self.best_error, self.stalled = error, 0
        else:
            self.stalled += 1
        return step < rules.tolerance or same_pairs or settled \
            or self.stalled >= rules.stall_iterations


# long: the hot loop of every match, kept flat (no per-iteration calls: numpy's call overhead
# dominates at ~300 points; docs/performance.md).
def _icp_loop(src, rows, tgt: Target, pose, options: IcpOptions, max_iterations: int,
              min_inliers: int, radius: float) -> _Loop:
    """Iterate correspondences and closed-form / Gauss-Newton steps from pose (x, y, yaw);
    src = source points as x + iy (N,), rows = the target's residual rows (Target.rows)."""
    state = _Loop(*pose, reason=f'max_iterations ({max_iterations}) reached')
    x, y, yaw = pose
    corr = options.correspondences
    gate = corr.max_correspondence_distance
    min_gate = min(corr.min_correspondence_distance, gate)
    floor_sq = (0.25 * min_gate) ** 2
    point_to_line = options.method == 'point_to_line'
    stop = _Stop(options.convergence)
    n = src.shape[0]
    for iteration in range(1, max_iterations + 1):
        state.iterations = iteration
        lever = src * complex(math.cos(yaw), math.sin(yaw))      # R·s
        moved = lever + complex(x, y)
        keep, index = _nearest(tgt, moved, gate)
        count = int(np.count_nonzero(keep))
        if count < min_inliers:
            state.reason = f'too few correspondences ({count} < {min_inliers}) within {gate:.3f} m'
            state.converged = False
            state.inliers = count
            break
        # Whitened Jacobian columns over (x, y, yaw) and residual of each pair's two rows:
        # [U | U·J·l | U·(p - q)], J = 90° rotation. Pairs beyond the gate get a clipped (wrong
        # but finite) target row and an infinite size, which keeps them out of the median and
        # of every rule below without copying the rest.
        whitened = rows.take(index, axis=2, mode='clip')          # (4, 2, n): [U | 0 | -U·q]
        u0, u1 = whitened[0], whitened[1]
        np.multiply(u1, lever.real, out=whitened[2])
        whitened[2] -= u0 * lever.imag
        residual = whitened[3]
        residual += u0 * moved.real
        residual += u1 * moved.imag
        size_sq = np.einsum('ji,ji->i', residual, residual)   # squared Mahalanobis-like (m²)
        if count < n:
            size_sq[~keep] = math.inf
        chosen, median_sq = _choose_pairs(size_sq, keep, count, corr, min_inliers, floor_sq)
        if chosen is not None:
            whitened, size_sq = whitened.take(chosen, axis=2), size_sq.take(chosen)
        state.inliers = size_sq.size
        state.error = float(np.sqrt(size_sq).sum()) / size_sq.size
        state.history.append(state.error)
        flat = whitened.reshape(4, -1)
        state.normal, state.origin = flat @ flat.T, (x, y)
        if point_to_line:
            dx, dy, dyaw = _solve_step(state.normal, radius, options.degeneracy_ratio)
        else:
            dx, dy, dyaw = _point_to_point_step(np.column_stack((moved.real, moved.imag)), index,
                                                chosen, tgt, x, y)
        x, y = x + dx, y + dy
        yaw = math.remainder(yaw + dyaw, 2.0 * math.pi)
        state.x, state.y, state.yaw = x, y, yaw
        if corr.robust == 'adaptive':
            gate = max(min_gate, min(gate, 2.0 * corr.adaptive_factor * 1.4826
                                     * math.sqrt(median_sq)))
        step = math.hypot(dx, dy) + abs(dyaw) * radius
        if stop.converged(step, (index, chosen), state.history):
            state.converged = True
            state.reason = ''
            break
    return state


def _score(src, tgt: Target, pose, inlier_distance: float) -> float:
    """Fraction of source points within inlier_distance (m) of a target point at pose."""
    moved = _complex(src) * complex(math.cos(pose[2]), math.sin(pose[2])) + complex(*pose[:2])
    keep, _ = _nearest(tgt, moved, inlier_distance)
    return float(keep.mean())


def _min_inliers(options: IcpOptions, source_count: int) -> int:
    corr = options.correspondences
    return max(corr.min_points, int(math.ceil(corr.min_inlier_fraction * source_count)))


def _search_yaw(src, rows, tgt: Target, start, options: IcpOptions, radius: float):
    """The seed of the fine match: the best-scoring coarse match over the yaw hypotheses."""
    search = options.yaw_search
    coarse = voxel_downsample(src, search.coarse_voxel_size) \
        if search.coarse_voxel_size > 0 else src
    if coarse.shape[0] < max(options.correspondences.min_points, 20):
        coarse = src            # too few points left to be worth a coarse stage
    best, best_score = start, -1.0
    for offset in (0.0, *search.yaw_hypotheses):
        seed = (start[0], start[1], start[2] + float(offset))
        state = _icp_loop(_complex(coarse), rows, tgt, seed, options,
                          search.coarse_iterations, _min_inliers(options, coarse.shape[0]),
                          radius)
        candidate = (state.x, state.y, state.yaw) if state.normal is not None else seed
        score = _score(coarse, tgt, candidate, search.score_distance)
        # The guess's own result wins unless a hypothesis explains clearly more points.
        if score > best_score + (search.hypothesis_margin if offset else 0.0):
            best, best_score = candidate, score
    return best


def match(
    source: ArrayLike,
    target: ArrayLike | Target,
    initial: ArrayLike = (0.0, 0.0, 0.0),
    *,
    options: IcpOptions | None = None,
    **keywords,
) -> MatchResult:
    """Align source (N, 2) to target ((M, 2) or a prepared Target), both in their own frames (m),
    starting from `initial` (x, y, yaw). See MatchResult for the output.

    Options: `options=IcpOptions(...)`, or flat keywords naming any of its fields (method,
    max_iterations, max_correspondence_distance, tolerance, robust, yaw_hypotheses, ...), which
    are set on top of `options` (the defaults when it is None); see IcpOptions and its parts for
    what each does. Malformed arrays or options raise ValueError (an unknown name TypeError);
    valid but unusable input (too few points, all points identical, a non-finite guess) returns
    converged=False with a reason.
    """
    options = options or _DEFAULT_OPTIONS
    if keywords:
        options = options.updated(**keywords)
    guess = np.asarray(initial, dtype=float).ravel()
    if guess.shape != (3,):
        raise ValueError(f'initial must be (x, y, yaw), got shape {guess.shape}')
    src, dropped = _as_points(source, 'source')
    tgt = target if isinstance(target, Target) else prepare_target(target)
    dropped += tgt.dropped
    if not np.all(np.isfinite(guess)):
        return _failed(guess, 'initial guess is not finite', src.shape[0], dropped)
    if options.voxel_size > 0:
        src = voxel_downsample(src, options.voxel_size)
    min_points = options.correspondences.min_points
    if src.shape[0] < min_points or tgt.points.shape[0] < min_points:
        return _failed(guess, f'too few valid points (source {src.shape[0]}, target '
                       f'{tgt.points.shape[0]}, need {min_points})', src.shape[0], dropped)
    centred = _complex(src)
    centred = (centred - centred.sum() / centred.size).view(np.float64)
    radius = math.sqrt(float(centred @ centred) / src.shape[0])
    target_points = _complex(tgt.points)
    if radius < 1e-9 or float(np.abs(target_points - target_points[0]).max()) < 1e-9:
        return _failed(guess, 'all points identical: rotation undefined', src.shape[0], dropped)

    if options.method == 'point_to_line':
        rows = tgt.rows if tgt.rows is not None else _residual_rows(tgt.points, tgt.information)
    else:
        rows = _identity_rows(tgt.points)
    start = (float(guess[0]), float(guess[1]), float(guess[2]))
    if options.yaw_search.yaw_hypotheses:
        start = _search_yaw(src, rows, tgt, start, options, radius)
    min_inliers = _min_inliers(options, src.shape[0])
    state = _icp_loop(_complex(src), rows, tgt, start, options,
                      options.convergence.max_iterations, min_inliers, radius)
    if state.normal is None or state.inliers < min_inliers:
        return MatchResult(state.x, state.y, state.yaw, np.eye(3) * FAILED_VARIANCE,
                           state.iterations, False, state.error, state.reason,
                           source_points=src.shape[0], dropped_points=dropped,
                           history=state.history, inliers=state.inliers)
    return _final_result(state, options, radius, src.shape[0], dropped)


def _final_result(state: _Loop, options: IcpOptions, radius: float, source_count: int,
                  dropped: int) -> MatchResult:
    """The MatchResult of a loop that ended with inliers, with its covariance."""
    x, y, yaw = state.x, state.y, state.yaw
    # Final linearised system over the last iteration's inlier pairs (converged: a tiny step),
    # with the levers taken about the final translation: moving the lever origin by Δt changes
    # each yaw Jacobian U·J·l by -U·J·Δt, i.e. the yaw column by a mix of the x and y columns.
    jx, jy = state.origin[1] - y, x - state.origin[0]      # J·Δt, Δt = final - origin
    shift = np.eye(4)
    shift[0, 2], shift[1, 2] = -jx, -jy
    normal = shift.T @ state.normal @ shift
    hessian = normal[:3, :3]
    # Each pair gives rank(Mᵢ) residuals: 1 on a line (tangent weight aside), 2 point-to-point;
    # trace(Mᵢ) = |Uᵢ|², summed over the pairs, is the trace of the x-y block.
    residual_count = float(normal[0, 0] + normal[1, 1])
    dof = max(1.0, residual_count - 3.0)
    variance = max(float(normal[3, 3]) / dof, options.min_residual_std ** 2)
    covariance, degenerate, direction, condition = _covariance(
        hessian, variance, radius, options.degeneracy_ratio)
    reason = state.reason
    if degenerate and state.converged:
        reason = 'degenerate: geometry leaves one direction unconstrained'
    return MatchResult(
        x=x, y=y, yaw=yaw, covariance=covariance, iterations=state.iterations,
        converged=state.converged, error=state.error, reason=reason, degenerate=degenerate,
        degenerate_direction=direction, inliers=state.inliers, source_points=source_count,
        dropped_points=dropped, condition=condition, history=state.history,
        residual_variance=variance)


def _covariance(info, variance, radius, degeneracy_ratio):
    """variance · info⁻¹ over (x, y, yaw); an unconstrained direction gets DEGENERATE_VARIANCE.
    Eigenvalues are compared with yaw as arc length at the scan radius (metres with metres)."""
    scale = np.array([1.0, 1.0, 1.0 / radius])
    outer = scale[:, None] * scale[None, :]
    values, vectors = np.linalg.eigh(info * outer)
    top = max(float(values[-1]), 1e-300)
    condition = max(float(values[0]), 0.0) / top
    weak = values <= degeneracy_ratio * top
    if not weak.any():
        cov = (vectors * (variance / values)) @ vectors.T
        cov *= outer
        return 0.5 * (cov + cov.T), False, None, condition
    inverse_values = np.where(weak, 0.0, 1.0 / np.where(weak, 1.0, values))
    cov_scaled = variance * (vectors * inverse_values) @ vectors.T
    cov_scaled += DEGENERATE_VARIANCE * (vectors[:, weak] @ vectors[:, weak].T)
    cov = cov_scaled * outer
    return 0.5 * (cov + cov.T), True, vectors[:, 0].copy(), condition
