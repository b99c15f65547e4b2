"""Node runtime without rclpy: ROS 2 names, parameters and ``--ros-args``, QoS profiles,
Cyclone DDS transport with ROS 2's topic and type naming, a rosbag2 sink, logging and the
Node base class (see docs/publishing.md and docs/ros2.md)."""
