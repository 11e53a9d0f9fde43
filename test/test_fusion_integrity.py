"""The fusion's integrity: every input gated at a stated probability, fault isolation (which
input a refused scan match accuses), re-acquisition after a refusal streak, the session's
episodes and /diagnostics figures, and the simulated fault catalogue (core/sim/faults.py,
core/evaluation/faults.py; docs/fusion.md "Integrity")."""

import math

import numpy as np
import pytest

from sensing_nodes.core.evaluation.faults import CATALOGUE, CATALOGUE_SECONDS, fault_figures
from sensing_nodes.core.evaluation.fusion import EVERY_OUTPUT
from sensing_nodes.core.fusion.config import default_config, session_config
from sensing_nodes.core.fusion.ekf import EkfFusion, EkfSettings
from sensing_nodes.core.fusion.inputs import InputConfig, NoiseModel, Reading, mask_from_names
from sensing_nodes.core.fusion.integrity import gate_threshold
from sensing_nodes.core.fusion.session import FusionSession
from sensing_nodes.core.sim.faults import Fault, arrival_order, inject_matches
from sensing_nodes.core.sim.simulator import SimParams, simulate
from sensing_nodes.core.sim.world import load_world
from sensing_nodes.parameters import ParameterError
from sensing_nodes.paths import config_file

T0 = 1_700_000_000_000_000_000
MS = 1_000_000


def test_the_gates_are_the_chi_square_quantiles_of_their_probability():
    """0.999 of a consistent innovation lies within 10.83 (one row), 13.82 (two), 16.27
    (three): the quantiles of chi-square."""
    assert [round(gate_threshold(0.999, dof), 2) for dof in (1, 2, 3)] == [10.83, 13.82, 16.27]
    assert gate_threshold(0.99, 3) == pytest.approx(11.34, abs=0.01)


def test_a_gate_cannot_be_switched_off():
    """gate_chi2 (the former threshold, 0 = off) stops the configuration naming
    gate_probability; gate_probability 1 is refused."""
    with pytest.raises(ParameterError, match='scan_match.gate_chi2.*gate_probability'):
        session_config({'scan_match': {'gate_chi2': 0.0}})
    with pytest.raises(ParameterError, match='gate_probability'):
        session_config({'imu': {'gate_probability': 1.0}})


def _wheels_and_matches(wheel_speed_after: float = 1.0, match_offset: float = 0.0,
                        settings: EkfSettings | None = None, seconds: float = 2.0):
    """Wheels (50 Hz, precise) and matches in one map (10 Hz, 1 mm) of a robot driving along x
    at 1 m/s; after 1 s the wheels report wheel_speed_after m/s and the matches are
    match_offset m to the left: the filter's outcomes per input."""
    wheel = InputConfig('wheel_odom', mask=mask_from_names(['x', 'y', 'yaw']),
                        covariance='model', noise=NoiseModel(1e-4, 1e-4, 1e-4))
    scan = InputConfig('scan_match', mask=mask_from_names(['x', 'y', 'yaw']), keyframes=True,
                       covariance='message')
    ekf = EkfFusion((wheel, scan), settings or EkfSettings())
    outcomes = {'wheel_odom': [], 'scan_match': []}
    wheel_x = 0.0
    for k in range(int(seconds * 50) + 1):
        t = T0 + k * 20 * MS
        seconds_in = k * 0.02
        wheel_x += 0.02 * (wheel_speed_after if seconds_in > 1.0 else 1.0)
        outcomes['wheel_odom'].append(ekf.update('wheel_odom', Reading(t, (wheel_x, 0.0, 0.0))))
        if k % 5 == 0:
            if k == 0:
                reading = Reading(t, map_ns=T0, new_keyframe=True)
            else:
                offset = match_offset if seconds_in > 1.0 else 0.0
                reading = Reading(t, (seconds_in, offset, 0.0), np.diag([1e-6, 1e-6, 1e-8]),
                                  map_ns=T0)
            outcomes['scan_match'].append((seconds_in, ekf.update('scan_match', reading)))
    return ekf, outcomes


def test_wheels_that_slip_are_blamed_and_the_matches_fused():
    """From 1 s the wheels report 2 m/s while the matches and the motion model say 1 m/s: the
    first match after the slip is refused against the wheels' state, the replay without the
    wheels takes it, and the wheels are blamed (their readings since the last match dropped,
    the next ones held back until a match vouches for them, which none does); every match is
    fused; the fused pose stays on the matches (within 2 cm at 2 s, where the wheels are 1 m
    ahead)."""
    ekf, outcomes = _wheels_and_matches(wheel_speed_after=2.0)
    after = [o for s, o in outcomes['scan_match'] if s > 1.0]
    assert all(o.fused for o in after), [o.note for o in after]
    assert after[0].blamed == 'wheel_odom'
    held = [o for o in outcomes['wheel_odom'][51:] if o.gated]
    assert held and all('held back' in o.note for o in held)
    assert ekf.health['wheel_odom'].blamed > 0 and ekf.health['scan_match'].refused == 0
    assert ekf.pose[0] == pytest.approx(2.0, abs=0.02)


def test_a_matcher_that_jumps_is_refused_and_nobody_blamed():
    """Matches 1 m to the left from 1 s for 0.3 s against wheels and a motion model that agree:
    every wrong match refused, no input blamed, the fused y stays at 0."""
    ekf, outcomes = _wheels_and_matches(match_offset=1.0, seconds=1.3)
    after = [o for s, o in outcomes['scan_match'] if s > 1.0]
    assert len(after) == 3 and all(o.gated and not o.blamed for o in after)
    assert ekf.health['wheel_odom'].blamed == 0 and ekf.health['scan_match'].refused == 3
    assert abs(ekf.pose[1]) < 1e-3


def test_a_source_refused_long_enough_is_taken_back():
    """Matches 0.3 m to the left from 1 s on for good (the wheels, which agree with the motion
    model, had drifted): refused for reacquire_after_s (1 s) and 3 matches in a row, then taken
    back: the pose moves to the matches and they are fused again; the refusal is told once,
    the return once."""
    ekf, outcomes = _wheels_and_matches(match_offset=0.3, seconds=3.0)
    after = [(s, o) for s, o in outcomes['scan_match'] if s > 1.0]
    refused = [s for s, o in after if o.gated]
    assert refused and max(refused) <= 2.0 + 1e-9 and len(refused) >= 3
    assert all(o.fused for s, o in after if s > 2.1)
    assert ekf.health['scan_match'].reacquired == 1
    assert ekf.pose[1] == pytest.approx(0.3, abs=0.01)


def test_the_session_tells_each_episode_once_and_diagnostics_name_the_input():
    """Through the session: the matcher's jump is told once as a warning naming it (with why),
    its return once; session.integrity() gives /diagnostics its counts, its refused share and
    that it is distrusted within a second of its last refusal."""
    config = default_config(overrides={**EVERY_OUTPUT, 'use_imu': False})
    session = FusionSession(config)
    notices, states = [], []
    wheel_x = 0.0
    for k in range(0, 151):
        t = T0 + k * 20 * MS
        seconds_in = k * 0.02
        wheel_x += 0.02
        session.feed('wheel_odom', Reading(t, (wheel_x, 0.0, 0.0), np.diag([1e-8] * 3)))
        if k % 5 == 0:
            offset = 1.0 if 1.0 < seconds_in <= 1.3 else 0.0
            reading = Reading(t, map_ns=T0, new_keyframe=True) if k == 0 else \
                Reading(t, (seconds_in, offset, 0.0), np.diag([1e-6, 1e-6, 1e-8]), map_ns=T0)
            session.feed('scan_match', reading)
        session.flush()
        notices += session.take_notices()
        if k in (60, 149):
            states.append(session.integrity()['scan_match'])
    told = [n for n in notices if 'scan_match' in n.text and n.level == 'warn'
            and 'distrusted' in n.text]
    back = [n for n in notices if 'scan_match in use again' in n.text]
    assert len(told) == 1 and 'squared Mahalanobis distance' in told[0].text
    assert len(back) == 1
    assert states[0]['distrusted'] and states[0]['refused'] >= 1
    assert not states[1]['distrusted'] and states[1]['refused'] == 3
    assert 0.0 < states[1]['refused_share'] < 0.2


@pytest.fixture(scope='module')
def catalogue():
    """The fault catalogue on the default route's first 40 s, seed 0, with the shipped
    configuration (every output)."""
    run = simulate(SimParams(), load_world(config_file('default_world.yaml')), CATALOGUE_SECONDS,
                   0)
    return fault_figures(run, default_config(overrides=EVERY_OUTPUT), list(CATALOGUE))


def test_faults_of_the_matcher_are_refused_named_and_leave_the_output_alone(catalogue):
    """A 1 m sideways slip for 2 scans and a 1 m jump along the route for 0.8 s: every wrong
    match refused (at least 90 %), the matcher named within 1 s, used again within 2 s of its
    good matches, the fused RMS position and heading within 1.5x the fault-free run's."""
    for kind in ('matcher_slip', 'corridor_jump'):
        figures = catalogue[kind]
        assert figures['wrong_matches'] >= 2 and figures['wrong_refused'] >= 0.9, kind
        assert figures['named_after_s'] <= 1.0, kind
        assert figures['in_use_again_after_s'] <= 2.0, kind
        assert figures['position_ratio'] <= 1.5 and figures['heading_ratio'] <= 1.5, kind


def test_faults_the_fusion_absorbs(catalogue):
    """Scans from another place (the matcher fails on them: docs/fusion.md), a 10 ms gyro
    spike of 5 rad/s and the matcher's readings of 2 s held back then delivered at once: the
    fused RMS position and heading within 1.5x the fault-free run's; the spike's input named
    within 1 s."""
    for kind in ('foreign_scan', 'imu_spike', 'delayed_burst'):
        figures = catalogue[kind]
        assert figures['position_ratio'] <= 1.5 and figures['heading_ratio'] <= 1.5, kind
    assert catalogue['imu_spike']['named_after_s'] <= 1.0


def test_faults_of_the_dead_reckoning_are_named_and_the_input_comes_back(catalogue):
    """A 0.5 s full wheel slip and a gyro stuck at zero for 2 s of a turn: the faulty input
    refused or blamed within 1 s and fused again within 2 s of its good readings. (The fused
    error then: docs/fusion.md, "Integrity": the slip is told from the matches' disagreement
    only after a few scans.)"""
    for kind in ('wheel_slip', 'imu_stuck'):
        figures = catalogue[kind]
        assert figures['named_after_s'] <= 1.0, kind
        assert figures['in_use_again_after_s'] <= 2.0, kind
        assert figures['heading_ratio'] <= 2.0, kind


def test_a_delayed_burst_arrives_in_stamp_order_within_the_window():
    """arrival_order holds the input's readings of the window back and delivers them, in
    stamp order, with the first reading stamped at the window's end."""
    readings = [('wheel_odom', Reading(T0 + k * 50 * MS)) for k in range(40)] + \
        [('scan_match', Reading(T0 + k * 100 * MS + MS)) for k in range(20)]
    readings.sort(key=lambda r: r[1].stamp_ns)
    moved = arrival_order(readings, T0, Fault('delayed_burst', 0.5, 0.5))
    stamps = [(n, r.stamp_ns) for n, r in moved]
    end = T0 + 1000 * MS
    first_at_end = next(i for i, (n, s) in enumerate(stamps) if s >= end)
    held = stamps[first_at_end - 5:first_at_end]
    assert all(n == 'scan_match' and T0 + 500 * MS <= s < end for n, s in held)
    assert not any(n == 'scan_match' and T0 + 500 * MS <= s < end
                   for n, s in stamps[:first_at_end - 5])
    assert sorted(stamps, key=lambda x: x[1]) == sorted(
        [(n, r.stamp_ns) for n, r in readings], key=lambda x: x[1])


def test_matcher_faults_move_the_matches_the_way_they_say():
    """matcher_slip puts the matches of its window 1 m to the robot's left, corridor_jump 1 m
    ahead; outside the window nothing moves."""
    from sensing_nodes.core.sim.inputs import inputs_from_run

    run = simulate(SimParams(), load_world(config_file('default_world.yaml')), 12.0, 0)
    inputs = inputs_from_run(run)
    first = int(run.truth_t[0])
    for kind, expected in (('matcher_slip', (0.0, 1.0)), ('corridor_jump', (1.0, 0.0))):
        fault = Fault(kind, 8.0, 0.3)
        moved = inject_matches(inputs, fault)
        start, end = fault.window_ns(first)
        inside = (inputs.scan_map_t >= start) & (inputs.scan_map_t < end) \
            & (inputs.scan_map_id >= 0) & (inputs.scan_map_id != inputs.scan_map_t)
        assert inside.sum() == 3
        for i in np.flatnonzero(inside):
            yaw = inputs.scan_map_pose[i][2]
            dx, dy = moved.scan_map_pose[i][:2] - inputs.scan_map_pose[i][:2]
            along = dx * math.cos(yaw) + dy * math.sin(yaw)
            left = -dx * math.sin(yaw) + dy * math.cos(yaw)
            assert (along, left) == pytest.approx(expected, abs=1e-9)
        assert np.array_equal(moved.scan_map_pose[~inside], inputs.scan_map_pose[~inside])
