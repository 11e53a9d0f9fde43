"""Fast paths between the nodes' high-rate messages and their CDR bytes (what DDS carries).

Decoding: subscriptions whose messages are decoded by rosbags' CDR decoder instead of rclpy's.
rclpy turns every received message into Python objects through each field's generated
Python setter (a Python __init__ per sub-message, a numpy array per covariance): ~100 us for an
Imu and ~270 us for an Odometry on the development machine, more than the nodes' own work.
rosbags (already the bag library) decodes the same bytes 3-5x faster into a message with the
same fields, read the same way (attribute access; fixed and numeric arrays as numpy arrays,
strings as str), so callbacks written for rclpy messages read these alike. They are for reading
only: copy fields out (numbers, strings, arrays), never assign a decoded sub-message into an
rclpy message (rclpy's converter expects its own classes).

Encoding: publishing an rclpy message converts it field by field back into C and serialises it
(~80 us for an Odometry). The stamped outputs published per input message (Imu, Odometry) are
a header, strings and a fixed block of float64 fields, so they are packed here directly into
little-endian CDR (XCDR1, as rmw_fastrtps writes) and published as bytes: the same message on
the wire, checked against rclpy's serialiser in test/test_cdr.py.
"""

from __future__ import annotations

import functools
import struct
from typing import Any, Callable, Sequence

import numpy as np
from rclpy.node import Node
from rclpy.qos import QoSProfile
from rclpy.serialization import deserialize_message

from sensing_nodes.bags.storage import TYPESTORE, type_name
from sensing_nodes.core.geometry import quaternion
from sensing_nodes.core.geometry.se2 import Pose2
from sensing_nodes.core.geometry.transform import Transform
from sensing_nodes.ros.conversions import PLANAR_IN_36

_CDR_LE = b'\x00\x01\x00\x00'   # encapsulation: plain CDR, little endian, no options
_STAMP = struct.Struct('<iI')
_LENGTH = struct.Struct('<I')
_IMU_DOUBLES = struct.Struct('<37d')      # orientation, covariance, rate, cov., accel., cov.
_ODOMETRY_DOUBLES = struct.Struct('<85d')  # pose (7), covariance (36), twist (6), cov. (36)
_TRANSFORM_DOUBLES = struct.Struct('<7d')  # translation, rotation (x, y, z, w)
_ONE = _LENGTH.pack(1)
_ZEROS_36 = (0.0,) * 36


def cdr_decoder(msg_class: type) -> Callable[[bytes], Any]:
    """A function decoding serialized (CDR) bytes of msg_class into a message with its fields.

    Big- and little-endian CDR are decoded by rosbags; bytes after the last field (Fast-CDR's
    padding before an empty sequence of doubles) are ignored, as rclpy does. Anything rosbags
    does not take goes through rclpy's own deserializer.
    """
    msgdef = TYPESTORE.get_msgdef(type_name(msg_class))
    cls = msgdef.cls
    decoders = {0: msgdef.deserialize_cdr_be, 1: msgdef.deserialize_cdr_le}

    def decode(raw: bytes) -> Any:
        decode_body = decoders.get(raw[1]) if len(raw) >= 4 and raw[0] == 0 else None
        if decode_body is not None:
            try:
                return decode_body(memoryview(raw)[4:], 0, cls, TYPESTORE)[0]
            except Exception:   # noqa: BLE001 - rclpy's deserializer decides (and says why)
                pass
        return deserialize_message(raw, msg_class)

    return decode


def create_decoded_subscription(node: Node, msg_class: type, topic: str,
                                callback: Callable[[Any], None], qos: QoSProfile | int,
                                on_error: Callable[[Exception], None] | None = None):
    """node.create_subscription(msg_class, topic, callback, qos), with messages decoded by
    cdr_decoder. A message neither decoder can read is passed to on_error (default: a warning
    in the node's log) and dropped; the node keeps running."""
    decode = cdr_decoder(msg_class)

    def report(error: Exception) -> None:
        node.get_logger().warn(f'{topic}: undecodable {msg_class.__name__} message dropped '
                               f'({error})', throttle_duration_sec=5.0)

    handle_error = on_error or report

    def on_raw(raw: bytes) -> None:
        try:
            msg = decode(raw)
        except Exception as error:  # noqa: BLE001 - bad input is reported, not fatal
            handle_error(error)
            return
        callback(msg)

    return node.create_subscription(msg_class, topic, on_raw, qos, raw=True)


def _stamped_prefix(stamp_ns: int, strings: tuple[str, ...], lead: bytes = b'') -> bytes:
    """Encapsulation, `lead` (4-byte fields before the header: a sequence's length), header
    stamp and the strings that follow it (frame ids), padded so the float64 fields after them
    start 8-aligned (CDR aligns relative to the encapsulation end)."""
    sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
    return _CDR_LE + lead + _STAMP.pack(sec, nanosec) + _strings(strings, len(lead) + 8)


@functools.lru_cache(maxsize=64)
def _strings(strings: tuple[str, ...], size: int) -> bytes:
    """CDR strings starting `size` bytes into the body, then padding to an 8-byte boundary (the
    same few frame ids in every message of a node: built once)."""
    parts = []
    for text in strings:
        data = text.encode() + b'\x00'
        pad = -size % 4
        parts += [b'\x00' * pad, _LENGTH.pack(len(data)), data]
        size += pad + 4 + len(data)
    parts.append(b'\x00' * (-size % 8))
    return b''.join(parts)


def imu_cdr(stamp_ns: int, frame_id: str, orientation: Sequence[float],
            orientation_covariance: Sequence[float], angular_velocity: Sequence[float],
            angular_velocity_covariance: Sequence[float], linear_acceleration: Sequence[float],
            linear_acceleration_covariance: Sequence[float]) -> bytes:
    """sensor_msgs/Imu as CDR bytes: quaternion (x, y, z, w), rates (rad/s), accelerations
    (m/s^2) and their 9-element row-major covariances."""
    return _stamped_prefix(stamp_ns, (frame_id,)) + _IMU_DOUBLES.pack(
        *orientation, *orientation_covariance, *angular_velocity, *angular_velocity_covariance,
        *linear_acceleration, *linear_acceleration_covariance)


def _planar_36(cov3) -> list[float]:
    """3x3 covariance over (x, y, yaw) -> 36 values of a 6x6 ROS covariance (rest zero)."""
    out = list(_ZEROS_36)
    for index, value in zip(PLANAR_IN_36, np.asarray(cov3, dtype=float).ravel().tolist()):
        out[index] = value
    return out


def odometry_cdr(stamp_ns: int, frame_id: str, child_frame_id: str, pose: Pose2,
                 pose_covariance, twist: tuple[float, float, float] = (0.0, 0.0, 0.0),
                 twist_covariance=None) -> bytes:
    """nav_msgs/Odometry as CDR bytes, the same message as conversions.make_odometry with the
    same arguments: planar pose (x, y, yaw) in frame_id with its 3x3 covariance, twist (vx, vy,
    wz) in child_frame_id with its 3x3 covariance (None: zero)."""
    return _stamped_prefix(stamp_ns, (frame_id, child_frame_id)) + _ODOMETRY_DOUBLES.pack(
        float(pose[0]), float(pose[1]), 0.0, *quaternion.from_yaw(float(pose[2])),
        *_planar_36(pose_covariance),
        float(twist[0]), float(twist[1]), 0.0, 0.0, 0.0, float(twist[2]),
        *(_ZEROS_36 if twist_covariance is None else _planar_36(twist_covariance)))


def transform_cdr(stamp_ns: int, parent: str, child: str, transform: Transform) -> bytes:
    """tf2_msgs/TFMessage of one transform as CDR bytes, the same message as
    tf.transform_message with the same arguments: the child frame's pose in the parent frame."""
    return _stamped_prefix(stamp_ns, (parent, child), _ONE) + _TRANSFORM_DOUBLES.pack(
        *(float(v) for v in transform.translation), *(float(v) for v in transform.rotation))


# -- stamps in CDR bytes (the recorder, the replay and the pipeline read them without decoding) --
# Every serialised message starts with a 4-byte encapsulation header; its second byte is 1 for
# little endian. A Header (or a Time) first: its stamp is the two 32-bit words after it. A
