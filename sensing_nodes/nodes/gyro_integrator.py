"""gyro_integrator: /imu/data_raw -> /imu/data (integrated heading, bias-corrected rates)."""

from __future__ import annotations

import math
import sys
from typing import Callable

import numpy as np
from nav_msgs.msg import Odometry
from sensor_msgs.msg import Imu
from std_srvs.srv import Trigger

from sensing_nodes.core.config.gyro_integrator import GYRO_INTEGRATOR_PARAMETERS
from sensing_nodes.core.geometry import quaternion
from sensing_nodes.core.geometry.imu_mount import to_base
from sensing_nodes.core.gyro import GyroConfig, GyroIntegrator
from sensing_nodes.core.timing import StampStep
from sensing_nodes.ros.cdr import imu_cdr
from sensing_nodes.ros.conversions import stamp_to_ns
from sensing_nodes.ros.diagnostics import Diagnostics
from sensing_nodes.ros.logging import ThrottledWarnings
from sensing_nodes.ros.params import declare_config
from sensing_nodes.ros.processing_node import ProcessingNode
from sensing_nodes.ros.processor import Input, Output, Outputs, subscribed, wire
from sensing_nodes.ros.qos import ESTIMATE_QOS, SENSOR_QOS
from sensing_nodes.ros.run import run_node
from sensing_nodes.ros.tf import ImuMount, imu_mount
from sensing_nodes.topics import IMU, IMU_RAW, WHEEL_ODOM

_HEADING_ONLY = (0.0,) * 8   # orientation covariance: only yaw's variance (last) is known


class GyroIntegratorNode(ProcessingNode):
    def __init__(self, **node_options) -> None:
        # node_options: rclpy Node keywords (sensing_pipeline passes this node's own cli_args)
        # and `lifecycle` (ros/processing_node.py)
        super().__init__('gyro_integrator', **node_options)

    def configure(self) -> None:
        parameters = declare_config(self, GYRO_INTEGRATOR_PARAMETERS)
        config, use_wheels = parameters.integrator, parameters.use_wheel_odom
        self._restart_on_backwards = parameters.restart_on_backwards
        # A rotated IMU: rates and accelerations are turned into base_link's axes before
        # anything else, so stillness, bias and heading are about base_link's z.
        mount_source = imu_mount(self, parameters.base_frame, parameters.mount_rpy,
                                 parameters.frame_id,
                                 on_update=lambda: self.processor.mount_changed())

        self.diagnostics = Diagnostics(self, update=self._refresh_diagnostics)
        self.processor = GyroIntegratorProcessor(
            config,
            mount_source,
            parameters.gyro_scale_error,
            self._restart_on_backwards,
            use_wheels,
            self.diagnostics,
            ThrottledWarnings(self),
            self.get_logger(),
        )
        self.processor.listened = subscribed(
            wire(self, self.processor.inputs(), self.processor.outputs()))
        self.create_service(Trigger, '~/calibrate', self._on_calibrate)
        self.get_logger().info(
            f'bias estimation {"on" if config.bias_estimation else "off"}, stillness window '
            f'{config.stillness_window_s} s, wheel odometry veto {"on" if use_wheels else "off"}')

    def _refresh_diagnostics(self, diag: Diagnostics) -> None:
        gi = self.processor.integrator
        diag.values['bias_z_rad_s'] = f'{gi.bias[2]:.6f}'
        diag.values['bias_z_std_rad_s'] = f'{math.sqrt(gi.p_bias):.2e}'
        diag.values['still'] = str(gi.still)
        diag.values['heading_std_rad'] = f'{math.sqrt(max(gi.heading_variance, 0.0)):.2e}'

    def _on_calibrate(self, request: Trigger.Request,
                      response: Trigger.Response) -> Trigger.Response:
        gi = self.processor.integrator
        before = gi.bias[2]
        gi.request_calibration()
        self.diagnostics.count('calibrations_requested')
        response.success = True
        response.message = (f'calibration armed: the bias (now z = {before:.6f} rad/s) is '
                            're-estimated over the next still window; keep the robot still for '
                            f'{gi.config.stillness_window_s} s')
        self.get_logger().info(response.message)
        return response


class GyroIntegratorProcessor:
    """gyro_integrator's per-message logic (ros/processor.py): /imu/data_raw -> /imu/data
    (heading about base_link's z, bias-corrected rates in rad/s); /wheel/odom vetoes stillness.
    Every reading is integrated; /imu/data is made only while `listened` (topic -> bool) says
    someone takes it (the node's matched subscriptions; every reading by default, as
    sensing_pipeline records it): the fusion reads the raw IMU itself."""

    def __init__(self, config: GyroConfig, mount: ImuMount, scale_error: float,
                 restart_on_backwards: bool,
                 use_wheels: bool, diagnostics: Diagnostics, warnings: ThrottledWarnings,
                 logger) -> None:
        self._config = config
        self._mount_source = mount
        self._z_scale = 1.0 + scale_error
        # Resolved per IMU frame id, again after /tf_static changes: (frame, rotation, output)
        self._mount_for: tuple[str, np.ndarray | None, str] | None = None
        self._restart_on_backwards = restart_on_backwards
        self._use_wheels = use_wheels
        self.integrator = GyroIntegrator(config)
        self.diagnostics = diagnostics   # counted here, published by the node
        self._warnings = warnings
        self._logger = logger
        self._was_still = False
        self.listened: Callable[[str], bool] = lambda topic: True

    def inputs(self) -> list[Input]:
        return [Input(IMU_RAW, Imu, SENSOR_QOS, self.on_imu, decoded=True)] + \
            ([Input(WHEEL_ODOM, Odometry, ESTIMATE_QOS, self.on_wheel_odom, decoded=True)]
             if self._use_wheels else [])

    def outputs(self) -> list[Output]:
        return [Output(IMU, Imu, ESTIMATE_QOS)]

    def mount_changed(self) -> None:
        """/tf_static changed: resolve the mount again at the next message."""
        self._mount_for = None

    def on_wheel_odom(self, msg: Odometry) -> Outputs:
        twist = msg.twist.twist
        self.integrator.observe_wheels(
            stamp_to_ns(msg.header.stamp), twist.linear.x, twist.angular.z)
        return []

    def on_imu(self, msg: Imu) -> Outputs:
        stamp = stamp_to_ns(msg.header.stamp)
        w, a = msg.angular_velocity, msg.linear_acceleration
        rate, accel = (w.x, w.y, w.z), (a.x, a.y, a.z)
        frame = msg.header.frame_id
        if self._mount_for is None or self._mount_for[0] != frame:
            self._mount_for = (frame, *self._mount_source.resolve(frame))
        _, rotation, self._output_frame = self._mount_for
        if rotation is not None:
            rate, accel = to_base(rate, rotation), to_base(accel, rotation)
        if self._z_scale != 1.0:       # calibrated scale factor of base_link's z rate
            rate = (rate[0], rate[1], rate[2] / self._z_scale)
        gi = self.integrator
        if self._restart_on_backwards and gi.stamp_ns is not None and stamp < gi.stamp_ns:
            self.diagnostics.count(StampStep.BACKWARDS.value)
            self._warnings.warn(StampStep.BACKWARDS.value, (
                f'Imu at {stamp * 1e-9:.3f} s: time went backwards by '
                f'{(gi.stamp_ns - stamp) * 1e-9:.3f} s (looping bag?): integrator restarted '
                '(heading 0, bias estimate from scratch)'))
            gi = self.integrator = GyroIntegrator(self._config)
            self._was_still = False
        result = gi.update(stamp, rate, accel)
        diag = self.diagnostics
        if result.rejection is not None:
            key = result.rejection.value
            diag.count(key)
            self._warnings.warn(key, f'Imu at {stamp * 1e-9:.3f} s not integrated ({key}): '
                                     f'{result.note}')
            return []
        if result.step in (StampStep.BACKWARDS, StampStep.GAP):
            diag.count(result.step.value)
            self._warnings.warn(result.step.value, f'Imu at {stamp * 1e-9:.3f} s: {result.note}')
        if result.still != self._was_still:
            self._was_still = result.still
            if not result.still:
                self._logger.info(
                    f'moving at {stamp * 1e-9:.3f} s; gyro bias z = {gi.bias[2]:.6f} rad/s '
                    f'(std {math.sqrt(gi.p_bias):.2e})')
        return self._publish(msg, stamp, accel)

    def _publish(self, raw: Imu, stamp: int, accel) -> Outputs:
        diag = self.diagnostics
        diag.last_stamp_ns = stamp
        if not self.listened(IMU):
            diag.count('unsubscribed')   # integrated, not published: nobody takes /imu/data
            return []
        gi = self.integrator
        # Packed straight into CDR bytes (ros/cdr.py): filling an rclpy Imu and having rclpy
        # convert and serialise it cost more than the integration.
        # Planar: roll and pitch are taken as zero (level IMU), so only yaw carries variance.
        rate_var = gi.rate_variance()
        out = imu_cdr(
            stamp, self._output_frame, quaternion.from_yaw(gi.heading),
            _HEADING_ONLY + (gi.heading_variance,), gi.rate,
            (rate_var, 0.0, 0.0, 0.0, rate_var, 0.0, 0.0, 0.0, rate_var),
            (float(accel[0]), float(accel[1]), float(accel[2])),
            raw.linear_acceleration_covariance.tolist())
        diag.count('published')
        return [(IMU, out)]


def main(args: list[str] | None = None) -> None:
    sys.exit(run_node(GyroIntegratorNode, args))
