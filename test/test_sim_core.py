"""The simulated robot's core without ROS: ray casting, noise statistics, IMU, encoders, route,
determinism and parameter validation (sensing_nodes.core.sim.simulator / core.route)."""

import dataclasses
import math

import numpy as np
import pytest

from sensing_nodes.core.geometry.se2 import wrap_angle
from sensing_nodes.core.sim import simulator as sim
from sensing_nodes.core.sim.route import Route, parse_leg
from sensing_nodes.core.sim.world import load_world, raycast, world_from_dict
from sensing_nodes.parameters import ParameterError, load_parameters
from sensing_nodes.paths import config_file

DEFAULT_WORLD = load_world(config_file('default_world.yaml'))

NOISELESS = dict(range_noise_std_m=0.0, range_bias_m=0.0, gyro_bias_rad_s=0.0,
                 gyro_noise_std_rad_s=0.0, accel_noise_std_m_s2=0.0, accel_bias_x_m_s2=0.0,
                 accel_bias_y_m_s2=0.0, accel_bias_z_m_s2=0.0, left_radius_error=0.0,
                 right_radius_error=0.0, slip_noise_sqrt_m=0.0)


def still(seconds: float = 1.0, **overrides) -> sim.SimParams:
    """Parameters of a robot standing at the origin facing +x, laser at base_link."""
    values = dict(route=(f'wait {seconds}',), start_x_m=0.0, start_y_m=0.0, start_yaw_rad=0.0,
                  laser_x_m=0.0, laser_y_m=0.0, laser_yaw_rad=0.0)
    values.update(overrides)
    return sim.SimParams(**values)


def beam_index(params: sim.SimParams, degrees: float) -> int:
    index = (math.radians(degrees) - params.scan_angle_min_rad) / params.scan_angle_increment_rad
    assert abs(index - round(index)) < 1e-9
    return int(round(index))


def point_segment_distance(points, segments):
    a, b = segments[:, :2], segments[:, 2:]
    ab = b - a
    t = np.clip(((points[:, None, :] - a) * ab).sum(-1) / (ab * ab).sum(-1), 0.0, 1.0)
    return np.linalg.norm(points[:, None, :] - (a + t[..., None] * ab), axis=-1).min(axis=1)


# --- defaults -------------------------------------------------------------------------------

def test_simparams_defaults_equal_config_file():
    values = load_parameters('sensor_sim', config_file('sensor_sim.yaml'))
    names = {f.name for f in dataclasses.fields(sim.SimParams)}
    assert names <= set(values), f'missing in config/sensor_sim.yaml: {names - set(values)}'
    from_file = sim.params_from_dict(values)
    for name in names:
        assert getattr(from_file, name) == getattr(sim.SimParams(), name), name
        assert type(values[name]) is type(getattr(sim.SimParams(), name)) or name == 'route', name


def test_defaults_a_student_recognises():
    p = sim.SimParams()
    lidar = (p.scan_beams, p.scan_rate_hz, p.range_noise_std_m, p.range_max_m)
    assert lidar == (360, 10.0, 0.01, 8.0)
    assert (p.imu_rate_hz, p.joint_rate_hz) == (200.0, 50.0)
    assert math.degrees(p.gyro_bias_rad_s) == pytest.approx(0.5)
    assert (p.wheel_radius_m, p.wheel_separation_m) == (0.05, 0.30)
    # 2000 counts/rev x 4: 400 counts = 2*pi*0.05/8000*400 = 1.57 cm of travel.
    assert 400 * p.count_angle_rad * p.wheel_radius_m == pytest.approx(0.015708, abs=1e-6)
    assert abs(p.right_radius_error - p.left_radius_error) == pytest.approx(0.01)


# --- ray casting ----------------------------------------------------------------------------

def test_wall_at_two_metres_reads_two_with_noise_off():
    world = world_from_dict({'walls': [[2.0, -5.0, 2.0, 5.0]]})
    params = still(**NOISELESS)
    run = sim.simulate(params, world, 0.5, seed=3)
    ahead = run.scan_ranges[:, beam_index(params, 0.0)]
    assert ahead.dtype == np.float32
    np.testing.assert_array_equal(ahead, np.float32(2.0))
    # Off-axis beams hit the same wall at 2 / cos(angle).
    b45 = beam_index(params, 45.0)
    assert run.scan_ranges[0, b45] == pytest.approx(2.0 * math.sqrt(2.0), abs=1e-6)


def test_beam_at_30_degrees_through_2165_125_reads_250():
    # A wall through (2.165, 1.25), perpendicular to the 30 degree beam, and a vertical wall
    # through the same point: both read 2.50 (to the 3 decimals of the worked example).
    normal = np.array([math.cos(math.radians(30.0)), math.sin(math.radians(30.0))])
    along = np.array([-normal[1], normal[0]])
    point = np.array([2.165, 1.25])
    for wall in (np.concatenate((point - 3 * along, point + 3 * along)),
                 np.array([2.165, -5.0, 2.165, 5.0])):
        world = world_from_dict({'walls': [wall.tolist()]})
        params = still(**NOISELESS)
        reading = sim.simulate(params, world, 0.0, seed=0).scan_ranges[0, beam_index(params, 30.0)]
        assert reading == pytest.approx(2.50, abs=5e-4)
    # Exact: the vertical wall x = 2.165 is hit at 2.165 / cos 30 deg.
    assert reading == pytest.approx(2.165 / math.cos(math.radians(30.0)), abs=1e-6)


def test_occlusion_laser_mount_and_yaw_follow_from_the_nearest_hit():
    world = world_from_dict({'walls': [[3.0, -5.0, 3.0, 5.0], [1.5, -0.1, 1.5, 0.1]]})
    params = still(**NOISELESS, laser_x_m=0.5, start_yaw_rad=math.pi / 2,
                   start_x_m=0.0, start_y_m=-0.5)
    # base at (0, -0.5) facing +y, laser 0.5 m ahead at the origin still facing +y: the beam at
    # -90 deg (laser frame) points along +x and sees the short wall at 1.5 m, which hides the
    # far one.
    run = sim.simulate(params, world, 0.0, seed=0)
    assert run.scan_ranges[0, beam_index(params, -90.0)] == pytest.approx(1.5, abs=1e-6)
    far = 3.0 / math.cos(math.radians(10))
    assert run.scan_ranges[0, beam_index(params, -80.0)] == pytest.approx(far, abs=1e-5)


def test_no_return_beyond_range_max_and_too_close_are_rep117_infinities():
    world = world_from_dict({'walls': [[9.0, -1.0, 9.0, 1.0], [-0.05, -1.0, -0.05, 1.0]]})
    params = still(**NOISELESS)
    ranges = sim.simulate(params, world, 0.0, seed=0).scan_ranges[0]
    assert ranges[beam_index(params, 0.0)] == np.inf          # wall at 9 m > range_max 8 m
    assert ranges[beam_index(params, 90.0)] == np.inf         # nothing there at all
    assert ranges[beam_index(params, -180.0)] == -np.inf     # wall 5 cm behind < range_min
    assert not np.isnan(ranges).any()


def test_range_noise_mean_is_the_bias_and_std_is_sigma_over_many_beams():
    bias, sigma = 0.02, 0.01
    params = still(seconds=10.0, range_bias_m=bias, range_noise_std_m=sigma, start_x_m=-2.5,
                   start_y_m=-2.0)
    run = sim.simulate(params, DEFAULT_WORLD, 10.0, seed=11)
    true = raycast(DEFAULT_WORLD.segments, (-2.5, -2.0), run.scan_angles)
    errors = (run.scan_ranges.astype(float) - true)[:, np.isfinite(true) & (true < 7.9)].ravel()
    n = errors.size
    assert n > 30_000
    assert abs(errors.mean() - bias) < 4.0 * sigma / math.sqrt(n)
    # + 1e-6 for float32 rounding
    assert abs(errors.std() - sigma) < 4.0 * sigma / math.sqrt(2.0 * n) + 1e-6


# --- IMU ------------------------------------------------------------------------------------

def test_accelerometer_reads_plus_g_on_z_and_gyro_reads_bias_at_rest():
    params = still(seconds=5.0)
    run = sim.simulate(params, DEFAULT_WORLD, 5.0, seed=5)
    n = len(run.imu_t)
    assert n == 1001                                            # 200 Hz, both ends included
    accel = run.imu_accel.mean(axis=0)
    tol = 4.0 * params.accel_noise_std_m_s2 / math.sqrt(n)
    assert accel[2] == pytest.approx(9.81 + params.accel_bias_z_m_s2, abs=tol)
    assert accel[0] == pytest.approx(params.accel_bias_x_m_s2, abs=tol)
    gyro_tol = 4.0 * params.gyro_noise_std_rad_s / math.sqrt(n)
    assert run.imu_gyro[:, 2].mean() == pytest.approx(math.radians(0.5), abs=gyro_tol)
    assert run.imu_gyro[:, 2].std() == pytest.approx(params.gyro_noise_std_rad_s, rel=0.15)


def test_gyro_integrates_exactly_to_the_true_heading_change_without_bias_and_noise():
    params = sim.SimParams(**NOISELESS)
    run = sim.simulate(params, DEFAULT_WORLD, 60.0, seed=0)
    period = 1.0 / params.imu_rate_hz
    integrated = np.cumsum(run.imu_gyro[:, 2]) * period
    truth_yaw = np.unwrap(run.truth_pose[:, 2])
    at_imu = np.interp(run.imu_t, run.truth_t, truth_yaw) - truth_yaw[0]
    # truth is at 100 Hz and the IMU at 200 Hz: compare at the common stamps.
    common = np.isin(run.imu_t, run.truth_t)
    np.testing.assert_allclose(integrated[common], at_imu[common], atol=1e-9)
    assert abs(at_imu[-1]) > math.pi / 2                        # it did turn


def test_accelerometer_sees_ramps_and_centripetal_force():
    params = sim.SimParams(**NOISELESS)
    run = sim.simulate(params, DEFAULT_WORLD, 130.0, seed=0)
    ax, ay = run.imu_accel[:, 0], run.imu_accel[:, 1]
    assert ax.max() == pytest.approx(params.max_linear_accel_m_s2, rel=1e-6)
    assert ax.min() == pytest.approx(-params.max_linear_accel_m_s2, rel=1e-6)
    # On the 0.5 m arc at 0.25 m/s: v * w = 0.25 * 0.5 = 0.125 m/s^2 to the left.
    assert ay.max() == pytest.approx(0.25 * 0.25 / 0.5, rel=1e-6)


# --- encoders -------------------------------------------------------------------------------

def test_encoder_positions_are_whole_counts_and_velocities_their_differences():
    params = sim.SimParams()
    run = sim.simulate(params, DEFAULT_WORLD, 40.0, seed=2)
    counts = run.joint_position / params.count_angle_rad
    np.testing.assert_allclose(counts, np.round(counts), atol=1e-6)
    assert counts[-1].min() > 20_000                           # they did turn
    dt = 1.0 / params.joint_rate_hz
    np.testing.assert_allclose(run.joint_velocity[1:], np.diff(run.joint_position, axis=0) / dt,
                               atol=1e-9)


def test_one_metre_straight_counts_and_one_percent_radius_error():
    params = sim.SimParams(**{**NOISELESS, 'right_radius_error': 0.01},
                           route=('straight 1.0 0.25', 'wait 2'))
    run = sim.simulate(params, DEFAULT_WORLD, 6.0, seed=0)
    counts = np.round(run.joint_position[-1] / params.count_angle_rad).astype(int)
    per_metre = 1.0 / (params.wheel_radius_m * params.count_angle_rad)    # 25464.79 counts
    assert counts[0] == math.floor(per_metre) == 25464
    assert counts[1] == math.floor(per_metre / 1.01) == 25212
    # the truth is unaffected by the radius error
    np.testing.assert_allclose(run.truth_pose[-1], (-1.5, -2.0, 0.0), atol=1e-12)


def test_slip_noise_grows_with_distance_and_leaves_standing_wheels_still():
    params = sim.SimParams(**{**NOISELESS, 'slip_noise_sqrt_m': 0.01},
                           route=('wait 2', 'straight 4.0 0.25', 'wait 2'))
    finals = []
    for seed in range(12):
        run = sim.simulate(params, DEFAULT_WORLD, 21.0, seed=seed)
        assert np.all(run.joint_position[:100] == 0.0)          # still for the first 2 s
        finals.append(run.joint_position[-1] * params.wheel_radius_m - 4.0)
    spread = np.std(finals)
    assert 0.3 * 0.01 * 2.0 < spread < 2.0 * 0.01 * 2.0         # std ~ k * sqrt(4 m) = 2 cm


# --- truth and route ------------------------------------------------------------------------

def test_default_route_loops_clear_of_obstacles_with_still_start_slow_turn_and_stop():
    params = sim.SimParams()
    route = sim.make_route(params)
    assert 120.0 <= route.period_s <= 140.0
    run = sim.simulate(params, DEFAULT_WORLD, route.period_s, seed=0)
    np.testing.assert_allclose(run.truth_pose[-1], run.truth_pose[0], atol=1e-6)   # back at start
    assert point_segment_distance(run.truth_pose[:, :2], DEFAULT_WORLD.segments).min() >= 0.4
    v, w = np.abs(run.truth_twist).T
    moving = (v > 0) | (w > 0)
    t = (run.truth_t - run.truth_t[0]) / 1e9
    assert t[np.argmax(moving)] >= 3.0                          # >= 3 s still for gyro calibration
    # a stop of >= 3 s between two motions, mid-route
    runs, start = [], None
    for i, m in enumerate(moving):
        if not m and start is None:
            start = i
        if m and start is not None:
            runs.append((t[start], t[i]))
            start = None
    assert any(b - a >= 3.0 and a > 10.0 for a, b in runs[1:])
    # a slow turn: the robot turns in place for >= 10 s at <= 5 deg/s
    slow = (v == 0) & (w > 0) & (w <= math.radians(5.0) + 1e-12)
    assert slow.sum() / params.truth_rate_hz >= 10.0
    # both directions of turning
    assert run.truth_twist[:, 1].min() < 0 < run.truth_twist[:, 1].max()
    # the table (at the origin) is circled: winding angle of the path around it is 2 pi
    xy = run.truth_pose[:, :2]
    winding = np.sum(wrap_angle(np.diff(np.arctan2(xy[:, 1], xy[:, 0]))))
    assert winding == pytest.approx(2.0 * math.pi, abs=1e-6)


def test_route_repeats_when_the_run_is_longer():
    params = sim.SimParams(route=('straight 1.0 0.5', 'turn 180 90', 'straight 1.0 0.5',
                                  'turn 180 90', 'wait 1'))
    route = sim.make_route(params)
    run = sim.simulate(params, DEFAULT_WORLD, 2.5 * route.period_s, seed=0)
    for loops in (1, 2):
        end = run.truth_t[0] + int(round(loops * route.period_s * 1e9))
        i = np.searchsorted(run.truth_t, end) - 1
        # the last truth sample of the loop (100 Hz), in its final wait
        np.testing.assert_allclose(run.truth_pose[i], run.truth_pose[0], atol=1e-6)


def test_truth_twist_is_the_derivative_of_the_truth_pose():
    params = sim.SimParams()
    run = sim.simulate(params, DEFAULT_WORLD, 60.0, seed=0)
    dt = 1.0 / params.truth_rate_hz
    yaw = np.unwrap(run.truth_pose[:, 2])
    w_fd = np.diff(yaw) / dt
    w_mid = 0.5 * (run.truth_twist[1:, 1] + run.truth_twist[:-1, 1])
    assert np.abs(w_fd - w_mid).max() < 0.02
    d = np.diff(run.truth_pose[:, :2], axis=0)
    forward = d[:, 0] * np.cos(yaw[:-1]) + d[:, 1] * np.sin(yaw[:-1])
    v_mid = 0.5 * (run.truth_twist[1:, 0] + run.truth_twist[:-1, 0])
    assert np.abs(forward / dt - v_mid).max() < 0.01


def test_route_leg_profiles():
    leg = parse_leg('straight 2.0 0.5', 0.5, 1.0)
    assert leg.duration_s == pytest.approx(2.0 / 0.5 + 0.5 / 0.5)   # L/v + v/a
    short = parse_leg('straight 0.1 0.5', 0.5, 1.0)                 # never reaches 0.5 m/s
    assert short.u_rate_max == pytest.approx(math.sqrt(0.1 * 0.5))
    route = Route(['turn -90 30'], 0.5, 1.0)
    m = route.motion([route.period_s])
    assert m.heading[0] == pytest.approx(-math.pi / 2)
    assert m.distance[0] == 0.0
    for bad in ('fly 3', 'straight 1', 'turn 0 30', 'wait -1', 'arc 90 0 0.2', 'straight nan 1'):
        with pytest.raises(ValueError):
            parse_leg(bad, 0.5, 1.0)


# --- determinism ----------------------------------------------------------------------------

ARRAYS = [f.name for f in dataclasses.fields(sim.SimBlock)]


def test_same_seed_same_numbers_different_seed_different_noise_same_truth():
    params = sim.SimParams()
    a = sim.simulate(params, DEFAULT_WORLD, 12.0, seed=7)
    b = sim.simulate(params, DEFAULT_WORLD, 12.0, seed=7)
    c = sim.simulate(params, DEFAULT_WORLD, 12.0, seed=8)
    for name in ARRAYS:
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    for name in ('truth_pose', 'truth_twist', 'truth_t', 'scan_t', 'imu_t'):
        np.testing.assert_array_equal(getattr(a, name), getattr(c, name), err_msg=name)
    for name in ('scan_ranges', 'imu_gyro', 'imu_accel', 'joint_position'):
        assert not np.array_equal(getattr(a, name), getattr(c, name)), name


def test_each_sensor_has_its_own_noise_stream():
    base = sim.SimParams()
    a = sim.simulate(base, DEFAULT_WORLD, 8.0, seed=1)
    b = sim.simulate(dataclasses.replace(base, range_noise_std_m=0.05, scan_beams=720),
                     DEFAULT_WORLD, 8.0, seed=1)
    np.testing.assert_array_equal(a.imu_gyro, b.imu_gyro)
    np.testing.assert_array_equal(a.joint_position, b.joint_position)
    c = sim.simulate(dataclasses.replace(base, gyro_noise_std_rad_s=0.01), DEFAULT_WORLD, 8.0,
                     seed=1)
    np.testing.assert_array_equal(a.scan_ranges, c.scan_ranges)


def test_stepping_block_by_block_gives_the_batch_numbers():
    params = sim.SimParams()
    run = sim.simulate(params, DEFAULT_WORLD, 3.0, seed=4)
    engine = sim.SensorSim(params, DEFAULT_WORLD, seed=4)
    blocks = [engine.advance() for _ in range(30)]
    times, kinds, _ = sim.block_events(blocks[0])
    assert np.all(np.diff(times) >= 0)
    assert list(kinds[:4]) == [sim.CLOCK, sim.TRUTH, sim.IMU, sim.JOINTS]
    # The first scan (stamped at the start) goes out when its sweep ends, 0.1 s later.
    first_scan = times[kinds == sim.SCAN][0]
    assert first_scan == params.start_ns + 10**8 == blocks[0].scan_publish_t[0]
    assert blocks[0].scan_t[0] == params.start_ns
    for name in ARRAYS:
        stacked = np.concatenate([getattr(b, name) for b in blocks])
        np.testing.assert_array_equal(stacked, getattr(run, name)[:len(stacked)], err_msg=name)
    assert run.imu_t[0] == params.start_ns and run.imu_t[-1] == params.start_ns + 3 * 10**9
    assert np.all(np.diff(run.scan_t) == 10**8)


# --- the sweep: each beam at its own time ---------------------------------------------------

def test_a_scan_is_stamped_at_its_first_beam_and_published_when_its_sweep_ends():
    params = sim.SimParams()
    run = sim.simulate(params, DEFAULT_WORLD, 2.0, seed=1)
    assert params.scan_time_increment_s == pytest.approx(0.1 / 360)
    assert run.scan_time_increment == params.scan_time_increment_s
    assert np.all(run.scan_t == params.start_ns + 10**8 * np.arange(run.scan_t.size))
    np.testing.assert_array_equal(run.scan_publish_t - run.scan_t, 10**8)
    half = sim.simulate(dataclasses.replace(params, scan_sweep_fraction=0.5), DEFAULT_WORLD,
                        2.0, seed=1)
    np.testing.assert_array_equal(half.scan_publish_t - half.scan_t, 5 * 10**7)


def test_each_beam_is_ranged_from_where_the_laser_was_at_its_own_time():
    # Turning in place at 1 rad/s with the laser 0.1 m ahead: during a 0.1 s sweep the laser
    # turns 5.7 deg and moves 1 cm. Every beam equals a ray cast from the truth at its own time;
    # from the pose at the stamp, the last beams are centimetres off.
    params = dataclasses.replace(
        sim.SimParams(**NOISELESS), route=('turn 360 57.29577951308232',),
        max_angular_accel_rad_s2=1e3, start_x_m=0.0, start_y_m=0.0)
    run = sim.simulate(params, DEFAULT_WORLD, 1.0, seed=0)
    k = 5                                              # a scan well inside the turn
    beam_times = run.scan_t[k] + np.round(np.arange(params.scan_beams)
                                          * params.scan_time_increment_s * 1e9).astype(np.int64)
    truth = run.truth_at(beam_times)
    origins = truth[:, :2] + 0.1 * np.column_stack((np.cos(truth[:, 2]), np.sin(truth[:, 2])))
    swept = raycast(DEFAULT_WORLD.segments, origins, truth[:, 2] + run.scan_angles)
    at_stamp = raycast(DEFAULT_WORLD.segments, origins[0], truth[0, 2] + run.scan_angles)
    valid = np.isfinite(swept) & (swept < params.range_max_m)
    np.testing.assert_allclose(run.scan_ranges[k][valid], swept[valid], atol=2e-5)
    assert np.abs(run.scan_ranges[k][valid] - at_stamp[valid]).max() > 0.05
    # sweep 0: every beam from the pose at the stamp, as before the sweep was simulated.
    instant = sim.simulate(dataclasses.replace(params, scan_sweep_fraction=0.0), DEFAULT_WORLD,
                           1.0, seed=0)
    assert instant.scan_time_increment == 0.0
    np.testing.assert_array_equal(instant.scan_publish_t, instant.scan_t)
    np.testing.assert_allclose(instant.scan_ranges[k][valid], at_stamp[valid], atol=2e-5)


# --- /cmd_vel following ---------------------------------------------------------------------

def test_commanded_motion_ramps_to_the_command_and_stops_on_timeout():
    params = sim.SimParams(**NOISELESS)
    commands = sim.CommandedMotion(params)
    engine = sim.SensorSim(params, DEFAULT_WORLD, 0, commands)
    commands.command(0.4, 0.0, 0.0)
    speeds = []
    for _ in range(5):                                           # 0.5 s: timeout is 0.5 s
        speeds.extend(engine.advance().truth_twist[:, 0])
    assert speeds[-1] == pytest.approx(0.25, abs=1e-9)           # 0.5 m/s^2 x 0.5 s, still ramping
    for _ in range(10):
        block = engine.advance()
    assert block.truth_twist[-1, 0] == 0.0                       # no command for 1.5 s: stopped
    with pytest.raises(ValueError):
        commands.command(float('nan'), 0.0, 2.0)


# --- bad parameters -------------------------------------------------------------------------

@pytest.mark.parametrize('name, value', [
    ('wheel_radius_m', -0.05), ('scan_beams', 0), ('range_min_m', 8.0), ('range_max_m', math.inf),
    ('imu_rate_hz', 300.0), ('physics_rate_hz', 999), ('encoder_quadrature', 3),
    ('route', ('straight 1.0',)), ('route', ()), ('gyro_bias_rad_s', math.nan),
    ('scan_beams', 360.0), ('wheel_radius_m', '0.05'),
])
def test_bad_parameters_are_refused_naming_the_parameter(name, value):
    with pytest.raises(ParameterError) as info:
        sim.validate(dataclasses.replace(sim.SimParams(), **{name: value}))
    assert info.value.name == name
    assert f"'{name}'" in str(info.value)


def test_params_file_errors_name_the_file(tmp_path):
    with pytest.raises(ParameterError, match='params_file'):
        load_parameters('sensor_sim', tmp_path / 'missing.yaml')
    bad = tmp_path / 'bad.yaml'
    bad.write_text('sensor_sim: [unclosed\n')
    with pytest.raises(ParameterError, match='not valid YAML'):
        load_parameters('sensor_sim', bad)
    with pytest.raises(ParameterError, match='route'):
        sim.params_from_dict({'route': 'wait 3'})


def test_truth_at_interpolates_between_truth_samples():
    params = sim.SimParams(**NOISELESS)
    run = sim.simulate(params, DEFAULT_WORLD, 20.0, seed=0)
    np.testing.assert_array_equal(run.truth_at(run.truth_t[500]), run.truth_pose[500])
    half = (run.truth_t[700] + run.truth_t[701]) // 2          # on the first straight
    middle = 0.5 * (run.truth_pose[700] + run.truth_pose[701])
    np.testing.assert_allclose(run.truth_at(half), middle, atol=1e-12)
    assert run.truth_at(run.imu_t).shape == (len(run.imu_t), 3)
