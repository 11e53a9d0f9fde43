"""The shared ROS layer: conversions, parameters and bag round trips with real message types."""

import math
import os

import numpy as np
import pytest
from nav_msgs.msg import Odometry
from sensor_msgs.msg import LaserScan

from sensing_nodes.bags.storage import BagWriter, read_messages, topic_counts, type_name
from sensing_nodes.ros import conversions as conv


def test_stamp_round_trip_is_exact():
    ns = 1_700_000_123_456_789_012
    assert conv.stamp_to_ns(conv.ns_to_stamp(ns)) == ns


@pytest.mark.parametrize('yaw', [0.0, 0.3, -2.0, math.pi - 1e-9])
def test_yaw_quaternion_round_trip(yaw):
    assert conv.quaternion_to_yaw(conv.yaw_to_quaternion(yaw)) == pytest.approx(yaw)


def test_odometry_round_trip_places_planar_covariance():
    cov = np.array([[0.1, 0.01, 0.02], [0.01, 0.2, 0.03], [0.02, 0.03, 0.3]])
    msg = conv.make_odometry(
        5, 'odom', 'base_link', (1.0, 2.0, 0.5), cov, (0.3, 0.0, 0.1), cov * 2
    )
    assert msg.pose.covariance[0] == 0.1 and msg.pose.covariance[35] == 0.3
    assert msg.pose.covariance[5] == 0.02 and msg.pose.covariance[14] == 0.0
    pose, back = conv.odometry_pose(msg)
    assert pose == pytest.approx((1.0, 2.0, 0.5)) and back == pytest.approx(cov)
    twist, twist_cov = conv.odometry_twist(msg)
    assert twist == pytest.approx((0.3, 0.0, 0.1)) and twist_cov == pytest.approx(cov * 2)


def test_scan_arrays_and_float32_fields():
    msg = LaserScan(angle_min=-1.0, angle_increment=0.5)
    msg.ranges = conv.float32_array(np.array([1.0, np.inf, np.nan]))
    ranges, angles = conv.scan_arrays(msg)
    assert ranges[0] == 1.0 and np.isinf(ranges[1]) and np.isnan(ranges[2])
    assert angles == pytest.approx([-1.0, -0.5, 0.0])


def test_bag_round_trip_with_both_readers(tmp_path):
    from mcap_ros2.reader import read_ros2_messages

    path = tmp_path / 'bag'
    odom = conv.make_odometry(7, 'odom', 'base_link', (1.0, 2.0, 0.5), np.eye(3))
    with BagWriter(path) as bag:
        bag.write('/wheel/odom', odom, 7)
        bag.write('/wheel/odom', odom, 9)
    assert type_name(odom) == 'nav_msgs/msg/Odometry'
    assert topic_counts(path) == {'/wheel/odom': ('nav_msgs/msg/Odometry', 2)}
    ours = list(read_messages(path))
    assert [t for _, t, _ in ours] == [7, 9]
    assert isinstance(ours[0][2], Odometry) and ours[0][2].pose.pose.position.y == 2.0
    theirs = list(read_ros2_messages(str(next(path.glob('*.mcap')))))
    assert len(theirs) == 2 and theirs[1].ros_msg.pose.pose.position.x == 1.0
    assert theirs[0].channel.topic == '/wheel/odom'


def test_pid_domains_of_tools_benches_and_tests_never_meet():
    """Each kind of user takes its pid-derived ROS domain from its own range, within Fast DDS's
    0-232: a demo never joins a running benchmark's or test run's domain."""
    from sensing_nodes.graph.processes import DOMAIN_RANGES, pid_domain_id

    taken = {kind: {pid_domain_id(kind, offset) for offset in range(300)}
             for kind in DOMAIN_RANGES}
    for kind, (low, high) in DOMAIN_RANGES.items():
        assert taken[kind] == set(range(low, high + 1)) and 0 <= low and high <= 232
    kinds = list(taken)
    for i, a in enumerate(kinds):
        for b in kinds[i + 1:]:
            assert not taken[a] & taken[b], (a, b)


def test_a_benchmark_environment_is_this_machine_on_a_benchmark_domain(monkeypatch):
    """A tool's graph keeps a discovery range the user set, a benchmark's is forced to this
    machine; each takes its domain from its own range, and this process joins it."""
    from sensing_nodes.graph.processes import DOMAIN_RANGES, isolated_environment

    monkeypatch.setenv('ROS_AUTOMATIC_DISCOVERY_RANGE', 'SUBNET')
    monkeypatch.setenv('ROS_DOMAIN_ID', '0')
    tools = isolated_environment(None)
    assert tools['ROS_AUTOMATIC_DISCOVERY_RANGE'] == 'SUBNET'
    low, high = DOMAIN_RANGES['tools']
    assert low <= int(tools['ROS_DOMAIN_ID']) <= high
    bench = isolated_environment(None, 2, kind='bench', localhost=True)
    assert bench['ROS_AUTOMATIC_DISCOVERY_RANGE'] == 'LOCALHOST'
    low, high = DOMAIN_RANGES['bench']
    assert low <= int(bench['ROS_DOMAIN_ID']) <= high
    assert {k: os.environ[k] for k in ('ROS_AUTOMATIC_DISCOVERY_RANGE', 'ROS_DOMAIN_ID')} == {
        k: bench[k] for k in ('ROS_AUTOMATIC_DISCOVERY_RANGE', 'ROS_DOMAIN_ID')}
