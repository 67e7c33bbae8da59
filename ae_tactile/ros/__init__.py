"""Thin ROS 2 layer: nodes that convert messages and call the pure-Python core."""
