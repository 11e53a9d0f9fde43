"""icp_plot: render a scan pair before and after ICP alignment to a PNG (target frame, metres).

    icp_plot --carmen LOG [--index K] [--guess identity|reference] --out pair.png
    icp_plot --bag BAG_DIR [--topic /scan] [--index K] [--step S] --out pair.png

The target is scan K, the source scan K+S (S = 1 by default); the source is drawn at the initial
guess (left) and at the match (right). In a CARMEN log, ranges at or above the log's largest
value are its no-return beams (50.0 in ACES, 81.91 in Freiburg 101) and are dropped; the guess
'reference' is the relative pose of the log's corrected poses, 'identity' is no motion.
A bag has no reference, so its guess is identity.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

from numpy.typing import NDArray

from sensing_nodes.bags.carmen import read_carmen
from sensing_nodes.bags.sensor_streams import add_scan_source
from sensing_nodes.core import icp
from sensing_nodes.core.geometry.scan import scan_to_points
from sensing_nodes.core.geometry.se2 import Pose2, between, transform_points


def carmen_pair(path: str | Path, index: int, step: int
                ) -> tuple[NDArray, NDArray, Pose2, str]:
    """Target points (scan index), source points (index + step), their reference relative pose
    and a title, from a CARMEN log."""
    log = read_carmen(path)
    count = len(log.scans)
    if count < step + 1:
        raise ValueError(f'{path}: {count} scans, need at least {step + 1}')
    if not 0 <= index < count - step:
        raise ValueError(f'scan index {index} out of range: 0 .. {count - step - 1}')
    no_return, all_ranges = log.largest_range(), log.ranges_without_returns()
    clouds = []
    for ranges in (all_ranges[index], all_ranges[index + step]):
        clouds.append(scan_to_points(ranges, log.scan_angles(ranges.size), 0.01, no_return)[0])
    reference = between(log.scans[index].pose, log.scans[index + step].pose)
    return clouds[0], clouds[1], reference, f'{Path(path).name} scans {index} -> {index + step}'


def bag_pair(path: str | Path, topic: str, index: int, step: int
             ) -> tuple[NDArray, NDArray, None, str]:
    """Target and source points of LaserScan messages index and index + step in a rosbag2."""
    from sensing_nodes.bags.storage import read_messages
    from sensing_nodes.ros.conversions import scan_arrays

    wanted = {index: None, index + step: None}
    count = 0
    for _, _, msg in read_messages(path, [topic]):
        if count in wanted:
            ranges, angles = scan_arrays(msg)
            wanted[count] = scan_to_points(ranges, angles, msg.range_min, msg.range_max)[0]
        count += 1
        if count > index + step:
            break
    if any(v is None for v in wanted.values()):
        raise ValueError(f'{path}: {count} messages on {topic}, need index {index + step}')
    return (
        wanted[index],
        wanted[index + step],
        None,
        f'{Path(path).name} {topic} #{index} -> #{index + step}',
    )


def render(target, source, guess: Pose2, result: icp.MatchResult, out: str | Path, title: str,
           reference: Pose2 | None = None) -> None:
    """Two panels: the source (red) on the target (black) at the guess and after the match."""
    import matplotlib

    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(14, 7), sharex=True, sharey=True)
    for ax, pose, label in ((axes[0], guess, 'initial guess'), (axes[1], result.pose, 'matched')):
        moved = transform_points(pose, source)
        ax.plot(target[:, 0], target[:, 1], '.', color='black', markersize=2.5, label='target')
        ax.plot(moved[:, 0], moved[:, 1], '.', color='tab:red', markersize=2.5, label='source')
        ax.plot([0.0], [0.0], 'k^', markersize=7)
        ax.plot([pose[0]], [pose[1]], '^', color='tab:red', markersize=7)
        ax.set_aspect('equal')
        ax.grid(True, linewidth=0.3)
        ax.set_xlabel('x (m, target frame)')
        ax.set_title(f'{label}: x={pose[0]:.3f} m, y={pose[1]:.3f} m, '
                     f'yaw={math.degrees(pose[2]):.2f} deg', fontsize=10)
        ax.legend(loc='upper right', fontsize=8)
    axes[0].set_ylabel('y (m)')
    status = 'converged' if result.converged else f'NOT converged ({result.reason})'
    extra = ''
    if reference is not None:
        extra = (f'; reference x={reference[0]:.3f}, y={reference[1]:.3f}, '
                 f'yaw={math.degrees(reference[2]):.2f} deg')
    fig.suptitle(f'{title}: {status}, {result.iterations} iterations, mean error '
                 f'{result.error:.4f} m, {result.inliers}/{result.source_points} inliers{extra}',
                 fontsize=10)
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog='icp_plot', description=__doc__.split('\n')[0])
    add_scan_source(parser, 'target scan (0-based)')
    parser.add_argument('--step', type=int, default=1, help='source = scan index + step')
    parser.add_argument('--guess', choices=('identity', 'reference'), default='identity',
                        help="initial guess (CARMEN only: 'reference' = the logs' poses)")
    parser.add_argument('--method', choices=('point_to_line', 'point_to_point'),
                        default='point_to_line')
    parser.add_argument('--yaw-hypotheses', default='',
                        help='comma-separated yaw offsets (deg) tried around the guess')
    parser.add_argument('--out', required=True, help='PNG file to write')
    args = parser.parse_args(argv)
    if args.step < 1:
        parser.error('--step must be >= 1')
    try:
        hypotheses = tuple(math.radians(float(v)) for v in args.yaw_hypotheses.split(',') if v)
    except ValueError:
        parser.error(f'--yaw-hypotheses: not a list of numbers: {args.yaw_hypotheses!r}')
    try:
        if args.carmen:
            target, source_points, reference, title = carmen_pair(args.carmen, args.index,
                                                                  args.step)
        else:
            target, source_points, reference, title = bag_pair(args.bag, args.topic, args.index,
                                                               args.step)
        guess = reference if (args.guess == 'reference' and reference is not None) \
            else (0.0, 0.0, 0.0)
        result = icp.match(source_points, target, guess, method=args.method,
                           yaw_hypotheses=hypotheses)
        render(target, source_points, guess, result, args.out, title, reference)
    except (OSError, ValueError) as exc:
        print(f'icp_plot: {exc}', file=sys.stderr)
        return 1
    print(f'{title}: x={result.x:.4f} m, y={result.y:.4f} m, yaw={math.degrees(result.yaw):.3f} '
          f'deg, converged={result.converged}, iterations={result.iterations}, '
          f'error={result.error:.4f} m -> {args.out}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
