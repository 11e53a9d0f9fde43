"""sensing_pipeline's speed: x real time on a simulated bag at the default sensor rates.

A bag is recorded with `sensor_sim --record` (300 s, seed 5; 60 s
with --quick), then `sensing_pipeline BAG OUT --no-progress` runs as a child process, all five
nodes. Its CPU time (user + system, process start included) and wall time give x real time
(bag seconds per CPU second, the target's one-core figure, and per wall second). The load
average is reported with the figures: on a shared machine compare figures from one run only.
"""

from __future__ import annotations

import os
import resource
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path


def executable(name: str) -> str:
    """The venv's console script beside the running Python (else the PATH's)."""
    path = Path(sys.executable).parent / name
    return str(path) if path.is_file() else name


def record_sim_bag(bag: Path, duration_s: float) -> None:
    """sensor_sim's default route (seed 5) recorded into `bag` for duration_s simulated s."""
    subprocess.run([executable('sensor_sim'), '--record', str(bag), '--duration',
                    f'{duration_s:g}', '--seed', '5'], check=True, capture_output=True)


def child_cpu_s() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


@dataclass
class TimedRun:
    """A child process run to its end: its result, CPU and wall seconds, and the 1-minute load
    average when it started and ended."""

    result: subprocess.CompletedProcess
    cpu_s: float
    wall_s: float
    load_start: float
    load_end: float


def timed_child(command: list[str]) -> TimedRun:
    """Run `command` to its end, measuring its CPU (children's rusage) and wall time."""
    load_start = os.getloadavg()[0]
    cpu0, wall0 = child_cpu_s(), time.monotonic()
    result = subprocess.run(command, capture_output=True, text=True)
    cpu, wall = child_cpu_s() - cpu0, time.monotonic() - wall0
    return TimedRun(result, cpu, wall, load_start, os.getloadavg()[0])


def run(quick: bool = False) -> dict:
    """Record the bag, run the pipeline over it, return its speed figures."""
    duration_s = 60.0 if quick else 300.0
    with tempfile.TemporaryDirectory() as tmp:
        bag, out = Path(tmp) / 'bag', Path(tmp) / 'out'
        record_sim_bag(bag, duration_s)
        run_ = timed_child([executable('sensing_pipeline'), str(bag), str(out),
                            '--no-progress'])
        if run_.result.returncode != 0:
            return {'error': (run_.result.stderr.strip().splitlines() or ['failed'])[-1]}
    return {
        'pipeline_bag_seconds': duration_s,
        'pipeline_cpu_seconds': round(run_.cpu_s, 2),
        'pipeline_wall_seconds': round(run_.wall_s, 2),
        'pipeline_x_real_time_cpu': round(duration_s / run_.cpu_s, 2),
        'pipeline_x_real_time_wall': round(duration_s / run_.wall_s, 2),
        'pipeline_load_average_1min_start': round(run_.load_start, 2),
        'pipeline_load_average_1min_end': round(run_.load_end, 2),
    }


if __name__ == '__main__':
    print(run(quick='--quick' in sys.argv))
