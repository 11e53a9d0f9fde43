"""complementary_fusion: /wheel/odom + /imu/data + scan matching -> /odometry/filtered.

The node declares its parameters (core/fusion/config.py's tables), builds the fusion's
configuration from their values as the offline tools do (`FusionParameters.session_config`),
and runs the fusion's timeline (core/fusion/session.py: the EKF of core/fusion/ekf.py by
default, or the seed's complementary filter) through its processor: message conversion
(ros/fusion_readings.py), the IMU mount from /tf_static, and publishing.
"""

from __future__ import annotations

import dataclasses
import sys
import time
from typing import Any, Callable

import numpy as np
from diagnostic_msgs.msg import DiagnosticStatus
from geometry_msgs.msg import PoseWithCovarianceStamped
from nav_msgs.msg import Odometry
from rclpy.clock import Clock, ClockType
from sensor_msgs.msg import Imu
from tf2_msgs.msg import TFMessage

from sensing_nodes.core.fusion.config import FUSION_PARAMETERS
from sensing_nodes.core.fusion.inputs import IMU, INPUTS, SCAN, WHEEL
from sensing_nodes.core.fusion.session import FusedOutput, FusionSession
from sensing_nodes.core.geometry.transform import Transform
from sensing_nodes.ros.cdr import odometry_cdr, transform_cdr
from sensing_nodes.ros.conversions import quaternion_to_yaw, ros_covariance_to_planar
from sensing_nodes.ros.diagnostics import Diagnostics
from sensing_nodes.ros.fusion_readings import ReadingConverter, unit_quaternion
from sensing_nodes.ros.logging import ThrottledWarnings
from sensing_nodes.ros.params import declare, declare_config, refuse_retired
from sensing_nodes.ros.processing_node import ProcessingNode
from sensing_nodes.ros.processor import Input, Output, Outputs, wire
from sensing_nodes.ros.qos import ESTIMATE_QOS, SENSOR_BACKLOG_QOS, TF_QOS
from sensing_nodes.ros.run import run_node
from sensing_nodes.ros.tf import TF_TOPIC, ImuMount, imu_mount


class ComplementaryFusionNode(ProcessingNode):
    def __init__(self, **node_options) -> None:
        # node_options: rclpy Node keywords (sensing_pipeline passes this node's own cli_args)
        # and `lifecycle` (ros/processing_node.py)
        super().__init__('complementary_fusion', **node_options)

    def configure(self) -> None:
        # The parameters of the method the `method` parameter names.
        method = declare(self, FUSION_PARAMETERS['ekf']['method'])
        refuse_retired(self, {f'{name}.gate_chi2': f'is gone: every input has a gate, set by '
                              f'{name}.gate_probability (the chi-square quantile of its rows; '
                              '0.999 by default)' for name in INPUTS})
        config = declare_config(self, FUSION_PARAMETERS.get(
            method, FUSION_PARAMETERS['ekf'])).session_config()
        self.diagnostics = Diagnostics(self, update=self._update_diagnostics)
        session = FusionSession(config, counts=self.diagnostics.counts)
        converter = ReadingConverter.for_config(config)
        mount = None
        if config.method == 'ekf' and config.enabled[IMU] and config.imu_source != 'integrated':
            # The IMU's own orientation and rates are about its frame: /tf_static's base_frame
            # -> the Imu's frame_id gives the mount where published, imu.mount_*_rad otherwise
            # (gyro_integrator's output is already about base_link).
            mount = imu_mount(self, config.base_frame, config.imu_mount_rpy,
                              on_update=lambda: self.processor.imu_mount_changed(),
                              diagnostics=self.diagnostics)
        self.processor = ComplementaryFusionProcessor(
            session, converter, self.diagnostics, ThrottledWarnings(self), self.get_logger(),
            mount)
        self._flush_after_s = config.flush_after_s
        self._last_arrival = time.monotonic()
        self._output_publishers = wire(
            self, [dataclasses.replace(i, handler=self._arrival(i.handler))
                   for i in self.processor.inputs()], self.processor.outputs())
        # robot_localization's set_pose as a topic: a service would need an interface package
        # of our own, which the PyPI-wheel setup cannot build.
        self.create_subscription(PoseWithCovarianceStamped, '~/set_pose',
                                 self.when_active(self._on_set_pose), 10)
        # Wall time (steady): held inputs are processed when the bag has paused or ended, when
        # /clock (use_sim_time) has stopped too.
        self.create_timer(self._flush_after_s / 2.0, self._flush_if_idle,
                          clock=Clock(clock_type=ClockType.STEADY_TIME))
        self.get_logger().info(f'method {config.method}; inputs: ' + ', '.join(
            f'{name} ({config.topics[name]})' for name in INPUTS if config.enabled[name]))

    def _arrival(self, handler: Callable[[Any], Outputs]) -> Callable[[Any], Outputs]:
        """The handler, noting the wall time of each input (the idle flush's clock)."""
        def on_message(msg: Any) -> Outputs:
            self._last_arrival = time.monotonic()
            return handler(msg)
        return on_message

    def _on_set_pose(self, msg: PoseWithCovarianceStamped) -> None:
        for topic, out in self.processor.set_pose(msg):
            self._output_publishers[topic].publish(out)

    def _flush_if_idle(self) -> None:
        if self.processor.held() and time.monotonic() - self._last_arrival > self._flush_after_s:
            for topic, out in self.processor.flush():
                self._output_publishers[topic].publish(out)

    def _update_diagnostics(self, diag: Diagnostics) -> None:
        self.processor.update_diagnostics(diag)


class ComplementaryFusionProcessor:
    """complementary_fusion's per-message logic (ros/processor.py): messages of /wheel/odom,
    /imu/data and scan matches (topics from the parameters) -> readings (ros/fusion_readings.py)
    -> the fusion session -> /odometry/filtered and /tf (odom_frame -> base_frame, m and rad).
    Nothing here reads a clock: `flush` processes what is held (the node calls it after
    flush_after_s of wall time without input, sensing_pipeline at the end of the bag)."""

    def __init__(self, session: FusionSession, converter: ReadingConverter,
                 diagnostics: Diagnostics, warnings: ThrottledWarnings, logger,
                 imu_mount: ImuMount | None = None) -> None:
        self.session = session
        config = session.config
        self._converter = converter
        self._imu_source = config.imu_source
        self._topics = config.topics
        self._odom_frame, self._base_frame = config.odom_frame, config.base_frame
        self._publish_tf = config.publish_tf
        self._tf_stamp: int | None = None   # stamp of the last transform sent
        self.diagnostics = diagnostics   # counted here and by the session, published by the node
        self._warnings = warnings
        self._logger = logger
        # The IMU's mount (orientation and rate sources), resolved per Imu frame id, again
        # after /tf_static changes: (frame id, rotation into base_link)
        self._imu_mount = imu_mount
        self._imu_mount_for: tuple[str, np.ndarray] | None = None
        self._imu_read = False   # an Imu has been read: a new mount from now on restarts it

    def inputs(self) -> list[Input]:
        # The driver's Imu (orientation, rate: best effort, a deep queue: the fusion is the
        # graph's busiest node) or gyro_integrator's heading (reliable).
        imu_qos = SENSOR_BACKLOG_QOS if self._imu_source != 'integrated' else ESTIMATE_QOS
        kinds = {WHEEL: (Odometry, ESTIMATE_QOS), IMU: (Imu, imu_qos),
                 SCAN: (Odometry, ESTIMATE_QOS)}
        return [Input(self._topics[name], kinds[name][0], kinds[name][1],
                      lambda m, name=name: self.on_message(name, m), decoded=True)
                for name in INPUTS if self.session.config.enabled[name]]

    def outputs(self) -> list[Output]:
        return [Output('/odometry/filtered', Odometry, ESTIMATE_QOS)] + \
            ([Output(TF_TOPIC, TFMessage, TF_QOS)] if self._publish_tf else [])

    def imu_mount_changed(self) -> None:
        """/tf_static changed: resolve the IMU mount again at the next IMU message."""
        self._imu_mount_for = None

    def _apply_imu_mount(self, frame: str, stamp: int) -> None:
        """The mount of the IMU frame (from /tf_static, else the parameters) into the reading
        converter. A mount that changes once the IMU has been read (a late /tf_static) applies
        from this message on, and the IMU input restarts there in stamp order (its increments
        and relative origin were measured with the old mount): counted as imu_mount_changes."""
        if self._imu_mount_for is not None and self._imu_mount_for[0] == frame:
            return
        rotation, _ = self._imu_mount.resolve(frame)
        rotation = np.eye(3) if rotation is None else rotation
        started, self._imu_read = self._imu_read, True
        self._imu_mount_for = (frame, rotation)
        if np.allclose(rotation, self._converter.mount, atol=1e-12):
            return
        self._converter.set_mount(rotation)
        if started:
            self.diagnostics.count('imu_mount_changes')
            self._logger.warn(f'IMU mount of {frame!r} changed (/tf_static): applied from the Imu '
                              f'at {stamp * 1e-9:.3f} s on, where the IMU input restarts')
            self.session.restart(IMU, stamp)

    def held(self) -> int:
        """How many inputs the reorder buffer holds."""
        return self.session.held()

    def flush(self) -> Outputs:
        """Process everything held (end of a stream, or no input for a while)."""
        return self._published(self.session.flush())

    # -- input -------------------------------------------------------------------------------
    def on_message(self, source: str, msg) -> Outputs:
        session = self.session
        stamp = self._converter.stamp_ns(source, msg)   # less the input's delay_s
        resets = session.resets
        out = self._published(session.arrive(source, stamp))
        if session.resets != resets:
            self._new_timeline()
        if source == IMU and self._imu_mount is not None:
            self._apply_imu_mount(msg.header.frame_id, stamp)
        reading, problem = self._converter.reading(source, msg, stamp, session.records[source])
        if reading is None:
            session.reject(source, problem)
        else:
            out += self._published(session.add(source, reading))
        if session.notices:
            self._tell(session.take_notices())
        return out

    def set_pose(self, msg: PoseWithCovarianceStamped) -> Outputs:
        """robot_localization's set_pose: what is held is fused first, then the pose is set."""
        p = msg.pose.pose
        pose = (float(p.position.x), float(p.position.y), quaternion_to_yaw(p.orientation))
        problem = '' if unit_quaternion(p.orientation) else 'orientation is not a unit quaternion'
        out = self._published(self.session.set_pose(
            pose, ros_covariance_to_planar(msg.pose.covariance), problem))
        self._tell(self.session.take_notices())
        return out

    def _new_timeline(self) -> None:
        """Time went backwards and the session started again: so do the converter and /tf."""
        self._tf_stamp = None
        self._converter.reset()
        # /diagnostics carries the newest stamp of the new timeline (sensing_replay's warm-up
        # plays stamps after the bag's end: every status of the pass carried them)
        self.diagnostics.last_stamp_ns = 0

    def _tell(self, notices) -> None:
        """The session's notices in the log (a keyed warning throttled per key)."""
        for notice in notices:
            if notice.key is not None:
                self._warnings.warn(notice.key, notice.text)
            elif notice.level == 'info':
                self._logger.info(notice.text)
            else:
                self._logger.warn(notice.text)

    # -- output ------------------------------------------------------------------------------
    def _published(self, fused: list[FusedOutput]) -> Outputs:
        """/odometry/filtered for each output and odom -> base_link at its stamp on /tf (the
        input just fused: never ahead of the inputs). tf2 keeps one sample per stamp and drops a
        repeat with a TF_REPEATED_DATA warning, so of the outputs at one stamp (a wheel and a
        scan-match update) the last of a batch goes out, once."""
        out: Outputs = []
        held = None   # (stamp, pose) of the newest output not yet on /tf
        for stamp, state in fused:
            self.diagnostics.count('published')
            self.diagnostics.last_stamp_ns = max(self.diagnostics.last_stamp_ns, stamp)
            out.append(('/odometry/filtered', odometry_cdr(   # CDR bytes: see ros/cdr.py
                stamp, self._odom_frame, self._base_frame, state.pose, state.covariance,
                state.twist, state.twist_covariance)))
            if self._publish_tf:
                if held is not None and held[0] != stamp:
                    out += self._transform(*held)
                held = (stamp, state.pose)
        if held is not None:
            out += self._transform(*held)
        return out

    def _transform(self, stamp: int, pose) -> Outputs:
        if stamp == self._tf_stamp:
            return []
        self._tf_stamp = stamp
        return [(TF_TOPIC, transform_cdr(stamp, self._odom_frame, self._base_frame,   # ros/cdr.py
                                         Transform.from_planar(*pose)))]

    def update_diagnostics(self, diag: Diagnostics) -> None:
        session = self.session
        newest = session.buffer.newest_ns
        missing = []
        for name, record in session.records.items():
            if not record.enabled:
                diag.values[f'{name}_state'] = 'disabled'
                continue
            age = record.age_s(newest)
            diag.values[f'{name}_received'] = str(record.received)
            diag.values[f'{name}_age_s'] = f'{age:.3f}'
            diag.values[f'{name}_rate_hz'] = f'{record.rate_hz():.2f}'
            if age > session.config.input_timeout_s:
                missing.append(name)
        distrusted = []
        for name, figures in session.integrity().items():
            diag.values[f'{name}_fused'] = str(figures['fused'])
            diag.values[f'{name}_refused'] = str(figures['refused'])
            diag.values[f'{name}_blamed'] = str(figures['blamed'])
            diag.values[f'{name}_reacquired'] = str(figures['reacquired'])
            diag.values[f'{name}_refused_share'] = f"{figures['refused_share']:.3f}"
            diag.values[f'{name}_noise_scale'] = f"{figures['noise_scale']:.3g}"
            diag.values[f'{name}_last_problem'] = figures['last_problem'] or 'none'
            if figures['distrusted']:
                distrusted.append(f"{name} ({figures['last_problem']})")
        diag.values['method'] = session.config.method
        # The outputs' rate and how far they trail the newest input (stamp time): the reorder
        # buffer's hold, the output period, inputs that give no output.
        lag, most = session.output_lag_s()
        diag.values['publish_rate_hz'] = f'{session.config.publish_rate_hz:g}'
        diag.values['output_rate_hz'] = f'{session.outputs.rate_hz():.2f}'
        diag.values['output_lag_s'] = f'{lag:.3f}'
        diag.values['output_lag_max_s'] = f'{most:.3f}'
        diag.values['fusion_updates'] = str(session.fusion.updates)
        diag.values['late_dropped_total'] = str(session.buffer.late)
        if missing or distrusted:
            parts = (['missing: ' + ', '.join(missing)] if missing else []) + \
                (['distrusted: ' + '; '.join(distrusted)] if distrusted else [])
            diag.level, diag.message = DiagnosticStatus.WARN, ' | '.join(parts)
        else:
            diag.level, diag.message = DiagnosticStatus.OK, 'all enabled inputs present'


def main(args=None):
    sys.exit(run_node(ComplementaryFusionNode, args))
