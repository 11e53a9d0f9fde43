"""The commands sensing_doctor prints for running its preset on the robot name only what
robot.launch.py declares and what sensing_graph parses. Without ROS 2's launch: the launch
file is read, not run (test_ros2_cli.py runs it)."""

from __future__ import annotations

import ast
from pathlib import Path
from types import SimpleNamespace

from harness import REPO

from sensing_nodes.doctor.diagnosis import Diagnosis
from sensing_nodes.doctor.preset import commands
from sensing_nodes.tools.graph import parse_args


def _declared_arguments(launch_file: Path) -> set[str]:
    """The names of a launch file's DeclareLaunchArgument calls."""
    tree = ast.parse(launch_file.read_text())
    return {call.args[0].value for call in ast.walk(tree) if isinstance(call, ast.Call)
            and getattr(call.func, 'id', '') == 'DeclareLaunchArgument'}


def test_the_doctors_robot_commands_name_what_the_launch_file_and_sensing_graph_take():
    """A robot whose laser is /base_scan and IMU /imu, without a line extractor in the preset:
    the launch gets them as its driver-topic arguments, sensing_graph as remaps of the nodes
    that read them."""
    d = Diagnosis(SimpleNamespace(path=Path('robot.bag')), None)
    d.joints = SimpleNamespace(topic='/joint_states')
    d.scan, d.imu = SimpleNamespace(topic='/base_scan'), SimpleNamespace(topic='/imu')
    d.remaps = {'/base_scan': '/scan', '/imu': '/imu/data_raw'}
    d.nodes = ('wheel_odometry', 'gyro_integrator', 'icp_matcher', 'complementary_fusion')
    run = commands(d, Path('/robot/params.yaml'))

    launch = run['ros2 launch'].split()
    assert launch[:4] == ['ros2', 'launch', 'sensing_nodes', 'robot.launch.py']
    arguments = dict(a.split(':=', 1) for a in launch[4:])
    assert arguments == {'params_file': '/robot/params.yaml', 'nodes': ','.join(d.nodes),
                         'scan_topic': '/base_scan', 'imu_topic': '/imu'}
    assert set(arguments) <= _declared_arguments(REPO / 'launch' / 'robot.launch.py')

    graph = run['sensing_graph'].split()
    assert graph[0] == 'sensing_graph'
    parsed = parse_args(graph[1:])
    assert parsed.params_file == [Path('/robot/params.yaml')]
    assert parsed.nodes == ','.join(d.nodes)
    assert sorted(parsed.remap) == ['complementary_fusion:/imu/data_raw:=/imu',
                                    'gyro_integrator:/imu/data_raw:=/imu',
                                    'icp_matcher:/scan:=/base_scan']


def test_every_node_of_the_preset_runs_without_a_nodes_argument():
    d = Diagnosis(SimpleNamespace(path=Path('robot.bag')), None)
    d.joints = d.scan = d.imu = None
    d.nodes = ('wheel_odometry', 'gyro_integrator', 'line_extractor', 'icp_matcher',
               'complementary_fusion')
    run = commands(d, Path('p.yaml'))
    assert run['ros2 launch'] == 'ros2 launch sensing_nodes robot.launch.py params_file:=p.yaml'
    assert run['sensing_graph'] == 'sensing_graph --params-file p.yaml'
