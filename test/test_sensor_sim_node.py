"""The sensor_sim node over real DDS: topics at their rates (counted over simulated time), the
same numbers as the batch simulation, /cmd_vel following, bad input and bad parameters."""

import math

import numpy as np
import pytest
import yaml
from harness import REPO, Collector, NodeProcess, run_to_exit, spin_until

from sensing_nodes.core.sim import simulator as sim
from sensing_nodes.core.sim.world import load_world
from sensing_nodes.ros.sim_robot import NodeSettings

SECOND = 10**9
START = sim.SimParams().start_ns


def stamp_ns(msg) -> int:
    t = msg.header.stamp if hasattr(msg, 'header') else msg.clock
    return t.sec * SECOND + t.nanosec


def test_node_settings_defaults_equal_config_file():
    text = (REPO / 'config' / 'sensor_sim.yaml').read_text()
    values = yaml.safe_load(text)['sensor_sim']['ros__parameters']
    for name, f in NodeSettings.__dataclass_fields__.items():
        assert values[name] == f.default, name


@pytest.fixture(scope='module')
def live_run(probe):
    """Messages of a 6 s (simulated) run at 3x real time with seed 9; the node exits by itself."""
    from nav_msgs.msg import Odometry
    from rosgraph_msgs.msg import Clock
    from sensor_msgs.msg import Imu, JointState, LaserScan
    from tf2_msgs.msg import TFMessage

    from sensing_nodes.ros.qos import (
        CLOCK_QOS,
        ESTIMATE_QOS,
        SENSOR_QOS,
        TF_QOS,
        TF_STATIC_READER_QOS,
    )

    collectors = {
        '/tf': Collector(probe, TFMessage, '/tf', TF_QOS),
        '/tf_static': Collector(probe, TFMessage, '/tf_static', TF_STATIC_READER_QOS),
        '/scan': Collector(probe, LaserScan, '/scan', SENSOR_QOS),
        '/imu/data_raw': Collector(probe, Imu, '/imu/data_raw', SENSOR_QOS),
        '/joint_states': Collector(probe, JointState, '/joint_states', SENSOR_QOS),
        '/ground_truth/odom': Collector(probe, Odometry, '/ground_truth/odom', ESTIMATE_QOS),
        '/clock': Collector(probe, Clock, '/clock', CLOCK_QOS),
    }
    # Simulated time starts once the probe is subscribed to every sensor topic.
    # 1x: at 3x a loaded machine's probe lost a third of the best-effort IMU samples
    params = {'real_time_factor': 1.0, 'seed': 9, 'duration_s': 6.0, 'wait_for_subscribers': 1}
    node = NodeProcess('sensor_sim', params=params)
    with node:
        assert spin_until(probe, lambda: not node.alive(), timeout=60), node.output()
        spin_until(probe, lambda: False, timeout=0.5)
        code = node.proc.returncode
    for c in collectors.values():
        c.close()
    return {k: c.messages for k, c in collectors.items()}, code, node.output()


RATES = {'/scan': 10, '/imu/data_raw': 200, '/joint_states': 50, '/ground_truth/odom': 100,
         '/clock': 100}


def test_each_topic_at_its_configured_rate_over_simulated_time(live_run):
    messages, code, output = live_run
    assert code == 0, output
    for topic, rate in RATES.items():
        stamps = np.array(sorted(stamp_ns(m) for m in messages[topic]))
        period = SECOND // rate
        assert stamps.size, topic
        if topic != '/clock':                                     # /clock was not waited for
            assert stamps[0] == START, f'{topic}: the first sample was not received'
        assert np.all((stamps - START) % period == 0), f'{topic}: stamps off the {rate} Hz grid'
        assert stamps.max() <= START + 6 * SECOND, topic           # stopped at duration_s
        window = stamps[(stamps >= START + 2 * SECOND) & (stamps < START + 5 * SECOND)]
        print(f'{topic}: {window.size} of {3 * rate} in the 3 s window')
        # exactly rate x 3 s when nothing is lost; best-effort delivery may lose a few under load,
        # and /clock keeps the last sample only (CLOCK_QOS): a reader that falls behind skips some
        least = 0.5 if topic == '/clock' else 0.9
        assert least * 3 * rate <= window.size <= 3 * rate, (topic, window.size)
        assert len(np.unique(window)) == window.size, f'{topic}: duplicate stamps'


def test_live_messages_are_the_batch_simulation_numbers(live_run):
    messages, _, _ = live_run
    world = load_world(REPO / 'config' / 'default_world.yaml')
    run = sim.simulate(sim.SimParams(), world, 6.0, seed=9)
    scan_index = {t: i for i, t in enumerate(run.scan_t.tolist())}
    scans = messages['/scan']
    assert len(scans) >= 40
    for msg in scans:
        np.testing.assert_array_equal(np.asarray(msg.ranges, dtype=np.float32),
                                      run.scan_ranges[scan_index[stamp_ns(msg)]])
    assert scans[0].header.frame_id == 'laser'
    imu_index = {t: i for i, t in enumerate(run.imu_t.tolist())}
    for msg in messages['/imu/data_raw']:
        i = imu_index[stamp_ns(msg)]
        assert msg.angular_velocity.z == run.imu_gyro[i, 2]
        assert msg.linear_acceleration.z == run.imu_accel[i, 2]
    imu = messages['/imu/data_raw'][0]
    assert imu.header.frame_id == 'imu_link' and imu.orientation_covariance[0] == -1.0
    joint_index = {t: i for i, t in enumerate(run.joint_t.tolist())}
    for msg in messages['/joint_states']:
        assert list(msg.position) == run.joint_position[joint_index[stamp_ns(msg)]].tolist()
    truth_index = {t: i for i, t in enumerate(run.truth_t.tolist())}
    for msg in messages['/ground_truth/odom']:
        i = truth_index[stamp_ns(msg)]
        assert (msg.pose.pose.position.x, msg.pose.pose.position.y) == tuple(run.truth_pose[i, :2])
    assert (msg.header.frame_id, msg.child_frame_id) == ('map', 'base_link')


def test_mounts_on_tf_static_and_truth_on_tf(live_run):
    messages, _, _ = live_run
    statics = messages['/tf_static'][-1].transforms
    mounts = {(t.header.frame_id, t.child_frame_id): t.transform for t in statics}
    assert set(mounts) == {('base_link', 'laser'), ('base_link', 'imu_link')}
    laser = mounts[('base_link', 'laser')]
    p = sim.SimParams()
    assert (laser.translation.x, laser.translation.y) == (p.laser_x_m, p.laser_y_m)
    assert 2 * math.atan2(laser.rotation.z, laser.rotation.w) == pytest.approx(p.laser_yaw_rad)
    truth = {stamp_ns(m): m for m in messages['/ground_truth/odom']}
    matched = 0
    for msg in messages['/tf']:
        for t in msg.transforms:
            assert (t.header.frame_id, t.child_frame_id) == ('map', 'base_link_truth')
            odom = truth.get(stamp_ns(t))
            if odom is not None:
                matched += 1
                assert t.transform.translation.x == odom.pose.pose.position.x
                assert t.transform.translation.y == odom.pose.pose.position.y
                assert t.transform.rotation.z == pytest.approx(odom.pose.pose.orientation.z)
    assert matched >= 0.9 * len(truth)


def last_speed(collector) -> float:
    return collector.messages[-1].twist.twist.linear.x


def test_cmd_vel_is_followed_and_non_finite_commands_are_ignored_with_a_warning(probe):
    from geometry_msgs.msg import Twist
    from nav_msgs.msg import Odometry

    from sensing_nodes.ros.qos import ESTIMATE_QOS

    truth = Collector(probe, Odometry, '/ground_truth/odom', ESTIMATE_QOS)
    cmd = probe.create_publisher(Twist, '/cmd_vel', 10)
    forward = Twist()
    forward.linear.x, forward.angular.z = 0.3, 0.2
    bad = Twist()
    bad.linear.x = math.nan
    bad.angular.z = math.inf

    def drive(msg, until, timeout):
        def step():
            cmd.publish(msg)
            return until()
        return spin_until(probe, step, timeout)

    try:
        params = {'use_cmd_vel': True, 'real_time_factor': 2.0}
        with NodeProcess('sensor_sim', params=params) as node:
            assert spin_until(probe, lambda: len(truth.messages) > 10, 30), node.output()
            assert truth.messages[-1].twist.twist.linear.x == 0.0     # no command: standing
            reached = drive(forward, lambda: last_speed(truth) >= 0.3 - 1e-9, 30)
            assert reached, node.output()
            last = truth.messages[-1]
            assert last.twist.twist.angular.z == pytest.approx(0.2)
            assert last.pose.pose.position.x > -2.5 + 0.05            # it moved from the start
            assert drive(bad, lambda: 'ignoring /cmd_vel' in node.output(), 20), node.output()
            assert node.alive()
            # the bad commands changed nothing; without commands it stops after the timeout
            assert spin_until(probe, lambda: last_speed(truth) == 0.0, 20)
            assert all(math.isfinite(m.pose.pose.position.x) for m in truth.messages)
            assert node.stop() == 0, node.output()                    # SIGINT: clean exit
    finally:
        truth.close()
        probe.destroy_publisher(cmd)


def test_bad_parameters_exit_2_naming_the_parameter_before_publishing(probe, tmp_path):
    from rosgraph_msgs.msg import Clock

    from sensing_nodes.ros.qos import CLOCK_QOS

    malformed = tmp_path / 'world.yaml'
    malformed.write_text('polygons: [[[0, 0], [1, 1]]]\n')
    clock = Collector(probe, Clock, '/clock', CLOCK_QOS)
    cases = [
        (['-p', 'wheel_radius_m:=-0.05'], 'wheel_radius_m'),
        (['-p', 'scan_beams:=0'], 'scan_beams'),
        (['-p', 'range_min_m:=8.0', '-p', 'range_max_m:=8.0'], 'range_min_m'),
        (['-p', 'world_file:=/nonexistent/world.yaml'], 'world_file'),
        (['-p', f'world_file:={malformed}'], 'world_file'),
    ]
    try:
        for args, name in cases:
            result = run_to_exit('sensor_sim', ['--ros-args', *args])
            assert result.returncode == 2, (args, result.stdout, result.stderr)
            assert name in result.stderr, (args, result.stderr)
        spin_until(probe, lambda: False, 0.5)
        assert clock.messages == []
    finally:
        clock.close()


def test_paced_mode_waits_for_the_graph_and_loses_no_scan(probe):
    from nav_msgs.msg import Odometry
    from sensor_msgs.msg import LaserScan

    from sensing_nodes.ros.qos import ESTIMATE_QOS, SENSOR_QOS

    answer = probe.create_publisher(Odometry, '/pace_answer', ESTIMATE_QOS)
    scans = []

    def on_scan(msg):                      # a one-node "graph": answer each scan with its stamp
        scans.append(stamp_ns(msg))
        out = Odometry()
        out.header.stamp = msg.header.stamp
        answer.publish(out)

    sub = probe.create_subscription(LaserScan, '/scan', on_scan, SENSOR_QOS)
    try:
        params = {'pace_topic': '/pace_answer', 'pace_timeout_s': 60.0, 'duration_s': 5.0,
                  'real_time_factor': 1000.0}
        with NodeProcess('sensor_sim', params=params) as node:
            assert spin_until(probe, lambda: not node.alive(), timeout=60), node.output()
            assert node.proc.returncode == 0
            assert 'no answer' not in node.output()
        # every scan from the first to the last, none lost, none early (the one stamped at
        # 5 s ends its sweep at 5.1 s, after the run)
        assert scans == [START + k * SECOND // 10 for k in range(50)]
    finally:
        probe.destroy_subscription(sub)
        probe.destroy_publisher(answer)


def test_paced_mode_goes_on_after_the_timeout_with_a_warning(probe):
    from nav_msgs.msg import Odometry
    from sensor_msgs.msg import LaserScan

    from sensing_nodes.ros.qos import ESTIMATE_QOS, SENSOR_QOS

    silent = probe.create_publisher(Odometry, '/pace_silent', ESTIMATE_QOS)
    scans = Collector(probe, LaserScan, '/scan', SENSOR_QOS)
    try:
        params = {'pace_topic': '/pace_silent', 'pace_timeout_s': 0.2, 'duration_s': 0.5,
                  'real_time_factor': 1000.0}
        with NodeProcess('sensor_sim', params=params) as node:
            assert spin_until(probe, lambda: not node.alive(), timeout=60), node.output()
            assert node.proc.returncode == 0
            assert 'no answer on /pace_silent' in node.output()
        assert len(scans.messages) == 5          # stamped 0 .. 0.4 s: each sweep ends by 0.5 s
    finally:
        scans.close()
        probe.destroy_publisher(silent)
