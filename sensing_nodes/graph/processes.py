"""The graph's nodes as processes: where their executables are, an isolated DDS environment
for each run (its domain id and discovery range), starting and stopping them."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

from sensing_nodes.graph.cli import GraphArgumentError, node_arguments

# The one-process graph (sensing_graph), run by the interpreter of the tool that starts it.
ONE_PROCESS = 'sensing_graph'


def executable(name: str) -> str:
    """Path of a sibling executable: venv bin/ or a colcon install's lib/sensing_nodes/."""
    here = Path(sys.argv[0]).resolve().parent / name
    if here.is_file():
        return str(here)
    found = shutil.which(name)
    if found is None:
        raise SystemExit(f'executable {name!r} not found next to {sys.argv[0]} or on PATH')
    return found


# The ROS domain a process takes from its pid when none is given: one range per kind of user,
# so a tool's graph never shares a domain with a benchmark's or the tests' running at the same
# time (a demo and a benchmark on one domain once counted each other's scans). Fast DDS takes
# domain ids up to 232.
DOMAIN_RANGES = {'tests': (1, 99), 'tools': (100, 199), 'bench': (200, 229)}


def pid_domain_id(kind: str, offset: int = 0) -> int:
    """A ROS domain id (int) from this process's pid (+ offset) within kind's DOMAIN_RANGES."""
    low, high = DOMAIN_RANGES[kind]
    return low + (os.getpid() + offset) % (high - low + 1)


def isolated_environment(domain_id: int | None, offset: int = 0) -> dict[str, str]:
    """This process's environment for a graph of its own: this machine only, and the given
    ROS_DOMAIN_ID or one derived from the pid (offset keeps two tools started together apart);
    also applied to os.environ, so rclpy in this process joins the same domain."""
    env = dict(os.environ)
    env.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    env['ROS_DOMAIN_ID'] = str(domain_id if domain_id is not None
                               else pid_domain_id('tools', offset))
    os.environ.update({k: env[k] for k in ('ROS_AUTOMATIC_DISCOVERY_RANGE', 'ROS_DOMAIN_ID')})
    return env


class Graph:
    """The node processes, started with their parameter files (then params_file, a robot preset
    overriding them), stopped with SIGINT."""

    def __init__(self, out: Path, env: dict[str, str],
                 params_file: Path | None = None) -> None:
        self.out, self.env, self.params_file = out, env, params_file
        self.processes: dict[str, subprocess.Popen] = {}
        self._logs = {}

    def start(self, name: str, extra: list[str]) -> None:
        log = open(self.out / 'logs' / f'{name}.log', 'w')
        self._logs[name] = log
        cmd = [executable(name), *node_arguments(
            name, [self.params_file] if self.params_file else [], extra)]
        self.processes[name] = subprocess.Popen(
            cmd, stdout=log, stderr=subprocess.STDOUT, env=self.env, start_new_session=True)

    def start_one_process(self, names: tuple[str, ...], extras: dict[str, list[str]],
                          executor_kind: str | None = None) -> None:
        """The named processing nodes in one sensing_graph process (self.processes[ONE_PROCESS]),
        each with the arguments start() would give it; extras: node -> ['-p'|'-r', 'A:=B', ...]."""
        cmd = [sys.executable, '-m', 'sensing_nodes.tools.graph', '--nodes', ','.join(names)]
        if self.params_file:
            cmd += ['--params-file', str(self.params_file)]
        if executor_kind:
            cmd += ['--executor', executor_kind]
        options = {'-p': '--param', '-r': '--remap'}
        for name in names:
            extra = list(extras.get(name, []))
            if len(extra) % 2 or any(f not in options for f in extra[::2]):
                raise GraphArgumentError(f'{name}: one-process arguments must be -p/-r pairs: '
                                         f'{extra}')
            for flag, value in zip(extra[::2], extra[1::2]):
                cmd += [options[flag], f'{name}:{value}']
        log = open(self.out / 'logs' / f'{ONE_PROCESS}.log', 'w')
        self._logs[ONE_PROCESS] = log
        self.processes[ONE_PROCESS] = subprocess.Popen(
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
