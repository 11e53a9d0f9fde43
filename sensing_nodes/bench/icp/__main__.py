"""python -m sensing_nodes.bench.icp --dataset DATASET [--measure accuracy|speed]
[--against small_gicp,kiss]: the ICP benchmark on one dataset; prints its tables (--json: every
figure to a file).

Accuracy: carmen-pairs, ours (and small_gicp) per consecutive pair; sim, the route's drift,
modes, deskewing and corridor against the ground truth; sim, hall and outdoor with kiss, the
local map beside KISS-ICP against the ground truth; carmen-logs, the logs through carmen_to_bag,
sensing_pipeline and sensing_eval (with kiss: the local map beside KISS-ICP). Speed (its
comparators always): carmen-pairs (the textbook ICP, small_gicp), sim (small_gicp), fast_lidar.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from sensing_nodes.bench.icp import accuracy, comparators, datasets, logs, speed


def _accuracy(args, against: set[str]) -> tuple[dict, list[str]]:
    """(figures, tables) of the dataset's accuracy run."""
    voxels = comparators.KISS_VOXELS_M if 'kiss' in against else ()
    if args.dataset == 'carmen-pairs':
        result = accuracy.evaluate(stride=args.stride,
                                   methods=comparators.pair_matchers('small_gicp' in against))
        return result, [accuracy.pairs_table(result)]
    if args.dataset != 'carmen-logs':
        world = '' if args.dataset == 'sim' else args.dataset
        side = {f'simulated {args.dataset} ({args.seeds} seeds)':
                accuracy.kiss_sim_figures(args.seeds, world, voxels)}
        if world:
            return side, [accuracy.kiss_table(side)]
        result = accuracy.sim(args.quick)
        return {**result, 'side_by_side': side}, [json.dumps(result, indent=1),
                                                  accuracy.kiss_table(side)]
    args.out.mkdir(parents=True, exist_ok=True)
    names, modes = args.logs.split(','), tuple(filter(None, args.modes.split(',')))
    bags = {name: datasets.carmen_bag(name, args.out) for name in names}
    result = {name: logs.log_figures(bag, modes) for name, bag in bags.items() if modes}
    side = {name: accuracy.kiss_log_figures(bag, voxels=voxels) for name, bag in bags.items()}
    return {'pipeline': result, 'side_by_side': side}, (
        [logs.table(result)] * bool(modes) + [logs.integrity_table(result)] * (
            'local_map' in modes) + [accuracy.kiss_table(side)])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog='python -m sensing_nodes.bench.icp',
                                     description=__doc__.split('\n\n')[0])
    parser.add_argument('--dataset', required=True, choices=datasets.DATASETS)
    parser.add_argument('--measure', choices=('accuracy', 'speed'), default='accuracy')
    parser.add_argument('--against', default='small_gicp,kiss',
                        help='accuracy: the comparators (default small_gicp,kiss)')
    parser.add_argument('--out', type=Path, help='carmen-logs: a folder for the bags')
    parser.add_argument('--logs', default=','.join(datasets.CARMEN_LOGS), help='carmen-logs')
    parser.add_argument('--modes', default=','.join(logs.MODES),
                        help="carmen-logs: the matcher's modes in sensing_pipeline ('': none)")
    parser.add_argument('--seeds', type=int, default=2, help='sim, hall, outdoor: seeds')
    parser.add_argument('--stride', type=int, default=1, help='carmen-pairs: every n-th pair')
    parser.add_argument('--quick', action='store_true', help='smaller runs (a smoke test)')
    parser.add_argument('--json', type=Path, help='also write every figure here')
    args = parser.parse_args(argv)
    against = set(filter(None, args.against.split(',')))
    speeds = {'carmen-pairs': lambda: speed.carmen_pairs(args.quick),
              'sim': lambda: speed.sim(20.0 if args.quick else 60.0, 1 if args.quick else 3),
              'fast_lidar': lambda: speed.run_fast_lidar(args.quick)}
    if against - {'small_gicp', 'kiss'}:
        parser.error(f'unknown comparators in {sorted(against)}')
    unsupported = args.dataset not in speeds if args.measure == 'speed' \
        else args.dataset == 'fast_lidar'     # fast_lidar: speed only
    if unsupported:
        parser.error(f'no {args.measure} run for {args.dataset}')
    if args.measure == 'accuracy' and args.dataset == 'carmen-logs' and args.out is None:
        parser.error('carmen-logs needs --out, a folder for the converted and processed bags')
    if 'kiss' in against and args.measure == 'accuracy':
        try:
            import kiss_icp  # noqa: F401
        except ImportError:
            print('kiss-icp is not installed (pip install -r requirements.txt)', file=sys.stderr)
            return 1
    result, tables = ((speeds[args.dataset](), []) if args.measure == 'speed'
                      else _accuracy(args, against))
    print('\n\n'.join(tables) if tables else json.dumps(result, indent=1))
    if args.json:
        args.json.write_text(json.dumps(result, indent=1))
    return 0


if __name__ == '__main__':
    sys.exit(main())
