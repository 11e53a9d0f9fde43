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
        executor: str | None = None, threads: int | None = None,
        over_dds: bool = False) -> int:
    """Build the nodes (in `names` order) in one context and spin them until shutdown; 2 when a
    node refuses its parameters (the nodes built before it are destroyed). Topics between them
    are in-process edges (ros/in_process.py) unless over_dds, or the multi-threaded executor,
    or the DDS profile in force matches the participant's own endpoints."""
    import rclpy
    from rclpy.executors import ExternalShutdownException

    from sensing_nodes.graph.cli import node_arguments
    from sensing_nodes.nodes.registry import make_node
    from sensing_nodes.ros import in_process
    from sensing_nodes.ros.run import (
        _PARAMETER_ERRORS,
        EXIT_BAD_PARAMETER,
        executor_kind,
        ignore_further_interrupts,
        make_executor,
        spin_until_shutdown,
    )

    faulthandler.enable()
    kind = executor_kind(executor)
    off = ('--over-dds' if over_dds else
           'the multi-threaded executor (its threads would run a node\'s callbacks at once)'
           if kind == 'multi' else None)
    profile_dir = in_process.profile_directory()
    if off is None:
        off = in_process.request_profile(Path(profile_dir.name))
    # Never this tool's argv: its options are not ROS arguments, and every node gets its own.
    # rclpy's signal handlers (SIGINT, SIGTERM) shut the context down: the loop below ends.
    rclpy.init(args=[sys.argv[0]])
    nodes = []
    edges = None
    try:
        ignores_own = in_process.participant_ignores_own_endpoints(rclpy.get_default_context())
        if off is None and ignores_own:
            edges = in_process.enable(rclpy.get_default_context())
        elif ignores_own:
            # The user's DDS profile sets fastdds.ignore_local_endpoints: over DDS, the nodes
            # of this process would never hear each other.
            print(f'sensing_graph: error: the DDS profile in force makes the participant ignore '
                  f'its own endpoints ({in_process.IGNORE_LOCAL_ENDPOINTS}), but the in-process '
                  f'edges are off ({off}): the nodes would not hear each other',
                  file=sys.stderr, flush=True)
            return EXIT_BAD_PARAMETER
        elif off is None:
            off = ('the DDS participant matches its own endpoints (RMW_IMPLEMENTATION '
                   f'{rclpy.get_rmw_implementation_identifier()})')
        for name in names:
            try:
                nodes.append(make_node(name, node_arguments(name, params_files,
                                                            extras.get(name, []))))
            except _PARAMETER_ERRORS as exc:
                print(f'[{name}] invalid parameter: {exc}', file=sys.stderr, flush=True)
                return EXIT_BAD_PARAMETER
        if edges is not None and edges.unserved():
            print(f'sensing_graph: error: {", ".join(edges.unserved())} published here outside '
                  'the in-process edges and subscribed here: use --over-dds', file=sys.stderr,
                  flush=True)
            return EXIT_BAD_PARAMETER
        spinner = make_executor(kind, threads)
        for node in nodes:
            spinner.add_node(node)
        print(f'sensing_graph: {", ".join(names)} in one process ({type(spinner).__name__}); '
              + ('in-process edges: a topic published and subscribed here is handed over '
                 'without DDS, and published on DDS only while a subscriber outside matches'
                 if edges is not None else f'in-process edges off ({off}): every topic on DDS'),
              file=sys.stderr, flush=True)
        spin_until_shutdown(spinner)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except Exception:
        if rclpy.ok():
            raise
        # A callback run while a signal was shutting the context down (publishing on a
        # publisher that just became invalid: RCLError) is the shutdown, as in run_node.
    finally:
        ignore_further_interrupts()
        for node in reversed(nodes):
            node.destroy_node()
        rclpy.try_shutdown()
        profile_dir.cleanup()
        if edges is not None:
            print_counts(edges)
    return 0


def print_counts(edges) -> None:
    """What each topic's in-process publishers did, one line per topic, on stderr."""
    for topic, counts in sorted(edges.counts.items()):
        print(f'sensing_graph: {topic}: {counts.handed_over} handed over in-process, '
              f'{counts.on_dds} published on DDS, {counts.not_on_dds} not (no subscriber '
              'outside)', file=sys.stderr, flush=True)


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
    parser.add_argument('--over-dds', action='store_true',
                        help='every topic over DDS, as between separate processes: no '
                             'in-process edges (default: a topic published and subscribed in '
                             'this process is handed over directly, and published on DDS only '
                             'while a subscriber outside the process matches)')
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
    return run(names, args.params_file, extras, args.executor, args.threads, args.over_dds)


if __name__ == '__main__':
    sys.exit(main())
