"""Reading CARMEN laser logs (FLASER / ODOM / PARAM lines, optionally gzipped) into arrays, and
judging their time.

Beams span 180 degrees counter-clockwise from -90 degrees; the FLASER pose of the shared
"corrected" logs is the laser's pose (see ../shared/datasets/carmen/README.md).

Real logs' stamps can be broken: all written as 0 (freiburg-campus), lost to six significant
digits (1.13486e+09: far fewer distinct stamps than lines), a clock that stood still (many
consecutive lines on one stamp), going backwards, negative, or wrapped (a span of 2^32 s).
`check_time` names the problem; `line_order_time` rebuilds a time base from the order of the
lines, every ODOM line one tick of an assumed odometry rate.
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
    odom_line: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
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
                    odom_rows.append([float(w) for w in words[1:8]] + [number])
                    if len(odom_rows[-1]) != 8:
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
        log.odom_line = rows[:, 7].astype(np.int64)
    return log


# An ODOM line stamped below this is "stamped 0": Freiburg 101 writes 18 of its 292 zeros as
# garbage such as 2.5e-91 (each repeats its scan's reference pose, as the real zeros do).
ZERO_STAMP_S = 1e-6
WRAP_S = 2.0 ** 31     # a step or span of 68 years: a clock that wrapped, not a robot's run
# Fewer distinct stamps than this share of a stream's lines (ODOM or FLASER): too coarse to order
# them (six significant digits of seconds since 1970 keep one stamp per 10^4 s).
COARSE_DISTINCT = 0.5
# This many consecutive lines of one stream on one stamp: a clock that stood still, where the
# rest of the stamps may be sound. The shared logs' longest run is 2 (Edmonton's odometry).
REPEATED_RUN = 5


def reference_repeats(log: CarmenLog) -> NDArray[np.bool_]:
    """ODOM rows that repeat the reference pose of the FLASER line just before them (the
    "corrected" logs' re-anchoring line, whatever its stamp: freiburg-campus stamps some 3.46
    or 81.91, acapulco 3.7)."""
    repeats = np.zeros(len(log.odom_time_s), dtype=bool)
    after = np.searchsorted(log.odom_line, [scan.line for scan in log.scans], side='right')
    for scan, i in zip(log.scans, after.tolist()):
        if i < len(repeats) and tuple(log.odom_pose[i].tolist()) == tuple(scan.pose):
            repeats[i] = True
    return repeats


@dataclass(frozen=True)
class TimeCheck:
    """What is wrong with a log's stamps: kind '' (nothing), 'all_equal' or 'coarse' (no time
    to use: rebuild it), 'backwards', 'negative', 'wrapped' or 'repeated' (time that is partly
    sound: refuse, or rebuild when asked), and a sentence naming it with line numbers."""

    kind: str
    text: str = ''


def check_time(log: CarmenLog, anchors: NDArray[np.bool_]) -> TimeCheck:
    """Judge the stamps of the odometry rows that are not `anchors` and of the scans."""
    odom = ~anchors
    t, lines = log.odom_time_s[odom], log.odom_line[odom]
    scans = np.array([s.time_s for s in log.scans])
    merged = np.concatenate([t, scans])
    merged_lines = np.concatenate([lines, [s.line for s in log.scans]]).astype(np.int64)
    order = np.argsort(merged_lines, kind='stable')
    merged, merged_lines = merged[order], merged_lines[order]
    if merged.size and np.all(merged == merged[0]):
        return TimeCheck('all_equal', f'every stamp is {merged[0]:g}: the log has no time')
    negative = np.flatnonzero(merged <= -ZERO_STAMP_S)
    if negative.size:
        return TimeCheck('negative', f'stamps are negative at {negative.size} lines (the first: '
                                     f'line {merged_lines[negative[0]]}: '
                                     f'{merged[negative[0]]:g})')
    steps = np.diff(merged)
    wraps = np.flatnonzero(np.abs(steps) >= WRAP_S)
    if wraps.size or (merged.size and np.ptp(merged) >= WRAP_S):
        at = wraps[0] + 1 if wraps.size else int(np.argmax(merged))
        return TimeCheck('wrapped', f'the stamps span {np.ptp(merged):.4g} s (at line '
                                    f'{merged_lines[at]}: {merged[at]:.10g}): a clock that '
                                    'wrapped around')
    streams = (('ODOM', t, lines), ('FLASER', scans,
                                     np.array([s.line for s in log.scans], dtype=np.int64)))
    for name, stamps, _ in streams:
        coarse = coarse_stamps(name, stamps)
        if coarse:
            return TimeCheck('coarse', coarse)
    back = np.flatnonzero(steps < 0)
    if back.size:
        return TimeCheck('backwards', f'stamps go backwards at {back.size} lines (the first: '
                                      f'line {merged_lines[back[0] + 1]}: '
                                      f'{merged[back[0] + 1]:g} after {merged[back[0]]:g})')
    for name, stamps, stream_lines in streams:
        first, count = longest_run(stamps)
        if count >= REPEATED_RUN:
            return TimeCheck('repeated', f'{count} consecutive {name} lines carry the same stamp '
                                         f'{stamps[first]:.10g} (lines {stream_lines[first]} to '
                                         f'{stream_lines[first + count - 1]}): a clock that '
                                         'stood still')
    return TimeCheck('')


def coarse_stamps(name: str, stamps: NDArray[np.float64]) -> str:
    """Why the stamps (s) of a stream's lines (named `name`) are too coarse to order them
    (fewer distinct than COARSE_DISTINCT of the lines), or ''."""
    distinct = np.unique(stamps)
    if stamps.size < 2 or distinct.size >= COARSE_DISTINCT * stamps.size:
        return ''
    steps = np.diff(distinct)
    resolution = f'; the smallest step between them is {steps.min():g} s' if steps.size else ''
    return (f'the {stamps.size} {name} lines carry {distinct.size} distinct stamps: too coarse '
            f'to order them (written to too few significant digits, e.g. {stamps[0]:g}?)'
            f'{resolution}')


def longest_run(stamps: NDArray[np.float64]) -> tuple[int, int]:
    """(index of its first element, length) of the longest run of consecutive equal stamps."""
    if stamps.size == 0:
        return 0, 0
    starts = np.flatnonzero(np.concatenate([[True], stamps[1:] != stamps[:-1]]))
    lengths = np.diff(np.concatenate([starts, [stamps.size]]))
    longest = int(np.argmax(lengths))
    return int(starts[longest]), int(lengths[longest])


def line_order_time(log: CarmenLog, anchors: NDArray[np.bool_],
                    rate_hz: float) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """A time base from the order of the lines: the k-th ODOM line that is not an anchor at
    k / rate_hz s, an anchor and a scan at the time of the ODOM line before them (a logged
    FLASER carries its preceding odometry's stamp); (odometry times, scan times), s."""
    tick = np.cumsum(~anchors) - 1                   # ticks of the non-anchor rows so far
    odom_s = np.maximum(tick, 0) / rate_hz
    scan_lines = np.array([s.line for s in log.scans], dtype=np.int64)
    before = np.searchsorted(log.odom_line, scan_lines, side='left') - 1
    scan_s = np.where(before >= 0, odom_s[np.maximum(before, 0)], 0.0) if len(odom_s) else \
        np.zeros(len(scan_lines))
    return odom_s, scan_s
