"""What `ros2 run sensing_nodes NAME` relies on: a colcon build of this package, found through the
ament index, with every executable in lib/sensing_nodes, started from the install tree over DDS."""

import os
import subprocess
import sys
from pathlib import Path

import pytest
from harness import Collector, spin_until

ARCHITECTURE_EXECUTABLES = [
    'sensor_sim', 'wheel_odometry', 'gyro_integrator', 'line_extractor', 'icp_matcher',
    'complementary_fusion',
]


@pytest.fixture(scope='module')
def install_tree(colcon_workspace):
    """The session's colcon build of this checkout; returns (install prefix, environment with
    its prefix on AMENT_PREFIX_PATH and its site-packages on PYTHONPATH)."""
    ws = colcon_workspace
    prefix = ws / 'install' / 'sensing_nodes'
    site = (
        prefix
        / 'lib'
        / f'python{sys.version_info.major}.{sys.version_info.minor}'
        / 'site-packages'
    )
    env = dict(os.environ)
    env['AMENT_PREFIX_PATH'] = os.pathsep.join(
        filter(None, [str(prefix), env.get('AMENT_PREFIX_PATH')])
    )
    env['PYTHONPATH'] = os.pathsep.join(filter(None, [str(site), env.get('PYTHONPATH')]))
    return prefix, env


def test_ament_index_finds_package_and_every_executable(install_tree):
    prefix, env = install_tree
    code = (
        'from ament_index_python.packages import get_package_prefix, get_package_share_directory\n'
        'print(get_package_prefix("sensing_nodes"))\n'
        'print(get_package_share_directory("sensing_nodes"))\n'
        'import sensing_nodes; print(sensing_nodes.__file__)\n'
    )
    # Run outside the checkout, so its sensing_nodes/ cannot shadow the installed one.
    out = subprocess.run([sys.executable, '-c', code], env=env, capture_output=True, text=True,
                         cwd=prefix)
    assert out.returncode == 0, out.stderr
    found_prefix, share, module = out.stdout.split()
    assert Path(found_prefix) == prefix
    assert (Path(share) / 'package.xml').is_file()
    assert (Path(share) / 'config' / 'default_world.yaml').is_file()
    assert Path(module).is_relative_to(prefix), 'the installed copy, not the checkout, is imported'
    for name in ARCHITECTURE_EXECUTABLES:
        exe = prefix / 'lib' / 'sensing_nodes' / name
        assert exe.is_file() and os.access(exe, os.X_OK), name


def test_sensor_sim_runs_from_install_tree(install_tree, probe):
    from sensor_msgs.msg import LaserScan

    from sensing_nodes.ros.qos import SENSOR_QOS

    prefix, env = install_tree
    scans = Collector(probe, LaserScan, '/scan', SENSOR_QOS)
    exe = prefix / 'lib' / 'sensing_nodes' / 'sensor_sim'
    proc = subprocess.Popen(
        [str(exe), '--ros-args', '-p', 'real_time_factor:=5.0'], env=env,
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    try:
        assert spin_until(probe, lambda: len(scans.messages) >= 3, timeout=30), 'no /scan received'
    finally:
        proc.terminate()
        proc.wait(10)
        scans.close()
    assert scans.messages[0].header.frame_id == 'laser'
