"""Test set-up: an isolated DDS domain per run and a probe node for talking to node processes."""

import os

# Before rclpy creates a context: stay on this machine, and use a domain of this run's own so
# parallel runs (and other developers' runs) on one machine never see each other.
os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
os.environ.setdefault('ROS_DOMAIN_ID', str(1 + os.getpid() % 200))

import pytest  # noqa: E402


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
