"""python -m sensing_nodes.bench.icp --dataset DATASET [--measure accuracy|speed]
[--against small_gicp,kiss]: one ICP benchmark over one dataset, a table (and --json, every
figure). Accuracy: carmen-pairs, ours against small_gicp per pair (failure > 0.10 m or 2 deg);
sim, the route's drift, modes, deskewing and corridor against the ground truth; hall and outdoor,
the local map (and KISS-ICP) against the ground truth; carmen-logs, the logs through
carmen_to_bag, sensing_pipeline and sensing_eval (and the local map beside KISS-ICP). Speed:
carmen-pairs against the textbook ICP and small_gicp, sim against small_gicp, fast_lidar.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from sensing_nodes.bench.icp import accuracy, comparators, datasets, logs, speed

DEFAULT_AGAINST = {'carmen-pairs': 'small_gicp', 'hall': 'kiss', 'outdoor': 'kiss'}


def _accuracy(args, against: set[str]) -> tuple[dict, list[str]]:
    """(figures, tables) of the dataset's accuracy run."""
    voxels = comparators.KISS_VOXELS_M if 'kiss' in against else ()
    if args.dataset == 'carmen-pairs':
        methods = comparators.pair_matchers('small_gicp' in against)
        result = accuracy.evaluate(stride=args.stride, methods=methods)
        return result, [accuracy.pairs_table(result)]
    if args.dataset in ('hall', 'outdoor') or (args.dataset == 'sim' and voxels):
        world = '' if args.dataset == 'sim' else args.dataset
        rows = {f'simulated {args.dataset} ({args.seeds} seeds)':
                accuracy.kiss_sim_figures(args.seeds, world, voxels)}
        return rows, [accuracy.kiss_table(rows)]
    if args.dataset == 'sim':
        return accuracy.sim(args.quick), []
    # carmen-logs
    args.out.mkdir(parents=True, exist_ok=True)
    names, modes = [n for n in args.logs.split(',') if n], tuple(args.modes.split(','))
    result = {name: logs.log_figures(name, args.out, modes) for name in names}
    tables = [logs.table(result)] + ([logs.integrity_table(result)] if 'local_map' in modes
                                     else [])
    if voxels:
        side = {name: accuracy.kiss_log_figures(name, args.out, voxels=voxels) for name in names}
        result = {'pipeline': result, 'side_by_side': side}
        tables.append(accuracy.kiss_table(side))
    return result, tables


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog='python -m sensing_nodes.bench.icp',
                                     description=__doc__.split('\n\n')[0])
    parser.add_argument('--dataset', required=True, choices=datasets.DATASETS)
    parser.add_argument('--measure', choices=('accuracy', 'speed'), default='accuracy')
    parser.add_argument('--against', help='comparators for accuracy: small_gicp, kiss '
                        f'(default: {DEFAULT_AGAINST}, else none)')
    parser.add_argument('--out', type=Path, help='carmen-logs: folder for the bags')
    parser.add_argument('--logs', default=','.join(datasets.CARMEN_LOGS), help='carmen-logs')
    parser.add_argument('--modes', default=','.join(logs.MODES), help='carmen-logs')
    parser.add_argument('--seeds', type=int, default=2, help='sim, hall, outdoor: side by side')
    parser.add_argument('--stride', type=int, default=1, help='carmen-pairs: every n-th pair')
    parser.add_argument('--quick', action='store_true', help='smaller runs (a smoke test)')
    parser.add_argument('--json', type=Path, help='also write every figure here')
    args = parser.parse_args(argv)
    against = set(filter(None, (args.against if args.against is not None
                                else DEFAULT_AGAINST.get(args.dataset, '')).split(',')))
    if unknown := against - {'small_gicp', 'kiss'}:
        parser.error(f'unknown comparators {sorted(unknown)}')
    if 'kiss' in against:
        try:
            import kiss_icp  # noqa: F401
        except ImportError:
            print('kiss-icp is not installed (pip install -r requirements.txt)', file=sys.stderr)
            return 1
    if args.measure == 'speed':
        runs = {'carmen-pairs': lambda: speed.carmen_pairs(args.quick),
                'sim': lambda: speed.sim(20.0 if args.quick else 60.0, 1 if args.quick else 3),
                'fast_lidar': lambda: speed.run_fast_lidar(args.quick)}
        if args.dataset not in runs:
            parser.error(f'no speed run for {args.dataset} (its accuracy run has ms per scan)')
        result, tables = runs[args.dataset](), []
    elif args.dataset == 'fast_lidar':
        parser.error('fast_lidar measures speed only (--measure speed)')
    elif args.dataset == 'carmen-logs' and args.out is None:
        parser.error('carmen-logs needs --out, a folder for the converted and processed bags')
    else:
        result, tables = _accuracy(args, against)
    print('\n\n'.join(tables) if tables else json.dumps(result, indent=1))
    if args.json:
        args.json.write_text(json.dumps(result, indent=1))
    return 0


if __name__ == '__main__':
    sys.exit(main())
