"""rosbag2 writing (MCAP default, sqlite3 optional) and reading of any bag (rosbag2, bare
.mcap / .db3, ROS 1 .bag), with event topics packed and unpacked by numpy.

Writing event topics (:meth:`BagWriter.write_events`)
----------------------------------------------------
Events are cut into packets as metavision_driver does: a packet opens at its first event
and closes before the first event ``packet_ns`` later (default 1 ms), or after
``max_packet_events`` events. Each call packs its own events completely (a packet never
spans two calls); calls on one topic continue one stream (times must not go back, encoder
state and ``seq`` carry over). Every message's bag timestamp equals its ``header.stamp`` =
the time of the packet's first event (or of its first trigger when a trigger precedes it).

Encodings and our ``time_base`` convention (``event_camera_msgs/msg/EventPacket``):

- ``evt3`` / ``evt2``: the packets of a topic are consecutive chunks of ONE sensor stream
  (each chunk re-states time and y, so a reader may start at any packet). ``time_base`` is
  constant for the topic and is the ns time of sensor time 0, chosen as the time of the
  topic's first event (or trigger). Event time = ``time_base + 1000 * sensor_us``, so every
  time must lie on the whole-µs grid counted from that first time; otherwise InputError
  (use ``encoding="mono"`` or ``"array"`` for ns resolution, or round explicitly with
  ``evdnerf_ros.events.codecs.quantize_to_us``).
  External triggers are carried in-stream (only these encodings carry triggers).
- ``mono``: one 64-bit word per event; ``time_base`` = the packet's first event time and
  each event stores a 32-bit ns offset from it (packet_ns must be <= 2**32).
- ``array``: ``dvs_msgs/msg/EventArray`` (per-event ``builtin_interfaces/Time``, ns exact),
  built with numpy in the exact CDR layout (see :mod:`evdnerf_ros.io.event_messages`).

All times must be >= 0 (bag timestamps and ``time_base`` are unsigned).

Atomic output
-------------
The bag is written under its final name inside a temporary sibling directory
(:func:`evdnerf_ros.atomic.atomic_output`) and renamed into place when the writer closes
cleanly; on any exception (or :meth:`BagWriter.abort`) the temporary directory is removed,
and a bag whose ``write_events`` failed part-way is never published. An existing output
path is refused with OutputExistsError.

Reading
-------
:func:`open_bag` detects a rosbag2 directory (metadata.yaml + .mcap/.db3 files), a bare
``.mcap`` or ``.db3`` file, or a ROS 1 ``.bag`` file from its magic bytes.
:func:`read_events` / :func:`iter_event_packets` decode EventPacket (evt3, evt2: one
streaming decoder per topic, time_base of the first packet; mono: per packet) and
dvs_msgs EventArray (ROS 2 CDR and ROS 1) without per-event Python. :func:`bag_info`
summarises a bag. Damaged files raise FormatError naming the file.
"""

from __future__ import annotations

import abc

import os
import sqlite3
import struct
from collections.abc import Iterator
from contextlib import ExitStack
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..atomic import atomic_output, name_output_error
from ..errors import EvdnerfError, FormatError, InputError, OutputExistsError
from ..events.types import (EVENT_DTYPE, MAX_SENSOR_SIZE, TRIGGER_DTYPE, as_events, empty_events, empty_triggers,
                            validate_events)
from ..limits import check_memory, memory_budget
from . import event_messages as em
from .typestore import DVS_EVENT_ARRAY, EVENT_PACKET, ros1_typestore, ros2_typestore

STORAGES = ("mcap", "sqlite3")
PACKET_ENCODINGS = ("evt3", "evt2", "mono")
WRITE_ENCODINGS = PACKET_ENCODINGS + ("array",)
STREAM_ENCODINGS = ("evt3", "evt2")
DEFAULT_EVENT_TOPIC = "/event_camera/events"
DEFAULT_PACKET_NS = 1_000_000
EVENT_TYPES = (EVENT_PACKET, DVS_EVENT_ARRAY)

MCAP_MAGIC = b"\x89MCAP0\r\n"
SQLITE_MAGIC = b"SQLite format 3\x00"
ROS1_MAGIC = b"#ROSBAG V2.0\n"


# =========================================================================== atomic output


class _Aborted(Exception):
    """Thrown into the atomic-output context to discard the temporary output."""


class _AtomicOutput:
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


# =========================================================================== writers


@dataclass
class _TopicState:
    topic: str
    msgtype: str
    encoding: str
    width: int
    height: int
    frame_id: str
    conn: Any
    seq: int = 0
    time_base: int | None = None
    encoder: Any = None
    last_t: int | None = None
    prefix: Any = None


def _positive_int(value, what, *, upper=2**32 - 1):
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)) \
            or not 0 < int(value) <= upper:
        raise InputError(f"{what}: expected an integer in [1, {upper}], got {value!r}")
    return int(value)


def _check_topic(topic):
    if not isinstance(topic, str) or not topic.startswith("/") or len(topic) < 2 or any(c.isspace() for c in topic):
        raise InputError(f"topic {topic!r}: expected an absolute ROS topic name such as '/event_camera/events'")
    return topic


def _check_time(t_ns, what):
    if isinstance(t_ns, (bool, np.bool_)) or not isinstance(t_ns, (int, np.integer)):
        raise InputError(f"{what}: timestamps are int64 nanoseconds, got {type(t_ns).__name__} {t_ns!r}")
    t_ns = int(t_ns)
    if not 0 <= t_ns < 2**63:
        raise InputError(f"{what}: bag timestamp {t_ns} ns is negative or beyond int64; bag times are "
                         "unsigned, shift the time origin")
    return t_ns


class _EventBagWriter(abc.ABC):
    """Shared logic of the rosbag2 and ROS 1 writers: atomic output, topics, event packetising."""

    _ros1 = False
    _encodings = WRITE_ENCODINGS

    def __init__(self, path):
        self._out = None
        self._writer = None
        self.path = Path(path)
        if self.path.exists() or self.path.is_symlink():
            raise OutputExistsError(self.path)
        self._conns: dict[str, tuple[Any, str]] = {}
        self._topics: dict[str, _TopicState] = {}
        self._failed: str | None = None
        self._state = "new"

    # ----- lifecycle
    @abc.abstractmethod
    def _make_writer(self, tmp_path):
        ...

    def open(self):
        if self._state != "new":
            raise InputError(f"{self.path}: writer already {self._state}")
        self._out = _AtomicOutput(self.path, directory=not self._ros1)
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
            if self._failed:
                raise InputError(f"{self.path}: not written because an earlier write failed part-way "
                                 f"({self._failed}); fix the input and write the bag again")
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
        return ros1_typestore() if self._ros1 else ros2_typestore()

    @abc.abstractmethod
    def _add_connection(self, topic, msgtype):
        ...

    def _connection(self, topic, msgtype):
        _check_topic(topic)
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

    def add_topic(self, topic: str, msgtype: str) -> None:
        """Declare a topic now (a bag then lists it even if no message follows)."""
        self._check_open()
        self._connection(topic, msgtype)

    def write_raw(self, topic: str, msgtype: str, data, t_ns: int):
        """Write an already serialised message (CDR for rosbag2, ROS 1 wire format for .bag)."""
        self._check_open()
        t_ns = _check_time(t_ns, f"{self.path}: topic {topic}")
        if topic in self._topics:
            raise InputError(f"{self.path}: topic {topic} is an event topic written by write_events")
        self._write_raw(self._connection(topic, msgtype), t_ns, bytes(data))

    def write(self, topic: str, msgtype: str, msg, t_ns: int):
        """Serialise a rosbags message object and write it at bag time ``t_ns`` (int ns)."""
        self._check_open()
        what = f"{self.path}: topic {topic}"
        t_ns = _check_time(t_ns, what)
        if topic in self._topics:
            raise InputError(f"{what}: this is an event topic written by write_events")
        conn = self._connection(topic, msgtype)
        try:
            if self._ros1:
                data = self.typestore.serialize_ros1(msg, msgtype)
            else:
                data = self.typestore.serialize_cdr(msg, msgtype)
        except Exception as exc:  # noqa: BLE001 - rosbags raises assorted errors for bad objects
            raise InputError(f"{what}: cannot serialise the message as {msgtype}: {exc!r}; build it with "
                             "evdnerf_ros.io.messages or the typestore's types") from None
        self._write_raw(conn, t_ns, data)

    # ----- events
    def write_events(self, topic: str, events, *, width: int, height: int, encoding: str = "evt3",
                     triggers=None, packet_ns: int = DEFAULT_PACKET_NS, max_packet_events: int | None = None,
                     frame_id: str = "event_camera") -> int:
        """Append events to an event topic (see the module doc); returns the number of messages written."""
        self._check_open()
        what = f"{self.path}: topic {topic}"
        _check_topic(topic)
        if encoding not in self._encodings:
            raise InputError(f"{what}: encoding {encoding!r} is not one of {list(self._encodings)}")
        width = _positive_int(width, f"{what}: width")
        height = _positive_int(height, f"{what}: height")
        packet_ns = _positive_int(packet_ns, f"{what}: packet_ns", upper=2**62)
        if max_packet_events is not None:
            max_packet_events = _positive_int(max_packet_events, f"{what}: max_packet_events")
        if not isinstance(frame_id, str):
            raise InputError(f"{what}: frame_id must be a string")
        if encoding in STREAM_ENCODINGS and (width > MAX_SENSOR_SIZE or height > MAX_SENSOR_SIZE):
            raise InputError(f"{what}: {encoding} carries at most {MAX_SENSOR_SIZE}x{MAX_SENSOR_SIZE} pixels, "
                             f"got {width}x{height}; use encoding 'mono' or 'array'")
        if encoding == "mono":
            if packet_ns > 2**32:
                raise InputError(f"{what}: mono stores 32-bit ns offsets, so packet_ns must be <= 2**32 "
                                 f"(got {packet_ns})")
            if width > 1 << 16 or height > 1 << 15:
                raise InputError(f"{what}: mono carries x < 65536 and y < 32768, got {width}x{height}")
        events = validate_events(as_events(events, source=what), width=width, height=height, source=what)
        if triggers is not None and len(triggers):
            if encoding not in STREAM_ENCODINGS:
                raise InputError(f"{what}: triggers are only carried by encoding 'evt3' (or 'evt2'), not "
                                 f"{encoding!r}; write the events with encoding='evt3'")
            triggers = em.check_triggers(triggers, what=what)
        else:
            triggers = empty_triggers()
        if events.size == 0 and triggers.size == 0:
            return 0

        first_t = min(int(a["t"][0]) for a in (events, triggers) if a.size)
        last_t = max(int(a["t"][-1]) for a in (events, triggers) if a.size)
        if first_t < 0:
            raise InputError(f"{what}: time {first_t} ns is negative; bag timestamps and time_base are "
                             "unsigned, shift the time origin")
        if last_t >= 2**63:
            raise InputError(f"{what}: time {last_t} ns beyond int64")

        state = self._topics.get(topic)
        if state is None:
            if topic in self._conns:
                raise InputError(f"{what}: topic already carries {self._conns[topic][1]} messages written by write()")
            msgtype = DVS_EVENT_ARRAY if encoding == "array" else EVENT_PACKET
            state = _TopicState(topic, msgtype, encoding, width, height, frame_id, None)
            if encoding in STREAM_ENCODINGS:
                state.time_base = first_t
        else:
            if (state.encoding, state.width, state.height, state.frame_id) != (encoding, width, height, frame_id):
                raise InputError(
                    f"{what}: earlier calls wrote encoding={state.encoding!r}, {state.width}x{state.height}, "
                    f"frame_id={state.frame_id!r}; got encoding={encoding!r}, {width}x{height}, "
                    f"frame_id={frame_id!r}; one topic carries one stream")
            if first_t < state.last_t:
                raise InputError(f"{what}: this call starts at t={first_t} ns, before the end of the previous "
                                 f"call (t={state.last_t} ns); successive calls must continue in time")
        if encoding in STREAM_ENCODINGS:
            for name, arr in (("event", events), ("trigger", triggers)):
                off = (arr["t"] - state.time_base) % 1000
                if np.any(off):
                    i = int(np.flatnonzero(off)[0])
                    raise InputError(
                        f"{what}: {name} {i} at t={int(arr['t'][i])} ns is not a whole microsecond after the "
                        f"topic's time_base {state.time_base} ns; {encoding} carries µs. Use encoding='mono' or "
                        "'array' for ns resolution, or round explicitly first with evdnerf_ros.events.codecs."
                        f"quantize_to_us(events, time_base_ns={state.time_base})")

        bounds = em.packet_bounds(events["t"], packet_ns, max_packet_events)
        if events.size:
            t0s = events["t"][bounds[:-1]]
        else:
            bounds = np.array([0, 0], dtype=np.int64)
            t0s = triggers["t"][:1]
        tbounds = em.assign_triggers(t0s, triggers["t"])
        stamps = t0s.copy()
        has_trig = tbounds[1:] > tbounds[:-1]
        if np.any(has_trig):
            first_trig = triggers["t"][np.minimum(tbounds[:-1], max(triggers.size - 1, 0))]
            stamps = np.where(has_trig, np.minimum(stamps, first_trig), stamps)

        if state.conn is None:  # first successful validation: now create the connection
            state.conn = self._connection(topic, state.msgtype)
            self._topics[topic] = state
        try:
            if encoding == "array":
                n = self._write_array_packets(state, events, bounds, stamps.tolist())
            else:
                n = self._write_event_packets(state, events, triggers, bounds, tbounds, stamps.tolist())
        except BaseException as exc:
            self._failed = f"write_events on {topic}: {exc}"
            raise
        state.last_t = last_t
        return n

    def _write_event_packets(self, state, events, triggers, bounds, tbounds, stamps):
        from ..events.codecs import make_encoder  # the codecs package is optional until needed

        what = f"{self.path}: topic {state.topic}"
        if state.prefix is None:
            cls = em.Ros1EventPacketPrefix if self._ros1 else em.CdrEventPacketPrefix
            state.prefix = cls(state.frame_id, state.height, state.width, state.encoding)
        if state.encoding in STREAM_ENCODINGS and state.encoder is None:
            state.encoder = make_encoder(state.encoding, time_base_ns=state.time_base)
        for k, stamp in enumerate(stamps):
            ev = events[bounds[k]:bounds[k + 1]]
            try:
                if state.encoding == "mono":
                    time_base = stamp
                    payload = make_encoder("mono", time_base_ns=time_base).encode(ev)
                else:
                    time_base = state.time_base
                    tr = triggers[tbounds[k]:tbounds[k + 1]]
                    payload = state.encoder.encode(ev, triggers=tr if tr.size else None)
            except EvdnerfError as exc:
                raise type(exc)(f"{what}: packet {state.seq}: {exc}") from exc
            if self._ros1:
                head = state.prefix(state.seq, stamp, state.seq, time_base, len(payload))
            else:
                head = state.prefix(stamp, state.seq, time_base, len(payload))
            self._write_raw(state.conn, stamp, head + payload)
            state.seq += 1
        return len(stamps)

    def _write_array_packets(self, state, events, bounds, stamps):
        what = f"{self.path}: topic {state.topic}"
        if state.prefix is None:
            cls = em.Ros1EventArrayPrefix if self._ros1 else em.CdrEventArrayPrefix
            state.prefix = cls(state.frame_id, state.height, state.width)
        prefix = state.prefix
        npk = len(stamps)
        scratch = None
        k = 0
        while k < npk:
            k2 = int(np.searchsorted(bounds, bounds[k] + em.BLOCK_EVENTS, "right")) - 1
            k2 = min(max(k2, k + 1), npk)
            s0, s1 = int(bounds[k]), int(bounds[k2])
            block = events[s0:s1]
            if self._ros1:  # events were validated sorted
                rec = em.ros1_event_records(block, what=what, is_sorted=True, out=scratch)
            else:
                rec = em.cdr_event_records(block, what=what, is_sorted=True, out=scratch)
            if scratch is None or rec.size > scratch.size:
                scratch = rec
            mv = memoryview(rec.view(np.uint8))
            local = (bounds[k:k2 + 1] - s0).tolist()
            for j in range(k, k2):
                a, b = local[j - k], local[j - k + 1]
                stamp = stamps[j]
                if self._ros1:
                    data = prefix(state.seq, stamp, b - a) + mv[13 * a:13 * b]
                else:
                    data = b"".join((prefix(stamp, b - a), mv[16 * a:16 * a + 4], mv[16 * a + 6:16 * b - 1]))
                self._write_raw(state.conn, stamp, data)
                state.seq += 1
            k = k2
        return npk


class BagWriter(_EventBagWriter):
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


class EventMessageEncoder(_EventBagWriter):
    """Packetise and serialise events exactly as :meth:`BagWriter.write_events` does, without a
    bag: every message goes to ``sink(topic, msgtype, data, stamp_ns)`` (a live publisher).
    Calls on a topic continue one stream (evt3 time_base, encoder state and seq carry over)."""

    def __init__(self, sink):
        self._sink = sink
        self.path = Path("<live>")
        self._out = None
        self._writer = None
        self._conns = {}
        self._topics = {}
        self._failed = None
        self._state = "open"

    def _make_writer(self, tmp_path):  # pragma: no cover - it starts open, so open() refuses
        raise TypeError("EventMessageEncoder sends messages to its sink; it never writes a bag file")

    def _add_connection(self, topic, msgtype):
        return (topic, msgtype)

    def _write_raw(self, conn, t_ns, data):
        self._sink(conn[0], conn[1], data, t_ns)

    def close(self):
        self._state = "closed"

    def abort(self):
        self._state = "aborted"


# =========================================================================== reading


@dataclass
class TopicSummary:
    name: str
    msgtype: str | None
    message_count: int


@dataclass
class BagMessage:
    topic: str
    msgtype: str
    t_ns: int
    data: bytes


def _detect(path: Path) -> tuple[str, str]:
    """(layout, storage): ("rosbag2", "mcap"|"sqlite3") for a directory, ("file", ...) for a bare file."""
    if not path.exists():
        raise InputError(f"{path}: no such file or directory")
    if path.is_dir():
        meta = path / "metadata.yaml"
        if not meta.exists():
            inside = sorted(p.name for p in path.iterdir() if p.suffix in (".mcap", ".db3", ".bag"))
            hint = f"; it holds {inside}: open that file instead" if inside else ""
            raise InputError(f"{path}: a directory without metadata.yaml is not a rosbag2 bag{hint}")
        try:
            from ruamel.yaml import YAML

            info = YAML(typ="safe").load(meta.read_text())["rosbag2_bagfile_information"]
            storage = str(info["storage_identifier"])
        except Exception as exc:  # noqa: BLE001
            raise FormatError(f"metadata.yaml is unreadable ({exc}); the bag directory is damaged",
                              source=str(meta)) from None
        if storage not in STORAGES:
            raise InputError(f"{path}: storage {storage!r} is not supported (only {list(STORAGES)})")
        return "rosbag2", storage
    with open(path, "rb") as f:
        head = f.read(16)
    for magic, storage, suffix in ((MCAP_MAGIC, "mcap", ".mcap"), (SQLITE_MAGIC, "sqlite3", ".db3"),
                                   (ROS1_MAGIC, "rosbag1", ".bag")):
        if head.startswith(magic):
            if storage != "rosbag1" and path.suffix != suffix:
                raise InputError(f"{path}: this is a bare {storage} bag file but its name does not end in "
                                 f"{suffix}; the reader picks the storage from the suffix, rename it")
            return "file", storage
    if not head:
        raise FormatError("file is empty", source=str(path))
    raise InputError(f"{path}: not a bag (no MCAP, SQLite or ROS 1 bag magic at the start); expected a rosbag2 "
                     "directory, a .mcap, a .db3 or a ROS 1 .bag")


def _reader_errors():
    import apsw
    from rosbags.rosbag1 import ReaderError as R1Error
    from rosbags.rosbag2 import ReaderError as R2Error

    # what rosbags / apsw / zstd raise on damaged input (a corrupt length field can even ask
    # for an impossible allocation: MemoryError / OverflowError)
    return (R1Error, R2Error, apsw.Error, sqlite3.Error, struct.error, EOFError, ValueError, KeyError,
            IndexError, AssertionError, OSError, RuntimeError, MemoryError, OverflowError, UnicodeError)


class BagReader:
    """An open bag of any supported kind (use :func:`open_bag`)."""

    def __init__(self, path):
        self.path = Path(path)
        self.layout, self.storage = _detect(self.path)
        self.ros1 = self.storage == "rosbag1"
        self._reader = None
        self._store = None

    # ----- lifecycle
    def open(self):
        if self.storage == "mcap":
            self._check_mcap_footers()
        errors = _reader_errors()
        try:
            if self.ros1:
                from rosbags.rosbag1 import Reader
            else:
                from rosbags.rosbag2 import Reader
            reader = Reader(self.path)
            reader.open()
        except errors as exc:
            raise FormatError(f"cannot open the bag: {exc}; the file is damaged or truncated "
                              "(an interrupted recording?)", source=str(self.path)) from None
        self._reader = reader
        return self

    def _check_mcap_footers(self):
        files = sorted(self.path.glob("*.mcap")) if self.path.is_dir() else [self.path]
        for f in files:
            with open(f, "rb") as fh:
                fh.seek(0, os.SEEK_END)
                size = fh.tell()
                fh.seek(max(0, size - len(MCAP_MAGIC)))
                tail = fh.read()
            if tail != MCAP_MAGIC:
                raise FormatError(f"MCAP file has no footer ({size} bytes): it is truncated or was not closed "
                                  "(an interrupted recording); try `mcap recover` to salvage it", source=str(f))

    def close(self):
        reader, self._reader = self._reader, None
        if reader is not None:
            reader.close()

    def __enter__(self):
        return self.open() if self._reader is None else self

    def __exit__(self, *exc):
        self.close()
        return False

    # ----- metadata
    @property
    def reader(self):
        if self._reader is None:
            raise InputError(f"{self.path}: bag is not open")
        return self._reader

    @property
    def topics(self) -> dict[str, TopicSummary]:
        out = {}
        for name, info in sorted(self.reader.topics.items()):
            out[name] = TopicSummary(name, info.msgtype, int(info.msgcount))
        return out

    @property
    def message_count(self) -> int:
        return int(self.reader.message_count)

    @property
    def start_ns(self) -> int | None:
        return int(self.reader.start_time) if self.message_count else None

    @property
    def end_ns(self) -> int | None:
        """Time of the last message (inclusive)."""
        if not self.message_count:
            return None
        return int(self.reader.end_time) - 1  # rosbags reports the end as last message + 1

    def topic(self, topic: str) -> TopicSummary:
        topics = self.topics
        if topic not in topics:
            listing = ", ".join(f"{n} [{t.msgtype}]" for n, t in topics.items()) or "none"
            raise InputError(f"{self.path}: no topic {topic!r}; topics in this bag: {listing}")
        return topics[topic]

    # ----- messages
    def messages(self, topics=None, *, start_ns: int | None = None, stop_ns: int | None = None
                 ) -> Iterator[BagMessage]:
        """Raw messages in bag time order (optionally only some topics, start <= t < stop)."""
        reader = self.reader
        conns = reader.connections
        if topics is not None:
            topics = [topics] if isinstance(topics, str) else list(topics)
            for t in topics:
                self.topic(t)
            conns = [c for c in conns if c.topic in topics]
            if not conns:
                return
        errors = _reader_errors()
        it = reader.messages(conns, start=start_ns, stop=stop_ns)
        while True:
            try:
                conn, t_ns, data = next(it)
            except StopIteration:
                return
            except errors as exc:
                raise FormatError(f"reading messages failed: {exc!r}; the bag is damaged or truncated",
                                  source=str(self.path)) from None
            yield BagMessage(conn.topic, conn.msgtype, int(t_ns), data)

    def _typestore_for(self, msgtype: str):
        """Our typestore, or (for types it lacks) a private copy extended with the bag's own definition."""
        base = ros1_typestore() if self.ros1 else ros2_typestore()
        if msgtype in base.fielddefs:
            return base
        from rosbags.typesys import Stores, get_types_from_msg

        from .typestore import MSG_DIR, _build

        if self._store is None:
            self._store = (_build(Stores.ROS1_NOETIC, MSG_DIR / "ros1") if self.ros1
                           else _build(Stores.ROS2_HUMBLE, MSG_DIR))
        if msgtype not in self._store.fielddefs:
            conn = next((c for c in self.reader.connections if c.msgtype == msgtype), None)
            text = conn.msgdef.data if conn is not None else ""
            if not text:
                raise InputError(f"{self.path}: message type {msgtype} is not known here and the bag carries "
                                 "no definition for it")
            try:
                self._store.register(get_types_from_msg(text, msgtype))
            except Exception as exc:  # noqa: BLE001 - rosbags raises assorted parse errors
                raise FormatError(f"cannot parse the bag's definition of {msgtype}: {exc}",
                                  source=str(self.path)) from None
        return self._store

    def deserialize(self, data, msgtype: str):
        store = self._typestore_for(msgtype)
        try:
            if self.ros1:
                return store.deserialize_ros1(data, msgtype)
            return store.deserialize_cdr(data, msgtype)
        except Exception as exc:  # noqa: BLE001
            raise FormatError(f"cannot deserialise a {msgtype} message: {exc!r}", source=str(self.path)) from None

    def read_messages(self, topic: str) -> Iterator[tuple[int, Any]]:
        """(bag time ns, message object) for every message of one topic (not for event topics:
        use :meth:`iter_event_packets`, which never builds per-event objects)."""
        for m in self.messages(topic):
            yield m.t_ns, self.deserialize(m.data, m.msgtype)

    def iter_event_packets(self, topic: str = DEFAULT_EVENT_TOPIC) -> Iterator[EventPacketData]:
        return _iter_event_packets(self, topic)


def open_bag(path) -> BagReader:
    """Open a rosbag2 directory, a bare .mcap / .db3 file or a ROS 1 .bag (use as a context manager)."""
    return BagReader(path).open()


# =========================================================================== event topics


@dataclass
class EventPacketData:
    """The decoded content of one event message."""

    index: int
    bag_time_ns: int
    stamp_ns: int
    events: np.ndarray
    triggers: np.ndarray
    width: int
    height: int
    encoding: str
    seq: int
    time_base: int | None


@dataclass
class EventStream:
    """All events of one topic."""

    events: np.ndarray
    triggers: np.ndarray
    width: int
    height: int
    encoding: str
    message_count: int
    topic: str
    msgtype: str = ""
    path: str = ""


def _decoded(dec):
    ev = getattr(dec, "events", None)
    tr = getattr(dec, "triggers", None)
    ev = empty_events() if ev is None else ev
    tr = empty_triggers() if tr is None else tr
    return ev, tr


class _Growing:
    """A 1-D array filled batch by batch: amortised growth instead of a final concatenate
    (one copy less, and no list of parts held next to the result).

    Growth is checked against the memory budget (`what` names the bag and topic); a size
    hint (from the bag index's message count, which a damaged or crafted bag can inflate) is
    only followed while it fits in a quarter of the budget."""

    def __init__(self, dtype, what: str = "events"):
        self.buf = np.empty(0, dtype)
        self.n = 0
        self._slot = None
        self.what = what

    def reserve(self, k: int, *, hint_total: int = 0) -> np.ndarray:
        need = self.n + k
        if need > self.buf.size:
            item = self.buf.dtype.itemsize
            check_memory(2 * need * item, f"{self.what}: {need} events so far",
                         "read the topic in pieces (iter_event_packets) or on a machine with more memory")
            if hint_total * item > memory_budget() // 4:
                hint_total = 0
            new = np.empty(max(need, int(self.buf.size * 1.5), hint_total), self.buf.dtype)
            new[:self.n] = self.buf[:self.n]
            self.buf = new
        self._slot = self.buf[self.n:need]
        return self._slot

    def append(self, arr: np.ndarray, *, hint_total: int = 0) -> None:
        if arr is not self._slot:
            self.reserve(arr.size, hint_total=hint_total)[:] = arr
        self.n += arr.size
        self._slot = None

    def result(self) -> np.ndarray:
        self._slot = None
        out = self.buf[:self.n]
        if self.buf.size - self.n > self.buf.size // 8:  # do not keep much unused capacity alive
            out = out.copy()
        self.buf = np.empty(0, self.buf.dtype)
        return out


#: Batched reading: decode once this many buffered events (arrays) / payload bytes (packets).
_BATCH_EVENTS = 1 << 20
_BATCH_BYTES = 2 << 20


class _TopicDecoder:
    """Decodes the messages of one event topic, checking that they form one consistent stream.

    ``packet(msg)`` decodes one message (for iteration); ``add(msg)`` + ``flush()`` decode
    many messages per numpy / codec call (for whole-topic reads).
    """

    def __init__(self, bag: BagReader, topic: str):
        info = bag.topic(topic)
        self.what = f"{bag.path}: topic {topic}"
        if info.msgtype not in EVENT_TYPES:
            raise InputError(f"{self.what} has type {info.msgtype}; event topics must be {EVENT_PACKET} "
                             f"(encodings {list(PACKET_ENCODINGS)}) or {DVS_EVENT_ARRAY}")
        self.bag, self.topic, self.info = bag, topic, info
        self.ros1 = bag.ros1
        self.geometry = None  # (width, height, encoding)
        self.stream = None  # evt3 / evt2 streaming decoder
        self.first_tb = None
        self.count = 0
        self._pending = []  # batched: (layout or fields, raw)
        self._pending_size = 0
        self.sink: _Growing | None = None  # batched array topics decode straight into it
        self.events_seen = 0

    # ----- per message
    def _fields(self, m: BagMessage):
        where = f"{self.what}: message {self.count}"
        if m.msgtype == DVS_EVENT_ARRAY:
            f = em.event_array_layout(m.data, ros1=self.ros1, what=where)
            enc, tb = "array", None
        else:
            f = em.parse_event_packet(m.data, ros1=self.ros1, what=where)
            enc, tb = f.encoding, f.time_base
            if f.is_bigendian:
                raise InputError(f"{where}: big-endian event packets are not supported")
            if enc not in PACKET_ENCODINGS:
                raise InputError(f"{where}: EventPacket encoding {enc!r} is not supported (supported: "
                                 f"{list(PACKET_ENCODINGS)})")
            if enc in STREAM_ENCODINGS:
                if self.first_tb is None:
                    self.first_tb = tb
                elif tb != self.first_tb:
                    raise FormatError(f"time_base changes from {self.first_tb} to {tb}; {enc} packets of one "
                                      "topic are read as one sensor stream with a constant time_base", source=where)
        geometry = (f.width, f.height, enc)
        if self.geometry is None:
            self.geometry = geometry
        elif geometry != self.geometry:
            raise FormatError(f"width/height/encoding change from {self.geometry} to {geometry}; one topic must "
                              "carry one stream", source=where)
        self.count += 1
        return f, enc, where

    def _stream_decoder(self, enc):
        if self.stream is None:
            from ..events.codecs import make_decoder

            self.stream = make_decoder(enc, time_base_ns=self.first_tb, source=self.what)
        return self.stream

    def _mono(self, payload, time_base, where):
        from ..events.codecs import make_decoder

        d = make_decoder("mono", time_base_ns=time_base, source=where)
        e1, t1 = _decoded(d.feed(payload))
        e2, t2 = _decoded(d.close())
        return (e1 if not e2.size else np.concatenate([e1, e2])), (t1 if not t2.size else np.concatenate([t1, t2]))

    def _check_bounds(self, ev, where):
        width, height, _ = self.geometry
        if ev.size and width and height:
            if int(ev["x"].max()) >= width or int(ev["y"].max()) >= height:
                j = int(np.flatnonzero((ev["x"] >= width) | (ev["y"] >= height))[0])
                raise FormatError(f"event at x={int(ev['x'][j])}, y={int(ev['y'][j])} lies outside the "
                                  f"declared {width}x{height} sensor", source=where)

    def packet(self, m: BagMessage) -> EventPacketData:
        index = self.count
        f, enc, where = self._fields(m)
        if enc == "array":
            ev = em.parse_event_array(m.data, ros1=self.ros1, what=where).events
            tr, tb = empty_triggers(), None
        elif enc == "mono":
            ev, tr = self._mono(f.events, f.time_base, where)
            tb = f.time_base
        else:
            ev, tr = _decoded(self._stream_decoder(enc).feed(f.events))
            tb = f.time_base
        self._check_bounds(ev, where)
        return EventPacketData(index, m.t_ns, f.stamp_ns, ev, tr, f.width, f.height, enc, f.seq, tb)

    def close(self):
        """Decode what the streaming decoder still holds; check the message count against the index."""
        if self.count != self.info.message_count:
            raise FormatError(f"topic {self.topic}: the index lists {self.info.message_count} messages but "
                              f"{self.count} could be read; the bag is damaged or truncated",
                              source=str(self.bag.path))
        if self.stream is None:
            return empty_events(), empty_triggers()
        ev, tr = _decoded(self.stream.close())
        self._check_bounds(ev, self.what)
        return ev, tr

    # ----- batched
    def add(self, m: BagMessage):
        """Buffer one message; returns decoded (events, triggers) when a batch is full, else None."""
        f, enc, where = self._fields(m)
        if enc == "mono":
            ev, tr = self._mono(f.events, f.time_base, where)
            self._check_bounds(ev, where)
            return ev, tr
        self._pending.append(f)
        self._pending_size += f.count if enc == "array" else len(f.events)
        if self._pending_size >= (_BATCH_EVENTS if enc == "array" else _BATCH_BYTES):
            return self.flush()
        return None

    def flush(self):
        pending, self._pending, self._pending_size = self._pending, [], 0
        if not pending:
            return empty_events(), empty_triggers()
        enc = self.geometry[2]
        if enc == "array":
            ev = self._flush_arrays(pending)
            tr = empty_triggers()
        else:
            data = pending[0].events if len(pending) == 1 else b"".join(f.events for f in pending)
            ev, tr = _decoded(self._stream_decoder(enc).feed(data))
        self._check_bounds(ev, self.what)
        return ev, tr

    def _flush_arrays(self, pending):
        counts = np.fromiter((f.count for f in pending), np.int64, len(pending))
        starts = np.concatenate([[0], np.cumsum(counts)])
        total = int(starts[-1])
        out = None
        if self.sink is not None:  # estimate the topic's total from the messages seen so far
            self.events_seen += total
            hint = self.events_seen * self.info.message_count // max(self.count, 1)
            out = self.sink.reserve(total, hint_total=hint + hint // 64 + 1024)
        if self.ros1:
            buf = np.empty(13 * total, np.uint8)
            for f, a in zip(pending, starts.tolist()):
                if f.count:
                    buf[13 * a:13 * (a + f.count)] = np.frombuffer(f.raw, np.uint8, 13 * f.count, f.offset)
            rec = buf.view(em.ROS1_EVENT_DTYPE)
        else:
            buf = np.zeros(16 * total, np.uint8)
            for f, a in zip(pending, starts.tolist()):
                em.place_cdr_events(buf, a, f.raw, f.offset, f.count)
            em.fix_first_cdr_events(buf, starts[:-1][counts > 0])
            rec = buf.view(em.CDR_EVENT_DTYPE)
        return em.records_to_events(rec, what=self.what, out=out)


def _iter_event_packets(bag: BagReader, topic: str) -> Iterator[EventPacketData]:
    dec = _TopicDecoder(bag, topic)
    held = None
    for m in bag.messages(topic):
        item = dec.packet(m)
        if held is not None:
            yield held
        held = item
    ev, tr = dec.close()
    if held is not None:
        if ev.size:
            held.events = np.concatenate([held.events, ev])
        if tr.size:
            held.triggers = np.concatenate([held.triggers, tr])
        yield held


def _topic_batches(bag: BagReader, topic: str, dec: _TopicDecoder):
    """Whole-topic batched decode: yields (events, triggers) per batch of messages."""
    for m in bag.messages(topic):
        out = dec.add(m)
        if out is not None:
            yield out
    yield dec.flush()
    yield dec.close()


def iter_event_packets(path, topic: str = DEFAULT_EVENT_TOPIC) -> Iterator[EventPacketData]:
    """Decode an event topic message by message (bounded memory for big bags). Events that the
    streaming decoder releases only at the end of the topic are added to the last packet."""
    with open_bag(path) as bag:
        yield from _iter_event_packets(bag, topic)


def read_events(path, topic: str = DEFAULT_EVENT_TOPIC, *, sort: bool = False) -> EventStream:
    """All events (and triggers) of an event topic as EVENT_DTYPE / TRIGGER_DTYPE arrays.

    Events must come out sorted by time; otherwise FormatError, unless ``sort=True``
    (stable sort by t).
    """
    ev_acc = _Growing(EVENT_DTYPE, f"{path}: topic {topic}")
    tr_acc = _Growing(TRIGGER_DTYPE, f"{path}: topic {topic}: triggers")
    with open_bag(path) as bag:
        dec = _TopicDecoder(bag, topic)
        dec.sink = ev_acc
        for ev, tr in _topic_batches(bag, topic, dec):
            # size the result from the events per message so far (one allocation for steady streams)
            hint = (ev_acc.n + ev.size) * dec.info.message_count // max(dec.count, 1)
            ev_acc.append(ev, hint_total=hint + hint // 64 + 1024)
            tr_acc.append(tr)
        del ev, tr
    events, triggers = ev_acc.result(), tr_acc.result()
    what = f"topic {topic}"
    for name, arr in (("events", events), ("triggers", triggers)):
        t = arr["t"]
        back = np.flatnonzero(t[1:] < t[:-1])
        if back.size:
            if not sort:
                j = int(back[0]) + 1
                raise FormatError(f"{what}: {name} go back in time at index {j} (t={int(t[j])} ns after "
                                  f"{int(t[j - 1])} ns); pass sort=True to sort them by time", source=str(path))
            if name == "events":
                events = events[np.argsort(t, kind="stable")]
            else:
                triggers = triggers[np.argsort(t, kind="stable")]
    width, height, encoding = dec.geometry or (0, 0, "")
    return EventStream(events, triggers, width, height, encoding, dec.count, topic, dec.info.msgtype or "",
                       str(path))


# =========================================================================== bag_info


@dataclass
class EventTopicInfo:
    event_count: int
    trigger_count: int
    width: int
    height: int
    encoding: str
    first_ns: int | None
    last_ns: int | None
    rate_ev_per_s: float  # display only (from int64 differences)


@dataclass
class TopicInfo:
    name: str
    msgtype: str | None
    message_count: int
    events: EventTopicInfo | None = None


@dataclass
class BagInfo:
    path: str
    storage: str  # "mcap" | "sqlite3" | "rosbag1"
    layout: str  # "rosbag2" (directory) | "file"
    message_count: int
    start_ns: int | None
    end_ns: int | None
    duration_ns: int
    topics: dict[str, TopicInfo] = field(default_factory=dict)


def bag_info(path, *, decode_events: bool = True) -> BagInfo:
    """Topics (type, message count), time span and storage; for event topics also the event
    count, rate and resolution, computed by decoding them (``decode_events=False`` skips that)."""
    with open_bag(path) as bag:
        topics = {}
        for name, t in bag.topics.items():
            ti = TopicInfo(name, t.msgtype, t.message_count)
            if decode_events and t.msgtype in EVENT_TYPES:
                dec = _TopicDecoder(bag, name)
                n = ntr = 0
                first = last = None
                for ev, tr in _topic_batches(bag, name, dec):  # bounded memory: one batch at a time
                    ntr += tr.size
                    if ev.size:
                        n += ev.size
                        lo, hi = int(ev["t"].min()), int(ev["t"].max())
                        first = lo if first is None else min(first, lo)
                        last = hi if last is None else max(last, hi)
                w, h, enc = dec.geometry or (0, 0, "")
                span = (last - first) if n > 1 else 0
                rate = n * 1e9 / span if span > 0 else 0.0
                ti.events = EventTopicInfo(n, ntr, w, h, enc, first, last, rate)
            topics[name] = ti
        start, end = bag.start_ns, bag.end_ns
        return BagInfo(str(path), bag.storage, bag.layout, bag.message_count, start, end,
                       (end - start) if start is not None else 0, topics)
