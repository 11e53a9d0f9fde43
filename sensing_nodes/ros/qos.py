"""The package's QoS profiles (sensor streams, estimates, /clock, /tf, /tf_static written and
read) and the one the graph uses on each of its topics."""

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from sensing_nodes.topics import CLOCK, SENSOR_TOPICS, TF, TF_STATIC

# Sensor streams: best effort, as drivers publish them (a reliable subscriber would not match a
# best-effort driver). The queue is deeper than rclpy's qos_profile_sensor_data (5) so that a
# replay running faster than real time does not overrun a subscriber between two spins.
SENSOR_QOS = QoSProfile(
    reliability=ReliabilityPolicy.BEST_EFFORT,
    durability=DurabilityPolicy.VOLATILE,
    history=HistoryPolicy.KEEP_LAST,
    depth=100,
)

# Estimates (odometry, fused pose, lines): reliable, so no consumer misses a step.
ESTIMATE_QOS = QoSProfile(
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.VOLATILE,
    history=HistoryPolicy.KEEP_LAST,
    depth=100,
)

# /clock: reliable, latest value only matters.
CLOCK_QOS = QoSProfile(
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.VOLATILE,
    history=HistoryPolicy.KEEP_LAST,
    depth=10,
)

# /tf: as tf2_ros's TransformBroadcaster (reliable, volatile, 100 deep).
TF_QOS = QoSProfile(
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.VOLATILE,
    history=HistoryPolicy.KEEP_LAST,
    depth=100,
)

# /tf_static: as tf2_ros's StaticTransformBroadcaster (reliable, transient local, 1 deep): a
# subscriber that starts later still gets the last message, which holds every static transform.
TF_STATIC_QOS = QoSProfile(
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
    history=HistoryPolicy.KEEP_LAST,
    depth=1,
)

# Reading /tf_static: deeper than 1, since several static broadcasters' latched messages can
# arrive at once.
TF_STATIC_READER_QOS = QoSProfile(
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
    history=HistoryPolicy.KEEP_LAST,
    depth=100,
)


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
