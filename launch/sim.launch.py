"""The simulated robot's graph on a machine with ROS 2 installed: sensor_sim and the five
processing nodes, six processes (the `sensing_graph` executable is the five processing nodes in
one process; a real robot's launch is robot.launch.py).

    ros2 launch sensing_nodes sim.launch.py [real_time_factor:=1.0] [seed:=0]

Each node reads its parameter file from this package's share/sensing_nodes/config. The simulator
is not paced by the graph here (sensing_demo paces it): above real time a 2-core machine loses
messages (docs/tools.md).
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

from launch import LaunchDescription

NODES = ['sensor_sim', 'wheel_odometry', 'gyro_integrator', 'line_extractor', 'icp_matcher',
         'complementary_fusion']


def generate_launch_description():
    config = os.path.join(get_package_share_directory('sensing_nodes'), 'config')
    arguments = [
        DeclareLaunchArgument('real_time_factor', default_value='1.0',
                              description='simulated seconds per wall second'),
        DeclareLaunchArgument('seed', default_value='0', description='simulation seed'),
    ]
    nodes = []
    for name in NODES:
        parameters = [os.path.join(config, f'{name}.yaml')]
        if name == 'sensor_sim':
            parameters.append({'real_time_factor': LaunchConfiguration('real_time_factor'),
                               'seed': LaunchConfiguration('seed')})
        nodes.append(Node(package='sensing_nodes', executable=name, name=name,
                          parameters=parameters, output='screen'))
    return LaunchDescription(arguments + nodes)
