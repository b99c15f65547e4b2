"""Shared pieces of the event codecs: the Decoded record, byte-buffer handling, input
validation, the streaming-decoder skeleton (left-over bytes, byte offsets, warnings) and the
numba kernel decorator.

The per-event work of the EVT codecs (decoding words, validating and encoding events) runs
in numba-compiled kernels (`kernel`): plain loops compiled to machine code, called once per
chunk. Kernels never raise: they report an error code and a position, and the Python side
raises the error with its message and byte offset. Python code never loops over events.
"""

from __future__ import annotations

import abc

import warnings
from dataclasses import dataclass, field

import numba
import numpy as np

from ...errors import FormatError, InputError
from ..types import EVENT_DTYPE, TRIGGER_DTYPE, as_events

_EMPTY_U8 = np.empty(0, np.uint8)


class DroppedEventsWarning(UserWarning):
    """Events or triggers were discarded because the stream gave no valid time (or row) yet."""


class TruncatedStreamWarning(UserWarning):
    """A file ended inside a word (a recording killed mid-write): every complete word was read."""


@dataclass
class Decoded:
    """Result of decoding a byte stream: events (EVENT_DTYPE) and external triggers (TRIGGER_DTYPE)."""

    events: np.ndarray = field(default_factory=lambda: np.empty(0, EVENT_DTYPE))
    triggers: np.ndarray = field(default_factory=lambda: np.empty(0, TRIGGER_DTYPE))
    # harmless time-word anomalies the decoder tolerated, by kind (EVT 3.0: see evt3.py)
    anomalies: dict = field(default_factory=dict)

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


def kernel(fn):
    """`@numba.njit(cache=True, nogil=True)`: compile `fn` on its first call, once per machine.

    The machine code is cached in the __pycache__ folder next to the module (numba falls back
    to its user-wide cache folder where that is read-only), so later processes load it in
    milliseconds. Where no cache folder is writable at all, numba refuses cache=True; the
    kernel then compiles once per process instead of failing at import.
    """
    try:
        return numba.njit(cache=True, nogil=True)(fn)
    except RuntimeError:       # "cannot cache function ...: no locator available"
        return numba.njit(nogil=True)(fn)


def readonly(a: np.ndarray) -> np.ndarray:
    """A read-only C-contiguous view (a copy only if `a` is not contiguous).

    Kernels compile one specialisation per argument type, and numpy arrays differ in type
    by writeability (e.g. np.frombuffer of bytes is read-only): passing every input as a
    read-only view keeps it to one compilation per kernel.
    """
    v = np.ascontiguousarray(a).view()
    v.flags.writeable = False
    return v


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


#: EVT 3.0 time is 24 bits of microseconds: a sensor clock's first period.
SENSOR_PERIOD_US = 1 << 24
#: Origins chosen by sensor_origin_ns are multiples of this: one EVT 3.0 TIME_HIGH unit, and
#: a multiple of EVT 2.0's (64 us), so the low time bits stay those of the absolute time.
ORIGIN_STEP_US = 4096


def sensor_origin_ns(first_ns) -> int:
    """The time origin (ns) for writing a stream whose first event or trigger is at `first_ns`,
    so that its sensor times start near zero whatever the date.

    An EVT stream counts time from its sensor clock's zero: a first time far from the time
    base costs one TIME_HIGH word per 2**22 us in between (hundreds of MB for an epoch time
    in 2023). Times already inside the first 2**24 us period are sensor times and keep origin
    0 (they are written as they are); any other time gets the origin `first_ns` rounded down
    to a whole multiple of 4096 us, so the stream's first sensor time is below 4096 us.
    The origin is a whole microsecond, so whole-microsecond times stay whole microseconds.
    """
    first_ns = int(first_ns)
    if 0 <= first_ns < SENSOR_PERIOD_US * 1000:
        return 0
    step = ORIGIN_STEP_US * 1000
    return first_ns // step * step


def check_time_base(time_base_ns) -> int:
    if isinstance(time_base_ns, (bool, float)) or not isinstance(time_base_ns, (int, np.integer)):
        raise InputError(f"time_base_ns must be an integer number of nanoseconds, got {time_base_ns!r}")
    if abs(int(time_base_ns)) >= TIME_BASE_LIMIT:
        raise InputError(f"time_base_ns={time_base_ns} is out of range (|value| < 2**62 ns)")
    return int(time_base_ns)


def chunk_to_us(events, time_base_ns: int, encoding: str, *, index_offset: int = 0,
                prev_t=None, max_x: int = 2048, max_y: int = 2048,
                source: str = "events", keep_us: bool = True) -> np.ndarray | None:
    """Validate one chunk of EVENT_DTYPE events for a microsecond format; return its times in
    us after time_base_ns (None with keep_us=False: validation only, which is faster).
    `index_offset` / `prev_t` place the chunk inside a larger array (for error messages and
    the sort check across chunk boundaries).

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
    us = np.empty(n if keep_us else 0, np.int64)
    bad_sort, bad_p, bad_x, bad_y, before, bad_rem = _scan_us(
        readonly(events), np.int64(time_base_ns), max_x, max_y, us)
    if bad_sort >= 0:
        i = bad_sort
        raise InputError(f"{source}: timestamps not sorted: event {index_offset + i} at t={int(t[i])} ns "
                         f"comes after t={int(t[i - 1])} ns; sort by t (np.argsort(t, kind='stable')) "
                         "first")
    if bad_p >= 0:
        i = bad_p
        raise InputError(f"{source}: event {index_offset + i} has polarity {int(events['p'][i])}; "
                         "polarity must be +1 or -1")
    for axis, limit, i in (("x", max_x, bad_x), ("y", max_y, bad_y)):
        if i >= 0:
            raise InputError(f"{source}: event {index_offset + i} has {axis}={int(events[axis][i])}, "
                             f"but {encoding} carries {axis} < {limit}; crop or remap the "
                             "coordinates first")
    if before:
        raise InputError(f"{source}: event {index_offset} at t={int(t[0])} ns is before time_base_ns="
                         f"{time_base_ns}; {encoding} times are offsets from the time base, "
                         "choose a time base at or before the first event")
    if bad_rem >= 0:
        i = bad_rem
        raise InputError(
            f"{source}: event {index_offset + i} at t={int(t[i])} ns is not a whole microsecond after "
            f"time_base_ns={time_base_ns}; {encoding} carries microseconds, so round explicitly "
            "first, e.g. evdnerf_ros.events.codecs.quantize_to_us(events, time_base_ns=...)")
    return us if keep_us else None


# whole-microsecond test without a division: 1000 = 8 * 125, and for odd 125 a 64-bit value r
# is a multiple iff r * 125**-1 (mod 2**64) <= (2**64 - 1) // 125
_INV125 = pow(125, -1, 1 << 64)
_LIM125 = ((1 << 64) - 1) // 125


@kernel
def _scan_us(ev, base, max_x, max_y, us):
    """One pass over EVENT_DTYPE records (at least one): us[i] = (t - base) // 1000 when `us`
    has room, else validation only. Returns the first index (-1 if none) where time goes
    backwards, polarity is not +-1, x >= max_x, y >= max_y, then whether the first event is
    before `base`, and the first index where t - base is not a whole microsecond.

    The pass only ORs problem flags together (branch-free); a second, exact pass that finds
    the first index of each problem runs only when some flag is set, i.e. before an error.
    """
    n = ev.shape[0]
    store = us.shape[0] == n
    flags = 0
    prev = ev[0].t
    for i in range(n):
        e = ev[i]
        t = e.t
        p = np.int64(e.p)
        rel = t - base
        r = np.uint64(rel)
        if store:
            q = np.int64(r // np.uint64(1000))               # exact for rel >= 0
            us[i] = q
            odd = rel != q * 1000
        else:
            odd = (((r & np.uint64(7)) != np.uint64(0))
                   | ((r >> np.uint64(3)) * np.uint64(_INV125) > np.uint64(_LIM125)))
        flags |= (np.int64(t < prev) | np.int64(p * p != 1) | np.int64(e.x >= max_x)
                  | np.int64(e.y >= max_y) | np.int64(odd) | np.int64(rel < 0))
        prev = t
    before = ev[0].t - base < 0
    bad_sort = bad_p = bad_x = bad_y = bad_rem = -1
    if flags == 0:
        return bad_sort, bad_p, bad_x, bad_y, before, bad_rem
    prev = ev[0].t
    for i in range(n):
        e = ev[i]
        t = e.t
        if t < prev and bad_sort < 0:
            bad_sort = i
        prev = t
        if e.p != 1 and e.p != -1 and bad_p < 0:
            bad_p = i
        if e.x >= max_x and bad_x < 0:
            bad_x = i
        if e.y >= max_y and bad_y < 0:
            bad_y = i
        rel = t - base
        q = rel // 1000                                      # floor, like numpy
        if store:
            us[i] = q
        if rel != q * 1000 and bad_rem < 0:
            bad_rem = i
    return bad_sort, bad_p, bad_x, bad_y, before, bad_rem


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
                    max_y=max_y, source=source, keep_us=False)
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


class StreamDecoderBase(abc.ABC):
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

    def close(self, *, strict: bool = True) -> Decoded:
        """End of stream. A partial word left over raises FormatError (``strict``) or, for a file
        cut mid-word as a killed recording ends, is dropped with a TruncatedStreamWarning naming
        its byte offset (every complete word was decoded)."""
        if self._closed:
            return Decoded()
        self._closed = True
        if self._rest.size:
            if not strict:
                warnings.warn(f"{self.source}: ends inside a {self.WORD}-byte {self.NAME} word at byte {self._offset} "
                              f"({self._rest.size} byte(s) dropped; every complete word was read): the recording "
                              "was cut", TruncatedStreamWarning, stacklevel=3)
                return Decoded()
            raise FormatError(
                f"{self._rest.size} dangling byte(s) at the end: {self.NAME} words are {self.WORD} "
                "bytes, so the stream or file is probably truncated; cut it at a word boundary "
                "(without --strict, a file's complete words are read)",
                source=self.source, offset=self._offset)
        return Decoded()

    @abc.abstractmethod
    def _count(self, words) -> int:
        ...

    @abc.abstractmethod
    def _decode_into(self, words, offset, out):
        ...


def run_decode_kernel(kern, words, out, state, report, trig_cap: int = 256):
    """Run a word decoder kernel over `words`, resuming it whenever its trigger buffer fills.

    `kern(w, start, out, k, trig, state, report) -> (next word, events written, triggers
    written)` decodes from word `start`, writing events to out[k:] and triggers to `trig`,
    and stops early at a trigger that does not fit (or, with report[0] set, at an error).
    The trigger buffer comes from here rather than growing inside the kernel: an array
    variable reassigned in a loop costs numba reference counting on every iteration.
    Returns (events written, TRIGGER_DTYPE triggers).
    """
    w = readonly(words)
    n = w.shape[0]
    start = k = 0
    parts = []
    while True:
        trig = np.empty(trig_cap, TRIGGER_DTYPE)
        start, k, ntr = kern(w, start, out, k, trig, state, report)
        if ntr:
            parts.append(trig[:ntr])
        if report[0] or start >= n:
            return int(k), concat_triggers(parts)
        trig_cap *= 4


def concat_triggers(parts) -> np.ndarray:
    parts = [p for p in parts if p.size]
    if not parts:
        return np.empty(0, TRIGGER_DTYPE)
    return parts[0] if len(parts) == 1 else np.concatenate(parts)


_PRIMED = False


def _prime_allocator() -> None:
    """Let glibc's adaptive malloc settle on its largest recycling thresholds, once.

    The numpy block decoders (mono) allocate a few MB of numpy temporaries per block. glibc serves
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


ENCODE_CHUNK = 1 << 18


class ChunkedEncoder(abc.ABC):
    """Streaming encoder for the microsecond formats (EVT 3.0 / EVT 2.0).

    Subclasses set NAME, MAX_TRIGGER_ID, WORD_DTYPE and `encode_words(us, events, tus,
    triggers, prev_high, carry) -> (words, prev_high, carry)`. Large inputs are encoded in
    chunks of ENCODE_CHUNK events (bounded temporaries); `carry` continues the word stream
    across chunks of one call without repeating the header words a new call starts with.

    The stream counts time from time_base_ns, and every 2**24 us (EVT 3.0) or 2**34 us (EVT
    2.0) wrap since then takes TIME_HIGH words: for absolute (epoch) times choose a time base
    near the first event, e.g. sensor_origin_ns(first time), as io/raw.py does.
    """

    NAME = "?"
    MAX_TRIGGER_ID = 16
    WORD_DTYPE = np.dtype("<u2")

    def __init__(self, *, time_base_ns: int = 0):
        self.time_base_ns = check_time_base(time_base_ns)
        self._prev_high = None     # full time-high value of the last TIME_HIGH written
        self._last_us = None       # last time written (us after the time base)

    @staticmethod
    @abc.abstractmethod
    def encode_words(us, events, tus, triggers, prev_high, carry):
        ...

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
                    us, ev, tus[tsl], triggers[tsl], self._prev_high, carry)
                parts.append(words.astype(self.WORD_DTYPE, copy=False))
                if ev.shape[0]:
                    prev_t = ev["t"][-1]
            self._last_us = int(carry["us"])
        except BaseException:
            self._prev_high, self._last_us = saved
            raise
        return b"".join(parts)           # one copy: join reads the arrays' buffers directly
