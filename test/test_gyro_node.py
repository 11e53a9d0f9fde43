"""gyro_integrator over real DDS: the published Imu equals the core's, bias estimation and the
wheel-odometry veto, bad input keeps the node alive, the calibration service, bad parameters."""

import math
import time

import numpy as np
import pytest
import rclpy
from harness import REPO, Collector, NodeProcess, publish_until, run_to_exit, spin_until
from nav_msgs.msg import Odometry
from sensor_msgs.msg import Imu
from std_srvs.srv import Trigger

from sensing_nodes.core.gyro import GyroConfig, GyroIntegrator
from sensing_nodes.ros.conversions import (
    make_odometry,
    ns_to_stamp,
    quaternion_to_yaw,
    stamp_to_ns,
)
from sensing_nodes.ros.qos import ESTIMATE_QOS, SENSOR_QOS

T0 = 1_700_000_000 * 1_000_000_000
STEP = 5_000_000                # 200 Hz
BIAS = math.radians(0.5)


def imu(t_ns, rate_z, accel=(0.0, 0.0, 9.81), rate_xy=(0.001, -0.002)):
    msg = Imu()
    msg.header.stamp = ns_to_stamp(t_ns)
    msg.header.frame_id = 'imu_link'
    msg.angular_velocity.x, msg.angular_velocity.y = rate_xy
    msg.angular_velocity.z = float(rate_z)
    msg.linear_acceleration.x, msg.linear_acceleration.y, msg.linear_acceleration.z = accel
    msg.linear_acceleration_covariance[0] = 4e-4
    msg.orientation_covariance[0] = -1.0        # raw IMU: no orientation
    return msg


def still_then_turn(n_still=300, n_turn=200, t0=T0):
    """1.5 s still with the bias, then 1 s turning at 0.5 rad/s (plus the bias)."""
    return [(t0 + k * STEP, BIAS if k < n_still else BIAS + 0.5) for k in range(n_still + n_turn)]


def expected(samples, config=None):
    gi = GyroIntegrator(config or GyroConfig())
    for t, rate in samples:
        gi.update(t, (0.001, -0.002, rate), (0.0, 0.0, 9.81))
    return gi


@pytest.fixture
def imu_pub(probe):
    pub = probe.create_publisher(Imu, '/imu/data_raw', SENSOR_QOS)
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
    for msg in messages:
        pub.publish(msg)
        time.sleep(0.002)
        for _ in range(3):      # drain the outputs, so the probe's own queue never overflows
            rclpy.spin_once(probe, timeout_sec=0)


def wait_stamp(probe, out, stamp):
    return spin_until(
        probe, lambda: out.messages and stamp_to_ns(out.messages[-1].header.stamp) == stamp, 20
    )


def test_imu_over_dds_with_bias_estimation_and_bad_input(probe, imu_pub):
    samples = still_then_turn()
    msgs = [imu(t, r) for t, r in samples]
    t_bad = samples[350][0]
    bad = [imu(t_bad + 1, math.nan), imu(t_bad + 2, 0.1, accel=(0.0, math.inf, 9.8)),
           imu(samples[350][0], samples[350][1])]             # duplicate stamp
    out = Collector(probe, Imu, '/imu/data', ESTIMATE_QOS)
    with NodeProcess('gyro_integrator', params={'use_wheel_odom': False}) as node:
        assert spin_until(probe, lambda: out._sub.get_publisher_count() > 0, 20)
        prime(probe, imu_pub, out, msgs[0], node)
        send(probe, imu_pub, msgs[1:351] + bad + msgs[351:])
        assert wait_stamp(probe, out, samples[-1][0]), node.output()
        log = node.output()
        assert node.alive(), log
    out.close()
    stamps = [stamp_to_ns(m.header.stamp) for m in out.messages]
    assert stamps == sorted(stamps)
    assert not set(stamps) & {t_bad + 1, t_bad + 2}
    received = [s for s in samples if s[0] in set(stamps)]
    assert len(received) >= 0.95 * len(samples)
    gi = expected(received)
    last = out.messages[-1]
    assert quaternion_to_yaw(last.orientation) == pytest.approx(gi.heading, abs=1e-9)
    assert last.orientation_covariance[8] == pytest.approx(gi.heading_variance, rel=1e-9)
    assert last.orientation_covariance[0] == 0.0 and last.orientation_covariance[4] == 0.0
    # The bias was learnt in the still start: the turn integrates to 0.5 rad/s x 1 s.
    assert quaternion_to_yaw(last.orientation) == pytest.approx(0.5, abs=2e-3)
    assert last.angular_velocity.z == pytest.approx(0.5, abs=1e-6)
    assert (last.angular_velocity.x, last.angular_velocity.y) == pytest.approx(
        (0.0, 0.0), abs=1e-6
    )
    assert last.angular_velocity_covariance[8] == pytest.approx(gi.rate_variance(), rel=1e-9)
    assert last.linear_acceleration.z == 9.81 and last.linear_acceleration_covariance[0] == 4e-4
    assert last.header.frame_id == 'imu_link'
    assert '(non_finite)' in log and '(repeated_stamp)' in log


def test_wheel_motion_veto_over_dds_and_calibration_service(probe, imu_pub):
    """A steady 1 deg/s turn looks still to the IMU; /wheel/odom says the robot turns, so the
    rate is integrated, not absorbed. Then estimation is re-armed by the service."""
    odom_pub = probe.create_publisher(Odometry, '/wheel/odom', ESTIMATE_QOS)
    client = probe.create_client(Trigger, '/gyro_integrator/calibrate')
    out = Collector(probe, Imu, '/imu/data', ESTIMATE_QOS)
    turn = math.radians(1.0)
    samples = [(T0 + k * STEP, BIAS + turn) for k in range(400)]      # 2 s
    with NodeProcess(
        'gyro_integrator', params_file=REPO / 'config' / 'gyro_integrator.yaml'
    ) as node:
        assert spin_until(probe, lambda: out._sub.get_publisher_count() > 0
                          and odom_pub.get_subscription_count() > 0, 20)
        odom_pub.publish(make_odometry(T0, 'odom', 'base_link', (0.0, 0.0, 0.0), np.eye(3),
                                       twist=(0.0, 0.0, turn)))
        prime(probe, imu_pub, out, imu(*samples[0]), node)
        for k, (t, r) in enumerate(samples[1:], start=1):
            if k % 4 == 0 or k == len(samples) - 1:      # 50 Hz wheel odometry reporting the turn
                odom_pub.publish(make_odometry(t, 'odom', 'base_link', (0.0, 0.0, 0.0), np.eye(3),
                                               twist=(0.0, 0.0, turn)))
            send(probe, imu_pub, [imu(t, r)])
        assert wait_stamp(probe, out, samples[-1][0]), node.output()
        moving = out.messages[-1]
        # Not still: nothing was absorbed into the bias, the raw rate is integrated (2 s).
        assert moving.angular_velocity.z == pytest.approx(BIAS + turn, abs=1e-9)
        assert quaternion_to_yaw(moving.orientation) == pytest.approx(
            2.0 * (BIAS + turn), rel=1e-2
        )
        # The robot stops (wheels say so) and the service re-arms calibration.
        assert client.wait_for_service(timeout_sec=20)
        future = client.call_async(Trigger.Request())
        rclpy.spin_until_future_complete(probe, future, timeout_sec=20)
        assert future.result().success and 'calibration' in future.result().message
        still = [(samples[-1][0] + k * STEP, BIAS) for k in range(1, 301)]
        for k, (t, r) in enumerate(still):
            if k % 4 == 0:
                odom_pub.publish(make_odometry(t, 'odom', 'base_link', (0.0, 0.0, 0.0), np.eye(3)))
            send(probe, imu_pub, [imu(t, r)])
        assert wait_stamp(probe, out, still[-1][0]), node.output()
        log = node.output()
        assert node.alive(), log
    probe.destroy_publisher(odom_pub)
    probe.destroy_client(client)
    out.close()
    assert out.messages[-1].angular_velocity.z == pytest.approx(0.0, abs=1e-6)
    assert 'calibration armed' in log


def test_time_backwards_resets_the_heading(probe, imu_pub):
    samples = [(T0 + k * STEP, 0.2) for k in range(200)]
    out = Collector(probe, Imu, '/imu/data', ESTIMATE_QOS)
    with NodeProcess('gyro_integrator', params={'bias_estimation': False}) as node:
        assert spin_until(probe, lambda: out._sub.get_publisher_count() > 0, 20)
        prime(probe, imu_pub, out, imu(*samples[0]), node)
        send(probe, imu_pub, [imu(t, r) for t, r in samples[1:]])
        assert wait_stamp(probe, out, samples[-1][0])
        assert quaternion_to_yaw(out.messages[-1].orientation) == pytest.approx(
            0.2 * 0.995, abs=1e-9
        )
        send(probe, imu_pub, [imu(t, r) for t, r in samples[:100]])
        assert wait_stamp(probe, out, samples[99][0])
        log = node.output()
        assert node.alive(), log
    out.close()
    assert 'time went backwards' in log
    assert quaternion_to_yaw(out.messages[-1].orientation) == pytest.approx(0.2 * 0.495, abs=1e-9)


@pytest.mark.parametrize('args, name', [
    (['-p', 'stillness_window_s:=0.0'], 'stillness_window_s'),
    (['-p', 'gyro_noise_density:=-1.0'], 'gyro_noise_density'),
    (['-p', 'max_gap_s:=0.0'], 'max_gap_s'),
])
def test_bad_parameters_exit_2_naming_the_parameter(args, name):
    result = run_to_exit('gyro_integrator', ['--ros-args', *args], timeout=30)
    assert result.returncode == 2, result.stdout + result.stderr
    assert f"parameter '{name}'" in result.stderr


def test_calibrated_scale_factor_and_bias_correct_the_heading(probe):
    """gyro_integrator's processor with the gyro_scale_error and initial_bias_z_rad_s that
    sensing_calibrate writes: on a simulated route whose gyro reads 2 % too much, the heading
    error against the truth drops several-fold; without them it is the scale error's."""
    from rclpy.node import Node

    from sensing_nodes.core.geometry.imu_mount import mount_rotation
    from sensing_nodes.core.sim.simulator import SimParams, simulate
    from sensing_nodes.core.sim.world import load_world
    from sensing_nodes.nodes.gyro_integrator import GyroIntegratorProcessor, ImuMount
    from sensing_nodes.paths import config_file
    from sensing_nodes.ros.diagnostics import Diagnostics
    from sensing_nodes.ros.logging import ThrottledWarnings

    params = SimParams(gyro_scale_error=0.02)
    run = simulate(params, load_world(config_file('default_world.yaml')), 130.0, seed=3)
    truth = run.truth_at(run.imu_t)
    node = Node('scale_test', context=probe.context)
    try:
        def rms_heading_error(scale_error: float, initial_bias: float) -> float:
            processor = GyroIntegratorProcessor(
                GyroConfig(initial_bias_z_rad_s=initial_bias),
                ImuMount(mount_rotation(0.0, 0.0, 0.0), 'base_link', ''), scale_error, True,
                False, Diagnostics(node), ThrottledWarnings(node), node.get_logger())
            errors = []
            for i, t in enumerate(run.imu_t.tolist()):
                msg = imu(t, float(run.imu_gyro[i, 2]), tuple(run.imu_accel[i].tolist()),
                          tuple(run.imu_gyro[i, :2].tolist()))
                processor.on_imu(msg)
                yaw = processor.integrator.yaw
                errors.append(math.remainder(yaw - (truth[i, 2] - truth[0, 2]), 2 * math.pi))
            return math.sqrt(float(np.mean(np.square(errors))))

        raw = rms_heading_error(0.0, 0.0)
        calibrated = rms_heading_error(0.02, params.gyro_bias_rad_s)
    finally:
        node.destroy_node()
    print(f'RMS heading error: {math.degrees(raw):.3f} deg raw, '
          f'{math.degrees(calibrated):.3f} deg calibrated')
    assert raw > math.radians(1.0)
    assert calibrated * 5 < raw
