"""line_extractor under hypothesis-generated malformed LaserScan bursts over real DDS.

One node process for the whole module (started with config/line_extractor.yaml). Each example
sends a burst of malformed or odd scans, then valid scans of the default world from a random
pose, stamped after the last valid one. The process must stay alive, warn, answer every scan
it gets with a table of finite numbers (an empty one for an unusable scan), and extract from the
valid scans exactly the lines the core extracts from them (extraction keeps no state, so the
fresh-node answer is the core's).
"""

import math

import numpy as np
import pytest
import yaml
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
from sensor_msgs.msg import LaserScan, PointCloud2

from sensing_nodes.core.geometry.scan import beam_angles
from sensing_nodes.core.lines import extract_lines
from sensing_nodes.core.sim.world import load_world, raycast
from sensing_nodes.nodes.line_extractor import TABLE_DTYPE
from sensing_nodes.paths import config_file
from sensing_nodes.ros.conversions import stamp_to_ns
from sensing_nodes.ros.qos import ESTIMATE_QOS, SENSOR_QOS

T0 = 1_700_000_000 * 1_000_000_000
STEP = 100_000_000                      # 10 Hz
BEAMS = 360
INCREMENT = 2 * math.pi / BEAMS
RANGE_MIN, RANGE_MAX = 0.12, 8.0
FAR_FUTURE = 100_000_000 * 1_000_000_000
WORLD = load_world(config_file('default_world.yaml'))
PARAMS = yaml.safe_load(
    config_file('line_extractor.yaml').read_text())['line_extractor']['ros__parameters']
CORE_OPTIONS = {k: PARAMS[k] for k in ('split_distance', 'max_line_gap', 'min_line_points',
                                       'min_line_length', 'min_range', 'max_range', 'range_sigma',
                                       'merge_chi2')}

KINDS = {
    'nan_ranges': 'NaN ranges',
    'inf_and_negative_ranges': None,       # REP 117 +-inf and negative values: invalid beams
    'all_ranges_invalid': 'none of the',
    'empty_ranges': 'no ranges',
    'intensities_mismatch': 'intensities',
    'zero_increment': 'angle_increment',
    'negative_increment': 'angle_increment',
    'non_finite_increment': 'angle_increment',
    'non_finite_angle_min': 'angle_min',
    'bad_range_limits': 'using only the parameters',
    'too_few_valid_ranges': 'fewer than',
    'repeated_stamp': None,                # stateless: a repeat is only counted
    'backwards_stamp': 'went backwards',
    'far_future_stamp': None,              # a gap is counted; the next scan then goes backwards
    'unknown_frame_id': None,
    'optional_fields_absent': None,        # no intensities, zero time_increment and scan_time
}


def room_ranges(x, y, yaw, noise_seed):
    """Ranges (float32, m) of the default world from a laser at (x, y, yaw), with range noise."""
    angles = -math.pi + INCREMENT * np.arange(BEAMS)
    ranges = raycast(WORLD.segments, (x, y), angles + yaw)
    ranges = ranges + np.random.default_rng(noise_seed).normal(0.0, 0.01, BEAMS)
    ranges[ranges > RANGE_MAX] = np.inf
    return ranges.astype(np.float32)


def scan(t_ns, ranges, **fields):
    return laser_scan(t_ns, ranges, **{'increment': INCREMENT, 'range_min': RANGE_MIN,
                                       'range_max': RANGE_MAX, **fields})


POSES = st.tuples(st.floats(-4.5, -1.6), st.floats(-3.5, 3.5), st.floats(-math.pi, math.pi),
                  st.integers(0, 2**32 - 1))


def bad_spec(kind=None):
    """Strategy: a malformed scan's kind and random choices (pure data; see make_bad)."""
    return st.fixed_dictionaries({
        'kind': st.just(kind) if kind else st.sampled_from(sorted(KINDS)),
        'offset': st.integers(1, STEP - 1),
        'pose': POSES,
        'fraction': st.floats(0.01, 1.0),
        'bad': st.sampled_from([math.nan, math.inf, -math.inf]),
        'negative': st.floats(-1e6, -1e-6),
        'count': st.integers(1, 5),
        'back': st.sampled_from([1, STEP, 10**9, 3600 * 10**9]),
        'limits': st.sampled_from([(5.0, 1.0), (math.nan, 8.0), (0.1, math.nan), (-1.0, -0.5),
                                   (math.inf, math.inf), (8.0, 8.0)]),
        'frame': st.text(max_size=12),
        'seed': st.integers(0, 2**32 - 1),
    })


def make_bad(spec, last_t):
    kind = spec['kind']
    t = last_t + spec['offset']
    ranges = room_ranges(*spec['pose'])
    rng = np.random.default_rng(spec['seed'])
    some = rng.random(BEAMS) < spec['fraction']
    if kind == 'nan_ranges':
        ranges[some] = np.nan
        ranges[0] = np.nan
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
        return scan(t, ranges, increment=-INCREMENT * spec['fraction'])
    if kind == 'non_finite_increment':
        return scan(t, ranges, increment=spec['bad'])
    if kind == 'non_finite_angle_min':
        return scan(t, ranges, angle_min=spec['bad'])
    if kind == 'bad_range_limits':
        return scan(t, ranges, range_min=spec['limits'][0], range_max=spec['limits'][1])
    if kind == 'too_few_valid_ranges':
        few = np.full(BEAMS, np.nan, np.float32)
        few[:spec['count']] = 2.0
        return scan(t, few)
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


def table(msg: PointCloud2) -> np.ndarray:
    assert msg.point_step == TABLE_DTYPE.itemsize and len(msg.data) == msg.width * msg.point_step
    return np.frombuffer(bytes(msg.data), dtype=TABLE_DTYPE)


def f32(value: float) -> float:
    """A float32 message field as the receiving node reads it."""
    return float(np.float32(value))


def core_table(msg: LaserScan) -> np.ndarray:
    """The lines the core extracts from the scan the node receives, as a table."""
    ranges = np.asarray(msg.ranges, dtype=float)
    angles = beam_angles(f32(msg.angle_min), f32(msg.angle_increment), ranges.size)
    options = {**CORE_OPTIONS, 'min_range': max(CORE_OPTIONS['min_range'], f32(msg.range_min)),
               'max_range': min(CORE_OPTIONS['max_range'], f32(msg.range_max))}
    lines = extract_lines(ranges, angles, **options)
    return np.array([(ln.r, ln.alpha, ln.covariance[0, 0], ln.covariance[0, 1],
                      ln.covariance[1, 1], *ln.start, *ln.end, ln.first, ln.last, ln.point_count)
                     for ln in lines], dtype=TABLE_DTYPE)


class Stream:
    def __init__(self, probe, node, publisher, out):
        self.probe, self.node, self.publisher, self.out = probe, node, publisher, out
        self.t = T0
        self.kinds_sent: set[str] = set()
        self.resumed = 0


@pytest.fixture(scope='module')
def stream(probe):
    publisher = probe.create_publisher(LaserScan, '/scan', SENSOR_QOS)
    out = Collector(probe, PointCloud2, '/scan/lines/table', ESTIMATE_QOS)
    with NodeProcess('line_extractor', params_file=config_file('line_extractor.yaml')) as node:
        assert spin_until(probe, lambda: out._sub.get_publisher_count() > 0, 30), node.output()
        s = Stream(probe, node, publisher, out)
        first = scan(s.t, room_ranges(-3.0, 0.0, 0.0, 0))
        assert publish_until(probe, publisher, first, lambda: len(out.messages) > 0,
                             outputs=out), node.output()
        yield s
    out.close()
    probe.destroy_publisher(publisher)


def run_example(s: Stream, specs, poses) -> None:
    burst = []
    for spec in specs:
        s.kinds_sent.add(spec['kind'])
        burst.append(make_bad(spec, s.t))
    valid = [scan(s.t + (k + 1) * STEP, room_ranges(*pose)) for k, pose in enumerate(poses)]
    s.t = stamp_to_ns(valid[-1].header.stamp)
    s.out.messages.clear()
    publish_paced(s.probe, s.publisher, burst, pause_s=0.005)
    publish_paced(s.probe, s.publisher, valid, pause_s=0.005)
    last = s.t
    spin_until(
        s.probe, lambda: any(stamp_to_ns(m.header.stamp) == last for m in s.out.messages), 5
    )
    assert s.node.alive(), s.node.output()

    for msg in s.out.messages:           # every answer, to bad scans too, is a finite table
        rows = table(msg)
        assert all(np.all(np.isfinite(rows[name])) for name in TABLE_DTYPE.names), rows
    by_stamp = {stamp_to_ns(m.header.stamp): m for m in s.out.messages}
    answered = [v for v in valid if stamp_to_ns(v.header.stamp) in by_stamp]
    assert len(answered) >= len(valid) - 1, f'only {len(answered)} of {len(valid)} answered'
    for msg in answered:
        out = by_stamp[stamp_to_ns(msg.header.stamp)]
        rows, expected = table(out), core_table(msg)
        assert out.header.frame_id == 'laser'
        assert len(expected) >= 3 and len(rows) == len(expected)
        for name in TABLE_DTYPE.names:
            np.testing.assert_allclose(rows[name], expected[name], rtol=1e-12, atol=1e-12)
    s.resumed += 1


@pytest.mark.parametrize('kind', sorted(KINDS))
def test_malformed_scans_keep_the_node_alive_and_correct(stream, kind):
    @settings(max_examples=2, deadline=None, derandomize=True, database=None, phases=NO_SHRINK,
              suppress_health_check=list(HealthCheck))
    @given(forced=bad_spec(kind), others=st.lists(bad_spec(), max_size=2),
           where=st.integers(0, 2), poses=st.lists(POSES, min_size=1, max_size=2))
    def example(forced, others, where, poses):
        run_example(stream, others[:where] + [forced] + others[where:], poses)

    example()
    assert stream.node.alive(), stream.node.output()


def test_every_kind_was_warned_about(stream):
    """Runs after the examples: each malformed kind left a warning in the node's log."""
    assert_every_kind_warned(stream, KINDS, examples_per_kind=2)
