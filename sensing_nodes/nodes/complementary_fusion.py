"""complementary_fusion: /wheel/odom + /imu/data + /scan_match/odom -> /odometry/filtered."""

from __future__ import annotations

import math
import sys
import time

import numpy as np
from diagnostic_msgs.msg import DiagnosticStatus
from nav_msgs.msg import Odometry
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.node import Node
from sensor_msgs.msg import Imu

from sensing_nodes.core.fusion import ComplementaryFusion, FusionSettings, StampOrderedBuffer
from sensing_nodes.ros.conversions import (
    make_odometry,
    odometry_pose,
    odometry_twist,
    quaternion_to_yaw,
    stamp_to_ns,
)
from sensing_nodes.ros.diagnostics import Diagnostics
from sensing_nodes.ros.logging import ThrottledWarnings
from sensing_nodes.ros.params import ParameterError, declare, require
from sensing_nodes.ros.qos import ESTIMATE_QOS
from sensing_nodes.ros.run import run_node

# Processing rank at equal stamps: dead reckoning up to a stamp is in before the scan match
# at that stamp is fused.
WHEEL, GYRO, SCAN = 0, 1, 2
INPUT_NAMES = {WHEEL: 'wheel_odom', GYRO: 'imu', SCAN: 'scan_match'}


def unit_quaternion(q) -> bool:
    """Finite and of unit length (within 1 %): an infinite or all-zero orientation still gives
    a finite yaw from atan2, but it is no rotation at all."""
    norm2 = q.x * q.x + q.y * q.y + q.z * q.z + q.w * q.w
    return math.isfinite(norm2) and abs(norm2 - 1.0) <= 0.02


class ComplementaryFusionNode(Node):
    def __init__(self) -> None:
        super().__init__('complementary_fusion')
        use_wheel = declare(self, 'use_wheel_odom', True, 'fuse x/y increments of /wheel/odom')
        use_gyro = declare(self, 'use_imu', True, 'heading increments from /imu/data orientation')
        use_scan_pos = declare(self, 'use_scan_match_position', True,
                               'fuse x/y increments of /scan_match/odom')
        use_scan_heading = declare(self, 'use_scan_match_heading', True,
                                   'absolute heading from /scan_match/odom (complementary filter)')
        alpha = self.declare_parameter(
            'alpha', 0.98, ParameterDescriptor(
                description="complementary filter weight of the gyro-propagated heading, in "
                            "[0, 1], or 'auto' to derive it each update from the two variances",
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

        if alpha == 'auto':
            alpha_value = None
        elif isinstance(alpha, (int, float)) and not isinstance(alpha, bool) and 0.0 <= alpha <= 1.0:
            alpha_value = float(alpha)
        else:
            raise ParameterError('alpha', "must be a number in [0, 1] or 'auto'", alpha)
        require(use_wheel or use_gyro or use_scan_pos or use_scan_heading, 'use_*',
                'at least one input must be enabled')
        require(bool(self._odom_frame) and bool(self._base_frame), 'odom_frame/base_frame',
                'must not be empty')

        self._fusion = ComplementaryFusion(FusionSettings(
            use_wheel=use_wheel, use_gyro=use_gyro, use_scan_position=use_scan_pos,
            use_scan_heading=use_scan_heading, alpha=alpha_value, max_gap_s=max_gap_s))
        self._buffer = StampOrderedBuffer(int(window_s * 1e9))
        self._enabled = {WHEEL: use_wheel, GYRO: use_gyro, SCAN: use_scan_pos or use_scan_heading}
        self._last_stamp = {k: None for k in INPUT_NAMES}
        self._received = {k: 0 for k in INPUT_NAMES}
        self._arrived = {k: None for k in INPUT_NAMES}
        self._start_ns: int | None = None
        self._processed = {k: 0 for k in INPUT_NAMES}
        self._first_stamp = {k: None for k in INPUT_NAMES}
        self._accepted_first = {k: False for k in INPUT_NAMES}
        self._origin: dict[int, object] = {}
        self._previous_scan_stamp: int | None = None
        self._last_arrival = time.monotonic()

        self._warnings = ThrottledWarnings(self)
        self._publisher = self.create_publisher(Odometry, '/odometry/filtered', ESTIMATE_QOS)
        self.diagnostics = Diagnostics(self, update=self._update_diagnostics)
        if use_wheel:
            self.create_subscription(Odometry, '/wheel/odom',
                                     lambda m: self._on_message(WHEEL, m), ESTIMATE_QOS)
        if use_gyro:
            self.create_subscription(Imu, '/imu/data', lambda m: self._on_message(GYRO, m),
                                     ESTIMATE_QOS)
        if use_scan_pos or use_scan_heading:
            self.create_subscription(Odometry, '/scan_match/odom',
                                     lambda m: self._on_message(SCAN, m), ESTIMATE_QOS)
        self.create_timer(self._flush_after_s / 2.0, self._flush_if_idle)

    # -- input -------------------------------------------------------------------------------
    def _on_message(self, source: int, msg) -> None:
        self._last_arrival = time.monotonic()
        stamp = stamp_to_ns(msg.header.stamp)
        name = INPUT_NAMES[source]
        self._received[source] += 1
        # Before the message is read: reading it uses per-timeline state (a source's starting
        # pose), which must already be the new timeline's.
        previous = self._arrived[source]
        if previous is not None and previous - stamp > self._reset_jump_s * 1e9:
            self.get_logger().warn(
                f'{name} stamp {stamp * 1e-9:.3f} s is {(previous - stamp) * 1e-9:.3f} s before its '
                'previous one: time went backwards (looping bag or restarted clock); resetting')
            self.diagnostics.count('resets')
            self._process(self._buffer.flush())  # what was held belongs to the old timeline
            self._reset()
        reading = self._reading(source, msg)
        if reading is None:
            return
        if not self._buffer.push(stamp, source, reading):
            self.diagnostics.count(f'{name}_dropped_late')
            self._warnings.warn(
                f'{name}_late',
                f'{name} message at {stamp * 1e-9:.3f} s arrived after inputs up to '
                f'{self._buffer.released_ns * 1e-9:.3f} s were fused: dropped '
                f'({self._buffer.late} so far)')
            return
        if self._start_ns is None:
            self._start_ns = stamp
        self._arrived[source] = stamp if self._arrived[source] is None else max(self._arrived[source], stamp)
        self._process(self._buffer.pop_ready(self._watermark()))

    def _watermark(self) -> int | None:
        """The stamp every live input has reached: nothing at or before it can still arrive
        (each input arrives in order), so it can be processed without waiting for the window.
        An enabled input not heard from for input_timeout_s (stamp time) is not waited for."""
        newest = self._buffer.newest_ns
        timeout_ns = self._input_timeout_s * 1e9
        reached = []
        for source, enabled in self._enabled.items():
            if not enabled:
                continue
            last = self._arrived[source]
            if last is None:
                if newest - self._start_ns <= timeout_ns:
                    return None  # not heard from yet, but may still be starting up
                continue
            if newest - last <= timeout_ns:
                reached.append(last)
        return min(reached) if reached else None

    def _reading(self, source: int, msg):
        """Validated (pose or yaw, covariance) from a message, or None after a warning."""
        name = INPUT_NAMES[source]
        if source == GYRO:
            yaw_var = float(msg.orientation_covariance[8])
            yaw = quaternion_to_yaw(msg.orientation)
            if not self._accepted_first[source]:
                self._origin[source] = yaw
            ok = unit_quaternion(msg.orientation) and math.isfinite(yaw_var) and (
                yaw_var > 0.0 or (yaw_var == 0.0 and yaw == self._origin[source]))
            if msg.orientation_covariance[0] == -1.0:
                ok = False
            reading = (yaw, yaw_var)
        else:
            pose, cov = odometry_pose(msg)
            diagonal = np.diag(cov)
            if not self._accepted_first[source]:
                self._origin[source] = pose
            ok = bool(unit_quaternion(msg.pose.pose.orientation)
                      and np.all(np.isfinite(pose)) and np.all(np.isfinite(cov)) and (
                          np.all(diagonal > 0.0) or
                          (np.all(diagonal == 0.0) and pose == self._origin[source])))
            reading = (pose, cov)
        if not ok:
            self.diagnostics.count(f'{name}_rejected')
            self._warnings.warn(
                f'{name}_rejected',
                f'{name}: rejected a message whose pose or covariance is NaN, negative, absent, '
                'or zero after moving (only a source\'s starting pose may be exactly known), or '
                'whose orientation is not a unit quaternion')
            return None
        if source == SCAN:
            # Only accepted matches may start the interval of the next one's covariance.
            reading = (*reading, self._scan_increment_covariance(msg, stamp_to_ns(msg.header.stamp)))
        self._accepted_first[source] = True
        return source, reading

    def _scan_increment_covariance(self, msg, stamp: int):
        """Covariance of the motion since the matcher's previous output, from its twist
        covariance (twist = motion / dt), when it provides one; else None and the fusion core
        recovers it from the cumulative covariances."""
        _, twist_cov = odometry_twist(msg)
        previous, self._previous_scan_stamp = self._previous_scan_stamp, stamp
        if previous is None or stamp <= previous or not np.all(np.isfinite(twist_cov)) \
                or not np.all(np.diag(twist_cov) > 0.0):
            return None
        dt = (stamp - previous) * 1e-9
        return twist_cov * dt * dt

    def _reset(self) -> None:
        self._fusion.reset()
        self._buffer.clear()
        self._last_stamp = {k: None for k in INPUT_NAMES}
        self._first_stamp = {k: None for k in INPUT_NAMES}
        self._arrived = {k: None for k in INPUT_NAMES}
        self._start_ns = None
        self._processed = {k: 0 for k in INPUT_NAMES}
        self._accepted_first = {k: False for k in INPUT_NAMES}
        self._previous_scan_stamp = None

    def _flush_if_idle(self) -> None:
        if len(self._buffer) and time.monotonic() - self._last_arrival > self._flush_after_s:
            self._process(self._buffer.flush())

    # -- fusion and output ---------------------------------------------------------------------
    def _process(self, ready) -> None:
        for stamp, (source, reading) in ready:
            self._last_stamp[source] = stamp
            if self._first_stamp[source] is None:
                self._first_stamp[source] = stamp
            self._processed[source] += 1
            if source == WHEEL:
                self._fusion.add_wheel(stamp, *reading)
            elif source == GYRO:
                self._fusion.add_gyro(stamp, *reading)
                if self._enabled[WHEEL] or self._enabled[SCAN]:
                    continue  # heading only: published with the next position update
            else:
                self._fusion.add_scan_match(stamp, *reading)
            self._publish(stamp)

    def _publish(self, stamp: int) -> None:
        state = self._fusion.state
        if state is None:
            return
        self._publisher.publish(make_odometry(
            stamp, self._odom_frame, self._base_frame, state.pose, state.covariance))
        self.diagnostics.count('published')
        self.diagnostics.last_stamp_ns = max(self.diagnostics.last_stamp_ns, stamp)

    def _update_diagnostics(self, diag: Diagnostics) -> None:
        newest = self._buffer.newest_ns
        missing = []
        for source, name in INPUT_NAMES.items():
            if not self._enabled[source]:
                diag.values[f'{name}_state'] = 'disabled'
                continue
            last = self._last_stamp[source]
            diag.values[f'{name}_received'] = str(self._received[source])
            if last is None or newest is None:
                age = math.inf
            else:
                age = (newest - last) * 1e-9
            diag.values[f'{name}_age_s'] = f'{age:.3f}'
            first = self._first_stamp[source]
            span = (last - first) * 1e-9 if last is not None and first is not None else 0.0
            rate = (self._processed[source] - 1) / span if span > 0 else 0.0
            diag.values[f'{name}_rate_hz'] = f'{rate:.2f}'
            if age > self._input_timeout_s:
                missing.append(name)
        diag.values['fusion_updates'] = str(self._fusion.updates)
        diag.values['late_dropped_total'] = str(self._buffer.late)
        if missing:
            diag.level, diag.message = DiagnosticStatus.WARN, 'missing: ' + ', '.join(missing)
        else:
            diag.level, diag.message = DiagnosticStatus.OK, 'all enabled inputs present'


def main(args=None):
    sys.exit(run_node(ComplementaryFusionNode, args))
