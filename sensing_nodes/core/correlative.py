"""Wide correlative search of a scan against a map (Olson, "Real-time correlative scan
matching", ICRA 2009): every rotation of the scan in a window is scored against a likelihood
grid of the map at every translation in a window, coarse to fine, to re-acquire the pose when
the local ICP has lost it.

Frames and units: the scan's points (N, 2) in the laser frame (m); the map's points and the
poses (x, y, yaw) of the laser in the map's frame (m, rad).

Two lookup tables as in the paper: the fine one is exp(-d²/2σ²) of each cell's distance d to
the nearest map point (σ = one cell); a coarse cell holds the largest fine value over the block
of fine translations it stands for, so a coarse score bounds every fine score of its block at
that rotation. Rotations are searched at the coarse step first and refined around the best
coarse candidates (the paper's exhaustive fine rotations cost too much in numpy for a +-180 deg
window).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from sensing_nodes.core import icp
from sensing_nodes.core.geometry.se2 import Pose2

# Scan points used for the search (a voxel-downsampled subset: the search is for the basin, the
# ICP that follows for the pose).
MAX_SEARCH_POINTS = 200
# Points further than this from the laser are left out of the search (m): they make the
# rotation step fine and the tables large, and the near ones suffice to find the basin.
MAX_SEARCH_RANGE_M = 15.0


def correlative_search(points: NDArray[np.float64], target: icp.Target, guess: Pose2,
                       window_m: float, window_rad: float, resolution_m: float = 0.05,
                       coarse_cells: int = 8, candidates: int = 12,
                       min_score: float = 0.5) -> Pose2 | None:
    """The laser pose (map frame) within window_m (x and y) and window_rad of guess whose scan
    best overlaps the map (target.points), or None when the best explains less than min_score
    (the mean likelihood of the scan's points, 1 = every point on a map point).

    Coarse: rotations at the step that moves the scan's furthest point by one coarse cell,
    each scored at every coarse block of translations through the coarse table (the most any
    translation in the block can score). Fine: the best `candidates` coarse results, each at
    the fine rotations within half a coarse step of it and every fine translation in its
    block."""
    scan = _search_points(np.asarray(points, dtype=float), resolution_m)
    if scan.shape[0] < 3 or target.points.shape[0] < 3:
        return None
    reach = max(float(np.sqrt(np.einsum('ij,ij->i', scan, scan).max())), resolution_m)
    margin = window_m + reach + 2.0 * coarse_cells * resolution_m
    lo, hi = np.array(guess[:2]) - margin, np.array(guess[:2]) + margin
    near = target.points[np.all((target.points >= lo) & (target.points <= hi), axis=1)]
    if near.shape[0] < 3:
        return None
    fine, origin = _likelihood(near, lo, hi, resolution_m)
    coarse = _block_max(fine, coarse_cells)
    w = int(math.ceil(window_m / resolution_m))
    starts = np.arange(-w, w + 1, coarse_cells)             # coarse blocks of fine offsets
    fine_step = resolution_m / reach
    coarse_step = coarse_cells * fine_step
    span = min(window_rad, math.pi)
    yaws = guess[2] + coarse_step * np.arange(-math.ceil(span / coarse_step),
                                              math.ceil(span / coarse_step) + 1)
    cells = _rotated_cells(scan, yaws, guess, origin, resolution_m)        # (A, N, 2)
    coarse_score = np.empty((yaws.size, starts.size, starts.size))
    chunk = max(1, 200_000 // (scan.shape[0] * starts.size ** 2))
    for first in range(0, yaws.size, chunk):
        part = cells[first:first + chunk]
        coarse_score[first:first + chunk] = _lookup(
            coarse, part[:, :, 0, None, None] + starts[:, None],
            part[:, :, 1, None, None] + starts[None, :]).sum(axis=1)
    best_score, best = -1.0, None
    offsets = np.arange(coarse_cells)
    turns = fine_step * np.arange(-(coarse_cells // 2), coarse_cells // 2 + 1)
    for flat in np.argsort(coarse_score, axis=None)[::-1][:candidates]:
        a, i, j = np.unravel_index(flat, coarse_score.shape)
        tx, ty = starts[i] + offsets, starts[j] + offsets
        tx, ty = tx[np.abs(tx) <= w], ty[np.abs(ty) <= w]
        around = yaws[a] + turns
        rotated = _rotated_cells(scan, around, guess, origin, resolution_m)    # (R, N, 2)
        score = _lookup(fine, rotated[:, :, 0, None, None] + tx[:, None],
                        rotated[:, :, 1, None, None] + ty[None, :]).sum(axis=1)
        r, u, v = np.unravel_index(int(score.argmax()), score.shape)
        if score[r, u, v] > best_score:
            best_score = float(score[r, u, v])
            best = (guess[0] + tx[u] * resolution_m, guess[1] + ty[v] * resolution_m,
                    float(math.remainder(around[r], 2.0 * math.pi)))
    if best is None or best_score / scan.shape[0] < min_score:
        return None
    return best


def _search_points(points: NDArray[np.float64], resolution_m: float) -> NDArray[np.float64]:
    """The scan points within MAX_SEARCH_RANGE_M, voxel-downsampled to at most
    MAX_SEARCH_POINTS."""
    points = points[np.einsum('ij,ij->i', points, points) <= MAX_SEARCH_RANGE_M ** 2]
    voxel = 2.0 * resolution_m
    while points.shape[0] > MAX_SEARCH_POINTS:
        points = icp.voxel_downsample(points, voxel)
        voxel *= 1.5
    return points


def _likelihood(points: NDArray[np.float64], lo: NDArray[np.float64], hi: NDArray[np.float64],
                resolution_m: float) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The fine table over [lo, hi] (m): exp(-d²/2σ²), d = distance of each cell's centre to
    the nearest map point's cell (m), σ = one cell; and the table's origin (m)."""
    shape = np.ceil((hi - lo) / resolution_m).astype(int) + 1
    index = np.floor((points - lo) / resolution_m).astype(int)
    occupied = np.ones(shape, dtype=bool)
    occupied[index[:, 0], index[:, 1]] = False
    distance = ndimage.distance_transform_edt(occupied)            # in cells
    return np.exp(-0.5 * distance * distance), lo


def _block_max(fine: NDArray[np.float64], k: int) -> NDArray[np.float64]:
    """coarse[i, j] = max of fine[i:i+k, j:j+k] (cells beyond the table count as 0)."""
    padded = np.zeros((fine.shape[0] + k - 1, fine.shape[1] + k - 1))
    padded[:fine.shape[0], :fine.shape[1]] = fine
    rows = padded[:fine.shape[0]].copy()
    for u in range(1, k):
        np.maximum(rows, padded[u:u + fine.shape[0]], out=rows)
    out = rows[:, :fine.shape[1]].copy()
    for v in range(1, k):
        np.maximum(out, rows[:, v:v + fine.shape[1]], out=out)
    return out


def _rotated_cells(scan: NDArray[np.float64], yaws: NDArray[np.float64], guess: Pose2,
                   origin: NDArray[np.float64], resolution_m: float) -> NDArray[np.intp]:
    """Fine cell (A, N, 2) of each scan point rotated by each yaw and placed at the guess's
    translation."""
    c, s = np.cos(yaws)[:, None], np.sin(yaws)[:, None]
    x = c * scan[:, 0] - s * scan[:, 1] + (guess[0] - origin[0])
    y = s * scan[:, 0] + c * scan[:, 1] + (guess[1] - origin[1])
    return np.floor(np.stack((x, y), axis=2) / resolution_m).astype(np.intp)


def _lookup(table: NDArray[np.float64], ix: NDArray[np.intp],
            iy: NDArray[np.intp]) -> NDArray[np.float64]:
    """table[ix, iy], 0 outside the table (broadcast shapes)."""
    inside = (ix >= 0) & (ix < table.shape[0]) & (iy >= 0) & (iy < table.shape[1])
    flat = np.clip(ix, 0, table.shape[0] - 1) * table.shape[1] + np.clip(iy, 0,
                                                                           table.shape[1] - 1)
    return np.where(inside, table.ravel().take(flat), 0.0)
