# SPDX-License-Identifier: Apache-2.0
"""Thin ROS 2 layer: nodes that convert messages and call the pure-Python core."""
