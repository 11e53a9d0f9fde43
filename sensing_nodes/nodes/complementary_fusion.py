"""complementary_fusion: /wheel/odom + /imu/data + scan matching -> /odometry/filtered.

method 'ekf' (default): core.ekf_fusion (EKF with stochastic cloning of the scan matcher's
keyframes, per-input masks, gates and noise models; docs/fusion.md). method 'complementary':
the seed's complementary filter (core.fusion.ComplementaryFusion) on /scan_match/odom.
"""

from __future__ import annotations

import math
import sys
import time

import numpy as np
from diagnostic_msgs.msg import DiagnosticStatus
from geometry_msgs.msg import PoseWithCovarianceStamped
from nav_msgs.msg import Odometry
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.node import Node
from sensor_msgs.msg import Imu

from sensing_nodes.core.ekf_fusion import (
    EkfFusion, EkfSettings, InputConfig, NoiseModel, Reading, mask_from_names,
)
from sensing_nodes.core.fusion import (
    ComplementaryMethod, FusionSettings, InputRecord, StampOrderedBuffer, covariance_problem,
    pose_problem, watermark,
)
from sensing_nodes.core.imu_mount import base_yaw, mount_rotation, to_base
from sensing_nodes.ros.conversions import (
    KEYFRAME_PREFIX, NO_KEYFRAME, keyframe_stamp, make_odometry, odometry_pose, odometry_twist, quaternion_to_yaw, ros_covariance_to_planar,
    stamp_to_ns,
)
from sensing_nodes.ros.diagnostics import Diagnostics
from sensing_nodes.ros.logging import ThrottledWarnings
from sensing_nodes.ros.params import ParameterError, declare, require
from sensing_nodes.ros.qos import ESTIMATE_QOS, SENSOR_QOS
from sensing_nodes.ros.run import run_node

# Processing rank at equal stamps: dead reckoning up to a stamp is in before the scan match
# at that stamp is fused.
WHEEL, IMU, SCAN = 'wheel_odom', 'imu', 'scan_match'
RANK = {WHEEL: 0, IMU: 1, SCAN: 2}
IMU_SOURCES = ('integrated', 'orientation', 'rate')


def unit_quaternion(q) -> bool:
    """Finite and of unit length (within 1 %): an infinite or all-zero orientation still gives
    a finite yaw from atan2, but it is no rotation at all."""
    norm2 = q.x * q.x + q.y * q.y + q.z * q.z + q.w * q.w
    return math.isfinite(norm2) and abs(norm2 - 1.0) <= 0.02


class ComplementaryFusionNode(Node):
    def __init__(self) -> None:
        super().__init__('complementary_fusion')
        method = declare(self, 'method', 'ekf',
                         "'ekf' (docs/fusion.md) or 'complementary' (the seed's filter)")
        use_wheel = declare(self, 'use_wheel_odom', True, 'fuse /wheel/odom')
        use_imu = declare(self, 'use_imu', True, 'fuse /imu/data')
        use_scan_pos = declare(self, 'use_scan_match_position', True,
                               'fuse x/y of scan matching')
        use_scan_heading = declare(self, 'use_scan_match_heading', True,
                                   'fuse the heading of scan matching')
        alpha = self.declare_parameter(
            'alpha', 0.98, ParameterDescriptor(
                description="complementary: weight of the gyro-propagated heading, in [0, 1], "
                            "or 'auto' to derive it each update from the two variances",
                dynamic_typing=True, read_only=True)).value
        window_s = declare(self, 'reorder_window_s', 2.0,
                           'longest an input may lag the newest (stamp time) and still be fused '
                           'in stamp order; later messages are dropped and counted',
                           minimum=0.0, maximum=10.0)
        self._flush_after_s = declare(self, 'flush_after_s', 0.5,
                                      'wall time without input after which held inputs are processed',
                                      minimum=0.01, maximum=60.0)
        max_gap_s = declare(self, 'max_gap_s', 2.0,
                            'an input silent longer than this (stamp time) restarts its increments',
                            minimum=0.001, maximum=3600.0)
        self._reset_jump_s = declare(self, 'reset_on_backwards_jump_s', 0.0,
                                     'an input stamp more than this before the same input\'s '
                                     'previous one means time went backwards (looping bag): the '
                                     'filter resets', minimum=0.0)
        self._input_timeout_s = declare(self, 'input_timeout_s', 2.0,
                                        'an enabled input silent for this long is reported missing',
                                        minimum=0.01)
        self._odom_frame = declare(self, 'odom_frame', 'odom', 'frame of the fused pose')
        self._base_frame = declare(self, 'base_frame', 'base_link', 'child frame of the fused pose')

        require(method in ('ekf', 'complementary'), 'method', "must be 'ekf' or 'complementary'",
                method)
        if alpha == 'auto':
            alpha_value = None
        elif isinstance(alpha, (int, float)) and not isinstance(alpha, bool) and 0.0 <= alpha <= 1.0:
            alpha_value = float(alpha)
        else:
            raise ParameterError('alpha', "must be a number in [0, 1] or 'auto'", alpha)
        require(use_wheel or use_imu or use_scan_pos or use_scan_heading, 'use_*',
                'at least one input must be enabled')
        require(bool(self._odom_frame) and bool(self._base_frame), 'odom_frame/base_frame',
                'must not be empty')

        self._method = method
        self._records = {WHEEL: InputRecord(WHEEL, use_wheel), IMU: InputRecord(IMU, use_imu),
                         SCAN: InputRecord(SCAN, use_scan_pos or use_scan_heading)}
        topics = {WHEEL: declare(self, 'wheel_odom.topic', '/wheel/odom', 'wheel odometry topic'),
                  IMU: declare(self, 'imu.topic', '/imu/data', 'IMU topic (sensor_msgs/Imu)')}
        self._imu_source = 'integrated'
        self._mount = np.eye(3)
        if method == 'ekf':
            configs = self._declare_ekf(use_wheel, use_imu, use_scan_pos, use_scan_heading,
                                        max_gap_s)
            settings = EkfSettings(
                accel_noise_density=declare(
                    self, 'ekf.accel_noise_density', EkfSettings.accel_noise_density,
                    'how fast vx, vy may change (m/s^2/sqrt(Hz))', minimum=1e-6),
                angular_accel_noise_density=declare(
                    self, 'ekf.angular_accel_noise_density',
                    EkfSettings.angular_accel_noise_density,
                    'how fast the yaw rate may change (rad/s^2/sqrt(Hz))', minimum=1e-6),
                bias_random_walk=declare(self, 'ekf.bias_random_walk',
                                         EkfSettings.bias_random_walk,
                                         'gyro bias random walk (rad/s/sqrt(s))', minimum=0.0),
                initial_bias_std=declare(self, 'ekf.initial_bias_std',
                                         EkfSettings.initial_bias_std,
                                         'gyro bias std before any input (rad/s)', minimum=0.0))
            self._fusion = EkfFusion(configs, settings)
            topics[SCAN] = declare(self, 'scan_match.topic', '/scan_match/keyframe_odom',
                                   'keyframe-relative scan matches (icp_matcher)')
        else:
            self._fusion = ComplementaryMethod(FusionSettings(
                use_wheel=use_wheel, use_gyro=use_imu, use_scan_position=use_scan_pos,
                use_scan_heading=use_scan_heading, alpha=alpha_value, max_gap_s=max_gap_s))
            topics[SCAN] = declare(self, 'scan_match.topic', '/scan_match/odom',
                                   'scan matching poses (icp_matcher)')
        self._buffer = StampOrderedBuffer(int(window_s * 1e9))
        self._start_ns: int | None = None
        self._previous_scan_stamp: int | None = None
        self._last_arrival = time.monotonic()

        self._warnings = ThrottledWarnings(self)
        self._publisher = self.create_publisher(Odometry, '/odometry/filtered', ESTIMATE_QOS)
        self.diagnostics = Diagnostics(self, update=self._update_diagnostics)
        if use_wheel:
            self.create_subscription(Odometry, topics[WHEEL],
                                     lambda m: self._on_message(WHEEL, m), ESTIMATE_QOS)
        if use_imu:
            qos = SENSOR_QOS if self._imu_source != 'integrated' else ESTIMATE_QOS
            self.create_subscription(Imu, topics[IMU], lambda m: self._on_message(IMU, m), qos)
        if use_scan_pos or use_scan_heading:
            self.create_subscription(Odometry, topics[SCAN],
                                     lambda m: self._on_message(SCAN, m), ESTIMATE_QOS)
        # robot_localization's set_pose as a topic: a service would need an interface package
        # of our own, which the PyPI-wheel setup cannot build.
        self.create_subscription(PoseWithCovarianceStamped, '~/set_pose', self._on_set_pose, 10)
        self.create_timer(self._flush_after_s / 2.0, self._flush_if_idle)
        self.get_logger().info(f'method {method}; inputs: ' + ', '.join(
            f'{name} ({topics[name]})' for name, r in self._records.items() if r.enabled))

    def _declare_input(self, name: str, mask: list[str], enabled: bool, max_gap_s: float,
                       **overrides) -> InputConfig | None:
        """Declare one input's EKF parameters (name.*) and return its validated config."""
        d = NoiseModel()
        names = declare(self, f'{name}.mask', mask,
                        'quantities fused, of x, y, yaw, vx, vy, vyaw (robot_localization order)')
        try:
            mask_tuple = mask_from_names(list(names))
        except ValueError as error:
            raise ParameterError(f'{name}.mask', str(error), names) from None
        gate = declare(self, f'{name}.gate_chi2', overrides.pop('gate_chi2', 0.0),
                       'reject a measurement whose squared Mahalanobis distance exceeds this '
                       '(chi-square value); 0 = no gate', minimum=0.0)
        cfg = InputConfig(
            name=name, mask=mask_tuple,
            pose_mode=declare(self, f'{name}.pose_mode', overrides.pop('pose_mode', 'differential'),
                              "pose quantities: 'absolute', 'relative' (to the first message) "
                              "or 'differential' (motion between consecutive messages)"),
            covariance=declare(self, f'{name}.covariance', overrides.pop('covariance', 'auto'),
                               "'auto' (the message's unless static or zero, then the noise "
                               "model), 'message' or 'model'"),
            noise=NoiseModel(
                variance_per_m=declare(self, f'{name}.variance_per_m',
                                       overrides.pop('variance_per_m', d.variance_per_m),
                                       'noise model: x/y variance per metre (m^2/m)', minimum=0.0),
                variance_per_rad=declare(self, f'{name}.variance_per_rad',
                                         overrides.pop('variance_per_rad', d.variance_per_rad),
                                         'noise model: yaw variance per radian (rad^2/rad)',
                                         minimum=0.0),
                yaw_variance_per_m=declare(self, f'{name}.yaw_variance_per_m',
                                           overrides.pop('yaw_variance_per_m',
                                                         d.yaw_variance_per_m),
                                           'noise model: yaw variance per metre (rad^2/m)',
                                           minimum=0.0),
                yaw_variance_per_s=declare(self, f'{name}.yaw_variance_per_s',
                                           overrides.pop('yaw_variance_per_s',
                                                         d.yaw_variance_per_s),
                                           'noise model: yaw variance per second (rad^2/s)',
                                           minimum=0.0)),
            covariance_scale=declare(self, f'{name}.covariance_scale',
                                     overrides.pop('covariance_scale', 1.0),
                                     "the message's covariance times this (distrust: > 1)",
                                     minimum=1e-6),
            twist_variance=tuple(declare(
                self, f'{name}.twist_variance', list(overrides.pop('twist_variance',
                                                                   (1e-4, 1e-4, 1e-4))),
                'vx, vy, vyaw variances when the message has none')),
            gate_chi2=gate if gate > 0.0 else math.inf, max_gap_s=max_gap_s, **overrides)
        for field, problem, value in cfg.problems():
            require(not enabled, f'{name}.{field}', problem, value)
        return cfg if enabled else None

    def _declare_ekf(self, use_wheel, use_imu, use_scan_pos, use_scan_heading, max_gap_s
                     ) -> tuple[InputConfig, ...]:
        configs = []
        wheel = self._declare_input(WHEEL, ['x', 'y', 'yaw'], use_wheel, max_gap_s)
        self._imu_source = declare(self, 'imu.source', 'integrated',
                                   "'integrated' (gyro_integrator's heading), 'orientation' "
                                   "(the IMU's own orientation) or 'rate' (raw gyro rate, bias "
                                   'estimated in the filter)')
        require(self._imu_source in IMU_SOURCES, 'imu.source', f'must be one of {IMU_SOURCES}',
                self._imu_source)
        mount = [declare(self, f'imu.mount_{axis}_rad', 0.0,
                         f'IMU mount {axis} in base_link (rad); upside down: roll = pi',
                         minimum=-2 * math.pi, maximum=2 * math.pi)
                 for axis in ('roll', 'pitch', 'yaw')]
        self._mount = mount_rotation(*mount)
        rate = self._imu_source == 'rate'
        imu = self._declare_input(
            IMU, ['vyaw'] if rate else ['yaw'], use_imu, max_gap_s, gyro_bias=rate,
            covariance='model' if self._imu_source == 'integrated' else 'auto',
            yaw_variance_per_s=5e-8, variance_per_rad=0.0, yaw_variance_per_m=0.0,
            variance_per_m=0.0, gate_chi2=16.0)
        scan_mask = (['x', 'y'] if use_scan_pos else []) + (['yaw'] if use_scan_heading else [])
        scan = self._declare_input(SCAN, scan_mask or ['x'], use_scan_pos or use_scan_heading,
                                   max_gap_s, keyframes=True, covariance='message', gate_chi2=25.0)
        for cfg in (wheel, imu, scan):
            if cfg is not None:
                configs.append(cfg)
        return tuple(configs)

    # -- input -------------------------------------------------------------------------------
    def _on_message(self, source: str, msg) -> None:
        self._last_arrival = time.monotonic()
        stamp = stamp_to_ns(msg.header.stamp)
        record = self._records[source]
        record.received += 1
        # Before the message is read: reading it uses per-timeline state (a source's starting
        # pose), which must already be the new timeline's.
        if record.arrived_ns is not None and record.arrived_ns - stamp > self._reset_jump_s * 1e9:
            self.get_logger().warn(
                f'{source} stamp {stamp * 1e-9:.3f} s is {(record.arrived_ns - stamp) * 1e-9:.3f} '
                's before its previous one: time went backwards (looping bag or restarted '
                'clock); resetting')
            self.diagnostics.count('resets')
            self._process(self._buffer.flush())  # what was held belongs to the old timeline
            self._reset()
        reading, problem = self._reading(source, msg, stamp)
        if reading is None:
            self.diagnostics.count(f'{source}_rejected')
            self._warnings.warn(f'{source}_rejected', f'{source}: rejected a message ({problem})')
            return
        if not self._buffer.push(stamp, RANK[source], (source, reading)):
            self.diagnostics.count(f'{source}_dropped_late')
            self._warnings.warn(
                f'{source}_late',
                f'{source} message at {stamp * 1e-9:.3f} s arrived after inputs up to '
                f'{self._buffer.released_ns * 1e-9:.3f} s were fused: dropped '
                f'({self._buffer.late} so far)')
            return
        if self._start_ns is None:
            self._start_ns = stamp
        record.arrived_ns = stamp if record.arrived_ns is None else max(record.arrived_ns, stamp)
        self._process(self._buffer.pop_ready(watermark(
            list(self._records.values()), self._buffer.newest_ns, self._start_ns,
            self._input_timeout_s)))

    def _reading(self, source: str, msg, stamp: int) -> tuple[Reading | None, str]:
        """A validated core Reading from a message, or (None, why not)."""
        record = self._records[source]
        if source == IMU:
            return self._imu_reading(msg, stamp, record)
        if not unit_quaternion(msg.pose.pose.orientation):
            return None, 'orientation is not a unit quaternion'
        if source == SCAN and self._method == 'ekf':
            return self._keyframe_reading(msg, stamp)
        pose, cov = odometry_pose(msg)
        twist, twist_cov = odometry_twist(msg)
        zero_ok = self._method == 'ekf' and self._fusion.inputs[source].covariance == 'model'
        problem = pose_problem(pose, cov, record.origin, zero_ok)
        if not problem and self._method == 'ekf' and any(self._fusion.inputs[source].mask[3:]):
            if not all(math.isfinite(v) for v in twist):
                problem = 'twist is not finite'
            else:
                problem = covariance_problem(twist_cov)
        if problem:
            return None, problem
        if record.origin is None:
            record.origin = pose
        increment_cov = None
        if source == SCAN:
            # Only accepted matches may start the interval of the next one's covariance.
            increment_cov = self._scan_increment_covariance(twist_cov, stamp)
        return Reading(stamp, pose, cov, twist,
                       increment_cov if source == SCAN else twist_cov), ''

    def _imu_reading(self, msg, stamp: int, record: InputRecord) -> tuple[Reading | None, str]:
        if self._imu_source == 'rate':
            w = msg.angular_velocity
            rate = float(to_base((w.x, w.y, w.z), self._mount)[2])
            var = float(msg.angular_velocity_covariance[8])
            if not math.isfinite(rate):
                return None, 'angular velocity is not finite'
            if not math.isfinite(var) or var < 0.0:
                return None, 'angular velocity variance is not finite or negative'
            cov = np.diag([0.0, 0.0, var])
            return Reading(stamp, twist=(0.0, 0.0, rate), twist_covariance=cov), ''
        if msg.orientation_covariance[0] == -1.0:
            return None, 'orientation_covariance[0] = -1: the IMU provides no orientation'
        if not unit_quaternion(msg.orientation):
            return None, 'orientation is not a unit quaternion'
        q = msg.orientation
        if self._imu_source == 'integrated':
            yaw = quaternion_to_yaw(q)
            var = float(msg.orientation_covariance[8])
        else:
            yaw = base_yaw((q.x, q.y, q.z, q.w), self._mount)
            orientation_cov = np.asarray(msg.orientation_covariance, dtype=float).reshape(3, 3)
            problem = covariance_problem(orientation_cov)
            if problem:
                return None, f'orientation {problem}'
            var = float((self._mount @ orientation_cov @ self._mount.T)[2, 2])
        if not math.isfinite(var) or var < 0.0:
            return None, 'yaw variance is not finite or negative'
        if record.origin is None:
            record.origin = yaw
        if var == 0.0 and yaw != record.origin and self._method == 'complementary':
            return None, 'yaw variance is zero after turning'
        w = msg.angular_velocity
        rate = float(to_base((w.x, w.y, w.z), self._mount)[2])
        cov = np.diag([0.0, 0.0, var])
        rate_cov = np.diag([0.0, 0.0, max(float(msg.angular_velocity_covariance[8]), 0.0)])
        return Reading(stamp, (0.0, 0.0, yaw), cov,
                       (0.0, 0.0, rate) if math.isfinite(rate) else None, rate_cov), ''

    def _keyframe_reading(self, msg, stamp: int) -> tuple[Reading | None, str]:
        """icp_matcher's keyframe-relative match (docs/fusion.md: frame ids name keyframes)."""
        new_keyframe = keyframe_stamp(msg.child_frame_id) == stamp
        keyframe = keyframe_stamp(msg.header.frame_id)
        if msg.header.frame_id != NO_KEYFRAME and keyframe is None:
            return None, (f"frame_id '{msg.header.frame_id}' names no keyframe "
                          f"('{KEYFRAME_PREFIX}<stamp ns>' or '{NO_KEYFRAME}')")
        if keyframe is None:
            return Reading(stamp, new_keyframe=new_keyframe), ''
        pose, cov = odometry_pose(msg)
        problem = pose_problem(pose, cov, None, False) or (
            '' if np.all(np.diag(cov) > 0.0) else 'a match must have a covariance')
        if problem:
            return None, problem
        return Reading(stamp, pose, cov, keyframe_ns=keyframe, new_keyframe=new_keyframe), ''

    def _scan_increment_covariance(self, twist_cov, stamp: int):
        """Covariance of the motion since the matcher's previous output, from its twist
        covariance (twist = motion / dt), when it provides one; else None and the fusion core
        recovers it from the cumulative covariances."""
        previous, self._previous_scan_stamp = self._previous_scan_stamp, stamp
        if previous is None or stamp <= previous or not np.all(np.isfinite(twist_cov)) \
                or not np.all(np.diag(twist_cov) > 0.0):
            return None
        dt = (stamp - previous) * 1e-9
        return twist_cov * dt * dt

    def _on_set_pose(self, msg: PoseWithCovarianceStamped) -> None:
        p = msg.pose.pose
        pose = (float(p.position.x), float(p.position.y), quaternion_to_yaw(p.orientation))
        cov = ros_covariance_to_planar(msg.pose.covariance)
        problem = '' if unit_quaternion(p.orientation) else 'orientation is not a unit quaternion'
        problem = problem or pose_problem(pose, cov, None, True)
        if problem:
            self.diagnostics.count('set_pose_rejected')
            self.get_logger().warn(f'set_pose rejected: {problem}')
            return
        self._process(self._buffer.flush())
        self._fusion.set_pose(pose, cov)
        self.diagnostics.count('set_pose')
        self.get_logger().info('pose set to x=%.3f m, y=%.3f m, yaw=%.3f rad' % pose)

    def _reset(self) -> None:
        self._fusion.reset()
        self._buffer.clear()
        for record in self._records.values():
            record.clear()
        self._start_ns = None
        self._previous_scan_stamp = None

    def _flush_if_idle(self) -> None:
        if len(self._buffer) and time.monotonic() - self._last_arrival > self._flush_after_s:
            self._process(self._buffer.flush())

    # -- fusion and output ---------------------------------------------------------------------
    def _process(self, ready) -> None:
        for stamp, (source, reading) in ready:
            self._records[source].processed_at(stamp)
            self._fusion.update(source, reading)
            if source == IMU and (self._records[WHEEL].enabled or self._records[SCAN].enabled):
                continue  # heading only: published with the next position update
            self._publish(stamp)

    def _publish(self, stamp: int) -> None:
        state = self._fusion.state
        if state is None:
            return
        twist, twist_cov = getattr(state, 'twist', (0.0, 0.0, 0.0)), \
            getattr(state, 'twist_covariance', None)
        self._publisher.publish(make_odometry(
            stamp, self._odom_frame, self._base_frame, state.pose, state.covariance,
            twist, twist_cov))
        self.diagnostics.count('published')
        self.diagnostics.last_stamp_ns = max(self.diagnostics.last_stamp_ns, stamp)

    def _update_diagnostics(self, diag: Diagnostics) -> None:
        newest = self._buffer.newest_ns
        missing = []
        for name, record in self._records.items():
            if not record.enabled:
                diag.values[f'{name}_state'] = 'disabled'
                continue
            age = record.age_s(newest)
            diag.values[f'{name}_received'] = str(record.received)
            diag.values[f'{name}_age_s'] = f'{age:.3f}'
            diag.values[f'{name}_rate_hz'] = f'{record.rate_hz():.2f}'
            diag.values[f'{name}_gated'] = str(self._fusion.gated.get(name, 0))
            if age > self._input_timeout_s:
                missing.append(name)
        diag.values['method'] = self._method
        diag.values['fusion_updates'] = str(self._fusion.updates)
        diag.values['late_dropped_total'] = str(self._buffer.late)
        if missing:
            diag.level, diag.message = DiagnosticStatus.WARN, 'missing: ' + ', '.join(missing)
        else:
            diag.level, diag.message = DiagnosticStatus.OK, 'all enabled inputs present'


def main(args=None):
    sys.exit(run_node(ComplementaryFusionNode, args))
