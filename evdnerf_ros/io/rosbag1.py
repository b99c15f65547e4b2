"""ROS 1 bag export (``.bag`` version 2.0, written with rosbags.rosbag1).

Event topics are ``dvs_msgs/EventArray`` by default (the rpg_dvs_ros message every ROS 1
event pipeline reads), serialised with numpy in ROS 1's packed layout: Header (seq u32,
stamp secs/nsecs u32, frame_id), height, width, then 13 bytes per event (x u16, y u16,
secs u32, nsecs u32, polarity u8). ``header.seq`` counts the topic's messages from 0.
ROS 1 time is unsigned: event times must be >= 0 and below 2**32 s.

:class:`Rosbag1Writer` is an :class:`~evdnerf_ros.io.bag_writer.EventBagWriter` (atomic
temp-then-rename output, topics, event topics through its packetizer in the ROS 1 wire
format). Read bags back with :func:`evdnerf_ros.io.bag_reader.read_events` (it detects ROS 1 bags).
"""

from __future__ import annotations

from .bag_writer import EventBagWriter
from .packetizer import DEFAULT_EVENT_TOPIC, DEFAULT_PACKET_NS
from .typestore import ros1_typestore


class Rosbag1Writer(EventBagWriter):
    """ROS 1 bag writer (context manager); messages are built from the ROS 1 typestore
    (:func:`evdnerf_ros.io.typestore.ros1_typestore`), e.g. ``std_msgs/msg/Header`` with seq.
    ``write_events`` defaults to ``dvs_msgs/EventArray`` (encoding "array")."""

    ros1 = True
    default_encoding = "array"

    def _make_writer(self, tmp_path):
        from rosbags.rosbag1 import Writer

        return Writer(tmp_path)

    def _add_connection(self, topic, msgtype):
        return self._writer.add_connection(topic, msgtype, typestore=ros1_typestore())


def write_events_rosbag1(path, events, *, width: int, height: int, topic: str = DEFAULT_EVENT_TOPIC,
                         packet_ns: int = DEFAULT_PACKET_NS, max_packet_events: int | None = None,
                         frame_id: str = "event_camera", encoding: str = "array", triggers=None) -> int:
    """Write one event topic to a new ROS 1 bag at ``path``; returns the number of messages."""
    with Rosbag1Writer(path) as w:
        return w.write_events(topic, events, width=width, height=height, encoding=encoding, triggers=triggers,
                              packet_ns=packet_ns, max_packet_events=max_packet_events, frame_id=frame_id)
