"""core.scan_matching without ROS: mount transforms, odometry interpolation, keyframe policy,
fallback without a jump, stamp handling, and the drift on the simulated default route."""

import math

import numpy as np
import pytest

from sensing_nodes.core import icp
from sensing_nodes.core.geometry.scan import beam_angles, scan_to_points
from sensing_nodes.core.geometry.se2 import between, compose, wrap_angle
from sensing_nodes.core.scan_matching import (
    KeyframeScanMatcher,
    OdometryBuffer,
    ScanMatcherSettings,
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

    from sensing_nodes.bench.icp_sim import route_drift
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
