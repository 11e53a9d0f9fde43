"""wheel_odometry: /joint_states (wheel encoder angles) -> /wheel/odom (odom -> base_link)."""

from __future__ import annotations

import sys

import numpy as np
from nav_msgs.msg import Odometry
from sensor_msgs.msg import JointState
from std_srvs.srv import Trigger
from tf2_msgs.msg import TFMessage

from sensing_nodes.core.config.wheel_odometry import WHEEL_ODOMETRY_PARAMETERS
from sensing_nodes.core.geometry.transform import Transform
from sensing_nodes.core.timing import StampStep
from sensing_nodes.core.wheel_odometry import WheelOdometry
from sensing_nodes.ros.cdr import odometry_cdr, transform_cdr
from sensing_nodes.ros.conversions import stamp_to_ns
from sensing_nodes.ros.diagnostics import Diagnostics
from sensing_nodes.ros.logging import ThrottledWarnings
from sensing_nodes.ros.params import declare_config
from sensing_nodes.ros.processing_node import ProcessingNode
from sensing_nodes.ros.processor import Input, Output, Outputs, wire
from sensing_nodes.ros.qos import ESTIMATE_QOS, SENSOR_QOS, TF_QOS
from sensing_nodes.ros.run import run_node
from sensing_nodes.ros.tf import TF_TOPIC
from sensing_nodes.topics import JOINT_STATES, WHEEL_ODOM


class WheelOdometryNode(ProcessingNode):
    def __init__(self, **node_options) -> None:
        # node_options: rclpy Node keywords (sensing_pipeline passes this node's own cli_args)
        # and `lifecycle` (ros/processing_node.py)
        super().__init__('wheel_odometry', **node_options)

    def configure(self) -> None:
        parameters = declare_config(self, WHEEL_ODOMETRY_PARAMETERS)
        config, left, right = (parameters.odometry, parameters.left_wheel_joint,
                               parameters.right_wheel_joint)
        mode = parameters.covariance_mode
        self._odom_frame, self._base_frame = parameters.odom_frame, parameters.base_frame

        self.diagnostics = Diagnostics(self, update=self._refresh_diagnostics)
        self.processor = WheelOdometryProcessor(
            WheelOdometry(config), (left, right),
            None if mode == 'propagated' else (np.diag(parameters.static_pose_variances),
                                               np.diag(parameters.static_twist_variances)),
            self._odom_frame, self._base_frame, parameters.publish_tf, self.diagnostics,
            ThrottledWarnings(self), self.get_logger())
        wire(self, self.processor.inputs(), self.processor.outputs())
        self.create_service(Trigger, '~/reset', self._on_reset)
        self.get_logger().info(
            f'wheels {left!r} / {right!r}: radius {config.wheel_radius_m} m '
            f'(x {config.left_radius_multiplier}, x {config.right_radius_multiplier}), '
            f'separation {config.wheel_separation_m} m, {config.method}, covariance {mode}')

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
