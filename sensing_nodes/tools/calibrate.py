"""sensing_calibrate: wheel radii, wheel separation, laser mount (and gyro bias and scale) from
an ordinary bag with JointState encoders and LaserScans, against scan-matched motion.

    sensing_calibrate BAG [--out FILE.yaml] [--png FILE.png] [--nominal PARAMS.yaml]
    sensing_calibrate BAG --odom-delay [--odom-topic T] [--match-topic T] [--out FILE.yaml]

--odom-delay estimates instead how far an odometry topic's stamps lag the scan matcher's
(/scan_match/odom, e.g. a sensing_pipeline output bag): complementary_fusion's
<input>.delay_s and icp_matcher's odom_delay_s.

The nominal geometry (what the nodes are told today) comes from --nominal (a ROS 2 parameter
file with wheel_odometry and icp_matcher sections; default: the package's config/ files) and
the --wheel-radius/--wheel-separation/--laser options. The written YAML loads into
wheel_odometry, icp_matcher and gyro_integrator as it is (their own parameter names), plus a
sensing_calibrate section with every estimate, standard deviation and correlation.
Exit status 0 on success, 2 on bad input (nothing written).
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from sensing_nodes.bags.sensor_streams import (
    EXIT_BAD_INPUT,
    SensorBagError,
    atomic_write,
    read_sensor_bag,
    read_yaw_track,
    stderr_progress,
)
from sensing_nodes.core.config.icp_matcher import ICP_MATCHER_PARAMETERS, IcpMatcherParameters
from sensing_nodes.core.config.wheel_odometry import (
    WHEEL_ODOMETRY_PARAMETERS,
    WheelOdometryParameters,
)
from sensing_nodes.core.evaluation import calibration as cal
from sensing_nodes.core.geometry.scan import scan_to_points
from sensing_nodes.parameters import ParameterError, load_parameters
from sensing_nodes.paths import config_file

PROG = 'sensing_calibrate'


def nominal_settings(nominal_file: Path | None
                     ) -> tuple[WheelOdometryParameters, IcpMatcherParameters]:
    """wheel_odometry's and icp_matcher's parameters as the nodes run with them: the --nominal
    file's, else the shipped config/ files' (each node's defaults for what a file leaves out)."""
    try:
        return (WHEEL_ODOMETRY_PARAMETERS.config(load_parameters(
                    'wheel_odometry', nominal_file or config_file('wheel_odometry.yaml'))),
                ICP_MATCHER_PARAMETERS.config(load_parameters(
                    'icp_matcher', nominal_file or config_file('icp_matcher.yaml'))))
    except ParameterError as exc:
        raise SensorBagError(f'cannot use the nominal parameters: {exc}') from None


def _wheel_columns(names: tuple[str, ...], left: str, right: str) -> tuple[int, int]:
    """Columns of the left and right wheel among the JointState names."""
    if left in names and right in names:
        return names.index(left), names.index(right)
    lefts = [i for i, n in enumerate(names) if 'left' in n.lower()]
    rights = [i for i, n in enumerate(names) if 'right' in n.lower()]
    if len(lefts) == 1 and len(rights) == 1:
        return lefts[0], rights[0]
    raise SensorBagError(f'cannot tell the wheel joints among {list(names)}: give '
                         '--left-joint and --right-joint')


def _yaml_header(result: cal.CalibrationResult, bag: str) -> list[str]:
    """The parameter file's comment lines: what was used, each estimate with its std."""
    lines = [
        f'# {PROG} {bag}',
        f'# {result.intervals_used} scan-matched intervals used, {result.outliers} outliers, '
        f'{sum(result.refused.values())} refused by the matcher; '
        f'{result.distance_m:.1f} m driven, {math.degrees(result.turned_rad):.0f} deg turned.',
    ]
    for e in result.estimates:
        if e.excited:
            lines.append(f'#   {e.name:<20} {e.value:.6f} +- {e.std:.2g} {e.unit}')
        else:
            lines.append(f'#   {e.name:<20} not estimated: {e.note} (nominal kept)')
    return lines + [f'#   note: {note}' for note in result.notes]


def _wheel_parameters(result: cal.CalibrationResult, wheel_radius_m: float) -> dict[str, float]:
    """wheel_odometry's parameters from the calibrated geometry and error model."""
    g = result.geometry()
    est = {e.name: e for e in result.estimates}
    radius_std = [est[n].std / est[n].value for n in ('left_radius_m', 'right_radius_m')
                  if est[n].excited]
    wheel = {
        'wheel_radius_m': float(wheel_radius_m),
        'wheel_separation_m': round(g.wheel_separation_m, 7),
        'left_radius_multiplier': round(g.left_radius_m / wheel_radius_m, 7),
        'right_radius_multiplier': round(g.right_radius_m / wheel_radius_m, 7),
        # What calibration leaves: the wheel_odometry systematic error model takes it.
        'radius_multiplier_std': round(float(max(radius_std)), 7) if radius_std else 0.0,
    }
    if math.isfinite(result.wheel_variance_per_m):
        # The random part: what the residuals show beyond the matcher's own noise.
        wheel['wheel_variance_per_m'] = float(f'{result.wheel_variance_per_m:.3g}')
    return wheel


def _gyro_section(gyro: cal.GyroCalibration, lines: list[str], doc: dict, report: dict) -> None:
    """The gyro's comment lines, gyro_integrator's parameters and the report's gyro figures."""
    lines.append(f'#   gyro z bias {gyro.bias.value:.6g} +- {gyro.bias.std:.2g} rad/s'
                 + (f', scale factor error {gyro.scale.value:+.5f} +- {gyro.scale.std:.2g}'
                    if gyro.scale.excited else f', scale not estimated: {gyro.scale.note}'))
    lines.append('#   (read about the IMU\'s own z, taken as base_link\'s: a level, unrotated '
                 'IMU; gyro_integrator refines the bias itself while still)')
    gyro_params = {'max_gyro_bias_rad_s': round(max(0.05, 3.0 * abs(gyro.bias.value)), 6),
                   'initial_bias_z_rad_s': float(gyro.bias.value)}
    if gyro.scale.excited:
        gyro_params['gyro_scale_error'] = float(gyro.scale.value)
    doc['gyro_integrator'] = {'ros__parameters': gyro_params}
    report['gyro_bias_rad_s'] = float(gyro.bias.value)
    report['gyro_bias_std_rad_s'] = float(gyro.bias.std)
    report['gyro_scale_estimated'] = gyro.scale.excited
    report['gyro_scale_error'] = float(gyro.scale.value) if gyro.scale.excited else 0.0
    report['gyro_scale_error_std'] = float(gyro.scale.std) if gyro.scale.excited else 0.0


def params_yaml(result: cal.CalibrationResult, wheel_radius_m: float, bag: str,
                gyro: cal.GyroCalibration | None) -> str:
    """The parameter file text: node sections with their own parameter names, comments with
    the uncertainties, and a sensing_calibrate section with every figure."""
    g = result.geometry()
    lines = _yaml_header(result, bag)
    laser = {'laser_x_m': round(g.laser_x_m, 6), 'laser_y_m': round(g.laser_y_m, 6),
             'laser_yaw_rad': round(g.laser_yaw_rad, 7)}
    doc: dict[str, Any] = {
        'wheel_odometry': {'ros__parameters': _wheel_parameters(result, wheel_radius_m)},
        'icp_matcher': {'ros__parameters': laser}}
    report: dict[str, Any] = {
        'parameters': list(cal.PARAMETERS),
        # ROS 2 parameter arrays take one type and no NaN: a parameter not estimated is
        # marked in `estimated`, with its nominal value and std 0.
        'estimated': [e.excited for e in result.estimates],
        'values': [float(v) for v in g.vector()],
        'stds': [float(e.std) if e.excited else 0.0 for e in result.estimates],
        'correlation': [round(float(v), 4)
                        for v in np.nan_to_num(result.correlation, nan=0.0).ravel()],
        'intervals_used': result.intervals_used,
        'outliers': result.outliers,
    }
    if gyro is not None:
        _gyro_section(gyro, lines, doc, report)
    doc['sensing_calibrate'] = {'ros__parameters': report}
    return '\n'.join(lines) + '\n' + yaml.safe_dump(doc, sort_keys=False)


def plot(result: cal.CalibrationResult, intervals: cal.Intervals, path: Path) -> None:
    """Residuals of the scan-matched motion per interval with the nominal and the calibrated
    geometry (mm, mm, deg)."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    moving = intervals.select(~intervals.still)
    before = cal.interval_residuals(moving, result.nominal.vector())
    after = cal.interval_residuals(moving, result.geometry().vector())
    t = (moving.t0_ns - moving.t0_ns[0]) * 1e-9
    fig, axes = plt.subplots(3, 1, figsize=(9, 7), sharex=True)
    labels = ('x residual (mm)', 'y residual (mm)', 'yaw residual (deg)')
    factors = (1e3, 1e3, math.degrees(1.0))
    for ax, label, c, f in zip(axes, labels, range(3), factors):
        ax.plot(t, before[:, c] * f, 'o', ms=3, color='tab:red', label='nominal geometry')
        ax.plot(t, after[:, c] * f, 'o', ms=3, color='tab:blue', label='calibrated')
        ax.axhline(0.0, color='k', lw=0.5)
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    axes[0].legend(loc='best')
    axes[0].set_title('Scan-matched laser motion minus wheel odometry seen through the mount, '
                      'per interval')
    axes[-1].set_xlabel('interval start (s since the first)')
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _nominal(args: argparse.Namespace) -> tuple[cal.Geometry, float, WheelOdometryParameters]:
    """The nominal geometry (command line over the --nominal parameter file over defaults),
    the nominal wheel radius (m) and wheel_odometry's parameters."""
    wheel, icp = nominal_settings(args.nominal)
    odometry = wheel.odometry
    radius = args.wheel_radius or odometry.wheel_radius_m
    separation = args.wheel_separation or odometry.wheel_separation_m
    laser = args.laser or list(icp.matcher.laser_pose)
    # A radius given on the command line replaces the file's, multipliers included.
    left_mult = 1.0 if args.wheel_radius else odometry.left_radius_multiplier
    right_mult = 1.0 if args.wheel_radius else odometry.right_radius_multiplier
    return cal.Geometry(radius * left_mult, radius * right_mult, separation, *laser), radius, \
        wheel


def _print_inputs(args, data, columns: tuple[int, int], nominal: cal.Geometry) -> None:
    left, right = columns
    scans = data.scans
    print(f'{args.bag}: {len(data.joint_t)} encoder samples ({data.joint_names[left]}, '
          f'{data.joint_names[right]}), {len(scans.t)} scans on {scans.topic}'
          + (f', {len(data.imu_t)} IMU samples on {data.imu_topic}' if data.imu_t is not None
             else ', no IMU'))
    print(f'nominal: radii {nominal.left_radius_m:.5f} / {nominal.right_radius_m:.5f} m, '
          f'separation {nominal.wheel_separation_m:.4f} m, laser ({nominal.laser_x_m:.3f}, '
          f'{nominal.laser_y_m:.3f}) m {math.degrees(nominal.laser_yaw_rad):.2f} deg')


def _print_result(result: cal.CalibrationResult, nominal: cal.Geometry,
                  gyro: cal.GyroCalibration | None) -> None:
    print(f'{result.intervals_used} intervals used ({result.outliers} outliers rejected; '
          f'matcher refused {sum(result.refused.values())}: {result.refused or "none"}); '
          f'{result.distance_m:.1f} m driven, {math.degrees(result.turned_rad):.0f} deg turned')
    if result.closed_form is not None:
        cf = result.closed_form
        print(f'closed form (Censi et al. 2013): radii {cf.left_radius_m:.6f} / '
              f'{cf.right_radius_m:.6f} m, separation {cf.wheel_separation_m:.5f} m, laser '
              f'({cf.laser_x_m:.4f}, {cf.laser_y_m:.4f}) m '
              f'{math.degrees(cf.laser_yaw_rad):.3f} deg')
    print('refined (nonlinear least squares):')
    for e, nom in zip(result.estimates, nominal.vector()):
        if not e.excited:
            print(f'  {e.name:<20} NOT ESTIMATED: {e.note}')
            continue
        shown = (f'{math.degrees(e.value):.4f} +- {math.degrees(e.std):.4f} deg'
                 if e.unit == 'rad' else f'{e.value:.6f} +- {e.std:.6f} m')
        rel = f' ({100 * (e.value / nom - 1):+.3f} % vs nominal)' if e.name in (
            'left_radius_m', 'right_radius_m', 'wheel_separation_m') else ''
        print(f'  {e.name:<20} {shown}{rel}')
    print(f'  random wheel error seen in the residuals: {result.wheel_variance_per_m:.3g} m^2 per '
          'm of wheel travel (wheel_odometry wheel_variance_per_m)')
    for note in result.notes:
        print(f'  note: {note}')
    names = [e.name for e in result.estimates if e.excited]
    idx = [i for i, e in enumerate(result.estimates) if e.excited]
    if len(idx) > 1:
        print('correlations:')
        print('  ' + ' ' * 20 + ''.join(f'{n[:9]:>10}' for n in names))
        for i, n in zip(idx, names):
            print(f'  {n:<20}' + ''.join(f'{result.correlation[i, j]:10.2f}' for j in idx))
    if gyro is not None:
        print(f'gyro z: bias {gyro.bias.value:.6f} +- {gyro.bias.std:.6f} rad/s '
              f'({math.degrees(gyro.bias.value):.4f} deg/s); '
              + (f'scale factor error {gyro.scale.value:+.5f} +- {gyro.scale.std:.5f}'
                 if gyro.scale.excited else f'scale NOT ESTIMATED: {gyro.scale.note}')
              + f' ({gyro.intervals} intervals)')


def run(args: argparse.Namespace) -> int:
    progress = None if args.quiet else stderr_progress(PROG)
    data = read_sensor_bag(args.bag, joint_topic=args.joint_topic, scan_topic=args.scan_topic,
                           imu_topic=args.imu_topic, want=('joints', 'scan', 'imu'),
                           required=('joints', 'scan'), purpose='calibration needs both',
                           progress=progress)
    nominal, radius, wheel = _nominal(args)
    columns = _wheel_columns(data.joint_names, args.left_joint or wheel.left_wheel_joint,
                             args.right_joint or wheel.right_wheel_joint)
    joints = data.joint_position[:, list(columns)]
    if np.ptp(joints, axis=0).max() < 1e-6:
        raise SensorBagError(f'{args.bag}: the wheels never turn: no motion to calibrate from')
    scans = data.scans
    converted = [scan_to_points(r, scans.angles, scans.range_min, scans.range_max)
                 for r in scans.ranges]
    points = [p for p, _ in converted]
    # A sweeping scanner (time_increment set): each scan deskewed by the nominal odometry.
    beam_times = None if not scans.time_increment_s > 0.0 else \
        [scans.beam_times(beams) for _, beams in converted]
    _print_inputs(args, data, columns, nominal)
    options = cal.IntervalOptions(distance_m=args.interval_distance,
                                  angle_rad=math.radians(args.interval_angle))

    def match_progress(done: int, total: int) -> None:
        if progress is not None and total:
            progress(f'scan matching interval {done}/{total}')

    intervals = cal.make_intervals(data.joint_t, joints, scans.t, points, nominal, options,
                                   match_progress, beam_times)
    result = cal.calibrate(intervals, nominal)
    gyro = None
    if data.imu_t is not None:
        try:
            gyro = cal.calibrate_gyro(intervals, data.imu_t, data.imu_gyro[:, 2])
        except cal.CalibrationError as exc:
            print(f'gyro: not calibrated: {exc}')
    _print_result(result, nominal, gyro)
    if not any(e.excited for e in result.estimates):
        raise SensorBagError('the motion in the bag excites none of the parameters')
    if args.out is not None:
        text = params_yaml(result, radius, str(args.bag), gyro)
        atomic_write(args.out, lambda p: p.write_text(text))
        print(f'wrote {args.out}')
    if args.png is not None:
        atomic_write(args.png, lambda p: plot(result, intervals, p))
        print(f'wrote {args.png}')
    return 0


def delay_yaml(result: cal.TimeOffset, bag: str, odom_topic: str, match_topic: str) -> str:
    """Parameter YAML of an odometry delay estimate: the fusion's wheel_odom input and the
    matcher's odometry guess, plus the estimate's figures."""
    delay = round(result.delay_s, 4)
    doc = {
        'complementary_fusion': {'ros__parameters': {'wheel_odom': {'delay_s': delay}}},
        'icp_matcher': {'ros__parameters': {'odom_delay_s': delay}},
        'sensing_calibrate': {'ros__parameters': {
            'bag': bag, 'odom_topic': odom_topic, 'match_topic': match_topic,
            'odom_delay_s': float(result.delay_s), 'odom_delay_std_s': float(result.std_s),
            'intervals': result.intervals, 'turned_deg': math.degrees(result.turned_rad),
            'yaw_disagreement_at_zero_deg': math.degrees(result.cost_at_zero_rad),
            'yaw_disagreement_at_delay_deg': math.degrees(float(result.cost_rad.min())),
            'two_sided': bool(result.two_sided)}},
    }
    return (f'# {PROG} --odom-delay {bag}: odometry stamped t describes the robot at t - delay\n'
            + yaml.safe_dump(doc, sort_keys=False))


def run_delay(args: argparse.Namespace) -> int:
    """--odom-delay: the odometry topic's delay against the scan matches
    (core/evaluation/calibration.py)."""
    odom_t, odom_yaw = read_yaw_track(args.bag, args.odom_topic)
    match_t, match_yaw = read_yaw_track(args.bag, args.match_topic)
    print(f'{args.bag}: {len(odom_t)} odometry poses on {args.odom_topic}, {len(match_t)} scan '
          f'matches on {args.match_topic}')
    result = cal.odometry_delay(odom_t, odom_yaw, match_t, match_yaw,
                                max_delay_s=args.max_delay)
    print(f'odometry delay: {result.delay_s:.4f} +- {result.std_s:.4f} s ({result.intervals} '
          f'intervals, {math.degrees(result.turned_rad):.0f} deg turned); yaw-increment '
          f'disagreement {math.degrees(result.cost_at_zero_rad):.3f} deg at 0, '
          f'{math.degrees(float(result.cost_rad.min())):.3f} deg at the delay')
    if result.two_sided:
        print('  note: the disagreement also drops on the other side of 0: no single delay '
              'explains it (odometry re-anchored at the scans? docs/calibration.md)')
    print(f'  complementary_fusion: wheel_odom.delay_s: {result.delay_s:.4f}; '
          f'icp_matcher: odom_delay_s: {result.delay_s:.4f}')
    if args.out is not None:
        text = delay_yaml(result, str(args.bag), args.odom_topic, args.match_topic)
        atomic_write(args.out, lambda p: p.write_text(text))
        print(f'wrote {args.out}')
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog=PROG, description=__doc__.split('\n\n')[0])
    parser.add_argument('bag', type=Path, help='rosbag2 folder or ROS 1 .bag file')
    parser.add_argument('--out', type=Path, help='write the parameter YAML here')
    parser.add_argument('--png', type=Path, help='write a residual plot here')
    parser.add_argument('--nominal', type=Path,
                        help='parameter file with wheel_odometry and icp_matcher sections '
                             '(default: the package config/)')
    parser.add_argument('--wheel-radius', type=float, help='nominal wheel radius (m); '
                        'overrides the file (multipliers then 1)')
    parser.add_argument('--wheel-separation', type=float, help='nominal separation (m)')
    parser.add_argument('--laser', type=float, nargs=3, metavar=('X', 'Y', 'YAW'),
                        help='nominal laser mount in base_link (m, m, rad)')
    parser.add_argument('--left-joint', help='left wheel joint name (default: from the '
                        "nominal file, else the one name containing 'left')")
    parser.add_argument('--right-joint', help='right wheel joint name')
    parser.add_argument('--joint-topic', help='JointState topic (default: /joint_states or the '
                        'busiest JointState topic)')
    parser.add_argument('--scan-topic', help='LaserScan topic')
    parser.add_argument('--imu-topic', help='Imu topic')
    parser.add_argument('--interval-distance', type=float, default=0.5,
                        help='interval length along the path (m, default 0.5)')
    parser.add_argument('--interval-angle', type=float, default=45.0,
                        help='interval turning (deg, default 45)')
    parser.add_argument('--quiet', action='store_true', help='no progress on stderr')
    parser.add_argument('--odom-delay', action='store_true',
                        help="estimate the odometry topic's delay against the scan matches "
                             'instead (nothing else is calibrated)')
    parser.add_argument('--odom-topic', default='/wheel/odom',
                        help='--odom-delay: nav_msgs/Odometry topic (default /wheel/odom)')
    parser.add_argument('--match-topic', default='/scan_match/odom',
                        help='--odom-delay: scan matcher poses (default /scan_match/odom)')
    parser.add_argument('--max-delay', type=float, default=0.5,
                        help='--odom-delay: offsets searched, +- this (s, default 0.5)')
    args = parser.parse_args(argv)
    if not (math.isfinite(args.max_delay) and args.max_delay > 0):
        parser.error('--max-delay must be a positive number')
    for name in ('wheel_radius', 'wheel_separation', 'interval_distance', 'interval_angle'):
        value = getattr(args, name)
        if value is not None and not (math.isfinite(value) and value > 0):
            parser.error(f'--{name.replace("_", "-")} must be a positive number')
    try:
        return run_delay(args) if args.odom_delay else run(args)
    except (SensorBagError, cal.CalibrationError) as exc:
        print(f'{PROG}: error: {exc}', file=sys.stderr)
        return EXIT_BAD_INPUT


if __name__ == '__main__':
    sys.exit(main())
