"""sensing_characterize: each sensor's error model from a bag, in the lesson's vocabulary.

    sensing_characterize BAG [--png DIR]

IMU: Allan deviation per gyro and accelerometer axis of a still recording, with the white-noise
density N, bias instability B and rate random walk K, and the gyro_integrator parameters they
give. LiDAR: range bias and noise against the ray-cast truth when the bag has /ground_truth/odom
(simulated bags; --world), else noise against the lines line_extractor fits. Encoders: the
quantisation step and counts per revolution. Exit 0 when something was characterised, 2 on bad
input (no sensor, an IMU with a gap, NaN); plots are written whole or not at all.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

from sensing_nodes.bags.sensor_streams import (
    EXIT_BAD_INPUT,
    SensorBagError,
    SensorData,
    atomic_write,
    describe_topics,
    read_sensor_bag,
    stderr_progress,
)
from sensing_nodes.core.evaluation import characterization as ch
from sensing_nodes.core.lines import extract_lines
from sensing_nodes.paths import config_file

PROG = 'sensing_characterize'
AXES = ('x', 'y', 'z')
# A still IMU: 1 s means of the gyro within this (rad/s) and of |accel| within this (m/s^2).
STILL_GYRO_RAD_S = 0.02
STILL_ACCEL_M_S2 = 0.1
# The ray-cast truth is used only when this share of the beams lands within 0.2 m of it.
MIN_WORLD_AGREEMENT = 0.8


def _plot_allan(results: dict, rate: float, path: Path, title: str) -> None:
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(13, 5.5))
    for ax, sensor, unit, dens in ((axes[0], 'gyro', 'rad/s', 'rad/s/√Hz'),
                                   (axes[1], 'accel', 'm/s²', 'm/s²/√Hz')):
        for axis, colour in zip(AXES, ('tab:red', 'tab:green', 'tab:blue')):
            ad, terms, bound = results[(sensor, axis)]
            ax.loglog(ad.tau, ad.adev, 'o-', ms=3, color=colour, label=f'{sensor} {axis}')
            tau = ad.tau
            if bound is not None:
                ax.loglog(tau, bound / np.sqrt(tau), '--', color=colour, lw=0.8,
                          label=f'{axis}: N ≤ {bound:.3g} {dens} (bound from the shortest τ)')
            if terms.n is not None:
                ax.loglog(tau, terms.n / np.sqrt(tau), '--', color=colour, lw=0.8,
                          label=f'{axis}: N = {terms.n:.3g} {dens} (slope −1/2, τ = 1 s)')
            if terms.b is not None:
                ax.loglog(tau, np.full(tau.size, ch.FLICKER_FACTOR * terms.b), ':', color=colour,
                          lw=0.8, label=f'{axis}: B = {terms.b:.3g} {unit} (floor / 0.664)')
            if terms.k is not None:
                ax.loglog(tau, terms.k * np.sqrt(tau / 3.0), '-.', color=colour, lw=0.8,
                          label=f'{axis}: K = {terms.k:.3g} {unit}·√Hz (slope +1/2, τ = 3 s)')
        ax.axvline(1.0, color='grey', lw=0.5)
        ax.axvline(3.0, color='grey', lw=0.5)
        ax.set_xlabel('cluster time τ (s)')
        ax.set_ylabel(f'Allan deviation ({unit})')
        ax.set_title(f'{sensor}: overlapping Allan deviation, {rate:.0f} Hz')
        ax.grid(True, which='both', alpha=0.3)
        ax.legend(fontsize=7, loc='best')
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _imu_moving(data: SensorData, rate: float, duration: float, png_dir: Path | None,
                spans: tuple[float, float]) -> None:
    """A moving IMU: only upper bounds on N, from the shortest cluster time."""
    print(f'  NOT STILL: 1 s gyro means span {spans[0]:.3f} rad/s, accelerometer means span '
          f'{spans[1]:.2f} m/s^2 (still: <= {STILL_GYRO_RAD_S} rad/s, <= '
          f'{STILL_ACCEL_M_S2} m/s^2).')
    print('  The Allan deviation of a moving IMU measures the motion, not the sensor: B and K '
          'cannot be read, nor N itself. What it can show: at the shortest cluster time the '
          'motion changes little between samples, so adev(tau0) * sqrt(tau0) bounds N from '
          'above (tight when the motion is slow against the sample rate):')
    results = {}
    for sensor, values, unit in (('gyro', data.imu_gyro, 'rad/s/sqrt(Hz)'),
                                 ('accel', data.imu_accel, 'm/s^2/sqrt(Hz)')):
        for i, axis in enumerate(AXES):
            ad = ch.allan_deviation(values[:, i], rate, min_clusters=9)
            bound = float(ad.adev[0] * math.sqrt(ad.tau[0]))
            results[(sensor, axis)] = (ad, ch.NoiseTerms(None, None, None, ()), bound)
            print(f'    {sensor} {axis}: N <= {bound:.3g} {unit}')
    if png_dir is not None:
        path = png_dir / 'imu_allan.png'
        atomic_write(path, lambda p: _plot_allan(
            results, rate, p, f'{Path(data.path).name}: {data.imu_topic}, {duration:.0f} s, '
            'NOT STILL: the curves show the motion; only the N bounds are the sensor\'s'))
        print(f'  wrote {path}')


def _print_gyro_parameters(results: dict, rate: float) -> None:
    """gyro_integrator's noise parameters from the still recording's Allan fits."""
    gz = results[('gyro', 'z')][1]
    ax_terms = [results[('accel', a)][1].n for a in AXES]
    print('  gyro_integrator parameters (config/gyro_integrator.yaml units):')
    if gz.n is not None:
        print(f'    gyro_noise_density: {gz.n:.3g}          # rad/s/sqrt(Hz), N of gyro z')
        print(f'    gyro_std_threshold_rad_s: {3.0 * gz.n * math.sqrt(rate):.3g}   '
              '# 3x the per-sample std N*sqrt(rate)')
    if gz.k is not None:
        print(f'    bias_random_walk: {gz.k:.3g}            # rad/s/sqrt(s), K of gyro z')
    else:
        print('    bias_random_walk: not seen in this recording (keep the configured value)')
    if all(v is not None for v in ax_terms):
        print(f'    accel_std_threshold_m_s2: {3.0 * max(ax_terms) * math.sqrt(rate):.3g}   '
              '# 3x the largest per-sample accelerometer std')


def _imu_still(data: SensorData, rate: float, period: float, duration: float,
               png_dir: Path | None) -> None:
    """A still IMU: N, B and K per axis from the Allan deviation, and the node's parameters."""
    t, dt = data.imu_t, np.diff(data.imu_t) * 1e-9
    gaps = np.flatnonzero(dt > 5.0 * period)
    if gaps.size:
        raise SensorBagError(f'{data.imu_topic}: the still recording has {gaps.size} gap(s), the '
                             f'first {dt[gaps[0]]:.3f} s long at {t[gaps[0]] * 1e-9:.3f} s; the '
                             'Allan deviation needs one unbroken, evenly sampled recording')
    irregular = float(np.std(dt) / period)
    if irregular > 0.1:
        print(f'  note: sample intervals vary by {100 * irregular:.0f} % (treated as even)')
    results = {}
    for sensor, values in (('gyro', data.imu_gyro), ('accel', data.imu_accel)):
        for i, axis in enumerate(AXES):
            ad = ch.allan_deviation(values[:, i], rate)
            results[(sensor, axis)] = (ad, ch.fit_noise_terms(ad), None)

    def show(v):
        return f'{v:12.4g}' if v is not None else '    not seen'

    print('  axis      N (/sqrt(Hz))   B            K (x sqrt(Hz))')
    for (sensor, axis), (_, terms, _) in results.items():
        print(f'  {sensor:5s} {axis}  {show(terms.n)}   {show(terms.b)}   {show(terms.k)}')
    for (sensor, axis), (_, terms, _) in results.items():
        for note in terms.notes:
            print(f'  {sensor} {axis}: {note}')
    _print_gyro_parameters(results, rate)
    if png_dir is not None:
        path = png_dir / 'imu_allan.png'
        atomic_write(path, lambda p: _plot_allan(results, rate, p,
                                                 f'{Path(data.path).name}: {data.imu_topic}, '
                                                 f'{duration:.0f} s still'))
        print(f'  wrote {path}')


def characterize_imu(data: SensorData, png_dir: Path | None) -> bool:
    """Print the IMU's Allan figures; True when they could be computed."""
    t, gyro, accel = data.imu_t, data.imu_gyro, data.imu_accel
    dt = np.diff(t) * 1e-9
    if dt.size < 100:
        print(f'IMU {data.imu_topic}: only {t.size} samples: no Allan deviation')
        return False
    period = float(np.median(dt))
    rate = 1.0 / period
    duration = (t[-1] - t[0]) * 1e-9
    print(f'IMU {data.imu_topic}: {t.size} samples, {rate:.1f} Hz, {duration:.1f} s')
    window = max(1, int(round(rate)))
    usable = (gyro.shape[0] // window) * window
    gyro_means = gyro[:usable].reshape(-1, window, 3).mean(axis=1)
    accel_means = accel[:usable].reshape(-1, window, 3).mean(axis=1)
    gyro_span = float(np.ptp(gyro_means, axis=0).max()) if gyro_means.shape[0] > 1 else 0.0
    accel_span = float(np.ptp(accel_means, axis=0).max()) if accel_means.shape[0] > 1 else 0.0
    if gyro_span <= STILL_GYRO_RAD_S and accel_span <= STILL_ACCEL_M_S2:
        _imu_still(data, rate, period, duration, png_dir)
    else:
        _imu_moving(data, rate, duration, png_dir, (gyro_span, accel_span))
    return True


def _truth_ranges(data: SensorData, world_file: Path, laser, every: int):
    """(measured, ray-cast true ranges) of every `every`-th scan, each beam cast from where the
    laser was when it was taken (a sweeping scanner: time_increment; else at the stamp)."""
    from sensing_nodes.core.sim.world import load_world, raycast

    world = load_world(world_file)
    scans = data.scans
    base = data.truth_t[0]
    tt = (data.truth_t - base).astype(float)
    yaw_u = np.unwrap(data.truth_pose[:, 2])
    offsets = scans.beam_times(np.arange(scans.angles.size))
    offsets = np.zeros(scans.angles.size) if offsets is None else offsets * 1e9
    measured, true = [], []
    for i in range(0, len(scans.t), every):
        ts = float(scans.t[i] - base) + offsets
        if ts[0] < tt[0] or ts[-1] > tt[-1]:
            continue
        x, y, yaw = (np.interp(ts, tt, c) for c in (data.truth_pose[:, 0], data.truth_pose[:, 1],
                                                      yaw_u))
        c, s = np.cos(yaw), np.sin(yaw)
        origins = np.column_stack((x + c * laser[0] - s * laser[1],
                                   y + s * laser[0] + c * laser[1]))
        true.append(raycast(world.segments, origins, yaw + laser[2] + scans.angles))
        measured.append(scans.ranges[i])
    return np.array(measured), np.array(true)


def _line_residuals(data: SensorData, every: int):
    scans = data.scans
    measured, fitted = [], []
    for i in range(0, len(scans.t), every):
        r = scans.ranges[i]
        for line in extract_lines(r, scans.angles, min_range=scans.range_min,
                                  max_range=scans.range_max):
            beams = (np.arange(line.first, line.last + 1) if line.first <= line.last else
                     np.concatenate((np.arange(line.first, r.size), np.arange(0, line.last + 1))))
            cos = np.cos(scans.angles[beams] - line.alpha)
            ok = np.isfinite(r[beams]) & (cos > 0.2)
            measured.append(r[beams][ok])
            fitted.append(line.r / cos[ok])
    if not measured:
        return np.zeros(0), np.zeros(0)
    return np.concatenate(measured), np.concatenate(fitted)


def _range_reference(data: SensorData, world_file: Path, laser, every: int):
    """(measured, reference ranges, what the reference is, whether it is the truth): the
    ray-cast truth when the bag has ground truth in this world, else the fitted lines."""
    if data.truth_t is not None:
        measured, true = _truth_ranges(data, world_file, laser, every)
        both = np.isfinite(measured) & np.isfinite(true)
        with np.errstate(invalid='ignore'):
            agree = float(np.mean(np.abs(measured[both] - true[both]) <= 0.2)) if both.any() \
                else 0.0
        if agree >= MIN_WORLD_AGREEMENT:
            return measured, true, \
                f'ray-cast truth ({world_file.name}, laser at {tuple(laser)})', True
        # /ground_truth/odom of a converted log (CARMEN's corrected poses) is not in the
        # world file's map: the ray cast would compare with the wrong walls.
        print(f'  the bag has {data.truth_t.size} ground-truth poses, but only '
              f'{100 * agree:.0f} % of the beams agree with {world_file.name} within 0.2 m: '
              'not its world (give --world); using the fitted lines instead')
    measured, fitted = _line_residuals(data, every)
    return measured, fitted, 'lines fitted by line_extractor (core/lines.py)', False


def _plot_range_residuals(path: Path, topic: str, measured, reference, errors,
                          reference_name: str) -> None:
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    finite = np.isfinite(measured) & np.isfinite(reference)
    res = measured[finite] - reference[finite]
    res = res[np.abs(res) <= 0.2]
    fig, ax = plt.subplots(figsize=(8, 5))
    ax.hist(res * 1000.0, bins=120, color='tab:blue')
    ax.axvline((errors.bias_m or 0.0) * 1000.0, color='tab:red',
               label=(f'bias {1000 * errors.bias_m:+.2f} mm' if errors.bias_m is not None
                      else 'bias not measurable'))
    ax.set_xlabel('measured - reference range (mm)')
    ax.set_ylabel('beams')
    ax.set_title(f'{topic} range residuals against the {reference_name.split(" (")[0]}: '
                 f'σ = {1000 * errors.sigma_m:.2f} mm')
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def characterize_lidar(data: SensorData, png_dir: Path | None, world_file: Path, laser,
                       every: int) -> bool:
    """Print the LiDAR's range noise (and bias, against a ray-cast truth); True when done."""
    scans = data.scans
    span = scans.range_max - scans.range_min
    print(f'LiDAR {scans.topic}: {len(scans.t)} scans x {scans.angles.size} beams, '
          f'{scans.range_min:g}-{scans.range_max:g} m')
    measured, reference, name, truth = _range_reference(data, world_file, laser, every)
    try:
        errors = ch.range_errors(measured, reference, span)
    except ValueError as exc:
        print(f'  no range statistics: {exc}')
        return False
    if not truth:
        # The lines were fitted to these very ranges: they absorb any bias, and each line's two
        # parameters take a little of the scatter.
        errors = ch.RangeErrors(None, errors.sigma_m, None, errors.precision, errors.beams)
    print(f'  against the {name}, {errors.beams} beams:')
    if errors.bias_m is not None:
        print(f'    range bias {1000 * errors.bias_m:+.2f} mm, noise sigma '
              f'{1000 * errors.sigma_m:.2f} mm, accuracy 1-|m-v|/v = {errors.accuracy:.5f}, '
              f'precision span/sigma = {errors.precision:.0f}')
    else:
        print(f'    noise sigma {1000 * errors.sigma_m:.2f} mm, precision span/sigma = '
              f'{errors.precision:.0f}; range bias and accuracy NOT MEASURABLE without ground '
              'truth (the lines absorb a bias)')
    if png_dir is not None:
        path = png_dir / 'lidar_ranges.png'
        atomic_write(path, lambda p: _plot_range_residuals(p, scans.topic, measured, reference,
                                                           errors, name))
        print(f'  wrote {path}')
    return True


def characterize_encoders(data: SensorData) -> bool:
    print(f'encoders {data.joint_topic}: {len(data.joint_t)} samples')
    for i, name in enumerate(data.joint_names):
        q = ch.encoder_quantisation(data.joint_position[:, i])
        if q.step_rad is None:
            print(f'  {name}: {q.note}')
        else:
            print(f'  {name}: quantisation step {q.step_rad:.6g} rad = {q.counts_per_rev:.1f} '
                  f'counts per revolution ({100 * q.on_grid_fraction:.1f} % of readings on the '
                  'grid)')
    return True


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog=PROG, description=__doc__.split('\n\n')[0])
    parser.add_argument('bag', type=Path, help='rosbag2 folder or ROS 1 .bag file')
    parser.add_argument('--png', type=Path, help='write the plots into this folder')
    parser.add_argument('--world', type=Path, default=None,
                        help='world YAML of a simulated bag (default: config/default_world.yaml)')
    parser.add_argument('--laser', type=float, nargs=3, metavar=('X', 'Y', 'YAW'),
                        default=(0.10, 0.0, 0.0), help='laser mount in base_link for the '
                        'ray-cast truth (m, m, rad; default sensor_sim\'s)')
    parser.add_argument('--scan-every', type=int, default=5, help='use every n-th scan')
    parser.add_argument('--imu-topic')
    parser.add_argument('--scan-topic')
    parser.add_argument('--joint-topic')
    parser.add_argument('--quiet', action='store_true', help='no progress on stderr')
    args = parser.parse_args(argv)
    if args.scan_every < 1:
        parser.error('--scan-every must be >= 1')
    try:
        if args.png is not None:
            args.png.mkdir(parents=True, exist_ok=True)
        data = read_sensor_bag(args.bag, joint_topic=args.joint_topic, scan_topic=args.scan_topic,
                               imu_topic=args.imu_topic,
                               progress=None if args.quiet else stderr_progress(PROG))
        if data.imu_t is None and data.scans is None and data.joint_t is None:
            raise SensorBagError(f'{args.bag} has no IMU, LaserScan or JointState topic '
                                 f'(topics: {describe_topics(data)})')
        done = []
        if data.imu_t is not None:
            done.append(characterize_imu(data, args.png))
        else:
            print('IMU: none in the bag')
        if data.scans is not None:
            done.append(characterize_lidar(data, args.png,
                                           args.world or config_file('default_world.yaml'),
                                           args.laser, args.scan_every))
        else:
            print('LiDAR: none in the bag')
        if data.joint_t is not None:
            done.append(characterize_encoders(data))
        else:
            print('encoders: none in the bag')
        if not any(done):
            raise SensorBagError('nothing in the bag could be characterised (see above)')
    except (SensorBagError, OSError) as exc:
        print(f'{PROG}: error: {exc}', file=sys.stderr)
        return EXIT_BAD_INPUT
    return 0


if __name__ == '__main__':
    sys.exit(main())
