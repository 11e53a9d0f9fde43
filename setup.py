import os
from glob import glob

from setuptools import find_packages, setup

PACKAGE = 'sensing_nodes'

# Every executable is a console script; setup.cfg puts them in lib/sensing_nodes so that
# `ros2 run sensing_nodes NAME` finds them in a colcon install.
EXECUTABLES = {
    'sensor_sim': 'sensing_nodes.nodes.sensor_sim:main',
    'wheel_odometry': 'sensing_nodes.nodes.wheel_odometry:main',
    'gyro_integrator': 'sensing_nodes.nodes.gyro_integrator:main',
    'line_extractor': 'sensing_nodes.nodes.line_extractor:main',
    'icp_matcher': 'sensing_nodes.nodes.icp_matcher:main',
    'complementary_fusion': 'sensing_nodes.nodes.complementary_fusion:main',
    'sensing_graph': 'sensing_nodes.tools.graph:main',
    'sensing_demo': 'sensing_nodes.tools.demo:main',
    'sensing_bench': 'sensing_nodes.bench.runner:main',
    'lines_plot': 'sensing_nodes.tools.lines_plot:main',
    'icp_plot': 'sensing_nodes.tools.icp_plot:main',
    'sensing_replay': 'sensing_nodes.tools.replay:main',
    'sensing_pipeline': 'sensing_nodes.tools.pipeline:main',
    'carmen_to_bag': 'sensing_nodes.tools.carmen_to_bag:main',
    'sensing_eval': 'sensing_nodes.tools.eval:main',
    'sensing_soak': 'sensing_nodes.tools.soak:main',
    'sensing_calibrate': 'sensing_nodes.tools.calibrate:main',
    'sensing_characterize': 'sensing_nodes.tools.characterize:main',
    'sensing_fuse_bag': 'sensing_nodes.tools.fuse_bag:main',
    'sensing_fusion_eval': 'sensing_nodes.tools.fusion_eval:main',
    'sensing_doctor': 'sensing_nodes.tools.doctor:main',
}

def bag_files():
    """(install folder, files) for bags/ and each bag folder in it, keeping their layout."""
    folders = {}
    for path in glob('bags/**/*', recursive=True):
        if os.path.isfile(path):
            folders.setdefault(os.path.join('share', PACKAGE, os.path.dirname(path)), []).append(
                path
            )
    return sorted(folders.items())


setup(
    name=PACKAGE,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + PACKAGE]),
        ('share/' + PACKAGE, ['package.xml']),
        ('share/' + PACKAGE + '/config', glob('config/*.yaml')),
        ('share/' + PACKAGE + '/config/robots', glob('config/robots/*.yaml')),
        ('share/' + PACKAGE + '/launch', glob('launch/*.py')),
        *bag_files(),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='sensing_nodes maintainers',
    maintainer_email='maintainers@sensing-nodes.invalid',
    description='Motion estimates from raw mobile-robot sensors as ROS 2 nodes',
    license='Apache-2.0',
    tests_require=['pytest'],
    entry_points={
        'console_scripts': [f'{name} = {target}' for name, target in EXECUTABLES.items()],
    },
)
