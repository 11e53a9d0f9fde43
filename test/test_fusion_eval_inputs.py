"""fusion_eval's input-consistency figures on worked examples (no simulation)."""

import math

import numpy as np
import pytest

from sensing_nodes.core.fusion_eval import (
    heading_increment_consistency, keyframe_match_consistency,
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
