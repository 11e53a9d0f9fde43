"""icp_matcher under hypothesis-generated malformed LaserScan bursts over real DDS.

One node process for the whole module (defaults: constant-velocity prediction, laser 0.10 m
ahead of base_link). Each example sends a burst of malformed or odd scans, then valid scans of
the default world taken along a drive, stamped after the last valid one. The process must stay
alive, warn, publish only finite poses and covariances, and after valid input resumes report the
true motion between consecutive outputs (a scan matcher restarts its keyframe after a reset, a
gap or a failed match, so "correct" is the motion, not the absolute pose).
"""

import math

import numpy as np
import pytest
from harness import (
    NO_SHRINK,
    Collector,
    NodeProcess,
    assert_every_kind_warned,
    laser_scan,
    publish_paced,
    publish_until,
    spin_until,
)
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from nav_msgs.msg import Odometry
from sensor_msgs.msg import LaserScan

from sensing_nodes.core.geometry import se2
from sensing_nodes.core.sim.world import load_world, raycast
from sensing_nodes.paths import config_file
from sensing_nodes.ros.conversions import odometry_pose, stamp_to_ns
from sensing_nodes.ros.qos import ESTIMATE_QOS, SENSOR_QOS

T0 = 1_700_000_000 * 1_000_000_000
STEP = 100_000_000                      # 10 Hz
STRETCH = 5
BEAMS = 360
INCREMENT = 2 * math.pi / BEAMS
RANGE_MIN, RANGE_MAX = 0.12, 8.0
LASER = (0.10, 0.0, 0.0)
FAR_FUTURE = 100_000_000 * 1_000_000_000
MIN_OFFSET = 1_000_000
WORLD = load_world(config_file('default_world.yaml'))
CENTRE = (-3.0, 0.0)                    # a free area west of the table

KINDS = {
    'nan_ranges': None,                  # invalid beams (REP 117): matched on the rest
    'inf_and_negative_ranges': None,
    'all_ranges_invalid': 'valid points',
    'empty_ranges': 'valid points',
    'intensities_mismatch': None,        # intensities are not used
    'zero_increment': None,              # every beam on one ray: a failed match at most
    'negative_increment': None,          # a mirrored scan: a failed match at most
    'non_finite_increment': 'valid points',
    'non_finite_angle_min': 'valid points',
    'bad_range_limits': None,
    'repeated_stamp': 'same stamp',
    'backwards_stamp': 'went backwards',
    'far_future_stamp': 'since the previous scan',
    'unknown_frame_id': None,
    'optional_fields_absent': None,
}


def room_ranges(base_pose):
    """Ranges (float32, m) of the default world seen by the laser of a robot at base_pose."""
    laser = se2.compose(base_pose, LASER)
    angles = -math.pi + INCREMENT * np.arange(BEAMS)
    ranges = raycast(WORLD.segments, laser[:2], angles + laser[2])
    ranges[ranges > RANGE_MAX] = np.inf
    return ranges.astype(np.float32)


def scan(t_ns, ranges, **fields):
    return laser_scan(t_ns, ranges, **{'increment': INCREMENT, 'range_min': RANGE_MIN,
                                       'range_max': RANGE_MAX, **fields})


def bad_spec(kind=None):
    """Strategy: a malformed scan's kind and random choices (pure data; see make_bad)."""
    return st.fixed_dictionaries({
        'kind': st.just(kind) if kind else st.sampled_from(sorted(KINDS)),
        # At least 1 ms after the previous scan: see test_a_scan_nanoseconds_after_the_previous
        'offset': st.integers(MIN_OFFSET, STEP - 1),
        'fraction': st.floats(0.01, 0.5),
        'bad': st.sampled_from([math.nan, math.inf, -math.inf]),
        'negative': st.floats(-1e6, -1e-6),
        'count': st.integers(1, 5),
        'back': st.sampled_from([1, STEP, 10**9, 3600 * 10**9]),
        'limits': st.sampled_from([(5.0, 1.0), (math.nan, 8.0), (0.1, math.nan), (-1.0, -0.5),
                                   (math.inf, math.inf), (8.0, 8.0)]),
        'frame': st.text(max_size=12),
        'seed': st.integers(0, 2**32 - 1),
    })


def make_bad(spec, last_t, pose):
    kind = spec['kind']
    t = last_t + spec['offset']
    ranges = room_ranges(pose)
    rng = np.random.default_rng(spec['seed'])
    some = rng.random(BEAMS) < spec['fraction']
    if kind == 'nan_ranges':
        ranges[some] = np.nan
        return scan(t, ranges)
    if kind == 'inf_and_negative_ranges':
        ranges[some] = rng.choice(np.array([np.inf, -np.inf, spec['negative']], np.float32),
                                  int(some.sum()))
        return scan(t, ranges)
    if kind == 'all_ranges_invalid':
        return scan(
            t, np.full(BEAMS, spec['bad'] if math.isnan(spec['bad']) else spec['negative'])
        )
    if kind == 'empty_ranges':
        return scan(t, [])
    if kind == 'intensities_mismatch':
        return scan(t, ranges, intensities=np.ones(BEAMS + spec['count']))
    if kind == 'zero_increment':
        return scan(t, ranges, increment=0.0)
    if kind == 'negative_increment':
        return scan(t, ranges, increment=-INCREMENT)
    if kind == 'non_finite_increment':
        return scan(t, ranges, increment=spec['bad'])
    if kind == 'non_finite_angle_min':
        return scan(t, ranges, angle_min=spec['bad'])
    if kind == 'bad_range_limits':
        return scan(t, ranges, range_min=spec['limits'][0], range_max=spec['limits'][1])
    if kind == 'repeated_stamp':
        return scan(last_t, ranges)
    if kind == 'backwards_stamp':
        return scan(last_t - spec['back'], ranges)
    if kind == 'far_future_stamp':
        return scan(last_t + FAR_FUTURE, ranges)
    if kind == 'unknown_frame_id':
        return scan(t, ranges, frame_id=spec['frame'])
    msg = scan(t, ranges)
    msg.time_increment = msg.scan_time = 0.0
    return msg


class Stream:
    def __init__(self, probe, node, publisher, out):
        self.probe, self.node, self.publisher, self.out = probe, node, publisher, out
        self.t = T0
        self.pose = (CENTRE[0], CENTRE[1], 0.3)
        self.kinds_sent: set[str] = set()
        self.resumed = 0
        self.worst = (0.0, 0.0)


@pytest.fixture(scope='module')
def stream(probe):
    publisher = probe.create_publisher(LaserScan, '/scan', SENSOR_QOS)
    out = Collector(probe, Odometry, '/scan_match/odom', ESTIMATE_QOS)
    with NodeProcess('icp_matcher') as node:
        assert spin_until(probe, lambda: out._sub.get_publisher_count() > 0, 30), node.output()
        s = Stream(probe, node, publisher, out)
        first = scan(s.t, room_ranges(s.pose))
        assert publish_until(probe, publisher, first, lambda: len(out.messages) > 0,
                             outputs=out), node.output()
        yield s
    out.close()
    probe.destroy_publisher(publisher)


def run_example(s: Stream, specs, speed, yaw_rate) -> None:
    # Drive towards the centre of the free area, so the robot never leaves it.
    to_centre = math.atan2(CENTRE[1] - s.pose[1], CENTRE[0] - s.pose[0])
    forward = math.cos(to_centre - s.pose[2]) >= 0.0
    v = abs(speed) if forward else -abs(speed)
    burst = []
    for spec in specs:
        s.kinds_sent.add(spec['kind'])
        burst.append(make_bad(spec, s.t, s.pose))
    valid, pose = [], s.pose
    for k in range(1, STRETCH + 1):
        pose = se2.compose(pose, (v * 0.1, 0.0, yaw_rate * 0.1))
        valid.append((s.t + k * STEP, pose))
    s.t, s.pose = valid[-1]
    s.out.messages.clear()
    publish_paced(s.probe, s.publisher, burst, pause_s=0.005)
    publish_paced(s.probe, s.publisher, [scan(t, room_ranges(p)) for t, p in valid], pause_s=0.005)
    last = valid[-1][0]
    spin_until(s.probe,
               lambda: any(stamp_to_ns(m.header.stamp) == last for m in s.out.messages), 10)
    assert s.node.alive(), s.node.output()

    for msg in s.out.messages:           # every output, after bad scans too, is finite
        pose_out, cov = odometry_pose(msg)
        assert np.all(np.isfinite(pose_out)) and np.all(np.isfinite(cov)), (pose_out, cov)
        assert np.all(np.linalg.eigvalsh(cov) > -1e-12), cov
    by_stamp = {stamp_to_ns(m.header.stamp): odometry_pose(m)[0] for m in s.out.messages}
    answered = [(t, p) for t, p in valid if t in by_stamp]
    assert len(answered) >= STRETCH - 1, f'only {len(answered)} of {STRETCH} answered'
    # The first valid scan may be a fallback against a bad keyframe (then it becomes the
    # keyframe); every later one is matched against valid scans only.
    for (t0, p0), (t1, p1) in zip(answered, answered[1:]):
        moved = se2.between(by_stamp[t0], by_stamp[t1])
        truth = se2.between(p0, p1)
        position_error = math.hypot(moved[0] - truth[0], moved[1] - truth[1])
        heading_error = abs(float(se2.wrap_angle(moved[2] - truth[2])))
        s.worst = (max(s.worst[0], position_error), max(s.worst[1], heading_error))
        assert position_error < 0.01 and heading_error < 0.01, \
            (moved, truth, s.node.output()[-2000:])
    s.resumed += 1


@pytest.mark.parametrize('kind', sorted(KINDS))
def test_malformed_scans_keep_the_matcher_alive_and_correct(stream, kind):
    @settings(max_examples=2, deadline=None, derandomize=True, database=None, phases=NO_SHRINK,
              suppress_health_check=list(HealthCheck))
    @given(forced=bad_spec(kind), others=st.lists(bad_spec(), max_size=2),
           where=st.integers(0, 2), speed=st.floats(0.05, 0.4), yaw_rate=st.floats(-0.5, 0.5))
    def example(forced, others, where, speed, yaw_rate):
        run_example(stream, others[:where] + [forced] + others[where:], speed, yaw_rate)

    example()
    assert stream.node.alive(), stream.node.output()


def test_every_kind_was_warned_about(stream):
    """Runs after the examples: each malformed kind left a warning in the node's log."""
    print(f'worst motion error after resuming: {stream.worst[0]:.2e} m, {stream.worst[1]:.2e} rad')
    assert_every_kind_warned(stream, KINDS, examples_per_kind=2)

def test_a_scan_nanoseconds_after_the_previous_does_not_derail_the_matcher(stream):
    """A valid scan 1 us after the previous one (a driver's duplicate with a nudged stamp, with
    a few beams missing), then the drive goes on: the matcher must keep tracking it."""
    spec = {'kind': 'nan_ranges', 'offset': 1_000, 'fraction': 0.25, 'bad': math.nan,
            'negative': -1.0, 'count': 1, 'back': 1, 'limits': (5.0, 1.0), 'frame': '', 'seed': 0}
    for _ in range(3):
        run_example(stream, [spec], 0.25, 0.0)
