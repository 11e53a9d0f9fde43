"""complementary_fusion over real DDS: stamp-ordered determinism, bad input, bad parameters."""

import math
import random
import time

import numpy as np
import pytest
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from harness import Collector, NodeProcess, run_to_exit, spin_until
from nav_msgs.msg import Odometry
from sensor_msgs.msg import Imu

from sensing_nodes.core.fusion.complementary import ComplementaryFusion, FusionSettings
from sensing_nodes.ros.conversions import (
    make_odometry,
    ns_to_stamp,
    odometry_pose,
    stamp_to_ns,
    yaw_to_quaternion,
)
from sensing_nodes.ros.qos import ESTIMATE_QOS

STEP_NS = 20_000_000  # 50 Hz wheel and gyro; scan match every 5th step (10 Hz)


def _inputs(count=60, start_ns=1_000_000_000):
    """A gently turning robot: wheel odometry drifting outwards, gyro and scan matching near
    truth."""
    events = []
    for k in range(count):
        t = start_ns + k * STEP_NS
        yaw = 0.01 * k
        wheel_cov = np.diag([1e-4, 1e-4, 1e-5]) * (k + 1)
        events.append(('wheel', t, (0.021 * k, 0.001 * k * k / 60, yaw * 1.05), wheel_cov))
        events.append(('imu', t, yaw + 0.0005 * k, 1e-6 * (k + 1)))
        if k % 5 == 0:
            events.append(
                (
                    'scan',
                    t,
                    (0.02 * k, 0.001 * k * k / 60, yaw),
                    np.diag([4e-5, 4e-5, 4e-6]) * (k + 1),
                )
            )
    return events


def _message(kind, t, value, cov):
    if kind == 'imu':
        msg = Imu()
        msg.header.stamp = ns_to_stamp(t)
        msg.header.frame_id = 'imu_link'
        msg.orientation = yaw_to_quaternion(value)
        msg.orientation_covariance = [0.0] * 8 + [float(cov)]
        return msg
    return make_odometry(t, 'odom', 'base_link', value, cov)


def _expected(events):
    """The core fed in stamp order (wheel, imu, scan at equal stamps), published as the node
    does: once per stamp, after every reading of it, where a wheel or scan reading is among
    them (the IMU alone only turns the heading)."""
    fusion = ComplementaryFusion(FusionSettings())
    out = []
    rank = {'wheel': 0, 'imu': 1, 'scan': 2}
    ordered = sorted(events, key=lambda e: (e[1], rank[e[0]]))
    wanted = False
    for index, (kind, t, value, cov) in enumerate(ordered):
        if kind == 'wheel':
            fusion.add_wheel(t, value, cov)
        elif kind == 'imu':
            fusion.add_gyro(t, value, cov)
        else:
            fusion.add_scan_match(t, value, cov)
        wanted = wanted or kind != 'imu'
        if index + 1 < len(ordered) and ordered[index + 1][1] == t:
            continue
        if wanted:
            out.append((t, fusion.state.pose, fusion.state.covariance))
        wanted = False
    return out


@pytest.fixture
def publishers(probe):
    pubs = {
        'wheel': probe.create_publisher(Odometry, '/wheel/odom', ESTIMATE_QOS),
        'imu': probe.create_publisher(Imu, '/imu/data', ESTIMATE_QOS),
        'scan': probe.create_publisher(Odometry, '/scan_match/odom', ESTIMATE_QOS),
    }
    yield pubs
    for pub in pubs.values():
        probe.destroy_publisher(pub)


def _send(probe, publishers, events, sent=None):
    """Publish events in the given order; sent (a list) gets each stamp once published."""
    assert spin_until(
        probe, lambda: all(p.get_subscription_count() > 0 for p in publishers.values()), 20
    )
    # Our writers see the node's readers; give the node's readers a moment to see our writers
    # too (discovery is not symmetric in time), or the first samples can be missed.
    spin_until(probe, lambda: False, 1.0)
    for kind, t, value, cov in events:
        publishers[kind].publish(_message(kind, t, value, cov))
        if sent is not None:
            sent.append(t)
        # Paced like a live source: a burst of hundreds of reliable samples makes DDS
        # retransmit some of them late, and late inputs are (correctly) dropped.
        time.sleep(0.002)
        rclpy.spin_once(probe, timeout_sec=0)


def _run(probe, publishers, events, params=None, before_stop=None, expected_count=None,
         sent=None):
    out = Collector(probe, Odometry, '/odometry/filtered', ESTIMATE_QOS)
    # A long idle flush: on a loaded machine the test's own publishing may stall for a moment,
    # and an idle flush mid-stream would (correctly) drop what arrives after it as late.
    # publish_rate_hz 0: an output per wheel and scan input, which these tests count
    params = {'method': 'complementary', 'reorder_window_s': 0.5, 'flush_after_s': 3.0,
              'publish_rate_hz': 0.0, **(params or {})}
    with NodeProcess('complementary_fusion', params=params) as node:
        assert spin_until(probe, lambda: out._sub.get_publisher_count() > 0, 20)
        _send(probe, publishers, events, sent)
        if expected_count is None:     # one output per stamp with a wheel or scan reading
            expected_count = len({e[1] for e in events if e[0] != 'imu'})
        out.wait_for(expected_count, timeout=20)
        if before_stop is not None:
            before_stop()
        log = node.output()
        assert node.alive(), log
    out.close()
    return out.messages, log


def test_output_is_the_stamp_ordered_fusion_whatever_the_arrival_order(probe, publishers):
    events = _inputs()
    # Each input arrives in its own order (as DDS delivers one publisher's messages), but the
    # inputs interleave at random, up to 0.3 s apart in stamps.
    rng = random.Random(7)
    queues = {kind: [e for e in events if e[0] == kind] for kind in ('wheel', 'imu', 'scan')}
    lag = {'wheel': 0, 'imu': 15 * STEP_NS, 'scan': 0}
    shuffled = []
    while any(queues.values()):
        kind = rng.choice([k for k, q in queues.items() if q])
        shuffled.append(queues[kind].pop(0))
    shuffled.sort(key=lambda e: e[1] + lag[e[0]] + rng.randrange(0, 5) * STEP_NS)
    shuffled = sorted(shuffled, key=lambda e: (e[1] + lag[e[0]]))
    assert shuffled != sorted(events, key=lambda e: e[1])
    messages, _ = _run(probe, publishers, shuffled)
    expected = _expected(events)
    assert len(messages) == len(expected)
    for msg, (t, pose, cov) in zip(messages, expected):
        got_pose, got_cov = odometry_pose(msg)
        assert msg.header.stamp == ns_to_stamp(t)
        assert got_pose == pytest.approx(pose, abs=1e-12)
        assert got_cov == pytest.approx(cov, abs=1e-15)
    assert msg.header.frame_id == 'odom' and msg.child_frame_id == 'base_link'


def test_bad_covariances_are_rejected_and_fusion_carries_on(probe, publishers):
    events = _inputs(30)
    bad = [('wheel', events[20][1] + 1, (0.0, 0.0, 0.0), np.diag([-1.0, 1.0, 1.0])),
           ('scan', events[20][1] + 2, (0.0, 0.0, 0.0), np.diag([math.nan, 1.0, 1.0])),
           ('imu', events[20][1] + 3, 0.0, -1.0)]
    messages, log = _run(probe, publishers, events[:20] + bad + events[20:],
                         expected_count=len(_expected(events)))
    assert (
        'wheel_odom: rejected' in log and 'scan_match: rejected' in log and 'imu: rejected' in log
    )
    expected = _expected(events)
    assert len(messages) == len(expected)
    assert odometry_pose(messages[-1])[0] == pytest.approx(expected[-1][1], abs=1e-12)


def test_time_going_backwards_resets_and_reproduces(probe, publishers):
    events = _inputs(80)  # 1.6 s: the replay jumps back further than reset_on_backwards_jump_s
    messages, log = _run(probe, publishers, events + events,
                         expected_count=2 * len(_expected(events)))
    assert 'time went backwards' in log
    half = len(messages) // 2
    first = np.array([odometry_pose(m)[0] for m in messages[:half]])
    second = np.array([odometry_pose(m)[0] for m in messages[half:]])
    assert len(messages) == 2 * len(_expected(events))
    assert second == pytest.approx(first, abs=1e-12)


def test_missing_input_is_reported_in_diagnostics(probe, publishers):
    diagnostics = Collector(probe, DiagnosticArray, '/diagnostics', 10)
    events = [e for e in _inputs(100) if e[0] != 'scan']
    def wait_for_diagnostics():   # a status after the inputs were fused (not one before)
        spin_until(probe, lambda: any(
            s.name == 'complementary_fusion' and
            {kv.key: kv.value for kv in s.values}.get('fusion_updates', '0') != '0'
            for m in diagnostics.messages for s in m.status), 5)

    # The scan matcher is never heard: not waited for beyond 0.05 s of stamps (its default, 10 s,
    # is for nodes started together), so every wheel input is answered.
    messages, _ = _run(probe, publishers, events,
                       params={'reorder_window_s': 0.05, 'startup_timeout_s': 0.05},
                       before_stop=wait_for_diagnostics)
    assert len(messages) == 100
    statuses = [
        s for m in diagnostics.messages for s in m.status if s.name == 'complementary_fusion'
    ]
    diagnostics.close()
    assert statuses, 'no diagnostics received'
    assert 'missing: scan_match' == statuses[-1].message, statuses[-1]
    values = {kv.key: kv.value for kv in statuses[-1].values}
    assert float(values['wheel_odom_rate_hz']) == pytest.approx(50.0, rel=1e-6)


@pytest.mark.parametrize('publish_tf', [True, False])
def test_odom_to_base_link_on_tf_with_each_output_never_ahead_of_the_inputs(probe, publishers,
                                                                            publish_tf):
    """One /tf transform per /odometry/filtered stamp, with the stamp, frames and pose of the
    last message at that stamp (a scan match after the wheel update at its stamp: tf2 keeps one
    sample per stamp), each stamped no later than the newest input sent before it arrived;
    none with publish_tf false."""
    from tf2_msgs.msg import TFMessage

    from sensing_nodes.ros.conversions import stamp_to_ns, transform_of
    from sensing_nodes.ros.qos import TF_QOS

    events = _inputs(40)
    sent = []
    received = []                                 # (transform, newest input stamp sent by then)
    sub = probe.create_subscription(
        TFMessage, '/tf', lambda m: received.extend((t, max(sent, default=None))
                                                    for t in m.transforms), TF_QOS)
    stamps = sorted({e[1] for e in events if e[0] != 'imu'})
    messages, _ = _run(probe, publishers, events, params={'publish_tf': publish_tf}, sent=sent,
                       before_stop=lambda: spin_until(
                           probe, lambda: len(received) >= len(stamps), 5))
    probe.destroy_subscription(sub)
    assert len(messages) == len(_expected(events)) == len(stamps)  # one output per stamp
    if not publish_tf:
        assert received == []
        return
    last_at = {stamp_to_ns(m.header.stamp): m for m in messages}
    assert [stamp_to_ns(t.header.stamp) for t, _ in received] == stamps
    for transform, newest_sent in received:
        stamp = stamp_to_ns(transform.header.stamp)
        assert newest_sent is not None and stamp <= newest_sent
        assert (transform.header.frame_id, transform.child_frame_id) == ('odom', 'base_link')
        x, y, yaw = transform_of(transform.transform).planar()
        pose, _ = odometry_pose(last_at[stamp])
        assert (x, y) == pytest.approx(pose[:2], abs=1e-12)
        assert math.remainder(yaw - pose[2], 2 * math.pi) == pytest.approx(0.0, abs=1e-9)


@pytest.mark.parametrize('param, value', [('alpha', '1.5'), ('alpha', 'fast'),
                                           ('reorder_window_s', '-1.0'),
                                           # beyond the reorder window (default 2 s), not finite
                                           ('wheel_odom.delay_s', '2.5'),
                                           ('scan_match.delay_s', '-2.5'),
                                           ('imu.delay_s', '.nan')])
def test_bad_parameters_exit_with_an_error_naming_them(param, value):
    result = run_to_exit(
        'complementary_fusion', ['--ros-args', '-p', f'{param}:={value}'], timeout=30
    )
    assert result.returncode == 2, result.stdout + result.stderr
    assert param in result.stderr


def test_no_input_enabled_is_a_parameter_error():
    args = ['--ros-args'] + [
        a
        for name in (
            'use_wheel_odom',
            'use_imu',
            'use_scan_match_position',
            'use_scan_match_heading',
        )
        for a in ('-p', f'{name}:=false')
    ]
    result = run_to_exit('complementary_fusion', args, timeout=30)
    assert result.returncode == 2 and 'at least one input' in result.stderr


def test_a_delayed_input_is_published_at_its_stamps_less_the_delay(probe, publishers):
    """wheel_odom.delay_s 0.1 (EKF, wheels alone): every output is stamped 0.1 s before the
    wheel message it came from (a message stamped t describes the robot at t - 0.1 s)."""
    events = [e for e in _inputs(count=20) if e[0] == 'wheel']
    out = Collector(probe, Odometry, '/odometry/filtered', ESTIMATE_QOS)
    params = {'method': 'ekf', 'use_imu': False, 'use_scan_match_position': False,
              'use_scan_match_heading': False, 'wheel_odom.delay_s': 0.1, 'flush_after_s': 3.0,
              'publish_rate_hz': 0.0}
    wheel = publishers['wheel']
    with NodeProcess('complementary_fusion', params=params) as node:
        assert spin_until(probe, lambda: out._sub.get_publisher_count() > 0
                          and wheel.get_subscription_count() > 0, 20), node.output()
        spin_until(probe, lambda: False, 1.0)    # the node's reader sees our writer too
        for kind, t, value, cov in events:
            wheel.publish(_message(kind, t, value, cov))
            time.sleep(0.002)
            rclpy.spin_once(probe, timeout_sec=0)
        out.wait_for(len(events), timeout=20)
        log = node.output()
        assert node.alive(), log
    out.close()
    stamps = [stamp_to_ns(m.header.stamp) for m in out.messages]
    assert stamps == [t - 100_000_000 for _, t, _, _ in events], log
