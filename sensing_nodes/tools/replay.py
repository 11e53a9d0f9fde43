"""sensing_replay: play a bag's input topics into the running nodes over DDS and record what
they publish into a new bag.

Lockstep (default): publish one input message, wait until the nodes have published what it
causes (the expectation table: input topic -> output topics, each carrying the input's stamp),
then the next; deterministic. Timed: respects the stamps, scaled by --rate, and publishes /clock.
With --launch the package's processing nodes are started (with their config/ parameter files)
and stopped by the tool itself; --make-bags DIR regenerates the project's bags in bags/.
The replay itself is graph/replayer.py, the input and output bags bags/input_bag.py, the
comparison (--check) graph/compare.py.
"""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import tempfile
from pathlib import Path

from sensing_nodes.bags.input_bag import InputBagError, discard
from sensing_nodes.graph.cli import (
    GraphArgumentError,
    parse_node_params,
    parse_nodes,
    parse_remaps,
)
from sensing_nodes.graph.compare import check_against
from sensing_nodes.graph.processes import executable
from sensing_nodes.graph.replayer import (
    DEFAULT_EXTRA_OUTPUTS,
    DEFAULT_SETTLE_AFTER,
    DEFAULT_SETTLE_BEFORE,
    PassSettings,
    ReplayError,
    ReplayOptions,
    replay,
)
from sensing_nodes.topics import PROCESSING_NODES

# The project's bags: name -> (sensor_sim parameter file in config/, seed, simulated seconds).
BAG_SPECS = {
    'nominal': ('bags_nominal.yaml', 1, 22.0),
    'strong_errors': ('bags_strong_errors.yaml', 2, 22.0),
}

EXIT_BAD_INPUT = 2
EXIT_FAILED = 1


def parse_expectations(specs: list[str]) -> dict[str, tuple[str, ...]]:
    """['/scan=/a,/b', '/odom='] -> {'/scan': ('/a', '/b'), '/odom': ()}."""
    table = {}
    for spec in specs:
        topic, sep, outputs = spec.partition('=')
        if not sep or not topic.startswith('/'):
            raise ReplayError(f"--expect {spec!r}: write INPUT=OUTPUT[,OUTPUT...] (OUTPUT may be "
                              "empty), e.g. /scan=/scan_match/odom")
        table[topic] = tuple(o for o in outputs.split(',') if o)
    return table



def _find_executables_next_to_python() -> None:
    """`python -m sensing_nodes.tools.replay` from a venv: its bin/ holds the node executables
    (graph.processes.executable looks next to sys.argv[0], then on PATH)."""
    bin_dir = Path(sys.executable).parent
    if (bin_dir / 'wheel_odometry').is_file() and str(bin_dir) not in os.environ['PATH'].split(
        os.pathsep
    ):
        os.environ['PATH'] = str(bin_dir) + os.pathsep + os.environ.get('PATH', '')


# -- the project's bags ---------------------------------------------------------------------
def make_bags(folder: str | Path, names: list[str] | None = None, progress: bool = True) -> None:
    """Regenerate bags/<name>: inputs recorded with `sensor_sim --record`, outputs by a lockstep
    replay through the real node processes."""
    from sensing_nodes.paths import config_file

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    for name in names or list(BAG_SPECS):
        params_file, seed, duration = BAG_SPECS[name]
        with tempfile.TemporaryDirectory(prefix='sensing_bags-') as tmp:
            inputs = Path(tmp) / 'inputs'
            subprocess.run([executable('sensor_sim'), '--record', str(inputs), '--duration',
                            str(duration), '--seed', str(seed), '--params-file',
                            str(config_file(params_file)), '--quiet'], check=True)
            target = folder / name
            discard(target)
            results = replay(inputs, target,
                             ReplayOptions(launch=True, progress=progress, compress=True))
            missing = dict(results[0].missing)
            if missing:
                discard(target)
                raise ReplayError(f'{name}: outputs missing in the lockstep replay: {missing}')
        size = sum(p.stat().st_size for p in target.iterdir())
        print(f'sensing_replay: wrote {target} ({size / 1e6:.2f} MB)')


# -- command line ---------------------------------------------------------------------------
# long: argparse declarations, one per option, and their validation.
def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog='sensing_replay', description=__doc__.split('\n\n')[0])
    parser.add_argument(
        'bag', nargs='?', help='input bag: a rosbag2 folder (MCAP or sqlite3) or a ROS 1 .bag file'
    )
    parser.add_argument('out', nargs='?', help='output bag folder to create (inputs + outputs)')
    parser.add_argument('--mode', choices=('lockstep', 'timed'), default='lockstep')
    parser.add_argument('--rate', type=float, default=1.0,
                        help='timed mode: bag seconds per wall second (default 1)')
    parser.add_argument('--expect', action='append', default=[], metavar='IN=OUT[,OUT]',
                        help='expectation table entry (replaces the default table when given): '
                             'an input topic and the outputs carrying its stamp; OUT may be empty')
    parser.add_argument('--record', action='append', default=None, metavar='TOPIC',
                        help='further outputs recorded as they come (default: '
                             + ' '.join(DEFAULT_EXTRA_OUTPUTS) + ')')
    parser.add_argument('--remap', action='append', default=[], metavar='BAG_TOPIC:=TOPIC',
                        help='publish a bag topic under another name (the default expectation '
                             'table then applies to it, e.g. /imu:=/imu/data_raw)')
    parser.add_argument('--launch', action='store_true',
                        help="start the package's processing nodes (config/ parameter files)")
    parser.add_argument('--nodes', default=','.join(PROCESSING_NODES),
                        help='with --launch: which nodes (comma separated)')
    parser.add_argument('--one-process', action='store_true',
                        help='with --launch: the nodes in one process (sensing_graph)')
    parser.add_argument('--param', action='append', default=[], metavar='NODE:NAME:=VALUE',
                        help='with --launch: a parameter override for one node')
    parser.add_argument('--params-file', type=Path, default=None,
                        help='with --launch: a parameter file read after each node\'s own in '
                             'config/, e.g. a robot preset: config/robots/turtlebot3.yaml, or '
                             'its name, turtlebot3')
    parser.add_argument('--loops', type=int, default=1,
                        help='play the bag this many times back to back (time jumps backwards); '
                             'outputs go to OUT/pass-K')
    parser.add_argument('--timeout', type=float, default=10.0,
                        help='lockstep: wall seconds to wait for an input\'s outputs (default 10)')
    parser.add_argument('--quiet-s', type=float, default=1.5,
                        help='end of a pass: wall seconds without output before it is over '
                             '(longer than the fusion\'s flush_after_s)')
    parser.add_argument('--settle-ms', type=float, default=2.0,
                        help='lockstep: wall ms to spin after the outputs of a --settle-after '
                             'input arrived (default 2)')
    parser.add_argument('--settle-after', action='append', default=None, metavar='TOPIC',
                        help='inputs followed by the settle time (default: '
                             + ' '.join(DEFAULT_SETTLE_AFTER) + ')')
    parser.add_argument(
        '--settle-before',
        action='append',
        default=None,
        metavar='TOPIC=MS',
        help='lockstep: wall ms to spin before publishing that input (default: '
        + ' '.join(f'{t}={1e3 * v:g}' for t, v in DEFAULT_SETTLE_BEFORE.items())
        + '); TOPIC=0 turns one off',
    )
    parser.add_argument('--warmup-s', type=float, default=None,
                        help='first play this much of the bag (bag seconds) and discard the '
                             'outputs, so every link of the graph is matched before the pass '
                             'that counts, which starts with time jumping back (every node of '
                             "the package resets); default 2 with --launch, none into a graph "
                             "already running (0: no warm-up)")
    parser.add_argument(
        '--logs', type=Path, default=None, help='with --launch: keep node logs here'
    )
    parser.add_argument('--make-bags', metavar='DIR', default=None,
                        help="regenerate the project's bags (" + ', '.join(BAG_SPECS) + ') in DIR')
    parser.add_argument(
        '--check',
        action='store_true',
        help='compare the outputs with those recorded in BAG; exit 1 if any differ',
    )
    parser.add_argument('--compress', action='store_true',
                        help='zstd-compress the output bag\'s MCAP chunks')
    parser.add_argument('--no-progress', action='store_true')
    args = parser.parse_args(argv)
    if args.make_bags is None and (args.bag is None or args.out is None):
        parser.error('give BAG and OUT (or --make-bags DIR)')
    if not (args.rate > 0 and args.timeout > 0 and args.loops >= 1 and args.quiet_s > 0):
        parser.error('--rate, --timeout and --quiet-s must be > 0 and --loops >= 1')
    return args


def _settle_before(specs: list[str] | None) -> dict[str, float]:
    table = dict(DEFAULT_SETTLE_BEFORE)
    for spec in specs or []:
        topic, sep, ms = spec.partition('=')
        try:
            table[topic] = float(ms) * 1e-3
        except ValueError:
            raise ReplayError(f'--settle-before {spec!r}: write TOPIC=MS') from None
        if not sep or table[topic] < 0:
            raise ReplayError(f'--settle-before {spec!r}: write TOPIC=MS with MS >= 0')
    return table


def _interrupt(signum, frame):
    raise KeyboardInterrupt


def options_from_args(args: argparse.Namespace) -> ReplayOptions:
    """The command line's ReplayOptions (GraphArgumentError on a bad --param/--remap/--nodes)."""
    passes = PassSettings(
        mode=args.mode, rate=args.rate, timeout_s=args.timeout, quiet_s=args.quiet_s,
        settle_s=args.settle_ms * 1e-3,
        settle_before=tuple(_settle_before(args.settle_before).items()),
        settle_after=(tuple(args.settle_after) if args.settle_after is not None
                      else DEFAULT_SETTLE_AFTER))
    return ReplayOptions(
        passes=passes,
        expectations=parse_expectations(args.expect) if args.expect else None,
        extra_outputs=tuple(args.record) if args.record is not None else DEFAULT_EXTRA_OUTPUTS,
        remaps=parse_remaps(args.remap), launch=args.launch, nodes=parse_nodes(args.nodes),
        node_params=dict(parse_node_params(args.param)), params_file=args.params_file,
        one_process=args.one_process, loops=args.loops, warmup_s=args.warmup_s,
        progress=not args.no_progress, logs=args.logs, compress=args.compress)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    _find_executables_next_to_python()
    signal.signal(signal.SIGTERM, _interrupt)  # a killed replay still stops its nodes
    try:
        if args.make_bags is not None:
            make_bags(args.make_bags, progress=not args.no_progress)
            return 0
        results = replay(args.bag, args.out, options_from_args(args))
    except (InputBagError, GraphArgumentError) as exc:
        print(f'sensing_replay: error: {exc}', file=sys.stderr)
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        print('sensing_replay: interrupted; no output written', file=sys.stderr)
        return 130
    for k, r in enumerate(results):
        counts = ', '.join(f'{t} {len(v)}' for t, v in sorted(r.outputs.items()))
        missing = sum(r.missing.values())
        print(f'sensing_replay: pass {k + 1}: {r.inputs_published} inputs in {r.wall_s:.1f} s; '
              f'outputs: {counts}' + (f'; MISSING {dict(r.missing)}' if missing else ''))
        print('  waiting for outputs per input topic: ' + ', '.join(
            f'{t} {s:.1f} s' for t, s in sorted(r.wait_s.items())))
    print(f'sensing_replay: wrote {args.out}')
    failed = any(r.missing for r in results)
    if args.check:
        failed |= not check_against(Path(args.bag), results)
    return EXIT_FAILED if failed else 0



if __name__ == '__main__':
    sys.exit(main())
