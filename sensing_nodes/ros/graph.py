"""The node graph: its topics (names, types, who publishes and takes what), its nodes as
processes (where their executables are, their isolated DDS environment, starting and stopping
them). One description used by the nodes, sensor_sim, sensing_demo, sensing_soak,
sensing_replay, sensing_pipeline and sensing_graph (all processing nodes in one process)."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

from sensing_nodes.paths import config_file

# -- topics ---------------------------------------------------------------------------------
CLOCK = '/clock'
GROUND_TRUTH = '/ground_truth/odom'
JOINT_STATES = '/joint_states'
IMU_RAW = '/imu/data_raw'
SCAN = '/scan'
CMD_VEL = '/cmd_vel'
WHEEL_ODOM = '/wheel/odom'
IMU = '/imu/data'
SCAN_LINES = '/scan/lines'
SCAN_LINES_TABLE = '/scan/lines/table'
SCAN_MATCH = '/scan_match/odom'
SCAN_MATCH_KEYFRAME = '/scan_match/keyframe_odom'
FUSED = '/odometry/filtered'
DIAGNOSTICS = '/diagnostics'
TF = '/tf'
TF_STATIC = '/tf_static'

TOPIC_TYPES = {
    CLOCK: 'rosgraph_msgs/msg/Clock',
    GROUND_TRUTH: 'nav_msgs/msg/Odometry',
    JOINT_STATES: 'sensor_msgs/msg/JointState',
    IMU_RAW: 'sensor_msgs/msg/Imu',
    SCAN: 'sensor_msgs/msg/LaserScan',
    CMD_VEL: 'geometry_msgs/msg/Twist',
    WHEEL_ODOM: 'nav_msgs/msg/Odometry',
    IMU: 'sensor_msgs/msg/Imu',
    SCAN_LINES: 'visualization_msgs/msg/MarkerArray',
    SCAN_LINES_TABLE: 'sensor_msgs/msg/PointCloud2',
    SCAN_MATCH: 'nav_msgs/msg/Odometry',
    SCAN_MATCH_KEYFRAME: 'nav_msgs/msg/Odometry',
    FUSED: 'nav_msgs/msg/Odometry',
    DIAGNOSTICS: 'diagnostic_msgs/msg/DiagnosticArray',
    TF: 'tf2_msgs/msg/TFMessage',
    TF_STATIC: 'tf2_msgs/msg/TFMessage',
}
# Raw sensor streams: published best effort, as a driver would (SENSOR_QOS); the rest reliable.
SENSOR_TOPICS = frozenset({JOINT_STATES, IMU_RAW, SCAN})
# Published on a wall-clock timer whatever the input: never waited for, not part of "quiet".
WALL_PERIODIC_TOPICS = frozenset({DIAGNOSTICS})
# What sensor_sim publishes (the simulated robot's drivers, its ground truth and clock).
SIMULATOR_TOPICS = (SCAN, IMU_RAW, JOINT_STATES, GROUND_TRUTH, CLOCK)


@dataclass(frozen=True)
class NodeTopics:
    """A processing node's topics (default names): what it takes, the input it answers one
    message at a time (`answers`, None for a node that buffers) with one message on each of
    `answered_with` carrying that input's stamp, and what else it always publishes."""

    inputs: tuple[str, ...]
    answered_with: tuple[str, ...]
    answers: str | None = None
    also: tuple[str, ...] = (DIAGNOSTICS,)
    optional: tuple[str, ...] = field(default=())   # only with some parameters (publish_tf...)

    @property
    def outputs(self) -> tuple[str, ...]:
        """What it publishes whatever its parameters: main output first."""
        return self.answered_with + self.also


NODES = {
    'wheel_odometry': NodeTopics((JOINT_STATES,), (WHEEL_ODOM,), JOINT_STATES, optional=(TF,)),
    'gyro_integrator': NodeTopics((IMU_RAW, WHEEL_ODOM, TF_STATIC), (IMU,), IMU_RAW),
    'line_extractor': NodeTopics((SCAN,), (SCAN_LINES, SCAN_LINES_TABLE), SCAN),
    'icp_matcher': NodeTopics((SCAN, WHEEL_ODOM, TF_STATIC), (SCAN_MATCH,), SCAN,
                              optional=(SCAN_MATCH_KEYFRAME, TF)),
    'complementary_fusion': NodeTopics((WHEEL_ODOM, IMU, SCAN_MATCH, SCAN_MATCH_KEYFRAME),
                                       (FUSED,), optional=(TF,)),
}
PROCESSING_NODES = tuple(NODES)
# Processing node name -> (module, class): what its executable constructs.
NODE_CLASSES = {
    'wheel_odometry': ('sensing_nodes.nodes.wheel_odometry', 'WheelOdometryNode'),
    'gyro_integrator': ('sensing_nodes.nodes.gyro_integrator', 'GyroIntegratorNode'),
    'line_extractor': ('sensing_nodes.nodes.line_extractor', 'LineExtractorNode'),
    'icp_matcher': ('sensing_nodes.nodes.icp_matcher', 'IcpMatcherNode'),
    'complementary_fusion': ('sensing_nodes.nodes.complementary_fusion',
                             'ComplementaryFusionNode'),
}
# The one-process graph (sensing_graph), run by the interpreter of the tool that starts it.
ONE_PROCESS = 'sensing_graph'

# Input topic -> the outputs that answer it, one message each carrying its stamp.
ANSWERS: dict[str, tuple[str, ...]] = {}
for _topics in NODES.values():
    if _topics.answers is not None:
        ANSWERS[_topics.answers] = ANSWERS.get(_topics.answers, ()) + _topics.answered_with
# Message type each node input takes (sensor_sim's /cmd_vel included).
NODE_INPUT_TYPES = {t: TOPIC_TYPES[t] for t in
                    [JOINT_STATES, IMU_RAW, SCAN, WHEEL_ODOM, IMU, SCAN_MATCH, CMD_VEL]}


class GraphArgumentError(ValueError):
    """A command-line description of nodes, parameters or remaps that does not parse."""


def parse_node_params(specs: list[str], flag: str = '-p',
                      option: str = '--param') -> dict[str, list[str]]:
    """['icp_matcher:laser_x_m:=0.0'] -> {'icp_matcher': ['-p', 'laser_x_m:=0.0']}; with
    flag='-r' (option '--remap') a remapping of one node: NODE:FROM:=TO -> ['-r', 'FROM:=TO']."""
    extra: dict[str, list[str]] = defaultdict(list)
    for spec in specs:
        node, sep, assignment = spec.partition(':')
        if not sep or ':=' not in assignment or node not in PROCESSING_NODES:
            what = 'NAME:=VALUE' if flag == '-p' else 'FROM:=TO'
            raise GraphArgumentError(f'{option} {spec!r}: write NODE:{what} with NODE one of '
                                     f'{", ".join(PROCESSING_NODES)}')
        extra[node] += [flag, assignment]
    return extra


def parse_remaps(specs: list[str]) -> dict[str, str]:
    """['/odom:=/wheel/odom'] -> {'/odom': '/wheel/odom'}."""
    remaps = {}
    for spec in specs:
        src, sep, dst = spec.partition(':=')
        if not sep or not src.startswith('/') or not dst.startswith('/'):
            raise GraphArgumentError(f'--remap {spec!r}: write /BAG_TOPIC:=/TOPIC')
        remaps[src] = dst
    return remaps


def parse_nodes(spec: str) -> tuple[str, ...]:
    """'a,b' -> ('a', 'b'), each one of PROCESSING_NODES."""
    nodes = tuple(n for n in spec.split(',') if n)
    unknown = [n for n in nodes if n not in PROCESSING_NODES]
    if unknown or not nodes:
        raise GraphArgumentError(f'--nodes: unknown node(s) {unknown}; known: {PROCESSING_NODES}')
    return nodes


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


def new_run_folder(out: Path | None, default_root: str, marker: str, prog: str) -> Path | None:
    """The output folder of a graph run (default: default_root/run-<date-time>), created; None
    (with a line on stderr) when it already holds a run (its `marker` file or folder exists)."""
    from datetime import datetime

    out = out or Path(default_root) / datetime.now().strftime('run-%Y%m%d-%H%M%S')
    if (out / marker).exists():
        print(f'{prog}: {out} already holds a run; choose another --out', file=sys.stderr)
        return None
    out.mkdir(parents=True, exist_ok=True)
    return out
def params_file_path(spec: str | Path) -> Path:
    """A --params-file argument as a path: a file, or the name of a robot preset in
    config/robots/ (turtlebot3); GraphArgumentError when it is neither."""
    if Path(spec).is_file():
        return Path(spec)
    preset = config_file(f'robots/{spec}.yaml')
    if not preset.is_file():
        raise GraphArgumentError(f'--params-file {spec}: no such file, and no preset {preset}')
    return preset


def node_arguments(name: str, params_files: list[Path], extra: list[str]) -> list[str]:
    """The ROS arguments a processing node starts with: its config/<name>.yaml, then
    params_files (a robot preset), then extra (its own -p/-r), as later overrides earlier."""
    args = ['--ros-args', '--params-file', str(config_file(f'{name}.yaml'))]
    for f in params_files:
        args += ['--params-file', str(f)]
    return args + list(extra)


def make_node(name: str, arguments: list[str], context=None):
    """The processing node `name` constructed in `context` (default: this process's rclpy
    context) with only `arguments` (node_arguments) as its own, as its executable constructs
    it; the process's global ROS arguments do not apply, so nodes built side by side never
    share a -p or -r."""
    import importlib

    module, cls = NODE_CLASSES[name]
    options = {} if context is None else {'context': context}
    return getattr(importlib.import_module(module), cls)(
        cli_args=arguments, use_global_arguments=False, **options)


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
