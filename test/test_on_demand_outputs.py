"""Outputs made only while subscribed, over real DDS, in both layouts (line_extractor as its own
process, and inside the one-process sensing_graph): with nobody on /scan/lines/table and
/scan/lines a scan is counted, not extracted, and nothing is published; a subscriber gets the
table of every scan while it listens; once it leaves the node skips them again. Recording keeps
them (sensing_pipeline makes every output; the lockstep replay subscribes before it plays: its
bags are reproduced in test_replay.py); and the fusion's /odometry/filtered and /tf follow
publish_rate_hz in the shipped bags."""

from __future__ import annotations

import math

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray
from harness import REPO, Collector, NodeProcess, publish_paced, spin_until
from sensor_msgs.msg import LaserScan, PointCloud2
from test_lines_node import _corner_ranges, _scan, parse_table

from sensing_nodes.bags.stamps import stamp_reader
from sensing_nodes.bags.storage import BagReader
from sensing_nodes.core.lines import extract_lines
from sensing_nodes.core.timing import StampRate
from sensing_nodes.ros.conversions import scan_arrays, stamp_to_ns
from sensing_nodes.ros.qos import ESTIMATE_QOS, SENSOR_QOS
from sensing_nodes.topics import FUSED, SCAN, SCAN_LINES, SCAN_LINES_TABLE, TF, WHEEL_ODOM

LAYOUTS = {
    'separate_process': ('line_extractor', []),
    # the five processing nodes in one process (sensing_graph takes no --ros-args)
    'sensing_graph': ('sensing_graph', None),
}


@pytest.fixture(scope='module', params=list(LAYOUTS))
def running(request, probe):
    executable, extra = LAYOUTS[request.param]
    node = NodeProcess(executable, extra_args=extra or [])
    if extra is None:
        node.cmd = node.cmd[:1]
    with node:
        scans = probe.create_publisher(LaserScan, SCAN, SENSOR_QOS)
        diagnostics = Collector(probe, DiagnosticArray, '/diagnostics', 10)
        assert spin_until(probe, lambda: 'line_extractor' in {
            i.node_name for i in probe.get_subscriptions_info_by_topic(SCAN)}
            and scans.get_subscription_count() > 0, 60), node.output()
        spin_until(probe, lambda: False, 0.5)   # the node's reader matches our writer too
        yield node, scans, diagnostics
        diagnostics.close()
        probe.destroy_publisher(scans)


def _counts(diagnostics: Collector) -> dict[str, int]:
    """line_extractor's latest counters on /diagnostics (absent: 0)."""
    for msg in reversed(diagnostics.messages):
        for status in msg.status:
            if status.name == 'line_extractor':
                values = {kv.key: kv.value for kv in status.values}
                return {k: int(values.get(k, 0)) for k in ('scans', 'scans_unsubscribed')}
    return {'scans': 0, 'scans_unsubscribed': 0}


def _wait_counts(probe, diagnostics, condition, node) -> dict[str, int]:
    diagnostics.messages.clear()   # only what the node says from now on
    assert spin_until(probe, lambda: condition(_counts(diagnostics)), 10.0), (
        _counts(diagnostics), node.output())
    return _counts(diagnostics)


def _no_subscriber(probe) -> bool:
    return not any(probe.get_subscriptions_info_by_topic(t) for t in (SCAN_LINES,
                                                                      SCAN_LINES_TABLE))


def test_lines_are_made_only_while_subscribed(probe, running):
    node, scans, diagnostics = running
    assert _no_subscriber(probe)
    # Nobody listens: every scan is counted as unsubscribed, none extracted.
    publish_paced(probe, scans, [_scan(1_000_000_000 + k * 100_000_000, _corner_ranges(k))
                                 for k in range(5)], pause_s=0.05)
    before = _wait_counts(probe, diagnostics, lambda c: c['scans_unsubscribed'] >= 1, node)
    assert before['scans'] == 0, before

    # A subscriber of the table alone: each scan's table comes, equal to the extraction.
    tables = Collector(probe, PointCloud2, SCAN_LINES_TABLE, ESTIMATE_QOS)
    try:
        assert spin_until(probe, tables.matched, 20.0), node.output()
        msg = _scan(2_000_000_000, _corner_ranges(7))
        for attempt in range(20):   # the node's writer matches our reader in its own time
            scans.publish(msg)
            if spin_until(probe, lambda: tables.messages, 0.5):
                break
            msg = _scan(2_000_000_000 + (attempt + 1) * 100_000_000, _corner_ranges(7))
        assert tables.messages, node.output()
        table = tables.messages[0]
        assert stamp_to_ns(table.header.stamp) == stamp_to_ns(msg.header.stamp)
        ranges, angles = scan_arrays(msg)
        expected = extract_lines(ranges, angles, min_range=0.05, max_range=8.0)
        rows = parse_table(table)
        assert len(rows) == len(expected) == 2
        assert rows['r'] == pytest.approx([line.r for line in expected], abs=1e-12)
        assert rows['alpha'] == pytest.approx([line.alpha for line in expected], abs=1e-12)
        during = _wait_counts(probe, diagnostics, lambda c: c['scans'] >= 1, node)
    finally:
        tables.close()

    # The subscriber gone: scans are skipped again, the extracted count stays.
    assert spin_until(probe, lambda: _no_subscriber(probe), 10.0)
    spin_until(probe, lambda: False, 1.0)   # the node's writer sees the reader leave
    publish_paced(probe, scans, [_scan(3_000_000_000 + k * 100_000_000, _corner_ranges(k))
                                 for k in range(5)], pause_s=0.05)
    after = _wait_counts(probe, diagnostics,
                         lambda c: c['scans_unsubscribed'] > during['scans_unsubscribed'], node)
    assert after['scans'] == during['scans'], after
    assert node.alive()


@pytest.mark.parametrize('name', ['nominal', 'strong_errors'])
def test_shipped_bags_hold_every_scans_lines_and_the_fused_outputs_at_the_rate(name):
    """The shipped bags (the lockstep replay over DDS, whose recorder subscribes before it
    plays): a table and markers for every scan; /odometry/filtered at publish_rate_hz 30 of
    stamp time (the first output in each 1/30 s) plus the scan matches', /tf at the same
    stamps."""
    reader = BagReader(REPO / 'bags' / name)
    topics = {SCAN, SCAN_LINES, SCAN_LINES_TABLE, FUSED, TF, WHEEL_ODOM}
    stamps: dict[str, list[int]] = {topic: [] for topic in topics}
    for topic, bag_ns, raw in reader.raw(topics):
        stamps[topic].append(stamp_reader(reader.topics[topic].msgtype)(raw, bag_ns))
    assert len(stamps[SCAN]) > 0
    assert stamps[SCAN_LINES_TABLE] == stamps[SCAN_LINES] == stamps[SCAN]
    fused = stamps[FUSED]
    assert fused == sorted(fused) and len(set(fused)) == len(fused)
    assert stamps[TF] == fused
    # The matches (local map mode: stamped mid-sweep) go out at their own stamps; of the
    # outputs at the wheels' stamps (50 Hz), the first in each 1/30 s of stamp time.
    wheels = set(stamps[WHEEL_ODOM])
    at_wheels = [s for s in fused if s in wheels]
    periods = [s // StampRate(30.0).period_ns for s in at_wheels]
    assert len(set(periods)) == len(periods)
    seconds = (fused[-1] - fused[0]) * 1e-9
    assert len(at_wheels) / seconds == pytest.approx(30.0, rel=0.03)
    assert len(fused) - len(at_wheels) <= len(stamps[SCAN])
    assert math.isclose(len(stamps[SCAN]) / seconds, 10.0, rel_tol=0.05)
    assert np.all(np.diff(fused) > 0)
