"""The fusion's IMU handling on real recorded bags (../shared/datasets/ros, README there):
robot_localization's test2.bag through the fusion core with the shipped parameter file, and an
upside-down IMU through gyro_integrator's mount rotation. Skipped when the datasets are absent."""

import math
from pathlib import Path

import numpy as np
import pytest

from sensing_nodes.core.geometry.imu_mount import mount_rotation, to_base
from sensing_nodes.core.gyro import GyroConfig, GyroIntegrator, integrate_rate
from sensing_nodes.paths import config_file

DATASETS = Path(__file__).resolve().parents[1] / '..' / 'shared' / 'datasets' / 'ros'
TEST2 = DATASETS / 'robot_localization-test2.bag'
UPSIDE_DOWN = DATASETS / 'imu_tools-phidgets_imu_upside_down.bag'


@pytest.mark.skipif(not TEST2.is_file(), reason=f'{TEST2} not present')
def test_test2_bag_ends_where_robot_localization_expects():
    """robot_localization's EKF test expects (1.0206, 3.4292) within 0.1383 m."""
    from sensing_nodes.tools.fuse_bag import fuse_bag

    result = fuse_bag(TEST2, [config_file('fusion_jackal_test2.yaml')])
    x, y, _ = result['final_pose']
    assert result['rejected'] == {} and result['received'] == {'wheel_odom': 3060, 'imu': 3061}
    assert math.hypot(x - 1.0206, y - 3.4292) <= 0.1383


def _upside_down_samples():
    from rosbags.highlevel import AnyReader

    t, gyro, accel = [], [], []
    with AnyReader([UPSIDE_DOWN]) as reader:
        connections = [c for c in reader.connections if c.topic == '/imu/data_raw']
        for connection, _, raw in reader.messages(connections=connections):
            m = reader.deserialize(raw, connection.msgtype)
            t.append(m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec)
            gyro.append((m.angular_velocity.x, m.angular_velocity.y, m.angular_velocity.z))
            accel.append((m.linear_acceleration.x, m.linear_acceleration.y,
                          m.linear_acceleration.z))
    return np.array(t, dtype=np.int64), np.array(gyro), np.array(accel)


def _integrate(t, gyro, accel, mount):
    """gyro_integrator's path: each sample turned into base_link's axes, then integrated."""
    integrator = GyroIntegrator(GyroConfig())
    headings, still, level = [], [], []
    for stamp, g, a in zip(t, gyro, accel):
        if mount is not None:
            g, a = to_base(g, mount), to_base(a, mount)
        result = integrator.update(int(stamp), g, a)
        headings.append(integrator.heading)
        still.append(result.still)
        level.append(a[2])
    return integrator, np.array(headings), np.array(still), np.array(level)


@pytest.mark.skipif(not UPSIDE_DOWN.is_file(), reason=f'{UPSIDE_DOWN} not present')
def test_upside_down_imu_heading_is_the_rotation_about_base_z():
    """A real Phidgets IMU lying upside down (accelerometer z about -9.88 m/s^2), turned by
    hand about the vertical. With the mount set to upside down (roll = pi) the reading of -g is
    level (+g about base_link's z), stillness is detected and the bias estimated on it, and the
    heading is the negative of the IMU-z integral, bias-corrected."""
    t, gyro, accel = _upside_down_samples()
    assert np.mean(accel[:, 2]) == pytest.approx(-9.88, abs=0.05)
    mount = mount_rotation(math.pi, 0.0, 0.0)
    base, heading, still, level = _integrate(t, gyro, accel, mount)
    imu, imu_heading, imu_still, _ = _integrate(t, gyro, accel, None)
    assert np.mean(level) == pytest.approx(9.88, abs=0.05)        # -g read as level
    assert still.sum() > 100 and np.array_equal(still, imu_still)  # stillness detected on it
    assert math.sqrt(base.p_bias) < GyroConfig().initial_bias_sigma_rad_s / 10  # bias learnt
    assert base.bias[2] == pytest.approx(-imu.bias[2], abs=1e-12)
    # Heading about base_link's z: the negative of the rotation about the IMU's z, everywhere.
    assert heading == pytest.approx(-imu_heading, abs=1e-9)
    # ... and while moving it is the bias-corrected integral of -(IMU z rate) (the final bias:
    # the estimate moves by less than 1e-3 rad/s over the bag, 2e-4 rad over this 0.2 s).
    moving = np.flatnonzero(~still)
    a = moving[len(moving) // 2]
    b = a + 50
    assert np.all(~still[a:b + 1])
    segment = integrate_rate(t[a:b + 1], -gyro[a:b + 1, 2], bias=base.bias[2])
    assert abs(segment[-1]) > 0.05
    assert heading[b] - heading[a] == pytest.approx(segment[-1], abs=2e-4)
    assert abs(math.degrees(heading[-1])) > 90.0    # it was turned by hand: a real rotation


@pytest.mark.parametrize('mount_from', ['parameters', 'tf_static'])
def test_gyro_integrator_node_with_an_upside_down_mount(probe, mount_from):
    """Over DDS: gyro_integrator with the IMU mount upside down (mount_roll_rad = pi, or
    /tf_static's base_link -> imu_link with roll pi against zero parameters: warned) reads an IMU
    lying upside down (-g on its z) as level, learns the bias while still and integrates minus
    the IMU's z rate; its output is in base_link."""
    import time

    import rclpy
    from harness import Collector, NodeProcess, publish_until, spin_until
    from sensor_msgs.msg import Imu

    from sensing_nodes.ros.conversions import ns_to_stamp, quaternion_to_yaw, stamp_to_ns
    from sensing_nodes.ros.qos import ESTIMATE_QOS, SENSOR_QOS

    t0, step, bias = 1_700_000_000 * 1_000_000_000, 5_000_000, math.radians(0.5)

    def raw(k):
        msg = Imu()
        msg.header.stamp = ns_to_stamp(t0 + k * step)
        msg.header.frame_id = 'imu_link'
        msg.angular_velocity.z = bias + (0.5 if k >= 300 else 0.0)   # IMU z: turning +0.5 rad/s
        msg.linear_acceleration.z = -9.81                             # lying upside down
        msg.orientation_covariance[0] = -1.0
        return msg

    from rclpy.node import Node

    from sensing_nodes.core.geometry import quaternion
    from sensing_nodes.core.geometry.transform import Transform
    from sensing_nodes.ros.tf import StaticTransformBroadcaster

    pub = probe.create_publisher(Imu, '/imu/data_raw', SENSOR_QOS)
    out = Collector(probe, Imu, '/imu/data', ESTIMATE_QOS)
    params = {'use_wheel_odom': False}
    talker = Node('imu_mount_talker', context=probe.context)   # destroyed: its latch goes too
    if mount_from == 'parameters':
        params['mount_roll_rad'] = math.pi
    else:
        StaticTransformBroadcaster(talker).send(t0, 'base_link', 'imu_link', Transform(
            (0.0, 0.0, 0.05), quaternion.from_rpy(math.pi, 0.0, 0.0)))
    with NodeProcess('gyro_integrator', params=params) as node:
        first = raw(0)
        # (the mount from /tf_static applies once it has arrived: the output then is in base_link)
        assert publish_until(probe, pub, first, lambda: any(
            m.header.frame_id == 'base_link' for m in out.messages), outputs=out), node.output()
        for k in range(1, 500):
            pub.publish(raw(k))
            time.sleep(0.001)
            rclpy.spin_once(probe, timeout_sec=0)
        last = t0 + 499 * step
        assert spin_until(probe, lambda: any(stamp_to_ns(m.header.stamp) == last
                                             for m in out.messages), 20), node.output()
        assert node.alive()
        log = node.output()
    talker.destroy_node()
    if mount_from == 'tf_static':
        assert 'IMU mount from /tf_static' in log and 'disagrees with the mount parameters' in log
    pub_out = [m for m in out.messages if stamp_to_ns(m.header.stamp) == last][-1]
    out.close()
    probe.destroy_publisher(pub)
    # 1 s turning at 0.5 rad/s about the IMU's z is -0.5 rad about base_link's z once the bias
    # (learnt while still: the -g reading counted as level) is taken off.
    # bias off: -0.509
    assert quaternion_to_yaw(pub_out.orientation) == pytest.approx(-0.5, abs=0.004)
    assert pub_out.header.frame_id == 'base_link'
    assert pub_out.linear_acceleration.z == pytest.approx(9.81)
