"""Message <-> array conversion, written once for every node and bag tool.

Readers only use attribute access, so they work on rclpy messages and on messages that
rclpy.serialization.deserialize_message produced from a bag alike.
"""

from __future__ import annotations

import array
import math
from dataclasses import dataclass

import numpy as np
from builtin_interfaces.msg import Time
from geometry_msgs.msg import Quaternion, TransformStamped
from nav_msgs.msg import Odometry
from numpy.typing import ArrayLike, NDArray

from sensing_nodes.core.geometry import quaternion
from sensing_nodes.core.geometry.scan import beam_angles
from sensing_nodes.core.geometry.se2 import Pose2
from sensing_nodes.core.geometry.transform import Transform

# Indices of x, y and yaw in a row-major 6x6 ROS covariance (x, y, z, roll, pitch, yaw), and
# of their 3x3 block's entries (row-major) among the 36 values.
_PLANAR = np.array([0, 1, 5])
PLANAR_IN_36 = (0, 1, 5, 6, 7, 11, 30, 31, 35)
_PLANAR_IN_36 = np.array(PLANAR_IN_36)


def stamp_to_ns(stamp) -> int:
    """builtin_interfaces/Time -> integer nanoseconds."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def ns_to_stamp(ns: int) -> Time:
    """Integer nanoseconds -> builtin_interfaces/Time."""
    sec, nanosec = divmod(int(ns), 1_000_000_000)
    return Time(sec=sec, nanosec=nanosec)


def yaw_to_quaternion(yaw: float, out: Quaternion | None = None) -> Quaternion:
    """Rotation about z by yaw (rad) as a unit quaternion; filled into `out` when given (a
    message refilled in place, where building a new one costs more than the numbers)."""
    x, y, z, w = quaternion.from_yaw(yaw)
    if out is None:
        return Quaternion(x=x, y=y, z=z, w=w)
    out.x, out.y, out.z, out.w = x, y, z, w
    return out


def quaternion_to_yaw(q) -> float:
    """Yaw (rad) of a quaternion, the z-axis part of its ZYX Euler angles."""
    return math.atan2(2.0 * (q.w * q.z + q.x * q.y), 1.0 - 2.0 * (q.y * q.y + q.z * q.z))


def planar_covariance_to_ros(cov3: ArrayLike) -> list[float]:
    """3x3 covariance over (x, y, yaw) -> 36-element ROS covariance; z, roll and pitch are
    exactly zero for a planar robot, so their rows stay 0."""
    cov6 = np.zeros((6, 6))
    cov6[np.ix_(_PLANAR, _PLANAR)] = np.asarray(cov3, dtype=float).reshape(3, 3)
    return cov6.ravel().tolist()


def ros_covariance_to_planar(cov36: ArrayLike) -> NDArray[np.float64]:
    """36-element ROS covariance -> 3x3 over (x, y, yaw)."""
    return np.asarray(cov36, dtype=float).reshape(36)[_PLANAR_IN_36].reshape(3, 3)


def make_odometry(
    stamp_ns: int,
    frame_id: str,
    child_frame_id: str,
    pose: Pose2,
    pose_covariance: ArrayLike,
    twist: tuple[float, float, float] = (0.0, 0.0, 0.0),
    twist_covariance: ArrayLike | None = None,
) -> Odometry:
    """nav_msgs/Odometry for a planar pose in frame_id and a twist (vx, vy, wz) in
    child_frame_id."""
    msg = Odometry()
    msg.header.stamp = ns_to_stamp(stamp_ns)
    msg.header.frame_id = frame_id
    msg.child_frame_id = child_frame_id
    msg.pose.pose.position.x = float(pose[0])
    msg.pose.pose.position.y = float(pose[1])
    msg.pose.pose.orientation = yaw_to_quaternion(float(pose[2]))
    msg.pose.covariance = planar_covariance_to_ros(pose_covariance)
    msg.twist.twist.linear.x = float(twist[0])
    msg.twist.twist.linear.y = float(twist[1])
    msg.twist.twist.angular.z = float(twist[2])
    if twist_covariance is not None:
        msg.twist.covariance = planar_covariance_to_ros(twist_covariance)
    return msg


def odometry_pose(msg) -> tuple[Pose2, NDArray[np.float64]]:
    """nav_msgs/Odometry -> planar pose (x, y, yaw) and its 3x3 covariance."""
    p = msg.pose.pose
    pose = (float(p.position.x), float(p.position.y), quaternion_to_yaw(p.orientation))
    return pose, ros_covariance_to_planar(msg.pose.covariance)


def odometry_twist(msg) -> tuple[tuple[float, float, float], NDArray[np.float64]]:
    """nav_msgs/Odometry -> twist (vx, vy, wz) in the child frame and its 3x3 covariance."""
    t = msg.twist.twist
    twist = (float(t.linear.x), float(t.linear.y), float(t.angular.z))
    return twist, ros_covariance_to_planar(msg.twist.covariance)


def float32_array(values: ArrayLike) -> array.array:
    """Numpy values -> array('f'), the fast path for float32[] message fields."""
    out = array.array('f')
    out.frombytes(np.ascontiguousarray(values, dtype=np.float32).tobytes())
    return out


def scan_arrays(msg) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """sensor_msgs/LaserScan -> (ranges, angles) as float64 arrays of equal length (rad, m)."""
    ranges = np.asarray(msg.ranges, dtype=float)
    return ranges, beam_angles(msg.angle_min, msg.angle_increment, ranges.size)


# icp_matcher's matches for the fusion (/scan_match/keyframe_odom;
# docs/fusion.md, "The scan matcher's input"): base_link's pose in a reference frame with a
# stable name, the local map (local_map mode) or base_link at the keyframe's scan (keyframe
# mode). A message whose child_frame_id is that frame starts the next reference at its stamp
# (a new map, its pose zero: base_link there is the map's origin; or the next keyframe, this
# scan); every other message is in the reference the latest such message started, in the
# order they were published.
SCAN_MATCH_MAP_FRAME = 'scan_match_map'
SCAN_MATCH_KEYFRAME_FRAME = 'scan_match_keyframe'
SCAN_MATCH_FRAMES = (SCAN_MATCH_MAP_FRAME, SCAN_MATCH_KEYFRAME_FRAME)
# pose.covariance[0] of a message that carries no match ("not provided", as REP 145 marks an
# Imu field): the scan was not matched, or only starts a keyframe.
NOT_MATCHED = -1.0


@dataclass(frozen=True)
class ScanMatchReference:
    """What one /scan_match/keyframe_odom message is relative to: a local map (`in_map`) or a
    keyframe, named by the stamp (ns) of its first scan (`reference_ns`; None: it started before
    the stream was heard); whether the message starts the next one at its stamp (`starts`) and
    carries a match (`matched`: its pose in the reference, with a covariance)."""

    in_map: bool
    reference_ns: int | None
    starts: bool
    matched: bool


class ScanMatchReferences:
    """Reads /scan_match/keyframe_odom in the order published and names the map or keyframe
    each message is relative to: the stamp of the latest message that started one (a message
    that starts one counts even where its match is refused). Messages of the encoding before the
    stable frames (bags recorded then: the stamp inside the frame ids) are read too."""

    def __init__(self, silence_s: float = 0.0) -> None:
        self._current: tuple[bool, int] | None = None     # (in a map, its stamp ns)
        # After the matcher was silent longer than this (the fusion's input_timeout_s; 0: never),
        # a message that starts nothing names a map or keyframe of its own (its stamp): the
        # matcher may have been restarted, and the message that started its present map sent
        # before this subscription had matched the new publisher (never received).
        self._silence_ns = round(silence_s * 1e9)
        self._last_ns: int | None = None

    def read(self, msg) -> tuple[ScanMatchReference | None, str]:
        """The reference of one message (nav_msgs/Odometry), or (None, why not)."""
        frame, child = msg.header.frame_id, msg.child_frame_id
        stamp = stamp_to_ns(msg.header.stamp)
        if frame.startswith(_OLD_PREFIXES):
            return _old_reference(frame, child, stamp)
        if frame not in SCAN_MATCH_FRAMES:
            return None, (f"frame_id '{frame}' is neither {SCAN_MATCH_MAP_FRAME} nor "
                          f'{SCAN_MATCH_KEYFRAME_FRAME}')
        in_map, starts = frame == SCAN_MATCH_MAP_FRAME, child == frame
        silent = (self._silence_ns > 0 and self._last_ns is not None
                  and stamp - self._last_ns > self._silence_ns)
        self._last_ns = stamp
        if silent and not starts:
            self._current = (in_map, stamp)
        current = self._current
        reference = current[1] if current is not None and current[0] == in_map else None
        if starts:
            self._current = (in_map, stamp)
        if in_map and starts:       # a new map: base_link here is its origin
            return ScanMatchReference(True, stamp, True, False), ''
        return ScanMatchReference(in_map, reference, starts,
                                  float(msg.pose.covariance[0]) != NOT_MATCHED), ''


# The encoding before the stable frames: 'map/<stamp ns>', 'keyframe/<stamp ns>' (the reference
# named in frame_id; a child_frame_id naming the message's own stamp starts it) and
# 'keyframe/none' (no match).
_OLD_MAP, _OLD_KEYFRAME = 'map/', 'keyframe/'
_OLD_PREFIXES = (_OLD_MAP, _OLD_KEYFRAME)


def _old_stamp(frame_id: str, prefix: str) -> int | None:
    """The stamp (ns) a frame id '<prefix><ns>' of the old encoding names; None for anything
    else."""
    digits = frame_id[len(prefix):] if frame_id.startswith(prefix) else ''
    return int(digits) if digits.isdigit() else None


def _old_reference(frame: str, child: str, stamp: int) -> tuple[ScanMatchReference | None, str]:
    """The reference of a message of the old encoding, or (None, why not)."""
    local_map, keyframe = _old_stamp(frame, _OLD_MAP), _old_stamp(frame, _OLD_KEYFRAME)
    if local_map is not None:
        starts = child == frame
        return ScanMatchReference(True, local_map, starts, not starts), ''
    if keyframe is None and frame != _OLD_KEYFRAME + 'none':
        return None, (f"frame_id '{frame}' names no keyframe or map ('keyframe/<stamp ns>', "
                      "'map/<stamp ns>' or 'keyframe/none')")
    return ScanMatchReference(False, keyframe, _old_stamp(child, _OLD_KEYFRAME) == stamp,
                              keyframe is not None), ''


def make_transform_stamped(stamp_ns: int, parent: str, child: str,
                           transform: Transform) -> TransformStamped:
    """geometry_msgs/TransformStamped: the child frame's pose in the parent frame at stamp_ns."""
    msg = TransformStamped()
    msg.header.stamp = ns_to_stamp(stamp_ns)
    msg.header.frame_id = parent
    msg.child_frame_id = child
    t, q = msg.transform.translation, msg.transform.rotation
    t.x, t.y, t.z = (float(v) for v in transform.translation)
    q.x, q.y, q.z, q.w = (float(v) for v in transform.rotation)
    return msg


def transform_of(msg) -> Transform:
    """geometry_msgs/Transform (or TransformStamped's .transform) -> Transform, unchecked."""
    t, q = msg.translation, msg.rotation
    return Transform((float(t.x), float(t.y), float(t.z)),
                     (float(q.x), float(q.y), float(q.z), float(q.w)))
