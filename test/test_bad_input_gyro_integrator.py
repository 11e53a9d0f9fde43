"""gyro_integrator under hypothesis-generated malformed Imu bursts over real DDS.

One node process for the whole module. Each example sends a burst of malformed or odd samples,
then a valid stretch (a constant turn, so the robot is never still and the bias stays put) whose
stamps continue from the last valid one. The process must stay alive, warn, and integrate the
stretch exactly as a fresh core does: after a reset (time went backwards) or a gap the absolute
heading differs, so "correct" is the heading change between consecutive outputs and the
published bias-corrected rate.
"""

import math

import numpy as np
import pytest
from harness import (
    NO_SHRINK,
    Collector,
    NodeProcess,
    assert_every_kind_warned,
    publish_paced,
    publish_until,
    spin_until,
)
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from sensor_msgs.msg import Imu

from sensing_nodes.core.geometry.se2 import wrap_angle
from sensing_nodes.core.gyro import GyroConfig, GyroIntegrator
from sensing_nodes.ros.conversions import ns_to_stamp, quaternion_to_yaw, stamp_to_ns
from sensing_nodes.ros.qos import ESTIMATE_QOS, SENSOR_QOS

T0 = 1_700_000_000 * 1_000_000_000
STEP = 5_000_000                       # 200 Hz
STRETCH = 20
FAR_FUTURE = 100_000_000 * 1_000_000_000
GRAVITY = (0.0, 0.0, 9.81)

KINDS = {
    'non_finite_rate': 'non_finite',
    'non_finite_accel': 'non_finite',
    'repeated_stamp': 'repeated_stamp',
    'backwards_stamp': 'time went backwards',
    'far_future_stamp': 'gap',
    'huge_dt': 'gap',
    'bad_covariances': None,         # NaN / negative covariances are the input's own claim
    'orientation_absent': None,      # orientation_covariance[0] = -1 (REP 145), zero quaternion
    'unknown_frame_id': None,
}


def imu(t_ns, gyro, accel=GRAVITY, frame_id='imu_link'):
    msg = Imu()
    msg.header.stamp = ns_to_stamp(t_ns)
    msg.header.frame_id = frame_id
    msg.orientation_covariance[0] = -1.0
    msg.angular_velocity.x, msg.angular_velocity.y, msg.angular_velocity.z = map(float, gyro)
    a = msg.linear_acceleration
    a.x, a.y, a.z = map(float, accel)
    msg.angular_velocity_covariance[0] = msg.angular_velocity_covariance[4] = 1e-6
    msg.angular_velocity_covariance[8] = 1e-6
    return msg


def bad_spec(kind=None):
    """Strategy: a malformed sample's kind and random choices (pure data; see make_bad)."""
    return st.fixed_dictionaries({
        'kind': st.just(kind) if kind else st.sampled_from(sorted(KINDS)),
        'offset': st.integers(1, STEP - 1),
        'bad': st.sampled_from([math.nan, math.inf, -math.inf]),
        'axis': st.integers(0, 2),
        'back': st.sampled_from([1, STEP, 10**9, 3600 * 10**9]),
        'gap': st.integers(1, 3600).map(lambda s: s * 10**9),
        'cov': st.sampled_from([math.nan, -1.0, math.inf, -1e9]),
        'frame': st.text(max_size=12),
    })


def make_bad(spec, last_t, rate):
    kind = spec['kind']
    t = last_t + spec['offset']
    gyro = [0.0, 0.0, rate]
    if kind == 'non_finite_rate':
        gyro[spec['axis']] = spec['bad']
        return imu(t, gyro)
    if kind == 'non_finite_accel':
        accel = list(GRAVITY)
        accel[spec['axis']] = spec['bad']
        return imu(t, gyro, accel)
    if kind == 'repeated_stamp':
        return imu(last_t, [0.0, 0.0, rate + 1.0])
    if kind == 'backwards_stamp':
        return imu(last_t - spec['back'], gyro)
    if kind == 'far_future_stamp':
        return imu(last_t + FAR_FUTURE, gyro)
    if kind == 'huge_dt':
        return imu(last_t + spec['gap'], gyro)
    if kind == 'bad_covariances':
        msg = imu(t, gyro)
        msg.angular_velocity_covariance[8] = spec['cov']
        msg.linear_acceleration_covariance[0] = spec['cov']
        return msg
    if kind == 'orientation_absent':
        msg = imu(t, gyro)
        msg.orientation.w = 0.0          # all-zero quaternion: not a rotation at all
        return msg
    return imu(t, gyro, frame_id=spec['frame'])


class Stream:
    def __init__(self, probe, node, publisher, out):
        self.probe, self.node, self.publisher, self.out = probe, node, publisher, out
        self.t = T0
        self.rate = 0.3
        self.kinds_sent: set[str] = set()
        self.resumed = 0


@pytest.fixture(scope='module')
def stream(probe):
    publisher = probe.create_publisher(Imu, '/imu/data_raw', SENSOR_QOS)
    out = Collector(probe, Imu, '/imu/data', ESTIMATE_QOS)
    with NodeProcess('gyro_integrator') as node:
        s = Stream(probe, node, publisher, out)
        assert publish_until(probe, publisher, imu(s.t, [0.0, 0.0, s.rate]),
                             lambda: len(out.messages) > 0, outputs=out), node.output()
        yield s
    out.close()
    probe.destroy_publisher(publisher)


def run_example(s: Stream, specs, rate) -> None:
    burst = []
    for spec in specs:
        s.kinds_sent.add(spec['kind'])
        burst.append(make_bad(spec, s.t, s.rate))
    valid = [(s.t + k * STEP, rate) for k in range(1, STRETCH + 1)]
    s.t, s.rate = valid[-1][0], rate
    s.out.messages.clear()
    publish_paced(s.probe, s.publisher, burst)
    publish_paced(s.probe, s.publisher, [imu(t, [0.0, 0.0, r]) for t, r in valid])
    last = valid[-1][0]
    spin_until(
        s.probe, lambda: any(stamp_to_ns(m.header.stamp) == last for m in s.out.messages), 5
    )
    assert s.node.alive(), s.node.output()

    by_stamp = {stamp_to_ns(m.header.stamp): m for m in s.out.messages}
    received = [(t, r) for t, r in valid if t in by_stamp]
    assert len(received) >= STRETCH - 3, f'only {len(received)} of {STRETCH} answered'
    core = GyroIntegrator(GyroConfig())
    expected = []
    for t, r in received:
        core.update(t, (0.0, 0.0, r), GRAVITY)
        expected.append((core.heading, float(core.rate[2])))
    for i in range(1, len(received)):
        msg_prev, msg = by_stamp[received[i - 1][0]], by_stamp[received[i][0]]
        values = [msg.orientation.z, msg.orientation.w, msg.orientation_covariance[8],
                  msg.angular_velocity.z, *msg.angular_velocity_covariance]
        assert np.all(np.isfinite(values)) and msg.orientation_covariance[8] >= 0.0, msg
        turned = wrap_angle(quaternion_to_yaw(msg.orientation)
                            - quaternion_to_yaw(msg_prev.orientation))
        assert turned == pytest.approx(wrap_angle(expected[i][0] - expected[i - 1][0]), abs=1e-9)
        assert msg.angular_velocity.z == pytest.approx(expected[i][1], abs=1e-12)
        assert msg.header.frame_id == 'imu_link'
    s.resumed += 1


@pytest.mark.parametrize('kind', sorted(KINDS))
def test_malformed_imu_samples_keep_the_node_alive_and_correct(stream, kind):
    @settings(max_examples=3, deadline=None, derandomize=True, database=None, phases=NO_SHRINK,
              suppress_health_check=list(HealthCheck))
    @given(forced=bad_spec(kind), others=st.lists(bad_spec(), max_size=3),
           where=st.integers(0, 3),
           rate=st.floats(0.1, 2.0) | st.floats(-2.0, -0.1))
    def example(forced, others, where, rate):
        run_example(stream, others[:where] + [forced] + others[where:], rate)

    example()
    assert stream.node.alive(), stream.node.output()


def test_every_kind_was_warned_about(stream):
    """Runs after the examples: each malformed kind left a warning in the node's log."""
    assert_every_kind_warned(stream, KINDS, examples_per_kind=3)
