"""Each node's configuration as one dataclass (its core's settings and the node's own: topics,
frames, what it publishes) and its parameter table (sensing_nodes/parameters.py): what the node
declares and what the tools that run its code without ROS build from the same parameter files.
complementary_fusion's is core/fusion/config.py."""
