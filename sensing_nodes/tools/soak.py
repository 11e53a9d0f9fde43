"""sensing_soak: the whole graph for a long simulated run; memory growth and dropped scans as JSON.

Starts sensor_sim and the five processing nodes (as sensing_demo does: each executable with its
config file) and drives the default route for --duration simulated seconds. By default the
simulator is paced by the graph (sensor_sim pace_topic=/odometry/filtered: a scan goes out only
once the fused output for the previous one is back), i.e. the highest rate the graph keeps up
with; --rate X runs at a fixed X times real time instead. Each node's resident memory (VmRSS of
/proc/<pid>/status) is sampled every simulated minute; the run passes when every node's RSS at
the end is within --rss-tolerance (10 %) of its value after the first simulated minute and every
scan the simulator published was processed by icp_matcher and line_extractor.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from datetime import datetime
from pathlib import Path

from sensing_nodes.graph.cli import new_run_folder
from sensing_nodes.graph.processes import Graph, isolated_environment
from sensing_nodes.topics import (
    DIAGNOSTICS,
    FUSED,
    NODES,
    PROCESSING_NODES,
    SCAN,
    SCAN_LINES_TABLE,
    SCAN_MATCH,
    TOPIC_TYPES,
)

NS = 1_000_000_000
COUNTED = {t: TOPIC_TYPES[t] for t in (SCAN, SCAN_MATCH, SCAN_LINES_TABLE, FUSED)}


def rss_kb(pid: int) -> int | None:
    """Resident set size (kB) of a process from /proc/<pid>/status, None if it is gone."""
    try:
        for line in Path(f'/proc/{pid}/status').read_text().splitlines():
            if line.startswith('VmRSS:'):
                return int(line.split()[1])
    except (FileNotFoundError, ProcessLookupError):
        return None
    return None


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog='sensing_soak', description=__doc__.split('\n\n')[0])
    parser.add_argument('--duration', type=float, default=1800.0,
                        help='simulated seconds (default 1800 = 30 min)')
    parser.add_argument('--rate', default='paced',
                        help="'paced' (default: as fast as the graph keeps up) or a fixed "
                             'real-time factor')
    parser.add_argument('--out', type=Path, default=None,
                        help='output folder for soak.json and logs/ (default soak_out/run-<time>)')
    parser.add_argument('--seed', type=int, default=0)
    parser.add_argument('--rss-tolerance', type=float, default=0.10,
                        help='allowed relative RSS change from minute 1 to the end (default 0.10)')
    parser.add_argument('--domain-id', type=int, default=None,
                        help="ROS_DOMAIN_ID (default: one of this run's own)")
    parser.add_argument('--quiet', action='store_true')
    args = parser.parse_args(argv)
    if args.rate != 'paced':
        try:
            args.rate = float(args.rate)
        except ValueError:
            parser.error("--rate must be 'paced' or a number")
        if args.rate <= 0:
            parser.error('--rate must be > 0')
    if args.duration <= 60.0:
        parser.error('--duration must be longer than the first simulated minute (60 s)')
    return args


class _Watch:
    """This process's view of the graph: answers counted per topic with the scan stamps they
    carry (simulated time), each node's latest diagnostics, and RSS samples per node."""

    def __init__(self, node, graph: Graph) -> None:
        from diagnostic_msgs.msg import DiagnosticArray

        from sensing_nodes.bags.storage import message_class
        from sensing_nodes.ros.qos import topic_qos

        self.graph = graph
        self.counts = {topic: 0 for topic in COUNTED}
        self.stamps_by_topic: dict[str, set[int]] = {t: set() for t in COUNTED if t != FUSED}
        self.first: int | None = None
        self.newest = 0
        self.diagnostics: dict[str, dict[str, str]] = {}
        self.samples: list[dict] = []        # {'sim_s', 'wall_s', 'rss_kb': {node: kB}}
        for topic, type_name in COUNTED.items():
            node.create_subscription(message_class(type_name), topic, self._counter(topic),
                                     topic_qos(topic), raw=True)
        node.create_subscription(DiagnosticArray, DIAGNOSTICS, self._on_diagnostics, 50)

    def _counter(self, topic: str):
        from sensing_nodes.bags.stamps import leading_stamp_ns

        def on_message(raw):
            self.counts[topic] += 1
            if topic in self.stamps_by_topic:
                # Every answer carries its scan's stamp, so simulated time is known even while
                # this process's own /scan reader is still being matched at the start.
                stamp = leading_stamp_ns(raw)
                self.stamps_by_topic[topic].add(stamp)
                self.first = stamp if self.first is None else min(self.first, stamp)
                self.newest = max(self.newest, stamp)
        return on_message

    def _on_diagnostics(self, msg) -> None:
        for status in msg.status:
            self.diagnostics[status.name] = {'message': status.message,
                                             **{kv.key: kv.value for kv in status.values}}

    def sim_s(self) -> float:
        """Simulated seconds answered so far."""
        return (self.newest - self.first) / NS if self.first else 0.0

    def sample(self, sim_s: float, wall_s: float) -> None:
        rss = {n: rss_kb(p.pid) for n, p in self.graph.processes.items()}
        self.samples.append({'sim_s': round(sim_s, 1), 'wall_s': round(wall_s, 1), 'rss_kb': rss})

    def answered_span_s(self) -> float:
        """Simulated seconds between the first and last stamp any answer carried."""
        known = set().union(*self.stamps_by_topic.values())
        self.first = min(known) if known else None
        return (max(known) - min(known)) / NS if known else 0.0


def _start_processing_nodes(graph: Graph, node, executor, out: Path) -> None:
    """The five processing nodes, until each is on the graph (90 s at most)."""
    for name in PROCESSING_NODES:
        graph.start(name, [])
    deadline = time.monotonic() + 90.0
    while not set(PROCESSING_NODES) <= set(node.get_node_names()):
        executor.spin_once(timeout_sec=0.1)
        if graph.failed() or time.monotonic() > deadline:
            raise SystemExit(f'sensing_soak: the graph did not come up (failed: '
                             f'{graph.failed()}); see {out / "logs"}')


def _sim_arguments(args: argparse.Namespace) -> list[str]:
    """sensor_sim's parameters: the run, paced by the fused output or at a fixed rate."""
    # Simulated time starts once every /scan reader (this process's counter included) is
    # matched: a scan published earlier is lost to a late reader (line_extractor missed the
    # first 2 s of a run that way).
    scan_readers = sum(SCAN in n.inputs for n in NODES.values()) + int(SCAN in COUNTED)
    sim_args = ['-p', f'seed:={args.seed}', '-p', f'duration_s:={args.duration}',
                '-p', f'wait_for_scan_subscribers:={scan_readers}']
    if args.rate == 'paced':
        return sim_args + ['-p', 'pace_topic:=/odometry/filtered', '-p', 'pace_timeout_s:=5.0',
                           '-p', 'real_time_factor:=1000.0']    # no cap: as fast as the graph
    return sim_args + ['-p', f'real_time_factor:={args.rate}']


def _follow_the_run(args: argparse.Namespace, watch: _Watch, executor, out: Path) -> float:
    """Spin until sensor_sim ends, an RSS sample each simulated minute and a progress line each
    10 s of wall time; the run's wall seconds."""
    graph = watch.graph
    wall_start = time.monotonic()
    graph.start('sensor_sim', _sim_arguments(args))
    sim = graph.processes['sensor_sim']
    next_minute, next_progress = 60.0, wall_start + 10.0
    while sim.poll() is None:
        executor.spin_once(timeout_sec=0.05)
        now = time.monotonic()
        sim_s = watch.sim_s()
        if sim_s >= next_minute:
            watch.sample(sim_s, now - wall_start)
            next_minute += 60.0
        if now >= next_progress:
            next_progress = now + 10.0
            if graph.failed():
                raise SystemExit(f'sensing_soak: node(s) exited early: {graph.failed()}; '
                                 f'see {out / "logs"}')
            if not args.quiet:
                print(f'  simulated {sim_s:7.1f} / {args.duration:.0f} s  '
                      f'({sim_s / (now - wall_start):4.1f}x real time)  '
                      f'scans {watch.counts["/scan"]:6d}  '
                      f'matched {watch.counts["/scan_match/odom"]:6d}', flush=True)
    return time.monotonic() - wall_start


def run(args: argparse.Namespace, out: Path) -> dict:
    """Run the graph for the simulated duration; return the soak report."""
    env = isolated_environment(args.domain_id, offset=37)

    import rclpy
    from rclpy.node import Node

    from sensing_nodes.ros.run import make_executor, spin_until_quiet

    graph = Graph(out / 'logs', env)
    rclpy.init()
    node = Node('sensing_soak')
    executor = make_executor()
    executor.add_node(node)
    watch = _Watch(node, graph)
    try:
        _start_processing_nodes(graph, node, executor, out)
        wall_s = _follow_the_run(args, watch, executor, out)
        # Let the last scans work through matching and fusion: until nothing arrives for 2 s.
        spin_until_quiet(executor, lambda: sum(watch.counts.values()), 2.0, timeout_s=60.0,
                         step_s=0.05)
        sim_s = watch.answered_span_s()
        watch.sample(sim_s, wall_s)
        failed = graph.failed()
    finally:
        codes = graph.stop()
        node.destroy_node()
        rclpy.try_shutdown()
    return report(args, watch.samples, watch.counts, watch.stamps_by_topic, watch.first,
                  watch.diagnostics, wall_s, sim_s, failed, codes)


def report(args, samples, counts, stamps_by_topic, first_stamp, diagnostics, wall_s, sim_s, failed,
           codes) -> dict:
    """soak.json's content: RSS after the first simulated minute and at the end, and scans."""
    first, last = samples[0], samples[-1]
    nodes = {}
    for name in PROCESSING_NODES:
        start_kb, end_kb = first['rss_kb'].get(name), last['rss_kb'].get(name)
        growth = (end_kb - start_kb) / start_kb if start_kb and end_kb else None
        nodes[name] = {
            'rss_kb_after_first_minute': start_kb, 'rss_kb_at_end': end_kb,
            'rss_change': None if growth is None else round(growth, 4),
            'within_tolerance': growth is not None and abs(growth) <= args.rss_tolerance,
            'exit_code': codes.get(name),
        }
    sim_diag = diagnostics.get('sensor_sim', {})
    known = set().union(*stamps_by_topic.values())
    published = max(int(sim_diag.get(SCAN, 0)), len(known))
    scans = {
        'published_by_sim': published,
        'received_by_soak': counts[SCAN],
        'processed_by_icp_matcher': counts[SCAN_MATCH],
        'processed_by_line_extractor': counts[SCAN_LINES_TABLE],
        'fused_outputs': counts[FUSED],
        'pace_timeouts': int(sim_diag.get('pace_timeouts', 0)),
    }
    # Which scans (by stamp, seconds after the first) got no answer. A reader that had not yet
    # matched the simulator's writer when the first scan went out misses it: that is start-up,
    # not a drop, so only misses after the first simulated second count as dropped.
    for consumer, topic in (('icp_matcher', SCAN_MATCH),
                            ('line_extractor', SCAN_LINES_TABLE)):
        missed = sorted(known - stamps_by_topic[topic])
        missed_s = [round((t - first_stamp) / NS, 1) for t in missed] if first_stamp else []
        scans[f'unanswered_by_{consumer}_s'] = missed_s[:20]
        scans[f'dropped_by_{consumer}'] = (sum(1 for t in missed_s if t >= 1.0)
                                           + published - len(known))
    fusion = diagnostics.get('complementary_fusion', {})
    result = {
        'when': datetime.now().isoformat(timespec='seconds'),
        'mode': ('paced by /odometry/filtered' if args.rate == 'paced'
                 else f'{args.rate}x real time'),
        'simulated_s': round(sim_s, 1),
        'wall_s': round(wall_s, 1),
        'real_time_factor': round(sim_s / wall_s, 2) if wall_s > 0 else None,
        'rss_tolerance': args.rss_tolerance,
        'nodes': nodes,
        'scans': scans,
        'fusion': {k: fusion.get(k) for k in ('message', 'late_dropped_total', 'resets')},
        'rss_kb_by_minute': samples,
        'failed_nodes': failed,
    }
    result['ok'] = (not failed and all(n['within_tolerance'] for n in nodes.values())
                    and scans['dropped_by_icp_matcher'] == 0
                    and scans['dropped_by_line_extractor'] == 0
                    and sim_s >= args.duration - 1.0)
    return result


def print_table(result: dict) -> None:
    print(f"\nsensing_soak: {result['simulated_s']:.0f} s simulated in "
          f"{result['wall_s']:.0f} s wall "
          f"({result['real_time_factor']}x real time, {result['mode']})")
    print(f"{'node':<22}{'RSS min 1 (kB)':>16}{'RSS end (kB)':>14}{'change':>9}")
    for name, n in result['nodes'].items():
        change = f"{100 * n['rss_change']:+.1f}%" if n['rss_change'] is not None else '-'
        print(f"{name:<22}{n['rss_kb_after_first_minute'] or '-':>16}"
              f"{n['rss_kb_at_end'] or '-':>14}"
              f"{change:>9}")
    s = result['scans']
    print(f"scans: published {s['published_by_sim']}, matched {s['processed_by_icp_matcher']}, "
          f"lines {s['processed_by_line_extractor']}, pace timeouts {s['pace_timeouts']}")
    print('PASS' if result['ok'] else 'FAIL')


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    out = new_run_folder(args.out, 'soak_out', 'soak.json', 'sensing_soak')
    if out is None:
        return 2
    print(f'sensing_soak: {args.duration:g} s simulated, '
          f"{'paced by the graph' if args.rate == 'paced' else f'{args.rate:g}x real time'}, "
          f'output in {out}', flush=True)
    result = run(args, out)
    (out / 'soak.json').write_text(json.dumps(result, indent=2) + '\n')
    print_table(result)
    print(f'wrote {out / "soak.json"}')
    return 0 if result['ok'] else 1


if __name__ == '__main__':
    sys.exit(main())
