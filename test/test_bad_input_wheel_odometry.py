"""wheel_odometry under hypothesis-generated malformed JointState bursts over real DDS.

One node process for the whole module. Each example sends a burst of malformed or odd messages,
then a valid stretch whose stamps continue from the last valid one. The process must stay alive,
warn, and move exactly as a fresh core fed the same valid stretch: the burst may have reset the
pose (time went backwards) or restarted it (a gap), so "correct" is the body-frame motion between
consecutive outputs of the valid stretch, plus the twist, which only depend on that stretch.
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
from nav_msgs.msg import Odometry
from sensor_msgs.msg import JointState

from sensing_nodes.core.geometry import se2
from sensing_nodes.core.wheel_odometry import WheelOdometry, WheelOdometryConfig
from sensing_nodes.ros.conversions import ns_to_stamp, odometry_pose, odometry_twist, stamp_to_ns
from sensing_nodes.ros.qos import ESTIMATE_QOS, SENSOR_QOS

JOINTS = ('left_wheel_joint', 'right_wheel_joint')
T0 = 1_700_000_000 * 1_000_000_000
STEP = 20_000_000                      # 50 Hz
STRETCH = 12                           # valid messages after each burst
FAR_FUTURE = 100_000_000 * 1_000_000_000  # ~3 years: still fits a 32-bit stamp
BAD_FLOATS = st.sampled_from([math.nan, math.inf, -math.inf])

# Kind of malformed message -> the key its warning carries in the node's log (None: the message
# is odd but valid and must simply be handled).
KINDS = {
    'non_finite_position': 'non_finite',
    'non_finite_velocity_only': 'non_finite',
    'length_mismatch': 'length_mismatch',
    'velocity_length_mismatch': 'length_mismatch',
    'empty_arrays': 'missing_joint',
    'no_position_or_velocity': 'no_position_or_velocity',
    'unknown_joint': 'missing_joint',
    'repeated_stamp': 'repeated_stamp',
    'backwards_stamp': 'time went backwards',
    'far_future_stamp': 'gap',
    'huge_jump': 'implausible_increment',
    'unknown_frame_id': None,
    'velocity_absent': None,
}


def joint_state(t_ns, names, positions, velocities=(), frame_id=''):
    msg = JointState()
    msg.header.stamp = ns_to_stamp(t_ns)
    msg.header.frame_id = frame_id
    msg.name = list(names)
    msg.position = [float(p) for p in positions]
    msg.velocity = [float(v) for v in velocities]
    return msg


def bad_spec(kind=None):
    """Strategy: the kind of a malformed message and every random choice it needs (pure data,
    turned into a message against the node's current timeline by make_bad)."""
    return st.fixed_dictionaries({
        'kind': st.just(kind) if kind else st.sampled_from(sorted(KINDS)),
        'offset': st.integers(1, STEP - 1),
        'bad': BAD_FLOATS,
        'wheel': st.integers(0, 1),
        'length': st.sampled_from([1, 3, 5]),
        'name': st.text('abcxyz_', max_size=8),
        'back': st.sampled_from([1, STEP, 10**9, 3600 * 10**9]),
        'jump': st.floats(10.0, 1e6) | st.floats(-1e6, -10.0),
        'frame': st.text(max_size=12),
    })


def make_bad(spec, last_t, last_pos):
    """The JointState of a spec, relative to the last valid stamp and wheel positions."""
    kind, wheel = spec['kind'], spec['wheel']
    t = last_t + spec['offset']  # between two valid stamps
    pos = list(last_pos)
    if kind == 'non_finite_position':
        pos[wheel] = spec['bad']
        return joint_state(t, JOINTS, pos)
    if kind == 'non_finite_velocity_only':
        vel = [0.1, 0.1]
        vel[wheel] = spec['bad']
        return joint_state(t, JOINTS, [], vel)
    if kind == 'length_mismatch':
        return joint_state(t, JOINTS, (pos * 3)[:spec['length']])
    if kind == 'velocity_length_mismatch':
        return joint_state(t, JOINTS, [], [0.2] * spec['length'])
    if kind == 'empty_arrays':
        return joint_state(t, [], [])
    if kind == 'no_position_or_velocity':
        return joint_state(t, JOINTS, [])
    if kind == 'unknown_joint':
        names = [JOINTS[0], spec['name']] if wheel else [spec['name'], JOINTS[1]]
        return joint_state(t, names, pos)
    if kind == 'repeated_stamp':
        return joint_state(last_t, JOINTS, [p + 0.05 for p in pos])
    if kind == 'backwards_stamp':
        return joint_state(last_t - spec['back'], JOINTS, pos)
    if kind == 'far_future_stamp':
        return joint_state(last_t + FAR_FUTURE, JOINTS, pos)
    if kind == 'huge_jump':
        return joint_state(t, JOINTS, [p + spec['jump'] for p in pos])
    if kind == 'unknown_frame_id':
        return joint_state(t, JOINTS, pos, frame_id=spec['frame'])
    return joint_state(t, JOINTS, pos, velocities=())  # velocity_absent


class Stream:
    """The running node, its input and output, and where the valid timeline has got to."""

    def __init__(self, probe, node, publisher, out):
        self.probe, self.node, self.publisher, self.out = probe, node, publisher, out
        self.t = T0
        self.positions = [0.0, 0.0]
        self.kinds_sent: set[str] = set()
        self.resumed = 0


@pytest.fixture(scope='module')
def stream(probe):
    publisher = probe.create_publisher(JointState, '/joint_states', SENSOR_QOS)
    out = Collector(probe, Odometry, '/wheel/odom', ESTIMATE_QOS)
    with NodeProcess('wheel_odometry') as node:
        assert spin_until(probe, lambda: out._sub.get_publisher_count() > 0, 30), node.output()
        s = Stream(probe, node, publisher, out)
        first = joint_state(s.t, JOINTS, s.positions)
        assert publish_until(probe, publisher, first, lambda: len(out.messages) > 0,
                             outputs=out), node.output()
        yield s
    out.close()
    probe.destroy_publisher(publisher)


def run_example(s: Stream, specs, speeds) -> None:
    burst = []
    for spec in specs:
        s.kinds_sent.add(spec['kind'])
        burst.append(make_bad(spec, s.t, s.positions))
    valid = []
    positions = list(s.positions)
    for k in range(1, STRETCH + 1):
        positions = [positions[0] + speeds[0], positions[1] + speeds[1]]
        valid.append((s.t + k * STEP, list(positions)))
    s.t, s.positions = valid[-1][0], valid[-1][1]
    s.out.messages.clear()
    publish_paced(s.probe, s.publisher, burst)
    publish_paced(s.probe, s.publisher, [joint_state(t, JOINTS, p) for t, p in valid])
    last = valid[-1][0]
    spin_until(
        s.probe, lambda: any(stamp_to_ns(m.header.stamp) == last for m in s.out.messages), 5
    )
    assert s.node.alive(), s.node.output()

    by_stamp = {stamp_to_ns(m.header.stamp): m for m in s.out.messages}
    received = [(t, p) for t, p in valid if t in by_stamp]
    assert len(received) >= STRETCH - 2, f'only {len(received)} of {STRETCH} answered'
    core = WheelOdometry(WheelOdometryConfig())
    expected = []
    for t, p in received:
        core.update(t, list(JOINTS), p, [], JOINTS)
        expected.append((core.pose, core.twist))
    for i in range(1, len(received)):
        msg_prev, msg = by_stamp[received[i - 1][0]], by_stamp[received[i][0]]
        pose_prev, _ = odometry_pose(msg_prev)
        pose, cov = odometry_pose(msg)
        twist, twist_cov = odometry_twist(msg)
        assert np.all(np.isfinite(pose)) and np.all(np.isfinite(cov)), (pose, cov)
        assert np.all(np.isfinite(twist_cov)) and np.all(np.linalg.eigvalsh(cov) > -1e-12)
        motion = se2.between(pose_prev, pose)
        expected_motion = se2.between(expected[i - 1][0], expected[i][0])
        assert motion == pytest.approx(expected_motion, abs=1e-9)
        assert twist == pytest.approx(expected[i][1], abs=1e-9)
    s.resumed += 1


@pytest.mark.parametrize('kind', sorted(KINDS))
def test_malformed_joint_states_keep_the_node_alive_and_correct(stream, kind):
    @settings(max_examples=3, deadline=None, derandomize=True, database=None, phases=NO_SHRINK,
              suppress_health_check=list(HealthCheck))
    @given(forced=bad_spec(kind), others=st.lists(bad_spec(), max_size=3),
           where=st.integers(0, 3), speeds=st.tuples(st.floats(-0.5, 0.5), st.floats(-0.5, 0.5)))
    def example(forced, others, where, speeds):
        run_example(stream, others[:where] + [forced] + others[where:], speeds)

    example()
    assert stream.node.alive(), stream.node.output()


def test_every_kind_was_warned_about(stream):
    """Runs after the examples: each malformed kind left a warning in the node's log."""
    assert_every_kind_warned(stream, KINDS, examples_per_kind=3)
