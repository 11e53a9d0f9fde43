"""The EKF on the real CARMEN logs (docs/real-data.md's command, icp_matcher's default local
map, every gate on): no worse than the better of the scan matcher and the odometry, to within
2 %, and no fused step far off the reference's motion where the odometry has none."""

import math
from pathlib import Path

import numpy as np
import pytest
from harness import carmen_pipeline

CARMEN = Path(__file__).resolve().parents[1] / '..' / 'shared' / 'datasets' / 'carmen'
FREIBURG = CARMEN / 'freiburg-101-corrected.log.gz'
ACES = CARMEN / 'aces-corrected.log.gz'
TOPICS = ['/odom', '/scan_match/odom', '/odometry/filtered']


def _report(log: Path, tmp_path: Path) -> dict:
    from sensing_nodes.tools.eval import evaluate

    return evaluate(carmen_pipeline(log, tmp_path, mode='local_map'), TOPICS)


def _far(errors) -> np.ndarray:
    """Relations more than 1 m or 30 deg off the reference's motion."""
    return (errors.translation_m > 1.0) | (errors.rotation_rad > math.radians(30.0))


@pytest.mark.parametrize('log', [FREIBURG, ACES], ids=['freiburg-101', 'aces'])
def test_ekf_is_no_worse_than_its_better_input(log, tmp_path):
    """ATE and consecutive RPE mean (translation) within 2 % of the better of matcher and
    odometry (the matcher on both logs), with the gates on (config/fusion_carmen.yaml sets
    none off). Measured (2026-11-28): Freiburg 101 fused ATE 0.044 m, RPE 0.0331 m (matcher
    0.044, 0.0329); ACES 0.916 m, 0.0425 m (matcher 0.916, 0.0427)."""
    if not log.is_file():
        pytest.skip(f'{log} not present')
    report = _report(log, tmp_path)
    fused, matcher, odometry = (report['estimates'][t] for t in
                                ('/odometry/filtered', '/scan_match/odom', '/odom'))
    for key in ('ate_rmse_m', 'rpe_translation_mean_m'):
        assert fused[key] <= 1.02 * min(matcher[key], odometry[key]), key
    errors = report['_errors']
    far = _far(errors['/odometry/filtered']) & ~_far(errors['/odom'])
    assert not far.any(), errors['/odometry/filtered'].t2[far]
