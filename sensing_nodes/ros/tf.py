"""/tf and /tf_static without tf2_ros (not on PyPI): broadcasters, and the static transforms a node
needs to know where its sensors sit on the robot.

Dynamic lookups (interpolating /tf over time) are out of scope: the nodes only need mounts, which
are static.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np
from rclpy.node import Node
from tf2_msgs.msg import TFMessage

from sensing_nodes.core.geometry import quaternion as quat
from sensing_nodes.core.geometry.imu_mount import is_identity, mount_rotation
from sensing_nodes.core.geometry.transform import Transform
from sensing_nodes.ros.conversions import make_transform_stamped, transform_of
from sensing_nodes.ros.logging import ThrottledWarnings
from sensing_nodes.ros.qos import TF_QOS, TF_STATIC_QOS, TF_STATIC_READER_QOS
from sensing_nodes.topics import TF, TF_STATIC

TF_TOPIC = TF
TF_STATIC_TOPIC = TF_STATIC

# A mount from /tf_static that differs from the parameters by more than this is warned about.
MOUNT_TOLERANCE_M = 1e-3
MOUNT_TOLERANCE_RAD = math.radians(0.1)


def frame_name(frame_id: str) -> str:
    """A frame id without ROS 1's leading slash (tf2 in ROS 2 rejects it)."""
    return frame_id.lstrip('/')


def transform_message(stamp_ns: int, parent: str, child: str, transform: Transform) -> TFMessage:
    """The /tf message of one transform: the child frame's pose in the parent frame at stamp_ns."""
    return TFMessage(transforms=[make_transform_stamped(stamp_ns, parent, child, transform)])


class TransformBroadcaster:
    """Publishes transforms on /tf, as tf2_ros.TransformBroadcaster."""

    def __init__(self, node: Node) -> None:
        self._publisher = node.create_publisher(TFMessage, TF_TOPIC, TF_QOS)

    def send(self, stamp_ns: int, parent: str, child: str, transform: Transform) -> None:
        """Broadcast the child frame's pose in the parent frame at stamp_ns."""
        self._publisher.publish(transform_message(stamp_ns, parent, child, transform))


class StaticTransformBroadcaster:
    """Publishes static transforms on /tf_static, transient local, as
    tf2_ros.StaticTransformBroadcaster: every message holds all of this node's static transforms,
    so a late subscriber gets them all from the one message it is sent."""

    def __init__(self, node: Node) -> None:
        self._publisher = node.create_publisher(TFMessage, TF_STATIC_TOPIC, TF_STATIC_QOS)
        self._transforms: dict[str, object] = {}

    def send(self, stamp_ns: int, parent: str, child: str, transform: Transform) -> None:
        """Add or replace the static transform of child and publish the whole set."""
        self._transforms[child] = make_transform_stamped(stamp_ns, parent, child, transform)
        self._publisher.publish(TFMessage(transforms=list(self._transforms.values())))


class StaticTransformBuffer:
    """The newest static transform of each child frame heard on /tf_static, and lookups along
    the tree they form. A transform with a non-finite value or a quaternion that is not unit is
    refused with a warning and counted (`rejected`); one close to unit is normalised."""

    def __init__(self, node: Node, on_update: Callable[[], None] | None = None,
                 diagnostics=None) -> None:
        self._node = node
        self._on_update = on_update
        self._diagnostics = diagnostics   # ros.diagnostics.Diagnostics: counts tf_static_rejected
        self._parents: dict[str, tuple[str, Transform]] = {}
        self.rejected = 0
        self._warnings = ThrottledWarnings(node, period_s=5.0)   # node clock: follows /clock
        node.create_subscription(TFMessage, TF_STATIC_TOPIC, self._on_message,
                                 TF_STATIC_READER_QOS)

    def _on_message(self, msg: TFMessage) -> None:
        changed = False
        for stamped in msg.transforms:
            parent = frame_name(stamped.header.frame_id)
            child = frame_name(stamped.child_frame_id)
            transform = transform_of(stamped.transform)
            problem = _problem(parent, child, transform)
            if problem:
                self.rejected += 1
                if self._diagnostics is not None:
                    self._diagnostics.count('tf_static_rejected')
                self._warnings.warn(f'{parent} -> {child}',
                                    f'ignoring /tf_static {parent!r} -> {child!r}: {problem}')
                continue
            transform = Transform(transform.translation, quat.normalized(transform.rotation))
            if self._parents.get(child) != (parent, transform):
                self._parents[child] = (parent, transform)
                changed = True
        if changed and self._on_update is not None:
            self._on_update()

    def lookup(self, target: str, source: str) -> Transform | None:
        """Pose of frame source in frame target (maps source points into target), or None when
        the static tree does not connect them."""
        target, source = frame_name(target), frame_name(source)
        up_source = self._chain(source)
        up_target = self._chain(target)
        common = next((frame for frame in up_source if frame in up_target), None)
        if common is None:
            return None
        return up_target[common].inverse().compose(up_source[common])

    def _chain(self, frame: str) -> dict[str, Transform]:
        """Every ancestor of frame (itself included) -> frame's pose in that ancestor."""
        chain = {frame: Transform()}
        pose = Transform()
        while frame in self._parents and len(chain) <= len(self._parents):
            parent, step = self._parents[frame]
            if parent in chain:                   # a loop in the tree: stop at the repeat
                break
            pose = step.compose(pose)
            chain[parent] = pose
            frame = parent
        return chain


def _problem(parent: str, child: str, transform: Transform) -> str:
    if not parent or not child:
        return 'empty frame id'
    if parent == child:
        return 'a frame cannot be its own parent'
    if not all(math.isfinite(v) for v in transform.translation):
        return f'non-finite translation {transform.translation}'
    if not quat.is_unit(transform.rotation):
        return f'rotation {transform.rotation} is not a unit quaternion'
    return ''


class SensorMount:
    """Where a sensor frame sits in the base frame: /tf_static's answer when it has one, else
    the node's mount parameters. A disagreement between the two is warned about once."""

    def __init__(self, node: Node, buffer: StaticTransformBuffer, base_frame: str,
                 parameters: Transform, what: str, compare_translation: bool = True) -> None:
        self._node = node
        self._compare_translation = compare_translation
        self._buffer = buffer
        self._base_frame = base_frame
        self.parameters = parameters
        self._what = what
        self._reported: set[tuple[str, Transform]] = set()

    def from_tf(self, sensor_frame: str) -> Transform | None:
        """The mount of sensor_frame (the frame id of the message at hand) in the base frame
        from /tf_static, or None when /tf_static does not give it: use the parameters then."""
        if frame_name(sensor_frame) == frame_name(self._base_frame):
            return Transform()
        from_tf = self._buffer.lookup(self._base_frame, sensor_frame) if sensor_frame else None
        if from_tf is not None:
            self._report(sensor_frame, from_tf)
        return from_tf

    def _report(self, sensor_frame: str, from_tf: Transform) -> None:
        """Log a mount from TF once, as a warning where it contradicts the parameters."""
        key = (sensor_frame, from_tf)
        if key in self._reported:
            return
        self._reported.add(key)
        distance, angle = from_tf.distance_to(self.parameters)
        if not self._compare_translation:
            distance = 0.0
        x, y, yaw = from_tf.planar()
        text = (f'{self._what} mount from /tf_static: {self._base_frame} -> {sensor_frame} '
                f'x={x:.4f} m y={y:.4f} m yaw={math.degrees(yaw):.3f} deg')
        if distance > MOUNT_TOLERANCE_M or angle > MOUNT_TOLERANCE_RAD:
            px, py, pyaw = self.parameters.planar()
            self._node.get_logger().warning(
                f'{text} disagrees with the mount parameters (x={px:.4f} m y={py:.4f} m '
                f'yaw={math.degrees(pyaw):.3f} deg; {distance * 1000:.1f} mm, '
                f'{math.degrees(angle):.2f} deg apart): using /tf_static')
        else:
            self._node.get_logger().info(text)


@dataclass
class ImuMount:
    """Which rotation turns an IMU frame's readings into base_frame's axes, and the frame the
    output is in: /tf_static's mount of the message's frame where `from_tf` gives one, else the
    mount parameters' rotation."""

    parameters: np.ndarray          # 3x3, from mount_*_rad
    base_frame: str
    output_frame: str               # frame_id parameter; '' = decided by the rotation
    from_tf: Callable[[str], Transform | None] | None = None

    def resolve(self, imu_frame: str) -> tuple[np.ndarray | None, str]:
        """(rotation into base_frame or None for none, output frame) for messages in imu_frame."""
        found = self.from_tf(imu_frame) if self.from_tf is not None else None
        rotation = self.parameters if found is None else \
            mount_rotation(*quat.to_rpy(found.rotation))
        if is_identity(rotation):
            rotation = None
        return rotation, self.output_frame or (self.base_frame if rotation is not None
                                               else imu_frame)


def imu_mount(node: Node, base_frame: str, roll_pitch_yaw: tuple[float, float, float],
              output_frame: str = '', on_update: Callable[[], None] | None = None,
              diagnostics=None) -> ImuMount:
    """A node's IMU mount: /tf_static's base_frame -> the Imu's frame_id where published (read
    by a StaticTransformBuffer of the node's own; on_update is called when it changes), else
    the mount_*_rad parameters' rotation; a disagreement is warned about once."""
    sensor = SensorMount(node, StaticTransformBuffer(node, on_update, diagnostics), base_frame,
                         Transform(rotation=quat.from_rpy(*roll_pitch_yaw)), 'IMU',
                         compare_translation=False)   # the mount parameters are a rotation only
    return ImuMount(mount_rotation(*roll_pitch_yaw), base_frame, output_frame, sensor.from_tf)
