"""The shared core: SE(2) algebra, angle wrapping, scan conversion, worlds, CARMEN reading."""

import gzip
import math

import numpy as np
import pytest

from sensing_nodes.bags.carmen import read_carmen
from sensing_nodes.core.geometry import se2
from sensing_nodes.core.geometry.scan import scan_to_points, valid_ranges
from sensing_nodes.core.sim.world import load_world, raycast, world_from_dict
from sensing_nodes.core.timing import StampStep, classify_step
from sensing_nodes.paths import config_file


def test_wrap_angle_range_is_half_open_at_minus_pi():
    assert se2.wrap_angle(math.pi) == pytest.approx(math.pi)
    assert se2.wrap_angle(-math.pi) == pytest.approx(math.pi)
    assert se2.wrap_angle(3 * math.pi / 2) == pytest.approx(-math.pi / 2)
    wrapped = se2.wrap_angle(np.linspace(-20, 20, 1001))
    assert np.all(wrapped > -math.pi) and np.all(wrapped <= math.pi)


def test_compose_inverse_between_round_trip():
    a, b = (1.0, 2.0, 0.5), (-0.3, 0.7, 2.9)
    assert se2.compose(a, se2.inverse(a)) == pytest.approx((0.0, 0.0, 0.0), abs=1e-12)
    assert se2.compose(a, se2.between(a, b)) == pytest.approx(b)
    # Driving 1 m forward after turning left by 90 degrees ends at (0, 1).
    assert se2.compose((0.0, 0.0, math.pi / 2), (1.0, 0.0, 0.0)) == pytest.approx(
        (0.0, 1.0, math.pi / 2)
    )


def test_transform_points_matches_compose():
    pose = (0.5, -1.0, 0.3)
    points = np.array([[1.0, 0.0], [0.2, -2.0]])
    expected = [se2.compose(pose, (x, y, 0.0))[:2] for x, y in points]
    assert se2.transform_points(pose, points) == pytest.approx(np.array(expected))


def test_compose_covariance_matches_numerical_jacobian():
    a, b = (1.0, 2.0, 0.5), (0.4, -0.2, 0.3)
    j_a, j_b = se2.compose_jacobians(a, b)
    eps = 1e-7
    for i in range(3):
        da, db = list(a), list(b)
        da[i] += eps
        db[i] += eps
        num_a = (np.array(se2.compose(da, b)) - se2.compose(a, b)) / eps
        num_b = (np.array(se2.compose(a, db)) - se2.compose(a, b)) / eps
        assert j_a[:, i] == pytest.approx(num_a, abs=1e-6)
        assert j_b[:, i] == pytest.approx(num_b, abs=1e-6)


def test_scan_to_points_keeps_only_valid_beams_rep117():
    ranges = np.array([1.0, np.inf, -np.inf, np.nan, 0.05, 2.0])
    angles = np.radians([0, 10, 20, 30, 40, 90])
    points, index = scan_to_points(ranges, angles, range_min=0.1, range_max=10.0)
    assert index.tolist() == [0, 5]
    assert points == pytest.approx(np.array([[1.0, 0.0], [0.0, 2.0]]), abs=1e-12)
    assert valid_ranges(ranges, 0.1, 10.0).tolist() == [True, False, False, False, False, True]
    with pytest.raises(ValueError, match='differ in length'):
        scan_to_points(ranges, angles[:-1])


def test_classify_step():
    assert classify_step(None, 5, 1.0) is StampStep.FIRST
    assert classify_step(5, 5, 1.0) is StampStep.REPEATED
    assert classify_step(5, 4, 1.0) is StampStep.BACKWARDS
    assert classify_step(0, 1_000_000_001, 1.0) is StampStep.GAP
    assert classify_step(0, 1_000_000_000, 1.0) is StampStep.OK


def test_raycast_exact_distances_and_no_return():
    wall = np.array([[2.0, -5.0, 2.0, 5.0]])
    ranges = raycast(wall, (0.0, 0.0), np.radians([0.0, 60.0, 90.0, 180.0]))
    assert ranges[0] == pytest.approx(2.0, abs=1e-12)
    assert ranges[1] == pytest.approx(4.0, abs=1e-12)
    assert np.isinf(ranges[2]) and np.isinf(ranges[3])


def test_raycast_occlusion_takes_nearest_wall():
    walls = np.array([[3.0, -1.0, 3.0, 1.0], [1.5, -0.1, 1.5, 0.1]])
    assert raycast(walls, (0.0, 0.0), [0.0])[0] == pytest.approx(1.5)


def test_default_world_is_closed_room():
    world = load_world(config_file('default_world.yaml'))
    ranges = raycast(world.segments, (-3.0, -2.2), np.linspace(-np.pi, np.pi, 720, endpoint=False))
    assert np.all(np.isfinite(ranges)), 'every beam from inside the room hits a wall'


@pytest.mark.parametrize('data, message', [
    ({'walls': [[0, 0, 1]]}, r'walls\[0\]'),
    ({'walls': [[0, 0, 0, 0]]}, 'zero length'),
    ({'polygons': [[[0, 0], [1, 1]]]}, r'polygons\[0\]'),
    ({}, 'no walls'),
    ([1, 2], 'mapping'),
])
def test_malformed_world_is_rejected_with_the_entry_named(data, message):
    with pytest.raises(ValueError, match=message):
        world_from_dict(data)


def test_missing_world_file_names_the_path(tmp_path):
    with pytest.raises(ValueError, match='nope.yaml'):
        load_world(tmp_path / 'nope.yaml')


def test_carmen_reader_parses_records_and_reports_bad_lines(tmp_path):
    log = tmp_path / 'tiny.log.gz'
    with gzip.open(log, 'wt') as f:
        f.write('# comment\n')
        f.write('PARAM robot_frontlaser_offset 0.0 nohost 0\n')
        f.write('ODOM 1 2 0.5 0.1 0.0 0 10.0 host 10.0\n')
        f.write('FLASER 3 1.0 2.0 50.0 1 2 0.5 1 2 0.5 10.5 host 10.5\n')
        f.write('FLASER 3 1.0 oops 50.0 1 2 0.5 1 2 0.5 11.0 host 11.0\n')
        f.write('FLASER 4 1.0 2.0\n')
    parsed = read_carmen(log)
    assert len(parsed.scans) == 1
    assert parsed.scans[0].ranges.tolist() == [1.0, 2.0, 50.0]
    assert parsed.scans[0].pose == (1.0, 2.0, 0.5) and parsed.scans[0].time_s == 10.5
    assert parsed.odom_pose.tolist() == [[1.0, 2.0, 0.5]]
    assert [number for number, _ in parsed.errors] == [5, 6]
    assert parsed.params['robot_frontlaser_offset'] == '0.0'
    assert parsed.scan_angles(180)[0] == pytest.approx(-np.pi / 2)
    assert parsed.scan_angles(180)[90] == pytest.approx(0.0)
