"""icp_matcher over real DDS: scans of the default room along a known path, odometry with a
scale error as the initial guess; the output follows the truth, falls back without a jump on a
blank scan, counts it on /diagnostics, and bad parameters exit with 2."""

import math
import time

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray
from harness import Collector, NodeProcess, run_to_exit, spin_until
from nav_msgs.msg import Odometry
from sensor_msgs.msg import LaserScan

from sensing_nodes.core.geometry.scan import beam_angles
from sensing_nodes.core.geometry.se2 import between, compose, wrap_angle
from sensing_nodes.core.sim.world import load_world, raycast
from sensing_nodes.paths import config_file
from sensing_nodes.ros.conversions import (
    float32_array,
    make_odometry,
    ns_to_stamp,
    odometry_pose,
    stamp_to_ns,
)
from sensing_nodes.ros.qos import ESTIMATE_QOS, SENSOR_QOS

T0 = 1_700_000_000 * 1_000_000_000
SCAN_DT = 100_000_000
MOUNT = (0.10, 0.0, 0.0)
BEAMS = 360
ANGLE_MIN, ANGLE_INC = -math.pi, 2 * math.pi / BEAMS
WORLD = load_world(config_file('default_world.yaml'))
ODOM_SCALE = 1.08           # the odometry overestimates every motion by 8 %


def truth(k):
    """base_link pose (map frame) at scan k: an arc south of the table."""
    return (-2.5 + 0.06 * k, -2.0 + 0.002 * k * k, 0.02 * k)


def scan_msg(k, blank=False, rng=None, mount=MOUNT):
    laser = compose(truth(k), mount)
    angles = beam_angles(ANGLE_MIN, ANGLE_INC, BEAMS)
    ranges = raycast(WORLD.segments, laser[:2], angles + laser[2])
    ranges = np.where(ranges > 8.0, np.inf, ranges + rng.normal(0.0, 0.005, BEAMS))
    if blank:
        ranges[:] = np.nan
    msg = LaserScan()
    msg.header.stamp = ns_to_stamp(T0 + k * SCAN_DT)
    msg.header.frame_id = 'laser'
    msg.angle_min, msg.angle_increment = ANGLE_MIN, ANGLE_INC
    msg.angle_max = ANGLE_MIN + ANGLE_INC * (BEAMS - 1)
    msg.range_min, msg.range_max = 0.12, 8.0
    msg.ranges = float32_array(ranges)
    return msg


def odom_msg(t_ns, k_float):
    """Odometry in its own odom frame (origin at scan 0's base pose), every motion 8 % too long."""
    k0 = int(math.floor(k_float))
    a, b = truth(k0), truth(k0 + 1)
    f = k_float - k0
    pose = (a[0] + f * (b[0] - a[0]), a[1] + f * (b[1] - a[1]), a[2] + f * (b[2] - a[2]))
    rel = between(truth(0), pose)
    biased = (rel[0] * ODOM_SCALE, rel[1] * ODOM_SCALE, rel[2] * ODOM_SCALE)
    return make_odometry(t_ns, 'odom', 'base_link', biased, np.eye(3) * 1e-4)


def reference(k):
    return between(truth(0), truth(k))


@pytest.fixture
def pubs(probe):
    scan_pub = probe.create_publisher(LaserScan, '/scan', SENSOR_QOS)
    odom_pub = probe.create_publisher(Odometry, '/wheel/odom', ESTIMATE_QOS)
    yield scan_pub, odom_pub
    probe.destroy_publisher(scan_pub)
    probe.destroy_publisher(odom_pub)


def run_sequence(probe, pubs, node, count, blank=(), odometry=True, mount=MOUNT):
    """Publish odometry (5 per scan interval, ahead of each scan) and scans 0..count-1; return
    the /scan_match/odom messages by stamp."""
    scan_pub, odom_pub = pubs
    out = Collector(probe, Odometry, '/scan_match/odom', ESTIMATE_QOS)
    rng = np.random.default_rng(0)
    assert spin_until(probe, lambda: scan_pub.get_subscription_count() > 0
                      and (odom_pub.get_subscription_count() > 0 or not odometry), 20), \
        node.output()
    # The node skips a repeated stamp without answering: its writer must reach our reader
    # before the first scan goes out (discovery is not symmetric in time).
    assert spin_until(probe, out.matched, 20), node.output()
    spin_until(probe, lambda: False, 0.5)
    first = scan_msg(0, rng=rng, mount=mount)
    # The odometry runs 1.4 scan intervals ahead of each scan: the node takes /odom and /scan
    # from two readers, and under load a round's odometry can be taken after its scan; the
    # previous round's then still covers the scan (within odom_max_extrapolation_s).
    for j in range(8):
        odom_pub.publish(odom_msg(T0 + j * SCAN_DT // 5, j / 5))
    deadline = time.monotonic() + 20
    while not out.messages and time.monotonic() < deadline:
        scan_pub.publish(first)            # best effort: repeat until the reader has matched
        spin_until(probe, lambda: bool(out.messages), 0.2)
    assert out.messages, 'the node never answered:\n' + node.output()
    for k in range(1, count):
        for j in range(5):
            sub = (k - 1) + (j + 1) / 5 + 1.4     # up to 1.4 scans ahead (above)
            odom_pub.publish(odom_msg(T0 + int(sub * SCAN_DT), sub))
        spin_until(probe, lambda: False, 0.01)
        scan_pub.publish(scan_msg(k, blank=k in blank, rng=rng, mount=mount))
        spin_until(probe, lambda: len({stamp_to_ns(m.header.stamp) for m in out.messages}) > k, 5)
    out.wait_for(count, 10)
    by_stamp = {stamp_to_ns(m.header.stamp): m for m in out.messages}
    out.close()
    return by_stamp


def pose_error(pose, ref):
    return math.hypot(pose[0] - ref[0], pose[1] - ref[1]), abs(wrap_angle(pose[2] - ref[2]))


def diagnostic_values(collector):
    """The newest value of every key the node reported on /diagnostics."""
    return {kv.key: kv.value for d in collector.messages for s in d.status for kv in s.values}


@pytest.mark.parametrize('mode', ['local_map', 'keyframe'])
def test_follows_the_truth_with_odometry_initial_guess(probe, pubs, mode):
    count = 25
    diagnostics = Collector(probe, DiagnosticArray, '/diagnostics', 10)
    with NodeProcess('icp_matcher', params_file=config_file('icp_matcher.yaml'),
                     params={'mode': mode}) as node:
        out = run_sequence(probe, pubs, node, count)
        spin_until(probe, lambda: diagnostic_values(diagnostics).get('matched') == str(count - 1),
                   5)
        assert node.alive(), node.output()
    values = diagnostic_values(diagnostics)
    diagnostics.close()
    assert values['mode'] == mode
    assert values['predicted_by_odometry'] == str(count - 1)      # every step, none by default
    assert values['matched'] == str(count - 1)
    assert 'fallback' not in values
    assert sorted(out) == [T0 + k * SCAN_DT for k in range(count)]      # scan stamps, each once
    final = out[T0 + (count - 1) * SCAN_DT]
    pose, cov = odometry_pose(final)
    ref = reference(count - 1)
    trans, rot = pose_error(pose, ref)
    odom_trans, _ = pose_error(odometry_pose(odom_msg(0, count - 1))[0], ref)
    assert odom_trans > 0.05                  # the guess alone would be this far off ...
    assert trans < 0.01 and rot < math.radians(0.3), (pose, ref)   # ... the match is not
    assert final.header.frame_id == 'odom' and final.child_frame_id == 'base_link'
    assert np.all(np.linalg.eigvalsh(cov) > 0) and cov[0, 0] < 1e-3
    # Twist = change of pose over the scan interval, in base_link.
    prev_pose, _ = odometry_pose(out[T0 + (count - 2) * SCAN_DT])
    delta = between(prev_pose, pose)
    assert final.twist.twist.linear.x == pytest.approx(delta[0] / 0.1, rel=1e-6, abs=1e-9)
    assert final.twist.twist.angular.z == pytest.approx(delta[2] / 0.1, rel=1e-6, abs=1e-9)
    assert final.twist.twist.angular.z == pytest.approx(0.2, abs=0.03)     # 0.02 rad per 0.1 s


def test_blank_scan_falls_back_to_the_prediction_without_a_jump(probe, pubs):
    count, blank = 16, 8
    diagnostics = Collector(probe, DiagnosticArray, '/diagnostics', 10)
    with NodeProcess('icp_matcher', params_file=config_file('icp_matcher.yaml')) as node:
        out = run_sequence(probe, pubs, node, count, blank={blank})
        spin_until(
            probe,
            lambda: any(
                kv.key == 'fallback'
                for d in diagnostics.messages
                for s in d.status
                for kv in s.values
            ),
            5,
        )
        assert node.alive()
        log = node.output()
    diagnostics.close()
    assert sorted(out) == [T0 + k * SCAN_DT for k in range(count)]
    poses = [odometry_pose(out[T0 + k * SCAN_DT]) for k in range(count)]
    # The blank scan's pose is the odometry prediction: close to the truth, covariance inflated.
    blank_pose, blank_cov = poses[blank]
    before_cov = poses[blank - 1][1]
    assert pose_error(blank_pose, reference(blank))[0] < 0.03
    assert blank_cov[0, 0] > before_cov[0, 0] + 0.05 ** 2 * 0.9
    # No jump anywhere: each step is the true step within 2 cm.
    for k in range(1, count):
        step = between(poses[k - 1][0], poses[k][0])
        true_step = between(reference(k - 1), reference(k))
        assert pose_error(step, true_step)[0] < 0.02, k
    # Matching resumes after the blank scan and the end is on the truth.
    assert pose_error(poses[-1][0], reference(count - 1))[0] < 0.03
    values = diagnostic_values(diagnostics)
    assert int(values['fallback']) == 1
    assert int(values['too_few_points']) == 1
    assert 'match failed' in log
    assert 'rate limits off' not in log                 # on by default


def test_constant_velocity_model_without_odometry(probe, pubs):
    count = 20
    with NodeProcess('icp_matcher', params={'odom_topic': ''}) as node:
        out = run_sequence(probe, pubs, node, count, odometry=False)
        assert node.alive()
    pose, _ = odometry_pose(out[T0 + (count - 1) * SCAN_DT])
    trans, rot = pose_error(pose, reference(count - 1))
    assert trans < 0.01 and rot < math.radians(0.3)


def test_rate_limits_off_are_said_once_at_start_up():
    """For stamps whose time is assumed (carmen_to_bag's rebuilt time base): one line."""
    with NodeProcess('icp_matcher', params={'rate_limits': False}) as node:
        started = time.monotonic()
        while 'rate limits off' not in node.output() and time.monotonic() - started < 20:
            time.sleep(0.1)
        time.sleep(0.5)                                  # a second such line would be out now
        assert node.alive(), node.output()
        log = node.output()
    assert log.count('rate limits off (rate_limits: false): max_speed_m_s and '
                     'max_yaw_rate_rad_s do not bound the matches') == 1, log


@pytest.mark.parametrize('args, name', [
    (['-p', 'method:=plane'], 'method'),
    (['-p', 'robust:=ransac'], 'robust'),
    (['-p', 'search:=octree'], 'search'),
    (['-p', 'keyframe_distance_m:=-1.0'], 'keyframe_distance_m'),
    (['-p', 'max_iterations:=0'], 'max_iterations'),
    (['-p', 'odom_delay_s:=1.5'], 'odom_delay_s'),
    (['-p', 'odom_delay_s:=.nan'], 'odom_delay_s'),
    (['-p', 'mode:=grid'], 'mode'),
    (['-p', 'map_cell_m:=0.0'], 'map_cell_m'),
    (['-p', 'max_speed_m_s:=0.0'], 'max_speed_m_s'),
])
def test_bad_parameters_exit_with_2(args, name):
    result = run_to_exit('icp_matcher', ['--ros-args', *args])
    assert result.returncode == 2, result.stderr + result.stdout
    assert name in result.stderr + result.stdout


def test_bad_scans_and_backwards_time_keep_the_node_running(probe, pubs):
    scan_pub, _ = pubs
    diagnostics = Collector(probe, DiagnosticArray, '/diagnostics', 10)
    with NodeProcess('icp_matcher', params={'odom_topic': ''}) as node:
        out = run_sequence(probe, pubs, node, 6, odometry=False)
        rng = np.random.default_rng(1)
        broken = scan_msg(6, rng=rng)
        broken.angle_increment = math.nan             # every beam angle NaN: no valid point
        backwards_sweep = scan_msg(7, rng=rng)
        backwards_sweep.time_increment = -1.0         # not deskewed, said, the scan used
        replay = scan_msg(2, rng=rng)                 # a looping bag: time goes backwards
        collector = Collector(probe, Odometry, '/scan_match/odom', ESTIMATE_QOS)
        # A new reader: the node's writer must match it before the scans go out (one-sided
        # discovery lost the first answer once).
        assert spin_until(probe, collector.matched, 20), node.output()
        spin_until(probe, lambda: False, 0.5)
        for msg in (broken, backwards_sweep, replay):
            scan_pub.publish(msg)
            spin_until(probe, lambda: False, 0.3)
        collector.wait_for(3, 10)
        spin_until(probe, lambda: 'reset_backwards' in diagnostic_values(diagnostics), 5)
        assert node.alive(), node.output()
        log = node.output()
    values = diagnostic_values(diagnostics)
    diagnostics.close()
    got = {stamp_to_ns(m.header.stamp): odometry_pose(m)[0] for m in collector.messages}
    collector.close()
    assert len(out) == 6
    assert set(got) == {T0 + 6 * SCAN_DT, T0 + 7 * SCAN_DT, T0 + 2 * SCAN_DT}
    # The unusable scan is the constant-velocity prediction, close to the truth; no jump.
    assert pose_error(got[T0 + 6 * SCAN_DT], reference(6))[0] < 0.02
    assert pose_error(got[T0 + 7 * SCAN_DT], reference(7))[0] < 0.02
    assert got[T0 + 2 * SCAN_DT] == (0.0, 0.0, 0.0)        # restarted at the origin
    assert values['reset_backwards'] == '1' and values['too_few_points'] == '1'
    assert values['time_increment_unusable'] == '1' and 'time_increment -1.0' in log
    assert 'backwards' in log


def test_laser_mount_from_tf_static_and_odom_to_base_link_on_tf(probe, pubs):
    """The laser sits turned 30 deg and 5 cm left, which /tf_static says and the parameters do
    not: the node warns, matches with the TF mount, and broadcasts its pose on /tf."""
    from rclpy.node import Node
    from tf2_msgs.msg import TFMessage

    from sensing_nodes.core.geometry.transform import Transform
    from sensing_nodes.ros.qos import TF_QOS
    from sensing_nodes.ros.tf import StaticTransformBroadcaster

    mount = (0.10, 0.05, math.radians(30.0))
    # Its own node, destroyed at the end: a latched /tf_static left on the session's probe would
    # reach every later test's subscribers.
    talker = Node('tf_static_talker', context=probe.context)
    statics = StaticTransformBroadcaster(talker)
    statics.send(T0, 'base_link', 'laser', Transform.from_planar(*mount))
    tf = Collector(probe, TFMessage, '/tf', TF_QOS)
    count = 15
    with NodeProcess('icp_matcher', params_file=config_file('icp_matcher.yaml'),
                     params={'publish_tf': True}) as node:
        # The mount must be there before the first scan (a late one restarts the keyframe):
        # the node's /tf_static reader matched, and a moment for the latched sample to land.
        assert spin_until(probe, lambda: statics._publisher.get_subscription_count() > 0, 30)
        spin_until(probe, lambda: False, 1.0)
        out = run_sequence(probe, pubs, node, count, mount=mount)
        spin_until(probe, lambda: len(tf.messages) >= count, 5)
        log = node.output()
    tf.close()
    talker.destroy_node()
    assert 'laser mount from /tf_static' in log and 'disagrees with the mount parameters' in log
    pose, _ = odometry_pose(out[T0 + (count - 1) * SCAN_DT])
    trans, rot = pose_error(pose, reference(count - 1))
    assert trans < 0.01 and rot < math.radians(0.3), (pose, reference(count - 1))
    sent = {stamp_to_ns(t.header.stamp): t for m in tf.messages for t in m.transforms}
    assert set(sent) == set(out)                      # one transform per published pose
    last = sent[T0 + (count - 1) * SCAN_DT]
    assert (last.header.frame_id, last.child_frame_id) == ('odom', 'base_link')
    assert (last.transform.translation.x, last.transform.translation.y) == pose[:2]


@pytest.mark.parametrize('delay_s, expected_x', [(0.1, 1.0), (0.0, 0.9)])
def test_odom_delay_reads_odometry_stamped_t_as_the_pose_at_t_minus_the_delay(delay_s, expected_x):
    """The matcher's per-message logic, without DDS: odometry of a robot at 1 m/s along x that
    lags by 0.1 s (stamped t, it reports x = t - 0.1 s - T0). With odom_delay_s 0.1 the guess
    reads x = 1.0 m at the scan stamp T0 + 1 s (the truth), 0.9 m without; the motion between
    two scans is the same 1 m/s either way."""
    from sensing_nodes.core.scan_matching import ScanMatcherSettings
    from sensing_nodes.nodes.icp_matcher import IcpMatcherProcessor

    processor = IcpMatcherProcessor(
        ScanMatcherSettings(), '/wheel/odom', 0.1, 20, 'odom', 'base_link', False, None, None,
        None, odom_delay_s=delay_s)
    for k in range(31):                     # stamps T0 + 0.1 s .. T0 + 3.1 s
        t = T0 + (k + 1) * 100_000_000
        x = (t - T0) * 1e-9 - 0.1
        assert processor.on_odometry(make_odometry(t, 'odom', 'base_link', (x, 0.0, 0.0),
                                                   np.eye(3) * 1e-4)) == []
    odometry = processor._odometry
    assert odometry.pose_at(T0 + 1_000_000_000)[0] == pytest.approx(expected_x, abs=1e-9)
    assert odometry.motion_between(T0 + 1_000_000_000, T0 + 2_000_000_000)[0] == \
        pytest.approx(1.0, abs=1e-9)
