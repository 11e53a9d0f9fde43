"""The two QoS profiles of the package: sensor streams and estimates."""

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

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
