"""sensing_graph: the processing nodes as separate rclpy nodes in one process, as a ROS component
container holds them.

Each node keeps its name, parameters (its config/<node>.yaml, then --params-file files, then its
--param overrides: the arguments its executable gets from a launch, given to that node alone),
remappings (--remap NODE:FROM:=TO) and topics; one executor spins them all. The process holds
the Python interpreter, numpy, rclpy and the DDS participant once instead of five times. SIGINT
or SIGTERM stops it cleanly; a bad parameter is reported and exits with 2. With --lifecycle
every node is managed (its `lifecycle` parameter true): each starts unconfigured and is brought
up through its own lifecycle services, and a bad parameter fails that node's configure instead.
docs/performance.md, docs/architecture.md (managed nodes).
"""

from __future__ import annotations

import argparse
import faulthandler
import sys
from pathlib import Path


def run(names: tuple[str, ...], params_files: list[Path], extras: dict[str, list[str]],
        executor_kind: str | None = None, threads: int | None = None) -> int:
    """Build the nodes (in `names` order) in one context and spin them until shutdown; 2 when a
    node refuses its parameters (the nodes built before it are destroyed)."""
    import rclpy
    from rclpy.executors import ExternalShutdownException

    from sensing_nodes.graph.cli import node_arguments
    from sensing_nodes.nodes.registry import make_node
    from sensing_nodes.ros.run import (
        _PARAMETER_ERRORS,
        EXIT_BAD_PARAMETER,
        ignore_further_interrupts,
        make_executor,
        spin_until_shutdown,
    )

    faulthandler.enable()
    # Never this tool's argv: its options are not ROS arguments, and every node gets its own.
    # rclpy's signal handlers (SIGINT, SIGTERM) shut the context down: the loop below ends.
    rclpy.init(args=[sys.argv[0]])
    nodes = []
    try:
        for name in names:
            try:
                nodes.append(make_node(name, node_arguments(name, params_files,
                                                            extras.get(name, []))))
            except _PARAMETER_ERRORS as exc:
                print(f'[{name}] invalid parameter: {exc}', file=sys.stderr, flush=True)
                return EXIT_BAD_PARAMETER
        executor = make_executor(executor_kind, threads)
        for node in nodes:
            executor.add_node(node)
        print(f'sensing_graph: {", ".join(names)} in one process ({type(executor).__name__})',
              file=sys.stderr, flush=True)
        spin_until_shutdown(executor)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        ignore_further_interrupts()
        for node in reversed(nodes):
            node.destroy_node()
        rclpy.try_shutdown()
    return 0


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    from sensing_nodes.ros.run import EXECUTORS
    from sensing_nodes.topics import PROCESSING_NODES

    parser = argparse.ArgumentParser(prog='sensing_graph', description=__doc__.split('\n\n')[0])
    parser.add_argument('--nodes', default=','.join(PROCESSING_NODES),
                        help='which processing nodes (comma separated; default all five)')
    parser.add_argument('--params-file', action='append', default=[], type=Path, metavar='FILE',
                        help='a ROS parameter file applied after each node\'s config/<node>.yaml '
                             '(repeatable; node-name keys and /** apply as in separate processes)')
    parser.add_argument('--param', action='append', default=[], metavar='NODE:NAME:=VALUE',
                        help='a parameter override for one node (after the parameter files)')
    parser.add_argument('--remap', action='append', default=[], metavar='NODE:FROM:=TO',
                        help='a topic remapping for one node (as its executable\'s -r FROM:=TO)')
    parser.add_argument('--lifecycle', action='store_true',
                        help='managed (lifecycle) nodes: each starts unconfigured, brought up '
                             'through /<node>/change_state (a lifecycle manager, ros2 lifecycle '
                             'set); the same as --param NODE:lifecycle:=true for every node')
    parser.add_argument('--executor', choices=EXECUTORS, default=None,
                        help='what spins the nodes: events (rclpy\'s EventsExecutor), single '
                             '(SingleThreadedExecutor) or multi (MultiThreadedExecutor: each '
                             'node\'s callbacks stay serialised in its default mutually exclusive '
                             'group); default: SENSING_NODES_EXECUTOR, else events, as each node '
                             'executable')
    parser.add_argument('--threads', type=int, default=None,
                        help='with --executor multi: worker threads (default: rclpy\'s, the CPU '
                             'count)')
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    from sensing_nodes.graph.cli import (
        GraphArgumentError,
        params_file_path,
        parse_node_params,
        parse_nodes,
    )

    args = parse_args(argv)
    try:
        names = parse_nodes(args.nodes)
        params = parse_node_params(args.param)
        remaps = parse_node_params(args.remap, flag='-r', option='--remap')
        args.params_file = [params_file_path(f) for f in args.params_file]
        if args.threads is not None and args.threads < 1:
            raise GraphArgumentError('--threads must be >= 1')
    except GraphArgumentError as exc:
        print(f'sensing_graph: error: {exc}', file=sys.stderr)
        return 2
    managed = ['-p', 'lifecycle:=true'] if args.lifecycle else []
    extras = {n: managed + params.get(n, []) + remaps.get(n, []) for n in names}
    return run(names, args.params_file, extras, args.executor, args.threads)


if __name__ == '__main__':
    sys.exit(main())
