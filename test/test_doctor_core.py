"""sensing_doctor's checks (core/diagnosis) on worked numbers: no bag, no ROS."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sensing_nodes.core.diagnosis import covariance, cross, imu, laser, tf, timing
from sensing_nodes.core.diagnosis.check import number, plural
from sensing_nodes.core.geometry.imu_mount import mount_rotation

S = 1_000_000_000


def _turning_yaw(t_s: np.ndarray) -> np.ndarray:
    """A yaw that turns back and forth with changing rates (rad)."""
    return 0.8 * np.sin(0.7 * t_s) + 0.3 * np.sin(2.3 * t_s + 0.4)


@pytest.mark.parametrize('offset_s', [0.0, 0.05, -0.12])
def test_time_offset_of_a_late_stream_with_a_scale_error(offset_s):
    """Stream a (200 Hz) shows b's (10 Hz) yaw offset_s later and 3 % too large: the offset is
    found to a millisecond, the scale does not pull it."""
    t_b = np.arange(0.0, 60.0, 0.1)
    t_a = np.arange(0.0, 60.0, 0.005)
    yaw_a = 1.03 * _turning_yaw(t_a - offset_s)
    found, turned, count = timing.estimate_offset((t_a * S).astype(np.int64), yaw_a,
                                                  (t_b * S).astype(np.int64), _turning_yaw(t_b))
    assert found == pytest.approx(offset_s, abs=0.001)
    assert turned > math.radians(90.0) and count > 500


def test_time_offset_needs_turning():
    t = (np.arange(0.0, 30.0, 0.01) * S).astype(np.int64)
    with pytest.raises(ValueError, match='turning'):
        timing.pairwise_offset(t, np.zeros(t.size), t[::10], np.zeros(t.size // 10))


def test_offsets_solved_from_pairs():
    """Three sources and a reference: the pairs' offsets, weighted, give each source's
    offset; a source no pair reaches is left out."""
    pairs = {('gyro', 'scan'): (0.0533, 500.0), ('wheels', 'scan'): (0.0052, 500.0),
             ('gyro', 'wheels'): (0.0500, 3000.0), ('odom', 'wheels'): (-0.0001, 3000.0)}
    solved = timing.solve_offsets(['gyro', 'wheels', 'odom', 'scan', 'alone'], 'scan', pairs)
    assert set(solved) == {'gyro', 'wheels', 'odom', 'scan'} and solved['scan'] == 0.0
    assert solved['gyro'] - solved['wheels'] == pytest.approx(0.050, abs=0.0005)
    assert solved['odom'] == pytest.approx(solved['wheels'] - 0.0001, abs=1e-6)
    assert 0.0 < solved['wheels'] < 0.0052


def test_stream_checks_count_backwards_repeated_and_gaps():
    t = np.arange(0, 1000) * 20_000_000                 # 50 Hz
    t[500:] += 600_000_000                              # a 0.62 s gap
    t[100], t[101] = t[101], t[100]                     # one step back
    t[300] = t[299]                                     # one repeat
    checks = {c.name: c for c in timing.stream_checks('/j', 'joints', t, t + 5_000_000)}
    assert checks['rate'].value == pytest.approx(50.0)
    back, same = checks['stamps_backwards'], checks['stamps_repeated']
    assert back.value == 1 and back.verdict == 'problem'
    assert same.value == 1 and same.verdict == 'warning'
    assert checks['gaps'].verdict == 'warning' and checks['gaps'].value == pytest.approx(0.62)
    assert checks['delay'].value == pytest.approx(0.005) and checks['delay'].verdict == 'ok'


def test_gravity_and_roll_pitch_of_a_tilted_imu():
    """An IMU at roll 20, pitch -10 deg reads g along the IMU axis that is base_link's z; the
    roll and pitch come back, and the check measures the tilt from a level declaration."""
    mount = mount_rotation(math.radians(20.0), math.radians(-10.0), 0.0)
    up = mount.T @ np.array([0.0, 0.0, 1.0])
    roll, pitch = imu.roll_pitch_of(up)
    assert (math.degrees(roll), math.degrees(pitch)) == pytest.approx((20.0, -10.0))
    n = 2000
    t = (np.arange(n) * 5_000_000).astype(np.int64)
    accel = np.tile(9.81 * up, (n, 1)) + np.random.default_rng(0).normal(0, 0.02, (n, 3))
    gyro = np.random.default_rng(1).normal(0, 0.001, (n, 3))
    still = imu.stillness(t, gyro, accel)
    assert still.still.all() and still.longest_s == pytest.approx(9.995, abs=0.01)
    check, found, found_std = imu.gravity_check('/imu', accel, still, np.eye(3))
    tilt = math.degrees(math.acos(math.cos(math.radians(20)) * math.cos(math.radians(10))))
    assert check.value == pytest.approx(tilt, abs=0.2) and check.verdict == 'problem'
    assert np.allclose(found, up, atol=0.005)
    # The accelerometer's unknown bias bounds the tilt's sigma from below (1.2 deg).
    assert math.degrees(found_std) == pytest.approx(1.17, abs=0.05)


def test_mount_yaw_from_accelerations():
    """An IMU yawed 30 deg sees base_link's forward acceleration 30 deg to its right."""
    t_s = np.arange(0.0, 40.0, 0.005)
    v = 0.4 * np.sin(0.5 * t_s) ** 2                     # speeds up and slows down
    w = 0.3 * np.cos(0.21 * t_s)
    a_base = np.column_stack((np.gradient(v, t_s), v * w, np.full(t_s.size, 9.81)))
    mount = mount_rotation(0.0, 0.0, math.radians(30.0))
    accel = a_base @ mount + [0.05, -0.03, 0.0]           # mount^T a, plus a bias
    t = (t_s * S).astype(np.int64)
    yaw, rms, std = imu.horizontal_yaw(t, accel, 0.0, 0.0, t, v, w)
    assert math.degrees(yaw) == pytest.approx(30.0, abs=0.5) and rms > 0.1
    assert math.degrees(std) < 0.5


def test_covariance_kinds_and_nees():
    zero = np.zeros((10, 3))
    static = np.tile([1e-3, 1e-3, 1e6], (10, 1))        # 1e6: an unused axis
    growing = np.cumsum(np.full((10, 3), 1e-4), axis=0)
    assert [covariance.covariance_kind(v) for v in (zero, static, growing)] == [
        'zero', 'static', 'growing']
    check = covariance.odometry_covariance_check('/odom', zero, zero)
    assert check.verdict == 'problem'
    errors = np.random.default_rng(2).normal(0.0, 0.01, (4000, 3))
    honest = covariance.nees_check('/odom', errors, np.full((4000, 3), 1e-4))
    assert honest.value == pytest.approx(1.0, abs=0.1) and honest.verdict == 'ok'
    assert covariance.nees_check('/odom', errors, np.full((4000, 3), 1e-6)).verdict == 'warning'


def test_laser_ranges_rep117():
    ranges = np.full((20, 100), 2.0)
    ranges[3, :10] = np.nan
    ranges[5, :] = np.nan
    ranges[7, :5] = 0.05                                 # below range_min, finite
    nan, conv, limits = laser.range_checks('/scan', ranges, 0.1, 8.0)
    assert nan.value == 110 and nan.verdict == 'problem'   # a scan all NaN
    assert nan.details['scans_with_nan'] == 2 and nan.details['scans_all_nan'] == 1
    assert conv.value == 5 and conv.verdict == 'warning'
    assert limits.verdict == 'ok'
    assert laser.range_checks('/scan', ranges, 8.0, 0.1)[2].verdict == 'problem'


def test_two_publishers_of_one_transform():
    """One smooth track alone passes; interleaved with a second one 0.3 m away it does not."""
    t = np.arange(0, 400) * 20_000_000
    track = np.column_stack((0.005 * np.arange(400), np.zeros(400), np.zeros(400)))
    assert tf.publishers_check('odom -> base_link', t, track).verdict == 'ok'
    other = track + [0.3, 0.1, 0.05]
    mixed = np.empty((800, 3))
    mixed[0::2], mixed[1::2] = track, other
    check = tf.publishers_check('odom -> base_link', np.repeat(t, 2), mixed)
    assert check.verdict == 'problem' and check.value > 90.0
    assert check.details['stamps_repeated'] == 400


def test_a_static_transform_declared_twice_differently():
    once = tf.static_check('base_link -> laser', np.array([[0.1, 0.0, 0.2]]),
                           np.array([[0.0, 0.0, 0.0, 1.0]]))
    assert once.verdict == 'ok'
    half_turn = np.array([[0.0, 0.0, 0.0, 1.0], [1.0, 0.0, 0.0, 0.0]])   # level, upside down
    twice = tf.static_check('base_link -> imu_link', np.zeros((2, 3)), half_turn)
    assert twice.verdict == 'problem' and twice.details['spread_deg'] == pytest.approx(180.0)


# --- cross-source checks, mounts with their sigma, the report's numbers -----------------------

def _yaw_tracks(gain: float, offset_rad_s: float = 0.0, seconds: float = 60.0):
    """A gyro's cumulative yaw (200 Hz) and a second source's (50 Hz) turning `gain` times as
    much plus a rate offset."""
    t_g = np.arange(0.0, seconds, 0.005)
    t_w = np.arange(0.0, seconds, 0.02)
    yaw_g = _turning_yaw(t_g)
    yaw_w = gain * _turning_yaw(t_w) + offset_rad_s * t_w
    return (t_w * S).astype(np.int64), yaw_w, (t_g * S).astype(np.int64), yaw_g


@pytest.mark.parametrize('gain, verdict', [(1.0, 'ok'), (5.0, 'problem'), (0.2, 'problem'),
                                           (1.12, 'problem')])
def test_yaw_rate_gain_against_the_gyro(gain, verdict):
    """Wheels turning `gain` times the gyro's yaw with a 0.01 rad/s offset: the gain and the
    offset come back; outside 0.9-1.1 a problem naming skid steer."""
    check = cross.yaw_rate_gain('wheels', '/imu', *_yaw_tracks(gain, 0.01), 'fix it')
    assert check.verdict == verdict and check.value == pytest.approx(gain, rel=0.01)
    assert check.details['offset_rad_s'] == pytest.approx(0.01, abs=0.002)
    assert check.details['correlation'] == pytest.approx(1.0, abs=1e-3)
    assert ('skid steer' in check.advice and 'fix it' in check.advice) == (verdict == 'problem')


def test_yaw_rate_gain_not_judged_without_turning():
    t = (np.arange(0.0, 60.0, 0.02) * S).astype(np.int64)
    check = cross.yaw_rate_gain('wheels', '/imu', t, np.zeros(t.size), t, np.zeros(t.size), '')
    assert check.verdict == 'skipped' and check.advice.startswith('not judged')


def test_speed_scale_against_scan_matching():
    rng = np.random.default_rng(4)
    reference = rng.uniform(0.05, 0.15, 200)
    far = cross.speed_scale('wheels', 1.03 * reference, reference, 'set the radius')
    assert far.verdict == 'problem' and far.value == pytest.approx(3.0, abs=0.01)
    assert cross.speed_scale('wheels', reference, reference, '').verdict == 'ok'
    short = cross.speed_scale('wheels', reference[:5], reference[:5], '')
    assert short.verdict == 'skipped' and short.advice.startswith('not judged')


def test_imu_orientation_placeholder_zero_covariance_and_a_good_one():
    n = 100
    identity = np.tile([0.0, 0.0, 0.0, 1.0], (n, 1))
    placeholder = cross.orientation_check('/imu', identity, np.zeros((n, 3)), math.radians(90))
    assert placeholder.verdict == 'problem' and placeholder.details['identity']
    assert 'integrates the gyro' in placeholder.advice
    yaw = np.linspace(0.0, 1.0, n)
    turning = np.column_stack((np.zeros(n), np.zeros(n), np.sin(yaw / 2), np.cos(yaw / 2)))
    unknown = cross.orientation_check('/imu', turning, np.zeros((n, 3)), 1.0)
    assert unknown.verdict == 'problem' and not unknown.details['constant']
    assert 'covariance: model' in unknown.advice
    good = cross.orientation_check('/imu', turning, np.full((n, 3), 1e-4), 1.0)
    assert good.verdict == 'ok' and good.value == pytest.approx(math.degrees(1.0), abs=0.1)


def test_heading_agreement_of_two_sources():
    t_w, yaw_w, t_g, yaw_g = _yaw_tracks(1.0, seconds=15.0)
    same = cross.heading_agreement('wheels', 'gyro', t_w, yaw_w, t_g, yaw_g)
    assert same.verdict == 'ok' and same.value < 0.1
    # 120 deg over some 700 deg of turning: a problem; 20 deg only a warning.
    for drift, verdict in ((120.0, 'problem'), (20.0, 'warning')):
        drifting = yaw_w + np.linspace(0.0, math.radians(drift), yaw_w.size)
        apart = cross.heading_agreement('wheels', 'gyro', t_w, drifting, t_g, yaw_g)
        assert apart.verdict == verdict and apart.value == pytest.approx(drift, rel=0.05)


@pytest.mark.parametrize('measured_deg, sigma_deg, expected_deg', [
    (89.4, 0.5, 90.0), (-179.4, 1.2, 180.0), (92.0, 0.5, 92.0), (2.0, 0.9, 2.0),
    (1.5, 0.9, 0.0), (3.0, None, 3.0)])
def test_an_angle_snaps_to_a_right_angle_within_two_sigma(measured_deg, sigma_deg, expected_deg):
    sigma = None if sigma_deg is None else math.radians(sigma_deg)
    found = math.degrees(imu.snap(math.radians(measured_deg), sigma))
    assert math.remainder(found - expected_deg, 360.0) == pytest.approx(0.0, abs=1e-9)


def test_gravity_is_not_judged_when_never_still():
    """An IMU turning all the time: no still window, so gravity says nothing (not judged)."""
    n = 2000
    t = (np.arange(n) * 5_000_000).astype(np.int64)
    gyro = np.column_stack((0.5 * np.sin(np.arange(n) * 0.01), np.zeros(n), np.full(n, 0.3)))
    accel = np.tile([0.0, 0.0, 9.81], (n, 1))
    still = imu.stillness(t, gyro, accel)
    check, up, up_std = imu.gravity_check('/imu', accel, still, np.eye(3))
    assert check.verdict == 'skipped' and up is None and up_std is None


def test_numbers_and_plurals_for_people():
    assert number(1.735e-14) == '0' and number(None) == '' and number(float('nan')) == ''
    assert number(0.123456) == '0.1235' and number(50.0) == '50' and number(2.5e7) == '2.5e+07'
    assert plural(1, 'problem') == '1 problem' and plural(3, 'problem') == '3 problems'


def test_reader_failures_in_words():
    from sensing_nodes.bags.storage import failure_reason

    class AnyReaderError(Exception):
        pass

    nested = AnyReaderError(('Header could not be read from file.',))
    assert failure_reason(nested) == 'Header could not be read from file'
    embedded = AnyReaderError("Bag index looks damaged: ('Header could not be read.',)")
    assert failure_reason(embedded) == 'Bag index looks damaged: Header could not be read'
    assert failure_reason(KeyError('relative_file_paths')) == \
        'the field relative_file_paths is missing'
