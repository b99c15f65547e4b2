"""Events, or a sensor's raw bytes passed through untouched, into event messages for a sink.

A :class:`Packetizer` serialises ``event_camera_msgs/msg/EventPacket`` or
``dvs_msgs/msg/EventArray`` messages (ROS 2 CDR, or the ROS 1 wire format with ``ros1=True``)
and hands each one to its *sink*: ``sink(topic, msgtype, data, t_ns)`` with ``data`` the
serialised bytes and ``t_ns`` the bag / publish time (= ``header.stamp`` unless told
otherwise). Bag writers (:class:`evdnerf_ros.io.bag_writer.EventBagWriter`), the DDS publisher
node and the capture node each own one.

Three ways in:

- :meth:`Packetizer.write_events`: events (EVENT_DTYPE, sorted) cut into packets as
  metavision_driver does: a packet opens at its first event and closes before the first event
  ``packet_ns`` later (default 1 ms), or after ``max_packet_events`` events. Each call packs its
  own events completely; calls on one topic continue one stream (times must not go back; encoder
  state and ``seq`` carry over).
- :meth:`Packetizer.write_packet`: one message from given events with a given stamp / seq /
  frame_id (re-encoding a recorded message keeps them).
- :meth:`Packetizer.write_raw_packet`: a sensor's bytes (EVT 3.0 from a Prophesee camera,
  libcaer records, ...) wrapped in an EventPacket byte for byte, with the stamp and time_base
  the caller gives (a camera driver's host time; ``time_base = 0`` for evt3).

Times (int64 ns ``t``) per encoding, and how the reader gets them back exactly
---------------------------------------------------------------------------------
- ``evt3`` / ``evt2`` (metavision_driver's convention): ``time_base = 0``, the payload carries
  sensor time, ``header.stamp`` = the time of the packet's first event (or of its first trigger
  when a trigger precedes it). The sensor clock's zero is the topic's *origin* ``O`` =
  :func:`stream_origin` of the topic's first time: 0 if that time lies in the first 2**24 us
  (sensor-like times stay as they are), else that time rounded down to a multiple of 4096 us,
  plus the first time's sub-microsecond rest (0 for times on the whole-µs grid). So
  ``sensor_us = (t - O) / 1000`` (a whole number: the times must be whole microseconds from
  ``O``, else InputError) and the stream's first sensor time is below 4096 us whatever the date.
  A reader recovers ``O = stamp - 1000 * sensor_us`` from the first packet's stamp and its
  first event (exact, since that stamp is that event's time) and gets
  ``t = O + 1000 * sensor_us`` back exactly; event_camera_codecs-based tools, which ignore
  ``time_base`` for evt3, see the same sensor times and stamps as from a camera. Only when the
  first packet is given a stamp other than its first time (:meth:`write_packet` keeping a
  recorded stamp) does the stamp not carry ``O``; then ``time_base = O`` (our earlier
  convention: ``t = time_base + 1000 * sensor_us``, which the reader also reads), with ``O``
  made non-zero for that. External triggers are carried in-stream (only these encodings carry
  triggers).
- ``mono``: ``time_base`` = the packet's first event time, 32-bit ns offsets (packet_ns <= 2**32).
- ``libcaer`` (libcaer_driver's convention): the same origin ``O`` as evt3; per packet
  ``time_base = O + 1000 * (sensor_us of its first event with the low 31 bits cleared)`` and
  each event's 31-bit timestamp = ``sensor_us mod 2**31`` (rollovers inside a packet are
  counted by the decoder).
- ``libcaer_cmp``: ``time_base`` = the packet's first event time; 24-bit microsecond offsets
  from it (packet_ns < 2**24 us).
- ``array``: ``dvs_msgs/msg/EventArray``, one ``builtin_interfaces/Time`` per event (ns exact),
  built with numpy in the exact CDR / ROS 1 layout (:mod:`evdnerf_ros.io.event_messages`).

All times must be >= 0 (bag timestamps and ``time_base`` are unsigned).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..errors import EvdnerfError, InputError
from ..topics import EVENTS
from ..events.types import MAX_SENSOR_SIZE, as_events, empty_triggers, validate_events
from . import event_messages as em
from .typestore import DVS_EVENT_ARRAY, EVENT_PACKET, LEGACY_EVENT_PACKET

PACKET_ENCODINGS = ("evt3", "evt2", "mono", "libcaer", "libcaer_cmp")
WRITE_ENCODINGS = PACKET_ENCODINGS + ("array",)
STREAM_ENCODINGS = ("evt3", "evt2")
CAER_ENCODINGS = ("libcaer", "libcaer_cmp")
#: bytes per word of each EventPacket encoding (a payload is a whole number of words)
WORD_BYTES = {"evt3": 2, "evt2": 4, "mono": 8, "libcaer": 8, "libcaer_cmp": 2}
DEFAULT_EVENT_TOPIC = EVENTS
DEFAULT_PACKET_NS = 1_000_000
#: the event message types read (EventPacket also under its pre-2023 name); written: the first two
EVENT_TYPES = (EVENT_PACKET, DVS_EVENT_ARRAY, LEGACY_EVENT_PACKET)

#: sink(topic, msgtype, serialised message bytes, t_ns)
Sink = Callable[[str, str, bytes, int], Any]

_LIBCAER_LOW = (1 << 31) - 1


def positive_int(value, what, *, upper=2**32 - 1):
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)) \
            or not 0 < int(value) <= upper:
        raise InputError(f"{what}: expected an integer in [1, {upper}], got {value!r}")
    return int(value)


def check_topic(topic):
    if not isinstance(topic, str) or not topic.startswith("/") or len(topic) < 2 or any(c.isspace() for c in topic):
        raise InputError(f"topic {topic!r}: expected an absolute ROS topic name such as '/event_camera/events'")
    return topic


def check_time(t_ns, what):
    if isinstance(t_ns, (bool, np.bool_)) or not isinstance(t_ns, (int, np.integer)):
        raise InputError(f"{what}: timestamps are int64 nanoseconds, got {type(t_ns).__name__} {t_ns!r}")
    t_ns = int(t_ns)
    if not 0 <= t_ns < 2**63:
        raise InputError(f"{what}: bag timestamp {t_ns} ns is negative or beyond int64; bag times are "
                         "unsigned, shift the time origin")
    return t_ns


@dataclass
class TopicState:
    """What a packetizer keeps per event topic."""

    topic: str
    msgtype: str
    encoding: str
    width: int
    height: int
    frame_id: str
    raw: bool = False                 # written by write_raw_packet (bytes passed through)
    seq: int = 0
    origin: int | None = None         # evt3 / evt2 / libcaer: ns of sensor time 0
    time_base: int | None = None      # evt3 / evt2: the time_base field (0, or origin; module doc)
    encoder: Any = None
    last_t: int | None = None
    prefix: Any = None
    messages: int = 0


def stream_origin(first_t: int) -> int:
    """The ns time of sensor time 0 for a topic whose first time is ``first_t`` (module doc):
    sensor_origin_ns of it (0, or a multiple of 4096 us) plus first_t's sub-microsecond rest,
    so that times on first_t's microsecond grid are whole sensor microseconds."""
    from ..events.codecs._common import sensor_origin_ns

    rest = int(first_t) % 1000
    return sensor_origin_ns(int(first_t) - rest) + rest


def _marked_origin(first_t: int, what: str) -> int:
    """A non-zero origin <= first_t on its microsecond grid (time_base must say it; module doc)."""
    origin = stream_origin(first_t)
    if origin == 0:
        origin = first_t % 1000 or (1000 if first_t >= 1000 else 0)
    if origin == 0:
        raise InputError(f"{what}: the first packet keeps a stamp other than its first time, so time_base must "
                         "carry the time origin, but its first time is 0; write it with its own stamp")
    return origin


class Packetizer:
    """Serialises event topics into messages for ``sink`` (module doc). ``ros1``: ROS 1 wire
    format instead of CDR; ``name`` names the destination in error messages."""

    def __init__(self, sink: Sink, *, ros1: bool = False, name: str = "<live>"):
        if not callable(sink):
            raise InputError(f"{name}: the packetizer's sink must be callable as sink(topic, msgtype, data, t_ns)")
        self.sink = sink
        self.ros1 = bool(ros1)
        self.name = str(name)
        self.topics: dict[str, TopicState] = {}
        #: set when a write failed after some of its messages went to the sink
        self.failed: str | None = None

    def is_event_topic(self, topic: str) -> bool:
        return topic in self.topics

    # ----- validation shared by every way in
    def _state(self, topic, encoding, width, height, frame_id, *, raw, encodings=WRITE_ENCODINGS):
        what = f"{self.name}: topic {topic}"
        check_topic(topic)
        if encoding not in encodings:
            raise InputError(f"{what}: encoding {encoding!r} is not one of {list(encodings)}")
        width = positive_int(width, f"{what}: width")
        height = positive_int(height, f"{what}: height")
        if not isinstance(frame_id, str):
            raise InputError(f"{what}: frame_id must be a string")
        state = self.topics.get(topic)
        if state is None:
            msgtype = DVS_EVENT_ARRAY if encoding == "array" else EVENT_PACKET
            return TopicState(topic, msgtype, encoding, width, height, frame_id, raw=raw), what
        if (state.encoding, state.width, state.height, state.frame_id) != (encoding, width, height, frame_id):
            raise InputError(
                f"{what}: earlier calls wrote encoding={state.encoding!r}, {state.width}x{state.height}, "
                f"frame_id={state.frame_id!r}; got encoding={encoding!r}, {width}x{height}, "
                f"frame_id={frame_id!r}; one topic carries one stream")
        if state.raw != raw:
            raise InputError(f"{what}: earlier calls wrote {'raw sensor bytes' if state.raw else 'events'} to this "
                             "topic; one topic carries either passed-through bytes or packetised events")
        return state, what

    def _check_events(self, state, what, events, triggers, packet_ns=None):
        enc, width, height = state.encoding, state.width, state.height
        if enc in STREAM_ENCODINGS and (width > MAX_SENSOR_SIZE or height > MAX_SENSOR_SIZE):
            raise InputError(f"{what}: {enc} carries at most {MAX_SENSOR_SIZE}x{MAX_SENSOR_SIZE} pixels, "
                             f"got {width}x{height}; use encoding 'mono' or 'array'")
        limits = {"mono": (1 << 16, 1 << 15), "libcaer": (1 << 15, 1 << 15), "libcaer_cmp": (1 << 11, 1 << 11)}
        if enc in limits and (width > limits[enc][0] or height > limits[enc][1]):
            raise InputError(f"{what}: {enc} carries x < {limits[enc][0]} and y < {limits[enc][1]}, got "
                             f"{width}x{height}; use encoding 'array'")
        if packet_ns is not None:
            if enc == "mono" and packet_ns > 2**32:
                raise InputError(f"{what}: mono stores 32-bit ns offsets, so packet_ns must be <= 2**32 "
                                 f"(got {packet_ns})")
            if enc == "libcaer_cmp" and packet_ns > (1 << 24) * 1000:
                raise InputError(f"{what}: libcaer_cmp stores 24-bit us offsets, so packet_ns must be <= "
                                 f"{(1 << 24) * 1000} (got {packet_ns})")
        events = validate_events(as_events(events, source=what), width=width, height=height, source=what)
        if triggers is not None and len(triggers):
            if enc not in STREAM_ENCODINGS:
                raise InputError(f"{what}: triggers are only carried by encoding 'evt3' (or 'evt2'), not "
                                 f"{enc!r}; write the events with encoding='evt3'")
            triggers = em.check_triggers(triggers, what=what)
        else:
            triggers = empty_triggers()
        if events.size == 0 and triggers.size == 0:
            return events, triggers, None, None
        first_t = min(int(a["t"][0]) for a in (events, triggers) if a.size)
        last_t = max(int(a["t"][-1]) for a in (events, triggers) if a.size)
        if first_t < 0:
            raise InputError(f"{what}: time {first_t} ns is negative; bag timestamps and time_base are "
                             "unsigned, shift the time origin")
        if last_t >= 2**63:
            raise InputError(f"{what}: time {last_t} ns beyond int64")
        if state.last_t is not None and first_t < state.last_t:
            raise InputError(f"{what}: this call starts at t={first_t} ns, before the end of the previous "
                             f"call (t={state.last_t} ns); successive calls must continue in time")
        return events, triggers, first_t, last_t

    def _check_grid(self, state, what, events, triggers, origin=None):
        origin = state.origin if origin is None else origin
        for name, arr in (("event", events), ("trigger", triggers)):
            off = (arr["t"] - origin) % 1000
            if np.any(off):
                i = int(np.flatnonzero(off)[0])
                raise InputError(
                    f"{what}: {name} {i} at t={int(arr['t'][i])} ns is not a whole microsecond after the "
                    f"topic's time origin {origin} ns; {state.encoding} carries µs. Use encoding='mono' or "
                    "'array' for ns resolution, or round explicitly first with evdnerf_ros.events.codecs."
                    f"quantize_to_us(events, time_base_ns={origin})")

    def _start(self, state, first_t, what, *, stamp_is_first=True):
        """First items of a topic: fix its origin and time_base field (module doc)."""
        from ..events.codecs import make_encoder

        if state.encoding in STREAM_ENCODINGS + ("libcaer",) and state.origin is None:
            if stamp_is_first or state.encoding == "libcaer":
                state.origin = stream_origin(first_t)
                state.time_base = 0
            else:
                state.origin = state.time_base = _marked_origin(first_t, what)
            if state.encoding in STREAM_ENCODINGS:
                state.encoder = make_encoder(state.encoding, time_base_ns=state.origin)
        if state.prefix is None:
            if state.encoding == "array":
                cls = em.Ros1EventArrayPrefix if self.ros1 else em.CdrEventArrayPrefix
                state.prefix = cls(state.frame_id, state.height, state.width)
            else:
                cls = em.Ros1EventPacketPrefix if self.ros1 else em.CdrEventPacketPrefix
                state.prefix = cls(state.frame_id, state.height, state.width, state.encoding)

    def _emit(self, state, data, t_ns):
        self.sink(state.topic, state.msgtype, data, t_ns)
        state.messages += 1

    def _emit_one(self, state, data, t_ns):
        try:
            self._emit(state, data, t_ns)
        except BaseException as exc:
            if not isinstance(exc, EvdnerfError):
                self.failed = f"writing a message on {state.topic}: {exc}"
            raise

    # ----- events, packetised
    def write_events(self, topic: str, events, *, width: int, height: int, encoding: str = "evt3",
                     triggers=None, packet_ns: int = DEFAULT_PACKET_NS, max_packet_events: int | None = None,
                     frame_id: str = "event_camera") -> int:
        """Append events to an event topic (module doc); returns the number of messages sent."""
        state, what = self._state(topic, encoding, width, height, frame_id, raw=False)
        packet_ns = positive_int(packet_ns, f"{what}: packet_ns", upper=2**62)
        if max_packet_events is not None:
            max_packet_events = positive_int(max_packet_events, f"{what}: max_packet_events")
        events, triggers, first_t, last_t = self._check_events(state, what, events, triggers, packet_ns)
        if first_t is None:
            return 0
        if encoding in STREAM_ENCODINGS + ("libcaer",):
            origin = state.origin if state.origin is not None else stream_origin(first_t)
            self._check_grid(state, what, events, triggers, origin)

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

        self._start(state, first_t, what)
        self.topics[topic] = state
        before = state.messages
        try:
            if encoding == "array":
                n = self._array_packets(state, events, bounds, stamps.tolist())
            else:
                n = self._event_packets(state, events, triggers, bounds, tbounds, stamps.tolist())
        except BaseException as exc:
            if state.messages > before or not isinstance(exc, EvdnerfError):
                self.failed = f"write_events on {topic}: {exc}"
            raise
        state.last_t = last_t
        return n

    def _payload(self, state, ev, tr, stamp, what):
        """(time_base field, payload bytes) of one EventPacket."""
        from ..events.codecs import make_encoder

        enc = state.encoding
        try:
            if enc == "mono":
                tb = int(ev["t"][0]) if ev.size else stamp
                return tb, make_encoder("mono", time_base_ns=tb).encode(ev)
            if enc == "libcaer_cmp":
                tb = int(ev["t"][0]) if ev.size else stamp
                return tb, make_encoder("libcaer_cmp", time_base_ns=tb).encode(ev)
            if enc == "libcaer":
                if not ev.size:
                    return state.origin, b""
                high = ((int(ev["t"][0]) - state.origin) // 1000) & ~_LIBCAER_LOW
                tb = state.origin + 1000 * high
                return tb, make_encoder("libcaer", time_base_ns=tb).encode(ev)
            return state.time_base, state.encoder.encode(ev, triggers=tr if tr.size else None)
        except EvdnerfError as exc:
            raise type(exc)(f"{what}: packet {state.seq}: {exc}") from exc

    def _packet_bytes(self, state, stamp, time_base, payload, header_seq=None):
        seq = state.seq
        if self.ros1:
            head = state.prefix(seq if header_seq is None else header_seq, stamp, seq, time_base, len(payload))
        else:
            head = state.prefix(stamp, seq, time_base, len(payload))
        return head + payload

    def _event_packets(self, state, events, triggers, bounds, tbounds, stamps):
        what = f"{self.name}: topic {state.topic}"
        for k, stamp in enumerate(stamps):
            ev = events[bounds[k]:bounds[k + 1]]
            tr = triggers[tbounds[k]:tbounds[k + 1]]
            time_base, payload = self._payload(state, ev, tr, stamp, what)
            self._emit(state, self._packet_bytes(state, stamp, time_base, payload), stamp)
            state.seq += 1
        return len(stamps)

    def _array_packets(self, state, events, bounds, stamps):
        what = f"{self.name}: topic {state.topic}"
        prefix = state.prefix
        npk = len(stamps)
        scratch = None
        k = 0
        while k < npk:
            k2 = int(np.searchsorted(bounds, bounds[k] + em.BLOCK_EVENTS, "right")) - 1
            k2 = min(max(k2, k + 1), npk)
            s0, s1 = int(bounds[k]), int(bounds[k2])
            block = events[s0:s1]
            if self.ros1:  # events were validated sorted
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
                if self.ros1:
                    data = prefix(state.seq, stamp, b - a) + mv[13 * a:13 * b]
                else:
                    data = b"".join((prefix(stamp, b - a), mv[16 * a:16 * a + 4], mv[16 * a + 6:16 * b - 1]))
                self._emit(state, data, stamp)
                state.seq += 1
            k = k2
        return npk

    # ----- one message from given events (re-encoding keeps stamp, seq, frame_id)
    def write_packet(self, topic: str, events, *, width: int, height: int, encoding: str, triggers=None,
                     stamp_ns: int | None = None, seq: int | None = None, frame_id: str = "event_camera",
                     t_ns: int | None = None) -> int:
        """One message holding exactly ``events`` (and triggers). ``stamp_ns``: header.stamp
        (default: the first event's time); ``seq``: EventPacket.seq / ROS 1 header.seq (default:
        the topic's count); ``t_ns``: bag time (default: the stamp). Returns 1."""
        state, what = self._state(topic, encoding, width, height, frame_id, raw=False)
        events, triggers, first_t, last_t = self._check_events(state, what, events, triggers)
        if first_t is None and stamp_ns is None:
            raise InputError(f"{what}: an empty packet needs stamp_ns")
        stamp = first_t if stamp_ns is None else check_time(stamp_ns, f"{what}: stamp_ns")
        t_ns = stamp if t_ns is None else check_time(t_ns, f"{what}: t_ns")
        if seq is not None and (isinstance(seq, bool) or not isinstance(seq, (int, np.integer)) or seq < 0):
            raise InputError(f"{what}: seq must be a non-negative integer, got {seq!r}")
        if first_t is not None:
            if state.origin is None and encoding in STREAM_ENCODINGS + ("libcaer",):
                self._start(state, first_t, what, stamp_is_first=stamp == first_t)
            if encoding in STREAM_ENCODINGS + ("libcaer",):
                self._check_grid(state, what, events, triggers)
        self._start(state, stamp if first_t is None else first_t, what)
        self.topics[topic] = state
        saved_seq = state.seq
        if seq is not None:
            state.seq = int(seq)
        try:
            if encoding == "array":
                rec_fn = em.ros1_event_records if self.ros1 else em.cdr_event_records
                rec = rec_fn(events, what=what, is_sorted=True)
                mv = memoryview(rec.view(np.uint8))
                n = events.size
                if self.ros1:
                    data = state.prefix(state.seq, stamp, n) + mv[:13 * n]
                else:
                    data = b"".join((state.prefix(stamp, n), *em.cdr_events_bytes(mv, 0, n)))
            else:
                if not events.size and not triggers.size and encoding in STREAM_ENCODINGS + ("libcaer",):
                    time_base, payload = (state.time_base if encoding in STREAM_ENCODINGS else 0), b""
                else:
                    time_base, payload = self._payload(state, events, triggers, stamp, what)
                data = self._packet_bytes(state, stamp, time_base, payload)
        except BaseException:
            state.seq = saved_seq
            raise
        self._emit_one(state, data, t_ns)
        state.seq += 1
        if last_t is not None:
            state.last_t = last_t
        return 1

    # ----- a sensor's bytes passed through
    def write_raw_packet(self, topic: str, payload, *, encoding: str, width: int, height: int, stamp_ns: int,
                         time_base: int = 0, seq: int | None = None, frame_id: str = "event_camera",
                         t_ns: int | None = None) -> int:
        """Wrap ``payload`` (bytes / memoryview / uint8 array: a whole number of the encoding's
        words) in an EventPacket as it is, with the given ``stamp_ns`` (header.stamp, the host
        time of its first event) and ``time_base`` (0 for evt3 as metavision_driver writes it;
        libcaer_driver's value for libcaer / libcaer_cmp). ``seq`` defaults to the topic's count;
        ``t_ns`` (bag time) to the stamp. Returns 1."""
        state, what = self._state(topic, encoding, width, height, frame_id, raw=True, encodings=PACKET_ENCODINGS)
        stamp = check_time(stamp_ns, f"{what}: stamp_ns")
        t_ns = stamp if t_ns is None else check_time(t_ns, f"{what}: t_ns")
        time_base = check_time(time_base, f"{what}: time_base")
        if seq is not None and (isinstance(seq, bool) or not isinstance(seq, (int, np.integer)) or seq < 0):
            raise InputError(f"{what}: seq must be a non-negative integer, got {seq!r}")
        if isinstance(payload, np.ndarray):
            payload = np.ascontiguousarray(payload).view(np.uint8).reshape(-1).tobytes()
        elif isinstance(payload, (bytes, bytearray, memoryview)):
            payload = bytes(payload)
        else:
            raise InputError(f"{what}: payload must be bytes, bytearray, memoryview or a numpy array, got "
                             f"{type(payload).__name__}")
        if len(payload) % WORD_BYTES[encoding]:
            raise InputError(f"{what}: {len(payload)} bytes of {encoding} are not a whole number of "
                             f"{WORD_BYTES[encoding]}-byte words; pass whole words (keep the rest for the next packet)")
        self._start(state, stamp, what)
        self.topics[topic] = state
        if seq is not None:
            state.seq = int(seq)
        self._emit_one(state, self._packet_bytes(state, stamp, time_base, payload), t_ns)
        state.seq += 1
        return 1
