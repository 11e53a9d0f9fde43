"""The package's QoS profiles (sensor streams, estimates, /clock, /tf, /tf_static written and
read) and the one the graph uses on each of its topics."""

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from sensing_nodes.topics import CLOCK, SENSOR_TOPICS, TF, TF_STATIC


def _profile(reliability: ReliabilityPolicy, durability: DurabilityPolicy, depth: int
             ) -> QoSProfile:
    return QoSProfile(reliability=reliability, durability=durability,
                      history=HistoryPolicy.KEEP_LAST, depth=depth)


_RELIABLE, _BEST_EFFORT = ReliabilityPolicy.RELIABLE, ReliabilityPolicy.BEST_EFFORT
_VOLATILE, _LATCHED = DurabilityPolicy.VOLATILE, DurabilityPolicy.TRANSIENT_LOCAL

# Sensor streams: best effort, as drivers publish them (a reliable subscriber would not match a
# best-effort driver). The queue is deeper than rclpy's qos_profile_sensor_data (5) so that a
# replay running faster than real time does not overrun a subscriber between two spins.
SENSOR_QOS = _profile(_BEST_EFFORT, _VOLATILE, 100)
# A fast sensor stream read by a node that can lag behind it (the fusion on the raw IMU, 200 Hz
# and more): best effort drops whatever the reader's history cannot hold, so it holds 5 s at
# 200 Hz (gyro_integrator's /imu/data, which the fusion read before, is reliable).
SENSOR_BACKLOG_QOS = _profile(_BEST_EFFORT, _VOLATILE, 1000)
# Estimates (odometry, fused pose, lines): reliable, so no consumer misses a step.
ESTIMATE_QOS = _profile(_RELIABLE, _VOLATILE, 100)
# /clock: reliable, latest value only matters.
CLOCK_QOS = _profile(_RELIABLE, _VOLATILE, 10)
# /tf: as tf2_ros's TransformBroadcaster (reliable, volatile, 100 deep).
TF_QOS = _profile(_RELIABLE, _VOLATILE, 100)
# /tf_static: as tf2_ros's StaticTransformBroadcaster (reliable, transient local, 1 deep): a
# subscriber that starts later still gets the last message, which holds every static transform.
TF_STATIC_QOS = _profile(_RELIABLE, _LATCHED, 1)
# Reading /tf_static: deeper than 1, since several static broadcasters' latched messages can
# arrive at once.
TF_STATIC_READER_QOS = _profile(_RELIABLE, _LATCHED, 100)

def topic_qos(topic: str) -> QoSProfile:
    """The profile the graph's nodes publish `topic` with, which a tool publishing it in their
    place or reading it must match (a /tf_static reader: TF_STATIC_READER_QOS)."""
    if topic in SENSOR_TOPICS:
        return SENSOR_QOS
    if topic == CLOCK:
        return CLOCK_QOS
    if topic == TF:
        return TF_QOS
    if topic == TF_STATIC:
        return TF_STATIC_QOS
    return ESTIMATE_QOS
