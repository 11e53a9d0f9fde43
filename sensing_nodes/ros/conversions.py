"""Message <-> array conversion, written once for every node and bag tool.

Readers only use attribute access, so they work on rclpy messages and on messages that
rclpy.serialization.deserialize_message produced from a bag alike.
"""

from __future__ import annotations

import array
import math

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


# Keyframe-relative scan matches (/scan_match/keyframe_odom, docs/fusion.md): frame ids name a
# keyframe by its scan's stamp in ns, 'keyframe/<ns>'; 'keyframe/none' means no keyframe.
KEYFRAME_PREFIX = 'keyframe/'
NO_KEYFRAME = KEYFRAME_PREFIX + 'none'


def keyframe_frame_id(stamp_ns: int | None) -> str:
    """The frame id naming the keyframe taken at stamp_ns (None: no keyframe)."""
    return NO_KEYFRAME if stamp_ns is None else f'{KEYFRAME_PREFIX}{int(stamp_ns)}'


def _named_stamp(frame_id: str, prefix: str) -> int | None:
    """The stamp (ns) a frame id '<prefix><ns>' names; None for anything else."""
    digits = frame_id[len(prefix):] if frame_id.startswith(prefix) else ''
    return int(digits) if digits.isdigit() else None


def keyframe_stamp(frame_id: str) -> int | None:
    """The keyframe stamp (ns) a frame id 'keyframe/<ns>' names; None for anything else
    ('keyframe/none' included)."""
    return _named_stamp(frame_id, KEYFRAME_PREFIX)


# icp_matcher's local map (/scan_match/keyframe_odom in local_map mode, docs/fusion.md): the
# pose is base_link in the map's frame, 'map/<ns>', the map named by the stamp of its first scan.
MAP_PREFIX = 'map/'


def map_frame_id(stamp_ns: int) -> str:
    """The frame id naming the local map started at stamp_ns."""
    return f'{MAP_PREFIX}{int(stamp_ns)}'


def map_stamp(frame_id: str) -> int | None:
    """The map stamp (ns) a frame id 'map/<ns>' names; None for anything else."""
    return _named_stamp(frame_id, MAP_PREFIX)


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
