# SPDX-License-Identifier: Apache-2.0
"""Test helper: three simulated fingers of one hand under one source of interference, the
package launch file included three times. `hand/index` and `hand/thumb` share the hand's
topic (hand_topic:=/hand/apex_packets), `hand/control` does not. Launch arguments:
scene_dir (hand_0.yaml, hand_1.yaml, hand_2.yaml: one scene per finger) and params_file.
Every driver waits for 1 subscriber.
"""
import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, GroupAction, IncludeLaunchDescription
from launch.launch_description_sources import PythonLaunchDescriptionSource
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution

FINGERS = (("index", "/hand/apex_packets"), ("thumb", "/hand/apex_packets"), ("control", ""))


def generate_launch_description():
    finger = PythonLaunchDescriptionSource(os.path.join(
        get_package_share_directory("ae_tactile"), "launch", "ae_tactile.launch.py"))
    includes = []
    for k, (name, topic) in enumerate(FINGERS):
        scene = PathJoinSubstitution([LaunchConfiguration("scene_dir"), f"hand_{k}.yaml"])
        args = {"namespace": f"hand/{name}",
                "scene": scene,
                "params_file": LaunchConfiguration("params_file"),
                "wait_for_subscribers": "1",
                **({"hand_topic": topic} if topic else {})}
        includes.append(GroupAction([IncludeLaunchDescription(finger,
                                                              launch_arguments=args.items())]))
    return LaunchDescription([DeclareLaunchArgument("scene_dir"),
                              DeclareLaunchArgument("params_file"), *includes])
