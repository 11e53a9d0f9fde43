"""Reading CARMEN laser logs (FLASER / ODOM / PARAM lines, optionally gzipped) into arrays.

Beams span 180 degrees counter-clockwise from -90 degrees; the FLASER pose of the shared
"corrected" logs is the laser's pose (see ../shared/datasets/carmen/README.md).
"""

from __future__ import annotations

import gzip
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

# Record types that carry nothing this package uses; skipped without complaint.
_IGNORED = {'NEFF', 'SYNC', 'RLASER', 'TRUEPOS', 'RAWLASER1', 'RAWLASER2', 'ROBOTLASER1'}


@dataclass
class CarmenScan:
    """One FLASER record: ranges (m), the reference pose (x, y, theta) and its time (s)."""

    ranges: NDArray[np.float64]
    pose: tuple[float, float, float]
    odom_pose: tuple[float, float, float]
    time_s: float
    line: int


@dataclass
class CarmenLog:
    scans: list[CarmenScan] = field(default_factory=list)
    odom_time_s: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))
    odom_pose: NDArray[np.float64] = field(default_factory=lambda: np.zeros((0, 3)))
    odom_velocity: NDArray[np.float64] = field(default_factory=lambda: np.zeros((0, 2)))
    params: dict[str, str] = field(default_factory=dict)
    errors: list[tuple[int, str]] = field(default_factory=list)  # (line number, reason)

    def scan_angles(self, beam_count: int) -> NDArray[np.float64]:
        """Beam angles (rad, laser frame) of a scan with beam_count beams over 180 degrees."""
        return -np.pi / 2 + np.pi * np.arange(beam_count) / beam_count

    def largest_range(self) -> float:
        """The largest range in the log (m): the plots take it for the no-return value."""
        return max(float(scan.ranges.max()) for scan in self.scans)

    def ranges_without_returns(self) -> list[NDArray[np.float64]]:
        """Ranges (m) of every scan, with the log's no-return value (its largest range) as +inf."""
        if not self.scans:
            return []
        no_return = self.largest_range()
        return [np.where(scan.ranges >= no_return, np.inf, scan.ranges) for scan in self.scans]


def _open_text(path: Path):
    return gzip.open(path, 'rt') if path.suffix == '.gz' else path.open('r')


def read_carmen(path: str | Path) -> CarmenLog:
    """Parse a CARMEN log; a line that does not parse is recorded in `errors` with its
    number and the rest is still read. Raises OSError when the file cannot be read."""
    log = CarmenLog()
    odom_rows: list[list[float]] = []
    with _open_text(Path(path)) as handle:
        for number, line in enumerate(handle, start=1):
            words = line.split()
            if not words or words[0].startswith('#'):
                continue
            kind = words[0]
            try:
                if kind == 'FLASER':
                    count = int(words[1])
                    values = np.array(words[2:2 + count + 7], dtype=float)
                    if values.size != count + 7 or count <= 0:
                        raise ValueError(f'expected {count} ranges, 6 pose values and a time')
                    log.scans.append(CarmenScan(
                        ranges=values[:count],
                        pose=tuple(values[count:count + 3]),
                        odom_pose=tuple(values[count + 3:count + 6]),
                        time_s=float(values[count + 6]),
                        line=number,
                    ))
                elif kind == 'ODOM':
                    odom_rows.append([float(w) for w in words[1:8]])
                    if len(odom_rows[-1]) != 7:
                        odom_rows.pop()
                        raise ValueError('expected x y theta tv rv accel time')
                elif kind == 'PARAM':
                    log.params[words[1]] = words[2]
                elif kind not in _IGNORED:
                    raise ValueError(f'unknown record type {kind!r}')
            except (ValueError, IndexError) as exc:
                log.errors.append((number, f'{kind}: {exc}'))
    if odom_rows:
        rows = np.array(odom_rows)
        log.odom_pose, log.odom_velocity, log.odom_time_s = rows[:, 0:3], rows[:, 3:5], rows[:, 6]
    return log
