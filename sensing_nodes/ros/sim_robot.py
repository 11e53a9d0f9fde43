"""The simulated robot's side of ROS: parameter values -> (SimParams, node settings, world),
samples -> rclpy messages, and the offline recording of a run into a bag. Shared by the
sensor_sim node and its --record mode."""

from __future__ import annotations

import signal
import sys
from pathlib import Path
from typing import Any, Iterator

import numpy as np
from nav_msgs.msg import Odometry
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import Imu, JointState, LaserScan

from sensing_nodes.core.config.sensor_sim import NODE_SETTINGS_PARAMETERS, NodeSettings
from sensing_nodes.core.sim import simulator as core
from sensing_nodes.core.sim.world import World, load_world
from sensing_nodes.parameters import ParameterError
from sensing_nodes.paths import config_file
from sensing_nodes.ros.conversions import float32_array, yaw_to_quaternion
from sensing_nodes.topics import CLOCK, GROUND_TRUTH, IMU_RAW, JOINT_STATES, SCAN, TOPIC_TYPES

TOPICS = {kind: (topic, TOPIC_TYPES[topic]) for kind, topic in (
    (core.CLOCK, CLOCK), (core.TRUTH, GROUND_TRUTH), (core.IMU, IMU_RAW),
    (core.JOINTS, JOINT_STATES), (core.SCAN, SCAN))}


def settings_from_values(values: dict[str, Any]) -> tuple[core.SimParams, NodeSettings, World]:
    """Parameters, node settings and world from a dict of parameter values; ParameterError
    names the first parameter of the wrong type, out of range, or unusable."""
    params = core.SIM_PARAMETERS.config(values)
    settings = NODE_SETTINGS_PARAMETERS.config(values)
    path = settings.world_file or str(config_file('default_world.yaml'))
    try:
        world = load_world(path)
    except ValueError as exc:
        raise ParameterError('world_file', str(exc), path) from None
    return params, settings, world


class SimMessages:
    """Turns a block's samples into rclpy messages (one reused message object per topic: both
    publishing and bag writing serialise a message at once)."""

    def __init__(self, params: core.SimParams, settings: NodeSettings) -> None:
        p = params
        self._clock = Clock()
        self._odom = Odometry()
        self._odom.header.frame_id = settings.map_frame
        self._odom.child_frame_id = settings.base_frame
        self._imu = Imu()
        self._imu.header.frame_id = settings.imu_frame
        self._imu.orientation_covariance[0] = -1.0          # no orientation (REP 145)
        gyro_var, accel_var = p.gyro_noise_std_rad_s ** 2, p.accel_noise_std_m_s2 ** 2
        self._imu.angular_velocity_covariance = np.diag([gyro_var] * 3).ravel().tolist()
        self._imu.linear_acceleration_covariance = np.diag([accel_var] * 3).ravel().tolist()
        self._joints = JointState()
        self._joints.name = [settings.left_joint_name, settings.right_joint_name]
        self._scan = LaserScan()
        self._scan.header.frame_id = settings.laser_frame
        self._scan.angle_min = p.scan_angle_min_rad
        self._scan.angle_increment = p.scan_angle_increment_rad
        self._scan.angle_max = (p.scan_angle_min_rad
                                + (p.scan_beams - 1) * p.scan_angle_increment_rad)
        # Beam i taken at stamp + i x time_increment (0: every beam at the stamp).
        self._scan.time_increment = p.scan_time_increment_s
        self._scan.scan_time = 1.0 / p.scan_rate_hz
        self._scan.range_min = p.range_min_m
        self._scan.range_max = p.range_max_m

    def messages(self, block: core.SimBlock) -> Iterator[tuple[int, int, Any]]:
        """(time ns, kind, message) for every sample of the block, in publishing order."""
        times, kinds, indices = core.block_events(block)
        for t, kind, i in zip(times.tolist(), kinds.tolist(), indices.tolist()):
            yield t, kind, self.message(block, kind, i, t)

    def message(self, block: core.SimBlock, kind: int, i: int, t: int) -> Any:
        """The message of sample i of the given kind, published at t (ns): stamped t, a scan
        with its first beam's time (block.scan_t)."""
        if kind == core.SCAN:
            t = int(block.scan_t[i])
        sec, nanosec = divmod(t, core.NS_PER_S)
        if kind == core.CLOCK:
            msg = self._clock
            msg.clock.sec, msg.clock.nanosec = sec, nanosec
            return msg
        if kind == core.TRUTH:
            msg = self._odom
            x, y, yaw = block.truth_pose[i].tolist()
            msg.pose.pose.position.x, msg.pose.pose.position.y = x, y
            yaw_to_quaternion(yaw, out=msg.pose.pose.orientation)
            msg.twist.twist.linear.x, msg.twist.twist.angular.z = block.truth_twist[i].tolist()
        elif kind == core.IMU:
            msg = self._imu
            g, a = msg.angular_velocity, msg.linear_acceleration
            g.x, g.y, g.z = block.imu_gyro[i].tolist()
            a.x, a.y, a.z = block.imu_accel[i].tolist()
        elif kind == core.JOINTS:
            msg = self._joints
            msg.position = block.joint_position[i].tolist()
            msg.velocity = block.joint_velocity[i].tolist()
        else:
            msg = self._scan
            msg.ranges = float32_array(block.scan_ranges[i])
        msg.header.stamp.sec, msg.header.stamp.nanosec = sec, nanosec
        return msg


def record(out_dir: str | Path, duration_s: float, params: core.SimParams, settings: NodeSettings,
           world: World, progress: bool = False) -> dict[str, int]:
    """Write a rosbag2 MCAP bag of every topic for duration_s simulated seconds; topic -> count."""
    from sensing_nodes.bags.storage import CHUNK_S, BagWriter

    sim = core.SensorSim(params, world, settings.seed)
    convert = SimMessages(params, settings)
    end_ns = params.start_ns + int(round(duration_s * core.NS_PER_S))
    skip = set() if settings.publish_clock else {core.CLOCK}
    next_report = params.start_ns
    # SIGINT stops between two messages, so the bag is closed with exactly what it holds
    # (an interrupt inside a write could leave a message in the file that the metadata misses).
    interrupted: list[int] = []
    previous_handler = signal.signal(
        signal.SIGINT, lambda signum, frame: interrupted.append(signum)
    )
    try:
        # A chunk per simulated second (CHUNK_S), on disk as it closes: killed or powered off,
        # the bag keeps all but its last simulated second (BagReader reads it unclosed).
        with BagWriter(out_dir, chunk_s=CHUNK_S) as bag:
            for kind, (topic, msg_type) in TOPICS.items():
                if kind not in skip:
                    bag.add_topic(topic, msg_type)
            while not interrupted:
                block = sim.advance()
                for t, kind, msg in convert.messages(block):
                    if t > end_ns or interrupted:
                        break
                    if kind not in skip:
                        bag.write(TOPICS[kind][0], msg, t)
                if sim.time_ns >= end_ns:
                    break
                if progress and sim.time_ns >= next_report:
                    print(f'\rsensor_sim: recorded {(sim.time_ns - params.start_ns) / 1e9:6.1f} / '
                          f'{duration_s:.1f} s', end='', file=sys.stderr, flush=True)
                    next_report += 10 * core.NS_PER_S
            if progress:
                print(file=sys.stderr)
            counts = dict(bag.counts)
    finally:
        signal.signal(signal.SIGINT, previous_handler)
    if interrupted:
        raise KeyboardInterrupt(f'interrupted: {sum(counts.values())} messages in {out_dir}')
    return counts
