"""Local-map scan matching without ROS (core/local_map.py, core/deskew.py, core/correlative.py,
core/scan_matching.LocalMapScanMatcher): the map's cells and their search, deskewing, accuracy
on the simulated route against the keyframe method, failing scans (the matcher never runs
away), a featureless corridor (honest degeneracy) and the map anchor of
/scan_match/keyframe_odom."""

import dataclasses
import math

import numpy as np
import pytest
from scipy.spatial import cKDTree

from sensing_nodes.bench.icp.accuracy import route_errors
from sensing_nodes.bench.icp.datasets import FAST_TURNS_ROUTE, simulated_run
from sensing_nodes.core import icp
from sensing_nodes.core.correlative import correlative_search
from sensing_nodes.core.deskew import deskew, twist_motion, twist_motions
from sensing_nodes.core.geometry.se2 import between, compose, transform_points, wrap_angle
from sensing_nodes.core.local_map import LocalMap, LocalMapSettings
from sensing_nodes.core.scan_matching import LocalMapScanMatcher
from sensing_nodes.core.sim.inputs import (
    match_scans,
    matcher_settings,
    scan_inputs,
)
from sensing_nodes.core.sim.simulator import SimParams, make_route, simulate
from sensing_nodes.core.sim.world import load_world, raycast
from sensing_nodes.paths import config_file

ROOM = load_world(config_file('default_world.yaml'))
CORRIDOR = load_world(config_file('corridor_world.yaml'))
ANGLES = -math.pi + 2 * math.pi / 360 * np.arange(360)


def room_scan(laser_pose, world=ROOM, noise=0.0, rng=None):
    """Points (laser frame) of a 360-beam scan from laser_pose (map frame), 0.12-8 m."""
    ranges = raycast(world.segments, laser_pose[:2], ANGLES + laser_pose[2])
    if noise:
        ranges = ranges + rng.normal(0.0, noise, ranges.size)
    keep = np.isfinite(ranges) & (ranges > 0.12) & (ranges < 8.0)
    return np.column_stack((ranges[keep] * np.cos(ANGLES[keep]),
                            ranges[keep] * np.sin(ANGLES[keep])))


# --- the map ---------------------------------------------------------------------------------

def test_cells_take_points_up_to_their_cap_and_are_pruned_by_distance_and_count():
    local = LocalMap(LocalMapSettings(cell_m=0.1, max_points_per_cell=3, radius_m=5.0,
                                      max_cells=4))
    wall = np.column_stack((np.full(5, 2.05), 0.1 * np.arange(5) + 0.05))   # 5 cells, x=2.05
    normals = np.tile([1.0, 0.0], (5, 1))
    for _ in range(5):
        local.insert(wall, normals, np.ones(5))
    assert len(local) == 5 and local.points == 15                        # capped at 3 a cell
    np.testing.assert_allclose(local.target().points, wall[np.argsort(wall[:, 1])])
    assert local.prune((0.0, 0.0)) == 1 and len(local) == 4             # max_cells: furthest
    assert local.prune((10.0, 0.0)) == 4 and len(local) == 0            # all beyond radius


def test_cell_normals_are_what_their_scans_agree_on():
    # A wall along y seen twice: every cell's normal is +-x and line-like; a corner's points,
    # not line-like in their scan, make their cell act point-to-point.
    local = LocalMap()
    rng = np.random.default_rng(0)
    for _ in range(2):
        wall = np.column_stack((2.0 + rng.normal(0, 0.005, 40), np.linspace(-1, 1, 40)))
        normals, planarity = icp.scan_normals(wall)
        local.insert(wall, normals, planarity)
    target = local.target()
    assert np.all(np.abs(target.normals[:, 0]) > 0.99)
    assert np.all(target.planarity > 0.9)
    local.insert(np.array([[3.05, 0.05]]), np.array([[0.0, 1.0]]), np.array([0.1]))
    corner = local.target()
    lone = np.flatnonzero(np.hypot(*(corner.points - [3.05, 0.05]).T) < 1e-9)
    np.testing.assert_array_equal(corner.information[lone], [[1.0, 0.0, 1.0]])


@pytest.mark.parametrize('gate', [0.05, 0.1, 0.35, 2.0])
def test_the_cells_find_the_nearest_point_as_a_kd_tree_does(gate):
    rng = np.random.default_rng(3)
    local = LocalMap(LocalMapSettings(cell_m=0.1))
    points = rng.uniform(-3, 3, (600, 2))
    local.insert(points, np.tile([1.0, 0.0], (600, 1)), np.ones(600))
    target = local.target()
    queries = rng.uniform(-4, 4, (500, 2))
    keep, index = icp._nearest(target, icp._complex(queries), gate)
    distance, expected = cKDTree(target.points).query(queries, distance_upper_bound=gate)
    np.testing.assert_array_equal(keep, distance < gate)
    found = np.hypot(*(target.points[index[keep]] - queries[keep]).T)
    np.testing.assert_allclose(found, distance[keep], rtol=0, atol=1e-12)


# --- deskewing -------------------------------------------------------------------------------

def test_twist_motions_are_the_exact_arcs_of_a_constant_twist():
    # The motions of a constant twist form a one-parameter group: m(a + b) = m(a) ⊕ m(b),
    # m(-t) = m(t)⁻¹, and m(t) / t tends to the twist.
    twist = (0.3, 0.05, 1.2)
    a, b = 0.037, 0.061
    ma, mb, mab, mneg = twist_motions(twist, np.array([a, b, a + b, -a]))
    np.testing.assert_allclose(compose(tuple(ma), tuple(mb)), mab, atol=1e-15)
    np.testing.assert_allclose(compose(tuple(ma), tuple(mneg)), (0, 0, 0), atol=1e-15)
    tiny = twist_motions(twist, np.array([1e-7]))[0] / 1e-7
    np.testing.assert_allclose(tiny, twist, rtol=1e-6)
    straight = twist_motions((0.3, 0.0, 0.0), np.array([0.5]))[0]
    np.testing.assert_allclose(straight, (0.15, 0.0, 0.0), atol=1e-15)
    for t in (a, -a, 1e-12):                        # the one-pose form agrees
        np.testing.assert_allclose(twist_motion(twist, t), twist_motions(twist, np.array([t]))[0],
                                   atol=1e-15)


def test_deskewing_with_the_sweeps_motion_gives_back_the_scan_at_the_stamp():
    # Laser 0.1 m ahead of a base turning at 1 rad/s and driving at 0.5 m/s: each beam taken
    # 0.1 s / 360 after the previous one, deskewed to the stamp, lands on the scan taken all at
    # once from the pose at the stamp.
    mount, twist, base = (0.1, 0.0, 0.0), (0.5, 0.0, 1.0), (-2.0, -1.5, 0.3)
    times = np.arange(360) * (0.1 / 360)
    motions = twist_motions(twist, times)
    swept = []
    for angle, motion in zip(ANGLES, motions):
        laser = compose(compose(base, tuple(motion)), mount)
        r = raycast(ROOM.segments, laser[:2], np.array([angle + laser[2]]))[0]
        swept.append((r * math.cos(angle), r * math.sin(angle)))
    swept = np.array(swept)
    fixed = deskew(swept, twist, times, mount)
    laser = compose(base, mount)
    # Each deskewed point lies on a wall of the world seen from the pose at the stamp.
    on_map = transform_points(laser, fixed)
    segments = ROOM.segments
    a, b = segments[:, :2], segments[:, 2:]
    t = np.clip(((on_map[:, None] - a) * (b - a)).sum(-1) / ((b - a) ** 2).sum(-1), 0, 1)
    distance = np.linalg.norm(on_map[:, None] - (a + t[..., None] * (b - a)), axis=-1).min(1)
    assert distance.max() < 1e-9
    raw = np.linalg.norm(transform_points(laser, swept)[:, None] - (a + t[..., None] * (b - a)),
                         axis=-1).min(1)
    assert raw.max() > 0.05                         # not deskewed: centimetres off


# --- accuracy on the simulated route ---------------------------------------------------------

@pytest.fixture(scope='module')
def route_run():
    """40 s of the default route (still start, the first straight and part of the turn)."""
    return simulated_run(seed=0, laps=40.0 / make_route(SimParams()).period_s)


def test_the_local_map_holds_the_heading_the_keyframe_chain_loses(route_run):
    local = route_errors(route_run, matcher_settings(route_run.params))
    chain = route_errors(route_run, matcher_settings(route_run.params, mode='keyframe'))
    # docs/nodes/icp_matcher.md: 8 seeds of the whole route pool at 0.042 deg and 1.5 mm.
    assert local['rms_heading_deg'] < 0.06 and local['rms_position_m'] < 0.004, local
    assert local['fallback'] == 0
    assert chain['rms_heading_deg'] > 2.0 * local['rms_heading_deg'], (chain, local)


def test_deskewing_cuts_the_heading_error_of_fast_turns():
    params = dataclasses.replace(SimParams(), route=FAST_TURNS_ROUTE[:6])
    run = simulated_run(seed=1, params=params)
    settings = matcher_settings(params)
    deskewed = route_errors(run, settings)
    skewed = route_errors(run, settings, deskew=False)
    assert deskewed['rms_heading_deg'] <= 0.3 * skewed['rms_heading_deg'], (deskewed, skewed)
    own = route_errors(run, settings, odometry=False)
    assert own['rms_heading_deg'] <= 0.3 * skewed['rms_heading_deg'], (own, skewed)


# --- never runs away -------------------------------------------------------------------------

def _feed(run, bad, kind, odometry, settings):
    """The matcher over a run with the scans whose index is in `bad` replaced by failing ones
    (no beam times, so no sweep motion); returns stamps, steps, the truth at the stamps and
    the odometry's motion since the previous scan given with each (zero without odometry)."""
    rng = np.random.default_rng(7)
    matcher = LocalMapScanMatcher(settings)
    stamps, steps, given = [], [], []
    for i, (stamp, points, predicted, times, sweep) in enumerate(scan_inputs(run)):
        if i in bad:
            truth = run.truth_at(stamp)
            laser = compose(tuple(truth), settings.laser_pose)
            points, times, sweep = {
                'empty': np.zeros((0, 2)),
                'random': rng.uniform(-4, 4, (300, 2)),
                'other_room': room_scan((laser[0] + 30.0, 0.0, laser[2]), CORRIDOR),
            }[kind], None, None
        if not odometry:
            predicted = sweep = None
        stamps.append(stamp)
        given.append(predicted or (0.0, 0.0, 0.0))
        steps.append(matcher.process(stamp, points, predicted, times, sweep))
    return np.array(stamps), steps, run.truth_at(np.array(stamps)), np.array(given)


@pytest.fixture(scope='module')
def moving_run():
    """21 s of the route: the still start and 15 s of its first straight at 0.25 m/s."""
    return simulate(SimParams(), ROOM, 21.0, seed=2)


@pytest.mark.parametrize('odometry', [True, False])
@pytest.mark.parametrize('kind', ['empty', 'random', 'other_room'])
def test_failing_scans_never_push_a_step_beyond_the_limits_and_the_pose_comes_back(
        moving_run, kind, odometry):
    settings = matcher_settings(moving_run.params, max_speed_m_s=1.0, max_yaw_rate_rad_s=1.5)
    bad = set(range(150, 175))                     # 2.5 s of failing scans at 0.25 m/s
    stamps, steps, truth, given = _feed(moving_run, bad, kind, odometry, settings)
    poses = np.array([step.pose for step in steps])
    dt = np.diff(stamps) * 1e-9
    moves = np.array([between(tuple(a), tuple(b)) for a, b in zip(poses[:-1], poses[1:])])
    # Each published step within the limits of the odometry's motion (without odometry: of
    # standing still).
    off = moves - given[1:]
    assert np.all(np.hypot(off[:, 0], off[:, 1]) <= settings.max_speed_m_s * dt + 1e-9)
    assert np.all(np.abs(wrap_angle(off[:, 2])) <= settings.max_yaw_rate_rad_s * dt + 1e-9)
    failed = sum(step.status == 'fallback' for step in steps)
    assert failed >= len(bad) - 1, failed
    # Within 2 s of good scans returning the published pose is on the truth again.
    reference = np.array([between(tuple(truth[0]), tuple(p)) for p in truth])
    lost = np.hypot(*(poses[150:175, :2] - reference[150:175, :2]).T).max()
    assert lost > (0.0 if odometry else 0.2)       # without odometry the pose was left behind
    after = 175 + 20
    error = np.hypot(*(poses[after:, :2] - reference[after:, :2]).T)
    heading = np.abs(wrap_angle(poses[after:, 2] - reference[after:, 2]))
    assert error.max() < 0.02 and np.degrees(heading.max()) < 0.5, (error.max(), heading.max())


def test_a_scan_found_far_from_the_prediction_is_reacquired():
    # A map of the room from one pose; the scan seen from 0.6 m and 100 deg away.
    truth_laser, guess = (-2.0, -1.5, 0.4), (-2.5, -1.1, 0.4 - math.radians(100))
    target = icp.prepare_target(transform_points(truth_laser, room_scan(truth_laser)),
                                search='kd_tree')
    found = correlative_search(room_scan(truth_laser), target, guess, 1.0, math.pi)
    assert found is not None
    assert math.hypot(found[0] - truth_laser[0], found[1] - truth_laser[1]) < 0.08
    assert abs(wrap_angle(found[2] - truth_laser[2])) < math.radians(1.5)
    assert correlative_search(np.random.default_rng(0).uniform(-4, 4, (200, 2)), target, guess,
                              1.0, math.pi) is None          # random points match nothing


# --- a featureless corridor ------------------------------------------------------------------

@pytest.fixture(scope='module')
def corridor_run():
    params = dataclasses.replace(SimParams(), start_x_m=-20.0, start_y_m=0.0,
                                 route=('wait 1', 'straight 8 0.5', 'wait 1'))
    return simulate(params, CORRIDOR, make_route(params).period_s, seed=0)


def test_a_corridor_is_reported_degenerate_along_it_and_the_odometry_moves_the_pose(
        corridor_run):
    run = corridor_run
    stamps, steps = match_scans(run, matcher_settings(run.params))
    matched = [s for s in steps if s.status == 'matched']
    assert len(matched) == len(steps) - 1
    ratio = np.array([s.keyframe.covariance[0, 0] / s.keyframe.covariance[1, 1]
                      for s in matched])
    assert np.all(ratio >= 100.0), ratio.min()
    assert sum('degenerate' in s.events for s in steps) >= 0.95 * len(matched)
    truth = run.truth_at(stamps)
    error = np.array([s.pose for s in steps])[-1] - (truth[-1] - truth[0])
    assert abs(error[0]) < 0.02 and abs(error[1]) < 0.005         # along from the wheels


def test_without_odometry_a_corridor_stops_the_pose_along_it_but_never_runs_away(corridor_run):
    run = corridor_run
    settings = matcher_settings(run.params)
    stamps, steps = match_scans(run, settings, odometry=False)
    poses = np.array([s.pose for s in steps])
    truth = run.truth_at(stamps)
    moves = np.array([between(tuple(a), tuple(b)) for a, b in zip(poses[:-1], poses[1:])])
    dt = np.diff(stamps) * 1e-9
    assert np.all(np.hypot(moves[:, 0], moves[:, 1]) <= settings.max_speed_m_s * dt + 1e-9)
    # Nothing says how far it went: the pose stays, across the corridor it stays right.
    assert np.abs(poses[:, 1] - (truth[:, 1] - truth[0, 1])).max() < 0.005
    assert np.abs(poses[:, 0]).max() < 0.05
    assert steps[-1].covariance[0, 0] > 100.0 * steps[-1].covariance[1, 1]


# --- the map anchor of /scan_match/keyframe_odom ---------------------------------------------

def test_matches_are_relative_to_an_anchor_kept_while_the_robot_stays_near_it(route_run):
    settings = matcher_settings(route_run.params, anchor_distance_m=2.0)
    stamps, steps = match_scans(route_run, settings)
    published = dict(zip(stamps.tolist(), steps))
    anchors = [s.stamp_ns for s in steps if s.new_keyframe]
    assert 2 <= len(anchors) <= 6                       # 40 s, ~5 m of travel, every 2 m
    for step in steps[1:]:
        anchor = published[step.keyframe.keyframe_stamp_ns]
        assert step.keyframe.keyframe_stamp_ns in anchors
        np.testing.assert_allclose(compose(anchor.pose, step.keyframe.pose), step.pose,
                                   atol=1e-9)
        assert math.hypot(*step.keyframe.pose[:2]) <= 2.0 + 0.05
        eigen = np.linalg.eigvalsh(step.keyframe.covariance)
        assert eigen.min() > 0 and eigen.max() < 1e-4
