"""The graph's nodes as processes: where their executables are, an isolated DDS environment
for each run (its domain id and discovery range), starting and stopping them."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path

from sensing_nodes.graph.cli import GraphArgumentError, node_arguments

# The one-process graph (sensing_graph), run by the interpreter of the tool that starts it.
ONE_PROCESS = 'sensing_graph'


def executable(name: str) -> str:
    """Path of a sibling executable: next to the running command (venv bin/ or a colcon
    install's lib/sensing_nodes/), next to the interpreter (a venv's bin/, for `python -m`),
    else on PATH."""
    for folder in (Path(sys.argv[0]).resolve().parent, Path(sys.executable).parent):
        if (folder / name).is_file():
            return str(folder / name)
    found = shutil.which(name)
    if found is None:
        raise SystemExit(f'executable {name!r} not found next to {sys.argv[0]}, next to '
                         f'{sys.executable} or on PATH')
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


def isolated_environment(domain_id: int | None, offset: int = 0, kind: str = 'tools',
                         localhost: bool = False) -> dict[str, str]:
    """This process's environment for a graph of its own: this machine only (the environment's
    ROS_AUTOMATIC_DISCOVERY_RANGE where set, unless localhost forces it), and the given
    ROS_DOMAIN_ID or one derived from the pid within kind's DOMAIN_RANGES (offset keeps two
    graphs started together apart); also applied to os.environ, so rclpy in this process joins
    the same domain."""
    env = dict(os.environ)
    if localhost:
        env['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    env.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    env['ROS_DOMAIN_ID'] = str(domain_id if domain_id is not None
                               else pid_domain_id(kind, offset))
    os.environ.update({k: env[k] for k in ('ROS_AUTOMATIC_DISCOVERY_RANGE', 'ROS_DOMAIN_ID')})
    return env


class Graph:
    """A graph's processes, each in a session of its own with env, its output in
    log_dir/<name>.log; stopped with SIGINT (the nodes shut down cleanly), killed if they hang."""

    def __init__(self, log_dir: Path, env: dict[str, str]) -> None:
        self.log_dir, self.env = log_dir, env
        log_dir.mkdir(parents=True, exist_ok=True)
        self.processes: dict[str, subprocess.Popen] = {}
        self._logs = {}

    def log(self, name: str) -> Path:
        return self.log_dir / f'{name}.log'

    def start_command(self, name: str, command: list[str]) -> subprocess.Popen:
        """Start a command as the process `name` (a node's: start(), start_one_process())."""
        log = self._logs[name] = open(self.log(name), 'w')
        self.processes[name] = subprocess.Popen(
            command, stdout=log, stderr=subprocess.STDOUT, env=self.env, start_new_session=True)
        return self.processes[name]

    def start(self, name: str, extra: list[str], params_files: Sequence[Path] = ()) -> None:
        """A node's executable with its config/<name>.yaml, then params_files (a robot preset
        overriding them), then extra (its own -p/-r)."""
        self.start_command(name, [executable(name),
                                  *node_arguments(name, list(params_files), extra)])

    def start_one_process(self, names: tuple[str, ...], extras: dict[str, list[str]],
                          executor_kind: str | None = None,
                          params_files: Sequence[Path] = ()) -> None:
        """The named processing nodes in one sensing_graph process (self.processes[ONE_PROCESS]),
        each with the arguments start() would give it; extras: node -> ['-p'|'-r', 'A:=B', ...]."""
        cmd = [sys.executable, '-m', 'sensing_nodes.tools.graph', '--nodes', ','.join(names)]
        for params_file in params_files:
            cmd += ['--params-file', str(params_file)]
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
        self.start_command(ONE_PROCESS, cmd)

    def failed(self) -> list[str]:
        return [n for n, p in self.processes.items() if p.poll() not in (None, 0)]

    def stop(self, timeout: float = 10.0) -> dict[str, int]:
        """SIGINT to every live process, then wait up to timeout s each; kill what hangs. The
        exit codes by name."""
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
