"""The scan matchers the ICP benchmark compares, one section each: ours (core.icp.match, and the
node's streaming matcher), the textbook ICP, small_gicp and KISS-ICP. A pair matcher maps
(source, target, guess) to the source's pose in the target frame (x m, y m, yaw rad); a streaming
estimator runs over a dataset's ScanInputs and returns (stamps ns, base_link poses, CPU ms per
scan)."""

from __future__ import annotations

import math
import time
from typing import Callable

import numpy as np
from numpy.typing import NDArray

from sensing_nodes.bench.icp.datasets import ScanInput
from sensing_nodes.core import icp
from sensing_nodes.core.geometry.se2 import Pose2, compose, inverse, rotation
from sensing_nodes.core.scan_matching import (
    ScanMatcherSettings,
    deskewed_by_odometry,
    make_scan_matcher,
)

Matcher = Callable[[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]], Pose2]
Estimate = tuple[NDArray[np.int64], NDArray[np.float64], float]


def pose_matrix(pose: Pose2) -> NDArray[np.float64]:
    """A planar pose as a 4x4 homogeneous transform."""
    m = np.eye(4)
    m[:2, :2] = rotation(pose[2])
    m[:2, 3] = pose[:2]
    return m


def planar(matrix: NDArray[np.float64]) -> Pose2:
    """A 4x4 homogeneous transform projected to the plane as (x, y, yaw)."""
    return float(matrix[0, 3]), float(matrix[1, 3]), math.atan2(matrix[1, 0], matrix[0, 0])


# --- ours -------------------------------------------------------------------------------------

# Our matcher's settings for real keyframe pairs (about 1 m and 10-20 deg apart): a coarse match
# from the guess and from four yaw offsets (+-14, +-29 deg), the best-scoring one refined.
OURS_OPTIONS: dict = {'yaw_hypotheses': (-0.5, -0.25, 0.25, 0.5)}
_TARGET_KEYS = {'normal_neighbours', 'normal_radius', 'min_planarity', 'tangent_weight', 'search'}


def ours(options: dict | None = None) -> Matcher:
    """core.icp.match with the given options (over OURS_OPTIONS), as a pair matcher."""
    opts = {**OURS_OPTIONS, **(options or {})}
    target_opts = {k: opts.pop(k) for k in list(opts) if k in _TARGET_KEYS}

    def run(source, target, guess):
        r = icp.match(source, icp.prepare_target(target, **target_opts), guess, **opts)
        return (r.x, r.y, r.yaw)
    return run


def run_local_map(inputs: list[ScanInput], settings: ScanMatcherSettings) -> Estimate:
    """The package's matcher (settings.mode) over the inputs: published stamps, base_link poses
    (odom frame) and CPU ms per scan of process()."""
    matcher = make_scan_matcher(settings)
    stamps, poses, spent = [], [], 0.0
    for args in inputs:
        start = time.process_time()
        step = matcher.process(*args)
        spent += time.process_time() - start
        if step.publish:
            stamps.append(args[0])
            poses.append(step.pose)
    return (np.array(stamps, dtype=np.int64), np.array(poses).reshape(-1, 3),
            1e3 * spent / max(len(inputs), 1))


def local_map_ms(settings: ScanMatcherSettings, inputs: list[ScanInput], repeats: int = 1
                 ) -> float:
    """CPU ms per scan of the package's matcher over the inputs, best of `repeats` passes."""
    return min(run_local_map(inputs, settings)[2] for _ in range(repeats))


# --- the textbook ICP -------------------------------------------------------------------------

def textbook_icp_loops(source, target, initial=(0.0, 0.0, 0.0), iterations: int = 20):
    """The textbook ICP: brute-force nearest neighbour written as loops over the points, the
    closed-form SVD step, a fixed number of iterations. Returns (x, y, yaw)."""
    target_list = [tuple(q) for q in np.asarray(target, dtype=float)]

    def nearest(moved, _):
        pairs = []
        for px, py in moved:
            best, best_d = None, math.inf
            for qx, qy in target_list:
                d = (px - qx) ** 2 + (py - qy) ** 2
                if d < best_d:
                    best, best_d = (qx, qy), d
            pairs.append(best)
        return np.array(pairs)
    return _textbook(nearest, source, target, initial, iterations)


def textbook_icp_numpy(source, target, initial=(0.0, 0.0, 0.0), iterations: int = 20):
    """The same textbook ICP with the brute-force search vectorised (full distance matrix)."""
    def nearest(moved, target):
        return target[((moved[:, None, :] - target[None, :, :]) ** 2).sum(axis=2).argmin(axis=1)]
    return _textbook(nearest, source, target, initial, iterations)


def _textbook(nearest, source, target, initial, iterations):
    """Fixed iterations of: pair each moved source point with nearest(moved, target), align."""
    r = rotation(initial[2])
    t = np.array(initial[:2], dtype=float)
    target = np.asarray(target, dtype=float)
    for _ in range(iterations):
        moved = np.asarray(source) @ r.T + t
        r_step, t_step = icp.align_paired(moved, nearest(moved, target))
        r, t = r_step @ r, r_step @ t + t_step
    return float(t[0]), float(t[1]), math.atan2(r[1, 0], r[0, 0])


# --- small_gicp -------------------------------------------------------------------------------

# small_gicp settings: the best of a grid tried on the CARMEN logs (docs/nodes/icp_matcher.md).
SMALL_GICP_OPTIONS = {
    'downsampling_resolution': 0.05,
    'max_correspondence_distance': 1.0,
    'max_iterations': 50,
    'heights_m': (-0.1, 0.0, 0.1),
    'num_neighbors': 10,
}
SMALL_GICP_TYPES = {'small_gicp_icp': 'ICP', 'small_gicp_plane_icp': 'PLANE_ICP',
                    'small_gicp_gicp': 'GICP'}


def lift(points: NDArray[np.float64], heights: tuple[float, ...]) -> NDArray[np.float64]:
    """2-D points copied at each height as (N·H, 3), so 3-D normals and covariances exist."""
    return np.vstack([np.column_stack((points, np.full(len(points), h))) for h in heights])


class SmallGicp:
    """small_gicp on lifted 2-D scans, single-threaded: prepare() a scan (downsampling, normals
    or covariances, k-d tree), align() a prepared source to a prepared target from a guess."""

    def __init__(self, registration_type: str, options: dict | None = None) -> None:
        import small_gicp

        self.small_gicp = small_gicp
        self.registration_type = registration_type
        self.options = {**SMALL_GICP_OPTIONS, **(options or {})}
        self.heights = tuple(self.options.pop('heights_m'))
        self.neighbours = int(self.options.pop('num_neighbors'))
        self.resolution = float(self.options.pop('downsampling_resolution'))

    def prepare(self, scan: NDArray[np.float64]) -> tuple:
        return self.small_gicp.preprocess_points(lift(scan, self.heights), self.resolution,
                                                 num_neighbors=self.neighbours, num_threads=1)

    def align(self, target: tuple, source: tuple, guess) -> Pose2:
        result = self.small_gicp.align(target[0], source[0], target[1], pose_matrix(guess),
                                       registration_type=self.registration_type,
                                       num_threads=1, **self.options)
        return planar(result.T_target_source)


def small_gicp_matcher(registration_type: str, options: dict | None = None) -> Matcher:
    """small_gicp.align on lifted points as a pair matcher, preparing both scans each call."""
    method = SmallGicp(registration_type, options)
    return lambda source, target, guess: method.align(method.prepare(target),
                                                      method.prepare(source), guess)


def pair_matchers(include_small_gicp: bool = True) -> dict[str, Matcher]:
    """The pair methods compared: ours, ours without yaw hypotheses (the node's setting) with
    neighbours from the scans' bearing order (the default) and from a k-d tree (the same
    neighbours: a check), and small_gicp's ICP, plane-ICP and GICP."""
    out = {'ours': ours(), 'ours_local': ours({'yaw_hypotheses': ()}),
           'ours_local_kd_tree': ours({'yaw_hypotheses': (), 'search': 'kd_tree'})}
    if include_small_gicp:
        out.update({name: small_gicp_matcher(kind) for name, kind in SMALL_GICP_TYPES.items()})
    return out


# --- KISS-ICP ---------------------------------------------------------------------------------

KISS_VOXELS_M = (0.25, 0.5)
KISS_RANGE_M = (0.05, 40.0)


def run_kiss(inputs: list[ScanInput], voxel_m: float, laser_pose: Pose2 = (0.0, 0.0, 0.0)
             ) -> Estimate:
    """KISS-ICP over the inputs, each scan planar 3-D points (z = 0) deskewed to its stamp by
    the odometry's sweep motion, its own deskewing off, one thread, its voxel map at voxel_m and,
    before each scan, last_delta set to the odometry's increment in the laser's frame (kept as
    its own when there is none): stamps, base_link poses (its first laser pose's frame) and CPU
    ms per register_frame."""
    from kiss_icp.config import KISSConfig
    from kiss_icp.kiss_icp import KissICP

    config = KISSConfig()
    config.data.min_range, config.data.max_range = KISS_RANGE_M
    config.data.deskew = False
    config.mapping.voxel_size = voxel_m
    config.registration.max_num_threads = 1
    odometry = KissICP(config)
    mount, unmount = pose_matrix(laser_pose), pose_matrix(inverse(laser_pose))
    stamps, poses, spent = [], [], 0.0
    previous = None
    for stamp, points, predicted, times, sweep in inputs:
        if previous is not None and stamp == previous:
            continue                                     # a repeated stamp: skipped
        points = deskewed_by_odometry(points, times, sweep, laser_pose)
        frame = np.column_stack((points, np.zeros(len(points))))
        if predicted is not None:
            odometry.last_delta = unmount @ pose_matrix(predicted) @ mount
        start = time.process_time()
        odometry.register_frame(frame, np.zeros(len(frame)))
        spent += time.process_time() - start
        stamps.append(stamp)
        poses.append(planar(odometry.last_pose @ unmount))
        previous = stamp
    # Its world is the first laser pose: base_link's first pose made the origin, as ours.
    poses = [compose(laser_pose, p) for p in poses]
    return (np.array(stamps, dtype=np.int64), np.array(poses).reshape(-1, 3),
            1e3 * spent / max(len(stamps), 1))


def estimators(inputs: list[ScanInput], settings: ScanMatcherSettings,
               voxels: tuple[float, ...] = KISS_VOXELS_M) -> dict[str, Estimate]:
    """name -> (stamps, poses, ms per scan) of the local map and of KISS-ICP at each voxel."""
    out = {'local_map': run_local_map(inputs, settings)}
    for voxel in voxels:
        out[f'kiss_icp_{voxel:g}'] = run_kiss(inputs, voxel, settings.laser_pose)
    return out


ESTIMATORS = ('local_map', *(f'kiss_icp_{v:g}' for v in KISS_VOXELS_M))
