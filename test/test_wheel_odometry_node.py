"""wheel_odometry over real DDS: the published odometry equals the core's, bad input keeps the
node alive with a warning, the reset service, and bad parameters."""

import math
import time

import numpy as np
import pytest
import rclpy
from harness import REPO, Collector, NodeProcess, publish_until, run_to_exit, spin_until
from nav_msgs.msg import Odometry
from sensor_msgs.msg import JointState
from std_srvs.srv import Trigger

from sensing_nodes.core.wheel_odometry import WheelOdometry, WheelOdometryConfig
from sensing_nodes.ros.conversions import (
    ns_to_stamp,
    odometry_pose,
    odometry_twist,
    stamp_to_ns,
)
from sensing_nodes.ros.qos import ESTIMATE_QOS, SENSOR_QOS

JOINTS = ('left_wheel_joint', 'right_wheel_joint')
T0 = 1_700_000_000 * 1_000_000_000
STEP = 20_000_000


def joint_state(t_ns, names, positions, velocities=()):
    msg = JointState()
    msg.header.stamp = ns_to_stamp(t_ns)
    msg.name = list(names)
    msg.position = [float(p) for p in positions]
    msg.velocity = [float(v) for v in velocities]
    return msg


def good_inputs(n=120, t0=T0):
    """An S-curve: right wheel ahead, then left wheel ahead (rad)."""
    out = []
    left = right = 0.0
    for k in range(n):
        out.append((t0 + k * STEP, list(JOINTS), [left, right]))
        left += 0.30 if k < n // 2 else 0.36
        right += 0.36 if k < n // 2 else 0.30
    return out


def expected_odometry(inputs, config=None):
    odo = WheelOdometry(config or WheelOdometryConfig())
    for t, names, pos in inputs:
        odo.update(t, names, pos, [], JOINTS)
    return odo


@pytest.fixture
def joint_pub(probe):
    pub = probe.create_publisher(JointState, '/joint_states', SENSOR_QOS)
    yield pub
    probe.destroy_publisher(pub)


def prime(probe, pub, out, msg, node):
    """Publish the first message until its output comes back (harness.publish_until)."""
    stamp = stamp_to_ns(msg.header.stamp)
    answered = publish_until(
        probe, pub, msg, lambda: any(stamp_to_ns(m.header.stamp) == stamp for m in out.messages),
        outputs=out)
    assert answered, 'the node never answered:\n' + node.output()


def send(probe, pub, messages):
    assert spin_until(probe, lambda: pub.get_subscription_count() > 0, 20)
    for msg in messages:
        pub.publish(msg)
        time.sleep(0.002)          # paced like a live driver; best effort must not overrun
        for _ in range(3):         # drain the outputs, so the probe's own queue never overflows
            rclpy.spin_once(probe, timeout_sec=0)


def test_odometry_over_dds_with_bad_input_in_between(probe, joint_pub):
    good = good_inputs()
    msgs = [joint_state(t, n, p) for t, n, p in good]
    t_bad = good[40][0]
    bad = [
        joint_state(t_bad + 1, JOINTS, [math.nan, 1.0]),                    # NaN position
        joint_state(t_bad + 2, ['left_wheel_joint', 'caster'], [1.0, 2.0]),  # missing joint
        joint_state(t_bad + 3, JOINTS, [1.0, 2.0, 3.0]),                     # length mismatch
        joint_state(good[40][0], JOINTS, good[40][2]),                       # duplicate stamp
    ]
    out = Collector(probe, Odometry, '/wheel/odom', ESTIMATE_QOS)
    with NodeProcess(
        'wheel_odometry', params={'wheel_radius_m': 0.05, 'wheel_separation_m': 0.3}
    ) as node:
        assert spin_until(probe, lambda: out._sub.get_publisher_count() > 0, 20)
        prime(probe, joint_pub, out, msgs[0], node)
        send(probe, joint_pub, msgs[1:41] + bad + msgs[41:])
        spin_until(
            probe,
            lambda: out.messages and stamp_to_ns(out.messages[-1].header.stamp) == good[-1][0],
            20,
        )
        log = node.output()
        assert node.alive(), log
    out.close()
    stamps = [stamp_to_ns(m.header.stamp) for m in out.messages]
    assert stamps == sorted(stamps) and stamps[-1] == good[-1][0]
    assert not set(stamps) & {t_bad + 1, t_bad + 2, t_bad + 3}
    # Best effort may lose a sample; the node's output must equal the core fed what arrived.
    received = [g for g in good if g[0] in set(stamps)]
    assert len(received) >= 0.95 * len(good)
    expected = expected_odometry(received)
    pose, cov = odometry_pose(out.messages[-1])
    assert pose == pytest.approx(expected.pose, abs=1e-9)
    np.testing.assert_allclose(cov, expected.covariance, rtol=1e-9, atol=1e-18)
    twist, twist_cov = odometry_twist(out.messages[-1])
    assert twist == pytest.approx(expected.twist, rel=1e-9)
    assert twist[0] == pytest.approx(0.5 * (0.36 + 0.30) * 0.05 / 0.02, rel=1e-9)
    assert (
        out.messages[-1].header.frame_id == 'odom'
        and out.messages[-1].child_frame_id == 'base_link'
    )
    assert cov[0, 0] > 0 and cov[2, 2] > 0
    for key in ('non_finite', 'missing_joint', 'length_mismatch', 'repeated_stamp'):
        assert f'({key})' in log, log


def test_time_backwards_resets_and_reset_service(probe, joint_pub):
    good = good_inputs(60)
    out = Collector(probe, Odometry, '/wheel/odom', ESTIMATE_QOS)
    client = probe.create_client(Trigger, '/wheel_odometry/reset')
    with NodeProcess('wheel_odometry') as node:
        assert spin_until(probe, lambda: out._sub.get_publisher_count() > 0, 20)
        msgs = [joint_state(t, n, p) for t, n, p in good]
        prime(probe, joint_pub, out, msgs[0], node)
        send(probe, joint_pub, msgs[1:])
        spin_until(
            probe,
            lambda: out.messages and stamp_to_ns(out.messages[-1].header.stamp) == good[-1][0],
            20,
        )
        assert odometry_pose(out.messages[-1])[0][0] > 0.5
        # A looping bag: the same stamps again, from the start.
        count = len(out.messages)
        send(probe, joint_pub, [joint_state(t, n, p) for t, n, p in good[:30]])
        spin_until(probe, lambda: stamp_to_ns(out.messages[-1].header.stamp) == good[29][0], 20)
        after_loop = out.messages[count:]
        assert odometry_pose(after_loop[0])[0] == pytest.approx((0.0, 0.0, 0.0), abs=1e-12)
        assert odometry_pose(after_loop[-1])[0] == pytest.approx(
            expected_odometry(good[:30]).pose, abs=1e-9)
        # Reset service: the pose goes back to the origin, the next step adds only its increment.
        assert client.wait_for_service(timeout_sec=20)
        future = client.call_async(Trigger.Request())
        rclpy.spin_until_future_complete(probe, future, timeout_sec=20)
        assert future.result().success and 'reset' in future.result().message
        t_next = good[30][0]
        send(probe, joint_pub, [joint_state(t_next, JOINTS, good[30][2])])
        spin_until(probe, lambda: stamp_to_ns(out.messages[-1].header.stamp) == t_next, 20)
        pose, cov = odometry_pose(out.messages[-1])
        step = expected_odometry(good[29:31])
        assert pose == pytest.approx(step.pose, abs=1e-12)
        np.testing.assert_allclose(cov, step.covariance, rtol=1e-9, atol=1e-18)
        log = node.output()
        assert node.alive(), log
    probe.destroy_client(client)
    out.close()
    assert 'time went backwards' in log and 'pose reset' in log


def test_params_file_and_velocity_only_driver(probe, joint_pub):
    out = Collector(probe, Odometry, '/wheel/odom', ESTIMATE_QOS)
    config = REPO / 'config' / 'wheel_odometry.yaml'
    with NodeProcess('wheel_odometry', params_file=config) as node:
        assert spin_until(probe, lambda: out._sub.get_publisher_count() > 0, 20)
        msgs = [joint_state(T0 + k * STEP, ['caster', 'right_wheel_joint', 'left_wheel_joint'],
                            [], [0.0, 4.0, 4.0]) for k in range(51)]
        prime(probe, joint_pub, out, msgs[0], node)
        send(probe, joint_pub, msgs[1:])
        spin_until(
            probe,
            lambda: out.messages and stamp_to_ns(out.messages[-1].header.stamp) == T0 + 50 * STEP,
            20,
        )
        assert node.alive(), node.output()
    out.close()
    pose, _ = odometry_pose(out.messages[-1])
    # 4 rad/s for 1 s; the config's calibrated right wheel (x 1.01) curves the path to the left.
    ds_l, ds_r = 4.0 * 0.05, 4.0 * 0.05 * 1.01
    assert pose[2] == pytest.approx((ds_r - ds_l) / 0.30, rel=1e-9)
    assert math.hypot(pose[0], pose[1]) == pytest.approx(0.5 * (ds_l + ds_r), rel=1e-4)


@pytest.mark.parametrize('args, name', [
    (['-p', 'wheel_radius_m:=0.0'], 'wheel_radius_m'),
    (['-p', 'wheel_separation_m:=-0.3'], 'wheel_separation_m'),
    (['-p', 'right_wheel_joint:=left_wheel_joint'], 'right_wheel_joint'),
    (['-p', 'integration_method:=rk4'], 'integration_method'),
])
def test_bad_parameters_exit_2_naming_the_parameter(args, name):
    result = run_to_exit('wheel_odometry', ['--ros-args', *args], timeout=30)
    assert result.returncode == 2, result.stdout + result.stderr
    assert f"parameter '{name}'" in result.stderr


def test_static_covariance_override(probe, joint_pub):
    good = good_inputs(20)
    msgs = [joint_state(t, n, p) for t, n, p in good]
    out = Collector(probe, Odometry, '/wheel/odom', ESTIMATE_QOS)
    params = {'covariance_mode': 'static', 'static_pose_variances': [0.01, 0.02, 0.03],
              'static_twist_variances': [0.1, 0.2, 0.3], 'integration_method': 'euler'}
    with NodeProcess('wheel_odometry', params=params) as node:
        assert spin_until(probe, lambda: out._sub.get_publisher_count() > 0, 20)
        prime(probe, joint_pub, out, msgs[0], node)
        send(probe, joint_pub, msgs[1:])
        spin_until(probe, lambda: stamp_to_ns(out.messages[-1].header.stamp) == good[-1][0], 20)
        assert node.alive(), node.output()
    out.close()
    pose, cov = odometry_pose(out.messages[-1])
    _, twist_cov = odometry_twist(out.messages[-1])
    np.testing.assert_array_equal(cov, np.diag([0.01, 0.02, 0.03]))
    np.testing.assert_array_equal(twist_cov, np.diag([0.1, 0.2, 0.3]))
    received = [g for g in good if g[0] in {stamp_to_ns(m.header.stamp) for m in out.messages}]
    euler = expected_odometry(received, WheelOdometryConfig(method='euler'))
    assert pose == pytest.approx(euler.pose, abs=1e-9)
    assert pose != pytest.approx(expected_odometry(received).pose, abs=1e-6)
