"""sensing_doctor's fault catalogue (issue 25): one clean simulated recording (55 s, recorded
once for the module) and faults injected by rewriting its messages (test/doctor_faults.py);
each is found with the right number, and the clean bag raises no problem, gives a preset that
loads into the nodes, and exits 0."""

from __future__ import annotations

import json
import math
from pathlib import Path

import doctor_faults as faults
import numpy as np
import pytest
import yaml

from sensing_nodes.core.diagnosis.imu import rotation_angle_deg
from sensing_nodes.core.geometry.imu_mount import mount_rotation
from sensing_nodes.tools import doctor


@pytest.fixture(scope='module')
def clean(tmp_path_factory) -> Path:
    return faults.record_clean(tmp_path_factory.mktemp('doctor'))


def _doctor(bag: Path, out: Path, *extra: str) -> tuple[int, dict]:
    code = doctor.main([str(bag), '--out', str(out), '--quiet', *extra])
    return code, json.loads((out / 'report.json').read_text())


def _faulty(clean: Path, tmp_path: Path, change) -> tuple[int, dict]:
    bag = faults.rewrite(clean, tmp_path / 'faulty', change)
    return _doctor(bag, tmp_path / 'out', '--no-fusion')


def _check(report: dict, name: str, subject: str | None = None) -> dict:
    found = [c for c in report['checks'] if c['name'] == name
             and (subject is None or c['subject'] == subject)]
    assert len(found) == 1, (name, subject, [c['subject'] for c in report['checks']
                                             if c['name'] == name])
    return found[0]


def _mount_found(check: dict) -> np.ndarray:
    d = check['details']
    return mount_rotation(*(math.radians(d[k]) for k in ('roll_deg', 'pitch_deg', 'yaw_deg')))


def test_clean_bag_raises_no_problem_and_its_preset_runs(clean, tmp_path):
    """The clean recording: exit 0, no problem, every check judged; the geometry found is the
    declared one (config/), the IMU level; params.yaml loads into the four nodes and their
    fused output stays within a few cm and a degree of scan matching."""
    code, report = _doctor(clean, tmp_path / 'out')
    problems = [c for c in report['checks'] if c['verdict'] == 'problem']
    assert code == 0 and not problems, problems
    assert report['exit_status'] == 0 and report['verdict'] in ('ok', 'warning')
    assert abs(_check(report, 'wheel_radius')['value']) < 0.5           # %
    assert abs(_check(report, 'wheel_separation')['value']) < 0.5
    assert _check(report, 'imu_mount')['value'] < 1.0                     # deg
    assert _check(report, 'gyro_noise')['verdict'] == 'ok'               # 12 s still: Allan
    params = yaml.safe_load((tmp_path / 'out' / 'params.yaml').read_text())
    assert set(params) == {'wheel_odometry', 'gyro_integrator', 'icp_matcher',
                           'complementary_fusion'}
    wheel = params['wheel_odometry']['ros__parameters']
    assert wheel['wheel_radius_m'] == pytest.approx(0.05, rel=0.005)
    assert wheel['wheel_radius_m'] * wheel['right_radius_multiplier'] == pytest.approx(
        0.0505, rel=0.005)       # sensor_sim's right wheel is 1 % large
    fused = _check(report, 'fused')
    assert fused['verdict'] == 'ok' and fused['value'] > 500
    against_scan = report['fused']['compared']['scan matching']
    assert against_scan['rms_position_error_m'] < 0.05
    assert against_scan['rms_heading_error_deg'] < 1.0
    html = (tmp_path / 'out' / 'report.html').read_text()
    assert html.count('data:image/png;base64,') >= 3 and 'http' not in html.replace(
        'https://', '').split('<body>')[0]


@pytest.mark.parametrize('name, mount', [
    ('upside down', mount_rotation(math.pi, 0.0, 0.0)),
    ('yawed 90 deg', mount_rotation(0.0, 0.0, math.pi / 2)),
    ('rolled -90 deg', mount_rotation(-math.pi / 2, 0.0, 0.0)),
])
def test_imu_mount_is_found_within_two_degrees(clean, tmp_path, name, mount):
    """The IMU's vectors rotated as a mount would turn them, /tf_static still declaring it
    level: a problem, and the mount found within 2 deg of the true one."""
    code, report = _faulty(clean, tmp_path, faults.rotated_imu(mount))
    check = _check(report, 'imu_mount')
    assert code == 1 and check['verdict'] == 'problem'
    assert rotation_angle_deg(_mount_found(check), mount) < 2.0, check
    if name == 'upside down':
        gravity = _check(report, 'imu_gravity')
        assert gravity['verdict'] == 'problem' and gravity['details']['seen'] == 'upside down'
    params = report['preset']['parameters']['gyro_integrator']['ros__parameters']
    preset = mount_rotation(params['mount_roll_rad'], params['mount_pitch_rad'],
                            params['mount_yaw_rad'])
    assert rotation_angle_deg(preset, mount) < 2.0


def test_wheel_radius_five_percent_off(clean, tmp_path):
    code, report = _faulty(clean, tmp_path, faults.wheel_radius_off(1.05))
    check = _check(report, 'wheel_radius')
    assert code == 1 and check['verdict'] == 'problem'
    assert check['value'] == pytest.approx(5.0, abs=0.5)                 # % of the declared
    assert abs(_check(report, 'wheel_separation')['value']) < 0.5


def test_wheel_separation_ten_percent_off(clean, tmp_path):
    code, report = _faulty(clean, tmp_path, faults.scaled_wheels(difference_scale=1.1))
    check = _check(report, 'wheel_separation')
    assert code == 1 and check['verdict'] == 'problem'
    assert check['value'] == pytest.approx(10.0, abs=0.5)
    assert abs(_check(report, 'wheel_radius')['value']) < 0.5


def test_imu_fifty_ms_late(clean, tmp_path):
    """The IMU's header stamps 50 ms late: its yaw motion against scan matching's is 50 ms
    late (within 5 ms), the wheels' is not, and the preset carries the fusion's delay."""
    _, report = _faulty(clean, tmp_path, faults.shifted_stamps('/imu/data_raw', 50_000_000))
    imu = _check(report, 'time_offset', '/imu/data_raw vs scan matching')
    wheels = _check(report, 'time_offset', 'wheels vs scan matching')
    assert imu['verdict'] != 'ok'      # warning from 10 ms, problem from 50 ms
    assert imu['value'] == pytest.approx(0.050, abs=0.005)
    assert abs(wheels['value']) < 0.01 and wheels['verdict'] == 'ok'
    fusion = report['preset']['parameters']['complementary_fusion']['ros__parameters']
    assert fusion['imu']['delay_s'] == pytest.approx(0.050, abs=0.005)


def test_odometry_with_zero_covariance(clean, tmp_path):
    code, report = _faulty(clean, tmp_path, faults.zero_covariance('/wheel/odom'))
    check = _check(report, 'covariance', '/wheel/odom')
    assert code == 1 and check['verdict'] == 'problem' and check['value'] == 0.0


def test_second_odom_to_base_link_publisher(clean, tmp_path):
    code, report = _faulty(clean, tmp_path, faults.second_tf_publisher())
    check = _check(report, 'tf_publishers', 'odom -> base_link')
    assert code == 1 and check['verdict'] == 'problem' and check['value'] > 20.0


def test_stamps_going_backwards(clean, tmp_path):
    code, report = _faulty(clean, tmp_path, faults.reversed_stamps('/joint_states', count=5))
    check = _check(report, 'stamps_backwards', '/joint_states')
    assert code == 1 and check['verdict'] == 'problem' and check['value'] == 5


def test_nan_ranges(clean, tmp_path):
    """NaN is REP 117's invalid reading: counted (300 beams in 10 scans) and warned about."""
    code, report = _faulty(clean, tmp_path, faults.nan_ranges(scans=10, beams=30))
    check = _check(report, 'laser_nan', '/scan')
    assert check['value'] == 300 and check['verdict'] == 'warning'
    assert check['details']['scans_with_nan'] == 10
    assert code == 0      # warnings only: the bag can be used


def test_unreadable_bag_exits_2_naming_why(tmp_path, capsys):
    (tmp_path / 'notabag.bag').write_bytes(b'not a bag at all')
    assert doctor.main([str(tmp_path / 'notabag.bag'), '--out', str(tmp_path / 'o')]) == 2
    assert 'cannot use the bag' in capsys.readouterr().err
    assert doctor.main([str(tmp_path / 'missing'), '--out', str(tmp_path / 'o')]) == 2
    assert 'no such bag' in capsys.readouterr().err
