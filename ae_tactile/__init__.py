# SPDX-License-Identifier: Apache-2.0
"""ae_tactile: ultrasonic acoustic-emission tactile fingertip (core + ROS 2 nodes).

Keep this file empty of code: in a colcon build, rosidl's Python generator
writes its own ``ae_tactile/__init__.py`` next to the generated ``ae_tactile.msg``.
The pure-Python core lives in the subpackages and never imports rclpy; the ROS
layer is ``ae_tactile.ros``.
"""
