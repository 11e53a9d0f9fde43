"""The ICP benchmark's datasets, each read one way: simulated runs (the default route, the open
worlds, the fast LiDAR), consecutive CARMEN scan pairs with the logs' corrected poses as the
reference, and CARMEN logs or ROS bags as a matcher's inputs (scans with the odometry's guess)."""

from __future__ import annotations

import dataclasses
import math
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from sensing_nodes.bags.carmen import read_carmen
from sensing_nodes.core.geometry.scan import scan_to_points
from sensing_nodes.core.geometry.se2 import Pose2, between
from sensing_nodes.core.icp import Correspondences, IcpOptions
from sensing_nodes.core.scan_matching import (
    OdometryBuffer,
    ScanMatcherSettings,
    odometry_guidance,
)
from sensing_nodes.core.sim.simulator import SimParams, SimRun, make_route, simulate
from sensing_nodes.core.sim.world import load_world
from sensing_nodes.paths import config_file

DATASETS = ('sim', 'hall', 'outdoor', 'fast_lidar', 'carmen-pairs', 'carmen-logs')

# One scan as a matcher is given it: stamp (ns), points (N, 2, laser frame, m), base_link's
# odometry motion since the previous scan (None: none), beam times (s) and the sweep's motion.
ScanInput = tuple[int, NDArray[np.float64], Pose2 | None, NDArray[np.float64] | None,
                  Pose2 | None]


def shared_dir(name: str, repo: str | Path | None = None) -> Path:
    """A shared dataset folder ('carmen', 'ros'), located as <repo>/../shared/datasets/<name>."""
    root = Path(repo) if repo is not None else Path(__file__).resolve().parents[3]
    return (root / '..' / 'shared' / 'datasets' / name).resolve()


# --- simulated runs ---------------------------------------------------------------------------

# The default route with every turn in place at 1 rad/s (57.3 deg/s): the deskewing benchmark.
FAST_TURNS_ROUTE = ('wait 6', 'straight 2.0 0.25', 'turn 90 57.2958', 'straight 2.0 0.25',
                    'turn 180 57.2958', 'wait 2', 'turn -360 57.2958', 'straight 2.0 0.25',
                    'turn 90 57.2958', 'wait 3')
# A Hokuyo UTM-30LX class scanner on the simulated robot.
FAST_LIDAR = {'scan_rate_hz': 40.0, 'scan_beams': 1081, 'scan_fov_rad': math.radians(270.0),
              'range_max_m': 30.0}


def simulated_run(seed: int = 0, laps: float = 1.0, params: SimParams | None = None) -> SimRun:
    """`laps` of the route of params (default: the default route) in the default world."""
    params = params or SimParams()
    return simulate(params, load_world(config_file('default_world.yaml')),
                    laps * make_route(params).period_s, seed)


def _loop(long_m: float, short_m: float, speed_m_s: float) -> tuple[str, ...]:
    """A rectangular loop to the left at speed_m_s, turning in place at 45 deg/s."""
    leg = ('straight {} %g' % speed_m_s, 'turn 90 45')
    return ('wait 2', *(part.format(length) for length in (long_m, short_m, long_m, short_m)
                        for part in leg), 'wait 1')


# Open spaces (docs/nodes/icp_matcher.md): a world file and the simulated robot's parameters
# there, a 40 m laser (360 beams, 1 deg apart, as the default) driving a loop at 1 m/s.
WORLDS = {
    # An 80 m x 50 m hall, walls 20-45 m from a 12 m x 8 m loop, pillars and booths.
    'hall': ('hall_world.yaml', {'start_x_m': -6.0, 'start_y_m': -4.0,
                                 'route': _loop(12.0, 8.0, 1.0), 'range_max_m': 40.0}),
    # Sparse posts, bushes and two building fronts around a 20 m x 12 m loop, 3 cm range noise.
    'outdoor': ('outdoor_world.yaml', {'start_x_m': -10.0, 'start_y_m': -6.0,
                                       'route': _loop(20.0, 12.0, 1.0), 'range_max_m': 40.0,
                                       'range_noise_std_m': 0.03}),
}
# The corridor world, 30 m along it at 0.5 m/s.
CORRIDOR = ('corridor_world.yaml', {'start_x_m': -20.0, 'start_y_m': 0.0,
                                    'route': ('wait 3', 'straight 30 0.5', 'wait 2')})


def world_run(world: str, seed: int = 0) -> SimRun:
    """One run of the route of a WORLDS scenario or of the corridor ('corridor')."""
    name, overrides = CORRIDOR if world == 'corridor' else WORLDS[world]
    params = dataclasses.replace(SimParams(), **overrides)
    return simulate(params, load_world(config_file(name)), make_route(params).period_s, seed)


# --- CARMEN scan pairs ------------------------------------------------------------------------

# Range reported for "no return" in each log (see the dataset README); ranges at or above it are
# invalid, not walls 50 m away.
NO_RETURN_M = {'aces': 50.0, 'freiburg-101': 81.91}
PAIR_LOGS = ('aces', 'freiburg-101')
GUESS_SIGMA_M = 0.10
GUESS_SIGMA_RAD = math.radians(5.0)
REGIMES = ('identity', 'perturbed')


@dataclass
class ScanPair:
    """Source = scan k+1, target = scan k, as (N, 2) laser-frame points (m); reference pose of
    the source in the target frame (m, rad)."""

    source: NDArray[np.float64]
    target: NDArray[np.float64]
    reference: Pose2


def scan_pairs(name: str, directory: Path | None = None, stride: int = 1) -> list[ScanPair]:
    """Consecutive pairs (k, k+1) of a log's FLASER scans, every `stride`-th pair; reference =
    between(pose_k, pose_k+1) of the log's corrected laser poses."""
    log = read_carmen((directory or shared_dir('carmen')) / f'{name}-corrected.log.gz')
    no_return_m = NO_RETURN_M[name]
    points, poses = [], []
    for scan in log.scans:
        ranges = np.where(scan.ranges >= no_return_m, np.inf, scan.ranges)
        points.append(scan_to_points(ranges, log.scan_angles(scan.ranges.size), 0.01,
                                     no_return_m)[0])
        poses.append(scan.pose)
    return [ScanPair(points[k + 1], points[k], between(poses[k], poses[k + 1]))
            for k in range(0, len(points) - 1, stride)]


def initial_guesses(pairs: list[ScanPair], regime: str, seed: int = 0) -> NDArray[np.float64]:
    """(P, 3) initial guesses: zeros, or each reference plus seeded Gaussian noise (sigma
    0.10 m per axis, 5 deg), as odometry would give."""
    if regime == 'identity':
        return np.zeros((len(pairs), 3))
    rng = np.random.default_rng(seed)
    reference = np.array([p.reference for p in pairs])
    noise = rng.normal(size=(len(pairs), 3)) * (GUESS_SIGMA_M, GUESS_SIGMA_M, GUESS_SIGMA_RAD)
    return reference + noise


# --- CARMEN logs and ROS bags as a matcher's inputs -------------------------------------------

CARMEN_LOGS = ('aces', 'freiburg-101', 'seattle', 'edmonton', 'fhw', 'acapulco',
               'freiburg-campus')
# icp_matcher on the logs (docs/real-data.md's sensing_pipeline command, config/icp_matcher.yaml):
# the laser at base_link, 60 s gaps (the logs' keyframes are 0.5 to 38 s apart), the odometry
# extrapolated up to 1 s.
CARMEN_MAX_GAP_S = 60.0
CARMEN_EXTRAPOLATION_S = 1.0
CARMEN_SETTINGS = ScanMatcherSettings(
    laser_pose=(0.0, 0.0, 0.0), max_gap_s=CARMEN_MAX_GAP_S,
    icp_options=IcpOptions(correspondences=Correspondences(min_inlier_fraction=0.3,
                                                           min_points=20)))
# The shared real Hokuyo bag (../shared/datasets/ros/README.md): laser_scan_matcher's demo.
HOKUYO_DEMO = 'scan_tools-laser_scan_matcher-demo.bag'


NOT_CONVERTED = {'error': 'carmen_to_bag could not convert it'}


def carmen_bag(name: str, out: Path) -> Path | None:
    """A shared CARMEN log converted by carmen_to_bag to out/<name> (None: it cannot be)."""
    from sensing_nodes.tools import carmen_to_bag

    bag = out / name
    shutil.rmtree(bag, ignore_errors=True)
    log = shared_dir('carmen') / f'{name}-corrected.log.gz'
    return bag if carmen_to_bag.main([str(log), str(bag)]) == 0 else None


def bag_messages(bag: Path) -> list[tuple[str, object]]:
    """(topic, message) of a bag's /scan and /odom, in bag order."""
    from sensing_nodes.bags.storage import BagReader

    return [(topic, msg) for topic, _, msg in BagReader(bag).messages(['/scan', '/odom'])]


def bag_inputs(messages: list[tuple[str, object]],
               settings: ScanMatcherSettings = CARMEN_SETTINGS,
               extrapolation_s: float = CARMEN_EXTRAPOLATION_S) -> list[ScanInput]:
    """What icp_matcher's matcher is given for each /scan of bag_messages: the points, beam times
    from time_increment (None when 0), and the /odom odometry's guess (None without /odom)."""
    from sensing_nodes.ros.conversions import odometry_pose, scan_arrays, stamp_to_ns

    buffer = OdometryBuffer(max_age_s=max(10.0, 2.0 * settings.max_gap_s),
                            max_extrapolation_s=extrapolation_s)
    out: list[ScanInput] = []
    last = None
    for topic, msg in messages:
        stamp = stamp_to_ns(msg.header.stamp)
        if topic == '/odom':
            buffer.add(stamp, odometry_pose(msg)[0])
            continue
        ranges, angles = scan_arrays(msg)
        points, beams = scan_to_points(ranges, angles, msg.range_min, msg.range_max)
        times = beams * float(msg.time_increment) if msg.time_increment > 0.0 else None
        predicted, sweep = odometry_guidance(buffer, last, stamp, times)
        out.append((stamp, points, predicted, times, sweep))
        if last is None or stamp != last:
            last = stamp
    return out
