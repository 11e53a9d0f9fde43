"""complementary_fusion: /wheel/odom + /imu/data + scan matching -> /odometry/filtered.

method 'ekf' (default): core.ekf_fusion (EKF with stochastic cloning of the scan matcher's
keyframes, per-input masks, gates and noise models; docs/fusion.md). method 'complementary':
the seed's complementary filter (core.fusion.ComplementaryFusion) on /scan_match/odom.
"""

from __future__ import annotations

import dataclasses
import math
import sys
import time
from typing import Any, Callable

import numpy as np
from diagnostic_msgs.msg import DiagnosticStatus
from geometry_msgs.msg import PoseWithCovarianceStamped
from nav_msgs.msg import Odometry
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from sensor_msgs.msg import Imu
from tf2_msgs.msg import TFMessage

from sensing_nodes.core.fusion.complementary import (
    ComplementaryMethod,
    FusionSettings,
    InputRecord,
    StampOrderedBuffer,
    pose_problem,
    watermark,
)
from sensing_nodes.core.fusion.ekf import (
    INPUT_DEFAULTS,
    EkfFusion,
    EkfSettings,
    InputConfig,
    input_config,
    with_mask,
)
from sensing_nodes.core.geometry.imu_mount import mount_rotation
from sensing_nodes.core.geometry.transform import Transform
from sensing_nodes.ros.cdr import odometry_cdr, transform_cdr
from sensing_nodes.ros.conversions import quaternion_to_yaw, ros_covariance_to_planar
from sensing_nodes.ros.diagnostics import Diagnostics
from sensing_nodes.ros.fusion_readings import (
    IMU,
    IMU_SOURCES,
    SCAN,
    WHEEL,
    ReadingConverter,
    unit_quaternion,
)
from sensing_nodes.ros.logging import ThrottledWarnings
from sensing_nodes.ros.params import ParameterError, declare, require
from sensing_nodes.ros.processor import Input, Output, Outputs, wire
from sensing_nodes.ros.qos import ESTIMATE_QOS, SENSOR_QOS, TF_QOS
from sensing_nodes.ros.run import run_node
from sensing_nodes.ros.tf import TF_TOPIC, ImuMount, imu_mount

# Processing rank at equal stamps: dead reckoning up to a stamp is in before the scan match
# at that stamp is fused.
RANK = {WHEEL: 0, IMU: 1, SCAN: 2}
RESTART = 'restart'   # in the reorder buffer: the input restarts here (a new IMU mount)


@dataclasses.dataclass(frozen=True)
class _Settings:
    """The node's own parameters (the inputs' EKF parameters are declared with the filter)."""

    method: str
    use_wheel: bool
    use_imu: bool
    use_scan_position: bool
    use_scan_heading: bool
    alpha: float | None          # complementary: None = 'auto'
    reorder_window_s: float
    max_gap_s: float
    publish_tf: bool


class ComplementaryFusionNode(Node):
    def __init__(self, **node_options) -> None:
        # node_options: rclpy Node keywords (sensing_pipeline passes this node's own cli_args)
        super().__init__('complementary_fusion', **node_options)
        settings = self._declare_settings()
        records = {WHEEL: InputRecord(WHEEL, settings.use_wheel),
                   IMU: InputRecord(IMU, settings.use_imu),
                   SCAN: InputRecord(SCAN, settings.use_scan_position
                                     or settings.use_scan_heading)}
        topics = {WHEEL: declare(self, 'wheel_odom.topic', '/wheel/odom', 'wheel odometry topic'),
                  IMU: declare(self, 'imu.topic', '/imu/data', 'IMU topic (sensor_msgs/Imu)')}
        self._imu_source = 'integrated'
        self._mount_rpy = (0.0, 0.0, 0.0)
        fusion, topics[SCAN] = self._make_fusion(settings)
        level = declare(self, 'level_with_imu_tilt', False,
                        "ekf, imu.source 'orientation': count only the horizontal part of body "
                        "velocities (the IMU's roll and pitch), for a robot on slopes")
        converter = ReadingConverter(
            settings.method, getattr(fusion, 'inputs', {}), self._imu_source,
            mount_rotation(*self._mount_rpy), level)
        self.diagnostics = Diagnostics(self, update=self._update_diagnostics)
        mount = None
        if settings.method == 'ekf' and settings.use_imu and self._imu_source != 'integrated':
            # The IMU's own orientation and rates are about its frame: /tf_static's base_frame
            # -> the Imu's frame_id gives the mount where published, imu.mount_*_rad otherwise
            # (gyro_integrator's output is already about base_link).
            mount = imu_mount(self, self._base_frame, self._mount_rpy,
                              on_update=lambda: self.processor.imu_mount_changed(),
                              diagnostics=self.diagnostics)
        self.processor = ComplementaryFusionProcessor(
            settings.method, fusion, records, topics, converter,
            StampOrderedBuffer(int(settings.reorder_window_s * 1e9)), self._imu_source,
            self._reset_jump_s, self._input_timeout_s, self._odom_frame, self._base_frame,
            settings.publish_tf, self.diagnostics, ThrottledWarnings(self), self.get_logger(),
            mount)
        self._last_arrival = time.monotonic()
        self._output_publishers = wire(
            self, [dataclasses.replace(i, handler=self._arrival(i.handler))
                   for i in self.processor.inputs()], self.processor.outputs())
        # robot_localization's set_pose as a topic: a service would need an interface package
        # of our own, which the PyPI-wheel setup cannot build.
        self.create_subscription(PoseWithCovarianceStamped, '~/set_pose', self._on_set_pose, 10)
        # Wall time (steady): held inputs are processed when the bag has paused or ended, when
        # /clock (use_sim_time) has stopped too.
        self.create_timer(self._flush_after_s / 2.0, self._flush_if_idle,
                          clock=Clock(clock_type=ClockType.STEADY_TIME))
        self.get_logger().info(f'method {settings.method}; inputs: ' + ', '.join(
            f'{name} ({topics[name]})' for name, r in records.items() if r.enabled))

    def _declare_settings(self) -> _Settings:
        """Declare and validate the node's own parameters (the frames, timeouts and flush on
        self, the rest returned)."""
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
        self._flush_after_s = declare(
            self,
            'flush_after_s',
            0.5,
            'wall time without input after which held inputs are processed',
            minimum=0.01,
            maximum=60.0,
        )
        max_gap_s = declare(
            self,
            'max_gap_s',
            2.0,
            'an input silent longer than this (stamp time) restarts its increments',
            minimum=0.001,
            maximum=3600.0,
        )
        self._reset_jump_s = declare(self, 'reset_on_backwards_jump_s', 0.0,
                                     'an input stamp more than this before the same input\'s '
                                     'previous one means time went backwards (looping bag): the '
                                     'filter resets', minimum=0.0)
        self._input_timeout_s = declare(
            self,
            'input_timeout_s',
            2.0,
            'an enabled input silent for this long is reported missing',
            minimum=0.01,
        )
        self._odom_frame = declare(self, 'odom_frame', 'odom', 'frame of the fused pose')
        self._base_frame = declare(
            self, 'base_frame', 'base_link', 'child frame of the fused pose'
        )
        publish_tf = declare(self, 'publish_tf', True,
                             'broadcast odom_frame -> base_frame on /tf with each output, stamped '
                             'as the output (one owner per tree: turn it off where another node '
                             'owns it)')

        require(method in ('ekf', 'complementary'), 'method', "must be 'ekf' or 'complementary'",
                method)
        if alpha == 'auto':
            alpha_value = None
        elif isinstance(alpha, (int, float)) and not isinstance(alpha, bool) \
                and 0.0 <= alpha <= 1.0:
            alpha_value = float(alpha)
        else:
            raise ParameterError('alpha', "must be a number in [0, 1] or 'auto'", alpha)
        require(use_wheel or use_imu or use_scan_pos or use_scan_heading, 'use_*',
                'at least one input must be enabled')
        require(bool(self._odom_frame) and bool(self._base_frame), 'odom_frame/base_frame',
                'must not be empty')
        return _Settings(method, use_wheel, use_imu, use_scan_pos, use_scan_heading, alpha_value,
                         window_s, max_gap_s, publish_tf)

    def _make_fusion(self, s: _Settings) -> tuple[Any, str]:
        """The filter the method names, with its parameters declared, and the scan-match topic
        it takes (keyframe-relative matches for the EKF)."""
        if s.method == 'ekf':
            configs = self._declare_ekf(s.use_wheel, s.use_imu, s.use_scan_position,
                                        s.use_scan_heading, s.max_gap_s, s.reorder_window_s)
            fusion = EkfFusion(configs, self._declare_ekf_settings())
            return fusion, declare(self, 'scan_match.topic', '/scan_match/keyframe_odom',
                                   'keyframe-relative scan matches (icp_matcher)')
        fusion = ComplementaryMethod(FusionSettings(
            use_wheel=s.use_wheel, use_gyro=s.use_imu, use_scan_position=s.use_scan_position,
            use_scan_heading=s.use_scan_heading, alpha=s.alpha, max_gap_s=s.max_gap_s))
        return fusion, declare(self, 'scan_match.topic', '/scan_match/odom',
                               'scan matching poses (icp_matcher)')

    def _declare_ekf_settings(self) -> EkfSettings:
        """The EKF's process noise (ekf.*)."""
        return EkfSettings(
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

    def _arrival(self, handler: Callable[[Any], Outputs]) -> Callable[[Any], Outputs]:
        """The handler, noting the wall time of each input (the idle flush's clock)."""
        def on_message(msg: Any) -> Outputs:
            self._last_arrival = time.monotonic()
            return handler(msg)
        return on_message

    _DESCRIPTIONS = {
        'mask': 'quantities fused, of x, y, yaw, vx, vy, vyaw (robot_localization order)',
        'pose_mode': "pose quantities: 'absolute', 'relative' (to the first message) or "
                     "'differential' (the motion between consecutive messages)",
        'covariance': "'auto' (the message's unless static or zero, then the noise model), "
                      "'message' or 'model'",
        'covariance_scale': "the message's covariance times this (distrust: > 1)",
        'variance_per_m': 'noise model: x/y variance per metre travelled (m^2/m)',
        'variance_per_rad': 'noise model: yaw variance per radian turned (rad^2/rad)',
        'yaw_variance_per_m': 'noise model: yaw variance per metre travelled (rad^2/m)',
        'yaw_variance_per_s': 'noise model: yaw variance per second (rad^2/s)',
        'twist_variance': 'vx, vy, vyaw variances when the message has none',
        'gate_chi2': 'refuse a measurement whose squared Mahalanobis distance exceeds this '
                     '(chi-square value); 0 = no gate',
        'max_gap_s': 'differential: no increment across a longer silence of this input (s); '
                     "0 = the node's max_gap_s, else the shorter of the two",
        'heading_delay_s': "how far the input's heading lags its stamp (s): its yaw is read as "
                           'yaw + yaw rate x this (sensor_sim: half its IMU period)',
        'delay_s': "how far the input's stamps lag the robot (s): a message stamped t is fused "
                   'and published as at t - this (< 0: stamps early); within +-reorder_window_s',
    }

    def _declare_input(self, name: str, enabled: bool, window_s: float, **fixed
                       ) -> InputConfig | None:
        """Declare one input's EKF parameters (name.*) and return its validated config."""
        values = {}
        for key, default in INPUT_DEFAULTS[name].items():
            numeric = isinstance(default, float) and key != 'delay_s'   # delay_s may be < 0
            values[key] = declare(self, f'{name}.{key}', default, self._DESCRIPTIONS[key],
                                  minimum=0.0 if numeric else None)
        try:
            cfg = input_config(name, values, **fixed)
        except ValueError as error:
            raise ParameterError(f'{name}.mask', str(error), values['mask']) from None
        for field, problem, value in cfg.problems():
            require(not enabled, f'{name}.{field}', problem, value)
        # A retimed input lags (or leads) the others by delay_s in stamp time: the reorder
        # buffer must hold the others that long, or its messages are dropped as late.
        require(not enabled or abs(cfg.delay_s) <= window_s, f'{name}.delay_s',
                f'must be within the reorder window (|delay_s| <= reorder_window_s = '
                f'{window_s:g} s)', cfg.delay_s)
        return cfg if enabled else None

    def _declare_ekf(self, use_wheel, use_imu, use_scan_pos, use_scan_heading, max_gap_s,
                     window_s) -> tuple[InputConfig, ...]:
        self._imu_source = declare(self, 'imu.source', 'integrated',
                                   "'integrated' (gyro_integrator's heading), 'orientation' "
                                   "(the IMU's own orientation) or 'rate' (raw gyro rate, bias "
                                   'estimated in the filter)')
        require(self._imu_source in IMU_SOURCES, 'imu.source', f'must be one of {IMU_SOURCES}',
                self._imu_source)
        self._mount_rpy = tuple(
            declare(self, f'imu.mount_{axis}_rad', 0.0,
                    f'IMU mount {axis} in base_link (rad, ZYX); upside down: roll = pi; '
                    "the fallback where /tf_static gives no base_frame -> the Imu's frame_id",
                    minimum=-2 * math.pi, maximum=2 * math.pi)
            for axis in ('roll', 'pitch', 'yaw'))
        configs = [
            self._declare_input(WHEEL, use_wheel, window_s, max_gap_s=max_gap_s),
            self._declare_input(IMU, use_imu, window_s, max_gap_s=max_gap_s,
                                gyro_bias=self._imu_source == 'rate'),
            self._declare_input(SCAN, use_scan_pos or use_scan_heading, window_s,
                                max_gap_s=max_gap_s, keyframes=True),
        ]
        scan = configs[2]
        if scan is not None:
            # use_scan_match_position / _heading switch the scan's quantities off.
            configs[2] = with_mask(scan, **({} if use_scan_pos else {'x': False, 'y': False}),
                                   **({} if use_scan_heading else {'yaw': False}))
        return tuple(cfg for cfg in configs if cfg is not None)

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
    """complementary_fusion's per-message logic (ros/processor.py): /wheel/odom, /imu/data and
    scan matches (topics from the parameters) -> /odometry/filtered (odom_frame -> base_frame,
    m and rad), inputs fused in stamp order through the reorder buffer. Nothing here reads a
    clock: `flush` processes what is held (the node calls it after flush_after_s of wall time
    without input, sensing_pipeline at the end of the bag)."""

    def __init__(self, method: str, fusion, records: dict[str, InputRecord],
                 topics: dict[str, str], converter: ReadingConverter,
                 buffer: StampOrderedBuffer, imu_source: str, reset_jump_s: float,
                 input_timeout_s: float, odom_frame: str, base_frame: str, publish_tf: bool,
                 diagnostics: Diagnostics, warnings: ThrottledWarnings, logger,
                 imu_mount: ImuMount | None = None) -> None:
        self._method = method
        self._fusion = fusion
        self._records = records
        self._topics = topics
        self._converter = converter
        self._buffer = buffer
        self._imu_source = imu_source
        self._reset_jump_s = reset_jump_s
        self._input_timeout_s = input_timeout_s
        self._odom_frame, self._base_frame = odom_frame, base_frame
        self._publish_tf = publish_tf
        self._tf_stamp: int | None = None   # stamp of the last transform sent
        self._start_ns: int | None = None
        # The filter starts at the first stamp by which every enabled input has spoken (or
        # when the reorder buffer stops waiting for a silent one): started on one input alone
        # it follows that input's start-up transients, e.g. gyro_integrator's heading before
        # its first bias estimate, which the wheels would have refused (a fusion subscribed a
        # moment after the wheels started ended 0.15 deg off and refused every scan match).
        self._first_ns: dict[str, int] = {}
        self._started = False
        self.diagnostics = diagnostics   # counted here, published by the node
        self._warnings = warnings
        self._logger = logger
        # The IMU's mount (orientation and rate sources), resolved per Imu frame id, again
        # after /tf_static changes: (frame id, rotation into base_link)
        self._imu_mount = imu_mount
        self._imu_mount_for: tuple[str, np.ndarray] | None = None
        self._imu_read = False   # an Imu has been read: a new mount from now on restarts it

    def inputs(self) -> list[Input]:
        imu_qos = SENSOR_QOS if self._imu_source != 'integrated' else ESTIMATE_QOS
        kinds = {WHEEL: (Odometry, ESTIMATE_QOS), IMU: (Imu, imu_qos),
                 SCAN: (Odometry, ESTIMATE_QOS)}
        return [Input(self._topics[name], kinds[name][0], kinds[name][1],
                      lambda m, name=name: self.on_message(name, m), decoded=True)
                for name in (WHEEL, IMU, SCAN) if self._records[name].enabled]

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
            self._records[IMU].origin = None
            self._buffer.push(stamp, RANK[IMU], (IMU, RESTART))

    def held(self) -> int:
        """How many inputs the reorder buffer holds."""
        return len(self._buffer)

    def flush(self) -> Outputs:
        """Process everything held (end of a stream, or no input for a while)."""
        return self._process(self._buffer.flush())

    # -- input -------------------------------------------------------------------------------
    def on_message(self, source: str, msg) -> Outputs:
        stamp = self._converter.stamp_ns(source, msg)   # less the input's delay_s
        record = self._records[source]
        record.received += 1
        # Before the message is read: reading it uses per-timeline state (a source's starting
        # pose), which must already be the new timeline's.
        if record.arrived_ns is not None and record.arrived_ns - stamp > self._reset_jump_s * 1e9:
            self._logger.warn(
                f'{source} stamp {stamp * 1e-9:.3f} s is {(record.arrived_ns - stamp) * 1e-9:.3f} '
                's before its previous one: time went backwards (looping bag or restarted '
                'clock); resetting')
            self.diagnostics.count('resets')
            out = self._process(self._buffer.flush())  # what was held: the old timeline
            self._reset()
        else:
            out = []
        if source == IMU and self._imu_mount is not None:
            self._apply_imu_mount(msg.header.frame_id, stamp)
        reading, problem = self._converter.reading(source, msg, stamp, record)
        if reading is None:
            self.diagnostics.count(f'{source}_rejected')
            self._warnings.warn(f'{source}_rejected: {problem}',
                                f'{source}: rejected a message ({problem})')
            return out
        if not self._buffer.push(stamp, RANK[source], (source, reading)):
            self.diagnostics.count(f'{source}_dropped_late')
            self._warnings.warn(
                f'{source}_late',
                f'{source} message at {stamp * 1e-9:.3f} s arrived after inputs up to '
                f'{self._buffer.released_ns * 1e-9:.3f} s were fused: dropped '
                f'({self._buffer.late} so far)')
            return out
        if self._start_ns is None:
            self._start_ns = stamp
        self._first_ns[source] = min(stamp, self._first_ns.get(source, stamp))
        record.arrived_ns = stamp if record.arrived_ns is None else max(record.arrived_ns, stamp)
        return out + self._process(self._buffer.pop_ready(watermark(
            list(self._records.values()), self._buffer.newest_ns, self._start_ns,
            self._input_timeout_s)))

    def set_pose(self, msg: PoseWithCovarianceStamped) -> Outputs:
        """robot_localization's set_pose: what is held is fused first, then the pose is set."""
        p = msg.pose.pose
        pose = (float(p.position.x), float(p.position.y), quaternion_to_yaw(p.orientation))
        cov = ros_covariance_to_planar(msg.pose.covariance)
        problem = '' if unit_quaternion(p.orientation) else 'orientation is not a unit quaternion'
        problem = problem or pose_problem(pose, cov, None, True)
        if problem:
            self.diagnostics.count('set_pose_rejected')
            self._logger.warn(f'set_pose rejected: {problem}')
            return []
        out = self._process(self._buffer.flush())
        self._fusion.set_pose(pose, cov)
        self.diagnostics.count('set_pose')
        self._logger.info('pose set to x=%.3f m, y=%.3f m, yaw=%.3f rad' % pose)
        return out

    def _reset(self) -> None:
        self._fusion.reset()
        self._buffer.clear()
        for record in self._records.values():
            record.clear()
        self._start_ns = None
        self._first_ns.clear()
        self._started = False
        self._tf_stamp = None
        self._converter.reset()
        # /diagnostics carries the newest stamp of the new timeline (sensing_replay's warm-up
        # plays stamps after the bag's end: every status of the pass carried them)
        self.diagnostics.last_stamp_ns = 0

    # -- fusion and output ---------------------------------------------------------------------
    def _process(self, ready) -> Outputs:
        out: Outputs = []
        held = None   # (stamp, pose) of the newest output not yet on /tf
        for stamp, (source, reading) in ready:
            if reading is RESTART:
                self._fusion.restart(source)
                continue
            if not self._started and self._before_every_input(stamp):
                self.diagnostics.count('before_every_input')
                continue
            self._records[source].processed_at(stamp)
            self._fusion.update(source, reading)
            if source == IMU and (self._records[WHEEL].enabled or self._records[SCAN].enabled):
                continue  # heading only: published with the next position update
            state = self._fusion.state   # computed once: the odometry and /tf both use it
            published = self._publish(stamp, state)
            out += published
            if published and self._publish_tf:
                if held is not None and held[0] != stamp:
                    out += self._transform(*held)
                held = (stamp, state.pose)
        if held is not None:
            out += self._transform(*held)
        return out

    def _before_every_input(self, stamp: int) -> bool:
        """True for a reading older than the first of some enabled input (not fused); the
        first reading that is not starts the filter."""
        enabled = [name for name, record in self._records.items() if record.enabled]
        if all(name in self._first_ns for name in enabled):
            start = max(self._first_ns[name] for name in enabled)
            if stamp < start:
                return True
            skipped = self.diagnostics.counts.get('before_every_input', 0)
            if skipped:
                self._logger.info(f'every input has spoken: fusing from {start * 1e-9:.3f} s; '
                                  f'{skipped} earlier readings not fused')
        else:
            silent = [name for name in enabled if name not in self._first_ns]
            self._logger.warn(f'starting without {", ".join(silent)} (silent for '
                              f'{self._input_timeout_s:g} s of stamps)')
        self._started = True
        return False

    def _transform(self, stamp: int, pose) -> Outputs:
        """odom -> base_link at the output's stamp (the input just fused: never ahead of the
        inputs). tf2 keeps one sample per stamp and drops a repeat with a TF_REPEATED_DATA
        warning, so of the outputs at one stamp (a wheel and a scan-match update) the last of a
        batch goes out, once."""
        if stamp == self._tf_stamp:
            return []
        self._tf_stamp = stamp
        return [(TF_TOPIC, transform_cdr(stamp, self._odom_frame, self._base_frame,   # ros/cdr.py
                                         Transform.from_planar(*pose)))]

    def _publish(self, stamp: int, state) -> Outputs:
        if state is None:
            return []
        twist, twist_cov = getattr(state, 'twist', (0.0, 0.0, 0.0)), \
            getattr(state, 'twist_covariance', None)
        self.diagnostics.count('published')
        self.diagnostics.last_stamp_ns = max(self.diagnostics.last_stamp_ns, stamp)
        return [('/odometry/filtered', odometry_cdr(   # CDR bytes: see ros/cdr.py
            stamp, self._odom_frame, self._base_frame, state.pose, state.covariance,
            twist, twist_cov))]

    def update_diagnostics(self, diag: Diagnostics) -> None:
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
