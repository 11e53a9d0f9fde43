"""core.lines: worked numbers, geometry, bad input, covariance consistency, accuracy on the default
world."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sensing_nodes.bench.lines import POSES as BENCH_POSES
from sensing_nodes.core.geometry.se2 import inverse, transform_points, wrap_angle
from sensing_nodes.core.lines import Line, extract_lines, fit_line
from sensing_nodes.core.sim.world import load_world, raycast
from sensing_nodes.paths import config_file

WORKED = np.array([(0, 0.1), (1, -0.1), (2, 0.0), (3, 0.1), (4, -0.1)], dtype=float)


def polar(points):
    """(ranges, angles) of points seen from the origin."""
    points = np.asarray(points, dtype=float)
    return np.hypot(points[:, 0], points[:, 1]), np.arctan2(points[:, 1], points[:, 0])


def scan_of(segments, angles, origin=(0.0, 0.0)):
    return raycast(np.asarray(segments, dtype=float), origin, angles)


def distances(line: Line, points):
    return np.asarray(points) @ [math.cos(line.alpha), math.sin(line.alpha)] - line.r


# ---------------------------------------------------------------- worked numbers

def test_worked_example_horizontal_line_has_residual_0_04():
    # Constrained to a horizontal line (alpha = 90 deg) the best r is the mean y = 0.00 ...
    r = WORKED[:, 1].mean()
    assert r == pytest.approx(0.0, abs=1e-12)
    # ... and the residual sum of squares is 0.04, the lesson's hand example.
    assert np.sum((WORKED[:, 1] - r) ** 2) == pytest.approx(0.04, abs=1e-12)


def test_worked_example_perpendicular_fit_is_tilted():
    fit = fit_line(WORKED)
    assert math.degrees(fit.alpha) == pytest.approx(88.850, abs=0.001)
    assert fit.r == pytest.approx(0.04014, abs=1e-5)
    assert fit.residual == pytest.approx(0.035986, abs=1e-6)
    # The perpendicular residual is the sum of squared distances to that line, and below 0.04.
    d = WORKED @ [math.cos(fit.alpha), math.sin(fit.alpha)] - fit.r
    assert np.sum(d * d) == pytest.approx(fit.residual, rel=1e-9)
    assert fit.residual < 0.04


def test_fit_from_sums_matches_eigen_decomposition():
    rng = np.random.default_rng(3)
    for _ in range(20):
        p = (
            rng.normal(size=(50, 2)) * [3.0, 0.2] @ np.array([[0.6, 0.8], [-0.8, 0.6]])
            + rng.normal(size=2) * 5
        )
        fit = fit_line(p)
        centred = p - p.mean(axis=0)
        values, vectors = np.linalg.eigh(centred.T @ centred)
        normal = vectors[:, 0]
        r = p.mean(axis=0) @ normal
        if r < 0:
            normal, r = -normal, -r
        assert fit.r == pytest.approx(r, abs=1e-9)
        assert fit.alpha == pytest.approx(math.atan2(normal[1], normal[0]), abs=1e-9)
        assert fit.residual == pytest.approx(values[0], rel=1e-9)


# ---------------------------------------------------------------- geometry

def test_noiseless_corner_gives_two_lines_meeting_at_the_corner():
    angles = np.linspace(-math.pi / 4, 3 * math.pi / 4, 181)
    ranges = scan_of([[2, -2, 2, 3], [2, 3, -3, 3]], angles)            # corner at (2, 3)
    lines = extract_lines(ranges, angles)
    assert len(lines) == 2
    a, b = lines
    assert (a.r, a.alpha) == pytest.approx((2.0, 0.0), abs=1e-9)
    assert (b.r, b.alpha) == pytest.approx((3.0, math.pi / 2), abs=1e-9)
    # The two fitted lines intersect at the corner, and their facing endpoints are there too
    # (within one beam spacing at that range: 3.6 m x 1 deg = 6.3 cm).
    normals = np.array(
        [[math.cos(a.alpha), math.sin(a.alpha)], [math.cos(b.alpha), math.sin(b.alpha)]]
    )
    corner = np.linalg.solve(normals, [a.r, b.r])
    assert corner == pytest.approx([2.0, 3.0], abs=1e-9)
    assert math.dist(a.end, corner) < 0.063
    assert math.dist(b.start, corner) < 0.063
    # Together they cover every beam.
    assert a.first == 0 and b.last == 180 and b.first - a.last <= 1


@pytest.mark.parametrize('normal_deg', [-180, -135, -90, -45, 0, 30, 90, 150, 180])
def test_walls_in_every_direction_without_singularity(normal_deg):
    phi = math.radians(normal_deg)
    n, d = np.array([math.cos(phi), math.sin(phi)]), np.array([-math.sin(phi), math.cos(phi)])
    wall = np.concatenate((2.5 * n - 3 * d, 2.5 * n + 3 * d))
    angles = phi + np.linspace(-0.8, 0.8, 100)
    lines = extract_lines(scan_of([wall], angles), angles)
    assert len(lines) == 1
    line = lines[0]
    assert line.r == pytest.approx(2.5, abs=1e-9)
    assert -math.pi < line.alpha <= math.pi
    assert abs(wrap_angle(line.alpha - phi)) < 1e-9
    assert line.point_count == 100 and (line.first, line.last) == (0, 99)


def test_vertical_wall_x_equals_2():
    angles = np.radians(np.arange(-60.0, 60.5, 0.5))
    ranges = 2.0 / np.cos(angles)
    (line,) = extract_lines(ranges, angles)
    assert line.alpha == 0.0 or abs(line.alpha) < 1e-12
    assert line.r == pytest.approx(2.0, abs=1e-12)
    assert line.start == pytest.approx((2.0, -2.0 * math.tan(math.radians(60))), abs=1e-9)
    assert line.end == pytest.approx((2.0, 2.0 * math.tan(math.radians(60))), abs=1e-9)
    assert np.all(np.isfinite(line.covariance))


def test_full_circle_scan_does_not_cut_a_wall_at_beam_zero():
    angles = -math.pi + 2 * math.pi * np.arange(360) / 360
    room = [[-3, -2, 3, -2], [3, -2, 3, 2], [3, 2, -3, 2], [-3, 2, -3, -2]]
    lines = extract_lines(scan_of(room, angles), angles)
    assert len(lines) == 4
    alphas = sorted(round(math.degrees(line.alpha)) for line in lines)
    assert alphas == [-90, 0, 90, 180]
    west = next(line for line in lines if abs(line.alpha) > 3)     # beam 0 points at -180 deg
    assert west.first > west.last                                    # it runs through beam 0
    assert west.r == pytest.approx(3.0, abs=1e-9)


def test_ring_without_any_break_is_closed_correctly():
    # A convex room with no gaps at all: the list start must not cut a wall in two.
    angles = -math.pi + 2 * math.pi * np.arange(720) / 720 + 0.3
    hexagon = [(4 * math.cos(k * math.pi / 3), 4 * math.sin(k * math.pi / 3)) for k in range(7)]
    walls = [[*hexagon[k], *hexagon[k + 1]] for k in range(6)]
    lines = extract_lines(scan_of(walls, angles), angles, max_line_gap=1.0)
    assert len(lines) == 6
    assert sum(line.point_count for line in lines) >= 720


def test_gap_and_invalid_ranges_split_but_a_single_invalid_beam_does_not_cut_a_wall():
    angles = np.radians(np.arange(-40.0, 40.5, 1.0))
    ranges = 3.0 / np.cos(angles)
    with_nan = ranges.copy()
    with_nan[40] = np.nan
    (line,) = extract_lines(with_nan, angles)
    assert (line.first, line.last, line.point_count) == (0, 80, 80)
    # A doorway: 10 beams with no return make a 0.55 m gap > max_line_gap = 0.5 m.
    door = ranges.copy()
    door[35:45] = np.inf
    lines = extract_lines(door, angles)
    assert [(ln.first, ln.last) for ln in lines] == [(0, 34), (45, 80)]
    assert extract_lines(door, angles, max_line_gap=1.0)[0].point_count == 71


def test_filters_min_points_length_and_range_window():
    angles = np.radians(np.arange(-40.0, 40.5, 1.0))
    ranges = 3.0 / np.cos(angles)                     # 81 beams, 5 m of wall
    assert len(extract_lines(ranges, angles, min_line_points=81)) == 1
    assert extract_lines(ranges, angles, min_line_points=82) == []
    assert extract_lines(ranges, angles, min_line_length=5.1) == []
    assert extract_lines(ranges, angles, max_range=2.9) == []
    (line,) = extract_lines(ranges, angles, max_range=3.2)   # only the middle of the wall
    assert all(abs(p[1]) <= math.sqrt(3.2 ** 2 - 9) + 1e-9 for p in (line.start, line.end))


def test_decreasing_angles_work_like_increasing_ones():
    angles = np.radians(np.arange(-40.0, 40.5, 1.0))
    ranges = scan_of([[2, -3, 2, 3]], angles) + np.random.default_rng(0).normal(0, 0.01, 81)
    (up,) = extract_lines(ranges, angles)
    (down,) = extract_lines(ranges[::-1], angles[::-1])
    assert (down.r, down.alpha) == pytest.approx((up.r, up.alpha), abs=1e-12)
    assert (down.first, down.last) == (0, 80)
    assert down.start == pytest.approx(up.end, abs=1e-12)


# ---------------------------------------------------------------- bad input

def test_bad_input():
    angles = np.linspace(-1, 1, 50)
    with pytest.raises(ValueError, match='differ in length'):
        extract_lines(np.ones(50), np.linspace(-1, 1, 49))
    assert extract_lines(np.full(50, np.nan), angles) == []
    assert extract_lines(np.full(50, np.inf), angles) == []
    assert extract_lines(np.full(50, -np.inf), angles) == []
    assert extract_lines(np.array([]), np.array([])) == []
    few = np.full(50, np.nan)
    few[:5] = 2.0
    assert extract_lines(few, angles) == []                  # 5 points < min_line_points = 6
    mixed = 2.0 / np.cos(angles)
    mixed[::7] = np.nan
    mixed[3::7] = np.inf
    mixed[5::11] = -np.inf
    (line,) = extract_lines(mixed, angles)                   # the valid beams still give the wall
    assert line.r == pytest.approx(2.0, abs=1e-9)
    nan_angles = angles.copy()
    nan_angles[10] = np.nan
    assert extract_lines(2.0 / np.cos(angles), nan_angles)[0].point_count == 49


@pytest.mark.parametrize('options', [
    dict(split_distance=0.0), dict(max_line_gap=-1.0), dict(min_line_points=1),
    dict(min_line_points=2.5), dict(min_line_length=-0.1), dict(min_range=2.0, max_range=1.0),
    dict(range_sigma=0.0), dict(merge_chi2=float('nan')),
])
def test_bad_options_raise(options):
    with pytest.raises(ValueError):
        extract_lines(np.ones(10), np.linspace(0, 1, 10), **options)


def test_unknown_option_is_an_error():
    with pytest.raises(TypeError):
        extract_lines(np.ones(10), np.linspace(0, 1, 10), split_threshold=0.1)


# ---------------------------------------------------------------- covariance

def test_covariance_matches_monte_carlo_spread():
    rng = np.random.default_rng(7)
    angles = np.radians(np.arange(-50.0, 20.5, 1.0))
    true = scan_of([[3, -5, 1.5, 4]], angles)
    estimates, covariances = [], []
    for _ in range(400):
        (line,) = extract_lines(true + rng.normal(0, 0.01, true.size), angles, range_sigma=0.01)
        estimates.append((line.r, line.alpha))
        covariances.append(line.covariance)
    estimates = np.array(estimates)
    empirical = np.cov(estimates.T)
    predicted = np.mean(covariances, axis=0)
    assert np.sqrt(np.diag(empirical)) == pytest.approx(np.sqrt(np.diag(predicted)), rel=0.1)
    corr = lambda c: c[0, 1] / math.sqrt(c[0, 0] * c[1, 1])  # noqa: E731
    assert corr(empirical) == pytest.approx(corr(predicted), abs=0.1)
    assert abs(corr(predicted)) > 0.3                        # the test would see a sign error
    fit = fit_line(np.array([[3, -5], [1.5, 4]]))
    # Unbiased: the mean of 400 estimates is within 3 standard errors of the truth.
    bound = 3 * np.sqrt(np.diag(empirical)) / math.sqrt(len(estimates))
    assert np.all(np.abs(estimates.mean(axis=0) - [fit.r, fit.alpha]) <= bound)


# ---------------------------------------------------------------- accuracy on the default world

SIGMA = 0.01
# The benchmark's poses, and more.
POSES = [
    *BENCH_POSES,
    (-4.2, 0.5, -2.0),
    (4.2, -3.2, 2.6),
    (-1.5, 3.0, 0.0),
    (1.8, 2.6, -1.9),
    (-2.5, -3.3, 1.0),
    (3.0, 0.5, 3.1),
    (-3.5, 1.0, -0.7),
    (1.5, -1.5, 0.9),
    (-0.5, -1.6, -3.0),
    (4.0, 1.5, 1.7),
]


def _nearest_wall(points_world, segments):
    a, b = segments[:, :2], segments[:, 2:]
    ab = b - a
    t = np.clip(((points_world[:, None, :] - a) * ab).sum(-1) / (ab * ab).sum(-1), 0.0, 1.0)
    return np.linalg.norm(points_world[:, None, :] - (a + t[..., None] * ab), axis=-1).argmin(
        axis=1
    )


@pytest.fixture(scope='module')
def simulated():
    """Per pose: noisy ranges, angles, the true wall hit by each beam (-1: none), extracted
    lines."""
    world = load_world(config_file('default_world.yaml'))
    rng = np.random.default_rng(2024)
    angles = -math.pi + 2 * math.pi * np.arange(360) / 360
    results = []
    for pose in POSES:
        true = raycast(world.segments, pose[:2], angles + pose[2])
        hit = true <= 8.0
        points = np.column_stack((true * np.cos(angles), true * np.sin(angles)))[hit]
        label = np.full(360, -1)
        label[hit] = _nearest_wall(transform_points(pose, points), world.segments)
        ranges = np.where(hit, true + rng.normal(0.0, SIGMA, 360), np.inf)
        results.append((pose, ranges, angles, label, extract_lines(ranges, angles)))
    return world, results


def _beams(line: Line, count: int):
    if line.first <= line.last:
        return np.arange(line.first, line.last + 1)
    return np.r_[line.first:count, 0:line.last + 1]


def _true_line(world, pose, wall):
    return fit_line(transform_points(inverse(pose), world.segments[wall].reshape(2, 2)))


def test_every_wall_seen_is_found(simulated):
    world, results = simulated
    for pose, ranges, angles, label, lines in results:
        found = set()
        for line in lines:
            wall_labels = label[_beams(line, 360)]
            found.add(int(np.bincount(wall_labels[wall_labels >= 0]).argmax()))
        seen = np.flatnonzero(np.bincount(label[label >= 0], minlength=len(world.segments)) >= 6)
        assert set(seen.tolist()) <= found, f'pose {pose}: walls {set(seen) - found} not found'


def test_accuracy_against_true_walls(simulated):
    world, results = simulated
    dr, da, nees, z = [], [], [], []
    for pose, ranges, angles, label, lines in results:
        for line in lines:
            beams = _beams(line, 360)
            labels = label[beams]
            wall = int(np.bincount(labels[labels >= 0]).argmax())
            truth = _true_line(world, pose, wall)
            error = np.array([line.r - truth.r, wrap_angle(line.alpha - truth.alpha)])
            dr.append(abs(error[0]))
            da.append(abs(error[1]))
            nees.append(error @ np.linalg.solve(line.covariance, error))
            valid = np.isfinite(ranges[beams])
            pts = np.column_stack((ranges[beams] * np.cos(angles[beams]),
                                   ranges[beams] * np.sin(angles[beams])))[valid]
            # Distance of each of the line's points to the TRUE wall, in units of sigma.
            z.extend((pts @ [math.cos(truth.alpha), math.sin(truth.alpha)] - truth.r) / SIGMA)
    dr, da, z = np.array(dr), np.degrees(da), np.abs(z)
    assert len(dr) >= 100
    assert np.median(dr) <= 0.01
    assert np.median(da) <= 0.5
    # No line spans a corner: its points are within 3 sigma of the true wall (what a Gaussian
    # gives: at most 1 % beyond 3 sigma, none beyond 4.5); a point of a neighbouring wall a beam
    # away from the corner would be 5-15 sigma off.
    assert np.mean(z > 3.0) <= 0.01
    assert z.max() <= 4.5
    # The covariance is consistent: mean NEES of a 2-dof Gaussian is 2 (+- 0.6 at this count).
    assert 1.4 <= np.mean(nees) <= 2.6


def test_deterministic(simulated):
    _, results = simulated
    pose, ranges, angles, _, lines = results[0]
    again = extract_lines(ranges.copy(), angles.copy())
    assert [(ln.r, ln.alpha, ln.first, ln.last) for ln in again] == \
        [(ln.r, ln.alpha, ln.first, ln.last) for ln in lines]


# ---------------------------------------------------------------- properties on random input



@settings(max_examples=150, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    beams=st.integers(0, 400),
    full_circle=st.booleans(),
    invalid_fraction=st.floats(0.0, 1.0),
    min_line_points=st.integers(2, 12),
    max_line_gap=st.floats(0.05, 2.0),
)
def test_random_scans_give_well_formed_lines(seed, beams, full_circle, invalid_fraction,
                                             min_line_points, max_line_gap):
    rng = np.random.default_rng(seed)
    span = 2 * math.pi if full_circle else rng.uniform(0.1, 2 * math.pi)
    angles = -span / 2 + span * np.arange(beams) / max(beams, 1)
    walls = rng.uniform(-6, 6, size=(rng.integers(1, 8), 4))
    ranges = raycast(walls, (0.0, 0.0), angles) + rng.normal(0, 0.01, beams)
    bad = rng.random(beams) < invalid_fraction
    ranges[bad] = rng.choice([np.nan, np.inf, -np.inf, 0.0, -1.0], size=int(bad.sum()))
    lines = extract_lines(
        ranges, angles, min_line_points=min_line_points, max_line_gap=max_line_gap
    )
    for line in lines:
        assert line.r >= 0.0 and -math.pi < line.alpha <= math.pi
        assert 0 <= line.first < beams and 0 <= line.last < beams
        assert line.point_count >= min_line_points and line.length >= 0.2
        assert np.all(np.isfinite(line.covariance))
        assert line.covariance[0, 1] == line.covariance[1, 0]
        assert np.all(np.linalg.eigvalsh(line.covariance) > 0)
        # The endpoints lie on the line.
        assert distances(line, [line.start, line.end]) == pytest.approx([0.0, 0.0], abs=1e-9)


@pytest.mark.parametrize('name', ['textbook_numpy', 'textbook_loops'])
def test_production_agrees_with_the_textbook_split_and_merge(name):
    """core.lines against the lesson's form (core.reference.lines) on scans of the default world:
    the same r and alpha on the lines both find; the textbook cuts a full circle at beam 0, which
    moves a few split points, so it finds most, not all, of ours."""
    from sensing_nodes.bench.lines import METHODS, agreement, simulated_scans

    dr, dalpha, found = agreement(simulated_scans(360)[:4], METHODS[name])
    assert dr < 1e-9 and dalpha < 1e-9
    assert found >= 0.85
