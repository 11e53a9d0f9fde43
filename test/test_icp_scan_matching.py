"""core.scan_matching without ROS: mount transforms, odometry interpolation, keyframe policy,
fallback without a jump, stamp handling, the drift on the simulated default route, and the
physical limits relative to the odometry's prediction (on and off)."""

import math

import numpy as np
import pytest

from sensing_nodes.core import icp
from sensing_nodes.core.geometry.scan import beam_angles, scan_to_points
from sensing_nodes.core.geometry.se2 import between, compose, wrap_angle
from sensing_nodes.core.scan_matching import (
    ZERO,
    KeyframeScanMatcher,
    LocalMapScanMatcher,
    OdometryBuffer,
    ScanMatcherSettings,
    limit_step,
    mount_transform,
    unmount_transform,
)
from sensing_nodes.core.sim.world import load_world, raycast
from sensing_nodes.paths import config_file

WORLD = load_world(config_file('default_world.yaml'))
ANGLES = beam_angles(-math.pi, 2 * math.pi / 360, 360)
MOUNT = (0.10, 0.05, 0.2)
T0 = 1_000_000_000_000
DT = 100_000_000


def laser_points(base_pose, mount=MOUNT):
    laser = compose(base_pose, mount)
    ranges = raycast(WORLD.segments, laser[:2], ANGLES + laser[2])
    return scan_to_points(ranges, ANGLES, 0.05, 8.0)[0]


def path(k):
    return (-2.5 + 0.05 * k, -2.0 + 0.01 * k, 0.03 * k)


def test_mount_transform_round_trip_and_covariance():
    base_motion = (0.3, -0.1, 0.25)
    laser_motion = mount_transform(base_motion, MOUNT)
    # The laser moves from compose(p, M) to compose(compose(p, motion), M).
    p = (1.0, 2.0, 0.4)
    expected = between(compose(p, MOUNT), compose(compose(p, base_motion), MOUNT))
    np.testing.assert_allclose(laser_motion, expected, atol=1e-12)
    back, cov = unmount_transform(laser_motion, np.diag([1e-4, 4e-4, 1e-5]), MOUNT)
    np.testing.assert_allclose(back, base_motion, atol=1e-12)
    np.testing.assert_allclose(cov, cov.T)
    assert np.trace(cov) > 0 and np.all(np.linalg.eigvalsh(cov) > 0)
    # A pure rotation of the laser about its own origin is a rotation plus a translation of
    # base_link when the laser sits ahead of it; the yaw variance feeds x/y through the lever arm.
    _, cov_yaw = unmount_transform((0.0, 0.0, 0.1), np.diag([0.0, 0.0, 1e-2]), (0.5, 0.0, 0.0))
    assert cov_yaw[1, 1] == pytest.approx(0.5 ** 2 * 1e-2, rel=0.02)


def test_odometry_buffer_interpolates_and_extrapolates_briefly():
    buf = OdometryBuffer(max_extrapolation_s=0.1)
    for k in range(5):
        buf.add(T0 + k * 20_000_000, (0.01 * k, 0.0, 0.02 * k))
    assert buf.pose_at(T0 + 30_000_000) == pytest.approx((0.015, 0.0, 0.03))
    assert buf.pose_at(T0 + 80_000_000 + 50_000_000) == pytest.approx((0.065, 0.0, 0.13))
    assert buf.pose_at(T0 + 80_000_000 + 150_000_000) is None       # too far past the newest
    assert buf.pose_at(T0 - 1) is None                                # before the oldest
    motion = buf.motion_between(T0 + 10_000_000, T0 + 70_000_000)
    np.testing.assert_allclose(motion, between((0.005, 0.0, 0.01), (0.035, 0.0, 0.07)))
    assert buf.add(T0, (0.0, 0.0, 0.0)) is False                      # backwards: cleared
    assert buf.stamps == [T0]


def test_matched_sequence_follows_the_truth_with_keyframes():
    settings = ScanMatcherSettings(laser_pose=MOUNT)
    matcher = KeyframeScanMatcher(settings)
    keyframes = 0
    for k in range(30):
        step = matcher.process(T0 + k * DT, laser_points(path(k)),
                               None if k == 0 else between(path(k - 1), path(k)))
        keyframes += step.new_keyframe
        assert step.status == ('first' if k == 0 else 'matched'), step.reason
    ref = between(path(0), path(29))     # 1.5 m and 50 deg, over 15 keyframes
    assert math.hypot(step.pose[0] - ref[0], step.pose[1] - ref[1]) < 0.01
    assert abs(wrap_angle(step.pose[2] - ref[2])) < math.radians(0.2)
    # 0.051 m and 1.7 deg per scan: a new keyframe every second scan (> 0.10 m), plus the first.
    assert keyframes == 15
    # Twist: the last step over 0.1 s, in base_link.
    assert step.twist[2] == pytest.approx(0.3, abs=0.01)


def test_failed_match_falls_back_to_the_prediction_and_never_jumps():
    matcher = KeyframeScanMatcher(ScanMatcherSettings(laser_pose=MOUNT))
    poses = []
    for k in range(12):
        points = laser_points(path(k))
        if k == 6:
            points = np.random.default_rng(0).uniform(-6, 6, (300, 2))     # garbage scan
        step = matcher.process(T0 + k * DT, points,
                               None if k == 0 else between(path(k - 1), path(k)))
        poses.append(step)
    bad = poses[6]
    assert bad.status == 'fallback' and bad.reason
    assert bad.new_keyframe            # a dense scan restarts the keyframe at the prediction
    ref = between(path(0), path(6))
    assert math.hypot(bad.pose[0] - ref[0], bad.pose[1] - ref[1]) < 2e-3   # exact prediction
    assert bad.covariance[0, 0] >= poses[5].covariance[0, 0] + 0.9 * 0.05 ** 2
    assert poses[7].status == 'fallback'      # the garbage keyframe fails the next one too ...
    assert poses[8].status == 'matched'       # ... then matching resumes
    for k in range(1, 12):
        step = between(poses[k - 1].pose, poses[k].pose)
        truth = between(path(k - 1), path(k))
        assert math.hypot(step[0] - truth[0], step[1] - truth[1]) < 5e-3


def test_sparse_scan_keeps_the_old_keyframe():
    matcher = KeyframeScanMatcher(ScanMatcherSettings(laser_pose=MOUNT))
    matcher.process(T0, laser_points(path(0)), None)
    empty = matcher.process(T0 + DT, np.zeros((0, 2)), between(path(0), path(1)))
    assert empty.status == 'fallback' and not empty.new_keyframe
    assert 'too few valid points' in empty.reason
    after = matcher.process(T0 + 2 * DT, laser_points(path(2)), between(path(1), path(2)))
    assert after.status == 'matched'


def test_stamp_handling_repeated_backwards_gap():
    matcher = KeyframeScanMatcher(ScanMatcherSettings(laser_pose=MOUNT, max_gap_s=1.0))
    matcher.process(T0, laser_points(path(0)), None)
    moved = matcher.process(T0 + DT, laser_points(path(1)), between(path(0), path(1)))
    repeated = matcher.process(T0 + DT, laser_points(path(1)), None)
    assert repeated.status == 'repeated' and not repeated.publish
    assert repeated.pose == moved.pose
    gap = matcher.process(T0 + DT + 5 * 10 ** 9, laser_points(path(2)), None)
    assert gap.status == 'gap' and gap.pose == moved.pose and gap.twist == (0.0, 0.0, 0.0)
    back = matcher.process(T0, laser_points(path(0)), None)
    assert back.status == 'reset_backwards' and back.pose == (0.0, 0.0, 0.0)
    assert 'backwards' in back.reason


def test_large_jump_from_the_prediction_is_rejected():
    # A prediction 0.6 m off: the match lands far from it and is not trusted.
    matcher = KeyframeScanMatcher(ScanMatcherSettings(laser_pose=MOUNT, max_jump_m=0.3))
    matcher.process(T0, laser_points(path(0)), None)
    wrong = (0.6, 0.0, 0.0)
    step = matcher.process(T0 + DT, laser_points(path(1)), wrong)
    if step.status == 'fallback':
        assert step.pose == pytest.approx(wrong)
    else:   # if it matched, it found the truth within the jump gate
        ref = between(path(0), path(1))
        assert math.hypot(step.pose[0] - ref[0], step.pose[1] - ref[1]) < 2e-3


def test_keyframe_matching_alone_drifts_under_1_percent_on_the_simulated_route():
    # The lesson's method on the lesson's scans: every beam at the stamp (without odometry the
    # keyframe mode does not deskew a sweep).
    import dataclasses

    from sensing_nodes.bench.icp.accuracy import route_drift
    from sensing_nodes.core.sim.inputs import matcher_settings
    from sensing_nodes.core.sim.simulator import SimParams

    params = dataclasses.replace(SimParams(), scan_sweep_fraction=0.0)
    result = route_drift(seed=0, laps=1.0, settings=matcher_settings(params, mode='keyframe'),
                         params=params)
    assert result['path_length_m'] > 15.0
    assert result['final_drift_fraction'] <= 0.01, result
    assert result['max_position_error_m'] <= 0.01 * result['path_length_m'], result
    assert result.get('steps_fallback', 0) <= 0.01 * result['scans'], result


def test_same_input_same_output():
    a, b = KeyframeScanMatcher(), KeyframeScanMatcher()
    for k in range(5):
        pa = a.process(T0 + k * DT, laser_points(path(k), (0, 0, 0)), None)
        pb = b.process(T0 + k * DT, laser_points(path(k), (0, 0, 0)), None)
        assert pa.pose == pb.pose
        np.testing.assert_array_equal(pa.covariance, pb.covariance)


def test_prepared_keyframe_is_reused():
    matcher = KeyframeScanMatcher(ScanMatcherSettings(laser_pose=MOUNT, keyframe_distance_m=1.0,
                                                      keyframe_angle_rad=1.0))
    matcher.process(T0, laser_points(path(0)), None)
    first = matcher.keyframe
    assert isinstance(first, icp.Target)
    for k in range(1, 5):
        matcher.process(T0 + k * DT, laser_points(path(k)), between(path(k - 1), path(k)))
    assert matcher.keyframe is first


def test_a_scan_a_microsecond_after_the_previous_keeps_the_velocity():
    """A duplicate scan with a nudged stamp must not turn a match residual into a velocity."""
    matcher = KeyframeScanMatcher(ScanMatcherSettings(laser_pose=MOUNT))
    for k in range(5):
        matcher.process(T0 + k * DT, laser_points(path(k)), None)
    twist = matcher.twist
    matcher.process(T0 + 4 * DT + 1_000, laser_points(path(4)), None)
    assert matcher.twist == twist
    for k in range(5, 10):
        step = matcher.process(T0 + k * DT, laser_points(path(k)), None)
        assert step.status == 'matched', step.reason
    ref = between(path(0), path(9))
    assert math.hypot(step.pose[0] - ref[0], step.pose[1] - ref[1]) < 0.01


# --- physical limits, relative to the odometry's prediction (local_map mode) -----------------
START = (-2.0, -1.5, 0.4)        # base_link in the room at the first scan (south-west)
TURN = (0.0, 0.0, math.pi / 2)   # what the odometry reports over the next 0.2 s: 90 deg in place
SCAN_DT = 2 * DT                 # 0.2 s: a yaw limit of 3 rad/s allows 0.6 rad (34 deg) a step


def test_limit_step_holds_the_deviation_from_the_reference():
    # Without a reference (the step itself): (0.3, 0.4) m over 0.1 s at 2 m/s is 0.2 m of its
    # 0.5 m, 0.5 rad at 3 rad/s is 0.3 rad.
    step, limited = limit_step((0.3, 0.4, 0.5), ZERO, 0.1, 2.0, 3.0)
    assert limited and step == pytest.approx((0.12, 0.16, 0.3))
    assert limit_step((0.1, 0.0, 0.1), ZERO, 0.1, 2.0, 3.0) == ((0.1, 0.0, 0.1), False)
    # The odometry turned 90 deg in 0.2 s: a step 0.05 m and 5 deg from it passes as it is ...
    turned = (0.05, 0.0, math.pi / 2 + math.radians(5.0))
    assert limit_step(turned, TURN, 0.2, 2.0, 3.0) == (turned, False)
    # ... one 0.5 m and 0.8 rad from it keeps 0.4 m (2 m/s) and 0.6 rad (3 rad/s) of that.
    step, limited = limit_step((0.3, -0.4, math.pi / 2 + 0.8), TURN, 0.2, 2.0, 3.0)
    assert limited and step == pytest.approx((0.24, -0.32, math.pi / 2 + 0.6))
    # Deviations are angles: 3.0 rad against -3.0 rad is 0.28 rad apart, within 0.3.
    assert limit_step((0.0, 0.0, -3.0), (0.0, 0.0, 3.0), 0.1, 2.0, 3.0)[1] is False


def _two_scans(settings, truth_motion, odometry_motion=TURN):
    """LocalMapScanMatcher over a scan at START and one SCAN_DT later after truth_motion (base
    frame), the odometry reporting odometry_motion; the second step and the truth (odom frame,
    whose origin is base_link at the first scan)."""
    matcher = LocalMapScanMatcher(settings)
    matcher.process(T0, laser_points(START), None)
    step = matcher.process(T0 + SCAN_DT, laser_points(compose(START, truth_motion)),
                           odometry_motion)
    return matcher, step


def test_a_90_deg_turn_the_odometry_reports_and_the_scans_confirm_passes_unclamped():
    """A turn of 90 deg in 0.2 s (the limit: 0.6 rad) reported by the odometry, the scans
    agreeing: matched and published as it is (the limits held the prediction and the step to
    34 deg before, as on a real log with 60-80 deg turns between scans)."""
    truth = (0.02, 0.01, math.pi / 2 + math.radians(2.0))
    _, step = _two_scans(ScanMatcherSettings(laser_pose=MOUNT), truth)
    assert step.status == 'matched', step.reason
    assert 'limited' not in step.events and 'prediction_limited' not in step.events
    assert math.hypot(step.pose[0] - truth[0], step.pose[1] - truth[1]) < 0.005
    assert abs(wrap_angle(step.pose[2] - truth[2])) < math.radians(0.2)


# The scans show 0.3 m sideways and 10 deg more than the odometry's 90 deg turn: the match is
# accepted (within max_jump: 0.5 m, 30 deg), but at 1 m/s and 0.5 rad/s the robot cannot be
# more than 0.2 m and 0.1 rad from the odometry's motion after 0.2 s.
SLIPPED = (0.0, 0.3, math.pi / 2 + math.radians(10.0))
SLOW = {'max_speed_m_s': 1.0, 'max_yaw_rate_rad_s': 0.5}


def test_a_match_beyond_the_limits_around_the_prediction_is_held_to_them_then_caught_up():
    matcher, step = _two_scans(ScanMatcherSettings(laser_pose=MOUNT, **SLOW), SLIPPED)
    assert step.status == 'matched', step.reason
    assert 'limited' in step.events
    np.testing.assert_allclose(step.pose, (0.0, 0.2, math.pi / 2 + 0.1), atol=0.003)
    # The map holds the match: the robot standing still, the published pose reaches it at the
    # next scan (0.1 m and 0.075 rad to go: within the limits).
    after = matcher.process(T0 + 2 * SCAN_DT, laser_points(compose(START, SLIPPED)), ZERO)
    assert after.status == 'matched' and 'limited' not in after.events, after.reason
    np.testing.assert_allclose(after.pose, SLIPPED, atol=0.003)


def test_rate_limits_off_publish_the_match_and_leave_the_prediction_alone():
    """Stamps whose time is assumed (rebuilt from a log's line order): nothing is held."""
    off = ScanMatcherSettings(laser_pose=MOUNT, rate_limits=False, **SLOW)
    _, step = _two_scans(off, SLIPPED)
    assert step.status == 'matched' and 'limited' not in step.events, step.reason
    np.testing.assert_allclose(step.pose, SLIPPED, atol=0.003)
    # Without odometry the constant-velocity prediction is held to the limits only when on:
    # after a 0.5 m step in 0.1 s (5 m/s, 2.5 times the default limit) the next prediction is
    # 5 m/s x 0.1 s again.
    for settings, held in ((ScanMatcherSettings(laser_pose=MOUNT), True),
                           (ScanMatcherSettings(laser_pose=MOUNT, rate_limits=False), False)):
        matcher = LocalMapScanMatcher(settings)
        for k in range(3):
            step = matcher.process(T0 + k * DT, laser_points(compose(START, (0.5 * k, 0, 0))),
                                   (0.5, 0.0, 0.0) if k == 1 else None)
        assert ('prediction_limited' in step.events) is held, step.events
