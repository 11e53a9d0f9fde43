"""Test set-up: an isolated DDS domain per run and a probe node for talking to node processes."""

import os

from sensing_nodes.graph.processes import pid_domain_id

# Before rclpy creates a context: stay on this machine, and use a domain of this run's own so
# parallel runs (and other developers' runs) on one machine never see each other. A pytest-xdist
# worker inherits its controller's environment: each worker takes a domain of its own pid.
os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
if os.environ.get('PYTEST_XDIST_WORKER'):
    os.environ['ROS_DOMAIN_ID'] = str(pid_domain_id('tests'))
else:
    os.environ.setdefault('ROS_DOMAIN_ID', str(pid_domain_id('tests')))

import shutil  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
from pathlib import Path  # noqa: E402

import pytest  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
_NOT_SOURCE = shutil.ignore_patterns(
    '.git', '.venv', 'build', 'install', 'log', '*.egg-info', '__pycache__', 'out', 'demo_out*')


def pytest_sessionstart(session):
    """Remove Fast DDS shared-memory ports and segments left by processes that were killed
    (SIGKILL skips their clean-up); live ones are left alone. Stale ports make new participants
    log 'open_and_lock_file failed' and can delay their first samples."""
    fastdds = Path(sys.executable).parent / 'fastdds'
    if fastdds.is_file():
        subprocess.run([str(fastdds), 'shm', 'clean'], capture_output=True, timeout=30)


@pytest.fixture(scope='session')
def probe():
    """An rclpy node in the test process, for publishing to and subscribing from node processes."""
    import rclpy
    from rclpy.node import Node

    rclpy.init()
    node = Node('test_probe')
    yield node
    node.destroy_node()
    rclpy.try_shutdown()


@pytest.fixture(scope='session')
def colcon_workspace(tmp_path_factory) -> Path:
    """A ROS 2 workspace with a copy of this checkout in src/sensing_nodes, built with
    `colcon build --packages-select sensing_nodes` (README, "In a ROS 2 workspace") once per
    test session (per pytest-xdist worker that asks for it); its root."""
    ws = tmp_path_factory.mktemp('ws')
    shutil.copytree(REPO, ws / 'src' / 'sensing_nodes', ignore=_NOT_SOURCE)
    colcon = Path(sys.executable).parent / 'colcon'
    build = subprocess.run(
        [str(colcon), 'build', '--packages-select', 'sensing_nodes'],
        cwd=ws, capture_output=True, text=True, timeout=300)
    assert build.returncode == 0, build.stdout + build.stderr
    return ws
