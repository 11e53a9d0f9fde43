"""The fusion's accuracy against ground truth on the simulated robot, through the core (the
package's own wheel odometry, gyro integrator and scan matcher over core-simulated sensors, the
scans swept as sensor_sim's, then the EKF as config/complementary_fusion.yaml sets it; no DDS).

Issue 26's targets are pooled over 8 seeds: `sensing_fusion_eval --seeds 8` (docs/fusion.md,
"Measured"). These tests are the fast part of them: the strong_errors route (22 s) on its 8
seeds pooled, the 124 s default route on seeds 0 and 1 pooled, each with icp_matcher's default
(the local map); and the lesson's keyframe matcher (config/fusion_keyframe.yaml) on the default
route's seed 0 with every beam at the stamp (its matches are taken at the stamp).
"""

import dataclasses

import pytest

from sensing_nodes.core.evaluation import fusion as fe
from sensing_nodes.core.fusion.config import default_config
from sensing_nodes.core.sim.inputs import simulated_inputs
from sensing_nodes.core.sim.simulator import SimParams, params_from_dict
from sensing_nodes.parameters import load_parameters
from sensing_nodes.paths import config_file


def _run(inputs, config=None):
    """{estimate: track_errors} of the EKF, the complementary filter and each input."""
    track = fe.run_ekf(inputs, config)
    comp = fe.run_complementary(inputs)
    return {**fe.input_errors(inputs),
            'ekf': fe.track_errors(inputs.truth_t, inputs.truth_pose, track.t, track.pose,
                                   track.covariance, track.heading_step_variance),
            'complementary': fe.track_errors(inputs.truth_t, inputs.truth_pose, comp.t,
                                             comp.pose)}


@pytest.fixture(scope='module')
def strong_errors():
    params = params_from_dict(load_parameters('sensor_sim',
                                              config_file('bags_strong_errors.yaml')))
    return [_run(simulated_inputs(seed, params)) for seed in range(8)]


@pytest.fixture(scope='module')
def default_route():
    return [_run(simulated_inputs(seed)) for seed in (0, 1)]


def test_default_route_fused_beats_the_best_input_by_a_fifth(default_route):
    """Pooled over seeds 0 and 1: fused RMS position 0.52x the local map's (0.79 against
    1.53 mm), heading 0.24x (0.010 against its 0.042 deg; the gyro 0.073 deg)."""
    ekf = fe.pooled(default_route)['ekf']
    assert ekf['ratio_position'] <= 0.8
    assert ekf['ratio_heading'] <= 0.8


def test_default_route_covariance_is_consistent(default_route):
    """Issue 26's bands, pooled over seeds 0 and 1 (measured: position within 3 0.959, beyond
    1 0.555; heading within 3 sigma 0.984, beyond 1 sigma 0.348)."""
    ekf = fe.pooled(default_route)['ekf']
    assert ekf['position_within_3'] >= 0.95
    assert 0.40 <= ekf['position_beyond_1'] <= 0.75
    assert ekf['heading_within_3'] >= 0.95
    assert 0.20 <= ekf['heading_beyond_1'] <= 0.45


def test_strong_errors_fused_beats_the_best_input_by_a_fifth(strong_errors):
    """Wheels 5 % slipping and a 1.7 deg/s gyro bias the dead reckoning does not know about,
    8 seeds pooled: fused RMS position 0.72x the local map's, heading 0.14x the gyro's."""
    ekf = fe.pooled(strong_errors)['ekf']
    assert ekf['ratio_position'] <= 0.8
    assert ekf['ratio_heading'] <= 0.8
    # The heading's covariance holds (within 3 sigma 0.984 pooled); the position's does not
    # on this route (within 3 0.62): the local map's matches are off along the robot's path by
    # 3-6 mm while it drives, persistently (its sweep deskewed by the slipping wheels), which no
    # covariance it reports says (docs/fusion.md).
    assert ekf['heading_within_3'] >= 0.95


def test_strong_errors_heading_steps_do_not_chatter(strong_errors):
    """The issue's chatter criterion, in the share of fused heading steps that depart from the
    true step by more than 3 sigma of the step's error (EkfFusion.heading_step_variance): at
    most a Gaussian's 0.27 %; measured 0 to 0.16 % of about 1290 steps a seed (at the final
    stop, where the gyro integrator's own corrections meet the wheels' zero increments)."""
    for run in strong_errors:
        assert run['ekf']['chatter_beyond_3'] <= 0.0027


def test_default_route_heading_steps_do_not_chatter(default_route):
    """As above on the default route: 0.014 to 0.082 % of about 7350 steps a seed (8 seeds;
    the ends of turns, where the wheels' 20 ms increment reads zero rotation: docs/fusion.md)."""
    for run in default_route:
        assert run['ekf']['chatter_beyond_3'] <= 0.0027


def test_the_ekf_beats_the_seed_complementary_filter(strong_errors, default_route):
    for run in strong_errors + default_route:
        assert run['ekf']['rms_position_m'] <= 0.5 * run['complementary']['rms_position_m']
        assert run['ekf']['rms_heading_deg'] <= 0.5 * run['complementary']['rms_heading_deg']


def test_the_lessons_keyframe_matcher_fused_beats_every_input():
    """The keyframe matcher (icp_matcher mode keyframe) with config/fusion_keyframe.yaml on the
    default route, seed 0, every beam at the stamp: fused RMS position 0.47x the best input's
    (6.4 against 13.7 mm), heading 0.23x (0.023 against the gyro's 0.097 deg), consistent."""
    inputs = simulated_inputs(0, dataclasses.replace(SimParams(), scan_sweep_fraction=0.0),
                              matcher_mode='keyframe')
    config = default_config(config_file('fusion_keyframe.yaml'), overrides=fe.EVERY_OUTPUT)
    run = _run(inputs, config)
    ekf = fe.pooled([run])['ekf']
    assert ekf['ratio_position'] <= 0.8 and ekf['ratio_heading'] <= 0.8
    assert ekf['position_within_3'] >= 0.95 and ekf['heading_within_3'] >= 0.95
    assert run['ekf']['chatter_beyond_3'] <= 0.0027
