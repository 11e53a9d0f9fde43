"""sensing_doctor on real recordings nobody on this project made (../shared/datasets, README
there): the upside-down Phidgets IMU, the TurtleBot3 whose encoders do not fit its /odom, the
Jackal of robot_localization's test2.bag (the preset against robot_localization's expected
final position), a CARMEN log without IMU. Skipped where the datasets are absent."""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

import pytest
import yaml

from sensing_nodes.tools import doctor

DATASETS = Path(__file__).resolve().parents[1] / '..' / 'shared' / 'datasets'
ROS = DATASETS / 'ros'
PHIDGETS = ROS / 'imu_tools-phidgets_imu_upside_down.bag'
TURTLEBOT = ROS / 'fuse-turtlebot3.bag'
JACKAL = ROS / 'robot_localization-test2.bag'
RAZOR = ROS / 'imu_tools-sparkfun_razor.bag'
FREIBURG = DATASETS / 'carmen' / 'freiburg-101-corrected.log.gz'


def _needs(path: Path):
    return pytest.mark.skipif(not path.is_file(), reason=f'{path} not present')


def _doctor(bag: Path, out: Path, *extra: str) -> tuple[int, dict]:
    code = doctor.main([str(bag), '--out', str(out), '--quiet', *extra])
    return code, json.loads((out / 'report.json').read_text())


def _checks(report: dict, name: str) -> dict[str, dict]:
    return {c['subject']: c for c in report['checks'] if c['name'] == name}


@_needs(PHIDGETS)
def test_phidgets_imu_is_found_upside_down(tmp_path):
    """A real IMU lying upside down (accelerometer z -9.88), nothing declared: gravity reads
    upside down, the mount found is a half turn about a horizontal axis (yaw unobservable: no
    wheels), and the preset's gyro_integrator takes it."""
    code, report = _doctor(PHIDGETS, tmp_path / 'out', '--no-fusion')
    gravity = _checks(report, 'imu_gravity')['/imu/data_raw']
    assert code == 1 and gravity['verdict'] == 'problem'
    assert gravity['details']['seen'] == 'upside down'
    assert gravity['details']['gravity_m_s2'] == pytest.approx(9.88, abs=0.1)
    mount = _checks(report, 'imu_mount')['/imu/data_raw']
    assert mount['verdict'] == 'problem' and mount['value'] > 170.0
    assert abs(abs(mount['details']['roll_deg']) - 180.0) < 5.0
    assert abs(mount['details']['pitch_deg']) < 5.0 and mount['details']['yaw_deg'] is None
    # -179.4 and 0.9 deg lie within 2 sigma of the right angles: the preset takes them.
    assert mount['details']['measured_deg'][0] == pytest.approx(-179.4, abs=1.0)
    params = yaml.safe_load((tmp_path / 'out' / 'params.yaml').read_text())
    gyro = params['gyro_integrator']['ros__parameters']
    assert abs(gyro['mount_roll_rad']) == pytest.approx(math.pi, abs=1e-6)
    assert gyro['mount_pitch_rad'] == 0.0


@_needs(TURTLEBOT)
def test_turtlebot3_encoders_do_not_fit_odom_and_the_preset_beats_the_hand_made(tmp_path):
    """fuse's TurtleBot3 (Gazebo): the encoders do not explain /odom (the wheels slip: dead
    reckoning ends ~60-70 deg off it), the accelerometer reads no gravity (Gazebo's zeros); the
    preset (joints, base_footprint, /imu remapped to gyro_integrator, the geometry and laser
    mount calibrated, noise measured) does at least as well against /odom as
    config/robots/turtlebot3.yaml did at the issue's time (0.036 m / 0.36 deg RMS)."""
    code, report = _doctor(TURTLEBOT, tmp_path / 'out')
    assert code == 1
    odom = _checks(report, 'encoders_vs_odometry')['/odom']
    assert odom['verdict'] == 'problem' and odom['value'] > 30.0, odom
    assert _checks(report, 'imu_gravity')['/imu']['verdict'] == 'problem'
    # The package's defaults (0.05 m radius) against the Waffle's 0.033 m: a third off.
    assert _checks(report, 'wheel_radius')['wheels']['value'] == pytest.approx(-34.0, abs=2.0)
    preset = report['preset']
    assert preset['remaps'] == {'/imu': '/imu/data_raw'}
    wheel = preset['parameters']['wheel_odometry']['ros__parameters']
    assert (wheel['left_wheel_joint'], wheel['right_wheel_joint'], wheel['base_frame']) == (
        'wheel_left_joint', 'wheel_right_joint', 'base_footprint')
    assert wheel['wheel_radius_m'] == pytest.approx(0.033, rel=0.03)
    assert preset['parameters']['icp_matcher']['ros__parameters']['laser_x_m'] == \
        pytest.approx(-0.064, abs=0.01)
    # As test_foreign_bags scores the hand-made preset: anchored at the first fused stamp.
    from sensing_nodes.core.evaluation.metrics import trajectory_errors
    from sensing_nodes.tools.eval import load_trajectories

    tracks = load_trajectories(tmp_path / 'out' / 'fused_bag', ['/odom', '/odometry/filtered'])
    fused = trajectory_errors(*tracks['/odom'], *tracks['/odometry/filtered']).summary()
    assert fused['rms_position_error_m'] <= 0.036, fused
    assert fused['rms_heading_error_deg'] <= 0.36, fused
    assert report['fused']['compared']['/odom']['rms_position_error_m'] <= 0.036
    # Every problem is the package's default geometry against the Waffle's (fixed) or the
    # data itself (Gazebo's slip against /odom, no gravity); the preset is usable.
    assert report['usable']['usable_with_params_yaml'] is True
    gain = _checks(report, 'yaw_rate_gain')['wheels vs /imu']
    assert gain['verdict'] == 'problem' and gain['fixed_by_preset']
    assert gain['details']['gain_with_preset_geometry'] == pytest.approx(1.0, abs=0.1)


@_needs(JACKAL)
def test_jackal_wheel_yaw_is_flagged_and_the_preset_ends_within_tolerance(tmp_path):
    """robot_localization's test2.bag: base-controller odometry (static covariance) whose yaw
    rate a skid-steer base inflates (its pose turns thousands of degrees against the IMU's few
    hundred) and an IMU with orientation in base_link. The odometry's yaw rate against the
    gyro's is a problem the preset fixes (its yaw left out of the fusion); the IMU never stands
    still, so gravity and the gyro bias are not judged; the preset fuses the odometry's speeds
    and the IMU's orientation (level_with_imu_tilt: the robot climbs) and ends within 0.1383 m
    of robot_localization's expected (1.0206, 3.4292)."""
    code, report = _doctor(JACKAL, tmp_path / 'out')
    odom = '/jackal_velocity_controller/odom'
    assert _checks(report, 'covariance')[odom]['details']['pose'] == 'static'
    gain = _checks(report, 'yaw_rate_gain')[f'{odom} vs /imu/data']
    assert gain['verdict'] == 'problem' and gain['value'] > 2.0, gain
    assert 'skid steer' in gain['advice'] and gain['fixed_by_preset']
    assert _checks(report, 'imu_gravity')['/imu/data']['verdict'] == 'skipped'
    assert _checks(report, 'gyro_bias')['/imu/data']['verdict'] == 'skipped'
    heading = _checks(report, 'heading_agreement')[f'{odom} vs /imu/data (gyro heading)']
    assert heading['verdict'] == 'problem' and heading['value'] > 1000.0
    assert code == 1
    fusion = report['preset']['parameters']['complementary_fusion']['ros__parameters']
    assert fusion['wheel_odom']['mask'] == ['vx', 'vy']
    assert fusion['imu']['source'] == 'orientation' and fusion['level_with_imu_tilt'] is True
    usable = report['usable']
    assert usable['usable_with_params_yaml'] is True and not usable['not_fixable'], usable
    fused = _checks(report, 'fused')['preset']
    assert fused['verdict'] == 'ok' and 'yaw_rate_gain' in fused['advice']
    pose = report['fused']['final_pose']
    assert math.hypot(pose['x_m'] - 1.0206, pose['y_m'] - 3.4292) <= 0.1383
    # The same preset over DDS: sensing_replay as params.yaml's comment gives it.
    from harness import run_to_exit

    from sensing_nodes.doctor.fused import load_odometry

    command = report['preset']['commands']['sensing_replay'].split()
    assert command[:3] == ['sensing_replay', str(JACKAL), 'OUT']
    args = [str(JACKAL), str(tmp_path / 'replayed')] + [
        str(tmp_path / 'out' / 'params.yaml') if a == 'params.yaml' else a for a in command[3:]]
    result = run_to_exit('sensing_replay', args + ['--no-progress'], timeout=300)
    assert result.returncode == 0, result.stdout + result.stderr
    _, poses = load_odometry(tmp_path / 'replayed', '/odometry/filtered')
    assert len(poses) == 3060
    assert math.hypot(poses[-1][0] - 1.0206, poses[-1][1] - 3.4292) <= 0.1383


@_needs(RAZOR)
def test_razor_constant_orientation_is_flagged_and_the_preset_integrates_the_gyro(tmp_path,
                                                                               capsys):
    """imu_tools' SparkFun Razor, turned by hand: its orientation is (0, 0, 0, 1) in every
    message with an all-zero covariance. A problem the preset fixes by integrating the gyro
    (gyro_integrator, then the fusion's integrated input); the IMU never stands still, so
    gravity, the mount and the bias are not judged and the preset carries none of them;
    --quiet prints no log line of the nodes."""
    code, report = _doctor(RAZOR, tmp_path / 'out')
    orientation = _checks(report, 'imu_orientation')['/imu/data_raw']
    assert orientation['verdict'] == 'problem' and orientation['details']['identity']
    assert 'integrates the gyro' in orientation['fixed_by_preset']
    for name in ('imu_gravity', 'imu_mount', 'gyro_bias'):
        check = _checks(report, name)['/imu/data_raw']
        assert check['verdict'] == 'skipped' and check['advice'].startswith('not judged'), check
    params = report['preset']['parameters']
    assert params['complementary_fusion']['ros__parameters']['imu']['source'] == 'integrated'
    gyro = params['gyro_integrator']['ros__parameters']
    assert 'initial_bias_z_rad_s' not in gyro
    assert (gyro['mount_roll_rad'], gyro['mount_pitch_rad']) == (0.0, 0.0)   # the declared
    assert code == 1
    out = capsys.readouterr()
    assert '[INFO]' not in out.out + out.err
    text = (tmp_path / 'out' / 'report.html').read_text().split('<h2>Plots')[0]
    assert not re.search(r'\bnan\b', text) and 'Usable with params.yaml' in text


@_needs(FREIBURG)
def test_carmen_log_without_imu(tmp_path, capsys):
    """A converted CARMEN log (scans a metre apart, odometry, reference poses): no IMU checks,
    the laser's REP 117 conventions, the odometry's time offset against scan matching (the
    -0.155 s docs/real-data.md measures with sensing_calibrate --odom-delay), and the preset
    (scan matcher bridging the log's gaps, fusion without IMU) followed against the log's
    reference poses."""
    from sensing_nodes.tools.carmen_to_bag import convert

    convert(FREIBURG, tmp_path / 'log')
    code, report = _doctor(tmp_path / 'log', tmp_path / 'out')
    assert report['checks'][0]['details']['found']['imu'] is None
    assert not _checks(report, 'imu_gravity') and not _checks(report, 'gyro_bias')
    assert _checks(report, 'laser_rep117')['/scan']['verdict'] == 'ok'
    offset = _checks(report, 'time_offset')['/odom vs scan matching']
    assert offset['value'] == pytest.approx(-0.155, abs=0.02)
    assert code == 1 and offset['verdict'] == 'problem'     # beyond 50 ms
    preset = report['preset']['parameters']
    assert preset['icp_matcher']['ros__parameters']['max_gap_s'] > 19.7   # the longest gap
    assert preset['complementary_fusion']['ros__parameters']['use_imu'] is False
    truth = report['fused']['compared']['ground truth (/ground_truth/odom)']
    assert truth['rms_position_error_m'] < 1.5
    # The log's raw odometry drifts from scan matching by some 200 deg over the log: of two
    # headings, the one against the reference (scan matching) is distrusted, and the verdict
    # stands on the fused output following scan matching.
    heading = _checks(report, 'heading_agreement')['/odom vs scan matching']
    assert heading['verdict'] == 'problem' and heading['value'] > 100.0
    assert '/odom' in report['usable']['distrusted']
    assert report['usable']['usable_with_params_yaml'] is True
    out = capsys.readouterr()
    assert '[WARN]' not in out.out + out.err and '[INFO]' not in out.out + out.err


@pytest.mark.skipif(not (ROS / 'rosbag2-resources').is_dir(), reason='rosbag2-resources absent')
@pytest.mark.parametrize('bag', ['rosbag2_py/test/resources/sqlite3/talker',
                                 'rosbag2_tests/resources/mcap/cdr_test'])
def test_bag_without_sensor_inputs_exits_2_naming_why(bag, tmp_path, capsys):
    """rosbag2's own test bags (std_msgs String; test_msgs, whose classes are not installed):
    read, and refused with the topics listed."""
    assert doctor.main([str(ROS / 'rosbag2-resources' / bag), '--out', str(tmp_path / 'o'),
                        '--quiet']) == 2
    assert 'holds no input the doctor can check' in capsys.readouterr().err
