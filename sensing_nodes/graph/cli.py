"""Command-line descriptions of a graph shared by the tools that start one (sensing_demo,
sensing_replay, sensing_pipeline, sensing_graph, sensing_soak): which nodes, their parameters,
remaps and parameter files, and the run's output folder."""

from __future__ import annotations

import sys
from collections import defaultdict
from pathlib import Path

from sensing_nodes.paths import config_file
from sensing_nodes.topics import PROCESSING_NODES


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
