"""Raw sensor streams of a bag as arrays, for the offline tools (sensing_calibrate,
sensing_characterize): rosbag2 folders and ROS 1 .bag files alike (rosbags' AnyReader), topics
found by type, header stamps in int64 ns, progress on long bags.

Non-finite encoder or IMU values are bad input (SensorBagError naming topic and stamp); scan
ranges keep their REP 117 values (NaN, +-inf mean no measurement).
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
from numpy.typing import NDArray

from sensing_nodes.topics import SCAN

JOINT_STATE = ('sensor_msgs/msg/JointState', 'sensor_msgs/JointState')
LASER_SCAN = ('sensor_msgs/msg/LaserScan', 'sensor_msgs/LaserScan')
IMU = ('sensor_msgs/msg/Imu', 'sensor_msgs/Imu')
ODOMETRY = ('nav_msgs/msg/Odometry', 'nav_msgs/Odometry')
GROUND_TRUTH = '/ground_truth/odom'
_DESCRIPTIONS = {'joints': 'wheel encoders (sensor_msgs/JointState)',
                 'scan': 'laser scans (sensor_msgs/LaserScan)', 'imu': 'IMU (sensor_msgs/Imu)',
                 'truth': f'ground truth ({GROUND_TRUTH})'}
EXIT_BAD_INPUT = 2


class SensorBagError(Exception):
    """The bag cannot give what a tool needs; the message says what and where."""


@dataclass
class ScanStream:
    """LaserScans: stamps (S,) ns, ranges (S, B) float (REP 117 values kept), beam angles (B,)
    rad in the laser frame, range limits (m), frame id, and the time between beams (s,
    LaserScan.time_increment of the first scan; 0: every beam taken at the stamp)."""

    topic: str
    t: NDArray[np.int64]
    ranges: NDArray[np.float64]
    angles: NDArray[np.float64]
    range_min: float
    range_max: float
    frame_id: str
    time_increment_s: float = 0.0

    def beam_times(self, beam_index: NDArray[np.intp]) -> NDArray[np.float64] | None:
        """When each beam was taken (s after the stamp), or None when all at the stamp."""
        if not self.time_increment_s > 0.0:
            return None
        return np.asarray(beam_index, dtype=float) * self.time_increment_s


@dataclass
class SensorData:
    """What one bag holds for calibration and characterisation (None: absent)."""

    path: str
    topics: dict[str, tuple[str, int]]                  # topic -> (type, count)
    joint_topic: str | None = None
    joint_names: tuple[str, ...] = ()
    joint_t: NDArray[np.int64] | None = None
    joint_position: NDArray[np.float64] | None = None  # (J, n joints) rad
    scans: ScanStream | None = None
    imu_topic: str | None = None
    imu_t: NDArray[np.int64] | None = None
    imu_gyro: NDArray[np.float64] | None = None         # (K, 3) rad/s
    imu_accel: NDArray[np.float64] | None = None        # (K, 3) m/s^2
    truth_t: NDArray[np.int64] | None = None
    truth_pose: NDArray[np.float64] | None = None       # (N, 3) x, y, yaw
    notes: list[str] = field(default_factory=list)


def _stamp(msg, fallback: int) -> int:
    header = getattr(msg, 'header', None)
    if header is None:
        return fallback
    ns = int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)
    return ns if ns > 0 else fallback


def _choose(topics: dict[str, tuple[str, int]], types: tuple[str, ...], wanted: str | None,
            preferred: tuple[str, ...], exclude: tuple[str, ...] = ()) -> str | None:
    """The topic to read for a message type: the one asked for, a preferred name, or the
    busiest topic of that type."""
    if wanted:
        if wanted not in topics:
            raise SensorBagError(f'topic {wanted} is not in the bag')
        if topics[wanted][0] not in types:
            raise SensorBagError(f'topic {wanted} holds {topics[wanted][0]}, not {types[0]}')
        return wanted
    candidates = [t for t, (ty, n) in topics.items() if ty in types and n > 0 and t not in exclude]
    for name in preferred:
        if name in candidates:
            return name
    return max(candidates, key=lambda t: topics[t][1]) if candidates else None


@contextmanager
def _open(path: Path):
    """(topics: topic -> (type, count), messages(topics) -> iterator of (topic, bag ns, msg)):
    a rosbag2 folder or a ROS 1 .bag file, through the package's one bag reader."""
    from sensing_nodes.bags.storage import BagError, BagReader

    try:
        reader = BagReader(path)
    except BagError as exc:
        raise SensorBagError(str(exc)) from None
    yield ({t: (i.msgtype, i.count) for t, i in reader.topics.items()},
           lambda wanted: reader.messages(wanted))


def read_sensor_bag(path: str | Path, *, joint_topic: str | None = None,
                    scan_topic: str | None = None, imu_topic: str | None = None,
                    want: tuple[str, ...] = ('joints', 'scan', 'imu', 'truth'),
                    required: tuple[str, ...] = (), purpose: str = '',
                    progress: Callable[[str], None] | None = None) -> SensorData:
    """Read the streams named in `want` from a rosbag2 folder or ROS 1 .bag file; the kinds in
    `required` must be there (SensorBagError naming what is missing for `purpose`, raised
    before any message is read)."""
    path = Path(path)
    if not path.exists():
        raise SensorBagError(f'{path}: no such bag')
    with _open(path) as (topics, messages):
        data = SensorData(str(path), topics)
        chosen = _choose_streams(topics, want, joint_topic, scan_topic, imu_topic)
        missing = [_DESCRIPTIONS[kind] for kind in required if kind not in chosen.values()]
        if missing:
            raise SensorBagError(f'{path} has no {" and no ".join(missing)}: {purpose} '
                                 f'(topics: {_topic_list(topics)})')
        rows = _StreamRows(data.notes)
        total = sum(topics[t][1] for t in chosen)
        done, last_report = 0, time.monotonic()
        for topic, timestamp, msg in (messages(list(chosen)) if chosen else ()):
            if not rows.add(chosen[topic], _stamp(msg, int(timestamp)), msg):
                continue
            done += 1
            if progress is not None and time.monotonic() - last_report > 2.0:
                progress(f'read {done}/{total} messages ({100.0 * done / max(total, 1):.0f} %)')
                last_report = time.monotonic()
    rows.fill(data, {kind: topic for topic, kind in chosen.items()})
    return data


def _choose_streams(topics: dict[str, tuple[str, int]], want: tuple[str, ...],
                    joint_topic: str | None, scan_topic: str | None,
                    imu_topic: str | None) -> dict[str, str]:
    """topic -> kind ('joints', 'scan', 'imu', 'truth') of the streams to read."""
    chosen: dict[str, str] = {}
    for kind, types, asked, preferred in (
            ('joints', JOINT_STATE, joint_topic, ('/joint_states',)),
            ('scan', LASER_SCAN, scan_topic, (SCAN,)),
            ('imu', IMU, imu_topic, ('/imu/data_raw', '/imu', '/imu/data'))):
        if kind in want:
            topic = _choose(topics, types, asked, preferred)
            if topic:
                chosen[topic] = kind
    if 'truth' in want and topics.get(GROUND_TRUTH, ('', 0))[0] in ODOMETRY:
        chosen[GROUND_TRUTH] = 'truth'
    return chosen


class _StreamRows:
    """Rows of each stream as the bag is read (stamp ns, values), then its arrays."""

    def __init__(self, notes: list[str]) -> None:
        self.rows: dict[str, list] = {'joints': [], 'scan': [], 'imu': [], 'truth': []}
        self.notes = notes
        self.scan_meta: tuple | None = None
        self.names: tuple[str, ...] = ()

    def add(self, kind: str, t: int, msg) -> bool:
        """Take one message of a stream; False when it is skipped."""
        if kind == 'joints':
            return self._joints(t, msg)
        if kind == 'scan':
            return self._scan(t, msg)
        if kind == 'imu':
            g, a = msg.angular_velocity, msg.linear_acceleration
            self.rows['imu'].append((t, (g.x, g.y, g.z), (a.x, a.y, a.z)))
        else:
            p, q = msg.pose.pose.position, msg.pose.pose.orientation
            yaw = np.arctan2(2.0 * (q.w * q.z + q.x * q.y), 1.0 - 2.0 * (q.y * q.y + q.z * q.z))
            self.rows['truth'].append((t, (p.x, p.y, float(yaw))))
        return True

    def _joints(self, t: int, msg) -> bool:
        """Positions in the first message's joint order; skipped: a sample without them all."""
        if not self.names:
            self.names = tuple(msg.name)
        if tuple(msg.name) != self.names:
            order = [list(msg.name).index(n) if n in msg.name else -1 for n in self.names]
            if min(order) < 0:
                return False
            position = [msg.position[i] for i in order]
        else:
            position = list(msg.position)
        if len(position) != len(self.names):
            return False                       # velocity-only or malformed sample
        self.rows['joints'].append((t, position))
        return True

    def _scan(self, t: int, msg) -> bool:
        """Ranges of scans with the first one's beam layout; another layout is skipped."""
        meta = (float(msg.angle_min), float(msg.angle_increment), len(msg.ranges),
                float(msg.range_min), float(msg.range_max), msg.header.frame_id,
                float(msg.time_increment))
        if self.scan_meta is None:
            self.scan_meta = meta
        if meta[:3] != self.scan_meta[:3]:
            self.notes.append(f'a scan at {t} ns has another beam layout: skipped')
            return False
        self.rows['scan'].append((t, np.asarray(msg.ranges, dtype=float)))
        return True

    def fill(self, data: SensorData, by_kind: dict[str, str]) -> None:
        """The streams' arrays (sorted by stamp) into data; SensorBagError for non-finite
        encoder or IMU values."""
        rows = self.rows
        if rows['joints']:
            t, pos = _sorted(rows['joints'], 1)
            bad = ~np.isfinite(pos).all(axis=1)
            if bad.any():
                raise SensorBagError(f'{by_kind["joints"]}: non-finite wheel position at stamp '
                                     f'{int(t[bad][0])} ns ({int(bad.sum())} samples)')
            data.joint_topic, data.joint_names, data.joint_t, data.joint_position = \
                by_kind['joints'], self.names, t, pos
        if rows['scan']:
            t, ranges = _sorted(rows['scan'], 1)
            amin, inc, n, rmin, rmax, frame, time_increment = self.scan_meta
            data.scans = ScanStream(by_kind['scan'], t, ranges, amin + inc * np.arange(n),
                                    rmin, rmax, frame, time_increment)
        if rows['imu']:
            t, gyro, accel = _sorted(rows['imu'], 2)
            bad = ~(np.isfinite(gyro).all(axis=1) & np.isfinite(accel).all(axis=1))
            if bad.any():
                raise SensorBagError(f'{by_kind["imu"]}: non-finite IMU values at stamp '
                                     f'{int(t[bad][0])} ns ({int(bad.sum())} samples)')
            data.imu_topic, data.imu_t, data.imu_gyro, data.imu_accel = \
                by_kind['imu'], t, gyro, accel
        if rows['truth']:
            data.truth_t, data.truth_pose = _sorted(rows['truth'], 1)


def _sorted(rows: list[tuple], columns: int) -> tuple[NDArray, ...]:
    """(stamps int64, then each value column as a float array) of rows (stamp, values...),
    in stamp order (stable: equal stamps keep the bag's order)."""
    t = np.array([r[0] for r in rows], dtype=np.int64)
    order = np.argsort(t, kind='stable')
    values = [np.array([r[1 + c] for r in rows], dtype=float)[order] for c in range(columns)]
    return (t[order], *values)


def read_yaw_track(path: str | Path, topic: str) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """Header stamps (int64 ns) and yaw (rad) of an Odometry topic, in bag order; a missing or
    non-Odometry topic, or a non-finite yaw, is SensorBagError."""
    from sensing_nodes.core.geometry.quaternion import yaw as quaternion_yaw

    path = Path(path)
    if not path.exists():
        raise SensorBagError(f'{path}: no such bag')
    with _open(path) as (topics, messages):
        if topic not in topics or topics[topic][0] not in ODOMETRY:
            raise SensorBagError(f'{path}: no nav_msgs/Odometry topic {topic} (topics: '
                                 f'{_topic_list(topics)})')
        t, yaw = [], []
        for _, bag_ns, msg in messages([topic]):
            q = msg.pose.pose.orientation
            value = quaternion_yaw((q.x, q.y, q.z, q.w))
            stamp = _stamp(msg, bag_ns)
            if not np.isfinite(value):
                raise SensorBagError(f'{topic}: yaw is not finite at {stamp * 1e-9:.3f} s')
            t.append(stamp)
            yaw.append(value)
    return np.array(t, dtype=np.int64), np.array(yaw, dtype=float)


def _topic_list(topics: dict[str, tuple[str, int]]) -> str:
    return '; '.join(f'{t} ({ty}, {n})' for t, (ty, n) in sorted(topics.items()))


def describe_topics(data: SensorData) -> str:
    """Every topic of the bag: name, type, count (for error messages)."""
    return _topic_list(data.topics)


def atomic_write(path: str | Path, write: Callable[[Path], None]) -> None:
    """Write through a temporary file in the same folder, renamed over `path` only when
    write(tmp) returned: a failure leaves no partial file."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(dir=path.parent if str(path.parent) else '.',
                               prefix=f'.{path.name}.', suffix=path.suffix)
    os.close(fd)
    try:
        write(Path(tmp))
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def add_scan_source(parser: argparse.ArgumentParser, index_help: str) -> None:
    """The plots' scan source: --carmen LOG or --bag BAG (with --topic), and --index."""
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument('--carmen', help='CARMEN log (.log or .log.gz)')
    source.add_argument('--bag', help='bag with LaserScan messages: a rosbag2 folder or a '
                        'ROS 1 .bag file')
    parser.add_argument('--topic', default=SCAN, help='LaserScan topic in the bag')
    parser.add_argument('--index', type=int, default=0, help=index_help)


def stderr_progress(prefix: str) -> Callable[[str], None]:
    """A progress callback printing `prefix: text` on stderr."""
    def report(text: str) -> None:
        print(f'{prefix}: {text}', file=sys.stderr, flush=True)
    return report
