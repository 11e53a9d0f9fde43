"""sensing_fuse_bag: complementary_fusion over a recorded bag (rosbag2 MCAP/sqlite3 or ROS 1) and
its final pose, with what each input contributed; optionally checked against an expected
final position.

    sensing_fuse_bag BAG [--params-file FILE]... [--param NAME:=VALUE]... \
        [--expect X Y [--tolerance M]]

The node is built as sensing_pipeline builds it (config/complementary_fusion.yaml, then each
--params-file or robot preset, then the --param overrides) and its processor takes the bag's
messages on the topics its parameters name, in bag order, without DDS: the same fusion session
as the running node and `sensing_pipeline BAG OUT --nodes complementary_fusion`, without
writing a bag. Prints JSON: the final pose (m, rad) and covariance, its stamp, the outputs, and
per input the messages received, rejected and gated, with the session's counters. Exit status
1 when --expect is given and the final position is further than --tolerance from it; 2 when
the bag or the parameters cannot be used (the message says why).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any

NODE = 'complementary_fusion'
EXIT_FAR = 1
EXIT_BAD_INPUT = 2
FUSED = '/odometry/filtered'


class FuseBagError(Exception):
    """The bag or the parameters cannot be used: the message names the file, topic or
    parameter."""


def fuse_bag(bag: str | Path, params_files: list[Path] | tuple = (),
             overrides: list[str] | tuple = ()) -> dict:
    """complementary_fusion over every message of the bag on its input topics (bag order), then
    flushed; the final output and the per-input counts (see the module's docstring).
    `overrides`: 'NAME:=VALUE' parameter assignments."""
    outputs, session = fused_outputs(bag, params_files, overrides)
    fused = [raw for topic, raw in outputs if topic == FUSED]
    return _result(session, fused[-1] if fused else None, len(fused))


def fused_outputs(bag: str | Path, params_files: list[Path] | tuple = (),
                  overrides: list[str] | tuple = ()) -> tuple[list[tuple[str, bytes]], Any]:
    """Every (topic, CDR bytes) the fusion node publishes over the bag, in order (the bag's
    messages on its input topics in bag order, then the flush at the end), and the node's
    fusion session (core/fusion/session.py) as it ended."""
    from sensing_nodes.bags.input_bag import InputBagError, load_bag
    from sensing_nodes.bags.storage import type_name
    from sensing_nodes.graph.pipeline import PipelineError, build_nodes, close
    from sensing_nodes.ros.cdr import cdr_decoder

    try:
        loaded = load_bag(bag)
        built = build_nodes((NODE,), list(params_files),
                            {NODE: [a for o in overrides for a in ('-p', o)]})
    except (InputBagError, PipelineError) as error:
        raise FuseBagError(str(error)) from None
    try:
        processor = built[NODE].processor
        handlers = {}
        for i in processor.inputs():
            if i.topic not in loaded.types:
                raise FuseBagError(
                    f'{bag}: no topic {i.topic}, an input of the fusion (the bag has: '
                    f'{", ".join(sorted(loaded.types))}); name its topic (--param '
                    'wheel_odom.topic:=..., imu.topic, scan_match.topic) or switch it off '
                    '(use_wheel_odom, use_imu, use_scan_match_position and _heading)')
            if loaded.types[i.topic] != type_name(i.msg_type):
                raise FuseBagError(f'{bag}: topic {i.topic} holds {loaded.types[i.topic]}, '
                                   f'the fusion takes {type_name(i.msg_type)}')
            handlers[i.topic] = (i.handler, cdr_decoder(i.msg_type))
        outputs = []
        for topic, _, raw in loaded.messages:
            if topic in handlers:
                handler, decode = handlers[topic]
                outputs += handler(decode(raw))
        outputs += processor.flush()
        return outputs, processor.session
    finally:
        close(built)


def _result(session, last: bytes | None, outputs: int) -> dict:
    """The final output (decoded from its CDR bytes) and the session's counts."""
    from nav_msgs.msg import Odometry

    from sensing_nodes.ros.cdr import cdr_decoder
    from sensing_nodes.ros.conversions import odometry_pose, stamp_to_ns

    enabled = [name for name, record in session.records.items() if record.enabled]
    result: dict = {'outputs': outputs, 'final_pose': None, 'final_covariance': None,
                    'stamp_ns': None}
    if last is not None:
        msg = cdr_decoder(Odometry)(last)
        pose, covariance = odometry_pose(msg)
        result.update(final_pose=list(pose), final_covariance=covariance.tolist(),
                      stamp_ns=stamp_to_ns(msg.header.stamp))
    counts = session.counts
    result.update(
        received={name: session.records[name].received for name in enabled},
        rejected={name: counts[f'{name}_rejected'] for name in enabled
                  if counts[f'{name}_rejected']},
        gated=dict(session.fusion.gated),
        counts=dict(sorted(counts.items())))
    return result


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog='sensing_fuse_bag', description=__doc__.split('\n\n')[0],
        formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__.split('\n\n', 2)[2])
    parser.add_argument('bag', help='a rosbag2 folder (MCAP or sqlite3) or a ROS 1 .bag file')
    parser.add_argument('--params-file', '--params', action='append', default=[],
                        metavar='FILE', help='complementary_fusion parameters over its config/ '
                        'file, or a robot preset name (repeatable)')
    parser.add_argument('--param', action='append', default=[], metavar='NAME:=VALUE',
                        help='a parameter override (after the parameter files)')
    parser.add_argument('--expect', nargs=2, type=float, metavar=('X', 'Y'),
                        help='the expected final position (m)')
    parser.add_argument('--tolerance', type=float, default=0.1383,
                        help='largest distance from --expect (m; default 0.1383, '
                             "robot_localization's test2.bag tolerance)")
    args = parser.parse_args(argv)
    from sensing_nodes.graph.cli import GraphArgumentError, params_file_path

    try:
        params_files = [params_file_path(f) for f in args.params_file]
        bad = [p for p in args.param if ':=' not in p]
        if bad:
            raise FuseBagError(f'--param {bad[0]!r}: write NAME:=VALUE')
        result = fuse_bag(args.bag, params_files, args.param)
        if args.expect and result['final_pose'] is None:
            raise FuseBagError(f'{args.bag}: the fusion published nothing: no final position')
    except (FuseBagError, GraphArgumentError) as error:
        print(f'sensing_fuse_bag: error: {error}', file=sys.stderr)
        return EXIT_BAD_INPUT
    if args.expect:
        x, y = result['final_pose'][:2]
        result['distance_to_expected_m'] = math.hypot(x - args.expect[0], y - args.expect[1])
    print(json.dumps(result, indent=1))
    if args.expect and result['distance_to_expected_m'] > args.tolerance:
        print(f"sensing_fuse_bag: final position {result['distance_to_expected_m']:.4f} m from "
              f'the expected one (> {args.tolerance} m)', file=sys.stderr)
        return EXIT_FAR
    return 0


if __name__ == '__main__':
    sys.exit(main())
