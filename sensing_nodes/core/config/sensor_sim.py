"""sensor_sim's own settings (everything that is not a number of the simulation: seed, world,
pacing, frames, joint names) and their parameters; the simulation's numbers are SimParams
(core/sim/simulator.py, SIM_PARAMETERS)."""

from __future__ import annotations

import math
from dataclasses import dataclass

from sensing_nodes.parameters import Param, ParameterTable

_FRAMES = ('map_frame', 'base_frame', 'laser_frame', 'imu_frame', 'truth_frame',
           'left_joint_name', 'right_joint_name')


@dataclass(frozen=True)
class NodeSettings:
    """The node's own parameters (everything that is not a number of the simulation)."""

    seed: int = 0
    world_file: str = ''
    real_time_factor: float = 1.0
    duration_s: float = 0.0
    use_cmd_vel: bool = False
    publish_clock: bool = True
    map_frame: str = 'map'
    base_frame: str = 'base_link'
    laser_frame: str = 'laser'
    imu_frame: str = 'imu_link'
    left_joint_name: str = 'left_wheel_joint'
    right_joint_name: str = 'right_wheel_joint'
    wait_for_subscribers: int = 0
    wait_for_scan_subscribers: int = 0
    pace_topic: str = ''
    pace_timeout_s: float = 5.0
    publish_tf: bool = True
    truth_frame: str = 'base_link_truth'

    def problems(self) -> list[tuple[str, str, object]]:
        """(field, problem, value) for each setting the node cannot run with (types and
        ranges checked: NODE_SETTINGS_PARAMETERS); the world file is read where it is used."""
        out: list[tuple[str, str, object]] = [
            (name, 'must be finite', getattr(self, name))
            for name in ('real_time_factor', 'duration_s', 'pace_timeout_s')
            if not math.isfinite(getattr(self, name))]
        out += [(name, 'must not be empty', None) for name in _FRAMES
                if not getattr(self, name).strip()]
        if self.left_joint_name == self.right_joint_name:
            out.append(('right_joint_name', 'must differ from left_joint_name',
                        self.right_joint_name))
        return out


NODE_SETTINGS_PARAMETERS = ParameterTable(NodeSettings(), described={
    'seed': Param('random seed; same seed and parameters give the same messages', 0,
                  2**63 - 1),
    'world_file': Param("world YAML (walls/polygons); '' = the shipped "
                        'config/default_world.yaml'),
    'real_time_factor': Param('simulated seconds per wall second (1.0 live, > 1 faster; with '
                              'pace_topic the most)', 1e-3, 1e6),
    'duration_s': Param('stop publishing and exit after this much simulated time; 0 = run on',
                        0.0),
    'use_cmd_vel': Param('follow /cmd_vel (geometry_msgs/Twist) instead of the scripted route'),
    'publish_clock': Param('publish simulated time on /clock'),
    'map_frame': Param('frame of the ground truth pose'),
    'base_frame': Param('child frame of the ground truth (the robot body)'),
    'laser_frame': Param('frame of /scan'),
    'imu_frame': Param('frame of /imu/data_raw (coincides with base_frame)'),
    'left_joint_name': Param('name of the left wheel joint in /joint_states'),
    'right_joint_name': Param('name of the right wheel joint in /joint_states'),
    'wait_for_subscribers': Param(
        'start simulated time once /scan, /imu/data_raw, /joint_states and /ground_truth/odom '
        'have at least this many subscribers each', 0, 1000),
    'wait_for_scan_subscribers': Param(
        'and /scan at least this many (every scan consumer matched, so none misses the first '
        'scans)', 0, 1000),
    'pace_topic': Param("'' = paced by real_time_factor; else also paced by the graph (at most "
                        'real_time_factor): a scan is published only once an Odometry stamped '
                        'at or after the previous scan arrived on this topic'),
    'pace_timeout_s': Param('with pace_topic: wall seconds to wait for an answer before going on '
                            '(with a warning)', 1e-3),
    'publish_tf': Param('publish the sensor mounts on /tf_static (base_frame -> laser_frame, '
                        'imu_frame) and the ground truth on /tf (map_frame -> truth_frame)'),
    'truth_frame': Param('child frame of the ground truth on /tf (not base_frame: the estimate '
                         'owns odom -> base_frame)'),
})
