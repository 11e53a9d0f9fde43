"""The local-map matcher on a fast LiDAR: a synthetic Hokuyo UTM-30LX class stream (1081 beams
over 270 deg, 40 Hz, 30 m) on the simulated default route with the wheel odometry's guess, as
icp_matcher runs it; and the shared real Hokuyo demo bag (681 beams, 10 Hz, hand-carried, no
odometry: the matcher's constant-velocity prediction).

Per scan: CPU ms of the matcher's process() (deskewing, matching, the local map's update) plus
the scan's conversion to points, from this process's CPU time (time.process_time), best of
`repeats` passes; the % of one core at 1x is ms per scan x scans per second / 10. And the
synthetic stream through the real nodes (sensor_sim -> wheel_odometry, icp_matcher over DDS, as
graph_cpu measures the graph): icp_matcher's % of a core at 1x with its LaserScan decoding, the
odometry's guess, DDS and publishing.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import time
from pathlib import Path

from sensing_nodes.core.scan_matching import ScanMatcherSettings, make_scan_matcher
from sensing_nodes.core.sim.simulator import SimParams

# A Hokuyo UTM-30LX class scanner on the simulated robot.
FAST_LIDAR = {'scan_rate_hz': 40.0, 'scan_beams': 1081, 'scan_fov_rad': math.radians(270.0),
              'range_max_m': 30.0}
# The shared real Hokuyo bag (../shared/datasets/ros/README.md): laser_scan_matcher's demo.
HOKUYO_DEMO = 'scan_tools-laser_scan_matcher-demo.bag'


def ros_datasets() -> Path:
    """The shared ROS bags, located as <repo>/../shared/datasets/ros."""
    return (Path(__file__).resolve().parents[2] / '..' / 'shared' / 'datasets' / 'ros').resolve()


def _ms_per_scan(settings: ScanMatcherSettings, inputs: list[tuple], repeats: int) -> float:
    """CPU ms per scan of a fresh local-map matcher over `inputs` (process() arguments), best of
    `repeats` passes."""
    best = math.inf
    for _ in range(repeats):
        matcher = make_scan_matcher(settings)
        start = time.process_time()
        for args in inputs:
            matcher.process(*args)
        best = min(best, time.process_time() - start)
    return 1e3 * best / len(inputs)


def synthetic(seconds: float, repeats: int) -> dict:
    """The 1081-beam, 40 Hz stream over `seconds` of the default route (seed 0)."""
    from sensing_nodes.bench.icp_sim import simulated_run
    from sensing_nodes.core.sim.inputs import matcher_settings, scan_inputs
    from sensing_nodes.core.sim.simulator import make_route

    params = dataclasses.replace(SimParams(), **FAST_LIDAR)
    run = simulated_run(seed=0, laps=seconds / make_route(params).period_s, params=params)
    start = time.process_time()
    inputs = scan_inputs(run)       # the points and the odometry's guess, as the node has them
    convert_ms = 1e3 * (time.process_time() - start) / len(inputs)
    ms = _ms_per_scan(matcher_settings(run.params), inputs, repeats)
    rate = FAST_LIDAR['scan_rate_hz']
    return {'fast_lidar_beams': FAST_LIDAR['scan_beams'], 'fast_lidar_rate_hz': rate,
            'fast_lidar_scans': len(inputs),
            'fast_lidar_points_mean': sum(len(i[1]) for i in inputs) / len(inputs),
            'fast_lidar_match_ms_per_scan': ms,
            'fast_lidar_inputs_ms_per_scan': convert_ms,
            'fast_lidar_core_percent_at_1x': ms * rate / 10.0}


def hokuyo_demo(repeats: int) -> dict:
    """The shared real Hokuyo bag's 360 scans (laser at base_link); {} without the bag."""
    from sensing_nodes.bags.storage import BagReader
    from sensing_nodes.core.geometry.scan import scan_to_points
    from sensing_nodes.ros.conversions import scan_arrays, stamp_to_ns

    bag = ros_datasets() / HOKUYO_DEMO
    if not bag.is_file():
        return {'hokuyo_demo': f'skipped: {bag} absent'}
    scans = [msg for _, _, msg in BagReader(bag).messages(['/scan'])]
    start = time.process_time()
    inputs = []
    for msg in scans:
        ranges, angles = scan_arrays(msg)
        points, beams = scan_to_points(ranges, angles, msg.range_min, msg.range_max)
        times = beams * float(msg.time_increment) if msg.time_increment > 0.0 else None
        inputs.append((stamp_to_ns(msg.header.stamp), points, None, times, None))
    convert_ms = 1e3 * (time.process_time() - start) / len(inputs)
    stamps = [i[0] for i in inputs]
    rate = (len(stamps) - 1) / ((stamps[-1] - stamps[0]) * 1e-9)
    ms = _ms_per_scan(ScanMatcherSettings(laser_pose=(0.0, 0.0, 0.0)), inputs, repeats)
    return {'hokuyo_demo_beams': len(scans[0].ranges), 'hokuyo_demo_scans': len(inputs),
            'hokuyo_demo_rate_hz': rate,
            'hokuyo_demo_points_mean': sum(len(i[1]) for i in inputs) / len(inputs),
            'hokuyo_demo_match_ms_per_scan': ms,
            'hokuyo_demo_inputs_ms_per_scan': convert_ms,
            'hokuyo_demo_core_percent_at_1x': ms * rate / 10.0}


def node(window_s: float) -> dict:
    """icp_matcher (and the wheel_odometry it takes its guess from) as processes on
    sensor_sim's 1081-beam, 40 Hz stream: CPU over window_s wall seconds."""
    from sensing_nodes.bench.graph_cpu import measure

    processes = measure(('wheel_odometry', 'icp_matcher'), FAST_LIDAR, window_s)['processes']
    matcher = processes['icp_matcher']
    return {'fast_lidar_node_core_percent_at_1x': matcher['core_percent_per_1x'],
            'fast_lidar_node_ms_per_scan': matcher['cpu_us_per_message'] / 1e3,
            'fast_lidar_node_rss_mb': matcher['rss_mb']}


def run(quick: bool = False) -> dict:
    """Figures for `make bench`."""
    repeats = 1 if quick else 3
    out: dict = {'load_average_1min_start': os.getloadavg()[0]}
    out.update(synthetic(20.0 if quick else 60.0, repeats))
    out.update(hokuyo_demo(repeats))
    out.update(node(10.0 if quick else 30.0))
    out['load_average_1min_end'] = os.getloadavg()[0]
    return out


if __name__ == '__main__':
    import sys

    print(json.dumps(run(quick='--quick' in sys.argv), indent=1))
