"""File and message I/O: rosbag2 (MCAP / sqlite3) and ROS 1 bags, ROS message builders,
event files.

The bag API is re-exported here lazily (importing ``evdnerf_ros.io`` does not load rosbags):

- packets: :class:`Packetizer` (events or raw sensor bytes -> event messages, to any sink)
- writing: :class:`BagWriter` (rosbag2), :class:`Rosbag1Writer`, :func:`write_events_rosbag1`,
  :func:`reencode_bag` (bag -> bag, keeping stamps, seq, frame_id and the other topics)
- reading: :func:`open_bag`, :func:`read_events`, :func:`iter_event_packets`, :func:`bag_info`,
  :func:`pick_event_topic`
- messages: :func:`camera_info`, :func:`pose_stamped`, :func:`joint_state`,
  :func:`time_reference`, :func:`stamp_to_ns`, :func:`ns_to_stamp` and their readers
- typestores: :func:`ros2_typestore`, :func:`ros1_typestore`
"""

from __future__ import annotations

import importlib

_EXPORTS = {
    "packetizer": ("Packetizer",),
    "rosbag2": ("BagWriter",),
    "bag_reader": ("BagReader", "BagInfo", "TopicInfo", "EventTopicInfo", "EventStream", "EventPacketData",
                   "open_bag", "read_events", "iter_event_packets", "bag_info", "pick_event_topic", "event_topics"),
    "reencode": ("reencode_bag",),
    "rosbag1": ("Rosbag1Writer", "write_events_rosbag1"),
    "messages": ("camera_info", "pose_stamped", "joint_state", "time_reference", "stamp_to_ns", "ns_to_stamp",
                 "K_from_camera_info", "intrinsics_from_camera_info", "pose_from_pose_stamped", "pose_to_matrix",
                 "time_reference_ns"),
    "typestore": ("ros2_typestore", "ros1_typestore", "EVENT_PACKET", "DVS_EVENT_ARRAY"),
}
_WHERE = {name: module for module, names in _EXPORTS.items() for name in names}

__all__ = sorted(_WHERE)


def __getattr__(name):
    module = _WHERE.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f"{__name__}.{module}"), name)
    globals()[name] = value
    return value


def __dir__():
    return sorted(set(globals()) | set(__all__))
