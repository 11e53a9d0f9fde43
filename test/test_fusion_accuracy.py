"""The fusion's accuracy against ground truth on the simulated robot, through the core (the
package's own wheel odometry, gyro integrator and keyframe scan matcher over core-simulated
sensors, then the EKF as config/complementary_fusion.yaml sets it; no DDS).

These bounds were measured with the keyframe matcher on scans whose beams are all taken at the
stamp, and are pinned under those conditions (`INPUTS`): the local-map matcher (icp_matcher's
default since issue 26) and the simulated sweep change the scan input, and the fusion's figures
with them are docs/nodes/icp_matcher.md's ("What the fusion should do with it").

Figures over all 8 seeds of both configurations are in docs/fusion.md (measured with
`sensing_fusion_eval`); these tests pin what holds: the strong_errors route on 8 seeds and the
default route on seed 0.
"""

import dataclasses

import numpy as np
import pytest

from sensing_nodes.core.evaluation import fusion as fe
from sensing_nodes.core.sim.inputs import simulated_inputs
from sensing_nodes.core.sim.simulator import SimParams, load_params_file, params_from_dict
from sensing_nodes.paths import config_file

INPUTS = {'scan_sweep_fraction': 0.0}         # every beam at the stamp, the keyframe matcher


def _inputs(seed, params=None):
    params = dataclasses.replace(params or SimParams(), **INPUTS)
    return simulated_inputs(seed, params, matcher_mode='keyframe')


def _score(inputs):
    inp = fe.input_errors(inputs)
    track = fe.run_ekf(inputs)
    fused = fe.track_errors(inputs.truth_t, inputs.truth_pose, track.t, track.pose,
                            track.covariance, track.heading_step_variance)
    comp = fe.run_complementary(inputs)
    seed_filter = fe.track_errors(inputs.truth_t, inputs.truth_pose, comp.t, comp.pose)
    best_position = min(inp['wheel']['rms_position_m'], inp['scan']['rms_position_m'])
    best_heading = min(inp['wheel']['rms_heading_deg'], inp['scan']['rms_heading_deg'],
                       inp['gyro']['rms_heading_deg'])
    return fused, seed_filter, best_position, best_heading


@pytest.fixture(scope='module')
def strong_errors():
    params = params_from_dict(load_params_file(config_file('bags_strong_errors.yaml')))
    return [_score(_inputs(seed, params)) for seed in range(8)]


def test_strong_errors_heading_beats_every_input_by_a_fifth(strong_errors):
    """Wheels 5 % slipping and a 1.7 deg/s gyro bias the dead reckoning does not know about:
    the fused RMS heading is at most 0.8x the best of gyro, scan matching and wheels."""
    for fused, _, _, best_heading in strong_errors:
        assert fused['rms_heading_deg'] <= 0.8 * best_heading


def test_strong_errors_position_beats_the_best_input_on_average(strong_errors):
    """Fused RMS position over 8 seeds: 0.69x the best input's on average (0.37x to 1.38x: on
    two seeds the scan matcher alone is within 2 mm all along and the fusion is level with it)."""
    ratios = [fused['rms_position_m'] / best for fused, _, best, _ in strong_errors]
    assert np.mean(ratios) <= 0.8
    assert max(ratios) <= 1.5


def test_strong_errors_covariance_is_consistent(strong_errors):
    for fused, _, _, _ in strong_errors:
        assert fused['position_within_3'] >= 0.95
        assert fused['heading_within_3'] >= 0.85


def test_strong_errors_heading_steps_do_not_chatter(strong_errors):
    """The issue's chatter criterion, in the share of fused heading steps that depart from the
    true step by more than 3 sigma of the step's error (EkfFusion.heading_step_variance): at
    most a Gaussian's 0.27 %; measured 0 to 0.077 % of about 7350 steps a seed (the few at the
    end of a turn, where the wheels' zero increment is taken as exact)."""
    for fused, _, _, _ in strong_errors:
        assert fused['chatter_beyond_3'] <= 0.0027


def test_strong_errors_ekf_beats_the_seed_complementary_filter(strong_errors):
    for fused, seed_filter, _, _ in strong_errors:
        assert fused['rms_position_m'] <= 0.5 * seed_filter['rms_position_m']
        assert fused['rms_heading_deg'] <= 0.8 * seed_filter['rms_heading_deg']


def test_default_route_seed_0_beats_every_input():
    """The 124 s default route, seed 0: fused RMS position 0.47x the scan matcher's, heading
    0.42x the gyro's, with a consistent covariance (heading beyond 1 sigma in 15 % of samples:
    on the cautious side of the issue's 20-45 % since the IMU's heading delay is compensated,
    docs/fusion.md)."""
    fused, seed_filter, best_position, best_heading = _score(_inputs(0))
    assert fused['rms_position_m'] <= 0.8 * best_position
    assert fused['rms_heading_deg'] <= 0.8 * best_heading
    assert fused['position_within_3'] >= 0.95 and fused['heading_within_3'] >= 0.95
    assert 0.1 <= fused['heading_beyond_1'] <= 0.45
    assert fused['rms_position_m'] < seed_filter['rms_position_m']
    assert fused['rms_heading_deg'] < 0.6 * seed_filter['rms_heading_deg']
    # Chatter: 1 of 7354 steps beyond 3 sigma (a Gaussian would give 20): the end of a turn
    # where the wheels' zero increment is taken as exact (docs/fusion.md).
    assert fused['chatter_beyond_3'] <= 0.0027
