"""The node graph as processes: which nodes, where their executables are, their isolated DDS
environment, and starting and stopping them (used by sensing_demo, sensing_soak and
sensing_replay --launch)."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

from sensing_nodes.paths import config_file

PROCESSING_NODES = ('wheel_odometry', 'gyro_integrator', 'line_extractor', 'icp_matcher',
                    'complementary_fusion')


def executable(name: str) -> str:
    """Path of a sibling executable: venv bin/ or a colcon install's lib/sensing_nodes/."""
    here = Path(sys.argv[0]).resolve().parent / name
    if here.is_file():
        return str(here)
    found = shutil.which(name)
    if found is None:
        raise SystemExit(f'executable {name!r} not found next to {sys.argv[0]} or on PATH')
    return found


def isolated_environment(domain_id: int | None, offset: int = 0) -> dict[str, str]:
    """This process's environment for a graph of its own: this machine only, and the given
    ROS_DOMAIN_ID or one derived from the pid (offset keeps two tools started together apart);
    also applied to os.environ, so rclpy in this process joins the same domain."""
    env = dict(os.environ)
    env.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    env['ROS_DOMAIN_ID'] = str(domain_id if domain_id is not None
                               else 100 + (os.getpid() + offset) % 100)
    os.environ.update({k: env[k] for k in ('ROS_AUTOMATIC_DISCOVERY_RANGE', 'ROS_DOMAIN_ID')})
    return env


class Graph:
    """The node processes, started with their parameter files, stopped with SIGINT."""

    def __init__(self, out: Path, env: dict[str, str]) -> None:
        self.out, self.env = out, env
        self.processes: dict[str, subprocess.Popen] = {}
        self._logs = {}

    def start(self, name: str, extra: list[str]) -> None:
        log = open(self.out / 'logs' / f'{name}.log', 'w')
        self._logs[name] = log
        cmd = [executable(name), '--ros-args', '--params-file', str(config_file(f'{name}.yaml')),
               *extra]
        self.processes[name] = subprocess.Popen(
            cmd, stdout=log, stderr=subprocess.STDOUT, env=self.env, start_new_session=True)

    def failed(self) -> list[str]:
        return [n for n, p in self.processes.items() if p.poll() not in (None, 0)]

    def stop(self, timeout: float = 10.0) -> dict[str, int]:
        for proc in self.processes.values():
            if proc.poll() is None:
                proc.send_signal(signal.SIGINT)
        codes = {}
        for name, proc in self.processes.items():
            try:
                codes[name] = proc.wait(timeout)
            except subprocess.TimeoutExpired:
                proc.kill()
                codes[name] = proc.wait()
        for log in self._logs.values():
            log.close()
        return codes
