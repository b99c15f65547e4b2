"""Reading any bag (rosbag2 directory, bare .mcap / .db3 file, ROS 1 .bag) and decoding its event
topics with numpy, without per-event Python.

Opening
-------
:func:`open_bag` detects a rosbag2 directory (metadata.yaml + .mcap/.db3 files), a bare ``.mcap``
or ``.db3`` file, or a ROS 1 ``.bag`` file from its magic bytes. A metadata.yaml whose
``storage_identifier`` is empty (ros2 bag writes that for some plugins; its ``files`` list may be
empty too) gets the storage inferred from its files, as ROS 2's reader does: by the files'
suffixes (``.mcap`` / ``.db3``), else by their magic bytes. Damaged files raise FormatError
naming the file.

Event topics
------------
:func:`read_events` / :func:`iter_event_packets` decode ``event_camera_msgs/msg/EventPacket``
(encodings evt3, evt2, mono, libcaer, libcaer_cmp) and ``dvs_msgs/msg/EventArray`` (ROS 2 CDR and
ROS 1). :func:`pick_event_topic` finds the only event topic of a bag. :func:`bag_info` summarises
a bag.

How EventPacket times are read (``t`` in ns):

- ``evt3`` / ``evt2``: the packets of a topic are one sensor stream (one streaming decoder).
  * ``time_base == 0`` (metavision_driver's convention, and what our writer writes): the
    payload carries sensor time and ``header.stamp`` is the host time of the packet's first
    event. Times are put on the host clock: ``t = offset + 1000 * sensor_us`` with
    ``offset = stamp - 1000 * sensor_us(first event)`` of the first message that holds an event
    (or trigger); later stamps are not used (the sensor clock is the steady one). For bags our
    writer wrote this gives back the written times exactly; for a real camera's bag it puts
    the stream at the host time of its first packet, as event_camera_codecs-based tools do.
  * ``time_base != 0`` (our writer's earlier convention): ``t = time_base + 1000 * sensor_us``,
    and ``time_base`` must be constant over the topic.
  :attr:`EventStream.time_offset_ns` says which offset was added (``(t - offset) / 1000`` are
  the payload's sensor microseconds).
- ``mono``: ``t = time_base + dt`` per packet.
- ``libcaer``: ``t = time_base + 1000 * timestamp`` per packet, plus 2**31 us at each rollover of
  the 31-bit timestamp inside the packet (libcaer_driver puts the sensor time's high bits into
  ``time_base``).
- ``libcaer_cmp``: ``t = time_base + 1000 * offset_us`` per packet; events outside the packet's
  width x height are dropped, as event_camera_codecs drops them.
See :mod:`evdnerf_ros.events.codecs.libcaer` for the libcaer layouts.
"""

from __future__ import annotations

import os
import sqlite3
import struct
import warnings
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import FormatError, InputError
from ..events.types import EVENT_DTYPE, TRIGGER_DTYPE, empty_events, empty_triggers
from ..limits import check_memory, memory_budget
from . import event_messages as em
from .packetizer import (CAER_ENCODINGS, DEFAULT_EVENT_TOPIC, EVENT_TYPES, PACKET_ENCODINGS, STREAM_ENCODINGS,
                         WORD_BYTES)
from .typestore import DVS_EVENT_ARRAY, EVENT_PACKET, ros1_typestore, ros2_typestore

STORAGES = ("mcap", "sqlite3")

MCAP_MAGIC = b"\x89MCAP0\r\n"
SQLITE_MAGIC = b"SQLite format 3\x00"
ROS1_MAGIC = b"#ROSBAG V2.0\n"


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


def _magic_storage(path: Path) -> str | None:
    try:
        with open(path, "rb") as f:
            head = f.read(16)
    except OSError:
        return None
    for magic, storage in ((MCAP_MAGIC, "mcap"), (SQLITE_MAGIC, "sqlite3"), (ROS1_MAGIC, "rosbag1")):
        if head.startswith(magic):
            return storage
    return None


def infer_storage(path: Path, files) -> str:
    """The storage of a rosbag2 directory whose metadata names none, from its files (as ROS 2's
    reader does): the suffixes of ``relative_file_paths`` (or of the files in the directory),
    else their magic bytes."""
    names = [Path(str(f)).name for f in (files or [])]
    if not names:
        names = sorted(p.name for p in path.iterdir() if p.suffix in (".mcap", ".db3"))
    found = set()
    for name in names:
        suffix = Path(name).suffix
        storage = {".mcap": "mcap", ".db3": "sqlite3"}.get(suffix) or _magic_storage(path / name)
        found.add(storage)
    found.discard(None)
    if len(found) != 1 or "rosbag1" in found:
        what = f"its files {names} are of kinds {sorted(found)}" if found else f"it lists the files {names}"
        raise FormatError(f"metadata.yaml names no storage_identifier and {what}; expected .mcap or .db3 files of "
                          "one kind (set storage_identifier: mcap or sqlite3)", source=str(path / "metadata.yaml"))
    return found.pop()


def _detect(path: Path) -> tuple[str, str, bool]:
    """(layout, storage, inferred): ("rosbag2", "mcap"|"sqlite3", inferred) for a directory,
    ("file", ..., False) for a bare file. ``inferred``: metadata.yaml named no storage."""
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
            storage = info.get("storage_identifier")
            storage = "" if storage is None else str(storage)
            files = info.get("relative_file_paths") or []
        except Exception as exc:  # noqa: BLE001
            raise FormatError(f"metadata.yaml is unreadable ({exc}); the bag directory is damaged",
                              source=str(meta)) from None
        if not storage:
            return "rosbag2", infer_storage(path, files), True
        if storage not in STORAGES:
            raise InputError(f"{path}: storage {storage!r} is not supported (only {list(STORAGES)})")
        return "rosbag2", storage, False
    with open(path, "rb") as f:
        head = f.read(16)
    for magic, storage, suffix in ((MCAP_MAGIC, "mcap", ".mcap"), (SQLITE_MAGIC, "sqlite3", ".db3"),
                                   (ROS1_MAGIC, "rosbag1", ".bag")):
        if head.startswith(magic):
            if storage != "rosbag1" and path.suffix != suffix:
                raise InputError(f"{path}: this is a bare {storage} bag file but its name does not end in "
                                 f"{suffix}; the reader picks the storage from the suffix, rename it")
            return "file", storage, False
    if not head:
        raise FormatError("file is empty", source=str(path))
    raise InputError(f"{path}: not a bag (no MCAP, SQLite or ROS 1 bag magic at the start); expected a rosbag2 "
                     "directory, a .mcap, a .db3 or a ROS 1 .bag")


def _inferred_reader(path: Path, storage: str):
    """rosbags' rosbag2 reader for a directory whose metadata names no storage (rosbags refuses
    an empty storage_identifier): its directory reader, told which plugin "" stands for."""
    from rosbags.rosbag2 import Reader
    from rosbags.rosbag2.reader import DirectoryReader

    class _Inferred(DirectoryReader):
        STORAGE_PLUGINS = {**DirectoryReader.STORAGE_PLUGINS, "": DirectoryReader.STORAGE_PLUGINS[storage]}

    reader = Reader(path)
    reader.storage = _Inferred(path)
    return reader


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
        self.layout, self.storage, self.storage_inferred = _detect(self.path)
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
            reader = _inferred_reader(self.path, self.storage) if self.storage_inferred else Reader(self.path)
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
    frame_id: str = ""
    header_seq: int = 0  # ROS 1 header.seq (0 in ROS 2, whose Header has none)


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
    #: evt3 / evt2: ns added to the payload's sensor times (module doc); None for other encodings
    time_offset_ns: int | None = None
    #: libcaer_cmp: events outside the packets' width x height, dropped as event_camera_codecs drops them
    dropped_out_of_geometry: int = 0


def decoded_parts(dec):
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


class TopicDecoder:
    """Decodes the messages of one event topic, checking that they form one consistent stream.

    ``packet(msg)`` decodes one message (for iteration); ``add(msg)`` + ``flush()`` decode
    many messages per numpy / codec call (for whole-topic reads). Times: see the module doc.
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
        self.caer = None  # libcaer / libcaer_cmp decoder (per-packet time base, carried state)
        self.first_tb = None
        self.time_offset_ns = None  # what was added to the sensor times (evt3 / evt2)
        self._probe = None  # time_base 0: a decoder finding the first event's sensor time
        self._held = []  # time_base 0: payloads fed to the probe before an event showed up
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
            if len(f.events) % WORD_BYTES[enc]:
                raise FormatError(f"{enc} payload of {len(f.events)} bytes is not a whole number of "
                                  f"{WORD_BYTES[enc]}-byte words; the message is damaged", source=where)
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
            self.time_offset_ns = self.first_tb
        return self.stream

    def _stream_feed_tb0(self, enc, payload, stamp_ns):
        """time_base 0 (module doc): decode with a probe until the first event (or trigger) gives
        the offset, then decode everything so far with a decoder that adds it."""
        from ..events.codecs import DroppedEventsWarning, make_decoder

        if self.stream is not None:
            return decoded_parts(self.stream.feed(payload))
        if self._probe is None:
            self._probe = make_decoder(enc, time_base_ns=0, source=self.what)
        self._held.append(payload)
        with warnings.catch_warnings():  # the real decoder warns about the same words below
            warnings.simplefilter("ignore", DroppedEventsWarning)
            ev, tr = decoded_parts(self._probe.feed(payload))
        if not ev.size and not tr.size:
            return ev, tr
        first = min(int(a["t"][0]) for a in (ev, tr) if a.size)
        self.time_offset_ns = int(stamp_ns) - first
        self.stream = make_decoder(enc, time_base_ns=self.time_offset_ns, source=self.what)
        held, self._held, self._probe = self._held, [], None
        for h in held[:-1]:
            self.stream.feed(h)  # no events in these (the probe saw none): only decoder state
        return decoded_parts(self.stream.feed(held[-1]))

    def _stream_feed(self, enc, payload, stamp_ns):
        if self.first_tb == 0:
            return self._stream_feed_tb0(enc, payload, stamp_ns)
        return decoded_parts(self._stream_decoder(enc).feed(payload))

    def _caer(self, f, enc, where):
        from ..events.codecs.libcaer import LibcaerCmpDecoder, LibcaerDecoder

        if self.caer is None:
            self.caer = (LibcaerDecoder(source=self.what) if enc == "libcaer"
                         else LibcaerCmpDecoder(source=self.what))
        if enc == "libcaer":
            self.caer.next_packet(f.time_base)
        else:
            self.caer.next_packet(f.time_base, f.width, f.height)
        self.caer.source = where
        return self.caer.feed(f.events).events, empty_triggers()

    def _mono(self, payload, time_base, where):
        from ..events.codecs import make_decoder

        d = make_decoder("mono", time_base_ns=time_base, source=where)
        e1, t1 = decoded_parts(d.feed(payload))
        e2, t2 = decoded_parts(d.close())
        return (e1 if not e2.size else np.concatenate([e1, e2])), (t1 if not t2.size else np.concatenate([t1, t2]))

    def _check_bounds(self, ev, where):
        width, height, _ = self.geometry
        if ev.size and width and height:
            if int(ev["x"].max()) >= width or int(ev["y"].max()) >= height:
                j = int(np.flatnonzero((ev["x"] >= width) | (ev["y"] >= height))[0])
                raise FormatError(f"event at x={int(ev['x'][j])}, y={int(ev['y'][j])} lies outside the "
                                  f"declared {width}x{height} sensor", source=where)

    @property
    def dropped_out_of_geometry(self) -> int:
        return int(getattr(self.caer, "dropped_out_of_geometry", 0))

    def packet(self, m: BagMessage) -> EventPacketData:
        index = self.count
        f, enc, where = self._fields(m)
        if enc == "array":
            ev = em.parse_event_array(m.data, ros1=self.ros1, what=where).events
            tr, tb = empty_triggers(), None
        elif enc == "mono":
            ev, tr = self._mono(f.events, f.time_base, where)
            tb = f.time_base
        elif enc in CAER_ENCODINGS:
            ev, tr = self._caer(f, enc, where)
            tb = f.time_base
        else:
            ev, tr = self._stream_feed(enc, f.events, f.stamp_ns)
            tb = f.time_base
        self._check_bounds(ev, where)
        return EventPacketData(index, m.t_ns, f.stamp_ns, ev, tr, f.width, f.height, enc, f.seq, tb, f.frame_id,
                               f.header_seq if enc != "array" else f.seq)

    def close(self):
        """Decode what the streaming decoder still holds; check the message count against the index."""
        if self.count != self.info.message_count:
            raise FormatError(f"topic {self.topic}: the index lists {self.info.message_count} messages but "
                              f"{self.count} could be read; the bag is damaged or truncated",
                              source=str(self.bag.path))
        if self.stream is None:
            return empty_events(), empty_triggers()
        ev, tr = decoded_parts(self.stream.close())
        self._check_bounds(ev, self.what)
        return ev, tr

    # ----- batched
    def add(self, m: BagMessage):
        """Buffer one message; returns decoded (events, triggers) when a batch is full, else None."""
        f, enc, where = self._fields(m)
        if enc == "mono" or enc in CAER_ENCODINGS:
            ev, tr = self._mono(f.events, f.time_base, where) if enc == "mono" else self._caer(f, enc, where)
            self._check_bounds(ev, where)
            return ev, tr
        if enc in STREAM_ENCODINGS and self.first_tb == 0 and self.stream is None:
            ev, tr = self._stream_feed_tb0(enc, f.events, f.stamp_ns)  # one by one until the offset is known
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
            ev, tr = self._stream_feed(enc, data, pending[0].stamp_ns)
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
    dec = TopicDecoder(bag, topic)
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


def _topic_batches(bag: BagReader, topic: str, dec: TopicDecoder):
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
        dec = TopicDecoder(bag, topic)
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
                       str(path), dec.time_offset_ns, dec.dropped_out_of_geometry)


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
                dec = TopicDecoder(bag, name)
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


def event_topics(bag_or_path) -> dict[str, str]:
    """{topic: message type} of the event topics (EventPacket, dvs_msgs EventArray) of a bag."""
    if isinstance(bag_or_path, BagReader):
        topics = bag_or_path.topics
    else:
        with open_bag(bag_or_path) as bag:
            topics = bag.topics
    return {name: t.msgtype for name, t in topics.items() if t.msgtype in EVENT_TYPES}


def pick_event_topic(bag_or_path, topic: str | None = None) -> str:
    """``topic`` if given, else the bag's only event topic; InputError listing the event topics
    when there are none or several (then name one, e.g. with ``--topic``)."""
    if topic is not None:
        return topic
    found = event_topics(bag_or_path)
    if len(found) == 1:
        return next(iter(found))
    path = bag_or_path.path if isinstance(bag_or_path, BagReader) else bag_or_path
    if not found:
        raise InputError(f"{path}: the bag has no event topic ({EVENT_PACKET} or {DVS_EVENT_ARRAY})")
    listing = ", ".join(f"{n} [{t}]" for n, t in found.items())
    raise InputError(f"{path}: the bag has {len(found)} event topics ({listing}); choose one with --topic")
