"""sensing_demo: the whole graph on the simulated robot, recorded and scored against ground truth.

Starts sensor_sim and the five processing nodes as separate processes over DDS (each from its
executable with its parameter file in config/), records every topic into an MCAP bag, stops
everything cleanly, and writes report.json, a table and PNG plots into the output folder.
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

from sensing_nodes.core.evaluation.metrics import path_length, sigma_consistency, trajectory_errors
from sensing_nodes.core.geometry import se2
from sensing_nodes.graph.cli import GraphArgumentError, new_run_folder, parse_node_params
from sensing_nodes.graph.processes import Graph, isolated_environment
from sensing_nodes.paths import config_file
from sensing_nodes.ros.qos import topic_qos
from sensing_nodes.topics import (
    DIAGNOSTICS,
    FUSED,
    GROUND_TRUTH,
    IMU,
    NODES,
    ON_DEMAND_TOPICS,
    PROCESSING_NODES,
    SCAN,
    SCAN_LINES,
    SCAN_MATCH,
    SCAN_MATCH_KEYFRAME,
    SENSOR_TOPICS,
    SIMULATOR_TOPICS,
    TOPIC_TYPES,
    WALL_PERIODIC_TOPICS,
    WHEEL_ODOM,
)

# Estimate name -> (topic, what it estimates)
ESTIMATES = {
    'wheel_odometry': (WHEEL_ODOM, 'pose'),
    'gyro': (IMU, 'heading'),
    'scan_matching': (SCAN_MATCH, 'pose'),
    'fused': (FUSED, 'pose'),
}
# Node -> (input topic it processes one output per message of, its output topics)
NODE_TOPICS = {'sensor_sim': (None, list(SIMULATOR_TOPICS)),
               **{name: (t.answers, [t.outputs[0]]) for name, t in NODES.items()}}


# Simulator topics the recorder subscribes to before the simulator starts.
SIM_TOPICS = {t: (TOPIC_TYPES[t], topic_qos(t)) for t in SIMULATOR_TOPICS}
# Topics between processing nodes, and how many subscribers each has in the graph (the
# recorder included) once every node has matched, with config/'s parameters.
# /imu/data and /scan_match/odom: the recorder (the fusion takes the raw IMU);
# /scan_match/keyframe_odom: the fusion (method ekf).
INTERNAL_EDGES = {WHEEL_ODOM: 4, IMU: 1, SCAN_MATCH: 1, SCAN_MATCH_KEYFRAME: 1}
# line_extractor's outputs, published only while subscribed: the recorder's subscription must
# be there before the first scan.
RECORDED_ON_DEMAND = {t: 1 for t in ON_DEMAND_TOPICS}
SCAN_SUBSCRIBERS = 3  # line_extractor, icp_matcher and the recorder
# Simulator topics and their subscribers among the processing nodes. The simulator (started with
# them) counts the recorder's subscription too, so they must be there before the recorder's.
SIM_CONSUMERS = {t: sum(t in n.inputs for n in NODES.values()) for t in SENSOR_TOPICS}
PACE_TOPIC = FUSED   # a scan goes out once the fused output reached the last one
DRAIN_QUIET_S = 1.0   # the end: this long without an output (fusion flushes after 0.5 s idle)


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog='sensing_demo', description=__doc__.split('\n\n')[0])
    parser.add_argument('--out', type=Path, default=None,
                        help='output folder (default: demo_out/run-<date-time>)')
    parser.add_argument(
        '--duration',
        type=float,
        default=130.0,
        help='simulated seconds to drive (default 130: one lap of the default route)',
    )
    parser.add_argument('--seed', type=int, default=0, help='simulation seed (default 0)')
    parser.add_argument('--rate', type=float, default=5.0,
                        help='the most simulated seconds per wall second (default 5); the '
                             'simulator also waits for the fused answer to each scan, so a '
                             'machine that cannot keep up slows the run instead of dropping data')
    parser.add_argument(
        '--domain-id',
        type=int,
        default=None,
        help='ROS_DOMAIN_ID for the graph (default: one of this run\'s own, so the '
        'demo never talks to a robot on your network)',
    )
    parser.add_argument('--param', action='append', default=[], metavar='NODE:NAME:=VALUE',
                        help='a parameter override for one node, sensor_sim or a processing '
                             'node (as sensing_replay)')
    parser.add_argument('--one-process', action='store_true',
                        help='the processing nodes in one process (sensing_graph) instead of '
                             'one process each')
    parser.add_argument('--quiet', action='store_true', help='no progress lines')
    args = parser.parse_args(argv)
    if args.duration <= 0 or args.rate <= 0:
        parser.error('--duration and --rate must be > 0')
    try:
        sim = 'sensor_sim:'
        args.node_params = parse_node_params([p for p in args.param if not p.startswith(sim)])
        args.node_params['sensor_sim'] = [a for p in args.param if p.startswith(sim)
                                          for a in ('-p', p[len(sim):])]
        if any(':=' not in a for a in args.node_params['sensor_sim'][1::2]):
            raise GraphArgumentError('--param sensor_sim:NAME:=VALUE')
    except GraphArgumentError as exc:
        parser.error(str(exc))
    return args


class Collected:
    """What the demo keeps for scoring: arrival wall times live, everything else from the bag."""

    def __init__(self) -> None:
        self.poses: dict[str, list] = defaultdict(list)       # topic -> [(stamp, x, y, yaw)]
        self.covariances: dict[str, list] = defaultdict(list)  # topic -> [3x3]
        self.scan_wall: dict[int, int] = {}    # scan stamp -> wall ns it arrived
        self.fused_wall: dict[int, int] = {}   # fused stamp -> wall ns of the last output with it

    def listeners(self):
        def scan(raw, stamp, wall):
            self.scan_wall.setdefault(stamp, wall)

        def fused(raw, stamp, wall):
            self.fused_wall[stamp] = wall  # the scan-match update comes after wheel updates

        return {SCAN: scan, FUSED: fused}

    def load(self, bag_path: Path) -> None:
        """Estimates, ground truth and final diagnostics from the recorded bag."""
        from sensing_nodes.bags.storage import read_messages
        from sensing_nodes.ros.conversions import odometry_pose, quaternion_to_yaw

        odometry = {GROUND_TRUTH, WHEEL_ODOM, SCAN_MATCH, FUSED}
        self.diagnostics: dict[str, dict[str, str]] = {}
        for topic, stamp, msg in read_messages(bag_path, odometry | {IMU, DIAGNOSTICS}):
            if topic in odometry:
                pose, cov = odometry_pose(msg)
                self.poses[topic].append((stamp, *pose))
                self.covariances[topic].append(cov)
            elif topic == IMU:
                self.poses[topic].append((stamp, 0.0, 0.0, quaternion_to_yaw(msg.orientation)))
                self.covariances[topic].append(np.diag([0.0, 0.0, msg.orientation_covariance[8]]))
            else:
                for status in msg.status:
                    self.diagnostics[status.name] = {kv.key: kv.value for kv in status.values}

    def arrays(self, topic: str):
        rows = sorted(self.poses.get(topic, []), key=lambda r: r[0])
        if not rows:
            return np.zeros(0, dtype=np.int64), np.zeros((0, 3))
        data = np.array([r[1:] for r in rows], dtype=float)
        return np.array([r[0] for r in rows], dtype=np.int64), data


def _start_graph(args: argparse.Namespace, graph: Graph) -> None:
    """The processing nodes (separate processes or one), then sensor_sim: it starts simulated
    time once the recorder has subscribed, paced by the fusion's answers (at most --rate)."""
    # Paced by the fusion's answer: the graph and the recorder take ~0.8 of a core per 1x of
    # simulated time (EKF fusion, /tf), so unpaced at 5x a 2-core machine fell seconds behind
    # and the fusion dropped late scan matches.
    sim_args = ['-p', f'seed:={args.seed}', '-p', f'duration_s:={args.duration}',
                '-p', f'real_time_factor:={args.rate}', '-p', 'wait_for_subscribers:=1',
                '-p', f'wait_for_scan_subscribers:={SCAN_SUBSCRIBERS}',
                '-p', f'pace_topic:={PACE_TOPIC}', '-p', 'pace_timeout_s:=5.0',
                *args.node_params['sensor_sim']]
    if args.one_process:
        graph.start_one_process(PROCESSING_NODES, args.node_params)
    else:
        for name in PROCESSING_NODES:
            graph.start(name, args.node_params.get(name, []))
    graph.start('sensor_sim', sim_args)


def _follow(args: argparse.Namespace, graph: Graph, recorder, executor, launched: float,
            out: Path) -> float:
    """Spin until sensor_sim ends: late publishers discovered, a progress line every 2 s; the
    wall seconds from the recorder's subscription to the end."""
    wall_start = time.monotonic()
    sim = graph.processes['sensor_sim']
    next_progress = next_discovery = wall_start
    start_stamp = None
    while sim.poll() is None:
        executor.spin_once(timeout_sec=0.01)
        now = time.monotonic()
        if now >= next_discovery:
            recorder.discover()
            next_discovery = now + 0.25
        if start_stamp is None and recorder.newest_stamp_ns:
            start_stamp = recorder.newest_stamp_ns
            if not args.quiet:
                print(f'  graph up: simulation started {now - launched:.1f} s after launch',
                      flush=True)
        if now < next_progress:
            continue
        next_progress = now + 2.0
        if not args.quiet and start_stamp is not None:
            sim_s = (recorder.newest_stamp_ns - start_stamp) * 1e-9
            print(f'  simulated {sim_s:6.1f} / {args.duration:g} s  '
                  f'({sim_s / max(now - wall_start, 1e-9):4.1f}x real time)  '
                  f'scans {recorder.counts.get("/scan", 0):5d}  '
                  f'fused {recorder.counts.get("/odometry/filtered", 0):6d}', flush=True)
        if graph.failed():
            raise SystemExit(f'sensing_demo: node(s) exited early: {graph.failed()}; '
                             f'see {out / "logs"}')
    return time.monotonic() - wall_start


def run_graph(args: argparse.Namespace, out: Path) -> tuple[Collected, dict, float, float]:
    """Run the graph to the end of the simulated duration; returns what was collected, the
    recorder's counts, the wall time taken and the simulated time covered."""
    import rclpy
    from rclpy.node import Node

    from sensing_nodes.bags.storage import BagWriter
    from sensing_nodes.graph.recorder import TopicRecorder
    from sensing_nodes.ros.run import make_executor, spin_until_quiet

    env = isolated_environment(args.domain_id)
    collected = Collected()
    graph = Graph(out / 'logs', env)
    rclpy.init()
    node = Node('sensing_demo_recorder')
    executor = make_executor()
    executor.add_node(node)
    try:
        with BagWriter(out / 'bag') as bag:
            recorder = TopicRecorder(node, bag, collected.listeners())
            # Every process starts at once (their imports take most of the start-up); the
            # recorder is the only subscriber of the ground truth and subscribes only once every
            # edge between the processing nodes is matched: simulated time starts then, so
            # neither the bag nor any node misses the first messages.
            launched = time.monotonic()
            _start_graph(args, graph)
            _wait_for_nodes(node, executor, PROCESSING_NODES, graph, recorder)
            for topic, (type_name, qos) in SIM_TOPICS.items():
                recorder.subscribe(topic, type_name, qos)
            wall_s = _follow(args, graph, recorder, executor, launched, out)
            # Let the last scans work through matching and fusion (and fusion's idle flush):
            # until no output has arrived for a second. /diagnostics comes every wall second
            # from every node whatever the data, so it does not count.
            spin_until_quiet(executor, lambda: sum(
                n for t, n in recorder.counts.items() if t not in WALL_PERIODIC_TOPICS),
                DRAIN_QUIET_S, timeout_s=30.0)
            counts = dict(recorder.counts)
    finally:
        codes = graph.stop()
        node.destroy_node()
        rclpy.try_shutdown()
    bad = {n: c for n, c in codes.items() if c not in (0, -signal.SIGINT)}
    if bad:
        print(f'sensing_demo: warning: exit codes {bad}; see {out / "logs"}', file=sys.stderr)
    return collected, counts, wall_s, args.duration


def _wait_for_nodes(node, executor, names, graph, recorder, timeout=30.0) -> None:
    """Until every processing node and every edge between them is discovered (so no early
    message is missed), then a moment for the nodes to match each other as we matched them."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        executor.spin_once(timeout_sec=0.1)
        recorder.discover(not_yet=set(SIM_TOPICS))   # subscribed once the nodes are matched
        if graph.failed():
            raise SystemExit(f'sensing_demo: node(s) failed at start-up: {graph.failed()}')
        if set(names) <= set(node.get_node_names()) and all(
                len(node.get_subscriptions_info_by_topic(topic)) >= count
                for topic, count in {**INTERNAL_EDGES, **RECORDED_ON_DEMAND,
                                     **SIM_CONSUMERS}.items()):
            settle = time.monotonic() + 0.5
            while time.monotonic() < settle:
                executor.spin_once(timeout_sec=0.05)
            return
    missing = set(names) - set(node.get_node_names())
    raise SystemExit(
        f'sensing_demo: nodes not discovered within {timeout:.0f} s: {sorted(missing)}'
    )


def score(collected: Collected, counts: dict, wall_s: float, duration_s: float) -> dict:
    """report.json's content from what was collected."""
    t_ref, truth = collected.arrays(GROUND_TRUTH)
    if len(t_ref) < 2:
        raise SystemExit('sensing_demo: no ground truth was recorded')
    report = {
        'distance_m': path_length(truth),
        'duration_s': (t_ref[-1] - t_ref[0]) * 1e-9,
        'real_time_factor': duration_s / wall_s if wall_s > 0 else None,
        'estimates': {},
    }
    errors_by_name = {}
    for name, (topic, kind) in ESTIMATES.items():
        t_est, est = collected.arrays(topic)
        if len(t_est) == 0:
            report['estimates'][name] = {'missing': True}
            continue
        errors = trajectory_errors(t_ref, truth, t_est, est)
        errors_by_name[name] = errors
        entry = errors.summary(with_position=(kind == 'pose'))
        entry['samples'] = int(len(errors.t))
        if kind == 'pose':
            cov = np.array(collected.covariances[topic])[np.argsort(
                [r[0] for r in collected.poses[topic]], kind='stable')][errors.kept]
            entry.update(sigma_consistency(errors.xy_in_estimate_frame[1:], cov[1:]))
        report['estimates'][name] = entry

    report['nodes'] = {}
    for name, (input_topic, outputs) in NODE_TOPICS.items():
        published = int(sum(counts.get(t, 0) for t in outputs))
        processed = published if input_topic is None else int(counts.get(outputs[0], 0))
        report['nodes'][name] = {'published': published, 'processed': processed}
    # What a node processed is what it counted itself ('scans' on /diagnostics); the
    # recorder's count of its outputs can be lower only because the recorder lost some.
    scans_processed = {
        name: max(counts.get(topic, 0), int(collected.diagnostics.get(name, {}).get('scans', 0)))
        for name, topic in (('icp_matcher', SCAN_MATCH), ('line_extractor', SCAN_LINES))}
    sim_diag = collected.diagnostics.get('sensor_sim', {})
    # The simulator's last diagnostics may predate its last scans and the recorder's best-effort
    # subscription may miss one; no consumer can process a scan that was not published.
    scans_published = max(int(sim_diag.get(SCAN, 0)), counts.get(SCAN, 0),
                          *scans_processed.values())
    report['scans'] = {
        'published_by_sim': scans_published,
        'received_by_recorder': counts.get(SCAN, 0),
        'processed_by_icp_matcher': scans_processed['icp_matcher'],
        'processed_by_line_extractor': scans_processed['line_extractor'],
    }
    latencies = [(collected.fused_wall[stamp] - wall) * 1e-6
                 for stamp, wall in collected.scan_wall.items() if stamp in collected.fused_wall]
    report['latency_ms'] = ({'p50': float(np.percentile(latencies, 50)),
                             'p99': float(np.percentile(latencies, 99)), 'samples': len(latencies)}
                            if latencies else {'p50': None, 'p99': None, 'samples': 0})
    report['_errors'] = errors_by_name
    return report


def print_table(report: dict) -> None:
    distance = report['distance_m']
    rtf = report['real_time_factor']
    print(f"\nDrove {distance:.1f} m in {report['duration_s']:.1f} s simulated "
          + (f"({rtf:.1f}x real time)\n" if rtf is not None else '\n'))
    print(f"{'estimate':<16}{'final pos':>11}{'% dist':>8}{'rms pos':>10}{'final yaw':>11}"
          f"{'rms yaw':>10}{'in 3σ':>8}")
    for name, e in report['estimates'].items():
        if e.get('missing'):
            print(f'{name:<16}   (no messages)')
            continue
        pos = e.get('final_position_error_m')
        cols = [
            f'{pos:9.3f} m' if pos is not None else f'{"-":>11}',
            # % of the distance driven: none after a still start
            f'{100 * pos / distance:7.2f}%' if pos is not None and distance > 0 else f'{"-":>8}',
            f"{e['rms_position_error_m']:8.3f} m" if pos is not None else f'{"-":>10}',
            f"{e['final_heading_error_deg']:9.2f}°",
            f"{e['rms_heading_error_deg']:8.2f}°",
            f"{100 * e['within_3_sigma']:7.1f}%" if 'within_3_sigma' in e else f'{"-":>8}',
        ]
        print(f'{name:<16}' + ''.join(cols))
    lat = report['latency_ms']
    if lat['p50'] is not None:
        print(f"\nlatency scan -> fused output: p50 {lat['p50']:.1f} ms, p99 {lat['p99']:.1f} ms")
    s = report['scans']
    print(f"scans: published {s['published_by_sim']}, matched {s['processed_by_icp_matcher']}, "
          f"lines {s['processed_by_line_extractor']}")


def plot(report: dict, collected: Collected, out: Path) -> list[Path]:
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    from sensing_nodes.core.evaluation.metrics import express_in_reference_frame, interpolate_poses
    from sensing_nodes.core.sim.world import load_world

    world = load_world(config_file('default_world.yaml'))
    t_ref, truth = collected.arrays(GROUND_TRUTH)
    fig, ax = plt.subplots(figsize=(9, 7.5))
    for x0, y0, x1, y1 in world.segments:
        ax.plot([x0, x1], [y0, y1], color='0.3', lw=2)
    ax.plot(truth[:, 0], truth[:, 1], 'k-', lw=2.5, label='ground truth')
    colours = {'wheel_odometry': 'tab:red', 'scan_matching': 'tab:blue', 'fused': 'tab:green'}
    for name, colour in colours.items():
        t_est, est = collected.arrays(ESTIMATES[name][0])
        if len(t_est) == 0:
            continue
        start = interpolate_poses(t_ref, truth, t_est[:1])[0]
        origin = se2.compose(tuple(start), se2.inverse(tuple(est[0])))
        aligned = express_in_reference_frame(origin, est)
        ax.plot(aligned[:, 0], aligned[:, 1], '-', color=colour, lw=1.3, label=name)
    ax.set_aspect('equal')
    ax.set_xlabel('x (m, map)')
    ax.set_ylabel('y (m, map)')
    ax.set_title('sensing_demo: trajectories over the world map')
    ax.legend(loc='upper right', fontsize=8)
    paths = [out / 'trajectories.png']
    fig.savefig(paths[0], dpi=110, bbox_inches='tight')
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(9, 4))
    t0 = t_ref[0]
    for name, errors in report['_errors'].items():
        ax.plot((errors.t - t0) * 1e-9, np.degrees(errors.heading_rad), lw=1.2, label=name,
                color=colours.get(name, 'tab:orange'))
    ax.axhline(0.0, color='0.5', lw=0.8)
    ax.set_xlabel('simulated time (s)')
    ax.set_ylabel('heading error (deg)')
    ax.legend(fontsize=8)
    ax.set_title('heading error against ground truth')
    paths.append(out / 'heading_error.png')
    fig.savefig(paths[1], dpi=110, bbox_inches='tight')
    plt.close(fig)
    return paths


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    out = new_run_folder(args.out, 'demo_out', 'bag', 'sensing_demo')
    if out is None:
        return 2
    print(
        f'sensing_demo: {args.duration:g} s of the default route at {args.rate:g}x, '
        f'seed {args.seed}'
    )
    collected, counts, wall_s, duration = run_graph(args, out)
    collected.load(out / 'bag')
    report = score(collected, counts, wall_s, duration)
    plots = plot(report, collected, out)
    errors = report.pop('_errors')
    del errors
    (out / 'report.json').write_text(json.dumps(report, indent=2) + '\n')
    print_table(report)
    print(f'\nwrote {out}/: report.json, bag/ (MCAP), logs/, ' + ', '.join(p.name for p in plots))
    return 0


if __name__ == '__main__':
    sys.exit(main())
