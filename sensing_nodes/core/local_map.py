"""A 2-D map of the recent surroundings for scan-to-map registration (icp_matcher's local_map
mode).

Frame and units: the odom frame (m). Points are binned in square cells of side `cell_m`; each
cell keeps the count and sum of the points that fell into it (up to `max_points_per_cell`: a
full cell takes no more, so the first views of a wall stay the reference) and the sum of their
normals' outer products n·nᵀ, each normal found in its own scan (icp.scan_normals: the point's
nearest neighbours in that scan, which reach along a distant wall however sparse its points).
The map is pruned by distance from the robot and bounded in size. What a scan is registered
against is one point per cell: the mean of its points, with the normal the cell's normals agree
on, line-like when most of its points were and their normals agree.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from sensing_nodes.core import icp
from sensing_nodes.parameters import CheckedAtConstruction

# Cell (ix, iy) -> one int64 key (ix + OFFSET) · STRIDE + (iy + OFFSET): sorted keys group a
# column of cells, and a neighbour's key is the key plus dx · STRIDE + dy.
_OFFSET = 1 << 30
_STRIDE = 1 << 31


@dataclass(frozen=True)
class LocalMapSettings(CheckedAtConstruction):
    """Cell size (m), how many points a cell takes, how far from the robot cells are kept (m:
    at least radius_m, further where the scans reach further) and how many at most, and the
    planarity from which a cell's block counts as a line."""

    cell_m: float = 0.10
    max_points_per_cell: int = 20
    radius_m: float = 30.0
    # Cells are kept within max(radius_m, this x the recent scans' 90th-percentile range): the
    # map holds what the scans see. In an open hall (simulated, walls 20-45 m away, a 40 m
    # laser) a fixed 30 m dropped the far walls the scans still saw and 3 of 8 seeds slid
    # 0.25-1.0 m along the hall (0.011-0.025 m kept).
    radius_per_range: float = 1.25
    max_cells: int = 60_000
    min_planarity: float = 0.5

    def problems(self) -> list[tuple[str, str, object]]:
        """(field, problem, value) for each setting a map cannot be kept with."""
        checks = (('cell_m', self.cell_m > 0, 'must be > 0'),
                  ('max_points_per_cell', self.max_points_per_cell >= 1, 'must be >= 1'),
                  ('radius_m', self.radius_m > 0, 'must be > 0'),
                  ('radius_per_range', self.radius_per_range >= 0, 'must be >= 0'),
                  ('max_cells', self.max_cells >= 1, 'must be >= 1'),
                  ('min_planarity', 0 <= self.min_planarity <= 1, 'must be in [0, 1]'))
        return [(name, problem, getattr(self, name)) for name, ok, problem in checks if not ok]


class LocalMap:
    """Cells of points in the odom frame (m): insert(), prune(), and target() for icp.match."""

    # Per cell: count, Σx, Σy of its points relative to the cell's centre, then Σ n·nᵀ over its
    # line-like points (nx², nx·ny, ny²) and how many were line-like.
    _COLUMNS = 7

    def __init__(self, settings: LocalMapSettings | None = None) -> None:
        self.settings = settings or LocalMapSettings()
        self.clear()

    def clear(self) -> None:
        """Forget every cell."""
        self.keys = np.zeros(0, dtype=np.int64)
        self.stats = np.zeros((0, self._COLUMNS))
        self._target: icp.Target | None = None

    def __len__(self) -> int:
        return int(self.keys.size)

    @property
    def points(self) -> int:
        """Points held over all cells."""
        return int(self.stats[:, 0].sum())

    def _cells(self, points: NDArray[np.float64]) -> tuple[NDArray[np.int64],
                                                           NDArray[np.float64]]:
        """Each point's cell key and its offset (m) from the cell's centre."""
        cell = self.settings.cell_m
        index = np.floor(points * (1.0 / cell))
        offset = points - (index + 0.5) * cell
        index = index.astype(np.int64) + _OFFSET
        return index[:, 0] * _STRIDE + index[:, 1], offset

    def cells(self) -> NDArray[np.int64]:
        """Integer index (M, 2) of every cell: floor(x / cell_m), floor(y / cell_m)."""
        ix, iy = np.divmod(self.keys, _STRIDE)
        return np.column_stack((ix, iy)) - _OFFSET

    def centres(self) -> NDArray[np.float64]:
        """Centre (M, 2) of every cell (m)."""
        return (self.cells() + 0.5) * self.settings.cell_m

    def insert(self, points: NDArray[np.float64], normals: NDArray[np.float64],
               planarity: NDArray[np.float64]) -> None:
        """Add points (N, 2), odom frame (m), with their unit normals (N, 2, odom frame) and
        planarity (N,) from their own scan, to their cells; cells already holding
        max_points_per_cell points take no more (a cell below it takes the whole scan's)."""
        points = np.asarray(points, dtype=float).reshape(-1, 2)
        if points.shape[0] == 0:
            return
        keys, offset = self._cells(points)
        unique, inverse = np.unique(keys, return_inverse=True)
        at = np.searchsorted(self.keys, unique)
        known = np.zeros(unique.size, dtype=bool)
        inside = at < self.keys.size
        known[inside] = self.keys[at[inside]] == unique[inside]
        if not known.all():
            merged = np.concatenate((self.keys, unique[~known]))
            order = np.argsort(merged, kind='stable')
            self.keys = merged[order]
            self.stats = np.vstack((self.stats,
                                    np.zeros(((~known).sum(), self._COLUMNS))))[order]
            at = np.searchsorted(self.keys, unique)
        slot = at[inverse.ravel()]
        open_cell = self.stats[:, 0].take(slot) < self.settings.max_points_per_cell
        if not open_cell.all():
            slot, offset = slot[open_cell], offset[open_cell]
            normals, planarity = normals[open_cell], planarity[open_cell]
        line = (planarity >= self.settings.min_planarity).astype(float)
        nx, ny = normals[:, 0] * line, normals[:, 1] * line
        size = self.keys.size
        columns = (None, offset[:, 0], offset[:, 1], nx * nx, nx * ny, ny * ny, line)
        for column, weights in enumerate(columns):
            self.stats[:, column] += np.bincount(slot, weights, minlength=size)
        self._target = None

    def prune(self, centre: tuple[float, float], radius_m: float | None = None) -> int:
        """Drop the cells whose centre is further than radius_m (default: the settings') from
        centre (x, y), odom frame (m), then the furthest beyond max_cells; returns how many
        were dropped."""
        if self.keys.size == 0:
            return 0
        s = self.settings
        radius = s.radius_m if radius_m is None else radius_m
        away = self.centres() - np.asarray(centre, dtype=float)
        distance_sq = np.einsum('ij,ij->i', away, away)
        keep = distance_sq <= radius * radius
        if np.count_nonzero(keep) > s.max_cells:
            nearest = np.argpartition(distance_sq, s.max_cells - 1)[:s.max_cells]
            keep = np.zeros_like(keep)
            keep[nearest] = True
        dropped = int(keep.size - np.count_nonzero(keep))
        if dropped:
            self.keys, self.stats = self.keys[keep], self.stats[keep]
            self._target = None
        return dropped

    def target(self) -> icp.Target:
        """The cells as an icp target (built once per change of the map): each cell's mean point
        with its normal, found through the cells."""
        if self._target is None:
            self._target = self._build_target()
        return self._target

    def _build_target(self) -> icp.Target:
        s = self.settings
        count, sx, sy, nxx, nxy, nyy, lines = self.stats.T
        cells = self.cells()
        mean = (cells + 0.5) * s.cell_m
        mean[:, 0] += sx / count
        mean[:, 1] += sy / count
        # The direction the normals agree on: the principal axis of Σ n·nᵀ, in closed form;
        # agreement (λ1 - λ2)/(λ1 + λ2) times the share of line-like points is the planarity.
        half_difference = 0.5 * (nxx - nyy)
        theta = 0.5 * np.arctan2(nxy, half_difference)
        normals = np.column_stack((np.cos(theta), np.sin(theta)))
        half_trace = 0.5 * (nxx + nyy)
        with np.errstate(invalid='ignore', divide='ignore'):
            planarity = np.hypot(half_difference, nxy) / half_trace * (lines / count)
        planarity[~(half_trace > 0)] = 0.0
        np.clip(planarity, 0.0, 1.0, out=planarity)
        grid = icp.grid_index(mean, cells, s.cell_m)
        return icp.map_target(mean, normals, planarity, grid, s.min_planarity)

    def memory_bytes(self) -> int:
        """Bytes held by the cells (keys and statistics)."""
        return int(self.keys.nbytes + self.stats.nbytes)


def cell_count_bound(settings: LocalMapSettings) -> int:
    """The most cells the map can hold: max_cells, or every cell within radius_m if fewer (with
    radius_per_range the reach follows the scans: max_cells)."""
    if settings.radius_per_range:
        return settings.max_cells
    within = math.pi * (settings.radius_m / settings.cell_m + 1.0) ** 2
    return int(min(settings.max_cells, within))
