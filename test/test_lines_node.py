"""line_extractor over real DDS: the table parsed with numpy alone, markers, bad input, bad
parameters."""

import math

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray
from harness import Collector, NodeProcess, run_to_exit, spin_until
from sensor_msgs.msg import LaserScan, PointCloud2
from visualization_msgs.msg import Marker, MarkerArray

from sensing_nodes.core.lines import extract_lines
from sensing_nodes.core.sim.world import raycast
from sensing_nodes.ros.conversions import ns_to_stamp, scan_arrays, stamp_to_ns
from sensing_nodes.ros.qos import ESTIMATE_QOS, SENSOR_QOS

# sensor_msgs/PointField datatypes -> numpy, as any consumer would write them.
_POINTFIELD_NUMPY = {1: 'i1', 2: 'u1', 3: 'i2', 4: 'u2', 5: 'i4', 6: 'u4', 7: 'f4', 8: 'f8'}


def parse_table(msg) -> np.ndarray:
    """A consumer's parser: PointCloud2 -> numpy structured array, from the message alone."""
    endian = '>' if msg.is_bigendian else '<'
    dtype = np.dtype({
        'names': [f.name for f in msg.fields],
        'formats': [endian + _POINTFIELD_NUMPY[f.datatype] for f in msg.fields],
        'offsets': [f.offset for f in msg.fields],
        'itemsize': msg.point_step,
    })
    return np.frombuffer(bytes(msg.data), dtype=dtype, count=msg.width * msg.height)


COLUMNS = ['r', 'alpha', 'cov_rr', 'cov_ra', 'cov_aa', 'x0', 'y0', 'x1', 'y1', 'first', 'last',
           'point_count']


def _scan(stamp_ns, ranges, angle_min=-math.pi / 4, angle_increment=math.radians(0.5),
          intensities=None, range_min=0.05, range_max=8.0):
    msg = LaserScan()
    msg.header.stamp = ns_to_stamp(stamp_ns)
    msg.header.frame_id = 'laser'
    msg.angle_min = float(np.float32(angle_min))
    msg.angle_increment = float(np.float32(angle_increment))
    msg.angle_max = float(np.float32(angle_min + angle_increment * (len(ranges) - 1))) \
        if math.isfinite(angle_min + angle_increment) else 0.0
    msg.range_min, msg.range_max = range_min, range_max
    msg.ranges = np.asarray(ranges, dtype=np.float32).tolist()
    msg.intensities = [] if intensities is None else [float(v) for v in intensities]
    return msg


def _corner_ranges(seed=0):
    angles = -math.pi / 4 + math.radians(0.5) * np.arange(361)
    ranges = raycast(np.array([[2.0, -2.0, 2.0, 3.0], [2.0, 3.0, -3.0, 3.0]]), (0.0, 0.0), angles)
    ranges = ranges + np.random.default_rng(seed).normal(0.0, 0.01, ranges.size)
    ranges[100] = np.nan
    ranges[200] = np.inf
    return ranges


@pytest.fixture(scope='module')
def node_io(probe):
    with NodeProcess('line_extractor') as node:
        scans = probe.create_publisher(LaserScan, '/scan', SENSOR_QOS)
        tables = Collector(probe, PointCloud2, '/scan/lines/table', ESTIMATE_QOS)
        markers = Collector(probe, MarkerArray, '/scan/lines', ESTIMATE_QOS)
        diagnostics = Collector(probe, DiagnosticArray, '/diagnostics', 10)
        assert spin_until(probe, lambda: scans.get_subscription_count() > 0
                          and tables._sub.get_publisher_count() > 0
                          and markers._sub.get_publisher_count() > 0, 30), node.output()
        yield node, scans, tables, markers, diagnostics
        for collector in (tables, markers, diagnostics):
            collector.close()
        probe.destroy_publisher(scans)


def _exchange(probe, node_io, msg):
    """Publish a scan until its table and markers (matched by stamp) come back."""
    node, scans, tables, markers, _ = node_io
    stamp = stamp_to_ns(msg.header.stamp)

    def find(collector):
        got = [m for m in collector.messages if stamp_to_ns(
            (m.header if hasattr(m, 'header') else m.markers[0].header).stamp) == stamp]
        return got[-1] if got else None

    for _ in range(5):   # best-effort input: resend if a sample was lost
        scans.publish(msg)
        if spin_until(probe, lambda: find(tables) is not None and find(markers) is not None, 3.0):
            return find(tables), find(markers)
    pytest.fail(f'no output for stamp {stamp}\n{node.output()}')


def test_lines_table_and_markers(probe, node_io):
    msg = _scan(5_000_000_000, _corner_ranges())
    table, markers = _exchange(probe, node_io, msg)
    ranges, angles = scan_arrays(msg)
    expected = extract_lines(ranges, angles, min_range=0.05, max_range=8.0)
    assert len(expected) == 2

    rows = parse_table(table)
    assert [f.name for f in table.fields] == COLUMNS
    assert table.header.frame_id == 'laser' and stamp_to_ns(table.header.stamp) == 5_000_000_000
    assert (table.height, table.width) == (1, 2)
    for row, line in zip(rows, expected):
        assert row['r'] == pytest.approx(line.r, abs=1e-12)
        assert row['alpha'] == pytest.approx(line.alpha, abs=1e-12)
        assert [row['cov_rr'], row['cov_ra'], row['cov_aa']] == pytest.approx(
            [line.covariance[0, 0], line.covariance[0, 1], line.covariance[1, 1]], rel=1e-12)
        assert [row['x0'], row['y0'], row['x1'], row['y1']] == pytest.approx(
            [*line.start, *line.end], abs=1e-12)
        assert (row['first'], row['last'], row['point_count']) == (
            line.first,
            line.last,
            line.point_count,
        )
    # The walls themselves: x = 2 (alpha 0) and y = 3 (alpha 90 deg), to noise level.
    assert rows['r'] == pytest.approx([2.0, 3.0], abs=0.01)
    assert np.degrees(rows['alpha']) == pytest.approx([0.0, 90.0], abs=0.5)

    clear, strip = markers.markers
    assert clear.action == Marker.DELETEALL
    assert strip.type == Marker.LINE_LIST and strip.action == Marker.ADD
    assert strip.header.frame_id == 'laser' and stamp_to_ns(strip.header.stamp) == 5_000_000_000
    ends = np.array([(p.x, p.y) for p in strip.points])
    assert ends == pytest.approx(
        np.array([pt for ln in expected for pt in (ln.start, ln.end)]), abs=1e-12
    )


# (name, scan, warning expected in the log; None: same kind as the one before, so throttled)
BAD_SCANS = [
    ('all NaN', dict(ranges=np.full(100, np.nan)), 'none of the 100 ranges is valid'),
    ('all +inf', dict(ranges=np.full(100, np.inf)), None),
    (
        'too few points',
        dict(ranges=np.r_[np.full(3, 2.0), np.full(97, np.inf)]),
        'only 3 valid ranges',
    ),
    ('no ranges', dict(ranges=np.zeros(0)), 'scan has no ranges'),
    ('zero increment', dict(ranges=np.full(100, 2.0), angle_increment=0.0), 'angle_increment=0.0'),
    ('negative increment', dict(ranges=np.full(100, 2.0), angle_increment=-0.01), None),
    ('NaN angle_min', dict(ranges=np.full(100, 2.0), angle_min=float('nan')), 'angle_min=nan'),
    (
        'intensities mismatch',
        dict(ranges=np.full(100, 2.0), intensities=np.ones(99)),
        '100 ranges but 99 intensities',
    ),
]


def test_bad_scans_publish_empty_results_and_warn(probe, node_io):
    node = node_io[0]
    for k, (name, kwargs, warning) in enumerate(BAD_SCANS):
        table, markers = _exchange(probe, node_io, _scan(6_000_000_000 + k, **kwargs))
        assert table.width == 0 and len(parse_table(table)) == 0, name
        assert [m.action for m in markers.markers] == [Marker.DELETEALL], name
        if warning:
            assert spin_until(probe, lambda: warning in node.output(), 5.0), (name, node.output())
    # Throttled warnings still count every rejected scan.
    diagnostics = node_io[4]
    expected = {'rejected_no_valid_ranges': 2, 'rejected_bad_increment': 2,
                'rejected_too_few_points': 1, 'rejected_empty': 1, 'rejected_bad_angle_min': 1,
                'rejected_length_mismatch': 1}

    def counts_reached():
        for m in reversed(diagnostics.messages):
            values = {kv.key: kv.value for s in m.status for kv in s.values}
            return all(values.get(key) == str(n) for key, n in expected.items())
        return False
    assert spin_until(probe, counts_reached, 5.0), diagnostics.messages[-1:]
    assert node.alive()
    # Scan limits that make no sense are reported and the parameters used instead.
    table, _ = _exchange(probe, node_io, _scan(6_100_000_000, _corner_ranges(1), range_min=5.0,
                                               range_max=1.0))
    assert table.width == 2
    assert 'using only the parameters' in node.output()
    # A stamp going backwards (a looping bag) is reported; extraction goes on.
    table, _ = _exchange(probe, node_io, _scan(1_000_000_000, _corner_ranges(2)))
    assert table.width == 2
    assert spin_until(probe, lambda: 'went backwards' in node.output(), 5.0)
    # NaN ranges among valid ones are ignored with a warning; the lines are still found.
    assert 'NaN ranges; they are ignored' in node.output()
    assert node.alive()


@pytest.mark.parametrize('args, text', [
    (['-p', 'min_range:=5.0', '-p', 'max_range:=1.0'],
     "parameter 'max_range' must be greater than min_range"),
    (['-p', 'split_distance:=-1.0'], 'split_distance'),
    (['-p', 'min_line_points:=1'], 'min_line_points'),
])
def test_bad_parameters_exit_2(args, text):
    result = run_to_exit('line_extractor', ['--ros-args', *args])
    assert result.returncode == 2, result.stderr
    assert 'invalid parameter' in result.stderr and text in result.stderr
