"""Shared pieces of the event codecs: the Decoded record, byte-buffer handling, input
validation and the streaming-decoder skeleton (left-over bytes, byte offsets, warnings).

Everything here works on whole numpy arrays; no code path touches events one by one.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import numpy as np

from ...errors import FormatError, InputError
from ..types import EVENT_DTYPE, TRIGGER_DTYPE, as_events

_EMPTY_U8 = np.empty(0, np.uint8)


class DroppedEventsWarning(UserWarning):
    """Events or triggers were discarded because the stream gave no valid time (or row) yet."""


@dataclass
class Decoded:
    """Result of decoding a byte stream: events (EVENT_DTYPE) and external triggers (TRIGGER_DTYPE)."""

    events: np.ndarray = field(default_factory=lambda: np.empty(0, EVENT_DTYPE))
    triggers: np.ndarray = field(default_factory=lambda: np.empty(0, TRIGGER_DTYPE))

    def __len__(self) -> int:
        return int(self.events.shape[0])

    @staticmethod
    def concatenate(parts) -> "Decoded":
        """Join decoded pieces in order (e.g. the results of successive feed() calls)."""
        parts = list(parts)
        ev = [p.events for p in parts if p.events.size]
        tr = [p.triggers for p in parts if p.triggers.size]
        return Decoded(
            np.concatenate(ev) if len(ev) > 1 else (ev[0] if ev else np.empty(0, EVENT_DTYPE)),
            np.concatenate(tr) if len(tr) > 1 else (tr[0] if tr else np.empty(0, TRIGGER_DTYPE)),
        )


def as_u8(data, *, source: str) -> np.ndarray:
    """View bytes / bytearray / memoryview / numpy array as a flat uint8 array (no copy)."""
    if isinstance(data, np.ndarray):
        if not data.flags.c_contiguous:
            data = np.ascontiguousarray(data)
        return data.reshape(-1).view(np.uint8)
    if isinstance(data, (bytes, bytearray, memoryview)):
        mv = memoryview(data)
        if not mv.c_contiguous:
            raise InputError(f"{source}: the byte buffer is not contiguous; pass bytes(...) of it")
        return np.frombuffer(mv, np.uint8)
    raise InputError(f"{source}: expected bytes, bytearray, memoryview or a numpy array, "
                     f"got {type(data).__name__}")


#: Largest |time_base_ns| accepted (about 146 years), so that times never overflow int64.
TIME_BASE_LIMIT = 1 << 62
#: Largest sensor time (us) a decoder turns into ns before int64 would overflow.
MAX_SENSOR_US = ((1 << 63) - 1 - TIME_BASE_LIMIT) // 1000


def check_time_base(time_base_ns) -> int:
    if isinstance(time_base_ns, (bool, float)) or not isinstance(time_base_ns, (int, np.integer)):
        raise InputError(f"time_base_ns must be an integer number of nanoseconds, got {time_base_ns!r}")
    if abs(int(time_base_ns)) >= TIME_BASE_LIMIT:
        raise InputError(f"time_base_ns={time_base_ns} is out of range (|value| < 2**62 ns)")
    return int(time_base_ns)


def chunk_to_us(events, time_base_ns: int, encoding: str, *, index_offset: int = 0,
                prev_t=None, max_x: int = 2048, max_y: int = 2048,
                source: str = "events") -> np.ndarray:
    """Validate one chunk of EVENT_DTYPE events for a microsecond format; return its times in
    us after time_base_ns. `index_offset` / `prev_t` place the chunk inside a larger array
    (for error messages and the sort check across chunk boundaries).

    Raises InputError when times are unsorted, not a whole microsecond after time_base_ns or
    before it, polarity is not +1/-1, or a coordinate does not fit.
    """
    n = events.shape[0]
    if n == 0:
        return np.empty(0, np.int64)
    t = events["t"]
    if prev_t is not None and t[0] < prev_t:
        raise InputError(f"{source}: timestamps not sorted: event {index_offset} at t={int(t[0])} ns "
                         f"comes after t={int(prev_t)} ns; sort by t (np.argsort(t, kind='stable')) first")
    back = t[1:] < t[:-1]
    if back.any():
        i = int(np.flatnonzero(back)[0]) + 1
        raise InputError(f"{source}: timestamps not sorted: event {index_offset + i} at t={int(t[i])} ns "
                         f"comes after t={int(t[i - 1])} ns; sort by t (np.argsort(t, kind='stable')) "
                         "first")
    p = events["p"]
    badp = (p != 1) & (p != -1)
    if badp.any():
        i = int(np.flatnonzero(badp)[0])
        raise InputError(f"{source}: event {index_offset + i} has polarity {int(p[i])}; polarity must "
                         "be +1 or -1")
    for axis, limit in (("x", max_x), ("y", max_y)):
        col = events[axis]
        if int(col.max()) >= limit:
            i = int(np.flatnonzero(col >= limit)[0])
            raise InputError(f"{source}: event {index_offset + i} has {axis}={int(col[i])}, but "
                             f"{encoding} carries {axis} < {limit}; crop or remap the coordinates first")
    rel = t - np.int64(time_base_ns)
    if rel[0] < 0:
        raise InputError(f"{source}: event {index_offset} at t={int(t[0])} ns is before time_base_ns="
                         f"{time_base_ns}; {encoding} times are offsets from the time base, "
                         "choose a time base at or before the first event")
    us, rem = np.divmod(rel, 1000)
    if rem.any():
        bad = np.flatnonzero(rem)
        i = int(bad[0])
        raise InputError(
            f"{source}: event {index_offset + i} at t={int(t[i])} ns is not a whole microsecond after "
            f"time_base_ns={time_base_ns}; {encoding} carries microseconds, so round explicitly "
            "first, e.g. evdnerf_ros.events.codecs.quantize_to_us(events, time_base_ns=...)")
    return us


def check_events_for_us(events, time_base_ns: int, encoding: str, *, chunk: int = 1 << 18,
                        max_x: int = 2048, max_y: int = 2048, source: str = "events") -> np.ndarray:
    """Validate a whole event array for a microsecond format (chunk by chunk, bounded memory);
    return it as EVENT_DTYPE."""
    events = as_events(events, source=source)
    if events.ndim != 1:
        raise InputError(f"{source}: expected a 1-D event array, got shape {events.shape}")
    prev = None
    for a in range(0, events.shape[0], chunk):
        part = events[a:a + chunk]
        chunk_to_us(part, time_base_ns, encoding, index_offset=a, prev_t=prev, max_x=max_x,
                    max_y=max_y, source=source)
        prev = part["t"][-1]
    return events


def check_coords(events, max_x: int, max_y: int, encoding: str, source: str) -> None:
    for axis, limit in (("x", max_x), ("y", max_y)):
        col = events[axis]
        if col.size and int(col.max()) >= limit:
            i = int(np.flatnonzero(col >= limit)[0])
            raise InputError(f"{source}: event {i} has {axis}={int(col[i])}, but {encoding} "
                             f"carries {axis} < {limit}; crop or remap the coordinates first")


def triggers_to_us(triggers, time_base_ns: int, encoding: str, *, max_id: int,
                   source: str = "triggers") -> tuple[np.ndarray, np.ndarray]:
    """Validate triggers for a microsecond format; return (triggers, us)."""
    if triggers is None:
        return np.empty(0, TRIGGER_DTYPE), np.empty(0, np.int64)
    triggers = np.asarray(triggers)
    if triggers.dtype != TRIGGER_DTYPE:
        names = triggers.dtype.names or ()
        if not {"t", "id", "value"} <= set(names):
            raise InputError(f"{source}: expected TRIGGER_DTYPE fields t, id, value; got "
                             f"{names or triggers.dtype}")
        conv = np.empty(triggers.shape[0], TRIGGER_DTYPE)
        for name in ("t", "id", "value"):
            conv[name] = triggers[name]
        triggers = conv
    if triggers.ndim != 1:
        raise InputError(f"{source}: expected a 1-D trigger array, got shape {triggers.shape}")
    if triggers.size == 0:
        return triggers, np.empty(0, np.int64)
    t = triggers["t"]
    back = np.flatnonzero(t[1:] < t[:-1])
    if back.size:
        i = int(back[0]) + 1
        raise InputError(f"{source}: trigger {i} at t={t[i]} ns comes after t={t[i - 1]} ns; "
                         "sort triggers by time first")
    bad_id = np.flatnonzero(triggers["id"] >= max_id)
    if bad_id.size:
        i = int(bad_id[0])
        raise InputError(f"{source}: trigger {i} has id {triggers['id'][i]}, but {encoding} carries "
                         f"ids 0..{max_id - 1}")
    bad_v = np.flatnonzero(triggers["value"] > 1)
    if bad_v.size:
        i = int(bad_v[0])
        raise InputError(f"{source}: trigger {i} has value {triggers['value'][i]}; "
                         "a trigger edge value must be 0 (falling) or 1 (rising)")
    rel = t - np.int64(time_base_ns)
    if rel[0] < 0:
        raise InputError(f"{source}: trigger 0 at t={t[0]} ns is before time_base_ns={time_base_ns}")
    us, rem = np.divmod(rel, 1000)
    badr = np.flatnonzero(rem)
    if badr.size:
        i = int(badr[0])
        raise InputError(f"{source}: trigger {i} at t={t[i]} ns is not a whole microsecond after "
                         f"time_base_ns={time_base_ns}; {encoding} carries microseconds, round "
                         "the trigger times explicitly first")
    return triggers, us


def check_not_before(first_us: int, last_us: int | None, what: str) -> None:
    """A StreamEncoder call must not start before the previous call ended."""
    if last_us is not None and first_us < last_us:
        raise InputError(f"{what}: this chunk starts at {first_us} us after the time base, before the "
                         f"previous chunk's last time {last_us} us; chunks must be in time order")


def drop_warning(source: str, n_events: int, n_triggers: int, reason: str) -> None:
    parts = []
    if n_events:
        parts.append(f"{n_events} event(s)")
    if n_triggers:
        parts.append(f"{n_triggers} trigger(s)")
    warnings.warn(f"{source}: dropped {' and '.join(parts)} {reason}", DroppedEventsWarning,
                  stacklevel=4)


class StreamDecoderBase:
    """Splits incoming bytes into whole words, keeps the left-over bytes and the byte offset.

    Subclasses set WORD (bytes per word) and DTYPE (the word dtype) and implement
    `_count(words)` (an upper bound of the events the words decode to, no state needed) and
    `_decode_into(words, offset, out)` that decodes whole words starting at absolute byte
    `offset` into `out` (length >= the count), updates the stream state and returns
    (number of events written, triggers array, dropped events, dropped triggers).
    """

    WORD = 1
    DTYPE = np.uint8
    NAME = "?"
    DROP_REASON = "before the stream gave a valid time"

    def __init__(self, *, time_base_ns: int = 0, source: str = "<stream>", offset: int = 0):
        self.time_base_ns = check_time_base(time_base_ns)
        self.source = str(source)
        self._offset = int(offset)   # absolute byte offset of the next whole word
        self._rest = _EMPTY_U8       # bytes of a partial word carried to the next feed
        self._closed = False

    @property
    def offset(self) -> int:
        """Absolute byte offset (including any starting offset) of the first byte not yet decoded."""
        return self._offset

    def _whole_words(self, chunk) -> np.ndarray:
        if self._closed:
            raise InputError(f"{self.source}: feed() after close()")
        data = as_u8(chunk, source=self.source)
        if self._rest.size:
            data = np.concatenate([self._rest, data])
        n_whole = (data.size // self.WORD) * self.WORD
        if n_whole != data.size:
            self._rest = data[n_whole:].copy()
            data = data[:n_whole]
        else:
            self._rest = _EMPTY_U8
        if data.ctypes.data % self.WORD:
            data = data.copy()           # aligned words for fast numpy loops
        return data.view(self.DTYPE)

    def feed(self, chunk) -> Decoded:
        """Decode the whole words available so far; a partial word waits for the next chunk."""
        words = self._whole_words(chunk)
        if words.size == 0:
            return Decoded()
        out = np.empty(self._count(words), EVENT_DTYPE)
        k, trig = self._run(words, out)
        if k < out.shape[0]:
            out = out[:k].copy() if k < out.shape[0] // 2 else out[:k]
        return Decoded(out, trig)

    def _feed_into(self, chunk, out: np.ndarray) -> tuple[int, np.ndarray]:
        """Decode into a caller-provided event array (len >= count_events(chunk)); for readers."""
        words = self._whole_words(chunk)
        if words.size == 0:
            return 0, np.empty(0, TRIGGER_DTYPE)
        return self._run(words, out)

    def count_events(self, chunk) -> int:
        """Upper bound of the events that the whole words of `chunk` decode to (stateless)."""
        data = as_u8(chunk, source=self.source)
        n = (data.size // self.WORD) * self.WORD
        data = data[:n]
        if data.ctypes.data % self.WORD:
            data = data.copy()
        return self._count(data.view(self.DTYPE))

    def _run(self, words, out):
        _prime_allocator()
        k, trig, d_ev, d_tr = self._decode_into(words, self._offset, out)
        self._offset += words.size * self.WORD
        if d_ev or d_tr:
            drop_warning(self.source, d_ev, d_tr, self.DROP_REASON)
        return k, trig

    def close(self) -> Decoded:
        """End of stream: raises FormatError if a partial word is left over."""
        if self._closed:
            return Decoded()
        self._closed = True
        if self._rest.size:
            raise FormatError(
                f"{self._rest.size} dangling byte(s) at the end: {self.NAME} words are {self.WORD} "
                "bytes, so the stream or file is probably truncated; cut it at a word boundary",
                source=self.source, offset=self._offset)
        return Decoded()

    def _count(self, words) -> int:  # pragma: no cover
        raise NotImplementedError

    def _decode_into(self, words, offset, out):  # pragma: no cover
        raise NotImplementedError


def concat_triggers(parts) -> np.ndarray:
    parts = [p for p in parts if p.size]
    if not parts:
        return np.empty(0, TRIGGER_DTYPE)
    return parts[0] if len(parts) == 1 else np.concatenate(parts)


_ARANGE = np.arange(1 << 20, dtype=np.int64)
_PRIMED = False


def _prime_allocator() -> None:
    """Let glibc's adaptive malloc settle on its largest recycling thresholds, once.

    The block decoders allocate a few MB of numpy temporaries per block. glibc serves
    allocations above its mmap threshold with fresh mmaps, and returns freed heap tops above
    its trim threshold to the OS, so until a large buffer has been freed in the process every
    block pays page faults for its temporaries again (about a 3x slowdown on small inputs).
    glibc raises both thresholds (to at most 32 / 64 MB) when it frees a large mmapped
    chunk, which is what allocating and freeing one untouched 31 MB array does here. This is
    the state any numpy program reaches after its first big temporary; elsewhere it is a no-op.
    """
    global _PRIMED
    if not _PRIMED:
        _PRIMED = True
        del_me = np.empty(31 << 20, np.uint8)
        del del_me


def arange(n: int) -> np.ndarray:
    """A cached 0..n-1 int64 range (read-only use)."""
    global _ARANGE
    if n > _ARANGE.shape[0]:
        _ARANGE = np.arange(max(n, 2 * _ARANGE.shape[0]), dtype=np.int64)
    return _ARANGE[:n]


def time_high_fillers(high: np.ndarray, prev_high: int | None, spacing: int):
    """Plan extra TIME_HIGH words so that a decoder can count every wrap of the time counter.

    `high` holds the full (unwrapped) time-high values of the elements that emit a TIME_HIGH,
    in stream order; `prev_high` is the value of the last TIME_HIGH already emitted (None at
    the start of a stream, which behaves as a virtual TIME_HIGH of 0 that must be made real
    when the first jump is large). Whenever the step from one TIME_HIGH to the next exceeds
    `spacing` (a quarter of the counter range), intermediate TIME_HIGH values
    prev + k * spacing are inserted so no step exceeds `spacing`.

    Returns (counts, values): counts[i] filler words precede element i; values are the full
    time-high values of all fillers, in stream order.
    """
    n = high.shape[0]
    if n == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    prev = np.empty(n, np.int64)
    prev[0] = 0 if prev_high is None else prev_high
    prev[1:] = high[:-1]
    gap = high - prev
    counts = np.where(gap > spacing, (gap - 1) // spacing, 0)
    kstart = np.ones(n, np.int64)
    if prev_high is None and gap[0] > spacing:
        counts[0] += 1          # make the virtual TIME_HIGH 0 real
        kstart[0] = 0
    total = int(counts.sum())
    if total == 0:
        return counts, np.zeros(0, np.int64)
    nz = np.flatnonzero(counts)
    owner = np.repeat(nz, counts[nz])
    first = np.cumsum(counts) - counts
    k = np.arange(total, dtype=np.int64) - first[owner] + kstart[owner]
    return counts, prev[owner] + k * spacing


ENCODE_CHUNK = 1 << 18


class ChunkedEncoder:
    """Streaming encoder for the microsecond formats (EVT 3.0 / EVT 2.0).

    Subclasses set NAME, MAX_TRIGGER_ID, WORD_DTYPE and `encode_words(us, x, y, p, tus, tid,
    tval, prev_high, carry) -> (words, prev_high, carry)`. Large inputs are encoded in chunks
    of ENCODE_CHUNK events (bounded temporaries); `carry` continues the word stream across
    chunks of one call without repeating the header words a new call starts with.
    """

    NAME = "?"
    MAX_TRIGGER_ID = 16
    WORD_DTYPE = np.dtype("<u2")

    def __init__(self, *, time_base_ns: int = 0):
        self.time_base_ns = check_time_base(time_base_ns)
        self._prev_high = None     # full time-high value of the last TIME_HIGH written
        self._last_us = None       # last time written (us after the time base)

    @staticmethod
    def encode_words(us, x, y, p, tus, tid, tval, prev_high, carry):  # pragma: no cover
        raise NotImplementedError

    def encode(self, events, triggers=None) -> bytes:
        """Encode sorted events (and triggers) that follow everything encoded before."""
        events = as_events(events, source="events")
        if events.ndim != 1:
            raise InputError(f"events: expected a 1-D event array, got shape {events.shape}")
        triggers, tus = triggers_to_us(triggers, self.time_base_ns, self.NAME,
                                       max_id=self.MAX_TRIGGER_ID)
        n = events.shape[0]
        if n == 0 and tus.shape[0] == 0:
            return b""
        saved = (self._prev_high, self._last_us)
        parts = []
        carry = None
        tr_lo = 0
        prev_t = None
        try:
            for a in range(0, max(n, 1), ENCODE_CHUNK):
                ev = events[a:a + ENCODE_CHUNK]
                us = chunk_to_us(ev, self.time_base_ns, self.NAME, index_offset=a, prev_t=prev_t)
                if a + ENCODE_CHUNK >= n:
                    tr_hi = tus.shape[0]
                else:
                    tr_hi = int(np.searchsorted(tus, us[-1], side="right"))
                tsl = slice(tr_lo, tr_hi)
                tr_lo = tr_hi
                if carry is None:
                    firsts = [int(v[0]) for v in (us, tus[tsl]) if v.shape[0]]
                    check_not_before(min(firsts), self._last_us, f"{self.NAME} encoder")
                words, self._prev_high, carry = self.encode_words(
                    us, ev["x"], ev["y"], ev["p"], tus[tsl], triggers["id"][tsl],
                    triggers["value"][tsl], self._prev_high, carry)
                parts.append(words.astype(self.WORD_DTYPE, copy=False).tobytes())
                if ev.shape[0]:
                    prev_t = ev["t"][-1]
            self._last_us = int(carry["us"])
        except BaseException:
            self._prev_high, self._last_us = saved
            raise
        return b"".join(parts)
