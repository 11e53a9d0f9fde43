"""Throughput of the dead-reckoning cores (wheel odometry, gyro integrator), and whether the two
nodes keep up with 1 kHz input over DDS.

Inputs are the default simulated run (124 s: 50 Hz joint states, 200 Hz IMU), the joint states
tiled for integrate_path (a whole path in one call). Figures are messages per second on one
core, measured in one run.
"""

from __future__ import annotations

import json
import math
import sys
import time

import numpy as np

from sensing_nodes.bench.probe import DdsProbe
from sensing_nodes.core.gyro import GyroConfig, GyroIntegrator
from sensing_nodes.core.sim.simulator import SimParams, simulate
from sensing_nodes.core.sim.world import load_world
from sensing_nodes.core.wheel_odometry import (
    WheelOdometry,
    WheelOdometryConfig,
    integrate_path,
    wheel_increments,
)
from sensing_nodes.graph.processes import executable
from sensing_nodes.paths import config_file

JOINTS = ('left_wheel_joint', 'right_wheel_joint')


def _best_rate(count: int, fn, repeats: int) -> float:
    """Items per second of fn() over count items: the best of `repeats` runs (least disturbed)."""
    best = math.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return count / best


def _wheel_rates(run, quick: bool) -> dict:
    cfg = WheelOdometryConfig(right_radius_multiplier=1.01)
    tiles = 20 if quick else 200
    positions = run.joint_position
    steps = np.diff(positions, axis=0)
    tiled = np.concatenate([[positions[0]],
                            positions[0] + np.cumsum(np.tile(steps, (tiles, 1)), axis=0)])
    n = tiled.shape[0] - 1

    def batch():
        ds_l, ds_r = wheel_increments(tiled[:-1], tiled[1:], cfg.radii)
        integrate_path((0.0, 0.0, 0.0), ds_l, ds_r, cfg.wheel_separation_m, cfg.variance_per_m)

    names = list(JOINTS)
    samples = [(int(t), p.tolist()) for t, p in zip(run.joint_t, positions)]
    if quick:
        samples = samples[:2000]

    def per_message():
        odo = WheelOdometry(cfg)
        for t, p in samples:
            odo.update(t, names, p, (), JOINTS)

    batch_rate = _best_rate(n, batch, 3)
    message_rate = _best_rate(len(samples), per_message, 2)
    return {'wheel_batch_msgs_per_s': batch_rate, 'wheel_per_message_msgs_per_s': message_rate,
            'wheel_batch_over_per_message': batch_rate / message_rate, 'wheel_batch_n': n}


def _gyro_rates(run, quick: bool) -> dict:
    cfg = GyroConfig()
    samples = list(zip(run.imu_t.tolist(), run.imu_gyro.tolist(), run.imu_accel.tolist()))
    if quick:
        samples = samples[:5000]

    def per_message():
        gi = GyroIntegrator(cfg)
        for ti, g, a in samples:
            gi.update(ti, g, a)

    return {'gyro_per_message_samples_per_s': _best_rate(len(samples), per_message, 2)}


def _dds_check(name: str, seconds: float, rate_hz: float) -> dict:
    """Run the node as a process, publish rate_hz input paced by wall time, count outputs.

    Returns the numbers sent and received (by stamp); a node that keeps up answers every one.
    """
    from nav_msgs.msg import Odometry
    from sensor_msgs.msg import Imu, JointState

    from sensing_nodes.ros.conversions import ns_to_stamp, stamp_to_ns
    from sensing_nodes.ros.qos import ESTIMATE_QOS, SENSOR_QOS

    def joint_state(k, t):
        msg = JointState()
        msg.header.stamp = ns_to_stamp(t)
        msg.name = list(JOINTS)
        msg.position = [0.01 * k, 0.011 * k]
        return msg

    def imu(k, t):
        msg = Imu()
        msg.header.stamp = ns_to_stamp(t)
        msg.angular_velocity.z = 0.1
        msg.linear_acceleration.z = 9.81
        return msg

    # The input each node takes, its output, and how to make input message k stamped t.
    (in_type, in_topic), (out_type, out_topic), message = {
        'wheel_odometry': ((JointState, '/joint_states'), (Odometry, '/wheel/odom'), joint_state),
        'gyro_integrator': ((Imu, '/imu/data_raw'), (Imu, '/imu/data'), imu)}[name]
    command = [executable(name), '--ros-args', '-p', 'max_gap_s:=0.5']
    received: set[int] = set()
    with DdsProbe(name, command, 2, 'dead_reckoning_bench') as probe:
        pub = probe.node.create_publisher(in_type, in_topic, SENSOR_QOS)
        probe.node.create_subscription(out_type, out_topic, lambda m: received.add(
            stamp_to_ns(m.header.stamp)), ESTIMATE_QOS)
        if not probe.publish_until_answered(lambda: pub.publish(message(0, 1_000_000_000)),
                                            lambda: bool(received), 30.0):
            return {'sent': 0, 'received': 0, 'error': 'node never answered: '
                    + probe.log_tail()}
        received.clear()
        count = int(seconds * rate_hz)
        period_ns = int(1e9 / rate_hz)
        stamps = set()
        for k, elapsed in probe.paced(rate_hz, spin_s=0.0005):
            stamp = 1_000_000_000 + k * period_ns
            pub.publish(message(k, stamp))
            stamps.add(stamp)
            if k >= count:
                break
        probe.spin_until(lambda: len(received & stamps) >= count, 5.0)
        return {'sent': count, 'received': len(received & stamps),
                'send_rate_hz': count / elapsed}


def run(quick: bool = False, dds: bool = True) -> dict:
    """Measured figures: core throughput (batch and per message) and the 1 kHz DDS check."""
    params = SimParams()
    world = load_world(config_file('default_world.yaml'))
    sim = simulate(params, world, 20.0 if quick else 124.0, seed=1)
    out = {}
    out.update(_wheel_rates(sim, quick))
    out.update(_gyro_rates(sim, quick))
    if dds:
        seconds = 2.0 if quick else 5.0
        for exe in ('wheel_odometry', 'gyro_integrator'):
            result = _dds_check(exe, seconds, 1000.0)
            for key, value in result.items():
                out[f'{exe}_1khz_{key}'] = value
    return out


if __name__ == '__main__':
    print(json.dumps(run(quick='--quick' in sys.argv, dds='--no-dds' not in sys.argv), indent=2))
