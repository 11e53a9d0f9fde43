"""The processing nodes by name: what sensing_graph and sensing_pipeline construct, as each
executable constructs it."""

from __future__ import annotations

from sensing_nodes.nodes.complementary_fusion import ComplementaryFusionNode
from sensing_nodes.nodes.gyro_integrator import GyroIntegratorNode
from sensing_nodes.nodes.icp_matcher import IcpMatcherNode
from sensing_nodes.nodes.line_extractor import LineExtractorNode
from sensing_nodes.nodes.wheel_odometry import WheelOdometryNode
from sensing_nodes.topics import PROCESSING_NODES

NODE_CLASSES = {
    'wheel_odometry': WheelOdometryNode,
    'gyro_integrator': GyroIntegratorNode,
    'line_extractor': LineExtractorNode,
    'icp_matcher': IcpMatcherNode,
    'complementary_fusion': ComplementaryFusionNode,
}
assert tuple(NODE_CLASSES) == PROCESSING_NODES


def make_node(name: str, arguments: list[str], context=None, lifecycle: bool | None = None):
    """The processing node `name` constructed in `context` (default: this process's rclpy
    context) with only `arguments` (graph.cli.node_arguments) as its own, as its executable
    constructs it; the process's global ROS arguments do not apply, so nodes built side by side
    never share a -p or -r. `lifecycle`: managed or plain whatever its `lifecycle` parameter
    says (default: as it says; ros/processing_node.py)."""
    options = {} if context is None else {'context': context}
    return NODE_CLASSES[name](cli_args=arguments, use_global_arguments=False,
                              lifecycle=lifecycle, **options)
