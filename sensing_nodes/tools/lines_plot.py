"""lines_plot: render one scan and the lines extracted from it to a PNG (laser frame, metres).

    lines_plot --carmen LOG [--index K] --out scan.png
    lines_plot --bag BAG_DIR [--topic /scan] [--index K] --out scan.png

In a CARMEN log the no-return value is the log's largest range (50.0 in ACES, 81.91 in
Freiburg 101); such beams are treated as +inf (no return, REP 117).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from sensing_nodes.bags.carmen import read_carmen
from sensing_nodes.bags.sensor_streams import add_scan_source
from sensing_nodes.core.lines import Line, extract_lines


def carmen_scan(path: str | Path, index: int) -> tuple[NDArray, NDArray, dict, str]:
    """(ranges, angles, extraction limits, title) of scan `index` of a CARMEN log."""
    log = read_carmen(path)
    if not log.scans:
        raise ValueError(f'{path}: no FLASER scans')
    ranges = log.ranges_without_returns()[_check_index(index, len(log.scans))]
    return ranges, log.scan_angles(ranges.size), {}, f'{Path(path).name} scan {index}'


def bag_scan(path: str | Path, topic: str, index: int) -> tuple[NDArray, NDArray, dict, str]:
    """(ranges, angles, extraction limits, title) of message `index` on `topic` in a rosbag2."""
    from sensing_nodes.bags.storage import read_messages
    from sensing_nodes.ros.conversions import scan_arrays, stamp_to_ns

    count = 0
    for _, _, msg in read_messages(path, [topic]):
        if count == index:
            ranges, angles = scan_arrays(msg)
            limits = {}
            if np.isfinite(msg.range_min) and np.isfinite(msg.range_max) and \
                    0.0 <= msg.range_min < msg.range_max:
                limits = {'min_range': float(msg.range_min), 'max_range': float(msg.range_max)}
            stamp_s = stamp_to_ns(msg.header.stamp) / 1e9
            return (
                ranges,
                angles,
                limits,
                f'{Path(path).name} {topic} #{index} '
                f'(t={stamp_s:.3f} s, frame {msg.header.frame_id})',
            )
        count += 1
    if count == 0:
        raise ValueError(f'{path}: no messages on {topic}')
    _check_index(index, count)
    raise AssertionError('unreachable')


def _check_index(index: int, count: int) -> int:
    if not -count <= index < count:
        raise ValueError(f'scan index {index} out of range: there are {count} scans')
    return index


def render(ranges, angles, lines: list[Line], out: str | Path, title: str) -> None:
    """Write a PNG of the scan's valid points (grey) and the lines (coloured, numbered)."""
    import matplotlib

    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    r, a = np.asarray(ranges, dtype=float), np.asarray(angles, dtype=float)
    valid = np.isfinite(r)
    xs = np.r_[0.0, r[valid] * np.cos(a[valid])]
    ys = np.r_[0.0, r[valid] * np.sin(a[valid])]
    aspect = (np.ptp(ys) + 1.0) / (np.ptp(xs) + 1.0)
    fig, ax = plt.subplots(figsize=(10, float(np.clip(10 * aspect, 4, 12))))
    ax.plot(r[valid] * np.cos(a[valid]), r[valid] * np.sin(a[valid]), '.', color='0.55',
            markersize=3, label=f'{valid.sum()} valid beams')
    colours = plt.get_cmap('tab10')
    for k, line in enumerate(lines):
        (x0, y0), (x1, y1) = line.start, line.end
        ax.plot([x0, x1], [y0, y1], '-', color=colours(k % 10), linewidth=2.5)
        ax.annotate(str(k), ((x0 + x1) / 2, (y0 + y1) / 2), fontsize=8, color=colours(k % 10))
    ax.plot([0.0], [0.0], 'k^', markersize=8, label='laser')
    ax.set_aspect('equal')
    ax.grid(True, linewidth=0.3)
    ax.set_xlabel('x (m, laser frame)')
    ax.set_ylabel('y (m)')
    ax.set_title(f'{title}: {len(lines)} lines')
    ax.legend(loc='upper right', fontsize=8)
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog='lines_plot', description=__doc__.split('\n')[0])
    add_scan_source(parser, 'which scan (0-based; negative from the end)')
    parser.add_argument('--out', required=True, help='PNG file to write')
    parser.add_argument('--split-distance', type=float, default=0.05)
    parser.add_argument('--max-line-gap', type=float, default=0.5)
    parser.add_argument('--min-line-points', type=int, default=6)
    parser.add_argument('--min-line-length', type=float, default=0.2)
    parser.add_argument('--range-sigma', type=float, default=0.01)
    parser.add_argument('--max-range', type=float, default=None, help='ignore longer ranges (m)')
    args = parser.parse_args(argv)
    try:
        if args.carmen:
            ranges, angles, limits, title = carmen_scan(args.carmen, args.index)
        else:
            ranges, angles, limits, title = bag_scan(args.bag, args.topic, args.index)
        if args.max_range is not None:
            limits['max_range'] = min(args.max_range, limits.get('max_range', np.inf))
        lines = extract_lines(ranges, angles, split_distance=args.split_distance,
                              max_line_gap=args.max_line_gap, min_line_points=args.min_line_points,
                              min_line_length=args.min_line_length, range_sigma=args.range_sigma,
                              **limits)
        render(ranges, angles, lines, args.out, title)
    except (OSError, ValueError) as exc:
        print(f'lines_plot: {exc}', file=sys.stderr)
        return 1
    print(f'{title}: {len(lines)} lines -> {args.out}')
    for k, line in enumerate(lines):
        sd = np.sqrt(np.diag(line.covariance))
        print(
            f'  {k}: r={line.r:.3f} m (sd {sd[0]:.4f}), alpha={np.degrees(line.alpha):.2f} deg '
            f'(sd {np.degrees(sd[1]):.3f}), beams {line.first}-{line.last}, '
            f'length {line.length:.2f} m'
        )
    return 0


if __name__ == '__main__':
    sys.exit(main())
