# SPDX-License-Identifier: Apache-2.0
"""Test helper: two simulated fingers of one hand, the package launch file included twice.

finger `hand/f1`: three_pins scene, frame f1_tip; finger `hand/f2`: single_touch scene and
no frame_id given (it must get the default, not f1's). Both drivers wait for 1 subscriber.
"""
import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import GroupAction, IncludeLaunchDescription
from launch.launch_description_sources import PythonLaunchDescriptionSource


def generate_launch_description():
    finger = PythonLaunchDescriptionSource(os.path.join(
        get_package_share_directory("ae_tactile"), "launch", "ae_tactile.launch.py"))
    fingers = [
        {"namespace": "hand/f1", "scene": "three_pins", "frame_id": "f1_tip",
         "wait_for_subscribers": "1"},
        {"namespace": "hand/f2", "scene": "single_touch", "wait_for_subscribers": "1"},
    ]
    return LaunchDescription([
        GroupAction([IncludeLaunchDescription(finger, launch_arguments=args.items())])
        for args in fingers])
