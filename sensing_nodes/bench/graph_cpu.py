"""CPU cost of the node processes: % of one core per 1x real time and CPU microseconds per
input message, for the processing graph at the default sensor rates and for gyro_integrator
with a 1 kHz IMU.

Each case starts sensor_sim (timer-paced at real_time_factor) and the nodes as separate
processes over DDS on a private domain, exactly as the demo does but without the recorder, lets
them warm up, and reads every process's CPU time (user + system, /proc/<pid>/stat) at the start
and end of a measuring window. % of a core per 1x = CPU seconds / wall seconds / real-time
factor. Messages per simulated second come from config/sensor_sim.yaml (what each node takes
in); per-message figures are CPU time over those messages (whatever else the process does,
timers and /diagnostics included). The load average is reported with the figures: on a shared
machine, compare figures from one run only. With one_process the nodes run in one sensing_graph
process instead (tools/graph.py); each process's resident memory (RSS, and its peak) is read from
/proc at the end of the window.
"""

from __future__ import annotations

import json
import os
import sys
import tempfile
import time
from pathlib import Path

from sensing_nodes.bench.probe import DdsProbe
from sensing_nodes.graph.processes import ONE_PROCESS, Graph, isolated_environment
from sensing_nodes.parameters import load_parameters
from sensing_nodes.paths import config_file
from sensing_nodes.topics import PROCESSING_NODES


def input_rates(sim_overrides: dict[str, float] | None = None) -> dict[str, float]:
    """Messages per simulated second each node takes in, from sensor_sim's parameter file."""
    params = {**load_parameters('sensor_sim', config_file('sensor_sim.yaml')),
              **(sim_overrides or {})}
    joints, imu, scan = (float(params[k]) for k in ('joint_rate_hz', 'imu_rate_hz',
                                                     'scan_rate_hz'))
    return {
        'wheel_odometry': joints,                     # /joint_states
        'gyro_integrator': imu + joints,              # /imu/data_raw, /wheel/odom
        'line_extractor': scan,                       # /scan
        'icp_matcher': scan,                          # /scan
        'complementary_fusion': joints + imu + scan,  # /wheel/odom, /imu/data_raw, the matches
        'sensor_sim': joints + imu + scan + float(params['truth_rate_hz'])
        + float(params['clock_rate_hz']),             # what it publishes
    }


def _cpu_seconds(pid: int) -> float | None:
    """User + system CPU time (s) of a live process; None once it is gone."""
    try:
        fields = Path(f'/proc/{pid}/stat').read_text().rsplit(')', 1)[1].split()
    except (FileNotFoundError, ProcessLookupError):
        return None
    return (int(fields[11]) + int(fields[12])) / os.sysconf('SC_CLK_TCK')


def _memory_mb(pid: int) -> dict[str, float] | None:
    """Resident memory (VmRSS), its peak (VmHWM) and the proportional set size (Pss: shared
    pages divided among the processes mapping them, so separate processes' figures add up
    fairly) of a live process, in MB (10^6 bytes)."""
    try:
        lines = (Path(f'/proc/{pid}/status').read_text().splitlines()
                 + Path(f'/proc/{pid}/smaps_rollup').read_text().splitlines())
    except (FileNotFoundError, ProcessLookupError):
        return None
    kb = {k: int(v.split()[0]) for k, _, v in (line.partition(':') for line in lines)
          if k in ('VmRSS', 'VmHWM', 'Pss')}
    return {'rss_mb': round(kb['VmRSS'] * 1.024e-3, 1),
            'peak_rss_mb': round(kb['VmHWM'] * 1.024e-3, 1),
            'pss_mb': round(kb['Pss'] * 1.024e-3, 1)}


def _load_average() -> float:
    return float(Path('/proc/loadavg').read_text().split()[0])


# long: one measurement's sequence (start, wait for the graph, sample /proc for the window,
# stop, collect), kept in order so the window's bounds are visible.
def measure(nodes: tuple[str, ...], sim_overrides: dict[str, float], window_s: float,
            rate: float = 1.0, start_timeout_s: float = 60.0, one_process: bool = False,
            executor: str | None = None, with_sim: bool = True,
            params_files: tuple[Path, ...] = ()) -> dict:
    """Run sensor_sim and `nodes` as processes (the nodes in one sensing_graph process with
    one_process, spun by `executor`); CPU per process over window_s wall seconds, and memory.
    Without with_sim the nodes run with no input at all: what their processes cost idle
    (executor, timers, /diagnostics, DDS), the floor under any per-message work. params_files
    apply to every node after its config/<node>.yaml (e.g. config/fusion_integrated.yaml).

    Returns {'processes': {name: {'core_percent_per_1x', 'cpu_us_per_message', 'rss_mb',
    'peak_rss_mb'}}, 'total...'}.
    """

    env = isolated_environment(None, kind='bench', localhost=True)
    scan_consumers = sum(n in nodes for n in ('line_extractor', 'icp_matcher')) if with_sim else 0
    sim_args = ['-p', f'real_time_factor:={rate}', '-p', 'duration_s:=3600.0',
                '-p', f'wait_for_scan_subscribers:={scan_consumers}']
    for name, value in sim_overrides.items():
        sim_args += ['-p', f'{name}:={value}']
    with tempfile.TemporaryDirectory() as tmp:
        graph = Graph(Path(tmp), env)
        procs = graph.processes
        try:
            if one_process:
                graph.start_one_process(nodes, {}, executor, params_files)
            else:
                for name in nodes:
                    graph.start(name, [], params_files)
            if with_sim:
                graph.start('sensor_sim', sim_args)
            # Started: the simulator says so (it waits for the scan consumers), or, with none to
            # wait for, every node has logged its start-up line.
            deadline = time.monotonic() + start_timeout_s
            while time.monotonic() < deadline:
                failed = [n for n, p in procs.items() if p.poll() is not None]
                if failed:
                    raise RuntimeError(f'{failed} exited: '
                                       + graph.log(failed[0]).read_text()[-400:])
                text = {n: graph.log(n).read_text() for n in procs}
                if (scan_consumers and 'starting' in text['sensor_sim']) or (
                        not scan_consumers and all(text.values())):
                    break
                time.sleep(0.2)
            else:
                raise RuntimeError('the graph did not start within '
                                   f'{start_timeout_s:.0f} s')
            time.sleep(3.0)   # discovery settled, caches warm
            load_before = _load_average()
            before = {n: _cpu_seconds(p.pid) for n, p in procs.items()}
            t0 = time.monotonic()
            time.sleep(window_s)
            after = {n: _cpu_seconds(p.pid) for n, p in procs.items()}
            wall = time.monotonic() - t0
            memory = {n: _memory_mb(p.pid) for n, p in procs.items()}
            load_after = _load_average()
        finally:
            graph.stop()
    rates = input_rates(sim_overrides)
    rates[ONE_PROCESS] = sum(rates[n] for n in nodes)
    out: dict = {'window_s': round(wall, 1), 'rate': rate,
                 'load_average_1min': [load_before, load_after], 'processes': {}}
    total, total_rss, total_pss = 0.0, 0.0, 0.0
    for name in procs:
        if before[name] is None or after[name] is None or memory[name] is None:
            out['processes'][name] = {'error': 'process ended inside the window'}
            continue
        cpu = after[name] - before[name]
        percent = 100.0 * cpu / wall / rate
        if name != 'sensor_sim':
            total += percent
            total_rss += memory[name]['rss_mb']
            total_pss += memory[name]['pss_mb']
        out['processes'][name] = {
            'core_percent_per_1x': round(percent, 2),
            'cpu_us_per_message': (round(1e6 * cpu / (wall * rate * rates[name]), 1)
                                   if with_sim else None),
            'messages_per_s_at_1x': rates[name], **memory[name]}
    out['processing_graph_core_percent_per_1x'] = round(total, 2)
    out['processing_graph_rss_mb'] = round(total_rss, 1)
    out['processing_graph_pss_mb'] = round(total_pss, 1)
    return out


def _relay_node(every: int):
    """A node that takes each Imu on /bench/relay_in (raw) and publishes the same bytes on
    /bench/relay_out: one message in, one out, no work, through run_node's executor. With
    every=N it answers the first message and every N-th only (a sink: what taking a message
    costs without answering it)."""
    from rclpy.node import Node
    from sensor_msgs.msg import Imu

    from sensing_nodes.ros.qos import ESTIMATE_QOS, SENSOR_QOS

    node = Node('bench_relay')
    publisher = node.create_publisher(Imu, '/bench/relay_out', ESTIMATE_QOS)
    taken = [0]

    def on_message(raw: bytes) -> None:
        if taken[0] % every == 0:
            publisher.publish(raw)
        taken[0] += 1

    node.create_subscription(Imu, '/bench/relay_in', on_message, SENSOR_QOS, raw=True)
    return node


def relay_floor(rate_hz: float, window_s: float, answer_every: int = 1) -> dict:
    """CPU per message of a relay process (_relay_node): what DDS, rclpy and the executor cost
    for one message in and one out, the floor under any node that answers every input; with
    answer_every=N, one answer per N messages taken."""
    from rclpy.serialization import serialize_message
    from sensor_msgs.msg import Imu

    from sensing_nodes.ros.qos import ESTIMATE_QOS, SENSOR_QOS

    relay = [sys.executable, '-m', 'sensing_nodes.bench.graph_cpu', '--relay',
             '--answer-every', str(answer_every)]
    with DdsProbe('bench_relay', relay, 1, 'bench_relay_driver') as probe:
        publisher = probe.node.create_publisher(Imu, '/bench/relay_in', SENSOR_QOS)
        received = [0]
        probe.node.create_subscription(Imu, '/bench/relay_out',
                                       lambda raw: received.__setitem__(0, received[0] + 1),
                                       ESTIMATE_QOS, raw=True)
        msg = Imu()
        msg.header.frame_id = 'imu_link'
        raw = serialize_message(msg)
        if not probe.publish_until_answered(lambda: publisher.publish(raw),
                                            lambda: received[0] > 0, 60.0):
            raise RuntimeError('the relay never answered: ' + probe.log_tail())
        before = None
        # Message k goes out k / rate_hz s after the first: k - 1 sent before it.
        for k, elapsed in probe.paced(rate_hz, spin_s=0.01):
            if before is None and elapsed >= 2.0:       # warmed up: start measuring
                before, t0, k0 = _cpu_seconds(probe.process.pid), elapsed, k
                load_before = _load_average()
            elif before is not None and elapsed - t0 >= window_s:
                after, wall, count = _cpu_seconds(probe.process.pid), elapsed - t0, k - k0
                break
            publisher.publish(raw)
    cpu = after - before
    return {'rate_hz': round(count / wall, 1), 'core_percent': round(100.0 * cpu / wall, 2),
            'cpu_us_per_message': round(1e6 * cpu / count, 1), 'load_average_1min': load_before}


# gyro_integrator at 1 kHz with its wheel veto and a consumer: publishing /imu/data to a
# subscriber costs what publishing to none does not (7.0 % of a core without the fusion, 11.1 %
# with it, 2026-11-25). The fusion takes the raw IMU by default: GYRO_1KHZ_FUSION has it fuse
# gyro_integrator's heading instead, so that /imu/data has its subscriber.
GYRO_1KHZ_NODES = ('wheel_odometry', 'gyro_integrator', 'complementary_fusion')
GYRO_1KHZ_FUSION = config_file('fusion_integrated.yaml')


def run(quick: bool = False) -> dict:
    """Figures for `make bench`: the graph at the default rates, gyro_integrator at 1 kHz."""
    window = 10.0 if quick else 30.0
    graph = measure(PROCESSING_NODES, {}, window)
    gyro = measure(GYRO_1KHZ_NODES, {'imu_rate_hz': 1000.0}, window,
                   params_files=(GYRO_1KHZ_FUSION,))
    figures: dict = {'load_average_1min_start': graph['load_average_1min'][0]}
    for name, values in graph['processes'].items():
        for key, value in values.items():
            if key != 'messages_per_s_at_1x':
                figures[f'{name}_{key}'] = value
    figures['processing_graph_core_percent_per_1x'] = graph['processing_graph_core_percent_per_1x']
    figures['processing_graph_rss_mb'] = graph['processing_graph_rss_mb']
    figures['processing_graph_pss_mb'] = graph['processing_graph_pss_mb']
    # The same nodes in one sensing_graph process: its memory and CPU against the sum above.
    one = measure(PROCESSING_NODES, {}, window, one_process=True)
    figures['one_process_graph_core_percent_per_1x'] = one['processing_graph_core_percent_per_1x']
    # The floor under both: the same processes with no input (no simulator; 10 s: a 10 ms
    # clock tick is 0.1 % of it).
    for key, one_process in (('processing_graph', False), ('one_process_graph', True)):
        idle = measure(PROCESSING_NODES, {}, min(window, 10.0), one_process=one_process,
                       with_sim=False)
        figures[f'{key}_idle_core_percent'] = idle['processing_graph_core_percent_per_1x']
    figures['one_process_graph_rss_mb'] = one['processing_graph_rss_mb']
    figures['one_process_graph_peak_rss_mb'] = one['processes'].get(ONE_PROCESS, {}).get(
        'peak_rss_mb')
    if (
        one['processing_graph_core_percent_per_1x']
        and graph['processing_graph_core_percent_per_1x']
    ):
        figures['one_process_over_separate_cpu_ratio'] = round(
            one['processing_graph_core_percent_per_1x']
            / graph['processing_graph_core_percent_per_1x'], 3)
    g = gyro['processes']['gyro_integrator']
    figures['gyro_integrator_1khz_imu_core_percent'] = g.get('core_percent_per_1x')
    figures['gyro_integrator_1khz_imu_cpu_us_per_message'] = g.get('cpu_us_per_message')
    floor = relay_floor(1000.0, window)
    figures['relay_floor_1khz_core_percent'] = floor['core_percent']
    figures['relay_floor_cpu_us_per_message'] = floor['cpu_us_per_message']
    # Taking a message without answering it (one answer per 100): a subscription's share.
    sink = relay_floor(1000.0, min(window, 10.0), answer_every=100)
    figures['sink_floor_cpu_us_per_message'] = sink['cpu_us_per_message']
    figures['load_average_1min_end'] = _load_average()
    return figures


if __name__ == '__main__':
    import argparse

    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--window', type=float, default=30.0, help='measuring window (wall s)')
    parser.add_argument('--rate', type=float, default=1.0, help='simulated s per wall s')
    parser.add_argument('--imu-rate', type=float, default=None,
                        help='IMU rate (Hz); given: measure wheel_odometry, gyro_integrator and '
                        'its consumer, complementary_fusion on /imu/data '
                        '(config/fusion_integrated.yaml)')
    parser.add_argument('--floor', type=float, default=None, metavar='HZ',
                        help='measure the relay floor (one Imu in, one out) at this rate')
    parser.add_argument('--answer-every', type=int, default=1, metavar='N',
                        help='with --floor: the relay answers one message in N')
    parser.add_argument('--one-process', action='store_true',
                        help='the processing nodes in one sensing_graph process')
    parser.add_argument('--executor', choices=('events', 'single', 'multi'), default=None,
                        help='with --one-process: sensing_graph\'s executor')
    parser.add_argument('--idle', action='store_true',
                        help='the processing nodes with no simulator: their cost without input')
    parser.add_argument('--nodes', default=','.join(PROCESSING_NODES),
                        help='the processing nodes measured (comma separated; default all five)')
    parser.add_argument('--params-file', action='append', default=[], type=Path,
                        help='a parameter file for every node after its config/ file '
                             '(repeatable), e.g. config/fusion_integrated.yaml')
    parser.add_argument('--relay', action='store_true', help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.answer_every < 1:
        parser.error(f'--answer-every {args.answer_every}: one answer per N >= 1 messages')
    if args.relay:
        from sensing_nodes.ros.run import run_node
        sys.exit(run_node(lambda: _relay_node(args.answer_every), []))
    if args.floor is not None:
        result = relay_floor(args.floor, args.window, args.answer_every)
    elif args.imu_rate is None:
        result = measure(
            tuple(args.nodes.split(',')),
            {},
            args.window,
            args.rate,
            one_process=args.one_process,
            executor=args.executor,
            with_sim=not args.idle,
            params_files=tuple(args.params_file),
        )
    else:
        result = measure(GYRO_1KHZ_NODES, {'imu_rate_hz': args.imu_rate}, args.window, args.rate,
                         params_files=(GYRO_1KHZ_FUSION,))
    print(json.dumps(result, indent=2))
