"""icp_plot renders a scan pair from a CARMEN log or a bag; bad input exits cleanly."""

import math
import re

import numpy as np
import pytest
from harness import REPO, run_to_exit
from sensor_msgs.msg import LaserScan

from sensing_nodes.bags.storage import BagWriter
from sensing_nodes.core.geometry.scan import beam_angles
from sensing_nodes.core.geometry.se2 import compose
from sensing_nodes.core.sim.world import load_world, raycast
from sensing_nodes.paths import config_file
from sensing_nodes.ros.conversions import float32_array, ns_to_stamp

CARMEN = (REPO / '..' / 'shared' / 'datasets' / 'carmen').resolve()
PNG = b'\x89PNG\r\n\x1a\n'


def write_scan_bag(path, poses):
    world = load_world(config_file('default_world.yaml'))
    angles = beam_angles(-math.pi, 2 * math.pi / 360, 360)
    with BagWriter(path) as bag:
        for k, pose in enumerate(poses):
            msg = LaserScan()
            stamp = 1_700_000_000_000_000_000 + k * 100_000_000
            msg.header.stamp = ns_to_stamp(stamp)
            msg.header.frame_id = 'laser'
            msg.angle_min, msg.angle_increment = -math.pi, 2 * math.pi / 360
            msg.angle_max = msg.angle_min + 359 * msg.angle_increment
            msg.range_min, msg.range_max = 0.12, 8.0
            ranges = raycast(world.segments, pose[:2], angles + pose[2])
            msg.ranges = float32_array(np.where(ranges > 8.0, np.inf, ranges))
            bag.write('/scan', msg, stamp)


def test_plot_from_a_bag(tmp_path):
    start = (-2.0, -2.0, 0.1)
    write_scan_bag(tmp_path / 'bag', [start, compose(start, (0.15, 0.05, 0.1))])
    out = tmp_path / 'pair.png'
    result = run_to_exit('icp_plot', ['--bag', str(tmp_path / 'bag'), '--out', str(out)])
    assert result.returncode == 0, result.stderr
    assert out.read_bytes()[:8] == PNG
    assert 'converged=True' in result.stdout
    # The printed motion is the true one: x=0.15 m, y=0.05 m, yaw=5.73 deg.
    found = re.search(r'x=(\S+) m, y=(\S+) m, yaw=(\S+) deg', result.stdout)
    x, y, yaw = (float(v) for v in found.groups())
    assert abs(x - 0.15) < 2e-3 and abs(y - 0.05) < 2e-3 and abs(yaw - math.degrees(0.1)) < 0.05


@pytest.mark.skipif(not CARMEN.is_dir(), reason=f'CARMEN logs not found at {CARMEN}')
def test_plot_from_a_carmen_log(tmp_path):
    out = tmp_path / 'pair.png'
    result = run_to_exit('icp_plot', [
        '--carmen', str(CARMEN / 'freiburg-101-corrected.log.gz'), '--index', '10',
        '--guess', 'reference', '--out', str(out)])
    assert result.returncode == 0, result.stderr
    assert out.read_bytes()[:8] == PNG
    assert 'scans 10 -> 11' in result.stdout


def test_bad_input_and_arguments(tmp_path):
    missing = run_to_exit('icp_plot', ['--carmen', str(tmp_path / 'none.log'), '--out',
                                       str(tmp_path / 'x.png')])
    assert missing.returncode == 1 and 'icp_plot:' in missing.stderr
    start = (-2.0, -2.0, 0.1)
    write_scan_bag(tmp_path / 'bag', [start])
    short = run_to_exit('icp_plot', ['--bag', str(tmp_path / 'bag'), '--out',
                                     str(tmp_path / 'x.png')])
    assert short.returncode == 1 and 'need index 1' in short.stderr
    usage = run_to_exit('icp_plot', ['--out', str(tmp_path / 'x.png')])
    assert usage.returncode == 2
    bad_step = run_to_exit('icp_plot', ['--bag', str(tmp_path / 'bag'), '--step', '0',
                                        '--out', str(tmp_path / 'x.png')])
    assert bad_step.returncode == 2 and '--step' in bad_step.stderr
