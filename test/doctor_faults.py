"""Faulty bags for sensing_doctor's tests, each derived from one clean simulated recording by
rewriting its messages (no simulator change): the IMU rotated, the encoders scaled, one topic's
stamps shifted or reversed, an Odometry's covariance zeroed, a second odom -> base_link on /tf,
NaN ranges.

The clean bag: sensor_sim's recording of a short route that stands still, drives, turns both
ways and follows an arc (the package's default geometry: config/ declares it), plus
wheel_odometry's /wheel/odom and /tf (odom -> base_link, through sensing_pipeline's code) and
/tf_static declaring the mounts as sensor_sim's node does (the IMU level, the laser 0.1 m ahead).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Callable, Iterable

import numpy as np

from sensing_nodes.bags.storage import BagReader, BagWriter, type_name
from sensing_nodes.core.geometry.imu_mount import mount_rotation

ROUTE = ('wait 12', 'straight 2.0 0.25', 'turn 90 45', 'straight 1.5 0.25', 'turn -180 45',
         'arc 90 0.6 0.25', 'straight 1.0 0.25', 'turn 360 60', 'wait 3')
DURATION_S = 55.0
START_NS = 1_700_000_000 * 1_000_000_000

Rewrite = Callable[[str, int, object], Iterable[tuple[str, object, int]]]


def record_clean(root: Path, duration_s: float = DURATION_S, seed: int = 3) -> Path:
    """The clean bag (see the module doc) under root; returns its path."""
    from sensing_nodes.core.sim import simulator as sim
    from sensing_nodes.core.sim.world import load_world
    from sensing_nodes.graph.pipeline import run
    from sensing_nodes.paths import config_file
    from sensing_nodes.ros.sim_robot import NodeSettings, record

    raw = root / 'sim_raw'
    record(raw, duration_s, sim.SimParams(route=ROUTE), NodeSettings(seed=seed),
           load_world(config_file('default_world.yaml')))
    with_odom = root / 'sim_odom'
    run(raw, with_odom, ('wheel_odometry',),
        node_params={'wheel_odometry': ['-p', 'publish_tf:=true']}, progress=False)
    clean = root / 'clean'
    rewrite(with_odom, clean, lambda topic, t, msg: [(topic, msg, t)], static=True)
    return clean


def _tf_static(stamp_ns: int):
    from geometry_msgs.msg import TransformStamped
    from tf2_msgs.msg import TFMessage

    from sensing_nodes.ros.conversions import ns_to_stamp

    msg = TFMessage()
    for child, x in (('laser', 0.1), ('imu_link', 0.0)):
        tr = TransformStamped()
        tr.header.stamp = ns_to_stamp(stamp_ns)
        tr.header.frame_id = 'base_link'
        tr.child_frame_id = child
        tr.transform.translation.x = x
        tr.transform.rotation.w = 1.0
        msg.transforms.append(tr)
    return msg


def rewrite(src: Path, dst: Path, change: Rewrite, static: bool = False) -> Path:
    """Copy a bag message by message through change(topic, record ns, msg) -> [(topic, msg,
    record ns)]; with static, /tf_static (the clean bag's mounts) first."""
    reader = BagReader(src)
    with BagWriter(dst) as bag:
        for topic, info in reader.topics.items():
            bag.add_topic(topic, info.msgtype, list(info.qos) or None)
        first = True
        for topic, stamp, msg in reader.messages():
            if static and first:
                bag.add_topic('/tf_static', 'tf2_msgs/msg/TFMessage')
                bag.write('/tf_static', _tf_static(stamp), stamp)
                first = False
            for out_topic, out_msg, out_stamp in change(topic, stamp, msg):
                bag.add_topic(out_topic, type_name(out_msg))
                bag.write(out_topic, out_msg, out_stamp)
    return dst


def rotated_imu(mount: np.ndarray) -> Rewrite:
    """The IMU mounted at `mount` (its frame in base_link): it reads mount^T of base vectors;
    /tf_static still declares it level."""
    def change(topic, t, msg):
        if topic == '/imu/data_raw':
            for field in ('angular_velocity', 'linear_acceleration'):
                v = getattr(msg, field)
                v.x, v.y, v.z = (float(c) for c in mount.T @ np.array([v.x, v.y, v.z]))
        return [(topic, msg, t)]
    return change


def upside_down() -> Rewrite:
    return rotated_imu(mount_rotation(math.pi, 0.0, 0.0))


def scaled_wheels(mean_scale: float = 1.0, difference_scale: float = 1.0) -> Rewrite:
    """Encoder angles with their mean scaled (a wheel radius off by 1/mean_scale) and their
    difference scaled (a separation off by difference_scale)."""
    def change(topic, t, msg):
        if topic == '/joint_states':
            left, right = msg.position
            mean, diff = 0.5 * (left + right) * mean_scale, (right - left) * difference_scale
            msg.position = [mean - 0.5 * diff, mean + 0.5 * diff]
            if len(msg.velocity) == 2:
                vl, vr = msg.velocity
                vm, vd = 0.5 * (vl + vr) * mean_scale, (vr - vl) * difference_scale
                msg.velocity = [vm - 0.5 * vd, vm + 0.5 * vd]
        return [(topic, msg, t)]
    return change


def wheel_radius_off(scale: float) -> Rewrite:
    """The wheels truly `scale` times the declared radius: every encoder angle 1/scale of
    what the declared radius needs (mean and difference alike)."""
    return scaled_wheels(1.0 / scale, 1.0 / scale)


def shifted_stamps(topic_name: str, offset_ns: int) -> Rewrite:
    """One topic's header stamps moved by offset_ns (a driver stamping late)."""
    from sensing_nodes.ros.conversions import ns_to_stamp, stamp_to_ns

    def change(topic, t, msg):
        if topic == topic_name:
            msg.header.stamp = ns_to_stamp(stamp_to_ns(msg.header.stamp) + offset_ns)
        return [(topic, msg, t)]
    return change


def zero_covariance(topic_name: str = '/wheel/odom') -> Rewrite:
    def change(topic, t, msg):
        if topic == topic_name:
            msg.pose.covariance = [0.0] * 36
            msg.twist.covariance = [0.0] * 36
        return [(topic, msg, t)]
    return change


def second_tf_publisher() -> Rewrite:
    """The ground truth (map frame) also published as odom -> base_link on /tf, as a second
    node with publish_tf would."""
    from geometry_msgs.msg import TransformStamped
    from tf2_msgs.msg import TFMessage

    def change(topic, t, msg):
        out = [(topic, msg, t)]
        if topic == '/ground_truth/odom':
            tr = TransformStamped()
            tr.header.stamp = msg.header.stamp
            tr.header.frame_id, tr.child_frame_id = 'odom', 'base_link'
            p = msg.pose.pose
            tr.transform.translation.x, tr.transform.translation.y = p.position.x, p.position.y
            tr.transform.rotation = p.orientation
            out.append(('/tf', TFMessage(transforms=[tr]), t))
        return out
    return change


def reversed_stamps(topic_name: str = '/joint_states', every: int = 400, count: int = 5
                    ) -> Rewrite:
    """`count` pairs of consecutive messages of a topic with their stamps swapped (a step back
    each), one pair every `every` messages."""
    state = {'n': 0, 'held': None}

    def change(topic, t, msg):
        if topic != topic_name:
            return [(topic, msg, t)]
        state['n'] += 1
        n = state['n']
        if n % every == 0 and n // every <= count:
            state['held'] = (msg, t)
            return []
        if state['held'] is not None:
            held, held_t = state['held']
            state['held'] = None
            held.header.stamp, msg.header.stamp = msg.header.stamp, held.header.stamp
            return [(topic, held, held_t), (topic, msg, t)]
        return [(topic, msg, t)]
    return change


def nan_ranges(scans: int = 10, beams: int = 30, every: int = 20) -> Rewrite:
    """NaN in `beams` ranges of `scans` scans (one scan in `every`)."""
    state = {'n': 0}

    def change(topic, t, msg):
        if topic == '/scan':
            state['n'] += 1
            if state['n'] % every == 0 and state['n'] // every <= scans:
                ranges = np.asarray(msg.ranges, dtype=np.float32).copy()
                ranges[:beams] = np.nan
                msg.ranges = ranges
        return [(topic, msg, t)]
    return change


# sensor_sim's wheel radii (config/sensor_sim.yaml: the right wheel 1 % large).
SIM_RADII_M = (0.05, 0.0505)


def skid_steer(gain: float) -> Rewrite:
    """The wheels' yaw rate `gain` times the robot's: the difference of the two wheels'
    travel scaled by gain, their mean kept (a skid-steer base whose wheels slip sideways in
    turns: gain > 1; or a track width declared gain times too small)."""
    left_r, right_r = SIM_RADII_M

    def change(topic, t, msg):
        if topic == '/joint_states':
            left, right = msg.position[0] * left_r, msg.position[1] * right_r
            mean, diff = 0.5 * (left + right), (right - left) * gain
            msg.position = [(mean - 0.5 * diff) / left_r, (mean + 0.5 * diff) / right_r]
            if len(msg.velocity) == 2:
                vl, vr = msg.velocity[0] * left_r, msg.velocity[1] * right_r
                vm, vd = 0.5 * (vl + vr), (vr - vl) * gain
                msg.velocity = [(vm - 0.5 * vd) / left_r, (vm + 0.5 * vd) / right_r]
        return [(topic, msg, t)]
    return change


def _without(topics: tuple[str, ...], change: Rewrite | None = None) -> Rewrite:
    def rewrite_one(topic, t, msg):
        if topic in topics:
            return []
        return change(topic, t, msg) if change is not None else [(topic, msg, t)]
    return rewrite_one


# An IMU-only bag (the gyro and the ground truth to score against): what an IMU's own
# orientation is fused for when nothing else gives a heading.
IMU_ONLY_DROPS = ('/joint_states', '/scan', '/wheel/odom', '/tf')


def imu_only() -> Rewrite:
    """The clean bag's IMU alone (no encoders, laser, odometry): the reference run of
    constant_orientation."""
    return _without(IMU_ONLY_DROPS)


def constant_orientation() -> Rewrite:
    """The IMU alone, its orientation the identity in every message with an all-zero
    covariance (a driver filling the field with a placeholder, like imu_tools' Razor bag)."""
    def change(topic, t, msg):
        if topic == '/imu/data_raw':
            msg.orientation.x = msg.orientation.y = msg.orientation.z = 0.0
            msg.orientation.w = 1.0
            msg.orientation_covariance = [0.0] * 9
        return [(topic, msg, t)]
    return _without(IMU_ONLY_DROPS, change)


def never_still(amplitude_rad_s: float = 0.2, frequency_hz: float = 0.3) -> Rewrite:
    """An IMU that never stands still: it rocks about its x axis (amplitude_rad_s at
    frequency_hz, its gravity reading turning with it) all the time, the wheels' stops
    included."""
    def change(topic, t, msg):
        if topic == '/imu/data_raw':
            phase = 2.0 * math.pi * frequency_hz * (t - START_NS) * 1e-9
            msg.angular_velocity.x += amplitude_rad_s * math.sin(phase)
            tilt = -amplitude_rad_s / (2.0 * math.pi * frequency_hz) * math.cos(phase)
            a = msg.linear_acceleration
            a.y, a.z = (math.cos(tilt) * a.y + math.sin(tilt) * a.z,
                        -math.sin(tilt) * a.y + math.cos(tilt) * a.z)
        return [(topic, msg, t)]
    return change


def imu_on_its_side_plus(yaw_deg: float = 2.0) -> Rewrite:
    """The IMU on its side (rolled -90 deg) and turned yaw_deg about the vertical off the right
    angle, /tf_static declaring only the laser (the nodes take the mount from params.yaml)."""
    from tf2_msgs.msg import TFMessage

    turn = rotated_imu(mount_rotation(-math.pi / 2, 0.0, math.radians(yaw_deg)))

    def change(topic, t, msg):
        if topic == '/tf_static':
            msg = TFMessage(transforms=[tr for tr in msg.transforms
                                        if tr.child_frame_id != 'imu_link'])
        return turn(topic, t, msg)
    return change


CATALOGUE = {
    'upside_down': lambda: upside_down(),
    'imu_yaw_90': lambda: rotated_imu(mount_rotation(0.0, 0.0, math.pi / 2)),
    'imu_roll_minus_90': lambda: rotated_imu(mount_rotation(-math.pi / 2, 0.0, 0.0)),
    'wheel_radius_5pct': lambda: wheel_radius_off(1.05),
    'separation_10pct': lambda: scaled_wheels(difference_scale=1.1),
    'imu_50ms_late': lambda: shifted_stamps('/imu/data_raw', 50_000_000),
    'zero_covariance': lambda: zero_covariance('/wheel/odom'),
    'second_tf_publisher': lambda: second_tf_publisher(),
    'stamps_backwards': lambda: reversed_stamps('/joint_states'),
    'nan_ranges': lambda: nan_ranges(),
    'skid_yaw_gain_0.2': lambda: skid_steer(0.2),
    'skid_yaw_gain_5': lambda: skid_steer(5.0),
    'imu_only': lambda: imu_only(),
    'constant_orientation': lambda: constant_orientation(),
    'never_still': lambda: never_still(),
    'imu_side_plus_2deg': lambda: imu_on_its_side_plus(2.0),
}


if __name__ == '__main__':
    # python test/doctor_faults.py DIR: the clean bag and every fault of the catalogue in DIR,
    # for `sensing_doctor DIR/<name>` (docs/doctor.md's table).
    import sys

    root = Path(sys.argv[1])
    root.mkdir(parents=True, exist_ok=False)
    clean = record_clean(root)
    for name, make in CATALOGUE.items():
        rewrite(clean, root / name, make())
        print(root / name)
