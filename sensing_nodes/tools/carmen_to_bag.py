"""carmen_to_bag: convert a CARMEN laser log into a rosbag2 MCAP bag.

  /scan               sensor_msgs/LaserScan from FLASER (frame `laser`, 180 degrees from -90,
                      counter-clockwise; the log's no-return value -> +inf, REP 117)
  /odom               nav_msgs/Odometry from ODOM (the robot's raw odometry, odom -> base_link)
  /ground_truth/odom  nav_msgs/Odometry: the FLASER reference pose (map -> base_link)

The "corrected" benchmark logs carry the reference pose of the laser in each FLASER line and an
extra ODOM line after it (stamped 0, or garbage) holding that same pose; those ODOM lines are
not odometry and are skipped (and counted), and the ODOM lines after them, which continue from
that reference pose, are chained on from the odometry before it (`odometry_chain`): /odom
carries no reference information. The laser sits `--laser-x` metres ahead of base_link (default
0: the shared logs' FLASER pose measures as the laser's and their declared offsets do not hold,
see ../shared/datasets/carmen/README.md), so base_link's reference pose is the laser pose moved
back by it. A line that does not parse is reported with its number and the rest converts.

Time: the log's stamps are used when they are sound. Where they carry no time (all equal, e.g.
all 0; or fewer distinct stamps than half the ODOM or FLASER lines, written to too few digits)
a time base is rebuilt from the order of the lines (`--time-base auto`, the default): every
ODOM line one tick of an assumed rate (`--odom-rate`, 10 Hz), every scan at its preceding ODOM
line's time; the output and the bag's metadata.yaml (custom_data `carmen_to_bag.time_base`) say
so, with the speed the odometry then has and the settings for an assumed time (icp_matcher's
`rate_limits:=false`, complementary_fusion's `ekf.hold_back_max_s:=0.0`). Stamps that go
backwards, are negative, wrapped or stand still (many consecutive lines on one stamp) are
refused with a message naming the first line: rebuilding would throw away the time that is
sound; `--time-base lines` rebuilds a time base for those too. A line order that cannot
time the scans (fewer ODOM lines between them than scans) is refused too.
"""

from __future__ import annotations

import argparse
import math
import shutil
import sys
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from sensing_nodes.bags.carmen import (
    COARSE_DISTINCT,
    ZERO_STAMP_S,
    CarmenLog,
    TimeCheck,
    check_time,
    line_order_time,
    read_carmen,
    reference_repeats,
)
from sensing_nodes.core.geometry import se2
from sensing_nodes.topics import GROUND_TRUTH, SCAN

EXIT_BAD_INPUT = 2
NS = 1_000_000_000
DEFAULT_ODOM_RATE_HZ = 10.0   # a round rate within the shared logs' 4.5-17 Hz (median intervals)
TIME_BASE_KEY = 'carmen_to_bag.time_base'


@dataclass(frozen=True)
class ConvertOptions:
    """How a log is converted (the command line's options)."""

    laser_x_m: float = 0.0
    time_offset_s: float = 0.0
    odom_var_per_m_xy: float = 1e-2
    odom_var_per_m_yaw: float = 1e-3
    odom_var_per_rad_yaw: float = 2.5e-3
    compress: bool = True
    time_base: str = 'auto'          # 'auto': the log's stamps unless they carry no time
    odom_rate_hz: float = DEFAULT_ODOM_RATE_HZ


@dataclass(frozen=True)
class TimeBase:
    """Times (s) of every ODOM row and every scan, which ODOM rows repeat a reference pose, and
    how the times were made ('' the log's own stamps; else what was rebuilt, and why)."""

    odom_s: np.ndarray
    scan_s: np.ndarray
    anchors: np.ndarray
    rebuilt: str = ''


# A no-return reading scatters a little below the log's sentinel (Edmonton: 51.14 and 51.10
# around 51.15, with a few at 51.16; freiburg-campus: 81.83 below 81.91): a range this close
# below the largest is a no-return too (what it loses: returns within 0.5 % of the range limit).
NO_RETURN_MARGIN = 0.005


def no_return_value(log: CarmenLog, min_share: float = 0.001) -> float | None:
    """The log's no-return range: its largest range value, when the ranges within
    NO_RETURN_MARGIN below it repeat in at least min_share of all beams (a sentinel with its
    scatter, not a far wall); else None. Ranges from (1 - NO_RETURN_MARGIN) x it up are no
    returns."""
    if not log.scans:
        return None
    ranges = np.concatenate([s.ranges for s in log.scans])
    largest = float(ranges.max())
    near = ranges >= largest * (1.0 - NO_RETURN_MARGIN)
    return largest if np.mean(near) >= min_share else None


def stuck_beams(log: CarmenLog, min_scans: int = 20) -> list[int]:
    """Beams that read one and the same range, below the no-return value, in every scan of the
    log (Acapulco's 181st beam: 50.0 in all 861 scans): no measurement. Only among the scans
    with the usual beam count, with at least min_scans of them, and only when fewer than a
    tenth of the beams are so (a robot that never moved reads the same everywhere)."""
    counts = [s.ranges.size for s in log.scans]
    usual = max(set(counts), key=counts.count) if counts else 0
    ranges = np.array([s.ranges for s in log.scans if s.ranges.size == usual])
    if len(ranges) < min_scans:
        return []
    sentinel = no_return_value(log)
    below = ranges[0] < (math.inf if sentinel is None else sentinel * (1.0 - NO_RETURN_MARGIN))
    stuck = np.flatnonzero(np.all(ranges == ranges[0], axis=0) & below)
    return stuck.tolist() if stuck.size < 0.1 * usual else []


def odometry_chain(log: CarmenLog,
                   time: TimeBase) -> tuple[np.ndarray, np.ndarray, dict[str, int]]:
    """The ODOM rows that are odometry (not an anchor, after the previous kept row) and their
    poses (x, y, theta; odom frame) with the reference taken out: (row indices, poses, skipped).

    In the "corrected" logs an ODOM line after each FLASER repeats the scan's reference pose
    (time.anchors), and the ODOM lines after it continue from that pose: the logged odometry
    is re-anchored on the reference at every scan (a jump of up to 14 deg). Read as it is, the
    odometry would carry the reference into every estimate fed from it. So each anchor is taken
    to stand where the previous kept row stood (the scan's own ODOM line, same time) and the
    rows after it continue by their own increments from the anchor: the robot's odometry as a
    wheel-encoder chain, without the corrections. A log without such lines is unchanged."""
    keep, poses = [], []
    skipped = {'reference_repeated': int(time.anchors.sum()), 'not_after_previous': 0}
    last = -math.inf
    offset = (0.0, 0.0, 0.0)     # chained pose = offset (+) logged pose
    anchor = None
    for i, t in enumerate(time.odom_s.tolist()):
        logged = tuple(float(v) for v in log.odom_pose[i])
        if time.anchors[i]:
            anchor = logged
        elif t <= last:
            skipped['not_after_previous'] += 1
        else:
            if anchor is not None and poses:
                offset = se2.compose(poses[-1], se2.inverse(anchor))
            anchor = None
            keep.append(i)
            poses.append(tuple(float(v) for v in se2.compose(offset, logged)))
            last = t
    return np.array(keep, dtype=int), np.array(poses).reshape(-1, 3), skipped


def time_base(log: CarmenLog, options: ConvertOptions) -> TimeBase:
    """The log's own stamps when they are sound; else one rebuilt from the line order
    (`options.time_base` 'auto': where the stamps carry no time; 'lines': always); ValueError
    naming what is wrong with stamps that go backwards, are negative, wrapped or stand still
    (with 'auto'), or with a line order that cannot time the scans."""
    repeats = reference_repeats(log)
    stamped_zero = np.abs(log.odom_time_s) < ZERO_STAMP_S
    odometry = int(np.sum(~repeats))
    if np.sum(stamped_zero & ~repeats) > odometry / 2:
        check = TimeCheck('all_equal', f'{int(np.sum(stamped_zero & ~repeats))} of the '
                                       f'{odometry} odometry lines are stamped 0')
    else:   # the README's rule besides: an ODOM line stamped 0 repeats the reference pose
        check = check_time(log, repeats | stamped_zero)
    if options.time_base == 'auto' and not check.kind:
        return TimeBase(log.odom_time_s, np.array([s.time_s for s in log.scans]),
                        repeats | stamped_zero)
    if options.time_base == 'auto' and check.kind not in ('all_equal', 'coarse'):
        raise ValueError(f'the log\'s time is broken: {check.text}; --time-base lines '
                         'rebuilds a time base from the order of the lines')
    odom_s, scan_s = line_order_time(log, repeats, options.odom_rate_hz)
    distinct = np.unique(scan_s).size
    if scan_s.size > 1 and distinct < COARSE_DISTINCT * scan_s.size:
        broken = f"the log's time is broken ({check.text}) and " if check.text else ''
        raise ValueError(f'{broken}the order of the lines cannot time the scans: its '
                         f'{scan_s.size} FLASER lines get {distinct} distinct times from its '
                         f'{odometry} ODOM lines of odometry (a scan takes the time of the ODOM '
                         'line before it)')
    why = check.text or 'asked for (--time-base lines)'
    return TimeBase(odom_s, scan_s, repeats,
                    f'rebuilt from the order of the lines ({why}): ODOM lines at an assumed '
                    f'{options.odom_rate_hz:g} Hz, each scan at the time of the ODOM line '
                    f'before it, {odom_s[-1] if len(odom_s) else 0.0:.1f} s in all')


def odometry_speed(times_s: np.ndarray, poses: np.ndarray) -> tuple[float, float]:
    """Median and 99th-percentile speed (m/s) of the odometry between consecutive rows."""
    dt, step = np.diff(times_s), np.hypot(*np.diff(poses[:, :2], axis=0).T)
    speed = step[dt > 0] / dt[dt > 0]
    return (float(np.median(speed)), float(np.percentile(speed, 99))) if speed.size else \
        (0.0, 0.0)


def odometry_covariances(poses: np.ndarray, per_m_xy: float, per_m_yaw: float,
                         per_rad_yaw: float) -> np.ndarray:
    """(N, 3, 3) covariance of odometry poses growing with distance (m) and turn (rad)
    travelled: variances per metre / per radian, as a wheel-odometry random walk."""
    step = np.hypot(np.diff(poses[:, 0]), np.diff(poses[:, 1]))
    turn = np.abs(se2.wrap_angle(np.diff(poses[:, 2])))
    distance = np.concatenate([[0.0], np.cumsum(step)])
    turned = np.concatenate([[0.0], np.cumsum(turn)])
    cov = np.zeros((len(poses), 3, 3))
    cov[:, 0, 0] = cov[:, 1, 1] = per_m_xy * distance
    cov[:, 2, 2] = per_m_yaw * distance + per_rad_yaw * turned
    return cov


def convert(log_path: str | Path, out: str | Path, options: ConvertOptions | None = None,
            **changes) -> dict:
    """Convert (options: ConvertOptions, or its fields by name); returns a summary (counts,
    skipped lines, errors with their line numbers, the time base). ValueError when the log
    cannot be converted honestly."""
    options = replace(options or ConvertOptions(), **changes)
    log_path, out = Path(log_path), Path(out)
    log = _read_log(log_path)
    time = time_base(log, options)
    rows, poses, skipped = odometry_chain(log, time)
    offset_ns = int(round(options.time_offset_s * NS))
    messages = _scan_messages(log, time, options, offset_ns) + \
        _odometry_messages(log, time, rows, poses, options, offset_ns)
    first = min(m[0] for m in messages)
    if first < 0:
        raise ValueError(f'--time-offset {options.time_offset_s:g} s puts the first stamp at '
                         f'{first / NS:g} s: stamps must not be negative')
    messages.sort(key=lambda m: (m[0], m[1]))
    counts = _write_bag(out, messages, options, time.rebuilt)
    speed = odometry_speed(time.odom_s[rows], poses) if len(rows) else (0.0, 0.0)
    return {'counts': counts, 'skipped_odom': skipped, 'errors': log.errors,
            'scans_on_previous_stamp': int(np.sum(np.diff(time.scan_s) == 0)),
            'no_return_value': no_return_value(log), 'beams': len(log.scans[0].ranges),
            'stuck_beams': stuck_beams(log),
            'time_base': time.rebuilt, 'odom_rate_hz': options.odom_rate_hz,
            'odometry_speed_m_s': speed,
            'declared_max_speed_m_s': _declared_max_speed(log)}


def _read_log(path: Path) -> CarmenLog:
    """The parsed log; ValueError (without the path: the caller names it) when it cannot be
    read or has no scan."""
    try:
        log = read_carmen(path)
    except (OSError, EOFError, UnicodeDecodeError) as exc:
        raise ValueError(f'cannot read the log ({exc})') from None
    if not log.scans:
        raise ValueError('no FLASER line parsed'
                         + (f' ({len(log.errors)} bad lines)' if log.errors else ''))
    return log


def _declared_max_speed(log: CarmenLog) -> float | None:
    """The log's PARAM robot_max_t_vel (m/s), if it declares one."""
    try:
        return float(log.params['robot_max_t_vel'])
    except (KeyError, ValueError):
        return None


def _scan_messages(log: CarmenLog, time: TimeBase, options: ConvertOptions,
                   offset_ns: int) -> list[tuple[int, int, str, object]]:
    """(stamp ns, order, topic, message) of every scan and its reference pose."""
    from sensor_msgs.msg import LaserScan

    from sensing_nodes.ros.conversions import float32_array, make_odometry

    sentinel = no_return_value(log)
    limit = None if sentinel is None else sentinel * (1.0 - NO_RETURN_MARGIN)
    stuck = stuck_beams(log)
    counts = [s.ranges.size for s in log.scans]
    usual = max(set(counts), key=counts.count)
    base_from_laser = se2.inverse((options.laser_x_m, 0.0, 0.0))
    zero_cov = np.zeros((3, 3))
    messages = []
    for scan, t in zip(log.scans, time.scan_s.tolist()):
        stamp = int(round(t * NS)) + offset_ns
        n = len(scan.ranges)
        msg = LaserScan()
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp, NS)
        msg.header.frame_id = 'laser'
        msg.angle_min = -math.pi / 2
        msg.angle_increment = math.pi / n      # n beams over 180 deg: log.scan_angles(n)
        msg.angle_max = msg.angle_min + (n - 1) * msg.angle_increment
        msg.time_increment = 0.0
        msg.scan_time = 0.0
        msg.range_min = 0.0
        ranges = scan.ranges.astype(float).copy()
        if stuck and n == usual:
            ranges[stuck] = np.nan                  # REP 117: an invalid measurement
        if limit is not None:
            ranges[ranges >= limit] = np.inf
            msg.range_max = float(limit)
        else:
            msg.range_max = float(np.max(ranges)) + 1.0
        msg.ranges = float32_array(ranges)
        messages.append((stamp, 2, SCAN, msg))
        base_pose = se2.compose(tuple(scan.pose), base_from_laser)
        truth = make_odometry(stamp, 'map', 'base_link', base_pose, zero_cov)
        messages.append((stamp, 0, GROUND_TRUTH, truth))
    return messages


def _odometry_messages(log: CarmenLog, time: TimeBase, rows: np.ndarray, poses: np.ndarray,
                       options: ConvertOptions,
                       offset_ns: int) -> list[tuple[int, int, str, object]]:
    """(stamp ns, order, topic, message) of the chained odometry."""
    from sensing_nodes.ros.conversions import make_odometry

    covs = odometry_covariances(poses, options.odom_var_per_m_xy, options.odom_var_per_m_yaw,
                                options.odom_var_per_rad_yaw)
    twist_cov = np.diag([1e-4, 1e-6, 1e-4])
    messages = []
    for j, i in enumerate(rows):
        stamp = int(round(float(time.odom_s[i]) * NS)) + offset_ns
        tv, rv = log.odom_velocity[i]
        msg = make_odometry(stamp, 'odom', 'base_link', tuple(poses[j]), covs[j],
                            (float(tv), 0.0, float(rv)), twist_cov)
        messages.append((stamp, 1, '/odom', msg))
    return messages


def _write_bag(out: Path, messages: list, options: ConvertOptions,
               rebuilt: str) -> dict[str, int]:
    """The bag at `out`, written under a hidden sibling and moved there when complete;
    topic -> count."""
    from sensing_nodes.bags.storage import BagWriter
    from sensing_nodes.ros.qos import ESTIMATE_QOS, SENSOR_QOS

    staging = out.with_name(f'.{out.name}.partial')
    shutil.rmtree(staging, ignore_errors=True)
    staging.mkdir(parents=True)
    counts = {SCAN: 0, '/odom': 0, GROUND_TRUTH: 0}
    try:
        # Written in one go: 1 MiB chunks (a crash leaves only the staging folder).
        with BagWriter(staging / out.name, compress=options.compress, chunk_s=None) as bag:
            # Offered QoS for `ros2 bag play`: the scan as a driver offers it, the rest reliable.
            bag.add_topic(SCAN, 'sensor_msgs/msg/LaserScan', SENSOR_QOS)
            bag.add_topic('/odom', 'nav_msgs/msg/Odometry', ESTIMATE_QOS)
            bag.add_topic(GROUND_TRUTH, 'nav_msgs/msg/Odometry', ESTIMATE_QOS)
            if rebuilt:
                bag.set_custom_data(TIME_BASE_KEY, rebuilt)
            for t, _, topic, msg in messages:
                bag.write(topic, msg, t)
                counts[topic] += 1
        (staging / out.name).rename(out)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return counts


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog='carmen_to_bag', description=__doc__.split('\n\n')[0])
    parser.add_argument('log', help='CARMEN log (.log or .log.gz)')
    parser.add_argument('out', help='bag folder to create')
    parser.add_argument('--laser-x', type=float, default=0.0,
                        help='laser mount ahead of base_link (m); default 0 (see module doc)')
    parser.add_argument('--time-offset', type=float, default=0.0,
                        help='seconds added to every log time (stamps are log seconds otherwise)')
    parser.add_argument('--time-base', choices=('auto', 'lines'), default='auto',
                        help="auto: the log's stamps, rebuilt from the line order where they "
                             'carry no time (all equal, too coarse); lines: always rebuilt')
    parser.add_argument('--odom-rate', type=float, default=DEFAULT_ODOM_RATE_HZ,
                        help='the odometry rate (Hz) a rebuilt time base assumes (default '
                             f'{DEFAULT_ODOM_RATE_HZ:g})')
    parser.add_argument('--no-compress', action='store_true', help='plain MCAP chunks')
    args = parser.parse_args(argv)
    if not (math.isfinite(args.odom_rate) and args.odom_rate > 0):
        parser.error('--odom-rate must be > 0')
    out = Path(args.out)
    if out.exists():
        print(f'carmen_to_bag: error: {out} already exists', file=sys.stderr)
        return EXIT_BAD_INPUT
    if not Path(args.log).is_file():
        print(f'carmen_to_bag: error: {args.log}: no such file', file=sys.stderr)
        return EXIT_BAD_INPUT
    options = ConvertOptions(laser_x_m=args.laser_x, time_offset_s=args.time_offset,
                             compress=not args.no_compress, time_base=args.time_base,
                             odom_rate_hz=args.odom_rate)
    try:
        summary = convert(args.log, out, options)
    except ValueError as exc:
        reason = str(exc)       # most name the log already: never twice
        named = reason if reason.startswith(str(args.log)) else f'{args.log}: {reason}'
        print(f'carmen_to_bag: error: {named}', file=sys.stderr)
        return EXIT_BAD_INPUT
    _report(args.log, out, summary)
    return 0


def _report(log: str, out: Path, summary: dict) -> None:
    """What was converted, skipped and rebuilt (bad lines and a doubtful rate on stderr)."""
    for number, reason in summary['errors']:
        print(f'carmen_to_bag: {log}:{number}: skipped: {reason}', file=sys.stderr)
    skipped = summary['skipped_odom']
    print(f"carmen_to_bag: wrote {out}: {summary['counts'][SCAN]} scans "
          f"({summary['beams']} beams, no-return value {summary['no_return_value']} and up to "
          f"{100 * NO_RETURN_MARGIN:g} % below it -> +inf"
          + (f", beams {summary['stuck_beams']} read one value in every scan -> NaN"
             if summary['stuck_beams'] else '') + '), '
          f"{summary['counts']['/odom']} odometry, {summary['counts'][GROUND_TRUTH]} "
          f"reference poses; ODOM lines skipped: {skipped['reference_repeated']} repeating the "
          f"scan's reference pose, {skipped['not_after_previous']} not after the previous; "
          f"{len(summary['errors'])} bad lines")
    if summary['time_base']:
        median, top = summary['odometry_speed_m_s']
        declared = summary['declared_max_speed_m_s']
        print(f"carmen_to_bag: time base {summary['time_base']}; the odometry then moves at "
              f'{median:.2f} m/s (median), {top:.2f} m/s (99th percentile)'
              + (f'; the log declares robot_max_t_vel {declared:g} m/s' if declared else ''))
        if declared and top > declared:
            slower = math.floor(10 * summary['odom_rate_hz'] * declared / top) / 10
            print(f'carmen_to_bag: warning: at the assumed rate the odometry is faster than the '
                  f'robot declares ({top:.2f} > {declared:g} m/s): its rate is likely lower '
                  f'(--odom-rate {slower:g} keeps it below)', file=sys.stderr)
        print('carmen_to_bag: the time is assumed, not measured: speed and yaw-rate limits '
              'measure nothing on it (run icp_matcher with rate_limits:=false, and '
              'complementary_fusion with ekf.hold_back_max_s:=0.0)')
    if summary['scans_on_previous_stamp']:
        print(f"carmen_to_bag: warning: {summary['scans_on_previous_stamp']} scans carry the "
              'stamp of the scan before them: the nodes skip a repeated stamp and sensing_eval '
              'scores one pose a stamp', file=sys.stderr)


if __name__ == '__main__':
    sys.exit(main())
