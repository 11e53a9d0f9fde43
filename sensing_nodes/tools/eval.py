"""sensing_eval: relative pose error (Kümmerle et al. 2009) and absolute trajectory error of
estimate topics in a bag, against the bag's /ground_truth/odom or a relations file.

Relations from the reference trajectory pair each reference sample with the first one at least
--delta-s later (0: the next sample, e.g. consecutive scans of a CARMEN log). A relations file
(`t1 t2 x y z roll pitch yaw`, seconds, pose of t2 in the frame of t1) is used as it is, its
times shifted by --time-offset to match the bag's stamps. Estimates are interpolated at the
relation times (linear in x, y, unwrapped yaw); where one stamp carries several messages the
last one counts (the fusion publishes its scan-match update after the odometry update).
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from sensing_nodes.bags.sensor_streams import atomic_write
from sensing_nodes.core.evaluation.metrics import (
    absolute_trajectory_error,
    read_relations,
    relations_from_trajectory,
    relative_pose_errors,
)

EXIT_BAD_INPUT = 2
ODOMETRY = 'nav_msgs/msg/Odometry'
REFERENCE = '/ground_truth/odom'
TIME_BASE_KEY = 'carmen_to_bag.time_base'   # custom_data of a bag whose stamps were rebuilt


class EvalError(Exception):
    """Bad input: the message names the file and topic."""


MIN_SHARE = 0.5   # default --min-share: fewer of the relations asked for scored is refused


@dataclass
class Trajectory:
    """An Odometry topic: header stamps (ns, sorted, one per stamp: the last message of a
    repeated stamp kept), poses (N, 3), and how many messages it had."""

    t: np.ndarray
    poses: np.ndarray
    messages: int


def _open(bag: Path):
    """The bag's BagReader; EvalError naming the bag when it cannot be read."""
    from sensing_nodes.bags.storage import BagError, BagReader

    if not bag.exists():
        raise EvalError(f'{bag}: no such bag')
    try:
        return BagReader(bag)
    except BagError as exc:
        raise EvalError(str(exc)) from None


def _read_odometry(reader, topics: list[str]) -> dict[str, Trajectory]:
    """topic -> Trajectory of Odometry topics, each checked to be there with 2 messages."""
    from sensing_nodes.ros.conversions import odometry_pose, stamp_to_ns

    available = {t: (i.msgtype, i.count) for t, i in reader.topics.items()}
    bag = reader.path
    for topic in topics:
        if topic not in available:
            raise EvalError(
                f'{bag}: topic {topic} is not in the bag (Odometry topics: '
                f'{", ".join(t for t, (ty, _) in sorted(available.items()) if ty == ODOMETRY)})'
            )
        if available[topic][0] != ODOMETRY:
            raise EvalError(f'{bag}: topic {topic} holds {available[topic][0]}, not {ODOMETRY}')
        if available[topic][1] < 2:
            raise EvalError(f'{bag}: topic {topic} has {available[topic][1]} messages (need 2)')
    rows: dict[str, dict[int, tuple]] = {t: {} for t in topics}
    try:
        for topic, _, msg in reader.messages(topics):
            pose, _ = odometry_pose(msg)
            rows[topic][stamp_to_ns(msg.header.stamp)] = pose  # a later message at a stamp wins
    except Exception as exc:
        from sensing_nodes.bags.storage import failure_reason

        raise EvalError(f'{bag}: cannot read the bag ({failure_reason(exc)}); '
                        'truncated?') from None
    out = {}
    for topic, by_stamp in rows.items():
        stamps = np.array(sorted(by_stamp), dtype=np.int64)
        out[topic] = Trajectory(stamps, np.array([by_stamp[s] for s in stamps.tolist()],
                                                 dtype=float).reshape(-1, 3),
                                available[topic][1])
    return out


def load_trajectories(bag: Path, topics: list[str]) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """topic -> (stamps ns, poses (N, 3)) from Odometry topics (header stamps, sorted, the last
    message of a repeated stamp kept)."""
    return {t: (r.t, r.poses) for t, r in _read_odometry(_open(Path(bag)), topics).items()}


def evaluate(bag: str | Path, topics: list[str] | None = None, relations_file: str | None = None,
             reference: str = REFERENCE, delta_s: float = 0.0,
             time_offset_s: float = 0.0, min_share: float = MIN_SHARE) -> dict:
    """{'reference': ..., 'estimates': {topic: RPE and ATE figures}} (ATE needs the reference
    trajectory in the bag). Each estimate is scored on the relations it spans; EvalError when
    that is fewer than min_share of the relations asked for, which are the reference's
    consecutive messages (or a relations file's lines), and a 'shortfall' note otherwise."""
    bag = Path(bag)
    reader = _open(bag)
    if topics is None:
        topics = _estimate_topics(reader, reference)
    from_file = None
    if relations_file is not None:  # read first: a bad file fails before the bag is loaded
        from_file = _read_relations_file(relations_file, time_offset_s)
    has_reference = reference in reader.topics
    trajectories = _read_odometry(reader, list(topics) + ([reference] if has_reference else []))
    if from_file is not None:
        relations, source, asked, notes = from_file, f'relations file {relations_file}', \
            len(from_file.t1), []
    elif has_reference:
        relations, source, asked, notes = _reference_relations(trajectories[reference],
                                                               reference, delta_s)
    else:
        raise EvalError(f'{bag}: topic {reference} is not in the bag and no --relations given')
    report = {'bag': str(bag), 'reference': source, 'estimates': {}, 'notes': notes,
              **({'time_base': reader.custom_data[TIME_BASE_KEY]}
                 if TIME_BASE_KEY in reader.custom_data else {})}
    for topic in topics:
        estimate = trajectories[topic]
        errors = relative_pose_errors(relations, estimate.t, estimate.poses)
        if errors.translation_m.size == 0:
            raise EvalError(f'{bag}: topic {topic} spans no relation of the {source} '
                            '(stamps do not overlap; --time-offset?)')
        entry = {**errors.summary(), 'relations_asked': asked}
        shortfall = _shortfall(topic, estimate, relations, errors, asked, notes)
        if shortfall and errors.translation_m.size < min_share * asked:
            raise EvalError(f'{bag}: {shortfall}; refused: fewer than {min_share:g} of them '
                            '(--min-share)')
        if shortfall:
            entry['shortfall'] = shortfall
        if has_reference:
            ref = trajectories[reference]
            entry.update(absolute_trajectory_error(ref.t, ref.poses, estimate.t, estimate.poses))
        report['estimates'][topic] = entry
        report.setdefault('_errors', {})[topic] = errors
    report['_trajectories'] = {t: (r.t, r.poses) for t, r in trajectories.items()}
    return report


def _estimate_topics(reader, reference: str) -> list[str]:
    """Every Odometry topic of the bag but the reference; EvalError when there is none."""
    topics = sorted(t for t, i in reader.topics.items()
                    if i.msgtype == ODOMETRY and t != reference)
    if not topics:
        held = ', '.join(f'{t} ({i.msgtype})' for t, i in sorted(reader.topics.items()))
        raise EvalError(f'{reader.path}: no {ODOMETRY} topic to score besides the reference '
                        f'{reference} (the bag holds: {held or "none"}); name one with --topic')
    return topics


def _read_relations_file(path: str, time_offset_s: float):
    try:
        return read_relations(path, int(round(time_offset_s * 1e9)))
    except OSError as exc:
        raise EvalError(f'{path}: {exc.strerror}') from None
    except ValueError as exc:
        raise EvalError(str(exc)) from None


def _reference_relations(ref: Trajectory, reference: str, delta_s: float):
    """(relations, their source in words, how many are asked for, notes) from the reference:
    consecutive messages are asked for, so a reference whose stamps repeat gives fewer."""
    relations = relations_from_trajectory(ref.t, ref.poses, delta_s)
    source = f'{reference} (delta {delta_s:g} s)' if delta_s > 0 else \
        f'{reference} (consecutive)'
    asked = len(relations.t1) if delta_s > 0 else ref.messages - 1
    notes = []
    if ref.t.size < ref.messages:
        notes.append(f'the reference {reference} has {ref.messages} messages at only '
                     f'{ref.t.size} distinct stamps (its time is broken?): '
                     f'{len(relations.t1)} relations')
    return relations, source, asked, notes


def _shortfall(topic: str, estimate: Trajectory, relations, errors, asked: int,
               notes: list[str]) -> str:
    """Why an estimate scores fewer relations than asked for, in words ('' when it does not)."""
    scored = int(errors.translation_m.size)
    if scored >= asked:
        return ''
    why = list(notes)
    if errors.skipped and relations.t1.size:
        first = int(relations.t1.min())
        span = (estimate.t[0] - first) * 1e-9, (estimate.t[-1] - first) * 1e-9
        whole = 0.0, (int(relations.t2.max()) - first) * 1e-9
        why.append(f'{errors.skipped} outside its stamps ({span[0]:.3f} to {span[1]:.3f} s; the '
                   f'relations {whole[0]:.3f} to {whole[1]:.3f} s)')
    return (f'{topic} scores {scored} of the {asked} relations asked for'
            + (': ' + '; '.join(why) if why else ''))


def table(report: dict) -> str:
    lines = [
        f"{report['bag']}: relative pose error against {report['reference']}",
        *([f"time base: {report['time_base']}"] if 'time_base' in report else []),
        '',
        f"{'estimate':<22}{'relations':>14}{'RPE translation (m)':>24}{'RPE rotation (deg)':>22}"
        f"{'ATE rmse (m)':>14}{'median RPE (m, deg)':>22}",
    ]
    for topic, e in report['estimates'].items():
        ate = f"{e['ate_rmse_m']:14.3f}" if 'ate_rmse_m' in e else f"{'-':>14}"
        scored = f"{e['relations']}/{e['relations_asked']}"
        lines.append(
            f"{topic:<22}{scored:>14}"
            f"{e['rpe_translation_mean_m']:>13.3f} ± {e['rpe_translation_std_m']:<8.3f}"
            f"{e['rpe_rotation_mean_deg']:>11.2f} ± {e['rpe_rotation_std_deg']:<8.2f}{ate}"
            f"{e['rpe_translation_median_m']:>14.3f}, {e['rpe_rotation_median_deg']:.2f}"
        )
    return '\n'.join(lines)


def plot(report: dict, path: Path, reference: str = REFERENCE) -> None:
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    from sensing_nodes.core.evaluation.metrics import align_rigid_2d, interpolate_poses
    from sensing_nodes.core.geometry import se2

    trajectories = report['_trajectories']
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(13, 5.5))
    if reference in trajectories:
        t_ref, ref = trajectories[reference]
        ax.plot(ref[:, 0], ref[:, 1], 'k-', lw=2, label=f'{reference} (reference)')
    for topic in report['estimates']:
        t, est = trajectories[topic]
        xy = est[:, :2]
        if reference in trajectories:
            at = interpolate_poses(t_ref, ref, t)
            keep = np.all(np.isfinite(at), axis=1)
            xy = se2.transform_points(align_rigid_2d(at[keep, :2], est[keep, :2]), est[:, :2])
        ax.plot(xy[:, 0], xy[:, 1], '-', lw=1.2, label=topic)
        errors = report['_errors'][topic]
        t0 = errors.t1[0] if errors.t1.size else 0
        bx.plot((errors.t1 - t0) * 1e-9, errors.translation_m, '.', ms=3, label=topic)
    ax.set_aspect('equal')
    ax.set_xlabel('x (m)')
    ax.set_ylabel('y (m)')
    ax.set_title('trajectories (estimates rigidly aligned to the reference)')
    ax.legend(fontsize=8)
    bx.set_xlabel('relation start (s from the first)')
    bx.set_ylabel('relative translation error (m)')
    bx.set_title(f"RPE per relation against {report['reference']}")
    bx.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog='sensing_eval', description=__doc__.split('\n\n')[0])
    parser.add_argument('bag', help='bag with the estimate topics (nav_msgs/Odometry): a rosbag2 '
                        'folder or a ROS 1 .bag file')
    parser.add_argument(
        '--topic',
        action='append',
        default=None,
        help='estimate topic (repeat; default: every Odometry topic but the reference)',
    )
    parser.add_argument(
        '--reference', default=REFERENCE, help=f'reference topic (default {REFERENCE})'
    )
    parser.add_argument(
        '--relations',
        default=None,
        help='relations file (t1 t2 x y z roll pitch yaw) instead of the reference',
    )
    parser.add_argument('--delta-s', type=float, default=0.0,
                        help='relations from the reference: pair samples this far apart (s); '
                             '0 = consecutive samples')
    parser.add_argument(
        '--time-offset',
        type=float,
        default=0.0,
        help='seconds added to the relation file times (carmen_to_bag --time-offset)',
    )
    parser.add_argument('--min-share', type=float, default=MIN_SHARE,
                        help='refuse when an estimate scores fewer than this share of the '
                             f'relations asked for (default {MIN_SHARE:g}; fewer than all is '
                             'always said)')
    parser.add_argument('--json', type=Path, default=None, help='write the figures as JSON here')
    parser.add_argument('--png', type=Path, default=None, help='write a plot here')
    args = parser.parse_args(argv)
    if args.delta_s < 0:
        parser.error('--delta-s must be >= 0')
    if not 0 <= args.min_share <= 1:
        parser.error('--min-share must be in [0, 1]')
    try:
        report = evaluate(args.bag, args.topic, args.relations, args.reference, args.delta_s,
                          args.time_offset, args.min_share)
    except EvalError as exc:
        print(f'sensing_eval: error: {exc}', file=sys.stderr)
        return EXIT_BAD_INPUT
    for entry in report['estimates'].values():
        if 'shortfall' in entry:
            print(f"sensing_eval: warning: {entry['shortfall']}", file=sys.stderr)
    print(table(report))
    if args.png is not None:
        atomic_write(args.png, lambda p: plot(report, p, args.reference))
        print(f'wrote {args.png}')
    if args.json is not None:
        public = {k: v for k, v in report.items() if not k.startswith('_')}
        atomic_write(args.json, lambda p: p.write_text(json.dumps(public, indent=2) + '\n'))
        print(f'wrote {args.json}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
