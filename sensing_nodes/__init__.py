"""sensing_nodes: motion estimates from a mobile robot's raw sensors, as ROS 2 nodes."""
