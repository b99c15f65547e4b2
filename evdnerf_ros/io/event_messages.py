"""Serialised event messages built and parsed with numpy (no per-event Python objects).

Byte layouts (measured against rosbags' serialisers; the tests check byte identity):

ROS 2 CDR (XCDR1, little-endian, 4-byte encapsulation header ``00 01 00 00``; alignment is
relative to the byte after that header):

- ``dvs_msgs/msg/EventArray``: header (sec i32, nanosec u32, frame_id string), height u32,
  width u32, event count u32, then the events. Event ``k >= 1`` occupies a 16-byte record
  ``x u16, y u16, 2 pad, sec i32, nanosec u32, polarity u8, 1 pad``; event 0 starts 4-byte
  aligned right after the count, so it has no pad between y and sec (14 bytes), and the
  message ends right after the last polarity byte: n events take ``16 n - 3`` bytes. We build
  one 16-byte record per event for a whole block of packets (:data:`CDR_EVENT_DTYPE`) and cut
  each message out of it with two slices.
- ``event_camera_msgs/msg/EventPacket``: header, height, width, seq u64, time_base u64,
  encoding string, is_bigendian bool, events uint8[] (u32 length + raw bytes).

ROS 1 (packed, no alignment, strings without NUL): Header = seq u32, stamp (secs u32,
nsecs u32), frame_id; ``dvs_msgs/EventArray`` events are 13 bytes each
(:data:`ROS1_EVENT_DTYPE`: x u16, y u16, secs u32, nsecs u32, polarity u8).

Times are int64 ns; stamps split exactly with floor division (nanosec in [0, 1e9)).
Out-of-range times raise InputError rather than wrap.
"""

from __future__ import annotations

import struct
from typing import NamedTuple

import numpy as np

from ..errors import FormatError, InputError
from ..events.types import EVENT_DTYPE, TRIGGER_DTYPE

NS_PER_S = 1_000_000_000
INT64_MAX = 2**63 - 1
CDR_LE_HEADER = b"\x00\x01\x00\x00"

#: One element of a CDR ``dvs_msgs/Event[]`` at 16-byte stride (elements k >= 1; see module doc).
CDR_EVENT_DTYPE = np.dtype({"names": ["x", "y", "sec", "nanosec", "polarity"],
                            "formats": ["<u2", "<u2", "<i4", "<u4", "u1"],
                            "offsets": [0, 2, 6, 10, 14], "itemsize": 16})
#: One ROS 1 ``dvs_msgs/Event`` (packed, 13 bytes).
ROS1_EVENT_DTYPE = np.dtype({"names": ["x", "y", "sec", "nanosec", "polarity"],
                             "formats": ["<u2", "<u2", "<u4", "<u4", "u1"],
                             "offsets": [0, 2, 4, 8, 12], "itemsize": 13})

#: Events per block when building EventArray records (bounds the temporary memory).
BLOCK_EVENTS = 1 << 20


# --------------------------------------------------------------------------- time helpers


def check_time_range(t: np.ndarray, *, ros1: bool, what: str, is_sorted: bool = False) -> None:
    """InputError unless every time fits the message's seconds field (int32 in ROS 2, uint32 in ROS 1)."""
    if not t.size:
        return
    lo, hi = (0, 2**32 * NS_PER_S - 1) if ros1 else (-(2**31) * NS_PER_S, 2**31 * NS_PER_S - 1)
    tmin, tmax = (int(t[0]), int(t[-1])) if is_sorted else (int(t.min()), int(t.max()))
    if tmin < lo or tmax > hi:
        bad = int(np.flatnonzero((t < lo) | (t > hi))[0])
        kind = "ROS 1 time (uint32 seconds)" if ros1 else "builtin_interfaces/Time (int32 seconds)"
        raise InputError(f"{what}: event {bad} at t={int(t[bad])} ns is outside the range of a {kind}; "
                         "shift the time origin")


def _fill_time(rec: np.ndarray, t: np.ndarray) -> None:
    """rec["sec"], rec["nanosec"] = floor(t / 1e9), t mod 1e9 (exact integer arithmetic)."""
    t = np.ascontiguousarray(t)  # one gather, then contiguous arithmetic
    sec = np.floor_divide(t, NS_PER_S)
    rec["sec"] = sec
    sec *= NS_PER_S
    np.subtract(t, sec, out=sec)
    rec["nanosec"] = sec


#: x and y as one 4-byte field: they are adjacent in EVENT_DTYPE and in both record layouts.
_EVENT_XY = np.dtype({"names": ["xy"], "formats": ["<u4"], "offsets": [8], "itemsize": EVENT_DTYPE.itemsize})


def _copy_xy(rec: np.ndarray, events: np.ndarray) -> None:
    dst = np.dtype({"names": ["xy"], "formats": ["<u4"], "offsets": [0], "itemsize": rec.dtype.itemsize})
    rec.view(dst)["xy"] = events.view(_EVENT_XY)["xy"]


# --------------------------------------------------------------------------- prefix builders
#
# Per topic, frame_id / height / width / encoding are constant, so every message prefix is
# "variable fields + constant bytes"; the builders below precompute the constant parts
# (including the CDR alignment padding, which only depends on the frame_id length).

_II = struct.Struct("<iI")
_UI = struct.Struct("<II")
_U = struct.Struct("<I")
_QQ = struct.Struct("<QQ")


def _stamp(stamp_ns: int, *, ros1: bool) -> tuple[int, int]:
    sec, nsec = divmod(int(stamp_ns), NS_PER_S)
    if ros1 and not 0 <= sec < 2**32:
        raise InputError(f"header stamp {stamp_ns} ns is outside ROS 1 time (uint32 seconds, no negative times)")
    if not ros1 and not -(2**31) <= sec < 2**31:
        raise InputError(f"header stamp {stamp_ns} ns is outside builtin_interfaces/Time's int32 seconds")
    return sec, nsec


def _cdr_string(s: str, pos: int) -> tuple[bytes, int]:
    """CDR string at 4-aligned ``pos``: u32 length (with NUL), bytes, NUL."""
    data = s.encode("utf-8") + b"\x00"
    return _U.pack(len(data)) + data, pos + 4 + len(data)


def _pad(pos: int, n: int) -> tuple[bytes, int]:
    k = -pos % n
    return b"\x00" * k, pos + k


class CdrEventArrayPrefix:
    """Bytes of a CDR ``dvs_msgs/msg/EventArray`` up to and including the event count."""

    def __init__(self, frame_id: str, height: int, width: int):
        fid, pos = _cdr_string(frame_id, 8)
        pad, pos = _pad(pos, 4)
        self._mid = fid + pad + _UI.pack(height, width)

    def __call__(self, stamp_ns: int, count: int) -> bytes:
        sec, nsec = _stamp(stamp_ns, ros1=False)
        return b"".join((CDR_LE_HEADER, _II.pack(sec, nsec), self._mid, _U.pack(count)))


class CdrEventPacketPrefix:
    """Bytes of a CDR ``event_camera_msgs/msg/EventPacket`` up to and including the events length."""

    def __init__(self, frame_id: str, height: int, width: int, encoding: str, is_bigendian: bool = False):
        fid, pos = _cdr_string(frame_id, 8)
        pad4, pos = _pad(pos, 4)
        pos += 8  # height, width
        pad8, pos = _pad(pos, 8)
        self._mid1 = fid + pad4 + _UI.pack(height, width) + pad8
        pos += 16  # seq, time_base
        enc, pos = _cdr_string(encoding, pos)
        pos += 1  # is_bigendian
        pad, pos = _pad(pos, 4)
        self._mid2 = enc + (b"\x01" if is_bigendian else b"\x00") + pad

    def __call__(self, stamp_ns: int, seq: int, time_base: int, nbytes: int) -> bytes:
        sec, nsec = _stamp(stamp_ns, ros1=False)
        return b"".join((CDR_LE_HEADER, _II.pack(sec, nsec), self._mid1, _QQ.pack(seq, time_base),
                         self._mid2, _U.pack(nbytes)))


class Ros1EventArrayPrefix:
    """Bytes of a ROS 1 ``dvs_msgs/EventArray`` up to and including the event count."""

    def __init__(self, frame_id: str, height: int, width: int):
        fid = frame_id.encode("utf-8")
        self._mid = _U.pack(len(fid)) + fid + _UI.pack(height, width)

    def __call__(self, seq: int, stamp_ns: int, count: int) -> bytes:
        sec, nsec = _stamp(stamp_ns, ros1=True)
        return b"".join((struct.pack("<III", seq & 0xFFFFFFFF, sec, nsec), self._mid, _U.pack(count)))


class Ros1EventPacketPrefix:
    """Bytes of a ROS 1 ``event_camera_msgs/EventPacket`` up to and including the events length."""

    def __init__(self, frame_id: str, height: int, width: int, encoding: str, is_bigendian: bool = False):
        fid = frame_id.encode("utf-8")
        enc = encoding.encode("utf-8")
        self._mid1 = _U.pack(len(fid)) + fid + _UI.pack(height, width)
        self._mid2 = _U.pack(len(enc)) + enc + (b"\x01" if is_bigendian else b"\x00")

    def __call__(self, header_seq: int, stamp_ns: int, seq: int, time_base: int, nbytes: int) -> bytes:
        sec, nsec = _stamp(stamp_ns, ros1=True)
        return b"".join((struct.pack("<III", header_seq & 0xFFFFFFFF, sec, nsec), self._mid1,
                         _QQ.pack(seq, time_base), self._mid2, _U.pack(nbytes)))


# --------------------------------------------------------------------------- event records


def _record_buffer(n: int, dtype: np.dtype, out: np.ndarray | None) -> np.ndarray:
    if out is not None and out.dtype == dtype and out.size >= n:
        return out[:n]  # reusing a buffer saves the page faults of a fresh allocation
    return np.empty(n, dtype)


def cdr_event_records(events: np.ndarray, *, what: str, is_sorted: bool = False,
                      out: np.ndarray | None = None) -> np.ndarray:
    """One 16-byte CDR record per event (see module doc); slice messages with :func:`cdr_events_bytes`.
    ``out``: an optional CDR_EVENT_DTYPE buffer to reuse (its first len(events) records are returned)."""
    check_time_range(events["t"], ros1=False, what=what, is_sorted=is_sorted)
    n = events.size
    rec = _record_buffer(n, CDR_EVENT_DTYPE, out)
    words = rec.view(np.uint16).reshape(n, 8)  # x, y, pad, sec lo/hi, nanosec lo/hi, polarity + pad
    words[:, 2] = 0
    _copy_xy(rec, events)
    _fill_time(rec, events["t"])
    words[:, 7] = events["p"] > 0  # polarity byte and the zero pad byte after it
    return rec


def cdr_events_bytes(records_bytes: memoryview, start: int, stop: int) -> list:
    """Byte pieces of the ``Event[]`` payload of events [start, stop) of a record block."""
    if stop <= start:
        return []
    a, b = 16 * start, 16 * stop
    return [records_bytes[a:a + 4], records_bytes[a + 6:b - 1]]


def ros1_event_records(events: np.ndarray, *, what: str, is_sorted: bool = False,
                       out: np.ndarray | None = None) -> np.ndarray:
    """One packed 13-byte ROS 1 dvs_msgs/Event record per event (``out``: a buffer to reuse)."""
    check_time_range(events["t"], ros1=True, what=what, is_sorted=is_sorted)
    rec = _record_buffer(events.size, ROS1_EVENT_DTYPE, out)
    _copy_xy(rec, events)
    _fill_time(rec, events["t"])
    rec["polarity"] = events["p"] > 0
    return rec


def records_to_events(rec: np.ndarray, *, what: str, out: np.ndarray | None = None) -> np.ndarray:
    """CDR or ROS 1 event records (fields x, y, sec, nanosec, polarity) -> EVENT_DTYPE (into ``out``)."""
    n = rec.shape[0]
    out = np.empty(n, EVENT_DTYPE) if out is None else out
    if n == 0:
        return out
    pol = rec["polarity"]
    if int(pol.max()) > 1:
        bad = int(np.flatnonzero(pol > 1)[0])
        raise FormatError(f"event {bad} has polarity byte {int(pol[bad])}; a bool must be 0 or 1", source=what)
    t = out["t"]
    t[:] = rec["sec"]  # widen to int64 before scaling
    t *= NS_PER_S
    t += rec["nanosec"]
    out["x"] = rec["x"]
    out["y"] = rec["y"]
    p = out["p"]
    np.multiply(pol, 2, out=p, casting="unsafe")
    p -= 1
    return out


# --------------------------------------------------------------------------- parsers

_HDR2 = struct.Struct("<iII")   # CDR: sec, nanosec, frame_id length
_HDR1 = struct.Struct("<IIII")  # ROS 1: seq, secs, nsecs, frame_id length
_III = struct.Struct("<III")


def _truncated(what, raw, need):
    return FormatError(f"message has {len(raw)} bytes but its fields need at least {need}; the message is "
                       "truncated or of another type", source=what)


def _parse_header(raw, ros1: bool, what: str) -> tuple[int, str, int, int]:
    """-> (stamp_ns, frame_id, seq, position after frame_id)."""
    try:
        if ros1:
            seq, sec, nsec, n = _HDR1.unpack_from(raw, 0)
            pos = 16
        else:
            if bytes(raw[:2]) != b"\x00\x01":
                if bytes(raw[:2]) == b"\x00\x00":
                    raise FormatError("big-endian CDR is not supported", source=what)
                raise FormatError(f"not a CDR payload (encapsulation {bytes(raw[:4]).hex()})", source=what)
            sec, nsec, n = _HDR2.unpack_from(raw, 4)
            seq, pos = 0, 16
    except struct.error:
        raise _truncated(what, raw, 16) from None
    end = pos + n
    if end > len(raw):
        raise _truncated(what, raw, end)
    data = bytes(raw[pos:end])
    if not ros1:
        if not data.endswith(b"\x00"):
            raise FormatError("CDR string without terminating NUL", source=what)
        data = data[:-1]
    try:
        frame_id = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise FormatError(f"frame_id is not UTF-8 ({exc})", source=what) from None
    return sec * NS_PER_S + nsec, frame_id, seq, end


class EventArrayLayout(NamedTuple):
    stamp_ns: int
    frame_id: str
    height: int
    width: int
    seq: int
    count: int
    offset: int  # byte offset of the first event
    raw: object = None  # the message bytes


def event_array_layout(raw, *, ros1: bool = False, what: str = "EventArray") -> EventArrayLayout:
    """Fields of a serialised dvs_msgs EventArray and where its events lie (events not converted)."""
    stamp, frame_id, seq, pos = _parse_header(raw, ros1, what)
    if not ros1:
        pos += -(pos - 4) % 4
    try:
        height, width, n = _III.unpack_from(raw, pos)
    except struct.error:
        raise _truncated(what, raw, pos + 12) from None
    pos += 12
    left = len(raw) - pos
    need = 13 * n if ros1 else (16 * n - 3 if n else 0)
    slack = 0 if ros1 else 3
    if not need <= left <= need + slack:
        raise FormatError(f"{n} events need {need} bytes but {left} follow the header; the message is truncated "
                          f"or not a {'ROS 1 dvs_msgs/EventArray' if ros1 else 'dvs_msgs/msg/EventArray'}",
                          source=what)
    return EventArrayLayout(stamp, frame_id, height, width, seq, n, pos, raw)


class EventArrayFields(NamedTuple):
    stamp_ns: int
    frame_id: str
    height: int
    width: int
    seq: int
    events: np.ndarray  # EVENT_DTYPE (a new array)


def parse_event_array(raw, *, ros1: bool = False, what: str = "EventArray") -> EventArrayFields:
    lay = event_array_layout(raw, ros1=ros1, what=what)
    n = lay.count
    if ros1:
        rec = np.frombuffer(raw, ROS1_EVENT_DTYPE, n, lay.offset)
    else:
        buf = np.zeros(16 * n, np.uint8)
        place_cdr_events(buf, 0, raw, lay.offset, n)
        rec = buf.view(CDR_EVENT_DTYPE)
        fix_first_cdr_events(buf, np.zeros(1 if n else 0, np.int64))
    return EventArrayFields(lay.stamp_ns, lay.frame_id, lay.height, lay.width, lay.seq,
                            records_to_events(rec, what=what))


def place_cdr_events(buf: np.ndarray, index: int, raw, offset: int, n: int) -> None:
    """Copy a CDR Event[] of n events into a 16-byte record buffer starting at record ``index``.

    The bytes go to ``16 * index + 2``: then events 1.. land exactly on records and event 0 has
    its sec / nanosec / polarity in place, with x and y shifted by 2 bytes
    (:func:`fix_first_cdr_events` moves them).
    """
    if n:
        a = 16 * index + 2
        buf[a:a + 16 * n - 3] = np.frombuffer(raw, np.uint8, 16 * n - 3, offset)


def fix_first_cdr_events(buf: np.ndarray, first_indices: np.ndarray) -> None:
    if first_indices.size:
        u16 = buf.view("<u2").reshape(-1, 8)
        u16[first_indices, 0] = u16[first_indices, 1]
        u16[first_indices, 1] = u16[first_indices, 2]


class EventPacketFields(NamedTuple):
    stamp_ns: int
    frame_id: str
    height: int
    width: int
    seq: int
    time_base: int
    encoding: str
    is_bigendian: bool
    events: memoryview  # the encoded bytes (a view into the message)
    header_seq: int = 0  # ROS 1 header.seq


_IIQQI = struct.Struct("<IIQQI")


def parse_event_packet(raw, *, ros1: bool = False, what: str = "EventPacket") -> EventPacketFields:
    stamp, frame_id, hseq, pos = _parse_header(raw, ros1, what)
    try:
        if ros1:
            height, width, seq, time_base, n = _IIQQI.unpack_from(raw, pos)
            pos += 28
        else:
            pos += -(pos - 4) % 4
            height, width = _UI.unpack_from(raw, pos)
            pos += 8
            pos += -(pos - 4) % 8
            seq, time_base = _QQ.unpack_from(raw, pos)
            pos += 16
            (n,) = _U.unpack_from(raw, pos)
            pos += 4
    except struct.error:
        raise _truncated(what, raw, pos + 32) from None
    end = pos + n
    if end > len(raw):
        raise _truncated(what, raw, end)
    enc = bytes(raw[pos:end])
    if not ros1:
        if not enc.endswith(b"\x00"):
            raise FormatError("CDR string without terminating NUL", source=what)
        enc = enc[:-1]
    encoding = enc.decode("utf-8", errors="replace")
    pos = end
    try:
        big = raw[pos]
        pos += 1
        if not ros1:
            pos += -(pos - 4) % 4
        (n,) = _U.unpack_from(raw, pos)
    except (struct.error, IndexError):
        raise _truncated(what, raw, pos + 5) from None
    pos += 4
    if big > 1:
        raise FormatError(f"is_bigendian byte is {big}; a bool must be 0 or 1", source=what)
    left = len(raw) - pos
    if not n <= left <= n + (0 if ros1 else 3):
        raise FormatError(f"events field declares {n} bytes but {left} follow; the message is truncated",
                          source=what)
    return EventPacketFields(stamp, frame_id, height, width, seq, time_base, encoding, bool(big),
                             memoryview(raw)[pos:pos + n], hseq)


# --------------------------------------------------------------------------- packetising


def packet_bounds(t: np.ndarray, packet_ns: int, max_events: int | None = None) -> np.ndarray:
    """Packet boundaries [b0=0, b1, ..., n] over sorted times.

    A packet opens at its first event and closes before the first event at or after
    ``t_first + packet_ns`` (as metavision_driver's time-based packets), or after
    ``max_events`` events. One Python step per packet, none per event.
    """
    t = np.ascontiguousarray(t, dtype=np.int64)  # a field view would be copied on every search
    n = t.size
    bounds = [0]
    s = 0
    limit = max_events if max_events else n
    while s < n:
        end_t = int(t[s]) + packet_ns
        e = n if end_t > INT64_MAX else int(t.searchsorted(np.int64(end_t), "left"))
        e = min(max(e, s + 1), s + limit)
        bounds.append(e)
        s = e
    return np.asarray(bounds, dtype=np.int64)


def assign_triggers(packet_t0: np.ndarray, trig_t: np.ndarray) -> np.ndarray:
    """Trigger slice bounds per packet: trigger i goes to the last packet starting at or before it
    (triggers before the first packet go to packet 0). Returns an array of len(packets) + 1."""
    idx = np.searchsorted(packet_t0, trig_t, "right") - 1
    idx = np.maximum(idx, 0)
    return np.searchsorted(idx, np.arange(packet_t0.size + 1), "left")


def check_triggers(triggers, *, what: str) -> np.ndarray:
    triggers = np.asarray(triggers)
    if triggers.dtype != TRIGGER_DTYPE:
        raise InputError(f"{what}: triggers dtype {triggers.dtype} is not TRIGGER_DTYPE {TRIGGER_DTYPE}; build "
                         "them with evdnerf_ros.events.types.make_triggers()")
    t = triggers["t"]
    if t.size > 1 and np.any(t[1:] < t[:-1]):
        i = int(np.flatnonzero(t[1:] < t[:-1])[0]) + 1
        raise InputError(f"{what}: trigger times not sorted (trigger {i} at t={int(t[i])} ns comes after "
                         f"t={int(t[i - 1])} ns); sort them by t first")
    return triggers
