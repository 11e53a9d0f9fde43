"""Fusion core: the worked numbers, stamp ordering, and fusing on consistent synthetic inputs."""

import math

import numpy as np
import pytest

from sensing_nodes.core.fusion.complementary import (
    ComplementaryFusion,
    FusionSettings,
    auto_alpha,
    complementary_heading,
    fuse_information,
    inverse_variance,
)
from sensing_nodes.core.fusion.increments import (
    compounded_increment_covariance,
    increment_covariance,
)
from sensing_nodes.core.fusion.timeline import StampOrderedBuffer
from sensing_nodes.core.geometry import se2


def test_inverse_variance_worked_numbers():
    fused, variance = inverse_variance(5.00, 0.01, 5.40, 0.09)
    assert fused == pytest.approx(5.04, abs=1e-12)
    assert variance == pytest.approx(0.009, abs=1e-12)


def test_complementary_heading_worked_numbers():
    theta = complementary_heading(math.radians(30.0), 0.0, 0.0, math.radians(28.0), 0.98)
    assert math.degrees(theta) == pytest.approx(29.96, abs=1e-9)


def test_complementary_heading_across_pi():
    theta = complementary_heading(math.radians(179.0), 0.0, 0.0, math.radians(-179.0), 0.5)
    assert abs(math.degrees(theta)) == pytest.approx(180.0, abs=1e-9)


def test_auto_alpha_is_inverse_variance_weight():
    assert auto_alpha(0.01, 0.09) == pytest.approx(0.9)
    # With alpha from the variances the complementary blend equals the inverse-variance mean.
    alpha = auto_alpha(0.01, 0.09)
    blended = complementary_heading(5.00, 0.0, 0.0, 5.40 - 2 * math.pi, alpha)
    assert blended == pytest.approx(inverse_variance(5.00, 0.01, 5.40, 0.09)[0] - 2 * math.pi)


def test_matrix_fusion_reduces_to_scalar_formula_for_diagonal_covariances():
    m, cov = fuse_information(np.array([5.0, 1.0]), np.diag([0.01, 0.04]),
                              np.array([5.4, 2.0]), np.diag([0.09, 0.04]))
    assert m == pytest.approx([5.04, 1.5]) and np.diag(cov) == pytest.approx([0.009, 0.02])


def test_increment_covariance_recovers_the_added_noise():
    pose_prev, cov_prev = (1.0, 2.0, 0.7), np.diag([0.02, 0.03, 0.01])
    step, step_cov = (0.3, 0.05, 0.1), np.diag([1e-4, 4e-4, 9e-4])
    pose_now, cov_now = se2.compose_with_covariance(pose_prev, cov_prev, step, step_cov)
    assert increment_covariance(pose_prev, cov_prev, pose_now, cov_now) == pytest.approx(
        step_cov, abs=1e-12
    )


def test_a_covariance_that_grows_with_distance_alone_does_not_compound():
    """carmen_to_bag's odometry covariance (diagonal, growing with distance): what compounding
    would carry of the earlier heading variance is missing, the recovered increment covariance
    is mostly negative: None (the EKF then uses its noise model). A compounded one is kept."""
    pose_prev, pose_now = (10.0, 5.0, 0.3), se2.compose((10.0, 5.0, 0.3), (0.2, 0.0, 0.05))
    cov_prev, cov_now = np.diag([0.5, 0.5, 0.05]), np.diag([0.502, 0.502, 0.0502])
    assert compounded_increment_covariance(pose_prev, cov_prev, pose_now, cov_now) is None
    assert np.linalg.eigvalsh(increment_covariance(pose_prev, cov_prev, pose_now, cov_now)
                              ).min() == pytest.approx(0.0, abs=1e-12)   # clipped: "exact"
    step_cov = np.diag([1e-4, 4e-4, 9e-4])
    _, compounded = se2.compose_with_covariance(pose_prev, cov_prev, (0.2, 0.0, 0.05), step_cov)
    assert compounded_increment_covariance(pose_prev, cov_prev, pose_now, compounded) == \
        pytest.approx(step_cov, abs=1e-12)


def test_buffer_releases_in_stamp_order_whatever_the_arrival_order():
    def run(order):
        buf = StampOrderedBuffer(window_ns=50)
        out = []
        for stamp, rank in order:
            buf.push(stamp, rank, (stamp, rank))
            out += [item for _, item in buf.pop_ready()]
        return out + [item for _, item in buf.flush()]

    events = [(0, 0), (10, 2), (10, 0), (20, 1), (100, 0), (60, 2), (200, 1)]
    expected = sorted(events)
    assert run(events) == expected
    assert run(list(reversed(events[:4])) + events[4:]) == expected


def test_buffer_refuses_and_counts_late_items():
    buf = StampOrderedBuffer(window_ns=10)
    buf.push(0, 0, 'a')
    buf.push(100, 0, 'b')
    assert [item for _, item in buf.pop_ready()] == ['a']
    assert buf.push(-5, 0, 'late') is False and buf.late == 1


def _straight_run(settings, wheel_scale=1.0, steps=200):
    """Robot driving straight at 0.5 m/s, 10 Hz; wheels overestimate by wheel_scale, scan is
    exact."""
    fusion = ComplementaryFusion(settings)
    wheel_cov, scan_cov = np.zeros((3, 3)), np.zeros((3, 3))
    for k in range(steps + 1):
        t = k * 100_000_000
        x = 0.05 * k
        wheel_cov = wheel_cov + np.diag([1e-4, 1e-4, 1e-5])
        scan_cov = scan_cov + np.diag([1e-4, 1e-4, 1e-5])
        fusion.add_wheel(t, (x * wheel_scale, 0.0, 0.0), wheel_cov)
        fusion.add_gyro(t, 0.0, 1e-6 * k)
        fusion.add_scan_match(t, (x, 0.0, 0.0), scan_cov)
    return fusion.state


def test_equal_variances_split_a_wheel_scale_error_in_half():
    state = _straight_run(FusionSettings(), wheel_scale=1.02)
    assert state.pose[0] == pytest.approx(10.0 * 1.01, rel=1e-9)
    assert state.pose[2] == pytest.approx(0.0, abs=1e-12)
    assert state.covariance[0, 0] == pytest.approx(200 * 1e-4 / 2, rel=1e-6)


def test_wheels_only_follow_wheel_odometry():
    state = _straight_run(FusionSettings(use_scan_position=False, use_scan_heading=False), 1.02)
    assert state.pose[0] == pytest.approx(10.0 * 1.02, rel=1e-9)


def test_scan_matcher_restart_is_tied_to_the_current_estimate():
    fusion = ComplementaryFusion(FusionSettings())
    cov = np.diag([1e-4, 1e-4, 1e-5])
    for k in range(11):
        fusion.add_wheel(k * 100_000_000, (0.1 * k, 0.0, 0.0), cov * (k + 1))
        fusion.add_scan_match(k * 100_000_000, (0.1 * k, 0.0, 0.0), cov * (k + 1))
    # The matcher restarts 2 s later from identity: the fused pose must not jump back to 0.
    fusion.add_wheel(12 * 100_000_000, (1.2, 0.0, 0.0), cov * 13)
    fusion.add_scan_match(31 * 100_000_000, (0.0, 0.0, 0.0), cov)
    assert fusion.state.pose[0] == pytest.approx(1.2, abs=1e-9)


def test_an_input_that_sent_nothing_does_not_claim_the_robot_stood_still():
    """Wheel odometry that starts late must not pin the fused pose while scan matching moves."""
    fusion = ComplementaryFusion(FusionSettings())
    for k in range(21):
        t = k * 100_000_000
        fusion.add_gyro(t, 0.0, 1e-6 * (k + 1))
        fusion.add_scan_match(t, (0.05 * k, 0.0, 0.0), np.diag([1e-4, 1e-4, 1e-5]) * (k + 1))
    assert fusion.state.pose[0] == pytest.approx(1.0, abs=1e-9)


@pytest.mark.parametrize('eigenvalues, verdict', [
    ((1.0, 2e-3, 1e-6), ''),                             # positive definite: the plain-float path
    ((1.0, 2e-3, 0.0), ''),                              # singular (a still wheel): numpy's path
    ((1.0, 2e-3, -0.5e-9), ''),                          # negative within 1e-9 of the scale
    ((1.0, 2e-3, -2e-9), 'covariance is not positive semi-definite'),
    ((1.0, -2e-3, 1e-6), 'covariance is not positive semi-definite'),
])
def test_covariance_problem_judges_the_eigenvalues_not_the_path(eigenvalues, verdict):
    """The plain-float positive-definite test (_plainly_positive_definite) and the
    eigendecomposition give one verdict: a rotated diagonal, eigenvalues known exactly enough."""
    from sensing_nodes.core.fusion.validation import (
        _plainly_positive_definite,
        covariance_problem,
    )

    c, s = math.cos(0.7), math.sin(0.7)
    rotation = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ \
        np.array([[1.0, 0.0, 0.0], [0.0, math.cos(0.3), -math.sin(0.3)],
                  [0.0, math.sin(0.3), math.cos(0.3)]])
    cov = rotation @ np.diag(eigenvalues) @ rotation.T
    cov = 0.5 * (cov + cov.T)
    assert covariance_problem(cov) == verdict
    if abs(min(eigenvalues)) > 1e-12:   # (exactly singular: rounding decides the path)
        assert _plainly_positive_definite(cov.tolist()) == (min(eigenvalues) > 0.0)
    asymmetric = cov.copy()
    asymmetric[0, 1] += 1e-6
    assert covariance_problem(asymmetric) == 'covariance is not symmetric'
    assert covariance_problem(np.where(np.eye(3) > 0, np.nan, cov)) == 'covariance is not finite'
