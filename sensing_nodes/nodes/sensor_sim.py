"""sensor_sim: the simulated robot as a ROS 2 node, and its offline recorder.

Live:    sensor_sim --ros-args --params-file config/sensor_sim.yaml [-p real_time_factor:=5.0]
Record:  sensor_sim --record DIR --duration S [--seed N] [--params-file F] [--ros-args -p N:=V]
         (a rosbag2 MCAP bag of every topic, no DDS, as fast as the CPU allows)

Both run the same engine (sensing_nodes.core.sim.simulator.SensorSim) and the same message
conversion,
so a recorded bag holds exactly the messages the live node publishes for the same seed.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path
from typing import Any, Iterator

from geometry_msgs.msg import Twist
from nav_msgs.msg import Odometry
from rclpy.clock import Clock as RosClock
from rclpy.clock import ClockType
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.node import Node
from rclpy.parameter import get_parameter_value, parameter_value_to_python
from rclpy.utilities import remove_ros_args
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import Imu, JointState, LaserScan

from sensing_nodes.core.config.sensor_sim import NODE_SETTINGS_PARAMETERS
from sensing_nodes.core.geometry.transform import Transform
from sensing_nodes.core.sim import simulator as core
from sensing_nodes.parameters import ParameterError, load_parameters
from sensing_nodes.ros.diagnostics import Diagnostics
from sensing_nodes.ros.params import declare
from sensing_nodes.ros.qos import CLOCK_QOS, ESTIMATE_QOS, SENSOR_QOS
from sensing_nodes.ros.run import run_node
from sensing_nodes.ros.sim_robot import TOPICS, SimMessages, record, settings_from_values
from sensing_nodes.ros.tf import StaticTransformBroadcaster, TransformBroadcaster
from sensing_nodes.topics import CMD_VEL, SCAN

NODE_NAME = 'sensor_sim'
EXIT_BAD_PARAMETER = 2
_WALL_PERIOD_S = 0.005          # how often the node checks which samples have come due
_PACED_PERIOD_S = 0.001         # ... and how often it checks for the pace topic's answer
_LINGER_S = 0.5                 # wall seconds between the last sample and shutdown
_SETTLE_S = 0.5                 # wall seconds between the graph's matching and simulated time

def ros_args_values(ros_args: list[str]) -> dict[str, Any]:
    """Parameter values of `--ros-args` arguments for --record, read as the live node reads them:
    rcl checks the arguments first (a malformed rule or an unreadable params file is an error),
    then `--params-file F` gives F's sensor_sim section and `-p name:=value` a value typed by
    rclpy's own rule; later ones win."""
    try:
        remove_ros_args([NODE_NAME, '--ros-args', *ros_args])
    except (_rclpy.RCLInvalidROSArgsError, _rclpy.UnknownROSArgsError) as exc:
        raise ParameterError('ros_args', f'cannot be parsed: {exc}') from None
    values: dict[str, Any] = {}
    for flag, argument in zip(ros_args, ros_args[1:]):
        if flag == '--params-file':
            values.update(load_parameters(NODE_NAME, argument, require_section=True))
        elif flag in ('-p', '--param'):
            name, _, text = argument.partition(':=')
            values[name] = parameter_value_to_python(get_parameter_value(text))
    return values


def _record_main(argv: list[str], ros_args: list[str]) -> int:
    parser = argparse.ArgumentParser(
        prog='sensor_sim', description='Record the simulated robot into a rosbag2 MCAP bag '
        '(no DDS); parameters from --params-file, then --ros-args (--params-file F, '
        '-p NAME:=VALUE). '
        'Without --record, sensor_sim runs as a ROS 2 node (--ros-args ...).')
    parser.add_argument('--record', required=True, metavar='DIR', help='bag directory to create')
    parser.add_argument('--duration', required=True, type=float, metavar='S',
                        help='simulated seconds to record')
    parser.add_argument('--seed', type=int, help='random seed (overrides the params file)')
    parser.add_argument('--params-file', metavar='F',
                        help='ROS 2 parameter YAML (sensor_sim: ros__parameters: ...)')
    parser.add_argument('--quiet', action='store_true', help='no progress output')
    args = parser.parse_args(argv)
    try:
        values = load_parameters(NODE_NAME, args.params_file, require_section=True) \
            if args.params_file else {}
        values.update(ros_args_values(ros_args))
        if args.seed is not None:
            values['seed'] = args.seed
        params, settings, world = settings_from_values(values)
        if not (math.isfinite(args.duration) and args.duration > 0.0):
            raise ParameterError('duration', 'must be a positive number of seconds',
                                         args.duration)
        if Path(args.record).exists():
            raise ParameterError('record', 'must name a directory that does not exist yet',
                                         args.record)
    except ParameterError as exc:
        print(f'[sensor_sim] invalid parameter: {exc}', file=sys.stderr, flush=True)
        return EXIT_BAD_PARAMETER
    started = time.perf_counter()
    try:
        counts = record(args.record, args.duration, params, settings, world,
                        progress=not args.quiet)
    except KeyboardInterrupt as exc:
        print(f'sensor_sim: {exc} (bag closed and complete up to there)', file=sys.stderr)
        return 130
    wall = time.perf_counter() - started
    print(f'sensor_sim: recorded {args.duration:g} s of simulated time in {wall:.2f} s wall '
          f'({args.duration / wall:.1f}x real time) into {args.record}')
    for topic, count in counts.items():
        rate = (count - 1) / args.duration if count > 1 else 0.0      # both ends are sampled
        print(f'  {topic:<20} {count:7d} messages  {rate:7.1f} Hz')
    return 0


class SensorSimNode(Node):
    """Publishes the simulation's samples as their simulated time comes due: simulated time
    runs at real_time_factor x the wall clock (steady clock, so /clock never drives it)."""

    def __init__(self) -> None:
        super().__init__(NODE_NAME)
        values = {p.name: declare(self, p) for table in (core.SIM_PARAMETERS,
                                                         NODE_SETTINGS_PARAMETERS)
                  for p in table.parameters}
        params, settings, world = settings_from_values(values)
        self.params, self.settings = params, settings
        self._commands = core.CommandedMotion(params) if settings.use_cmd_vel else None
        self.sim = core.SensorSim(params, world, settings.seed, self._commands)
        self._convert = SimMessages(params, settings)
        self._outputs = {
            core.TRUTH: self.create_publisher(Odometry, TOPICS[core.TRUTH][0], ESTIMATE_QOS),
            core.IMU: self.create_publisher(Imu, TOPICS[core.IMU][0], SENSOR_QOS),
            core.JOINTS: self.create_publisher(JointState, TOPICS[core.JOINTS][0], SENSOR_QOS),
            core.SCAN: self.create_publisher(LaserScan, TOPICS[core.SCAN][0], SENSOR_QOS),
        }
        if settings.publish_clock:
            self._outputs[core.CLOCK] = self.create_publisher(Clock, TOPICS[core.CLOCK][0],
                                                              CLOCK_QOS)
        if self._commands is not None:
            self.create_subscription(Twist, CMD_VEL, self._on_cmd_vel, 10)
        self._truth_tf = None
        if settings.publish_tf:
            self._publish_mounts()
            self._truth_tf = TransformBroadcaster(self)
        self.diagnostics = Diagnostics(self)
        self._end_ns = (params.start_ns + int(round(settings.duration_s * core.NS_PER_S))
                        if settings.duration_s > 0.0 else None)
        self._stream = self._events()
        self._upcoming = next(self._stream)
        self._sim_now_ns = params.start_ns
        # Simulated time runs at real_time_factor from this anchor (wall s, stamp ns); paced, a
        # scan held for the graph's answer moves the anchor, so no burst follows the wait.
        self._anchor = (time.monotonic(), params.start_ns)
        self._held = False
        self._finished = False
        self._connected_since: float | None = None
        self._paced = bool(settings.pace_topic)
        self._awaited_ns: int | None = None      # stamp of the scan whose answer is awaited
        self._awaited_since = 0.0
        self._answered_ns = -1
        self._started = False
        if self._paced:
            self.create_subscription(Odometry, settings.pace_topic, self._on_pace, ESTIMATE_QOS)
        self.create_timer(_PACED_PERIOD_S if self._paced else _WALL_PERIOD_S, self._on_timer,
                          clock=RosClock(clock_type=ClockType.STEADY_TIME))
        self.get_logger().info(
            f'simulating {"/cmd_vel" if self._commands else "the scripted route"} in world '
            f"'{world.name}' "
            + (f'paced by {settings.pace_topic}' if self._paced
               else f'at {settings.real_time_factor:g}x real time') + f', seed {settings.seed}')

    def _publish_mounts(self) -> None:
        """The sensors' mounts on /tf_static (transient local: late subscribers get them too)."""
        p, s = self.params, self.settings
        self._static_tf = StaticTransformBroadcaster(self)
        self._static_tf.send(p.start_ns, s.base_frame, s.laser_frame,
                             Transform.from_planar(p.laser_x_m, p.laser_y_m, p.laser_yaw_rad))
        self._static_tf.send(p.start_ns, s.base_frame, s.imu_frame, Transform())

    def _on_cmd_vel(self, msg: Twist) -> None:
        speed, yaw_rate = float(msg.linear.x), float(msg.angular.z)
        time_s = (self._sim_now_ns - self.params.start_ns) / core.NS_PER_S
        try:
            self._commands.command(speed, yaw_rate, time_s)
        except ValueError:
            self.diagnostics.count('cmd_vel_rejected')
            self.get_logger().warning(
                f'ignoring /cmd_vel with non-finite values (linear.x={speed}, '
                f'angular.z={yaw_rate})',
                throttle_duration_sec=2.0)
            return
        self.diagnostics.count('cmd_vel')

    def _events(self) -> Iterator[tuple[int, int, core.SimBlock, int]]:
        """Every sample in time order, advancing the engine a block at a time."""
        while True:
            block = self.sim.advance()
            times, kinds, indices = core.block_events(block)
            for t, kind, i in zip(times.tolist(), kinds.tolist(), indices.tolist()):
                yield t, kind, block, i

    def _on_pace(self, msg: Odometry) -> None:
        stamp = msg.header.stamp.sec * core.NS_PER_S + msg.header.stamp.nanosec
        self._answered_ns = max(self._answered_ns, stamp)

    def _graph_ready(self) -> bool:
        """Start simulated time once every sensor and truth topic has wait_for_subscribers
        subscribers and, when paced, /scan one and the pace topic a publisher."""
        if self._started:
            return True
        wanted = self.settings.wait_for_subscribers
        missing = [TOPICS[k][0] for k in (core.SCAN, core.IMU, core.JOINTS, core.TRUTH)
                   if self._outputs[k].get_subscription_count() < wanted]
        if self._outputs[core.SCAN].get_subscription_count() < \
                self.settings.wait_for_scan_subscribers:
            missing.append(TOPICS[core.SCAN][0])
        if self._paced:
            if self._outputs[core.SCAN].get_subscription_count() < 1:
                missing.append(SCAN)
            if self.count_publishers(self.settings.pace_topic) < 1:
                missing.append(f'a publisher on {self.settings.pace_topic}')
        if missing:
            self.get_logger().info(f'waiting for subscribers of {", ".join(sorted(set(missing)))}',
                                   throttle_duration_sec=10.0)
            self._connected_since = None
            return False
        # A subscription counted here is matched on our side; the subscriber's side of the match
        # can come later on a loaded machine (its first scans were then lost): settle first.
        now = time.monotonic()
        if self._connected_since is None:
            self._connected_since = now
        if (wanted or self.settings.wait_for_scan_subscribers or self._paced) \
                and now - self._connected_since < _SETTLE_S:
            return False
        self._started = True
        self._anchor = (time.monotonic(), self.params.start_ns)
        if wanted or self.settings.wait_for_scan_subscribers or self._paced:
            self.get_logger().info('the graph is connected: starting')
        return True

    def _scan_may_go(self) -> bool:
        """Paced mode: has the graph answered the previous scan (or has the wait timed out)?"""
        if self._awaited_ns is None or self._answered_ns >= self._awaited_ns:
            return True
        if time.monotonic() - self._awaited_since < self.settings.pace_timeout_s:
            return False
        self.diagnostics.count('pace_timeouts')
        self.get_logger().warning(
            f'no answer on {self.settings.pace_topic} to the scan stamped {self._awaited_ns} ns '
            f'within {self.settings.pace_timeout_s:g} s: going on', throttle_duration_sec=5.0)
        return True

    def _on_timer(self) -> None:
        if self._finished:
            return
        if not self._graph_ready():
            return
        anchor_wall, anchor_ns = self._anchor
        due_ns = anchor_ns + int((time.monotonic() - anchor_wall)
                                 * self.settings.real_time_factor * core.NS_PER_S)
        while self._upcoming[0] <= due_ns:
            t, kind, block, i = self._upcoming
            if self._end_ns is not None and t > self._end_ns:
                self._finish()
                return
            if self._paced and kind == core.SCAN:
                if not self._scan_may_go():
                    self._held = True
                    return
                if self._held:
                    self._held = False
                    self._anchor = (time.monotonic(), t)
                # The answer carries the scan's stamp (its first beam), not when it went out.
                self._awaited_ns = int(block.scan_t[i])
                self._awaited_since = time.monotonic()
            publisher = self._outputs.get(kind)
            if publisher is not None:
                publisher.publish(self._convert.message(block, kind, i, t))
                self.diagnostics.count(TOPICS[kind][0])
            if kind == core.TRUTH and self._truth_tf is not None:
                self._truth_tf.send(t, self.settings.map_frame, self.settings.truth_frame,
                                    Transform.from_planar(*block.truth_pose[i].tolist()))
            self._sim_now_ns = t
            self.diagnostics.last_stamp_ns = t
            self._upcoming = next(self._stream)
            if self._paced and kind == core.SCAN:
                return                            # let the executor deliver the answer

    def _finish(self) -> None:
        self._finished = True
        self.get_logger().info(
            f'simulated {self.settings.duration_s:g} s: done, shutting down')
        # Linger a moment before the publishers go: subscribers that lag (a loaded machine) still
        # take the last samples from them; shutting down at once lost the last second of scans.
        self.create_timer(_LINGER_S, self.context.try_shutdown,
                          clock=RosClock(clock_type=ClockType.STEADY_TIME))


def main(args: list[str] | None = None) -> None:
    argv = sys.argv[1:] if args is None else list(args)
    ros_index = argv.index('--ros-args') if '--ros-args' in argv else len(argv)
    if '--record' in argv[:ros_index] or '-h' in argv[:ros_index] or '--help' in argv[:ros_index]:
        sys.exit(_record_main(argv[:ros_index], argv[ros_index + 1:]))
    sys.exit(run_node(SensorSimNode, args))
