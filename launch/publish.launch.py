"""Start the event publisher node with config/event_publisher.yaml.

    ros2 launch rig publish.launch.py scene:=jet-down trajectory:=/path/to/odom_bag

Launch arguments override the YAML's scene, trajectory, run_dir and realtime_factor; the
events appear on /event_publisher/events (event_camera_msgs/msg/EventPacket, evt3) and
/event_publisher/camera_info.
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node


def generate_launch_description():
    params = os.path.join(get_package_share_directory("rig"), "config", "event_publisher.yaml")
    args = [
        DeclareLaunchArgument("scene", default_value="fork", description="scene preset or YAML"),
        DeclareLaunchArgument("run_dir", default_value="", description="trained run folder (overrides scene)"),
        DeclareLaunchArgument("trajectory", default_value="", description="robot poses: bag, .yaml or .csv"),
        DeclareLaunchArgument("realtime_factor", default_value="1.0", description="0: as fast as possible"),
    ]
    node = Node(
        package="rig",
        executable="event_publisher",
        name="event_publisher",
        output="screen",
        parameters=[params, {name: LaunchConfiguration(name)
                             for name in ("scene", "run_dir", "trajectory", "realtime_factor")}],
    )
    return LaunchDescription(args + [node])
