"""tf2_msgs built into the venv, and /tf, /tf_static over real DDS (sensing_nodes/ros/tf.py)."""

from __future__ import annotations

import math

import pytest
from harness import spin_until
from rclpy.node import Node
from tf2_msgs.msg import TFMessage

from sensing_nodes.core.geometry import quaternion as quat
from sensing_nodes.core.geometry.transform import Transform
from sensing_nodes.ros.qos import TF_QOS
from sensing_nodes.ros.tf import (
    StaticTransformBroadcaster,
    StaticTransformBuffer,
    TransformBroadcaster,
)

# `ros2 interface` of ROS 2 Jazzy reports this hash for tf2_msgs/msg/TFMessage.
JAZZY_TF_MESSAGE_HASH = 'RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087'


@pytest.fixture
def talker(probe):
    node = Node('tf_test_talker', context=probe.context)
    yield node
    node.destroy_node()


def test_tf_message_type_hash_is_jazzy_s(probe):
    publisher = probe.create_publisher(TFMessage, '/tf_hash_check', 1)
    infos = []
    spin_until(probe, lambda: bool(infos.extend(probe.get_publishers_info_by_topic(
        '/tf_hash_check')) or infos), 10.0)
    probe.destroy_publisher(publisher)
    assert str(infos[0].topic_type_hash) == JAZZY_TF_MESSAGE_HASH


def test_dynamic_transform_round_trip(probe, talker):
    received = []
    sub = probe.create_subscription(TFMessage, '/tf', received.append, TF_QOS)
    broadcaster = TransformBroadcaster(talker)
    sent = Transform.from_planar(1.25, -0.5, 0.3)
    assert spin_until(probe, lambda: broadcaster._publisher.get_subscription_count() > 0, 10.0)
    broadcaster.send(1_700_000_000_123_456_789, 'odom', 'base_link', sent)
    assert spin_until(probe, lambda: bool(received), 10.0)
    probe.destroy_subscription(sub)
    t = received[0].transforms[0]
    assert (t.header.frame_id, t.child_frame_id) == ('odom', 'base_link')
    assert (t.header.stamp.sec, t.header.stamp.nanosec) == (1_700_000_000, 123_456_789)
    assert (t.transform.translation.x, t.transform.translation.y) == (1.25, -0.5)
    assert 2 * math.atan2(t.transform.rotation.z, t.transform.rotation.w) == pytest.approx(0.3)


def test_late_subscriber_gets_every_static_transform_and_chains_them(probe, talker):
    # Frame names of this test's own: other tests' latched /tf_static may share the domain.
    statics = StaticTransformBroadcaster(talker)
    # chain_base -> chain_plate (raised 0.2 m) -> chain_laser (0.1 m ahead, turned 90 deg left)
    statics.send(0, 'chain_base', 'chain_plate', Transform((0.0, 0.0, 0.2)))
    statics.send(0, 'chain_plate', 'chain_laser', Transform.from_planar(0.1, 0.0, math.pi / 2))
    statics.send(0, 'chain_base', 'chain_imu', Transform((0.0, 0.0, 0.05),
                                                         quat.from_rpy(math.pi, 0.0, 0.0)))
    updates = []
    buffer = StaticTransformBuffer(probe, on_update=lambda: updates.append(1))
    assert spin_until(probe, lambda: buffer.lookup('chain_base', 'chain_laser') is not None, 10.0)
    laser = buffer.lookup('chain_base', 'chain_laser')
    assert laser.translation == pytest.approx((0.1, 0.0, 0.2))
    assert laser.planar() == pytest.approx((0.1, 0.0, math.pi / 2))
    # chain_laser -> chain_imu goes up to chain_base and down again.
    imu_in_laser = buffer.lookup('chain_laser', 'chain_imu')
    assert buffer.lookup('chain_base', 'chain_laser').compose(imu_in_laser).translation == \
        pytest.approx((0.0, 0.0, 0.05))
    assert buffer.lookup('chain_base', 'chain_wheel') is None
    assert buffer.lookup('/chain_base', '/chain_laser') is not None      # ROS 1 style names
    assert updates


def test_bad_static_transforms_are_refused_and_counted(probe, talker):
    statics = StaticTransformBroadcaster(talker)
    statics.send(0, 'base_link', 'bad_quaternion', Transform(rotation=(0.0, 0.0, 0.0, 2.0)))
    statics.send(0, 'base_link', 'bad_nan', Transform((math.nan, 0.0, 0.0)))
    statics.send(0, 'base_link', 'base_link', Transform())
    statics.send(0, 'base_link', 'good', Transform(rotation=(0.0, 0.0, 0.7071, 0.7071)))
    buffer = StaticTransformBuffer(probe)
    assert spin_until(probe, lambda: buffer.lookup('base_link', 'good') is not None, 10.0)
    assert buffer.rejected == 3
    assert buffer.lookup('base_link', 'bad_quaternion') is None
    assert buffer.lookup('base_link', 'bad_nan') is None
    assert quat.norm(buffer.lookup('base_link', 'good').rotation) == pytest.approx(1.0, abs=1e-15)
