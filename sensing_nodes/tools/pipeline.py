"""sensing_pipeline: the processing nodes' work over a bag without DDS, written into a new bag
(graph/pipeline.py does the work; docs/pipeline.md)."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from sensing_nodes.graph.pipeline import EXIT_BAD_INPUT, PipelineError, run


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    from sensing_nodes.topics import PROCESSING_NODES

    parser = argparse.ArgumentParser(prog='sensing_pipeline', description=__doc__.split('\n\n')[0])
    parser.add_argument('bag', help='input bag: a rosbag2 folder (MCAP or sqlite3) or a ROS 1 '
                        '.bag file')
    parser.add_argument('out', help='output bag folder to create (the bag\'s topics + outputs)')
    parser.add_argument('--nodes', default=','.join(PROCESSING_NODES),
                        help='which processing nodes (comma separated; default all five)')
    parser.add_argument('--param', action='append', default=[], metavar='NODE:NAME:=VALUE',
                        help='a parameter override for one node (after the parameter files)')
    parser.add_argument('--params-file', action='append', default=[], type=Path, metavar='FILE',
                        help='a ROS parameter file applied after config/<node>.yaml (repeatable)')
    parser.add_argument('--remap', action='append', default=[], metavar='BAG_TOPIC:=TOPIC',
                        help='feed a bag topic to the nodes under another name')
    parser.add_argument('--compress', action='store_true',
                        help='zstd-compress the output bag\'s MCAP chunks')
    parser.add_argument('--no-progress', action='store_true', help='no progress bar')
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    started = time.monotonic()
    args = parse_args(argv)
    from sensing_nodes.graph.cli import (
        GraphArgumentError,
        params_file_path,
        parse_node_params,
        parse_nodes,
        parse_remaps,
    )

    try:
        try:
            nodes = parse_nodes(args.nodes)
            node_params = parse_node_params(args.param)   # node -> ['-p', 'NAME:=VALUE', ...]
            remaps = parse_remaps(args.remap)
            params_files = [params_file_path(f) for f in args.params_file]
        except GraphArgumentError as exc:
            raise PipelineError(str(exc)) from None
        counts = run(args.bag, args.out, nodes, params_files=params_files,
                     node_params=node_params, remaps=remaps, progress=not args.no_progress,
                     compress=args.compress)
    except PipelineError as exc:
        print(f'sensing_pipeline: error: {exc}', file=sys.stderr)
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        print('sensing_pipeline: interrupted; no output written', file=sys.stderr)
        return 130
    print(f'sensing_pipeline: wrote {args.out} in {time.monotonic() - started:.1f} s; outputs: '
          + ', '.join(f'{t} {n}' for t, n in counts.items()))
    return 0


if __name__ == '__main__':
    sys.exit(main())
