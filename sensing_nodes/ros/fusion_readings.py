"""Messages of the fusion's inputs -> validated core Readings, for the fusion node and for
tools that run the fusion core over a bag (one conversion, one set of acceptance rules).

Inputs: 'wheel_odom' (nav_msgs/Odometry), 'imu' (sensor_msgs/Imu: gyro_integrator's heading,
the IMU's own orientation, or its raw rate, with the IMU mount rotation), 'scan_match'
(nav_msgs/Odometry: matches in a local map or against a keyframe for the EKF, cumulative poses
for the complementary filter). Poses in m and rad, stamps in ns. An EKF input's delay_s retimes its
messages here, in one place: a message stamped t describes the robot at t - delay_s
(`ReadingConverter.stamp_ns`, and the keyframes a match names).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from sensing_nodes.core.fusion.config import SessionConfig
from sensing_nodes.core.fusion.inputs import IMU, SCAN, DeltaAngles, InputConfig, Reading
from sensing_nodes.core.fusion.timeline import InputRecord
from sensing_nodes.core.fusion.validation import covariance_problem, pose_problem
from sensing_nodes.core.geometry.imu_mount import base_orientation, mount_rotation, to_base
from sensing_nodes.ros.conversions import (
    ScanMatchReferences,
    odometry_pose,
    odometry_twist,
    quaternion_to_yaw,
    stamp_to_ns,
)


def _yaw_only(variance: float) -> NDArray[np.float64]:
    """3x3 covariance over (x, y, yaw) with only the yaw variance: np.diag([0, 0, variance]),
    built without np.diag's generality (two per IMU message, 5 us each)."""
    out = np.zeros((3, 3))
    out[2, 2] = variance
    return out


def unit_quaternion(q) -> bool:
    """Finite and of unit length (within 1 %): an infinite or all-zero orientation still gives
    a finite yaw from atan2, but it is no rotation at all."""
    norm2 = q.x * q.x + q.y * q.y + q.z * q.z + q.w * q.w
    return math.isfinite(norm2) and abs(norm2 - 1.0) <= 0.02


# The key of a map or keyframe that started before the matcher's messages were first heard (no
# stamp has it): the EKF places it from its first fused match, as any it has not seen start.
UNHEARD = -1


@dataclass
class ReadingConverter:
    """Converts and validates input messages for one fusion method ('ekf' or
    'complementary'); `configs` are the EKF's inputs (empty for the complementary filter)."""

    method: str
    configs: dict[str, InputConfig] = field(default_factory=dict)
    imu_source: str = 'integrated'
    mount: NDArray[np.float64] = field(default_factory=lambda: np.eye(3))
    # Project body velocities onto the horizontal plane with the IMU's latest roll and pitch
    # (orientation source): on a slope the planar pose moves by the horizontal part only.
    level_with_imu_tilt: bool = False
    previous_scan_ns: int | None = None
    tilt: NDArray[np.float64] = field(default_factory=lambda: np.eye(3))
    _identity_mount: bool | None = field(default=None, init=False, repr=False)
    _delay_ns: dict[str, int] = field(default_factory=dict, init=False, repr=False)
    # The map or keyframe each match is in, from the order of the matcher's messages: the
    # matcher's state, kept when the fusion starts again (reset).
    # Silent longer than this (s, 0: never), the matcher may have restarted (ScanMatchReferences).
    input_timeout_s: float = 0.0
    _references: ScanMatchReferences = field(init=False, repr=False)

    @classmethod
    def for_config(cls, config: SessionConfig) -> ReadingConverter:
        """The converter of a fusion configuration (its method, EKF inputs, IMU source and
        mount parameters)."""
        return cls(config.method, config.input_map, config.imu_source,
                   mount_rotation(*config.imu_mount_rpy), config.level_with_imu_tilt,
                   input_timeout_s=config.input_timeout_s)

    def __post_init__(self) -> None:
        self._references = ScanMatchReferences(self.input_timeout_s)
        self._delay_ns = {name: round(cfg.delay_s * 1e9) for name, cfg in self.configs.items()
                          if cfg.delay_s}
        imu = self.configs.get(IMU)
        self.delta_angles = DeltaAngles(imu.max_gap_s if imu is not None else 0.5)

    def stamp_ns(self, source: str, msg) -> int:
        """The time (ns) a message of input `source` describes the robot at: its header stamp
        less the input's delay_s. Every stamp the fusion reads from a message comes from here."""
        return stamp_to_ns(msg.header.stamp) - self._delay_ns.get(source, 0)

    def reset(self) -> None:
        self.previous_scan_ns = None
        self.tilt = np.eye(3)
        self.delta_angles.reset()

    def set_mount(self, rotation: NDArray[np.float64]) -> None:
        """The IMU frame's rotation in base_link from now on (a mount from /tf_static)."""
        self.mount = rotation
        self._identity_mount = None

    def _level(self, vx: float, vy: float, wz: float) -> tuple[float, float, float]:
        """Body twist -> its horizontal part (in the yaw-only frame) and vertical rotation."""
        if not self.level_with_imu_tilt:
            return vx, vy, wz
        v = self.tilt @ np.array([vx, vy, 0.0])
        return float(v[0]), float(v[1]), float(self.tilt[2, 2] * wz)

    def reading(self, source: str, msg, stamp: int, record: InputRecord
                ) -> tuple[Reading | None, str]:
        """A validated core Reading from a message stamped `stamp` (ns, from stamp_ns), or
        (None, why not)."""
        if source == IMU:
            return self._imu(msg, stamp, record)
        if source == SCAN and self.method == 'ekf':
            return self._match(msg, stamp)
        if not unit_quaternion(msg.pose.pose.orientation):
            return None, 'orientation is not a unit quaternion'
        pose, cov = odometry_pose(msg)
        twist, twist_cov = odometry_twist(msg)
        cfg = self.configs.get(source)
        # A static or zero covariance is what the EKF's noise model is for ('auto', 'model').
        zero_ok = cfg is not None and (cfg.covariance != 'message' or not any(cfg.mask[:3]))
        problem = pose_problem(pose, cov, record.origin, zero_ok)
        if not problem and cfg is not None and any(cfg.mask[3:]):
            if not all(math.isfinite(v) for v in twist):
                problem = 'twist is not finite'
            else:
                problem = covariance_problem(twist_cov)
        if problem:
            return None, problem
        if record.origin is None:
            record.origin = pose
        if source == SCAN:
            # Only accepted matches may start the interval of the next one's covariance.
            return Reading(stamp, pose, cov, twist, self._scan_increment_covariance(
                twist_cov, stamp)), ''
        return Reading(stamp, pose, cov, self._level(*twist), twist_cov), ''

    def _yaw_rate(self, w) -> float:
        """Rate (rad/s) about base_link's z of a rate measured about the IMU's axes."""
        if self._identity_mount is None:
            self._identity_mount = bool(np.array_equal(self.mount, np.eye(3)))
        if self._identity_mount and math.isfinite(w.x) and math.isfinite(w.y):
            return float(w.z)   # what the product gives, without a matrix product per message
        return float(to_base((w.x, w.y, w.z), self.mount)[2])

    def _imu(self, msg, stamp: int, record: InputRecord) -> tuple[Reading | None, str]:
        w = msg.angular_velocity
        rate = self._yaw_rate(w)
        rate_var = float(msg.angular_velocity_covariance[8])
        if self.imu_source == 'rate':
            if not math.isfinite(rate):
                return None, 'angular velocity is not finite'
            problem = covariance_problem(
                np.asarray(msg.angular_velocity_covariance, dtype=float).reshape(3, 3))
            if problem:
                return None, f'angular velocity {problem}'
            # The rate (mask vyaw), and the rates summed into a heading (mask yaw: increments).
            self.delta_angles.add(stamp, rate, rate_var)
            return Reading(stamp, (0.0, 0.0, self.delta_angles.yaw),
                           _yaw_only(self.delta_angles.variance), (0.0, 0.0, rate),
                           _yaw_only(rate_var)), ''
        if msg.orientation_covariance[0] == -1.0:
            return None, 'orientation_covariance[0] = -1: the IMU provides no orientation'
        if not unit_quaternion(msg.orientation):
            return None, 'orientation is not a unit quaternion'
        q = msg.orientation
        if self.imu_source == 'integrated':
            yaw = quaternion_to_yaw(q)
            var = float(msg.orientation_covariance[8])
        else:
            base = base_orientation((q.x, q.y, q.z, q.w), self.mount)
            yaw = math.atan2(base[1, 0], base[0, 0])
            c, si = math.cos(yaw), math.sin(yaw)
            self.tilt = np.array([[c, si, 0.0], [-si, c, 0.0], [0.0, 0.0, 1.0]]) @ base
            if self.level_with_imu_tilt:
                rate = float((self.tilt @ to_base((w.x, w.y, w.z), self.mount))[2])
            orientation_cov = np.asarray(msg.orientation_covariance, dtype=float).reshape(3, 3)
            problem = covariance_problem(orientation_cov)
            if problem:
                return None, f'orientation {problem}'
            var = float((self.mount @ orientation_cov @ self.mount.T)[2, 2])
        if not math.isfinite(var) or var < 0.0:
            return None, 'yaw variance is not finite or negative'
        if record.origin is None:
            record.origin = yaw
        cfg = self.configs.get(IMU)
        if var == 0.0 and yaw != record.origin and (cfg is None or cfg.covariance != 'model'):
            return None, 'yaw variance is zero after turning'
        twist = (0.0, 0.0, rate) if math.isfinite(rate) else None
        return Reading(stamp, (0.0, 0.0, yaw), _yaw_only(var), twist,
                       _yaw_only(max(rate_var, 0.0))), ''

    def _match(self, msg, stamp: int) -> tuple[Reading | None, str]:
        """icp_matcher's match (docs/fusion.md): base_link in a local map's frame or relative to a
        keyframe, the map or keyframe named by the stamp of the message that started it (a
        keyframe's retimed as the message's; UNHEARD: started before the stream was heard)."""
        # Read first: a message that starts a map or keyframe does so even where it is refused.
        reference, problem = self._references.read(msg)
        if not unit_quaternion(msg.pose.pose.orientation):
            return None, 'orientation is not a unit quaternion'
        if reference is None:
            return None, problem
        key = UNHEARD if reference.reference_ns is None else reference.reference_ns
        if reference.in_map and reference.starts:
            # The scan that starts the map: base_link at this stamp is the map's origin.
            return Reading(stamp, new_keyframe=True, map_ns=key), ''
        if not reference.matched:
            return Reading(stamp, new_keyframe=reference.starts), ''
        pose, cov = odometry_pose(msg)
        problem = pose_problem(pose, cov, None, False) or (
            '' if np.all(np.diag(cov) > 0.0) else 'a match must have a covariance')
        if problem:
            return None, problem
        if reference.in_map:
            return Reading(stamp, pose, cov, map_ns=key), ''
        if key != UNHEARD:
            key -= self._delay_ns.get(SCAN, 0)
        return Reading(stamp, pose, cov, keyframe_ns=key, new_keyframe=reference.starts), ''

    def _scan_increment_covariance(self, twist_cov, stamp: int):
        """Covariance of the motion since the matcher's previous output, from its twist
        covariance (twist = motion / dt), when it provides one; else None and the fusion core
        recovers it from the cumulative covariances."""
        previous, self.previous_scan_ns = self.previous_scan_ns, stamp
        if previous is None or stamp <= previous or not np.all(np.isfinite(twist_cov)) \
                or not np.all(np.diag(twist_cov) > 0.0):
            return None
        dt = (stamp - previous) * 1e-9
        return twist_cov * dt * dt
