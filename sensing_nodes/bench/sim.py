"""Speed of the simulated robot: simulated seconds recorded per wall second with the default
sensors (engine alone, and engine + messages + MCAP bag), and ray-cast scans per second.

All figures come from one run on one core; ratios are between figures measured in that run.
Realtime factors are given per wall second (what the issue asks) and per CPU second of this
process (less disturbed when other work shares the machine), with the load average.
"""

from __future__ import annotations

import json
import os
import tempfile
import time
from pathlib import Path

import numpy as np

from sensing_nodes.core.sim import simulator as sim
from sensing_nodes.core.sim.world import load_world, raycast
from sensing_nodes.paths import config_file


def _best_of(repeats: int, fn) -> tuple[float, float]:
    """Shortest wall time and shortest CPU time (s) of `repeats` calls of fn: the least
    disturbed by other load on a shared machine (CPU time counts only this process)."""
    wall, cpu = [], []
    for _ in range(repeats):
        started, started_cpu = time.perf_counter(), time.process_time()
        fn()
        wall.append(time.perf_counter() - started)
        cpu.append(time.process_time() - started_cpu)
    return min(wall), min(cpu)


def run(quick: bool = False) -> dict:
    """Measure and return a flat dict of figures."""
    from sensing_nodes.ros.sim_robot import NodeSettings, record

    params = sim.SimParams()
    world = load_world(config_file('default_world.yaml'))
    duration = 20.0 if quick else sim.make_route(params).period_s
    repeats = 1 if quick else 3

    engine_s, engine_cpu_s = _best_of(
        repeats, lambda: sim.simulate(params, world, duration, seed=0)
    )

    counts: dict[str, int] = {}

    def record_once() -> None:
        with tempfile.TemporaryDirectory() as tmp:
            counts.update(record(Path(tmp) / 'bag', duration, params, NodeSettings(), world))

    record_s, record_cpu_s = _best_of(repeats, record_once)

    rng = np.random.default_rng(0)
    origins = np.column_stack((rng.uniform(-4.5, 4.5, 200), rng.uniform(-3.5, 3.5, 200)))
    angles = (params.scan_angle_min_rad
              + params.scan_angle_increment_rad * np.arange(params.scan_beams))
    scans = 200 if quick else 2000

    def cast() -> None:
        for i in range(scans):
            raycast(world.segments, origins[i % len(origins)], angles)

    raycast_s, _ = _best_of(repeats, cast)
    messages = sum(counts.values())
    return {
        'sim_duration_s': round(duration, 3),
        'sim_messages': messages,
        'sim_record_realtime_factor': round(duration / record_s, 1),
        'sim_record_realtime_factor_cpu': round(duration / record_cpu_s, 1),
        'sim_engine_realtime_factor': round(duration / engine_s, 1),
        'sim_engine_realtime_factor_cpu': round(duration / engine_cpu_s, 1),
        'sim_load_average_1min': round(os.getloadavg()[0], 2),
        'sim_record_messages_per_s': round(messages / record_s),
        'sim_raycast_scans_per_s': round(scans / raycast_s),
        'sim_raycast_beams': params.scan_beams,
        'sim_world_segments': int(len(world.segments)),
    }


if __name__ == '__main__':
    print(json.dumps(run(), indent=2))
