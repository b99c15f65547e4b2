"""The standard topic names of a capture session, in one place.

Every view's rosbag2 of a session (real rig, virtual rig or pure simulation) records these
topics (DESIGN.md, session layout); readers default to them and session.yaml names them.
"""

from __future__ import annotations

#: event_camera_msgs/msg/EventPacket in the camera's own encoding (evt3, libcaer, ...)
EVENTS = "/event_camera/events"
#: event_camera_msgs/msg/EventPacket (evt3, EXT_TRIGGER words only): the trigger edges of a
#: camera whose own encoding cannot carry them (libcaer records), as libcaer_driver keeps them apart
EVENT_TRIGGERS = "/event_camera/triggers"
#: sensor_msgs/msg/CameraInfo
CAMERA_INFO = "/event_camera/camera_info"
#: geometry_msgs/msg/PoseStamped: the view's T_world_cam
CAMERA_POSE = "/rig/camera_pose"
#: sensor_msgs/msg/JointState: the servo's commanded angles
SERVO_JOINT_STATES = "/rig/servo/joint_states"
#: sensor_msgs/msg/TimeReference: the firmware's START / DONE times
SERVO_TRIGGER = "/rig/servo/trigger"
