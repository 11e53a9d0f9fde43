"""Line extraction on the real CARMEN logs, and the lines_plot tool on a log and on a bag."""

import math
from pathlib import Path

import numpy as np
import pytest
from harness import run_to_exit
from sensor_msgs.msg import LaserScan

from sensing_nodes.bags.carmen import read_carmen
from sensing_nodes.bags.storage import BagWriter
from sensing_nodes.core.lines import extract_lines
from sensing_nodes.core.sim.world import raycast
from sensing_nodes.ros.conversions import ns_to_stamp

CARMEN = Path(__file__).resolve().parents[2] / 'shared' / 'datasets' / 'carmen'
LOGS = ['aces-corrected.log.gz', 'freiburg-101-corrected.log.gz']
needs_logs = pytest.mark.skipif(not CARMEN.is_dir(), reason=f'CARMEN logs not found in {CARMEN}')


@needs_logs
@pytest.mark.parametrize('name', LOGS)
def test_every_scan_of_the_real_logs(name):
    log = read_carmen(CARMEN / name)
    counts = []
    for ranges in log.ranges_without_returns():
        angles = log.scan_angles(ranges.size)
        lines = extract_lines(ranges, angles)
        counts.append(len(lines))
        for line in lines:
            assert line.r >= 0.0 and -math.pi < line.alpha <= math.pi
            assert np.all(np.isfinite(line.covariance)) and np.all(
                np.linalg.eigvalsh(line.covariance) > 0
            )
            assert 0 <= line.first < line.last < ranges.size      # 180 degrees: never wraps
            assert line.point_count >= 6 and line.length >= 0.2
            # Every fitted point is within split_distance (0.05 m) of its line; dropping end
            # points after splitting may tilt the line by a few millimetres more.
            beams = np.arange(line.first, line.last + 1)
            beams = beams[np.isfinite(ranges[beams])]
            d = ranges[beams] * np.cos(angles[beams] - line.alpha) - line.r
            assert np.abs(d).max() <= 0.06
    counts = np.array(counts)
    print(f'{name}: {len(counts)} scans, lines per scan min {counts.min()} median '
          f'{np.median(counts):.0f} max {counts.max()}, total {counts.sum()}')
    assert len(counts) == len(log.scans) and len(counts) > 200
    assert np.median(counts) >= 3                 # indoor scans: several walls each


@needs_logs
def test_lines_plot_on_a_carmen_log(tmp_path):
    out = tmp_path / 'aces.png'
    result = run_to_exit('lines_plot', ['--carmen', str(CARMEN / LOGS[0]), '--index', '200',
                                        '--out', str(out)])
    assert result.returncode == 0, result.stderr
    assert 'scan 200:' in result.stdout and ' lines -> ' in result.stdout
    assert out.read_bytes()[:8] == b'\x89PNG\r\n\x1a\n'


def test_lines_plot_on_a_bag(tmp_path):
    angles = -math.pi / 2 + math.radians(1.0) * np.arange(181)
    walls = np.array([[2.0, -3.0, 2.0, 1.0], [2.0, 1.0, -2.0, 1.0]])
    with BagWriter(tmp_path / 'bag') as bag:
        for k in range(3):
            msg = LaserScan()
            msg.header.stamp = ns_to_stamp(1_000_000_000 + k * 100_000_000)
            msg.header.frame_id = 'laser'
            msg.angle_min, msg.angle_increment = (
                float(np.float32(angles[0])),
                float(np.float32(math.radians(1.0))),
            )
            msg.angle_max = float(np.float32(angles[-1]))
            msg.range_min, msg.range_max = 0.1, 8.0
            msg.ranges = raycast(walls, (0.0, 0.0), angles).astype(np.float32).tolist()
            bag.write('/scan', msg, 1_000_000_000 + k * 100_000_000)
    out = tmp_path / 'bag.png'
    result = run_to_exit(
        'lines_plot', ['--bag', str(tmp_path / 'bag'), '--index', '1', '--out', str(out)]
    )
    assert result.returncode == 0, result.stderr
    assert '/scan #1' in result.stdout and ': 2 lines -> ' in result.stdout
    assert out.read_bytes()[:4] == b'\x89PNG'
    bad = run_to_exit(
        'lines_plot', ['--bag', str(tmp_path / 'bag'), '--index', '3', '--out', str(out)]
    )
    assert bad.returncode == 1 and 'scan index 3 out of range: there are 3 scans' in bad.stderr
