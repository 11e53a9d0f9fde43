"""fusion_eval's input-consistency figures on worked examples (no simulation)."""

import math

import numpy as np
import pytest

from sensing_nodes.core.evaluation.fusion import (
    heading_increment_consistency,
    keyframe_match_consistency,
    map_match_consistency,
    pooled,
    stop_corrections,
)

T0 = 1_700_000_000 * 10 ** 9


def _still_truth(seconds: float):
    t = T0 + np.arange(int(seconds * 100) + 1, dtype=np.int64) * 10 ** 7   # 100 Hz
    return t, np.zeros((t.size, 3))


def test_heading_increments_two_sigma_each_give_z_rms_two():
    truth_t, truth_pose = _still_truth(2.0)
    variance_per_s = 1e-8
    sigma = math.sqrt(variance_per_s * 0.1)
    t = T0 + np.arange(400, dtype=np.int64) * 5 * 10 ** 6                    # 200 Hz
    # Every 20th sample (0.1 s apart) alternates between 0 and 2 sigma: each increment is
    # +-2 sigma while the robot stands still.
    yaw = 2.0 * sigma * ((np.arange(400) // 20) % 2)
    out = heading_increment_consistency(truth_t, truth_pose, t, yaw, variance_per_s)
    assert out['z_rms'] == pytest.approx(2.0, rel=1e-6)
    assert out['beyond_3'] == 0.0
    assert out['max_error_rad'] == pytest.approx(2.0 * sigma, rel=1e-6)


def test_keyframe_matches_distance_heading_z_and_shared_error():
    truth_t, truth_pose = _still_truth(2.0)
    sigma = 1e-3
    stamps = T0 + np.arange(1, 7, dtype=np.int64) * 10 ** 8
    keyframe_t = np.full(6, T0)                 # six matches against the first scan
    heading = sigma * np.array([1.0, 1.0, 1.0, -1.0, -1.0, -1.0])
    relative = np.column_stack([np.zeros(6), np.zeros(6), heading])
    cov = np.tile(np.diag([sigma ** 2] * 3), (6, 1, 1))
    out = keyframe_match_consistency(truth_t, truth_pose, keyframe_t, stamps, relative, cov)
    assert out['mean_distance2'] == pytest.approx(1.0)
    assert out['heading_z_rms'] == pytest.approx(1.0)
    # Consecutive pairs (+,+), (+,+), (+,-), (-,-), (-,-): correlation 3.2 / 4.8.
    assert out['heading_error_correlation'] == pytest.approx(2.0 / 3.0)
    assert out['matches_per_keyframe'] == 6.0
    # A match with no keyframe (-1) is left out.
    out = keyframe_match_consistency(truth_t, truth_pose, np.append(keyframe_t, -1),
                                     np.append(stamps, T0 + 7 * 10 ** 8),
                                     np.vstack([relative, [1.0, 1.0, 1.0]]),
                                     np.vstack([cov, cov[:1]]))
    assert out['mean_distance2'] == pytest.approx(1.0)


def test_stop_corrections_drift_before_and_after_a_stop():
    truth_t, truth_pose = _still_truth(20.0)
    t = T0 + np.arange(4001, dtype=np.int64) * 5 * 10 ** 6                   # 200 Hz, 20 s
    seconds = (t - T0) * 1e-9
    # The robot stands still throughout: the integrator's heading drifts at 1e-4 rad/s until a
    # stop at 12-14 s, where its re-estimate brings it to 2e-4 rad and it stays there.
    yaw = np.where(seconds < 12.0, 1e-4 * seconds, 2e-4)
    still = (seconds < 6.0) | ((seconds >= 12.0) & (seconds <= 14.0))
    bias = np.where(seconds < 12.0, 0.01, 0.0101)
    variance = np.where(seconds < 12.0, 1e-9, 4e-10)
    out = stop_corrections(truth_t, truth_pose, t, yaw, bias, variance, still)
    assert len(out) == 1                        # the first still period is the calibration
    stop = out[0]
    assert stop['start_s'] == pytest.approx(12.0)
    assert stop['end_s'] == pytest.approx(14.0)
    # 0.6 s before the stop: 1e-4 rad/s x 11.4 s = 1.14e-3 rad.
    assert stop['heading_error_before_deg'] == pytest.approx(math.degrees(1.14e-3))
    assert stop['heading_error_after_deg'] == pytest.approx(math.degrees(2e-4))
    assert stop['bias_change_rad_s'] == pytest.approx(1e-4)
    assert stop['bias_std_before_rad_s'] == pytest.approx(math.sqrt(1e-9))
    assert stop['bias_std_after_rad_s'] == pytest.approx(2e-5)


def test_map_matches_distance_heading_z_and_drift_with_distance():
    """Matches in a map started at T0 (its origin, left out) on a straight 1 m/s run: errors of
    +-sigma alternate (mean squared distance 1, heading z 1, consecutive correlation -1), then a
    slowly growing x error of 1e-4 m per metre shows as a positive drift per metre in x, none in
    yaw."""
    t = T0 + np.arange(2001, dtype=np.int64) * 10 ** 7                       # 100 Hz, 20 s
    truth = np.column_stack([(t - T0) * 1e-9, np.zeros(t.size), np.zeros(t.size)])
    sigma = 1e-3
    stamps = T0 + np.arange(0, 200, dtype=np.int64) * 10 ** 8                # 10 Hz
    along = (stamps - T0) * 1e-9
    sign = (-1.0) ** np.arange(200)
    pose = np.column_stack([along + sigma * sign, sigma * sign, sigma * sign])
    cov = np.tile(np.diag([sigma ** 2] * 3), (200, 1, 1))
    out = map_match_consistency(t, truth, stamps, np.full(200, T0), pose, cov)
    assert out['mean_distance2'] == pytest.approx(3.0)
    assert out['heading_z_rms'] == pytest.approx(1.0)
    assert out['heading_error_correlation'] == pytest.approx(-1.0)
    pose[:, 0] += 1e-4 * along
    out = map_match_consistency(t, truth, stamps, np.full(200, T0), pose, cov)
    assert out['drift_xy_m2_per_m'] > 0.0
    assert out['drift_yaw_rad2_per_m'] == pytest.approx(0.0, abs=1e-15)


def test_pooled_figures_weigh_every_sample():
    """Two runs of 100 and 300 samples with RMS 1 and 2 pool to sqrt((100 + 1200) / 400); the
    shares by their samples; the fused against the best single input's pooled RMS."""
    def run(rms, share, samples):
        return {'ekf': {'rms_position_m': rms, 'rms_heading_deg': rms, 'samples': samples,
                        'position_within_3': share, 'position_beyond_1': share,
                        'heading_within_3': share, 'heading_beyond_1': share},
                'scan': {'rms_position_m': 2 * rms, 'rms_heading_deg': 4 * rms,
                         'samples': samples},
                'wheel': {'rms_position_m': 3 * rms, 'rms_heading_deg': 3 * rms,
                          'samples': samples},
                'gyro': {'rms_heading_deg': 5 * rms, 'samples': samples}}
    out = pooled([run(1.0, 1.0, 100), run(2.0, 0.0, 300)])
    assert out['ekf']['rms_position_m'] == pytest.approx(math.sqrt(1300 / 400))
    assert out['ekf']['position_within_3'] == pytest.approx(0.25)
    assert out['ekf']['samples'] == 400
    assert out['ekf']['ratio_position'] == pytest.approx(0.5)        # scan: twice the fused
    assert out['ekf']['ratio_heading'] == pytest.approx(1.0 / 3.0)   # wheels: three times
