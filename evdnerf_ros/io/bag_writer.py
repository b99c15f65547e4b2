"""What every bag writer shares (rosbag2 in :mod:`evdnerf_ros.io.rosbag2`, ROS 1 in
:mod:`evdnerf_ros.io.rosbag1`): the atomic output, topics / connections, serialised and
message-object writes, and event topics through a :class:`~evdnerf_ros.io.packetizer.Packetizer`
the writer owns (its sink writes into the bag).

Atomic output
-------------
The bag is written under its final name inside a temporary sibling directory
(:func:`evdnerf_ros.atomic.atomic_output`) and renamed into place when the writer closes
cleanly; on any exception (or :meth:`EventBagWriter.abort`) the temporary directory is removed,
and a bag whose event write failed part-way is never published. An existing output path is
refused with OutputExistsError.
"""

from __future__ import annotations

import abc
from contextlib import ExitStack
from pathlib import Path
from typing import Any

from ..atomic import atomic_output, name_output_error
from ..errors import InputError, OutputExistsError
from .packetizer import DEFAULT_PACKET_NS, Packetizer, check_time, check_topic
from .typestore import ros1_typestore, ros2_typestore


class _Aborted(Exception):
    """Thrown into the atomic-output context to discard the temporary output."""


class AtomicOutput:
    """Holds :func:`evdnerf_ros.atomic.atomic_output` open across open() / close() calls."""

    def __init__(self, path, *, directory: bool = True):
        self._stack = ExitStack()
        self.tmp_path = self._stack.enter_context(atomic_output(path, directory=directory))
        if not directory:
            # a ROS 1 bag is one file, and its writer refuses a path that exists already
            self.tmp_path.unlink()

    def publish(self):
        self._stack.close()

    def discard(self):
        exc = _Aborted()
        self._stack.__exit__(type(exc), exc, None)


class EventBagWriter(abc.ABC):
    """A bag writer (context manager) with event topics; subclasses open the storage."""

    #: ROS 1 wire format (else ROS 2 CDR)
    ros1 = False
    #: write_events' default encoding
    default_encoding = "evt3"

    def __init__(self, path):
        self.path = Path(path)
        if self.path.exists() or self.path.is_symlink():
            raise OutputExistsError(self.path)
        self._out = None
        self._writer = None
        self._conns: dict[str, tuple[Any, str]] = {}
        self._failed: str | None = None
        self._state = "new"
        self.packetizer = Packetizer(self._write_event_message, ros1=self.ros1, name=str(self.path))

    # ----- lifecycle
    @abc.abstractmethod
    def _make_writer(self, tmp_path):
        ...

    @abc.abstractmethod
    def _add_connection(self, topic, msgtype):
        ...

    def open(self):
        if self._state != "new":
            raise InputError(f"{self.path}: writer already {self._state}")
        self._out = AtomicOutput(self.path, directory=not self.ros1)
        try:
            self._writer = self._make_writer(self._out.tmp_path)
            self._writer.open()
        except BaseException:
            self._out.discard()
            raise
        self._state = "open"
        return self

    def close(self):
        """Finish the bag and move it into place (nothing is published if anything failed)."""
        if self._state != "open":
            raise InputError(f"{self.path}: writer is {self._state}, not open")
        try:
            failed = self._failed or self.packetizer.failed
            if failed:
                raise InputError(f"{self.path}: not written because an earlier write failed part-way "
                                 f"({failed}); fix the input and write the bag again")
            self._writer.close()
            self._writer = None
            self._out.publish()
        except BaseException as exc:
            name_output_error(exc, self.path)
            self.abort()
            raise
        self._state = "closed"

    def abort(self):
        """Drop everything written so far; the output path is left untouched."""
        writer, self._writer = self._writer, None
        if writer is not None:
            try:
                writer.abort()
            except Exception:  # noqa: BLE001 - best effort, the directory goes anyway
                pass
        if self._out is not None:
            self._out.discard()
        self._state = "aborted"

    def __enter__(self):
        return self.open()

    def __exit__(self, exc_type, exc, tb):
        if exc_type is None:
            self.close()
        elif self._state == "open":
            self.abort()
        return False

    def _check_open(self):
        if self._state != "open":
            raise InputError(f"{self.path}: writer is {self._state}; use it inside 'with' or call open() first")

    # ----- connections and raw writes
    @property
    def typestore(self):
        return ros1_typestore() if self.ros1 else ros2_typestore()

    def _connection(self, topic, msgtype):
        check_topic(topic)
        have = self._conns.get(topic)
        if have is not None:
            if have[1] != msgtype:
                raise InputError(f"{self.path}: topic {topic} already carries {have[1]}; cannot also write "
                                 f"{msgtype} to it (use another topic)")
            return have[0]
        if msgtype not in self.typestore.fielddefs:
            raise InputError(f"{self.path}: unknown message type {msgtype!r} for topic {topic}; use a type of "
                             "the ROS typestore (e.g. 'sensor_msgs/msg/CameraInfo') or register it first")
        conn = self._add_connection(topic, msgtype)
        self._conns[topic] = (conn, msgtype)
        return conn

    def _write_raw(self, conn, t_ns, data):
        try:
            self._writer.write(conn, t_ns, data)
        except OSError as exc:          # a full disk: the error names the bag, not a file object
            name_output_error(exc, self.path)
            raise

    def _write_event_message(self, topic, msgtype, data, t_ns):
        """The packetizer's sink."""
        self._write_raw(self._connection(topic, msgtype), t_ns, data)

    def add_topic(self, topic: str, msgtype: str) -> None:
        """Declare a topic now (a bag then lists it even if no message follows)."""
        self._check_open()
        self._connection(topic, msgtype)

    def write_raw(self, topic: str, msgtype: str, data, t_ns: int):
        """Write an already serialised message (CDR for rosbag2, ROS 1 wire format for .bag)."""
        self._check_open()
        t_ns = check_time(t_ns, f"{self.path}: topic {topic}")
        if self.packetizer.is_event_topic(topic):
            raise InputError(f"{self.path}: topic {topic} is an event topic written by write_events")
        self._write_raw(self._connection(topic, msgtype), t_ns, bytes(data))

    def write(self, topic: str, msgtype: str, msg, t_ns: int):
        """Serialise a rosbags message object and write it at bag time ``t_ns`` (int ns)."""
        self._check_open()
        what = f"{self.path}: topic {topic}"
        t_ns = check_time(t_ns, what)
        if self.packetizer.is_event_topic(topic):
            raise InputError(f"{what}: this is an event topic written by write_events")
        conn = self._connection(topic, msgtype)
        try:
            if self.ros1:
                data = self.typestore.serialize_ros1(msg, msgtype)
            else:
                data = self.typestore.serialize_cdr(msg, msgtype)
        except Exception as exc:  # noqa: BLE001 - rosbags raises assorted errors for bad objects
            raise InputError(f"{what}: cannot serialise the message as {msgtype}: {exc!r}; build it with "
                             "evdnerf_ros.io.messages or the typestore's types") from None
        self._write_raw(conn, t_ns, data)

    # ----- event topics (through the packetizer)
    def _event_topic_free(self, topic):
        self._check_open()
        check_topic(topic)
        if topic in self._conns and not self.packetizer.is_event_topic(topic):
            raise InputError(f"{self.path}: topic {topic}: topic already carries {self._conns[topic][1]} messages "
                             "written by write()")

    def write_events(self, topic: str, events, *, width: int, height: int, encoding: str | None = None,
                     triggers=None, packet_ns: int = DEFAULT_PACKET_NS, max_packet_events: int | None = None,
                     frame_id: str = "event_camera") -> int:
        """Append events to an event topic (see :mod:`evdnerf_ros.io.packetizer`); returns the
        number of messages written. ``encoding`` defaults to the writer's ``default_encoding``."""
        self._event_topic_free(topic)
        return self.packetizer.write_events(topic, events, width=width, height=height,
                                            encoding=encoding or self.default_encoding, triggers=triggers,
                                            packet_ns=packet_ns, max_packet_events=max_packet_events,
                                            frame_id=frame_id)

    def write_packet(self, topic: str, events, **kwargs) -> int:
        """One event message with a given stamp / seq / frame_id (:meth:`Packetizer.write_packet`)."""
        self._event_topic_free(topic)
        return self.packetizer.write_packet(topic, events, **kwargs)

    def write_raw_packet(self, topic: str, payload, **kwargs) -> int:
        """A sensor's bytes as one EventPacket, untouched (:meth:`Packetizer.write_raw_packet`)."""
        self._event_topic_free(topic)
        return self.packetizer.write_raw_packet(topic, payload, **kwargs)
