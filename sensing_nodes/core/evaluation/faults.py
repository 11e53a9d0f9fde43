"""The fusion's fault catalogue: each fault of core/sim/faults.py injected into the same
simulated run, the fusion session run as the node runs it, and what it did about the fault
against the ground truth and the fault-free run (docs/fusion.md "Integrity").

Per fault: the fused RMS position (m) and heading (deg) errors over the run and their ratio to
the fault-free run's; how long after the fault began the faulty input was first refused or
blamed (the node's /diagnostics names it from then on, for a second: core/fusion/integrity.py);
for matcher faults, the share of the wrong matches refused; how long after the fault ended the
input was fused again; the largest fused heading step and position error in units of their own
sigma from the fault's start to 2 s after its end. Times in s, stamps in ns.
"""

from __future__ import annotations

import math

import numpy as np

from sensing_nodes.core.evaluation.fusion import (
    RecordedRun,
    input_readings,
    run_recorded,
    track_errors,
)
from sensing_nodes.core.evaluation.metrics import express_in_reference_frame, interpolate_poses
from sensing_nodes.core.fusion.config import SessionConfig
from sensing_nodes.core.geometry import se2
from sensing_nodes.core.sim.faults import (
    SENSOR_FAULTS,
    Fault,
    arrival_order,
    inject_matches,
    inject_sensors,
    wrong_matches,
)
from sensing_nodes.core.sim.inputs import FusionInputs, inputs_from_run
from sensing_nodes.core.sim.simulator import SimRun

# After a fault ends, how long its effect on the fused steps is watched (s).
AFTER_S = 2.0


def _window_figures(track: RecordedRun, inputs: FusionInputs, window: tuple[int, int]) -> dict:
    """The largest fused heading step error (in its sigma) and position error (in the output
    covariance's sigma) over the window."""
    keep = (track.t >= window[0]) & (track.t <= window[1] + int(AFTER_S * 1e9))
    reference = interpolate_poses(inputs.truth_t, inputs.truth_pose, track.t)
    estimate = express_in_reference_frame(tuple(inputs.truth_pose[0]), track.pose)
    step_error = se2.wrap_angle(np.diff(estimate[:, 2]) - np.diff(reference[:, 2]))
    step_sigma = np.sqrt(np.maximum(track.heading_step_variance[1:], 0.0) + 1e-30)
    steps = np.abs(step_error) / step_sigma
    rot = se2.rotation(-float(inputs.truth_pose[0][2]))
    error = (estimate[:, :2] - reference[:, :2]) @ rot.T
    cov = track.covariance[:, :2, :2] + np.eye(2) * 1e-18
    d2 = np.einsum('ni,nij,nj->n', error, np.linalg.inv(cov), error)
    return {'step_max_sigma': float(np.max(steps[keep[1:]], initial=0.0)),
            'position_max_sigma': float(np.sqrt(np.max(d2[keep], initial=0.0)))}


def fault_figures(run: SimRun, config: SessionConfig, faults: list[Fault],
                  base_inputs: FusionInputs | None = None) -> dict:
    """The fault-free run's figures ('none') and each fault's (the module's docstring), every
    run over the same simulated samples with `config` (every output: publish_rate_hz 0)."""
    base_inputs = base_inputs or inputs_from_run(run)
    first = int(run.truth_t[0])
    base = run_recorded(config, input_readings(base_inputs, config))
    clean = track_errors(base_inputs.truth_t, base_inputs.truth_pose, base.t, base.pose)
    out = {'none': clean}
    for fault in faults:
        inputs = inputs_from_run(inject_sensors(run, fault)) \
            if fault.kind in SENSOR_FAULTS else base_inputs
        inputs = inject_matches(inputs, fault)
        track = run_recorded(config, arrival_order(input_readings(inputs, config), first, fault))
        figures = track_errors(inputs.truth_t, inputs.truth_pose, track.t, track.pose)
        start, end = fault.window_ns(first)
        problems = [stamp for name, stamp in track.problems
                    if name == fault.input and stamp is not None and stamp >= start]
        fused_again = [stamp for name, stamp, outcome in track.outcomes
                       if name == fault.input and outcome.fused and not outcome.blamed
                       and stamp >= end]
        wrong = set(wrong_matches(inputs, fault).tolist())
        refused_wrong = [stamp for name, stamp, outcome in track.outcomes
                         if name == fault.input and stamp in wrong and outcome.gated]
        figures.update({
            'position_ratio': figures['rms_position_m'] / clean['rms_position_m'],
            'heading_ratio': figures['rms_heading_deg'] / clean['rms_heading_deg'],
            'named_after_s': (min(problems) - start) * 1e-9 if problems else math.inf,
            'in_use_again_after_s': (min(fused_again) - end) * 1e-9 if fused_again
            else math.inf,
            'wrong_matches': len(wrong),
            'wrong_refused': len(refused_wrong) / len(wrong) if wrong else math.nan,
            **_window_figures(track, inputs, (start, end))})
        out[fault.kind] = figures
    return out


# The catalogue on the default route's first 40 s: faults on its first straight (0.25 m/s, from
# 6 to 27 s), in its first 90 deg turn (27 to 30 s), as the issue lists them.
CATALOGUE = (
    Fault('foreign_scan', 15.0, 0.25),        # 2-3 scans from another place
    Fault('matcher_slip', 15.0, 0.2),         # 2 scans 1 m to the left
    Fault('corridor_jump', 15.0, 0.8),        # 1 m ahead for 0.8 s
    Fault('wheel_slip', 15.0, 0.5),           # 0.5 s full wheel slip
    Fault('imu_spike', 28.0, 0.01, 5.0),      # 10 ms of +5 rad/s
    Fault('imu_stuck', 27.5, 2.0),            # the gyro reads 0 for 2 s of a turn
    Fault('delayed_burst', 15.0, 2.0),        # the matches of 2 s held back, then at once
)
CATALOGUE_SECONDS = 40.0
