"""wheel_odometry: /joint_states (wheel encoder angles) -> /wheel/odom (odom -> base_link)."""

from __future__ import annotations

import sys
from dataclasses import replace

import numpy as np
from nav_msgs.msg import Odometry
from rclpy.node import Node
from sensor_msgs.msg import JointState
from std_srvs.srv import Trigger
from tf2_msgs.msg import TFMessage

from sensing_nodes.core.geometry.transform import Transform
from sensing_nodes.core.timing import StampStep
from sensing_nodes.core.wheel_odometry import WheelOdometry, WheelOdometryConfig
from sensing_nodes.ros.cdr import odometry_cdr, transform_cdr
from sensing_nodes.ros.conversions import stamp_to_ns
from sensing_nodes.ros.diagnostics import Diagnostics
from sensing_nodes.ros.logging import ThrottledWarnings
from sensing_nodes.ros.params import Param, declare, declare_config, require
from sensing_nodes.ros.processor import Input, Output, Outputs, wire
from sensing_nodes.ros.qos import ESTIMATE_QOS, SENSOR_QOS, TF_QOS
from sensing_nodes.ros.run import run_node
from sensing_nodes.ros.tf import TF_TOPIC
from sensing_nodes.topics import JOINT_STATES, WHEEL_ODOM


class WheelOdometryNode(Node):
    def __init__(self, **node_options) -> None:
        # node_options: rclpy Node keywords (sensing_pipeline passes this node's own cli_args)
        super().__init__('wheel_odometry', **node_options)
        config, (left, right) = self._declare_odometry()
        mode, static_pose, static_twist = self._declare_covariance_mode()
        self._odom_frame = declare(self, 'odom_frame', 'odom', 'frame of the published pose')
        self._base_frame = declare(self, 'base_frame', 'base_link', 'child frame (robot base)')
        publish_tf = declare(self, 'publish_tf', False,
                             'broadcast odom_frame -> base_frame on /tf (one owner per tree: '
                             'the fusion broadcasts it by default)')
        require(bool(self._odom_frame) and bool(self._base_frame), 'odom_frame/base_frame',
                'must not be empty')

        self.diagnostics = Diagnostics(self, update=self._refresh_diagnostics)
        self.processor = WheelOdometryProcessor(
            WheelOdometry(config), (left, right),
            None if mode == 'propagated' else (np.diag(static_pose), np.diag(static_twist)),
            self._odom_frame, self._base_frame, publish_tf, self.diagnostics,
            ThrottledWarnings(self), self.get_logger())
        wire(self, self.processor.inputs(), self.processor.outputs())
        self.create_service(Trigger, '~/reset', self._on_reset)
        self.get_logger().info(
            f'wheels {left!r} / {right!r}: radius {config.wheel_radius_m} m '
            f'(x {config.left_radius_multiplier}, x {config.right_radius_multiplier}), '
            f'separation {config.wheel_separation_m} m, {config.method}, covariance {mode}')

    def _declare_odometry(self) -> tuple[WheelOdometryConfig, tuple[str, str]]:
        """The dead reckoning's parameters (defaults: WheelOdometryConfig's) and the joints."""
        d = WheelOdometryConfig()
        left = declare(self, 'left_wheel_joint', 'left_wheel_joint',
                       'name of the left wheel joint')
        right = declare(self, 'right_wheel_joint', 'right_wheel_joint',
                        'name of the right wheel joint')
        variance = declare(self, 'wheel_variance_per_m', d.variance_per_m[0],
                           'random error model: variance (m^2) of a wheel distance is '
                           'this * |distance (m)|', minimum=0.0)
        config = declare_config(self, replace(d, variance_per_m=(variance, variance)), (
            Param('wheel_radius_m', 'nominal wheel radius (m)'),
            Param('wheel_separation_m', 'distance between the wheel contact points (m)'),
            Param('left_radius_multiplier', 'calibration: left radius = wheel_radius_m * this',
                  minimum=0.5, maximum=1.5),
            Param('right_radius_multiplier', 'calibration: right radius = wheel_radius_m * this',
                  minimum=0.5, maximum=1.5),
            Param('method', "'exact_arc' (default) or 'euler' (the textbook update, for "
                  'teaching)', name='integration_method'),
            Param('radius_multiplier_std', "systematic error model: std of each wheel's "
                  'relative radius error (what calibration leaves)', minimum=0.0, maximum=0.49),
            Param('max_gap_s', 'a stamp gap longer than this (s) is not integrated across'),
            Param('max_wheel_speed_rad_s', 'fastest plausible wheel rate (rad/s): larger '
                  'increments are wrapped encoder readings, or rejected'),
        ), declared={'variance_per_m': 'wheel_variance_per_m'})
        require(bool(left), 'left_wheel_joint', 'must not be empty', left)
        require(bool(right), 'right_wheel_joint', 'must not be empty', right)
        require(left != right, 'right_wheel_joint', 'must differ from left_wheel_joint', right)
        return config, (left, right)

    def _declare_covariance_mode(self) -> tuple[str, list[float], list[float]]:
        """covariance_mode and the static variances it may use, validated."""
        mode = declare(self, 'covariance_mode', 'propagated',
                       "'propagated' (from the wheel error model) or 'static' (the lists below)")
        static_pose = declare(self, 'static_pose_variances', [1e-3, 1e-3, 1e-3],
                              "with covariance_mode 'static': variances of x, y (m^2), yaw "
                              '(rad^2)')
        static_twist = declare(self, 'static_twist_variances', [1e-3, 1e-9, 1e-3],
                               "with covariance_mode 'static': variances of vx, vy, wz")
        require(mode in ('propagated', 'static'), 'covariance_mode',
                "must be 'propagated' or 'static'", mode)
        for name, values in (('static_pose_variances', static_pose),
                             ('static_twist_variances', static_twist)):
            require(len(values) == 3 and all(np.isfinite(values)) and min(values) >= 0.0, name,
                    'must be three finite variances >= 0', list(values))
        return mode, static_pose, static_twist

    def _refresh_diagnostics(self, diag: Diagnostics) -> None:
        odo = self.processor.odometry
        diag.values['pose'] = '%.4f %.4f %.4f' % odo.pose
        std = np.sqrt(np.maximum(np.diag(odo.covariance), 0.0))
        diag.values['pose_std'] = '%.2e %.2e %.2e' % tuple(std)

    def _on_reset(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        odometry = self.processor.odometry
        before = odometry.pose
        self.diagnostics.values['pose_before_reset'] = '%.4f %.4f %.4f' % before
        odometry.reset()
        self.diagnostics.count('resets')
        response.success = True
        response.message = (f'pose reset to the origin (was x={before[0]:.4f} m, '
                            f'y={before[1]:.4f} m, yaw={before[2]:.4f} rad)')
        self.get_logger().info(response.message)
        return response


class WheelOdometryProcessor:
    """wheel_odometry's per-message logic (ros/processor.py): /joint_states -> /wheel/odom
    (odom_frame -> base_frame, m and rad) and, with publish_tf, the same pose on /tf."""

    def __init__(self, odometry: WheelOdometry, joints: tuple[str, str],
                 static: tuple | None, odom_frame: str, base_frame: str, publish_tf: bool,
                 diagnostics: Diagnostics, warnings: ThrottledWarnings, logger) -> None:
        self.odometry = odometry
        self._joints = joints
        self._static = static   # (pose, twist) covariances, or None: propagated
        self._odom_frame, self._base_frame = odom_frame, base_frame
        self._publish_tf = publish_tf
        self._warnings = warnings
        self._logger = logger
        self.diagnostics = diagnostics   # counted here, published by the node

    def inputs(self) -> list[Input]:
        return [Input(JOINT_STATES, JointState, SENSOR_QOS, self.on_joint_state, decoded=True)]

    def outputs(self) -> list[Output]:
        return [Output(WHEEL_ODOM, Odometry, ESTIMATE_QOS)] + \
            ([Output(TF_TOPIC, TFMessage, TF_QOS)] if self._publish_tf else [])

    def on_joint_state(self, msg: JointState) -> Outputs:
        stamp = stamp_to_ns(msg.header.stamp)
        result = self.odometry.update(
            stamp, list(msg.name), msg.position, msg.velocity, self._joints)
        diag = self.diagnostics
        if result.rejection is not None:
            key = result.rejection.value
            diag.count(key)
            self._warnings.warn(key, f'JointState at {stamp * 1e-9:.3f} s not integrated '
                                     f'({key}): {result.note}')
        elif result.step in (StampStep.BACKWARDS, StampStep.GAP):
            diag.count(result.step.value)
            self._warnings.warn(result.step.value,
                                f'JointState at {stamp * 1e-9:.3f} s: {result.note}')
        elif result.wrapped:
            diag.count('encoder_wraps')
            self._warnings.warn('wrap', f'JointState at {stamp * 1e-9:.3f} s: {result.note}')
        elif result.note:
            self._logger.info(result.note)
        return self._publish(stamp) if result.publish else []

    def _publish(self, stamp: int) -> Outputs:
        odo = self.odometry
        if self._static is None:
            pose_cov, twist_cov = odo.covariance, odo.twist_covariance
        else:
            pose_cov, twist_cov = self._static
        # Packed straight into CDR bytes (ros/cdr.py): building or refilling an rclpy Odometry
        # and having rclpy convert and serialise it cost more than the odometry itself.
        out: Outputs = [(WHEEL_ODOM, odometry_cdr(
            stamp, self._odom_frame, self._base_frame, odo.pose, pose_cov, odo.twist, twist_cov))]
        if self._publish_tf:
            out.append((TF_TOPIC, transform_cdr(stamp, self._odom_frame, self._base_frame,
                                                Transform.from_planar(*odo.pose))))
        self.diagnostics.count('published')
        self.diagnostics.last_stamp_ns = stamp
        return out


def main(args: list[str] | None = None) -> None:
    sys.exit(run_node(WheelOdometryNode, args))
