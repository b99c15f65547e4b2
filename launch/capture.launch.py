"""Capture a session with config/capture.yaml: one bag per view while the servo runs its motion.

    ros2 launch rig capture.launch.py output:=/data/fork_session
    ros2 launch rig capture.launch.py output:=/tmp/session virtual:=true

Launch arguments override the YAML's output, virtual and views; every other setting is in the
YAML (docs/capture.md; every parameter: docs/reference/node-capture.md). Live events appear on /capture/events
(event_camera_msgs/msg/EventPacket, best effort, the camera's own encoding).
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node


def generate_launch_description():
    params = os.path.join(get_package_share_directory("rig"), "config", "capture.yaml")
    args = [
        DeclareLaunchArgument("output", description="session folder to write"),
        DeclareLaunchArgument("virtual", default_value="false", description="true: the closed-loop virtual rig"),
        DeclareLaunchArgument("views", default_value="8", description="viewpoints to record"),
    ]
    node = Node(
        package="rig",
        executable="capture",
        name="capture",
        output="screen",
        parameters=[params, {name: LaunchConfiguration(name) for name in ("output", "virtual", "views")}],
    )
    return LaunchDescription(args + [node])
