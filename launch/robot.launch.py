"""A real robot's processing nodes (no simulator) on a machine with ROS 2 installed.

    ros2 launch sensing_nodes robot.launch.py params_file:=PRESET [use_sim_time:=false]
        [namespace:=NS] [one_process:=false] [lifecycle:=false] [nodes:=wheel_odometry,...]
        [scan_topic:=/scan] [imu_topic:=/imu/data_raw] [joint_states_topic:=/joint_states]

PRESET: a robot preset, either a file (sensing_doctor's params.yaml) or the name of one in
config/robots/ (turtlebot3). Each node reads its own config/<node>.yaml first, then the preset,
as `sensing_replay --launch --params-file` and `sensing_graph --params-file` do.
one_process:=true runs the `sensing_graph` executable (the nodes in one process) instead of one
process per node; the nodes, their names, parameters and topics are the same. The *_topic
arguments name the robot's driver topics where they differ (sensing_doctor prints them). With a
namespace the nodes and every topic of the graph move under it (/tf and /tf_static too, as
nav2 does for several robots; /diagnostics and /clock stay global), and the parameter files'
node keys are matched in it. lifecycle:=true starts every node managed (its `lifecycle`
parameter true; in one process, sensing_graph --lifecycle): unconfigured, for a lifecycle manager
(nav2's, with bond_timeout: 0.0) or `ros2 lifecycle set` to configure and activate
(docs/architecture.md, "Managed (lifecycle) nodes").
"""

import os
import re
import tempfile

from ament_index_python.packages import get_package_share_directory
from launch.actions import DeclareLaunchArgument, ExecuteProcess, OpaqueFunction
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node
from launch_ros.substitutions import ExecutableInPackage

from launch import LaunchDescription

PACKAGE = 'sensing_nodes'
BOOLEAN = ['true', 'false']


def generate_launch_description():
    from sensing_nodes.topics import PROCESSING_NODES

    return LaunchDescription([
        DeclareLaunchArgument('params_file', description=(
            'robot preset: a parameter file (sensing_doctor\'s params.yaml) or a name in '
            'config/robots/, read after each node\'s config/<node>.yaml')),
        DeclareLaunchArgument('use_sim_time', default_value='false', choices=BOOLEAN,
                              description='every node on /clock (a bag played with its clock)'),
        DeclareLaunchArgument('namespace', default_value='',
                              description='the nodes and their topics under this namespace'),
        DeclareLaunchArgument('one_process', default_value='false', choices=BOOLEAN,
                              description='the nodes in one sensing_graph process'),
        DeclareLaunchArgument('nodes', default_value=','.join(PROCESSING_NODES),
                              description='which processing nodes (comma separated)'),
        DeclareLaunchArgument('scan_topic', default_value='/scan',
                              description='the laser driver\'s LaserScan topic'),
        DeclareLaunchArgument('imu_topic', default_value='/imu/data_raw',
                              description='the IMU driver\'s Imu topic'),
        DeclareLaunchArgument('joint_states_topic', default_value='/joint_states',
                              description='the wheel encoders\' JointState topic'),
        DeclareLaunchArgument('lifecycle', default_value='false', choices=BOOLEAN,
                              description='managed (lifecycle) nodes: each starts unconfigured, '
                                          'brought up by a lifecycle manager or ros2 lifecycle '
                                          'set; false: they process from start-up'),
        OpaqueFunction(function=_processing_nodes),
    ])


def _processing_nodes(context):
    from sensing_nodes.graph.cli import params_file_path, parse_nodes

    def value(name):
        return LaunchConfiguration(name).perform(context)

    names = parse_nodes(value('nodes'))
    preset = str(params_file_path(value('params_file')))
    namespace = value('namespace').strip('/')
    sim_time = value('use_sim_time') == 'true'
    managed = value('lifecycle') == 'true'
    remaps = _topic_remaps(namespace, {'/scan': value('scan_topic'),
                                       '/imu/data_raw': value('imu_topic'),
                                       '/joint_states': value('joint_states_topic')})
    config = os.path.join(get_package_share_directory(PACKAGE), 'config')
    configs = {name: os.path.join(config, f'{name}.yaml') for name in names}
    if namespace:
        configs = {name: _keys_in_any_namespace(f) for name, f in configs.items()}
        preset = _keys_in_any_namespace(preset)
    if value('one_process') == 'true':
        # sensing_graph reads each node's config/<node>.yaml itself; in a namespace, where
        # their keys do not match, the copies that do follow it.
        command = [ExecutableInPackage(package=PACKAGE, executable='sensing_graph'),
                   '--nodes', ','.join(names)] + (['--lifecycle'] if managed else [])
        for f in [*configs.values(), preset] if namespace else [preset]:
            command += ['--params-file', f]
        for name in names:
            if sim_time:
                command += ['--param', f'{name}:use_sim_time:=true']
            if namespace:
                command += ['--remap', f'{name}:__ns:=/{namespace}']
            command += [arg for src, dst in remaps for arg in ('--remap', f'{name}:{src}:={dst}')]
        return [ExecuteProcess(cmd=command, name='sensing_graph', output='screen')]
    return [Node(package=PACKAGE, executable=name, name=name, namespace=namespace or None,
                 parameters=[configs[name], preset,
                             {'use_sim_time': sim_time, 'lifecycle': managed}],
                 remappings=remaps, output='screen') for name in names]


def _topic_remaps(namespace, drivers):
    """(graph topic, name) for each topic that moves: a driver topic named otherwise, and with a
    namespace every topic of the graph made relative (it then resolves under the namespace)."""
    from sensing_nodes.topics import DIAGNOSTICS, NODES

    topics = {t for n in NODES.values() for t in (*n.inputs, *n.outputs, *n.optional)}
    remaps = []
    for topic in sorted(topics - {DIAGNOSTICS}):
        name = drivers.get(topic, topic)
        if namespace and name == topic:
            name = topic.lstrip('/')
        if name != topic:
            remaps.append((topic, name))
    return remaps


def _keys_in_any_namespace(path):
    """A copy of a parameter file whose node keys ('wheel_odometry:') match the node in any
    namespace ('/**/wheel_odometry:'): rcl reads a bare key as the node in the root namespace.
    Rewritten as text, so that the rest (quoting that rcl's YAML needs) stays as it is."""
    with open(path) as f:
        text = re.sub(r'^(?![/\s#\'"])([^:\s]+):', r'/**/\1:', f.read(), flags=re.MULTILINE)
    handle, copy = tempfile.mkstemp(prefix='sensing_nodes_', suffix='.yaml')
    with os.fdopen(handle, 'w') as f:
        f.write(text)
    return copy
