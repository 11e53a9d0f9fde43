"""Everything sensing_doctor reads from a bag, in one pass: every topic's header stamps and
record (receive) times in bag order, and the contents of the kinds it checks (JointState,
LaserScan, Imu, Odometry, TFMessage on /tf and /tf_static), found by type, as arrays.

Any bag the package reads (rosbag2 MCAP or sqlite3 folders, ROS 1 .bag files: bags/storage.py).
Stamps in int64 ns; nothing is sorted or dropped here (the checks judge order and values), except
a JointState sample without a position for each of the first sample's joints (counted in
`notes`) and scans whose beam layout differs from the topic's first (counted too).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
from numpy.typing import NDArray

from sensing_nodes.bags.sensor_streams import (
    IMU,
    JOINT_STATE,
    LASER_SCAN,
    ODOMETRY,
    ScanStream,
    SensorBagError,
)
from sensing_nodes.core.geometry.quaternion import yaw as quaternion_yaw

TF_MESSAGE = ('tf2_msgs/msg/TFMessage', 'tf2_msgs/TFMessage')
KINDS = {**{t: 'joints' for t in JOINT_STATE}, **{t: 'scan' for t in LASER_SCAN},
         **{t: 'imu' for t in IMU}, **{t: 'odom' for t in ODOMETRY},
         **{t: 'tf' for t in TF_MESSAGE}}


@dataclass
class TopicTimes:
    """One topic in bag order: header stamps (ns; the record time where the type has no
    header), record times (ns), type, and its kind ('' for types the doctor does not read)."""

    topic: str
    msgtype: str
    kind: str
    header_ns: NDArray[np.int64]
    record_ns: NDArray[np.int64]
    frame_id: str = ''
    has_header: bool = True


@dataclass
class JointStream:
    """JointState positions (J, n) rad of the first message's joint names, in bag order."""

    topic: str
    names: tuple[str, ...]
    t: NDArray[np.int64]
    position: NDArray[np.float64]


@dataclass
class ImuStream:
    """Imu samples in bag order: rates (K, 3) rad/s, accelerations (K, 3) m/s^2, orientation
    (K, 4) x y z w, and the first message's covariance diagonals (orientation, rate, accel)."""

    topic: str
    frame_id: str
    t: NDArray[np.int64]
    gyro: NDArray[np.float64]
    accel: NDArray[np.float64]
    orientation: NDArray[np.float64]
    orientation_cov: NDArray[np.float64]    # (K, 3) diagonal; [0] == -1: no orientation
    gyro_cov: NDArray[np.float64]           # (K, 3)
    accel_cov: NDArray[np.float64]          # (K, 3)


@dataclass
class OdomStream:
    """Odometry in bag order: pose (K, 3) x, y, yaw, z (K,), twist (K, 3) vx, vy, wz, and the
    covariance diagonals over x, y, yaw (pose (K, 3), twist (K, 3))."""

    topic: str
    frame_id: str
    child_frame_id: str
    t: NDArray[np.int64]
    pose: NDArray[np.float64]
    z: NDArray[np.float64]
    twist: NDArray[np.float64]
    pose_var: NDArray[np.float64]
    twist_var: NDArray[np.float64]


@dataclass
class TransformSample:
    """One transform of a TFMessage: parent, child, header stamp, record time, topic,
    translation (x, y, z) m and rotation (x, y, z, w)."""

    parent: str
    child: str
    stamp_ns: int
    record_ns: int
    static: bool
    translation: tuple[float, float, float]
    rotation: tuple[float, float, float, float]


@dataclass
class Survey:
    """What one bag holds for the doctor."""

    path: str
    topics: dict[str, tuple[str, int]]
    times: dict[str, TopicTimes] = field(default_factory=dict)
    joints: dict[str, JointStream] = field(default_factory=dict)
    scans: dict[str, ScanStream] = field(default_factory=dict)
    imus: dict[str, ImuStream] = field(default_factory=dict)
    odoms: dict[str, OdomStream] = field(default_factory=dict)
    transforms: list[TransformSample] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)

    @property
    def duration_s(self) -> float:
        ends = [(t.record_ns[0], t.record_ns[-1]) for t in self.times.values() if t.record_ns.size]
        if not ends:
            return 0.0
        return (max(e[1] for e in ends) - min(e[0] for e in ends)) * 1e-9


def _header_ns(msg) -> int | None:
    header = getattr(msg, 'header', None)
    if header is None:
        return None
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def _diag3(cov) -> tuple[float, float, float]:
    """x, y, yaw variances of a 6x6 row-major covariance."""
    return (float(cov[0]), float(cov[7]), float(cov[35]))


class _Collector:
    """Rows per topic while the bag is read; arrays at the end."""

    def __init__(self, survey: Survey) -> None:
        self.survey = survey
        self.stamps: dict[str, list[int]] = {}
        self.records: dict[str, list[int]] = {}
        self.rows: dict[str, list] = {}
        self.meta: dict[str, tuple] = {}

    def add_stamp(self, topic: str, record_ns: int, stamp: int | None) -> None:
        """A message the doctor only times (its header stamp read from the CDR bytes)."""
        self.stamps.setdefault(topic, []).append(record_ns if stamp is None else stamp)
        self.records.setdefault(topic, []).append(record_ns)
        self.meta.setdefault(topic, ('', stamp is not None))

    def add(self, topic: str, kind: str, record_ns: int, msg) -> None:
        stamp = _header_ns(msg)
        self.stamps.setdefault(topic, []).append(record_ns if stamp is None else stamp)
        self.records.setdefault(topic, []).append(record_ns)
        if topic not in self.meta:
            frame = msg.header.frame_id if stamp is not None else ''
            self.meta[topic] = (frame, stamp is not None)
        if kind == 'tf':
            for tr in msg.transforms:
                t, r = tr.transform.translation, tr.transform.rotation
                self.survey.transforms.append(TransformSample(
                    tr.header.frame_id.lstrip('/'), tr.child_frame_id.lstrip('/'),
                    _header_ns(tr), record_ns, topic == '/tf_static',
                    (t.x, t.y, t.z), (r.x, r.y, r.z, r.w)))
            return
        if kind:
            getattr(self, '_' + kind)(topic, stamp if stamp is not None else record_ns, msg)

    def _joints(self, topic: str, t: int, msg) -> None:
        names = self.meta.setdefault(topic + '#names', tuple(msg.name))
        if tuple(msg.name) == names and len(msg.position) == len(names):
            self.rows.setdefault(topic, []).append((t, list(msg.position)))
            return
        try:
            position = [msg.position[list(msg.name).index(n)] for n in names]
        except (ValueError, IndexError):
            self.survey.notes.append(f'{topic}: a sample at {t} ns lacks a position for one of '
                                     f'{list(names)}: left out')
            return
        self.rows.setdefault(topic, []).append((t, position))

    def _scan(self, topic: str, t: int, msg) -> None:
        layout = (float(msg.angle_min), float(msg.angle_increment), len(msg.ranges))
        meta = self.meta.setdefault(topic + '#scan', layout + (
            float(msg.range_min), float(msg.range_max), msg.header.frame_id,
            float(msg.time_increment)))
        if layout != meta[:3]:
            self.survey.notes.append(f'{topic}: a scan at {t} ns has another beam layout: '
                                     'left out')
            return
        self.rows.setdefault(topic, []).append((t, np.asarray(msg.ranges, dtype=float)))

    def _imu(self, topic: str, t: int, msg) -> None:
        g, a, q = msg.angular_velocity, msg.linear_acceleration, msg.orientation
        self.rows.setdefault(topic, []).append((
            t, (g.x, g.y, g.z), (a.x, a.y, a.z), (q.x, q.y, q.z, q.w),
            _diag3_imu(msg.orientation_covariance), _diag3_imu(msg.angular_velocity_covariance),
            _diag3_imu(msg.linear_acceleration_covariance)))

    def _odom(self, topic: str, t: int, msg) -> None:
        self.meta.setdefault(topic + '#frames', (msg.header.frame_id, msg.child_frame_id))
        p, q = msg.pose.pose.position, msg.pose.pose.orientation
        v, w = msg.twist.twist.linear, msg.twist.twist.angular
        self.rows.setdefault(topic, []).append((
            t, (p.x, p.y, quaternion_yaw((q.x, q.y, q.z, q.w))), p.z, (v.x, v.y, w.z),
            _diag3(msg.pose.covariance), _diag3(msg.twist.covariance)))

    def finish(self, kinds: dict[str, str]) -> None:
        s = self.survey
        for topic, stamps in self.stamps.items():
            frame, has_header = self.meta[topic]
            s.times[topic] = TopicTimes(topic, s.topics[topic][0], kinds.get(topic, ''),
                                        np.array(stamps, dtype=np.int64),
                                        np.array(self.records[topic], dtype=np.int64),
                                        frame, has_header)
        for topic, rows in self.rows.items():
            kind = kinds[topic]
            t = np.array([r[0] for r in rows], dtype=np.int64)
            if kind == 'joints':
                s.joints[topic] = JointStream(topic, self.meta[topic + '#names'], t,
                                              np.array([r[1] for r in rows], dtype=float))
            elif kind == 'scan':
                amin, inc, n, rmin, rmax, frame, time_increment = self.meta[topic + '#scan']
                s.scans[topic] = ScanStream(topic, t, np.array([r[1] for r in rows]),
                                            amin + inc * np.arange(n), rmin, rmax, frame,
                                            time_increment)
            elif kind == 'imu':
                cols = [np.array([r[i] for r in rows], dtype=float) for i in range(1, 7)]
                s.imus[topic] = ImuStream(topic, self.meta[topic][0], t, *cols)
            elif kind == 'odom':
                frame, child = self.meta[topic + '#frames']
                cols = [np.array([r[i] for r in rows], dtype=float) for i in range(1, 6)]
                s.odoms[topic] = OdomStream(topic, frame, child, t, *cols)


def _diag3_imu(cov) -> tuple[float, float, float]:
    """Diagonal of a 3x3 row-major covariance."""
    return (float(cov[0]), float(cov[4]), float(cov[8]))


def _messages(reader, path: Path, topics: dict[str, tuple[str, int]], kinds: dict[str, str]):
    """(topic, record ns, message or None, header stamp ns or None) in bag order. A rosbag2
    bag's messages are decoded by rosbags (several times faster than rclpy's Python message
    classes; the same field names, arrays as numpy arrays), those of kinds the doctor does not
    read are only timed (their header stamp read from the CDR bytes); a ROS 1 bag's come as
    rclpy messages."""
    from sensing_nodes.bags.stamps import first_field_type, leading_stamp_ns
    from sensing_nodes.bags.storage import TYPESTORE

    if path.is_file():
        for topic, record_ns, msg in reader.messages():
            yield topic, record_ns, msg, None
        return
    def has_header(msgtype: str) -> bool:
        try:
            return first_field_type(msgtype) == 'std_msgs/Header'
        except (ImportError, AttributeError, ValueError):   # a type without rclpy classes here
            return False

    headed = {t: has_header(ty) for t, (ty, _) in topics.items() if not kinds[t]}
    for topic, record_ns, raw in reader.raw():
        if not kinds[topic]:
            yield topic, record_ns, None, leading_stamp_ns(raw) if headed[topic] else None
        else:
            yield topic, record_ns, TYPESTORE.deserialize_cdr(raw, topics[topic][0]), None


def survey_bag(path: str | Path, progress: Callable[[str], None] | None = None) -> Survey:
    """Read the bag once (see the module doc); SensorBagError when it cannot be read."""
    from sensing_nodes.bags.storage import BagError, BagReader, failure_reason

    path = Path(path)
    try:
        reader = BagReader(path)
        topics = {t: (i.msgtype, i.count) for t, i in reader.topics.items()}
    except BagError as exc:
        raise SensorBagError(str(exc)) from None
    survey = Survey(str(path), topics)
    kinds = {t: KINDS.get(ty, '') for t, (ty, _) in topics.items()}
    collect = _Collector(survey)
    total = sum(n for _, n in topics.values())
    done, last_report = 0, time.monotonic()
    try:
        for topic, record_ns, msg, stamp in _messages(reader, path, topics, kinds):
            if msg is None:
                collect.add_stamp(topic, int(record_ns), stamp)
            else:
                collect.add(topic, kinds[topic], int(record_ns), msg)
            done += 1
            if progress is not None and time.monotonic() - last_report > 2.0:
                progress(f'read {done}/{total} messages ({100.0 * done / max(total, 1):.0f} %)')
                last_report = time.monotonic()
    except BagError as exc:
        raise SensorBagError(str(exc)) from None
    except Exception as exc:  # rosbags and rclpy raise several types for damaged messages
        raise SensorBagError(f'{path}: cannot read message {done + 1} '
                             f'({failure_reason(exc)}); truncated or damaged?') from None
    collect.finish(kinds)
    if not survey.times:
        raise SensorBagError(f'{path}: the bag holds no messages')
    return survey
