"""A 2-D world of wall segments (map frame, metres) and exact, vectorised ray casting against
it."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml
from numpy.typing import ArrayLike, NDArray


@dataclass(frozen=True)
class World:
    """Wall segments as an (M, 4) array of [x0, y0, x1, y1] in the map frame (m)."""

    name: str
    segments: NDArray[np.float64]


def world_from_dict(data: dict) -> World:
    """Build a World from the YAML structure {name, walls: [[x0,y0,x1,y1]...], polygons:
    [[[x,y]...]...]}.

    Raises ValueError naming the faulty entry.
    """
    if not isinstance(data, dict):
        raise ValueError('world must be a mapping with walls and/or polygons')
    segments: list[list[float]] = []
    for i, wall in enumerate(data.get('walls') or []):
        values = np.asarray(wall, dtype=float) if _numeric(wall) else None
        if values is None or values.shape != (4,) or not np.all(np.isfinite(values)):
            raise ValueError(
                f'walls[{i}] must be four finite numbers [x0, y0, x1, y1], got {wall!r}'
            )
        if np.allclose(values[:2], values[2:]):
            raise ValueError(f'walls[{i}] has zero length')
        segments.append(values.tolist())
    for i, polygon in enumerate(data.get('polygons') or []):
        vertices = np.asarray(polygon, dtype=float) if _numeric(polygon) else None
        if vertices is None or vertices.ndim != 2 or vertices.shape[1] != 2 or len(vertices) < 3 \
                or not np.all(np.isfinite(vertices)):
            raise ValueError(f'polygons[{i}] must be at least three finite [x, y] vertices')
        closed = np.vstack((vertices, vertices[:1]))
        segments.extend(np.hstack((closed[:-1], closed[1:])).tolist())
    if not segments:
        raise ValueError('world has no walls and no polygons')
    return World(name=str(data.get('name', 'world')), segments=np.array(segments))


def load_world(path: str | Path) -> World:
    """Read a world YAML file; ValueError (with the path) when missing or malformed."""
    path = Path(path)
    try:
        data = yaml.safe_load(path.read_text())
    except OSError as exc:
        raise ValueError(f'cannot read world file {path}: {exc.strerror}') from exc
    except yaml.YAMLError as exc:
        raise ValueError(f'world file {path} is not valid YAML: {exc}') from exc
    try:
        return world_from_dict(data)
    except ValueError as exc:
        raise ValueError(f'world file {path}: {exc}') from exc


def _numeric(value) -> bool:
    try:
        np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        return False
    return True


def raycast(
    segments: NDArray[np.float64], origin: ArrayLike, angles: ArrayLike
) -> NDArray[np.float64]:
    """Distance (m) from origin (x, y), or from each beam's own origin ((B, 2): a laser that
    moves during its sweep), along each world-frame beam angle (rad) to the first segment it
    hits; +inf where it hits none. Occlusion follows from taking the nearest hit."""
    origin = np.asarray(origin, dtype=float)
    if origin.ndim == 2:
        ox, oy = origin[:, :1], origin[:, 1:]                            # (B, 1)
    else:
        ox, oy = float(origin[0]), float(origin[1])
    angles = np.asarray(angles, dtype=float)
    dx, dy = np.cos(angles)[:, None], np.sin(angles)[:, None]           # (B, 1)
    px, py = segments[:, 0] - ox, segments[:, 1] - oy                     # (M,)
    ex, ey = segments[:, 2] - segments[:, 0], segments[:, 3] - segments[:, 1]
    denom = dx * ey - dy * ex                                             # cross(d, e), (B, M)
    with np.errstate(divide='ignore', invalid='ignore'):
        t = (px * ey - py * ex) / denom                                   # along the beam
        s = (px * dy - py * dx) / denom                                   # along the segment
    hit = (np.abs(denom) > 1e-12) & (t > 0.0) & (s >= 0.0) & (s <= 1.0)
    return np.where(hit, t, np.inf).min(axis=1)
