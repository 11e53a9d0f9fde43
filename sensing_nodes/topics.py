"""The graph's topics: default names, message types, and which node takes and publishes what
(REP 105 frames and QoS are elsewhere: ros/qos.py, docs/tf.md). Every node, tool and test names a
topic through this module; remapping changes the name at run time, not here."""

from __future__ import annotations

from dataclasses import dataclass, field

CLOCK = '/clock'
GROUND_TRUTH = '/ground_truth/odom'
JOINT_STATES = '/joint_states'
IMU_RAW = '/imu/data_raw'
SCAN = '/scan'
CMD_VEL = '/cmd_vel'
WHEEL_ODOM = '/wheel/odom'
IMU = '/imu/data'
SCAN_LINES = '/scan/lines'
SCAN_LINES_TABLE = '/scan/lines/table'
SCAN_MATCH = '/scan_match/odom'
SCAN_MATCH_KEYFRAME = '/scan_match/keyframe_odom'
FUSED = '/odometry/filtered'
DIAGNOSTICS = '/diagnostics'
TF = '/tf'
TF_STATIC = '/tf_static'

TOPIC_TYPES = {
    CLOCK: 'rosgraph_msgs/msg/Clock',
    GROUND_TRUTH: 'nav_msgs/msg/Odometry',
    JOINT_STATES: 'sensor_msgs/msg/JointState',
    IMU_RAW: 'sensor_msgs/msg/Imu',
    SCAN: 'sensor_msgs/msg/LaserScan',
    CMD_VEL: 'geometry_msgs/msg/Twist',
    WHEEL_ODOM: 'nav_msgs/msg/Odometry',
    IMU: 'sensor_msgs/msg/Imu',
    SCAN_LINES: 'visualization_msgs/msg/MarkerArray',
    SCAN_LINES_TABLE: 'sensor_msgs/msg/PointCloud2',
    SCAN_MATCH: 'nav_msgs/msg/Odometry',
    SCAN_MATCH_KEYFRAME: 'nav_msgs/msg/Odometry',
    FUSED: 'nav_msgs/msg/Odometry',
    DIAGNOSTICS: 'diagnostic_msgs/msg/DiagnosticArray',
    TF: 'tf2_msgs/msg/TFMessage',
    TF_STATIC: 'tf2_msgs/msg/TFMessage',
}
# Raw sensor streams: published best effort, as a driver would (SENSOR_QOS); the rest reliable.
SENSOR_TOPICS = frozenset({JOINT_STATES, IMU_RAW, SCAN})
# Published on a wall-clock timer whatever the input: never waited for, not part of "quiet".
WALL_PERIODIC_TOPICS = frozenset({DIAGNOSTICS})
# Made and published only while a subscription matches them (line_extractor's: nothing in the
# graph takes them); a recorder that wants them subscribes before the inputs flow, and
# sensing_pipeline always makes them.
ON_DEMAND_TOPICS = frozenset({SCAN_LINES, SCAN_LINES_TABLE})
# What sensor_sim publishes (the simulated robot's drivers, its ground truth and clock).
SIMULATOR_TOPICS = (SCAN, IMU_RAW, JOINT_STATES, GROUND_TRUTH, CLOCK)


@dataclass(frozen=True)
class NodeTopics:
    """A processing node's topics (default names): what it takes, the input it answers one
    message at a time (`answers`, None for a node that buffers) with one message on each of
    `answered_with` carrying that input's stamp, and what else it always publishes."""

    inputs: tuple[str, ...]
    answered_with: tuple[str, ...]
    answers: str | None = None
    also: tuple[str, ...] = (DIAGNOSTICS,)
    optional: tuple[str, ...] = field(default=())   # only with some parameters (publish_tf...)

    @property
    def outputs(self) -> tuple[str, ...]:
        """What it publishes whatever its parameters: main output first."""
        return self.answered_with + self.also


NODES = {
    'wheel_odometry': NodeTopics((JOINT_STATES,), (WHEEL_ODOM,), JOINT_STATES, optional=(TF,)),
    'gyro_integrator': NodeTopics((IMU_RAW, WHEEL_ODOM, TF_STATIC), (IMU,), IMU_RAW),
    'line_extractor': NodeTopics((SCAN,), (SCAN_LINES, SCAN_LINES_TABLE), SCAN),
    'icp_matcher': NodeTopics((SCAN, WHEEL_ODOM, TF_STATIC), (SCAN_MATCH,), SCAN,
                              optional=(SCAN_MATCH_KEYFRAME, TF)),
    # The raw IMU (imu.source rate, config/complementary_fusion.yaml): gyro_integrator's /imu/data
    # is for other consumers (config/fusion_integrated.yaml fuses it instead).
    'complementary_fusion': NodeTopics((WHEEL_ODOM, IMU_RAW, SCAN_MATCH, SCAN_MATCH_KEYFRAME),
                                       (FUSED,), optional=(TF,)),
}
PROCESSING_NODES = tuple(NODES)
# Input topic -> the outputs that answer it, one message each carrying its stamp.
ANSWERS: dict[str, tuple[str, ...]] = {}
for _topics in NODES.values():
    if _topics.answers is not None:
        ANSWERS[_topics.answers] = ANSWERS.get(_topics.answers, ()) + _topics.answered_with
# Message type each node input takes (sensor_sim's /cmd_vel included).
NODE_INPUT_TYPES = {t: TOPIC_TYPES[t] for t in
                    [JOINT_STATES, IMU_RAW, SCAN, WHEEL_ODOM, IMU, SCAN_MATCH, CMD_VEL]}
