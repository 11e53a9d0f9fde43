"""Drift of scan matching alone (no odometry: constant-velocity prediction) on the simulated
default route, against the simulator's ground truth."""

from __future__ import annotations

import json

import numpy as np

from sensing_nodes.core.geometry.scan import scan_to_points
from sensing_nodes.core.geometry.se2 import between, wrap_angle
from sensing_nodes.core.scan_matching import KeyframeScanMatcher, ScanMatcherSettings
from sensing_nodes.core.sim.simulator import SimParams, make_route, simulate
from sensing_nodes.core.sim.world import load_world
from sensing_nodes.paths import config_file


def route_drift(seed: int = 0, laps: float = 1.0, settings: ScanMatcherSettings | None = None,
                params: SimParams | None = None) -> dict:
    """Run the simulator over `laps` of its route and the keyframe matcher over every scan.
    Returns the path length (m), final and maximum position error (m), the final error as a
    fraction of the path length, the final heading error (deg) and the step counts."""
    params = params or SimParams()
    duration = laps * make_route(params).period_s
    run = simulate(params, load_world(config_file('default_world.yaml')), duration, seed)
    settings = settings or ScanMatcherSettings(
        laser_pose=(params.laser_x_m, params.laser_y_m, params.laser_yaw_rad))
    matcher = KeyframeScanMatcher(settings)
    angles = run.scan_angles
    truth = run.truth_at(run.scan_t)
    estimates = np.zeros((len(run.scan_t), 3))
    statuses: dict[str, int] = {}
    for k, (stamp, ranges) in enumerate(zip(run.scan_t, run.scan_ranges)):
        points, _ = scan_to_points(ranges, angles, run.scan_range_min, run.scan_range_max)
        step = matcher.process(int(stamp), points)
        estimates[k] = step.pose
        statuses[step.status] = statuses.get(step.status, 0) + 1
    reference = np.array([between(tuple(truth[0]), tuple(p)) for p in truth])
    position_error = np.hypot(*(estimates[:, :2] - reference[:, :2]).T)
    path = float(np.hypot(*np.diff(truth[:, :2], axis=0).T).sum())
    return {
        'path_length_m': path,
        'final_position_error_m': float(position_error[-1]),
        'max_position_error_m': float(position_error.max()),
        'final_drift_fraction': float(position_error[-1] / path),
        'final_heading_error_deg': float(np.degrees(abs(wrap_angle(estimates[-1, 2]
                                                                   - reference[-1, 2])))),
        'scans': int(len(run.scan_t)),
        **{f'steps_{k}': v for k, v in sorted(statuses.items())},
    }


def run(quick: bool = False) -> dict:
    """Figures for the benchmark aggregator."""
    return route_drift(laps=1.0)


if __name__ == '__main__':
    print(json.dumps(run(), indent=1))
