"""rosbag2 writing (MCAP default, sqlite3 optional).

:class:`BagWriter` is an :class:`~evdnerf_ros.io.bag_writer.EventBagWriter`: atomic output,
topics, message writes, and event topics through its :class:`~evdnerf_ros.io.packetizer.Packetizer`
(see that module for packets, encodings and the time conventions).

Reading lives in :mod:`evdnerf_ros.io.bag_reader`; its names (:func:`open_bag`,
:func:`read_events`, :func:`iter_event_packets`, :func:`bag_info`, :class:`BagReader`, ...) are
re-exported here for existing callers, as is :class:`EventMessageEncoder` (now the
:class:`~evdnerf_ros.io.packetizer.Packetizer`).
"""

from __future__ import annotations

import os

from ..atomic import name_output_error
from ..errors import InputError
from .bag_reader import (  # noqa: F401 - re-exported for existing callers
    MCAP_MAGIC, ROS1_MAGIC, SQLITE_MAGIC, STORAGES, BagInfo, BagMessage, BagReader, EventPacketData, EventStream,
    EventTopicInfo, TopicInfo, TopicSummary, bag_info, event_topics,
    iter_event_packets, open_bag, pick_event_topic, read_events,
)
from .bag_writer import EventBagWriter
from .packetizer import (  # noqa: F401 - re-exported for existing callers
    DEFAULT_EVENT_TOPIC, DEFAULT_PACKET_NS, EVENT_TYPES, PACKET_ENCODINGS, STREAM_ENCODINGS, WRITE_ENCODINGS,
    Packetizer,
)

__all__ = [
    "BagWriter", "EventMessageEncoder", "Packetizer",
    # reading (evdnerf_ros.io.bag_reader)
    "BagInfo", "BagMessage", "BagReader", "EventPacketData", "EventStream", "EventTopicInfo", "TopicInfo",
    "TopicSummary", "bag_info", "event_topics", "iter_event_packets", "open_bag", "pick_event_topic", "read_events",
    "MCAP_MAGIC", "ROS1_MAGIC", "SQLITE_MAGIC", "STORAGES",
    # constants (evdnerf_ros.io.packetizer)
    "DEFAULT_EVENT_TOPIC", "DEFAULT_PACKET_NS", "EVENT_TYPES", "PACKET_ENCODINGS", "STREAM_ENCODINGS",
    "WRITE_ENCODINGS",
]

#: The live encoder of earlier versions: a Packetizer (sink(topic, msgtype, data, stamp_ns)).
EventMessageEncoder = Packetizer


class BagWriter(EventBagWriter):
    """rosbag2 writer (context manager). ``storage``: "mcap" (default) or "sqlite3";
    ``version``: rosbag2 metadata version 8 (default; its QoS strings are what Humble's
    rosbag2 parses) or 9."""

    def __init__(self, path, *, storage: str = "mcap", version: int = 8):
        if storage not in STORAGES:
            raise InputError(f"{path}: storage {storage!r} is not one of {list(STORAGES)}")
        if version not in (8, 9):
            raise InputError(f"{path}: rosbag2 version must be 8 or 9, got {version!r}")
        super().__init__(path)
        self.storage = storage
        self.version = version

    def _make_writer(self, tmp_path):
        from rosbags.rosbag2 import StoragePlugin, Writer

        plugin = StoragePlugin.MCAP if self.storage == "mcap" else StoragePlugin.SQLITE3
        return Writer(tmp_path, version=self.version, storage_plugin=plugin)

    def _add_connection(self, topic, msgtype):
        return self._writer.add_connection(topic, msgtype, typestore=self.typestore)

    def flush(self) -> None:
        """Put what was written so far on disk, so that a recording killed outright (SIGKILL,
        power loss) keeps it: MCAP closes its pending chunk, sqlite3 commits. The bag is still
        published under its name only by close(); a killed one's messages are salvaged with
        :func:`evdnerf_ros.io.mcap_salvage.salvage_bag` (``evdnerf salvage-bag``)."""
        self._check_open()
        storage = self._writer.storage          # rosbags' storage writer (rosbags pinned < 0.12)
        try:
            if self.storage == "mcap":
                if storage.chunk.bio.tell():
                    storage.close_chunk()
                storage.bio.flush()
                os.fsync(storage.bio.fileno())
            else:
                storage.conn.commit()
        except OSError as exc:
            name_output_error(exc, self.path)
            raise

    def write_camera_info(self, topic: str, width: int, height: int, K, D=(0.0, 0.0, 0.0, 0.0, 0.0), *,
                          stamp_ns: int, frame_id: str = "event_camera", **kwargs):
        """Write a ``sensor_msgs/msg/CameraInfo`` (see :func:`evdnerf_ros.io.messages.camera_info`)."""
        from .messages import camera_info

        msg = camera_info(width, height, K, D, frame_id=frame_id, stamp_ns=stamp_ns, **kwargs)
        self.write(topic, "sensor_msgs/msg/CameraInfo", msg, stamp_ns)
