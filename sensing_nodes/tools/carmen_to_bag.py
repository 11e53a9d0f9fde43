"""carmen_to_bag: convert a CARMEN laser log into a rosbag2 MCAP bag.

  /scan               sensor_msgs/LaserScan from FLASER (frame `laser`, 180 degrees from -90,
                      counter-clockwise; the log's no-return value -> +inf, REP 117)
  /odom               nav_msgs/Odometry from ODOM (the robot's raw odometry, odom -> base_link)
  /ground_truth/odom  nav_msgs/Odometry: the FLASER reference pose (map -> base_link)

The "corrected" benchmark logs carry the reference pose of the laser in each FLASER line and an
extra ODOM line stamped 0 after it holding that same pose; those ODOM lines are not odometry and
are skipped (and counted), and the ODOM lines after them, which continue from that reference
pose, are chained on from the odometry before it (`odometry_chain`): /odom carries no
reference information. The laser sits `--laser-x` metres ahead of base_link (default 0: the
shared logs' FLASER pose measures as the laser's and their declared offsets do not hold, see
../shared/datasets/carmen/README.md), so base_link's reference pose is the laser pose moved back
by it. A line that does not parse is reported with its number and the rest converts.
"""

from __future__ import annotations

import argparse
import math
import shutil
import sys
from pathlib import Path

import numpy as np

from sensing_nodes.bags.carmen import CarmenLog, read_carmen
from sensing_nodes.core.geometry import se2
from sensing_nodes.topics import GROUND_TRUTH, SCAN

EXIT_BAD_INPUT = 2
NS = 1_000_000_000
# An ODOM line stamped below this is "stamped 0": Freiburg 101 writes 18 of its 292 zeros as
# garbage such as 2.5e-91 (each repeats its scan's reference pose, as the real zeros do).
ZERO_STAMP_S = 1e-6


def no_return_value(log: CarmenLog, min_share: float = 0.001) -> float | None:
    """The log's no-return range: its largest range value, if it is a repeated sentinel
    (at least min_share of all beams), else None."""
    if not log.scans:
        return None
    ranges = np.concatenate([s.ranges for s in log.scans])
    largest = float(ranges.max())
    return largest if np.mean(ranges == largest) >= min_share else None


def odometry_chain(log: CarmenLog) -> tuple[np.ndarray, np.ndarray, dict[str, int]]:
    """The ODOM rows that are odometry (stamped, after the previous kept row) and their
    poses (x, y, theta; odom frame) with the reference taken out: (row indices, poses, skipped).

    In the "corrected" logs an ODOM line stamped 0 after each FLASER repeats the scan's
    reference pose, and the ODOM lines after it continue from that pose: the logged odometry
    is re-anchored on the reference at every scan (a jump of up to 14 deg). Read as it is, the
    odometry would carry the reference into every estimate fed from it. So each anchor is taken
    to stand where the previous kept row stood (the scan's own ODOM line, same time) and the
    rows after it continue by their own increments from the anchor: the robot's odometry as a
    wheel-encoder chain, without the corrections. A log without such lines is unchanged."""
    keep, poses, skipped = [], [], {'stamped_zero': 0, 'not_after_previous': 0}
    last = -math.inf
    offset = (0.0, 0.0, 0.0)     # chained pose = offset (+) logged pose
    anchor = None
    for i, t in enumerate(log.odom_time_s.tolist()):
        logged = tuple(float(v) for v in log.odom_pose[i])
        if t < ZERO_STAMP_S:
            skipped['stamped_zero'] += 1
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


def convert(log_path: str | Path, out: str | Path, laser_x_m: float = 0.0,
            time_offset_s: float = 0.0, odom_var_per_m_xy: float = 1e-2,
            odom_var_per_m_yaw: float = 1e-3, odom_var_per_rad_yaw: float = 2.5e-3,
            compress: bool = True) -> dict:
    """Convert; returns a summary (counts, skipped lines, errors with their line numbers)."""
    from nav_msgs.msg import Odometry  # noqa: F401  (rclpy message classes load here)
    from sensor_msgs.msg import LaserScan

    from sensing_nodes.bags.storage import BagWriter
    from sensing_nodes.ros.conversions import float32_array, make_odometry
    from sensing_nodes.ros.qos import ESTIMATE_QOS, SENSOR_QOS

    log_path, out = Path(log_path), Path(out)
    try:
        log = read_carmen(log_path)
    except (OSError, EOFError, UnicodeDecodeError) as exc:
        raise ValueError(f'{log_path}: cannot read the log ({exc})') from None
    if not log.scans:
        raise ValueError(f'{log_path}: no FLASER line parsed'
                         + (f' ({len(log.errors)} bad lines)' if log.errors else ''))
    sentinel = no_return_value(log)
    offset_ns = int(round(time_offset_s * NS))

    def stamp(t: float) -> int:
        return int(round(t * NS)) + offset_ns

    staging = out.with_name(f'.{out.name}.partial')
    shutil.rmtree(staging, ignore_errors=True)
    staging.mkdir(parents=True)
    try:
        rows, poses, skipped = odometry_chain(log)
        counts = {SCAN: 0, '/odom': 0, GROUND_TRUTH: 0}
        messages = []  # (stamp ns, order, topic, msg)
        laser_in_base = (laser_x_m, 0.0, 0.0)
        base_from_laser = se2.inverse(laser_in_base)
        zero_cov = np.zeros((3, 3))
        for k, scan in enumerate(log.scans):
            n = len(scan.ranges)
            msg = LaserScan()
            msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp(scan.time_s), NS)
            msg.header.frame_id = 'laser'
            msg.angle_min = -math.pi / 2
            msg.angle_increment = math.pi / n      # n beams over 180 deg: log.scan_angles(n)
            msg.angle_max = msg.angle_min + (n - 1) * msg.angle_increment
            msg.time_increment = 0.0
            msg.scan_time = 0.0
            msg.range_min = 0.0
            ranges = scan.ranges.astype(float).copy()
            if sentinel is not None:
                ranges[ranges >= sentinel] = np.inf
                msg.range_max = float(sentinel)
            else:
                msg.range_max = float(np.max(ranges)) + 1.0
            msg.ranges = float32_array(ranges)
            messages.append((stamp(scan.time_s), 2, SCAN, msg))
            base_pose = se2.compose(tuple(scan.pose), base_from_laser)
            truth = make_odometry(stamp(scan.time_s), 'map', 'base_link', base_pose, zero_cov)
            messages.append((stamp(scan.time_s), 0, GROUND_TRUTH, truth))
        covs = odometry_covariances(poses, odom_var_per_m_xy, odom_var_per_m_yaw,
                                    odom_var_per_rad_yaw)
        twist_cov = np.diag([1e-4, 1e-6, 1e-4])
        for j, i in enumerate(rows):
            t = float(log.odom_time_s[i])
            tv, rv = log.odom_velocity[i]
            msg = make_odometry(stamp(t), 'odom', 'base_link', tuple(poses[j]), covs[j],
                                (float(tv), 0.0, float(rv)), twist_cov)
            messages.append((stamp(t), 1, '/odom', msg))
        messages.sort(key=lambda m: (m[0], m[1]))
        with BagWriter(staging / out.name, compress=compress) as bag:
            # Offered QoS for `ros2 bag play`: the scan as a driver offers it, the rest reliable.
            bag.add_topic(SCAN, 'sensor_msgs/msg/LaserScan', SENSOR_QOS)
            bag.add_topic('/odom', 'nav_msgs/msg/Odometry', ESTIMATE_QOS)
            bag.add_topic(GROUND_TRUTH, 'nav_msgs/msg/Odometry', ESTIMATE_QOS)
            for t, _, topic, msg in messages:
                bag.write(topic, msg, t)
                counts[topic] += 1
        (staging / out.name).rename(out)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return {'counts': counts, 'skipped_odom': skipped, 'errors': log.errors,
            'no_return_value': sentinel, 'beams': len(log.scans[0].ranges)}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog='carmen_to_bag', description=__doc__.split('\n\n')[0])
    parser.add_argument('log', help='CARMEN log (.log or .log.gz)')
    parser.add_argument('out', help='bag folder to create')
    parser.add_argument('--laser-x', type=float, default=0.0,
                        help='laser mount ahead of base_link (m); default 0 (see module doc)')
    parser.add_argument('--time-offset', type=float, default=0.0,
                        help='seconds added to every log time (stamps are log seconds otherwise)')
    parser.add_argument('--no-compress', action='store_true', help='plain MCAP chunks')
    args = parser.parse_args(argv)
    out = Path(args.out)
    if out.exists():
        print(f'carmen_to_bag: error: {out} already exists', file=sys.stderr)
        return EXIT_BAD_INPUT
    if not Path(args.log).is_file():
        print(f'carmen_to_bag: error: {args.log}: no such file', file=sys.stderr)
        return EXIT_BAD_INPUT
    try:
        summary = convert(args.log, out, laser_x_m=args.laser_x, time_offset_s=args.time_offset,
                          compress=not args.no_compress)
    except ValueError as exc:
        print(f'carmen_to_bag: error: {exc}', file=sys.stderr)
        return EXIT_BAD_INPUT
    for number, reason in summary['errors']:
        print(f'carmen_to_bag: {args.log}:{number}: skipped: {reason}', file=sys.stderr)
    skipped = summary['skipped_odom']
    print(f"carmen_to_bag: wrote {out}: {summary['counts'][SCAN]} scans "
          f"({summary['beams']} beams, no-return value {summary['no_return_value']} -> +inf), "
          f"{summary['counts']['/odom']} odometry, {summary['counts'][GROUND_TRUTH]} "
          f"reference poses; ODOM lines skipped: {skipped['stamped_zero']} stamped 0 (the "
          f"reference pose repeated), {skipped['not_after_previous']} not after the previous; "
          f"{len(summary['errors'])} bad lines")
    return 0


if __name__ == '__main__':
    sys.exit(main())
