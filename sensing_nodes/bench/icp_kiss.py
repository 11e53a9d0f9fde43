"""KISS-ICP (PRBonn's scan-to-map odometry, pip `kiss-icp`) beside this package's local-map
matcher on the seven shared CARMEN logs, the simulated default route and the simulated hall
and outdoor worlds (bench/icp_sim.WORLDS), in one run:

    python -m sensing_nodes.bench.icp_kiss OUT_DIR [--logs aces,...] [--seeds 2] [--json F]

Both get the same scans and, before each scan, the same odometry increment since the previous
scan as their guess (OdometryBuffer and odometry_guidance, as icp_matcher builds them; for
KISS-ICP its `last_delta`, moved into the laser's frame). KISS-ICP sees each scan as planar 3-D
points (z = 0), ranges 0.05-40 m, deskewing off (CARMEN scans are instantaneous; the simulated
sweeps are deskewed to the stamp by the odometry's motion before either gets them), one thread,
its voxel map at 0.25 m and 0.5 m. The logs are converted by icp_carmen's carmen_to_bag step;
ATE (after a rigid alignment, at the reference's stamps) and the RPE between consecutive scans
are core.evaluation.metrics', as sensing_eval scores them; ms per scan is CPU time of the
register call alone. The local map's rows equal `icp_carmen`'s /scan_match/odom rows (the same
settings as its sensing_pipeline command).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from sensing_nodes.core.evaluation.metrics import (
    absolute_trajectory_error,
    relations_from_trajectory,
    relative_pose_errors,
)
from sensing_nodes.core.geometry.se2 import Pose2, compose, inverse
from sensing_nodes.core.icp import Correspondences, IcpOptions
from sensing_nodes.core.scan_matching import (
    OdometryBuffer,
    ScanMatcherSettings,
    deskewed_by_odometry,
    make_scan_matcher,
    odometry_guidance,
)

VOXELS_M = (0.25, 0.5)
RANGE_M = (0.05, 40.0)
ZERO: Pose2 = (0.0, 0.0, 0.0)
# icp_matcher as icp_carmen's sensing_pipeline command sets it (config/icp_matcher.yaml, laser
# at base_link, 60 s gaps, odometry extrapolated up to 1 s).
CARMEN_SETTINGS = ScanMatcherSettings(
    laser_pose=ZERO, max_gap_s=60.0,
    icp_options=IcpOptions(correspondences=Correspondences(min_inlier_fraction=0.3,
                                                           min_points=20)))
CARMEN_EXTRAPOLATION_S = 1.0

# One scan as a matcher is given it: stamp (ns), points (N, 2, laser frame, m), base_link's
# odometry motion since the previous scan (None: none), beam times (s) and the sweep's motion.
ScanInput = tuple[int, NDArray[np.float64], Pose2 | None, NDArray[np.float64] | None,
                  Pose2 | None]


def bag_inputs(bag: Path, settings: ScanMatcherSettings = CARMEN_SETTINGS,
               extrapolation_s: float = CARMEN_EXTRAPOLATION_S) -> list[ScanInput]:
    """What icp_matcher's matcher is given for each /scan of a bag with /odom, in bag order."""
    from sensing_nodes.bags.storage import BagReader
    from sensing_nodes.core.geometry.scan import scan_to_points
    from sensing_nodes.ros.conversions import odometry_pose, scan_arrays, stamp_to_ns

    buffer = OdometryBuffer(max_age_s=max(10.0, 2.0 * settings.max_gap_s),
                            max_extrapolation_s=extrapolation_s)
    out: list[ScanInput] = []
    last = None
    for topic, _, msg in BagReader(bag).messages(['/scan', '/odom']):
        stamp = stamp_to_ns(msg.header.stamp)
        if topic == '/odom':
            buffer.add(stamp, odometry_pose(msg)[0])
            continue
        ranges, angles = scan_arrays(msg)
        points, _ = scan_to_points(ranges, angles, msg.range_min, msg.range_max)
        predicted, _ = odometry_guidance(buffer, last, stamp, None)
        out.append((stamp, points, predicted, None, None))
        if last is None or stamp != last:
            last = stamp
    return out


def run_local_map(inputs: list[ScanInput], settings: ScanMatcherSettings
                  ) -> tuple[NDArray[np.int64], NDArray[np.float64], float]:
    """The package's matcher over the inputs: published stamps, base_link poses (odom frame)
    and CPU ms per scan of process()."""
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


def _matrix(pose: Pose2) -> NDArray[np.float64]:
    """A planar pose as a 4x4 homogeneous transform."""
    c, s = math.cos(pose[2]), math.sin(pose[2])
    m = np.eye(4)
    m[:2, :2] = ((c, -s), (s, c))
    m[:2, 3] = pose[:2]
    return m


def _planar(matrix: NDArray[np.float64]) -> Pose2:
    return float(matrix[0, 3]), float(matrix[1, 3]), math.atan2(matrix[1, 0], matrix[0, 0])


def run_kiss(inputs: list[ScanInput], voxel_m: float, laser_pose: Pose2 = ZERO
             ) -> tuple[NDArray[np.int64], NDArray[np.float64], float]:
    """KISS-ICP over the inputs with its voxel map at voxel_m and, before each scan, last_delta
    set to the odometry's increment in the laser's frame (kept as its own when there is none):
    stamps, base_link poses (its first laser pose's frame) and CPU ms per register_frame."""
    from kiss_icp.config import KISSConfig
    from kiss_icp.kiss_icp import KissICP

    config = KISSConfig()
    config.data.min_range, config.data.max_range = RANGE_M
    config.data.deskew = False
    config.mapping.voxel_size = voxel_m
    config.registration.max_num_threads = 1
    odometry = KissICP(config)
    mount, unmount = _matrix(laser_pose), _matrix(inverse(laser_pose))
    stamps, poses, spent = [], [], 0.0
    previous = None
    for stamp, points, predicted, times, sweep in inputs:
        if previous is not None and stamp == previous:
            continue                                     # a repeated stamp: skipped
        points = deskewed_by_odometry(points, times, sweep, laser_pose)
        frame = np.column_stack((points, np.zeros(len(points))))
        if predicted is not None:
            odometry.last_delta = unmount @ _matrix(predicted) @ mount
        start = time.process_time()
        odometry.register_frame(frame, np.zeros(len(frame)))
        spent += time.process_time() - start
        stamps.append(stamp)
        poses.append(_planar(odometry.last_pose @ unmount))
        previous = stamp
    # Its world is the first laser pose: base_link's first pose made the origin, as ours.
    poses = [compose(laser_pose, p) for p in poses]
    return (np.array(stamps, dtype=np.int64), np.array(poses).reshape(-1, 3),
            1e3 * spent / max(len(stamps), 1))


def scores(reference_t: NDArray[np.int64], reference_poses: NDArray[np.float64],
           relation_t: NDArray[np.int64], relation_poses: NDArray[np.float64],
           t: NDArray[np.int64], poses: NDArray[np.float64]) -> dict:
    """ATE (m) against the reference trajectory and the mean RPE (m, deg) between consecutive
    relation samples (the scans' reference poses), as sensing_eval scores them."""
    errors = relative_pose_errors(relations_from_trajectory(relation_t, relation_poses), t,
                                  poses)
    summary = errors.summary()
    return {'ate_rmse_m': absolute_trajectory_error(reference_t, reference_poses, t,
                                                    poses)['ate_rmse_m'],
            'rpe_translation_mean_m': summary['rpe_translation_mean_m'],
            'rpe_rotation_mean_deg': summary['rpe_rotation_mean_deg'],
            'relations': summary['relations']}


def estimators(inputs: list[ScanInput], settings: ScanMatcherSettings,
               voxels: tuple[float, ...] = VOXELS_M) -> dict[str, tuple]:
    """name -> (stamps, poses, ms per scan) of the local map and of KISS-ICP at each voxel."""
    out = {'local_map': run_local_map(inputs, settings)}
    for voxel in voxels:
        out[f'kiss_icp_{voxel:g}'] = run_kiss(inputs, voxel, settings.laser_pose)
    return out


def log_figures(name: str, out: Path, settings: ScanMatcherSettings = CARMEN_SETTINGS) -> dict:
    """{estimator: figures} of one CARMEN log (converted as icp_carmen converts it), or
    {'error': why}."""
    import shutil

    from sensing_nodes.bench.icp_real import carmen_dir
    from sensing_nodes.tools import carmen_to_bag
    from sensing_nodes.tools.eval import load_trajectories

    bag = out / name
    shutil.rmtree(bag, ignore_errors=True)
    if carmen_to_bag.main([str(carmen_dir() / f'{name}-corrected.log.gz'), str(bag)]) != 0:
        return {'error': 'carmen_to_bag could not convert it'}
    tracks = load_trajectories(bag, ['/ground_truth/odom', '/odom'])
    ref_t, ref_poses = tracks['/ground_truth/odom']
    inputs = bag_inputs(bag, settings)
    figures = {'odometry': scores(ref_t, ref_poses, ref_t, ref_poses, *tracks['/odom'])}
    for estimator, (t, poses, ms) in estimators(inputs, settings).items():
        figures[estimator] = scores(ref_t, ref_poses, ref_t, ref_poses, t, poses) | {
            'ms_per_scan': ms}
    figures['scans'] = len(inputs)
    return figures


def sim_figures(seeds: int = 2, world: str = '') -> dict:
    """{estimator: figures} on the simulated default route (one lap, the wheel odometry's
    guess), or one loop of an open-space world (icp_sim.WORLDS), pooled over seeds: ATE and
    heading RMS as RMS over seeds, RPE and ms as means."""
    from sensing_nodes.bench.icp_sim import simulated_run, world_run
    from sensing_nodes.core.evaluation.fusion import track_errors
    from sensing_nodes.core.sim.inputs import matcher_settings, scan_inputs

    rows: dict[str, list[dict]] = {}
    for seed in range(seeds):
        run = world_run(world, seed) if world else simulated_run(seed)
        inputs = scan_inputs(run)
        scan_t = np.array([i[0] for i in inputs], dtype=np.int64)
        truth = run.truth_at(scan_t)
        for estimator, (t, poses, ms) in estimators(inputs,
                                                    matcher_settings(run.params)).items():
            row = scores(run.truth_t, run.truth_pose, scan_t, truth, t, poses)
            row['rms_heading_deg'] = track_errors(run.truth_t, run.truth_pose, t,
                                                  poses)['rms_heading_deg']
            rows.setdefault(estimator, []).append(row | {'ms_per_scan': ms})
    out: dict = {}
    for estimator, per_seed in rows.items():
        out[estimator] = {
            key: (math.sqrt(float(np.mean([r[key] ** 2 for r in per_seed])))
                  if key in ('ate_rmse_m', 'rms_heading_deg')
                  else float(np.mean([r[key] for r in per_seed])))
            for key in per_seed[0]}
    out['seeds'] = seeds
    return out


ESTIMATORS = ('local_map', *(f'kiss_icp_{v:g}' for v in VOXELS_M))


def table(results: dict) -> str:
    """One row per log: ATE, consecutive RPE mean and ms per scan of each estimator."""
    head = ' | '.join(f'{e} ATE (m) | {e} RPE (m / deg) | {e} ms' for e in ESTIMATORS)
    lines = [f'| log | odometry ATE (m) | {head} |',
             '|---|---|' + '---|---|---|' * len(ESTIMATORS)]
    for log, figures in results.items():
        if 'error' in figures:
            lines.append(f"| {log} | cannot be scored: {figures['error']} |")
            continue
        odometry = figures.get('odometry', {}).get('ate_rmse_m')
        cells = [f'{odometry:.3f}' if odometry is not None else '']
        for e in ESTIMATORS:
            f = figures[e]
            cells += [f"{f['ate_rmse_m']:.3f}",
                      f"{f['rpe_translation_mean_m']:.4f} / {f['rpe_rotation_mean_deg']:.3f}",
                      f"{f['ms_per_scan']:.2f}"]
        lines.append(f"| {log} | {' | '.join(cells)} |")
    return '\n'.join(lines)


def main(argv: list[str] | None = None) -> int:
    from sensing_nodes.bench.icp_carmen import LOGS
    from sensing_nodes.bench.icp_sim import WORLDS

    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('out', type=Path, help='folder for the converted bags')
    parser.add_argument('--logs', default=','.join(LOGS))
    parser.add_argument('--seeds', type=int, default=2,
                        help='simulated route seeds (0: no simulated row)')
    parser.add_argument('--json', type=Path, help='also write every figure here')
    args = parser.parse_args(argv)
    try:
        import kiss_icp  # noqa: F401
    except ImportError:
        print('kiss-icp is not installed (pip install -r requirements.txt)', file=sys.stderr)
        return 1
    args.out.mkdir(parents=True, exist_ok=True)
    results = {}
    for name in (n for n in args.logs.split(',') if n):
        results[name] = log_figures(name, args.out)
        print(f'{name}: done', file=sys.stderr, flush=True)
    if args.seeds > 0:
        results[f'simulated route ({args.seeds} seeds)'] = sim_figures(args.seeds)
        for world in WORLDS:
            results[f'simulated {world} ({args.seeds} seeds)'] = sim_figures(args.seeds, world)
    print(table(results))
    if args.json:
        args.json.write_text(json.dumps(results, indent=1))
    return 0


def run(quick: bool = False) -> dict:
    """Figures for the benchmark aggregator (ACES, Freiburg 101 and one seed when quick)."""
    import tempfile

    from sensing_nodes.bench.icp_carmen import LOGS
    from sensing_nodes.bench.icp_sim import WORLDS

    with tempfile.TemporaryDirectory() as out:
        results = {name: log_figures(name, Path(out)) for name in (LOGS[:2] if quick else LOGS)}
    results['sim'] = sim_figures(1 if quick else 2)
    for world in WORLDS:
        results[f'sim_{world}'] = sim_figures(1 if quick else 2, world)
    flat: dict = {}
    for name, figures in results.items():
        if 'error' in figures:
            flat[f'{name}.error'] = figures['error']
            continue
        for estimator, f in figures.items():
            if isinstance(f, dict):
                for key, value in f.items():
                    if key != 'relations':
                        flat[f'{name}.{estimator}.{key}'] = value
    return flat


if __name__ == '__main__':
    sys.exit(main())
