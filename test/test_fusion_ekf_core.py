"""EKF core (core/fusion/ekf.py): worked numbers, Jacobians, cloning, gates, masks, noise model."""

import math

import numpy as np
import pytest

from sensing_nodes.core.fusion.ekf import EkfFusion, EkfSettings, adjoint, relative_jacobian
from sensing_nodes.core.fusion.inputs import (
    InputConfig,
    NoiseModel,
    Reading,
    input_config,
    mask_from_names,
)
from sensing_nodes.core.geometry import se2

# Nearly no process noise and exactly known velocities: the numbers are the measurements'.
QUIET = EkfSettings(pose_noise_density=0.0, accel_noise_density=1e-9,
                    angular_accel_noise_density=1e-9, initial_velocity_std=1e-9)
T0 = 1_000_000_000
MS = 1_000_000


def absolute(name, *quantities, **kw):
    return InputConfig(name, mask=mask_from_names(quantities), pose_mode='absolute',
                       covariance='message', **kw)


def test_two_absolute_readings_fuse_by_inverse_variance():
    """The first absolute reading sets x (5.00, var 0.01); a second input's 5.40 (var 0.09)
    gives the inverse-variance mean 5.04 with variance 0.009, as core.fusion's worked numbers."""
    ekf = EkfFusion((absolute('a', 'x'), absolute('b', 'x')), QUIET)
    ekf.update('a', Reading(T0, (5.0, 0.0, 0.0), np.diag([0.01, 1.0, 1.0])))
    ekf.update('b', Reading(T0, (5.4, 0.0, 0.0), np.diag([0.09, 1.0, 1.0])))
    state = ekf.state
    assert state.pose[0] == pytest.approx(5.04, abs=1e-9)
    assert state.covariance[0, 0] == pytest.approx(0.009, abs=1e-9)
    assert state.pose[1] == 0.0 and state.pose[2] == 0.0   # not in the masks


def test_relative_jacobian_matches_finite_differences():
    """Jacobians with respect to body-frame errors: pose ⊕ e (right perturbation)."""
    clone, pose = (1.0, -2.0, 0.7), (1.8, -1.1, 1.9)
    h, j_pose, j_clone = relative_jacobian(clone, pose)
    assert h == pytest.approx(se2.between(clone, pose), abs=1e-12)
    eps = 1e-7
    for i in range(3):
        error = [0.0, 0.0, 0.0]
        error[i] = eps
        moved_pose = se2.compose(pose, tuple(error))
        moved_clone = se2.compose(clone, tuple(error))
        for jac, moved_h in ((j_pose, relative_jacobian(clone, moved_pose)[0]),
                             (j_clone, relative_jacobian(moved_clone, pose)[0])):
            numeric = (np.array(moved_h) - np.array(h)) / eps
            assert jac[:, i] == pytest.approx(numeric, abs=1e-5)


def test_adjoint_carries_a_body_error_across_a_motion():
    """motion ⊕ e = (adjoint(motion) e) ⊕ motion, to first order."""
    motion, error = (0.8, -0.3, 0.6), np.array([1e-7, -2e-7, 3e-7])
    left = se2.compose(motion, tuple(error))
    right = se2.compose(tuple(adjoint(motion) @ error), motion)
    assert left == pytest.approx(right, abs=1e-12)


def test_matches_against_one_keyframe_do_not_shrink_its_own_error():
    """Stochastic cloning: a hundred matches against one keyframe (each 0.01 m std) cannot
    make the pose better known than the keyframe itself (0.1 m std); counting each as an
    independent increment would. The matches' own noise averages down."""
    scan = InputConfig('scan_match', mask=(True, True, True, False, False, False),
                       keyframes=True, covariance='message')
    ekf = EkfFusion((scan,), QUIET)
    ekf.reset(covariance=np.diag([0.01, 0.01, 1e-4]))
    ekf.update('scan_match', Reading(T0, new_keyframe=True))
    for k in range(1, 101):
        ekf.update('scan_match', Reading(T0 + k * 10_000_000, (0.0, 0.0, 0.0),
                                         np.diag([1e-4, 1e-4, 1e-6]), keyframe_ns=T0))
    var = ekf.state.covariance[0, 0]
    assert 0.01 <= var <= 0.01 + 1e-4 / 100 + 1e-6
    # The matched relative pose is known far better: pose minus keyframe.
    assert ekf.updates == 100


def test_a_keyframe_whose_first_message_was_lost_is_adopted_from_its_first_match():
    """The first match against an unknown keyframe (its own message dropped as late) is not
    fused but places the keyframe (pose ⊕ match⁻¹, with the match's noise); the next matches
    against it are fused: they measure the motion since that first match."""
    scan = InputConfig('scan_match', mask=(True, True, True, False, False, False),
                       keyframes=True, covariance='message')
    ekf = EkfFusion((scan,))   # velocities unknown (1 m/s, 1 rad/s std): the match decides
    ekf.reset(pose=(2.0, 1.0, math.pi / 2))
    outcome = ekf.update('scan_match', Reading(T0, (1.0, 0.0, 0.0), np.eye(3) * 1e-4,
                                               keyframe_ns=T0 - 5))
    assert not outcome.fused and 'adopted' in outcome.note and ekf.pose == (2.0, 1.0, math.pi / 2)
    outcome = ekf.update('scan_match', Reading(T0 + 10**9, (1.5, 0.0, 0.1), np.eye(3) * 1e-6,
                                               keyframe_ns=T0 - 5))
    # 0.5 m further along the keyframe's x, which points along the odom frame's y.
    assert outcome.fused
    assert ekf.pose == pytest.approx((2.0, 1.5, math.pi / 2 + 0.1), abs=2e-3)
    # The first match's noise is in the keyframe: the pose is no better known than it.
    assert ekf.state.covariance[1, 1] >= 1e-4


def test_gate_refuses_an_outlier_at_its_probability_and_counts_it():
    ekf = EkfFusion((absolute('a', 'x'), absolute('b', 'x')), QUIET)
    ekf.update('a', Reading(T0, (0.0, 0.0, 0.0), np.diag([0.01, 1.0, 1.0])))
    outcome = ekf.update('b', Reading(T0, (1.0, 0.0, 0.0), np.diag([0.01, 1.0, 1.0])))
    # innovation 1.0, its variance 0.02: squared distance 50 > 10.83, the 0.999 quantile of
    # chi-square with one degree of freedom (the mask's one row)
    assert outcome.gated and outcome.distance2 == pytest.approx(50.0) and outcome.dof == 1
    assert '10.8' in outcome.note
    assert ekf.gated == {'b': 1} and ekf.state.pose[0] == 0.0
    assert ekf.health['b'].refused == 1 and ekf.health['b'].streak == 1
    # 0.3 m: squared distance 4.5, inside the gate
    assert ekf.update('b', Reading(T0, (0.3, 0.0, 0.0), np.diag([0.01, 1.0, 1.0]))).fused
    assert ekf.health['b'].streak == 0 and ekf.health['b'].fused == 1


def test_static_covariance_gives_way_to_the_noise_model():
    """Odometry with a static covariance: each increment's variance comes from the noise model
    (variance_per_m x distance), so the fused x variance after 1 m in ten 0.1 m steps is 1e-3."""
    wheel = InputConfig('wheel_odom', mask=(True, False, False, False, False, False),
                        noise=NoiseModel(variance_per_m=1e-3, variance_per_rad=0.0,
                                         yaw_variance_per_m=0.0))
    ekf = EkfFusion((wheel,), EkfSettings(pose_noise_density=0.0, accel_noise_density=100.0,
                                          initial_velocity_std=100.0))
    static = np.diag([1e-3, 1e-3, 1e-3])
    for k in range(11):
        ekf.update('wheel_odom', Reading(T0 + k * 100_000_000, (0.1 * k, 0.0, 0.0), static))
    state = ekf.state
    assert state.pose[0] == pytest.approx(1.0, abs=1e-6)
    assert state.covariance[0, 0] == pytest.approx(1e-3, rel=0.02)


def test_a_propagated_covariance_is_used_for_its_increments():
    wheel = InputConfig('wheel_odom', mask=(True, False, False, False, False, False))
    ekf = EkfFusion((wheel,), EkfSettings(pose_noise_density=0.0, accel_noise_density=100.0,
                                          initial_velocity_std=100.0))
    for k in range(11):
        ekf.update('wheel_odom', Reading(T0 + k * 100_000_000, (0.1 * k, 0.0, 0.0),
                                         np.diag([2e-4 * k, 1e-6, 1e-6])))
    assert ekf.state.covariance[0, 0] == pytest.approx(2e-3, rel=0.02)


def test_raw_gyro_rate_with_its_bias_estimated_against_absolute_heading():
    """A gyro reading 0.02 rad/s too much while an absolute heading says the robot is still:
    the filter puts the 0.02 rad/s in the bias, not in the heading."""
    gyro = InputConfig('imu', mask=mask_from_names(['vyaw']), gyro_bias=True,
                       covariance='message')
    heading = absolute('compass', 'yaw')
    ekf = EkfFusion((gyro, heading), EkfSettings(initial_bias_std=0.1))
    for k in range(2000):
        t = T0 + k * 10_000_000
        ekf.update('imu', Reading(t, twist=(0.0, 0.0, 0.02),
                                  twist_covariance=np.diag([0.0, 0.0, 1e-6])))
        if k % 10 == 0:
            ekf.update('compass', Reading(t, (0.0, 0.0, 0.0), np.diag([1.0, 1.0, 1e-4])))
    state = ekf.state
    assert state.bias == pytest.approx(0.02, abs=1e-3)
    assert abs(state.pose[2]) < 0.01


def test_set_pose_moves_the_estimate_and_later_increments_continue_from_it():
    wheel = InputConfig('wheel_odom', mask=(True, True, True, False, False, False),
                        covariance='model', noise=NoiseModel(1e-4, 1e-4, 1e-4))
    ekf = EkfFusion((wheel,))
    ekf.update('wheel_odom', Reading(T0, (0.0, 0.0, 0.0), np.zeros((3, 3))))
    ekf.update('wheel_odom', Reading(T0 + 10**8, (0.1, 0.0, 0.0), np.zeros((3, 3))))
    ekf.set_pose((5.0, 5.0, math.pi / 2), np.diag([0.01, 0.01, 0.001]))
    for k in range(2, 12):
        ekf.update('wheel_odom', Reading(T0 + k * 10**8, (0.1 * k, 0.0, 0.0), np.zeros((3, 3))))
    pose = ekf.state.pose
    # The input starts again at the first message after set_pose (9 increments of 0.1 m north);
    # the kept velocity (1 m/s) carries the robot 0.1 m further from set_pose to that message.
    assert pose[0] == pytest.approx(5.0, abs=1e-3) and pose[1] == pytest.approx(6.0, abs=1e-3)
    assert pose[2] == pytest.approx(math.pi / 2, abs=1e-6)


def test_input_config_from_parameters_and_its_problems():
    cfg = input_config('wheel_odom', {'mask': ['vx', 'vyaw'], 'gate_probability': 0.99})
    assert cfg.mask == (False, False, False, True, False, True) and cfg.gate_probability == 0.99
    assert ('gate_probability', 'must be in [0.5, 1) (the gate cannot be switched off)', 1.0) \
        in input_config('imu', {'gate_probability': 1.0}).problems()
    with pytest.raises(ValueError, match='unknown quantities'):
        input_config('wheel_odom', {'mask': ['z']})
    bad = input_config('imu', {'pose_mode': 'sideways', 'covariance': 'guess', 'mask': []})
    assert {field for field, _, _ in bad.problems()} == {'pose_mode', 'covariance', 'mask'}


def _wheels_and_a_keyframe_match(match=(0.30, 0.05, 0.02)):
    """Wheels (differential, 3 cm per 0.1 m) along x at 0.1 m per 100 ms, a keyframe at 250 ms
    between two wheel messages, and at 500 ms (a wheel message's stamp) a tight match against
    it 5 cm off the wheels' motion (inside their gate): the filter, the pose published at the
    keyframe and the match's outcome."""
    wheel = InputConfig('wheel_odom', mask=(True, True, True, False, False, False),
                        covariance='model', noise=NoiseModel(1e-2, 1e-2, 1e-2))
    scan = InputConfig('scan_match', mask=(True, True, True, False, False, False),
                       keyframes=True, covariance='message')
    ekf = EkfFusion((wheel, scan))
    for k in range(3):
        ekf.update('wheel_odom', Reading(T0 + k * 100 * MS, (0.1 * k, 0.0, 0.0)))
    ekf.update('scan_match', Reading(T0 + 250 * MS, new_keyframe=True))
    published = ekf.state.pose
    for k in range(3, 6):
        ekf.update('wheel_odom', Reading(T0 + k * 100 * MS, (0.1 * k, 0.0, 0.0)))
    outcome = ekf.update('scan_match', Reading(T0 + 500 * MS, match, np.diag([1e-6] * 3),
                                               keyframe_ns=T0 + 250 * MS))
    return ekf, published, outcome


def test_a_match_moves_the_pose_not_its_already_published_keyframe():
    """A match the wheels say should be about (0.25, 0, 0) puts the pose at keyframe ⊕ match,
    and the keyframe stays the pose published at its scan (the optimal update would move it
    too: the wheels' increment across its stamp ties it to the motion after it)."""
    match = (0.30, 0.05, 0.02)
    ekf, published, outcome = _wheels_and_a_keyframe_match(match)
    assert outcome.fused
    slot = ekf._slots['scan_match']
    assert tuple(ekf.x[slot.offset:slot.offset + 3]) == pytest.approx(published, abs=1e-12)
    assert se2.between(published, ekf.state.pose) == pytest.approx(match, abs=2e-3)


def test_a_keyframe_correction_moves_the_clones_taken_since_the_keyframe_with_the_pose():
    """As above (the wheel clone is the pose before the match's update). The keyframe's kept
    correction moves the pose and the wheel clone together, and the next straight 0.1 m wheel
    increment is fused as measured, (0.1, 0, 0): nothing of the correction is taken back (a
    clone left behind made the increment take back 93 % of the heading shift; the increment's
    translation fused as white noise, the motion model took a share of it)."""
    ekf, _, _ = _wheels_and_a_keyframe_match()
    after = ekf.state.pose
    at = ekf._slots['wheel_odom'].offset
    clone = tuple(float(v) for v in ekf.x[at:at + 3])
    ekf.update('wheel_odom', Reading(T0 + 600 * MS, (0.6, 0.0, 0.0)))
    assert se2.between(clone, after) == pytest.approx((0.0, 0.0, 0.0), abs=1e-12)
    assert se2.between(after, ekf.state.pose) == pytest.approx((0.1, 0.0, 0.0), abs=1e-4)


def test_heading_delay_reads_the_yaw_as_the_heading_that_long_before_its_stamp():
    """An integrated heading that lags by 10 ms: from rest (yaw 0, rate 0) to yaw 0.5 rad at
    rate 1 rad/s, the fused heading is 0.5 + 1 x 0.01 = 0.51 rad (0.5 without the delay)."""
    def run(delay_s):
        imu = input_config('imu', {'covariance': 'model', 'heading_delay_s': delay_s})
        ekf = EkfFusion((imu,), EkfSettings(initial_velocity_std=100.0,
                                            angular_accel_noise_density=100.0,
                                            yaw_rate_std_rad_s=100.0))
        for stamp, yaw, rate in ((T0, 0.0, 0.0), (T0 + 100_000_000, 0.5, 1.0)):
            ekf.update('imu', Reading(stamp, (0.0, 0.0, yaw), np.zeros((3, 3)),
                                      (0.0, 0.0, rate)))
        return ekf.state.pose[2]

    assert run(0.0) == pytest.approx(0.5, abs=1e-4)
    assert run(0.01) == pytest.approx(0.51, abs=1e-4)
    bad = input_config('imu', {'heading_delay_s': -0.1})
    assert [field for field, _, _ in bad.problems()] == ['heading_delay_s']


def test_heading_step_variance_counts_both_ends_and_their_correlation():
    """The chatter measure's step variance (fusion_eval): a heading set with variance 0.01;
    1 s of prediction with pose noise 0.1 rad/√s (w, variance 0.01), then a second heading of
    variance 0.02 (v): gain 0.5, the step's error is -0.5·e0 + 0.5·w + 0.5·v, variance
    0.0025 + 0.0025 + 0.005 = 0.01, though the heading variance went from 0.01 back to 0.01
    (and the two variances summed would say 0.02)."""
    settings = EkfSettings(pose_noise_density=0.1, accel_noise_density=1e-9,
                           angular_accel_noise_density=1e-9, initial_velocity_std=1e-9)
    ekf = EkfFusion((absolute('a', 'yaw'), absolute('b', 'yaw')), settings)
    with pytest.raises(RuntimeError):
        ekf.heading_step_variance()
    ekf.follow_heading_steps()
    ekf.update('a', Reading(T0, (0.0, 0.0, 0.1), np.diag([1.0, 1.0, 0.01])))
    assert ekf.heading_step_variance() == pytest.approx(0.0, abs=1e-12)  # no step yet
    ekf.update('b', Reading(T0 + 1_000_000_000, (0.0, 0.0, 0.4), np.diag([1.0, 1.0, 0.02])))
    assert ekf.state.covariance[2, 2] == pytest.approx(0.01, abs=1e-9)
    assert ekf.state.pose[2] == pytest.approx(0.25, abs=1e-9)
    assert ekf.heading_step_variance() == pytest.approx(0.01, abs=1e-9)
    assert ekf.heading_step_variance() == pytest.approx(0.0, abs=1e-12)  # starts again
    ekf.update('b', Reading(T0 + 2_000_000_000, (0.0, 0.0, 0.4), np.diag([1.0, 1.0, 0.02])))
    ekf.set_pose((0.0, 0.0, 1.0), np.diag([1.0, 1.0, 0.5]))   # followed on from the new start
    assert ekf.heading_step_variance() == pytest.approx(0.0, abs=1e-12)


# --- matches in a local map's frame (icp_matcher's local_map mode) ----------------------------

def _map_input(**kw):
    return InputConfig('scan_match', mask=(True, True, True, False, False, False),
                       keyframes=True, covariance='message', **kw)


def test_a_match_in_a_map_measures_the_pose_from_the_maps_origin():
    """The map starts at T0 where the pose is exactly known: its origin is that pose. One
    second later (pose noise 0.1 m/sqrt(s): x variance 0.01) a match puts base_link at
    x = 0.02 m in the map with variance 0.01: the fused x is their inverse-variance mean,
    0.01 m with variance 0.005."""
    settings = EkfSettings(pose_noise_density=0.1, accel_noise_density=1e-9,
                           angular_accel_noise_density=1e-9, initial_velocity_std=1e-9)
    ekf = EkfFusion((_map_input(),), settings)
    assert "origin" in ekf.update('scan_match', Reading(T0, map_ns=T0)).note
    outcome = ekf.update('scan_match', Reading(T0 + 10**9, (0.02, 0.0, 0.0),
                                               np.diag([0.01, 0.01, 0.01]), map_ns=T0))
    assert outcome.fused
    assert ekf.state.pose[0] == pytest.approx(0.01, abs=1e-9)
    assert ekf.state.covariance[0, 0] == pytest.approx(0.005, abs=1e-9)


def test_matches_in_one_map_average_their_noise_and_each_moves_the_maps_origin():
    """A hundred matches at the origin (std 0.01 m, alternating +-0.01 m in x) in a map whose
    origin was placed by a first match (its noise in the origin): the pose stays between the
    origin's uncertainty and the matches' averaged noise, and the origin itself is revised
    (not held as a keyframe's clone is)."""
    ekf = EkfFusion((_map_input(),), QUIET)
    ekf.update('scan_match', Reading(T0, (0.0, 0.0, 0.0), np.diag([1e-4, 1e-4, 1e-6]),
                                     map_ns=T0 - 5))
    origin_before = ekf.x[7:10].copy()
    for k in range(1, 101):
        ekf.update('scan_match', Reading(T0 + k * 10 * MS, (0.01 * (-1) ** k, 0.0, 0.0),
                                         np.diag([1e-4, 1e-4, 1e-6]), map_ns=T0 - 5))
    assert ekf.updates == 100
    # The map's pose in odom absorbs the matches' mean (0): exact zero; its variance shrinks
    # from the first match's 1e-4 towards the averaged noise, 1e-4 / 101.
    assert ekf.x[7:10] == pytest.approx(origin_before, abs=1e-4)
    relative = ekf.p[0, 0] + ekf.p[7, 7] - 2 * ekf.p[0, 7]
    assert relative == pytest.approx(1e-4 / 101, rel=0.05)


def test_a_maps_origin_drifts_with_the_distance_travelled_as_seen_from_the_robot():
    """map_variance_per_m (x, y) and map_yaw_variance_per_m (yaw): a random walk of the map
    where the robot is. After 10 m along x at 1 m/s, in 1 m steps: x and yaw of the robot in
    the map are uncertain by 10 x each rate; y also by the yaw drift added 0 to 9 m behind the
    robot (the map ahead of a heading error is turned, as an odometry's path is): 1e-7 x
    (0² + ... + 9²) = 2.85e-5. Turned about the far origin instead, the 10 m lever arm would
    apply to all of it."""
    ekf = EkfFusion((_map_input(map_variance_per_m=1e-6, map_yaw_variance_per_m=1e-7),), QUIET)
    ekf.update('scan_match', Reading(T0, map_ns=T0))
    ekf.x[3] = 1.0                                      # vx: 1 m/s, exactly known (QUIET)
    for k in range(1, 11):
        ekf.predict(T0 + k * 10**9)
    assert ekf.pose == pytest.approx((10.0, 0.0, 0.0), abs=1e-9)
    _, j_pose, j_origin = relative_jacobian(tuple(ekf.x[7:10]), ekf.pose)
    h = np.zeros((3, ekf.p.shape[0]))
    h[:, :3], h[:, 7:10] = j_pose, j_origin
    seen = h @ ekf.p @ h.T
    assert np.diag(seen) == pytest.approx([1e-5, 1e-5 + 2.85e-5, 1e-6], rel=1e-6)
    # In the origin's frame the lever arms are 1 to 10 m: 1e-7 x (1² + ... + 10²) = 3.85e-5.
    assert ekf.p[8, 8] == pytest.approx(1e-5 + 3.85e-5, rel=1e-6)


def test_a_new_map_replaces_the_old_one():
    """A match in a map the filter has not seen (the matcher restarted it) places that map's
    origin from the match (not fused); the next match in it is fused."""
    ekf = EkfFusion((_map_input(),), QUIET)
    ekf.update('scan_match', Reading(T0, map_ns=T0))
    assert ekf.update('scan_match', Reading(T0 + 10 * MS, (0.0, 0.0, 0.0), np.eye(3) * 1e-4,
                                            map_ns=T0)).fused
    outcome = ekf.update('scan_match', Reading(T0 + 20 * MS, (5.0, 0.0, 0.0), np.eye(3) * 1e-4,
                                               map_ns=T0 + 20 * MS))
    assert not outcome.fused and 'adopted' in outcome.note
    assert ekf.pose == pytest.approx((0.0, 0.0, 0.0), abs=1e-9)
    assert ekf.update('scan_match', Reading(T0 + 30 * MS, (5.0, 0.0, 0.0), np.eye(3) * 1e-4,
                                            map_ns=T0 + 20 * MS)).fused
