"""Rigid 3-D transforms (translation in m, unit-quaternion rotation) as TF holds them.

A `Transform` named parent -> child maps points in the child frame into the parent frame:
p_parent = rotation * p_child + translation (REP 105, tf2's convention).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from sensing_nodes.core.geometry import quaternion as quat
from sensing_nodes.core.geometry.se2 import Pose2, wrap_angle


@dataclass(frozen=True)
class Transform:
    """Pose of a child frame in its parent frame (m, unit quaternion x, y, z, w)."""

    translation: quat.Vec3 = (0.0, 0.0, 0.0)
    rotation: quat.Quat = quat.IDENTITY

    @staticmethod
    def from_planar(x: float, y: float, yaw: float) -> Transform:
        """A transform in the plane: (x, y) in m, yaw about z in rad."""
        return Transform((float(x), float(y), 0.0), (0.0, 0.0, math.sin(yaw / 2.0),
                                                     math.cos(yaw / 2.0)))

    def planar(self) -> Pose2:
        """(x, y, yaw) of the child frame in the parent frame, dropping z, roll and pitch."""
        return (self.translation[0], self.translation[1], wrap_angle(quat.yaw(self.rotation)))

    def compose(self, other: Transform) -> Transform:
        """self * other: other's child frame in self's parent frame."""
        moved = quat.rotate(self.rotation, other.translation)
        t = self.translation
        return Transform((t[0] + moved[0], t[1] + moved[1], t[2] + moved[2]),
                         quat.normalized(quat.multiply(self.rotation, other.rotation)))

    def inverse(self) -> Transform:
        """The parent frame's pose in the child frame."""
        back = quat.conjugate(self.rotation)
        t = quat.rotate(back, self.translation)
        return Transform((-t[0], -t[1], -t[2]), back)

    def distance_to(self, other: Transform) -> tuple[float, float]:
        """(translation distance in m, rotation angle in rad) between two transforms."""
        a, b = self.translation, other.translation
        return (math.dist(a, b), quat.angle_between(self.rotation, other.rotation))
