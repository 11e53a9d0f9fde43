"""sensing_calibrate against simulated bags with known truth: the issue's 120 s target (radii,
separation, laser mount, 3-sigma honesty), wheel odometry with the written YAML, excitation,
and bad input (no topics, no motion, NaN) refused with nothing written."""

import math
import time
from pathlib import Path

import numpy as np
import pytest
import yaml
from harness import NodeProcess, carmen_pipeline

from sensing_nodes.bags.storage import BagWriter, read_messages
from sensing_nodes.core.sim import simulator as sim
from sensing_nodes.core.sim.world import load_world
from sensing_nodes.core.wheel_odometry import integrate_path
from sensing_nodes.paths import config_file
from sensing_nodes.ros.sim_robot import NodeSettings, record
from sensing_nodes.tools import calibrate

# The issue's case: right wheel +1 %, left -0.5 %, separation +2 %, laser yaw +2 deg, x +3 cm.
ERRORS = dict(right_radius_error=0.01, left_radius_error=-0.005, wheel_separation_error=0.02,
              laser_yaw_error_rad=math.radians(2.0), laser_x_error_m=0.03)
NOMINAL = {
    'wheel_odometry': {
        'ros__parameters': {
            'wheel_radius_m': 0.05,
            'wheel_separation_m': 0.30,
            'left_radius_multiplier': 1.0,
            'right_radius_multiplier': 1.0,
        }
    },
    'icp_matcher': {
        'ros__parameters': {'laser_x_m': 0.10, 'laser_y_m': 0.0, 'laser_yaw_rad': 0.0}
    },
}


def make_bag(path: Path, duration_s: float, seed: int = 1, **overrides) -> sim.SimParams:
    # sensor_sim's default scanner sweeps (each beam at its own time): the calibration deskews
    # each scan by the nominal odometry (without it, one run: the separation 1.0 % and the
    # laser yaw 2.0 deg off).
    params = sim.SimParams(**overrides)
    record(path, duration_s, params, NodeSettings(seed=seed),
           load_world(config_file('default_world.yaml')))
    return params


@pytest.fixture(scope='module')
def nominal_file(tmp_path_factory):
    path = tmp_path_factory.mktemp('nominal') / 'nominal.yaml'
    path.write_text(yaml.safe_dump(NOMINAL))
    return path


@pytest.fixture(scope='module')
def calibrated(tmp_path_factory, nominal_file):
    """The 120 s bag of the issue's target, calibrated once: (params, bag, yaml path, yaml)."""
    root = tmp_path_factory.mktemp('cal120')
    bag = root / 'bag'
    # Plus a 1 % gyro scale factor error (the IMU draws from its own random stream, so the
    # wheels and scans are those of the issue's case).
    params = make_bag(bag, 120.0, seed=1, gyro_scale_error=0.01, **ERRORS)
    out, png = root / 'calibration.yaml', root / 'calibration.png'
    code = calibrate.main([str(bag), '--out', str(out), '--png', str(png), '--nominal',
                           str(nominal_file), '--quiet'])
    assert code == 0
    assert png.stat().st_size > 10_000
    return params, bag, out, yaml.safe_load(out.read_text())


def test_the_issue_target_holds_with_truth_within_three_sigma(calibrated):
    params, _, _, doc = calibrated
    report = doc['sensing_calibrate']['ros__parameters']
    values = dict(zip(report['parameters'], report['values']))
    stds = dict(zip(report['parameters'], report['stds']))
    assert all(report['estimated'])
    r = params.wheel_radius_m
    truth = {'left_radius_m': r * (1 + params.left_radius_error),
             'right_radius_m': r * (1 + params.right_radius_error),
             'wheel_separation_m': params.true_wheel_separation_m,
             'laser_x_m': params.true_laser_pose[0], 'laser_y_m': params.true_laser_pose[1],
             'laser_yaw_rad': params.true_laser_pose[2]}
    for name in ('left_radius_m', 'right_radius_m'):
        assert abs(values[name] / truth[name] - 1.0) < 0.001, name
    assert abs(values['wheel_separation_m'] / truth['wheel_separation_m'] - 1.0) < 0.002
    assert abs(values['laser_yaw_rad'] - truth['laser_yaw_rad']) < math.radians(0.1)
    assert abs(values['laser_x_m'] - truth['laser_x_m']) < 0.005
    for name, value in truth.items():
        assert abs(values[name] - value) <= 3.0 * stds[name], (
            name,
            values[name],
            value,
            stds[name],
        )
    # The node sections carry the same numbers in the nodes' own parameter names.
    wheel = doc['wheel_odometry']['ros__parameters']
    assert wheel['right_radius_multiplier'] * wheel['wheel_radius_m'] == \
        pytest.approx(values['right_radius_m'], rel=1e-6)
    assert doc['icp_matcher']['ros__parameters']['laser_yaw_rad'] == \
        pytest.approx(values['laser_yaw_rad'], abs=1e-6)
    # The IMU in the bag: bias 0.5 deg/s and scale factor error 1 %, each within 3 sigma.
    assert abs(report['gyro_bias_rad_s'] - params.gyro_bias_rad_s) <= \
        3.0 * report['gyro_bias_std_rad_s']
    assert report['gyro_scale_estimated']
    assert abs(report['gyro_scale_error'] - 0.01) <= 3.0 * report['gyro_scale_error_std']
    assert abs(report['gyro_scale_error'] - 0.01) < 0.001


def _final_position_error(bag: Path, wheel: dict) -> float:
    """Dead reckoning over the bag with wheel_odometry's parameters (its names and formula:
    radius = wheel_radius_m x multiplier), final position error against the truth (m)."""
    joints, truth = [], []
    for topic, _, msg in read_messages(bag, ['/joint_states', '/ground_truth/odom']):
        if topic == '/joint_states':
            joints.append(msg.position)
        else:
            truth.append((msg.pose.pose.position.x, msg.pose.pose.position.y,
                          2.0 * math.atan2(msg.pose.pose.orientation.z,
                                           msg.pose.pose.orientation.w)))
    angles = np.diff(np.array(joints), axis=0)
    radius = wheel['wheel_radius_m']
    poses, _ = integrate_path(truth[0], angles[:, 0] * radius * wheel['left_radius_multiplier'],
                              angles[:, 1] * radius * wheel['right_radius_multiplier'],
                              wheel['wheel_separation_m'])
    return math.hypot(poses[-1, 0] - truth[-1][0], poses[-1, 1] - truth[-1][1])


def test_written_yaml_makes_wheel_odometry_ten_times_better(calibrated):
    _, bag, _, doc = calibrated
    nominal = _final_position_error(bag, NOMINAL['wheel_odometry']['ros__parameters'])
    fixed = _final_position_error(bag, doc['wheel_odometry']['ros__parameters'])
    assert nominal > 0.5            # the injected errors matter on this route
    assert fixed * 10.0 <= nominal, (nominal, fixed)


def test_nodes_start_with_the_written_yaml(calibrated):
    """wheel_odometry, icp_matcher and gyro_integrator accept the file as it is."""
    _, _, out, _ = calibrated
    nodes = [NodeProcess(name, params_file=out).start()
             for name in ('wheel_odometry', 'icp_matcher', 'gyro_integrator')]
    try:
        time.sleep(4.0)
        for node in nodes:
            assert node.alive(), node.output()
            assert 'parameter' not in node.output().lower(), node.output()
        gyro = yaml.safe_load(out.read_text())['gyro_integrator']['ros__parameters']
        assert set(gyro) >= {'initial_bias_z_rad_s', 'gyro_scale_error'}   # as parameters
    finally:
        for node in nodes:
            node.stop()


def test_straight_driving_leaves_separation_and_laser_position_unestimated(tmp_path, nominal_file):
    bag = tmp_path / 'straight'
    make_bag(bag, 24.0, route=('wait 1', 'straight 5.0 0.25'), **ERRORS)
    out = tmp_path / 'straight.yaml'
    assert calibrate.main([str(bag), '--out', str(out), '--nominal', str(nominal_file),
                           '--quiet']) == 0
    report = yaml.safe_load(out.read_text())['sensing_calibrate']['ros__parameters']
    estimated = dict(zip(report['parameters'], report['estimated']))
    assert not estimated['wheel_separation_m']
    assert not estimated['laser_x_m'] and not estimated['laser_y_m']
    # Straight driving still fixes both radii (equal wheel travel) and the laser yaw.
    values = dict(zip(report['parameters'], report['values']))
    assert estimated['left_radius_m'] and estimated['right_radius_m']
    assert values['right_radius_m'] / values['left_radius_m'] == pytest.approx(1.01 / 0.995,
                                                                              rel=2e-3)
    assert estimated['laser_yaw_rad']
    assert abs(values['laser_yaw_rad'] - math.radians(2.0)) < math.radians(0.5)
    # The wheel_odometry section keeps the nominal separation.
    assert yaml.safe_load(out.read_text())['wheel_odometry']['ros__parameters'][
        'wheel_separation_m'] == 0.30


def test_bag_without_motion_is_refused(tmp_path, capsys):
    bag = tmp_path / 'still'
    make_bag(bag, 5.0, route=('wait 10',))
    out = tmp_path / 'out.yaml'
    assert calibrate.main([str(bag), '--out', str(out), '--quiet']) == 2
    assert 'never turn' in capsys.readouterr().err
    assert not out.exists()


def test_bag_without_the_needed_topics_is_refused(tmp_path, capsys):
    from sensor_msgs.msg import Imu

    bag = tmp_path / 'imu_only'
    with BagWriter(bag) as writer:
        for i in range(10):
            msg = Imu()
            msg.header.stamp.sec = i
            writer.write('/imu/data_raw', msg, i * 1_000_000_000)
    out = tmp_path / 'out.yaml'
    assert calibrate.main([str(bag), '--out', str(out), '--quiet']) == 2
    err = capsys.readouterr().err
    assert 'no wheel encoders' in err and 'no laser scans' in err and '/imu/data_raw' in err
    assert not out.exists()
    assert calibrate.main([str(tmp_path / 'missing'), '--quiet']) == 2
    assert 'no such bag' in capsys.readouterr().err


def test_nan_encoder_reading_is_refused(tmp_path, capsys):
    bag = tmp_path / 'good'
    make_bag(bag, 3.0, route=('straight 1.0 0.25',))
    bad = tmp_path / 'nan'
    with BagWriter(bad) as writer:
        for n, (topic, stamp, msg) in enumerate(read_messages(bag, ['/joint_states', '/scan'])):
            if topic == '/joint_states' and n == 40:
                msg.position = [float('nan'), msg.position[1]]
            writer.write(topic, msg, stamp)
    out = tmp_path / 'out.yaml'
    assert calibrate.main([str(bad), '--out', str(out), '--quiet']) == 2
    assert 'non-finite wheel position' in capsys.readouterr().err
    assert not out.exists()


DATASETS = Path(__file__).resolve().parents[1] / '..' / 'shared' / 'datasets' / 'ros'


def test_real_turtlebot3_bag(tmp_path, capsys):
    """fuse's TurtleBot3 (Gazebo) bag: no truth to judge by, so the figures are checked against
    the Waffle's published geometry (r 0.033 m, b 0.287 m, laser 0.064 m behind base_link)
    within what a calibration may move them."""
    bag = DATASETS / 'fuse-turtlebot3.bag'
    if not bag.exists():
        pytest.skip(f'{bag} is not here')
    out = tmp_path / 'tb3.yaml'
    assert calibrate.main([str(bag), '--wheel-radius', '0.033', '--wheel-separation', '0.287',
                           '--laser', '-0.064', '0', '0', '--out', str(out), '--quiet']) == 0
    report = yaml.safe_load(out.read_text())['sensing_calibrate']['ros__parameters']
    values = dict(zip(report['parameters'], report['values']))
    assert all(report['estimated'])
    assert values['left_radius_m'] == pytest.approx(0.033, rel=0.02)
    assert values['right_radius_m'] == pytest.approx(0.033, rel=0.02)
    assert values['wheel_separation_m'] == pytest.approx(0.287, rel=0.03)
    assert values['laser_x_m'] == pytest.approx(-0.064, abs=0.015)
    assert 'gyro z: bias' in capsys.readouterr().out


def test_real_bag_without_encoders_or_laser_is_refused(capsys):
    bag = DATASETS / 'robot_localization-test2.bag'
    if not bag.exists():
        pytest.skip(f'{bag} is not here')
    assert calibrate.main([str(bag), '--quiet']) == 2
    err = capsys.readouterr().err
    assert 'no wheel encoders' in err and '/jackal_velocity_controller/odom' in err


# --- odometry time offset (sensing_calibrate --odom-delay) -----------------------------------

def _turning_yaw(t_s):
    """Yaw (rad) of a robot swinging left and right: two sines, up to 1.1 rad."""
    return 0.8 * np.sin(0.7 * t_s) + 0.3 * np.sin(2.1 * t_s)


def _delayed_streams(delay_s, seed=1):
    """Odometry at 20 Hz whose message stamped t reports the yaw at t - delay_s, and 110 scan
    matches at irregular stamps with 0.2 deg noise, three of them 10 deg off (failed matches)."""
    rng = np.random.default_rng(seed)
    odom_t = np.arange(0.0, 120.0, 0.05)
    match_t = np.sort(rng.uniform(1.0, 119.0, 110))
    match_yaw = _turning_yaw(match_t) + rng.normal(0.0, math.radians(0.2), match_t.size)
    match_yaw[[10, 50, 90]] += math.radians(10.0)
    return ((odom_t * 1e9).astype(np.int64), _turning_yaw(odom_t - delay_s),
            (match_t * 1e9).astype(np.int64), match_yaw)


@pytest.mark.parametrize('delay_s', [0.08, 0.0, -0.05])
def test_odometry_delay_is_found_to_the_millisecond(delay_s):
    """Worked numbers: odometry lagging 80 ms (or 0, or 50 ms early) is estimated within 2.5 ms,
    one-sided, with a std under 5 ms."""
    from sensing_nodes.core.evaluation.calibration import odometry_delay

    result = odometry_delay(*_delayed_streams(delay_s))
    assert result.delay_s == pytest.approx(delay_s, abs=0.0025)
    assert result.std_s < 0.005 and result.intervals == 109
    if delay_s:
        assert not result.two_sided


def test_odometry_delay_refuses_a_recording_without_turning():
    from sensing_nodes.core.evaluation.calibration import CalibrationError, odometry_delay

    odom_t, _, match_t, _ = _delayed_streams(0.0)
    with pytest.raises(CalibrationError, match='needs turning'):
        odometry_delay(odom_t, np.zeros(odom_t.size), match_t, np.zeros(match_t.size))


def test_odom_delay_tool_writes_the_two_nodes_parameters(tmp_path, capsys):
    from sensing_nodes.ros.conversions import make_odometry

    odom_t, odom_yaw, match_t, match_yaw = _delayed_streams(0.08)
    bag = tmp_path / 'delayed'
    rows = [(t, '/wheel/odom', y) for t, y in zip(odom_t, odom_yaw)] + \
        [(t, '/scan_match/odom', y) for t, y in zip(match_t, match_yaw)]
    with BagWriter(bag) as writer:
        for t, topic, yaw in sorted(rows, key=lambda r: r[0]):
            writer.write(topic, make_odometry(int(t), 'odom', 'base_link', (0.0, 0.0, float(yaw)),
                                              np.eye(3) * 1e-4), int(t))
    out = tmp_path / 'delay.yaml'
    assert calibrate.main([str(bag), '--odom-delay', '--out', str(out)]) == 0
    written = yaml.safe_load(out.read_text())
    delay = written['complementary_fusion']['ros__parameters']['wheel_odom']['delay_s']
    assert delay == pytest.approx(0.08, abs=0.0025)
    assert written['icp_matcher']['ros__parameters']['odom_delay_s'] == delay
    assert 'odometry delay: 0.08' in capsys.readouterr().out
    assert calibrate.main([str(bag), '--odom-delay', '--odom-topic', '/odom']) == 2
    assert 'no nav_msgs/Odometry topic /odom' in capsys.readouterr().err


CARMEN = DATASETS.parent / 'carmen'


@pytest.mark.parametrize('log', ['aces', 'freiburg-101'])
def test_odom_delay_on_the_carmen_logs(tmp_path, capsys, log):
    """docs/real-data.md's pipeline, then --odom-delay on /odom against /scan_match/odom.
    Measured on carmen_to_bag's chained odometry: ACES 0.044 +- 0.007 s, Freiburg 101
    -0.155 +- 0.006 s, both one-sided. (On the odometry as logged, re-anchored on the reference
    at every scan, Freiburg's disagreement fell on both sides of 0: no single delay.)"""
    path = CARMEN / f'{log}-corrected.log.gz'
    if not path.exists():
        pytest.skip(f'{path} is not here')
    processed = carmen_pipeline(path, tmp_path)
    out = tmp_path / 'delay.yaml'
    assert calibrate.main([str(processed), '--odom-delay', '--odom-topic', '/odom',
                           '--out', str(out)]) == 0
    report = yaml.safe_load(out.read_text())['sensing_calibrate']['ros__parameters']
    expected = {'aces': 0.044, 'freiburg-101': -0.155}[log]
    assert report['odom_delay_s'] == pytest.approx(expected, abs=0.02)
    assert not report['two_sided']


def test_a_swept_scan_is_deskewed_to_its_stamp_by_the_encoders():
    """A robot turning on the spot at 1 rad/s, its laser 0.1 m ahead: a wall point seen by beams
    taken 0..0.1 s after the stamp is moved to where the laser saw it at the stamp (worked: the
    laser's pose at each beam's time from the exact turn)."""
    from sensing_nodes.core.evaluation.calibration import Geometry, deskew_scans
    from sensing_nodes.core.geometry.se2 import compose, inverse, transform_points

    geometry = Geometry(0.05, 0.05, 0.30, 0.10, 0.0, 0.0)
    w = 1.0                                    # rad/s, on the spot: wheels at -+ w b / 2 r
    joint_t = np.arange(0, 201) * 5_000_000    # 200 Hz for 1 s
    wheel_rate = w * geometry.wheel_separation_m / 2 / geometry.left_radius_m
    joint_pos = np.column_stack([-wheel_rate * joint_t * 1e-9, wheel_rate * joint_t * 1e-9])
    stamp, times = 300_000_000, np.linspace(0.0, 0.1, 11)
    world = np.array([[2.0, 0.5]] * times.size)
    seen = np.array([transform_points(inverse(compose((0.0, 0.0, w * (0.3 + s)),
                                                      geometry.laser_pose)), world[:1])[0]
                     for s in times])
    at_stamp = transform_points(inverse(compose((0.0, 0.0, w * 0.3), geometry.laser_pose)),
                                world[:1])[0]
    out = deskew_scans(joint_t, joint_pos, np.array([stamp]), [seen], [times], geometry)[0]
    assert np.abs(seen - at_stamp).max() > 0.1          # the sweep moved the point
    np.testing.assert_allclose(out, np.tile(at_stamp, (times.size, 1)), atol=1e-9)


def test_no_free_parameter_is_none_unexcited():
    """A short bag can hold every parameter (none left free): the excitation test answers
    'none unexcited' instead of failing on an empty information matrix (sensing_doctor crashed
    with an IndexError on the first 30 s of the TurtleBot3 bag)."""
    from sensing_nodes.core.evaluation.calibration import _unexcited

    free = np.zeros(6, dtype=bool)
    assert _unexcited(np.ones((10, 6)), free).tolist() == [False] * 6
    free[1] = True
    jac = np.zeros((10, 6))
    jac[:, 1] = 1.0
    assert _unexcited(jac, free).tolist() == [False] * 6
