"""The `libcaer` and `libcaer_cmp` encodings of event_camera_msgs/EventPacket, as iniVation
cameras are recorded by libcaer_driver and decoded by event_camera_codecs.

``libcaer``: libcaer's polarity events copied as they are, 8 bytes per event, little-endian:

    u32 data       bit 0 valid, bit 1 polarity (1 = ON), bits 16-2 y (15 bits), bits 31-17 x (15 bits)
    i32 timestamp  the low 31 bits of the sensor time in microseconds

Event time (ns) = time_base + 1000 * timestamp. The driver puts the host time of the sensor's
zero plus the sensor time's high bits (above bit 31) into each packet's ``time_base``; when the
timestamp drops inside a packet, the 31-bit counter rolled over and 2**31 us are added (to
this and all later events of the packet; event_camera_codecs does the same). The valid bit is
ignored, as event_camera_codecs ignores it.

``libcaer_cmp``: a compressed stream of 16-bit little-endian tokens, code in bits 15-12:

    0 TIME_HIGH    bits 11-0 = time offset bits 23-12 (the low bits keep their value)
    1 TIME_LOW     bits 11-0 = time offset bits 11-0
    2 ADDR_X       x = bits 10-0
    3 ADDR_Y       y = bits 10-0, polarity = bit 11 -> one event at (current x, y)
    4 VECT_BASE_Y  base y = bits 10-0, vector polarity = bit 11
    5 VECT_8       bits 7-0 mask: an event at (current x, base y + i) for each set bit i, then
                   base y += 8
    6 VECT_12 and codes 7-15: ignored (event_camera_codecs' decoder ignores them)

Event time (ns) = time_base + 1000 * ((time high << 12) | time low). The time offset restarts
at 0 with every message (``next_packet``); x, base y and the vector polarity carry over, as in
event_camera_codecs. libcaer_driver sets ``time_base`` to the host time of the message's first
event. Events outside the message's width x height are dropped and counted, as the reference
decoder drops them (``dropped_out_of_geometry``).

The encoders write whole microseconds after ``time_base_ns`` (anything else is InputError;
round with quantize_to_us). Decoding and encoding are vectorised numpy (no per-event Python).
"""

from __future__ import annotations

import numpy as np

from ...errors import FormatError, InputError
from ..types import EVENT_DTYPE, TRIGGER_DTYPE, as_events, validate_events
from ._common import StreamDecoderBase, check_time_base

LIBCAER = "libcaer"
LIBCAER_CMP = "libcaer_cmp"

#: libcaer's timestamps are 31-bit microsecond counters
TS_BITS = 31
TS_PERIOD_US = 1 << TS_BITS
#: libcaer_cmp carries a 24-bit microsecond offset from the message's time_base
CMP_PERIOD_US = 1 << 24

RECORD_DTYPE = np.dtype([("data", "<u4"), ("ts", "<i4")])

# libcaer_cmp token codes
TIME_HIGH, TIME_LOW, ADDR_X, ADDR_Y, VECT_BASE_Y, VECT_8 = range(6)

_POPCOUNT8 = np.array([bin(i).count("1") for i in range(256)], np.int64)
#: _NTH_BIT[mask, k]: the position of the k-th set bit of an 8-bit mask (ascending)
_NTH_BIT = np.zeros((256, 8), np.int64)
for _m in range(256):
    _b = [i for i in range(8) if _m >> i & 1]
    _NTH_BIT[_m, :len(_b)] = _b
_LOWEST_BIT = _NTH_BIT[:, 0].copy()
_EMPTY_TRIG = np.empty(0, TRIGGER_DTYPE)


def _no_triggers(triggers, name):
    if triggers is not None and np.asarray(triggers).size:
        raise InputError(f"{name}: the {name} encoding carries no triggers; use evt3 for external triggers")


def _whole_us(events, time_base_ns: int, name: str) -> np.ndarray:
    """Microseconds after time_base_ns (int64); InputError unless whole and >= 0."""
    rel = events["t"] - np.int64(time_base_ns)
    if rel.size and int(rel[0]) < 0:
        raise InputError(f"{name}: event 0 at t={int(events['t'][0])} ns is before time_base_ns={time_base_ns}")
    us, rest = np.divmod(rel, 1000)
    if np.any(rest):
        i = int(np.flatnonzero(rest)[0])
        raise InputError(f"{name}: event {i} at t={int(events['t'][i])} ns is not a whole microsecond after "
                         f"time_base_ns={time_base_ns}; {name} carries microseconds, round first with "
                         f"evdnerf_ros.events.codecs.quantize_to_us(events, time_base_ns={time_base_ns})")
    return us


# =========================================================================== libcaer


class LibcaerDecoder(StreamDecoderBase):
    """Streaming ``libcaer`` decoder. The bytes fed between two ``next_packet`` calls (or since
    construction) are one message: a timestamp that drops adds 2**31 us."""

    WORD = 8
    DTYPE = RECORD_DTYPE
    NAME = LIBCAER

    def __init__(self, *, time_base_ns: int = 0, source: str = "<stream>", offset: int = 0):
        super().__init__(time_base_ns=time_base_ns, source=source, offset=offset)
        self._last_ts = 0        # as event_camera_codecs: only drops inside a message count
        self._wraps = 0
        self.rollovers = 0       # timestamp rollovers seen (all messages)

    def next_packet(self, time_base_ns: int) -> None:
        """Start the next message: its own time_base; the rollover count restarts."""
        self.time_base_ns = check_time_base(time_base_ns)
        self._last_ts = 0
        self._wraps = 0

    def _count(self, words) -> int:
        return int(words.shape[0])

    def _decode_into(self, words, offset, out):
        n = words.shape[0]
        o = out[:n]
        ts = words["ts"].astype(np.int64)
        if int(ts.min()) < 0:
            i = int(np.flatnonzero(ts < 0)[0])
            raise FormatError(f"libcaer event {i} has a negative timestamp {int(ts[i])}; libcaer timestamps are "
                              "31-bit counters (is this really the libcaer encoding?)", source=self.source,
                              offset=offset + 8 * i)
        drops = np.empty(n, np.int64)
        drops[0] = ts[0] < self._last_ts
        np.less(ts[1:], ts[:-1], out=drops[1:])
        wraps = np.cumsum(drops)
        wraps += self._wraps
        self.rollovers += int(wraps[-1] - self._wraps)
        self._wraps = int(wraps[-1])
        self._last_ts = int(ts[-1])
        wraps <<= TS_BITS
        ts += wraps
        ts *= 1000
        ts += self.time_base_ns
        o["t"] = ts
        d = words["data"]
        np.right_shift(d, 17, out=o["x"], casting="unsafe")          # 15 bits: fits u2 as is
        np.bitwise_and(d >> 2, 0x7FFF, out=o["y"], casting="unsafe")
        p = (d >> 1) & 1
        p <<= 1
        np.subtract(p.astype(np.int8), 1, out=o["p"])
        return n, _EMPTY_TRIG, 0, 0


class LibcaerEncoder:
    """Events -> ``libcaer`` records relative to one time base; successive calls continue one
    message (the timestamp may roll over: consecutive events must be < 2**31 us apart)."""

    def __init__(self, *, time_base_ns: int = 0):
        self.time_base_ns = check_time_base(time_base_ns)
        self._last_us = None

    def encode(self, events, triggers=None) -> bytes:
        _no_triggers(triggers, LIBCAER)
        events = validate_events(as_events(events, source="events"), source="events")
        if events.size == 0:
            return b""
        _check_xy(events, 1 << 15, LIBCAER)
        us = _whole_us(events, self.time_base_ns, LIBCAER)
        if self._last_us is not None and int(us[0]) < self._last_us:
            raise InputError(f"{LIBCAER} encoder: this chunk starts at t={int(events['t'][0])} ns, before the "
                             "previous chunk's last event; chunks must be in time order")
        prev = us[0] if self._last_us is None else self._last_us
        gaps = np.diff(us, prepend=prev)
        if int(gaps.max()) >= TS_PERIOD_US:
            i = int(np.argmax(gaps))
            raise InputError(f"{LIBCAER}: event {i} comes {int(gaps[i])} us after the one before; a 31-bit "
                             "timestamp cannot tell a gap of 2**31 us or more from a rollover: start a new packet")
        rec = np.empty(events.size, RECORD_DTYPE)
        rec["ts"] = us & (TS_PERIOD_US - 1)
        data = events["x"].astype(np.uint32) << 17
        data |= events["y"].astype(np.uint32) << 2
        data |= (events["p"] > 0).astype(np.uint32) << 1
        data |= 1                                            # valid
        rec["data"] = data
        self._last_us = int(us[-1])
        return rec.tobytes()


def _check_xy(events, limit, name):
    if events.size and (int(events["x"].max()) >= limit or int(events["y"].max()) >= limit):
        i = int(np.flatnonzero((events["x"] >= limit) | (events["y"] >= limit))[0])
        raise InputError(f"{name}: event {i} at x={int(events['x'][i])}, y={int(events['y'][i])} is beyond what "
                         f"{name} carries (x, y < {limit})")


# =========================================================================== libcaer_cmp


class LibcaerCmpDecoder(StreamDecoderBase):
    """Streaming ``libcaer_cmp`` decoder (module doc). ``width`` / ``height``: the message's
    geometry; events outside it are dropped and counted (None: keep every event)."""

    WORD = 2
    DTYPE = np.dtype("<u2")
    NAME = LIBCAER_CMP

    def __init__(self, *, time_base_ns: int = 0, source: str = "<stream>", offset: int = 0,
                 width: int | None = None, height: int | None = None):
        super().__init__(time_base_ns=time_base_ns, source=source, offset=offset)
        self.width, self.height = width, height
        self._high = 0            # time offset bits 23-12 (already shifted)
        self._low = 0
        self._x = 0               # carried across messages, as event_camera_codecs does
        self._base_y = 0
        self._vpol = 0
        self._last_t = None
        self.dropped_out_of_geometry = 0
        self.ignored_tokens = 0   # VECT_12 and unknown codes

    def next_packet(self, time_base_ns: int, width: int | None = None, height: int | None = None) -> None:
        """Start the next message: its time offset restarts at 0 from its own time_base."""
        self.time_base_ns = check_time_base(time_base_ns)
        self._high = self._low = 0
        self._last_t = None
        if width is not None:
            self.width, self.height = width, height

    def _count(self, words) -> int:
        code = words >> 12
        n_y = int(np.count_nonzero(code == ADDR_Y))
        v8 = words[code == VECT_8] & 0xFF
        return n_y + int(_POPCOUNT8[v8].sum())

    def _decode_into(self, words, offset, out):
        n = words.shape[0]
        code = (words >> 12).astype(np.int8)
        val = (words & 0x0FFF).astype(np.int32)
        is_y = code == ADDR_Y
        is_v8 = code == VECT_8
        # tokens that make events, in stream order, and how many each makes
        ev_tok = np.flatnonzero(is_y | is_v8)
        tok_v8 = is_v8[ev_tok]
        tok_val = val[ev_tok]
        counts = np.where(tok_v8, _POPCOUNT8[tok_val & 0xFF], 1)
        idx = np.arange(n, dtype=np.int32)

        at = np.append(ev_tok, n - 1)                         # event tokens, then the chunk's last token

        def last_pos(mask):
            """Index of the last token <= i with `mask` (-1: none in this chunk), for i in `at`."""
            pos = np.where(mask, idx, np.int32(-1))
            np.maximum.accumulate(pos, out=pos)
            return pos[at]

        def state_at(pos, values, initial):
            return np.where(pos >= 0, values[np.maximum(pos, 0)], initial)

        p_base = last_pos(code == VECT_BASE_Y)
        high = state_at(last_pos(code == TIME_HIGH), val.astype(np.int64) << 12, self._high)
        low = state_at(last_pos(code == TIME_LOW), val, self._low)
        x = state_at(last_pos(code == ADDR_X), val & 0x7FF, self._x)
        base_y = state_at(p_base, val & 0x7FF, self._base_y)
        vpol = state_at(p_base, val >> 11, self._vpol)
        # base y grows by 8 after every VECT_8 since the last VECT_BASE_Y (or since the chunk start)
        v8_cum = np.cumsum(is_v8, dtype=np.int32)            # VECT_8 tokens up to and including i
        v8_before = v8_cum[at] - np.append(tok_v8, False)    # ... strictly before i (the chunk end: all)
        at_base = np.where(p_base >= 0, v8_cum[np.maximum(p_base, 0)], 0)
        base_y = base_y + 8 * (v8_before - at_base)
        # state for the next chunk: the values after the chunk's last token
        self._high, self._low, self._x, self._vpol = int(high[-1]), int(low[-1]), int(x[-1]), int(vpol[-1])
        self._base_y = int(base_y[-1])
        high, low, x, base_y, vpol = high[:-1], low[:-1], x[:-1], base_y[:-1], vpol[:-1]

        total = int(counts.sum())
        t_tok = (high | low) * 1000 + self.time_base_ns
        y_tok = np.where(tok_v8, base_y, tok_val & 0x7FF)
        p_tok = np.where(tok_v8, vpol, tok_val >> 11)
        if total == counts.size and (counts.size == 0 or int(counts.min()) == 1):  # one event per token
            vrows = np.flatnonzero(tok_v8)
            if vrows.size:
                y_tok[vrows] += _LOWEST_BIT[tok_val[vrows] & 0xFF]
            src = None
        else:
            src = np.repeat(np.arange(counts.size), counts)  # event -> its token
            first = np.cumsum(counts) - counts
            sub = np.arange(total) - first[src]              # rank of the event within its token
            vrows = tok_v8[src]
            bit = _NTH_BIT[tok_val[src[vrows]] & 0xFF, sub[vrows]]
        ev = np.empty(total, EVENT_DTYPE)
        if src is None:
            ev["t"], ev["x"], ev["y"] = t_tok, x, y_tok
            ev["p"] = 2 * p_tok - 1
        else:
            y = y_tok[src]
            y[vrows] += bit
            ev["t"], ev["x"], ev["y"] = t_tok[src], x[src], y
            ev["p"] = 2 * p_tok[src] - 1
        self.ignored_tokens += int(np.count_nonzero(code > VECT_8))
        if total:
            t = ev["t"]
            prev = self._last_t
            back = np.flatnonzero(t[1:] < t[:-1])
            if (prev is not None and int(t[0]) < prev) or back.size:
                j = 0 if prev is not None and int(t[0]) < prev else int(back[0]) + 1
                raise FormatError(f"libcaer_cmp event {j} of this chunk goes back in time (offset "
                                  f"{(int(t[j]) - self.time_base_ns) // 1000} us); the stream is damaged",
                                  source=self.source, offset=offset)
            self._last_t = int(t[-1])
            if self.width is not None and self.height is not None:
                keep = (ev["x"] < self.width) & (ev["y"] < self.height)
                if not keep.all():
                    self.dropped_out_of_geometry += int(total - np.count_nonzero(keep))
                    ev = ev[keep]
        k = ev.size
        out[:k] = ev
        return k, _EMPTY_TRIG, 0, 0


class LibcaerCmpEncoder:
    """Events -> ``libcaer_cmp`` tokens relative to one time base (one message: offsets must stay
    below 2**24 us). Successive calls continue the message; the first call starts with ADDR_X.

    Events of equal time, x and polarity whose y share the upper bits (y & ~7) become one
    VECT_8 token when their low bits increase; any other event becomes an ADDR_Y, so decoding
    gives back the same events in the same order."""

    def __init__(self, *, time_base_ns: int = 0):
        self.time_base_ns = check_time_base(time_base_ns)
        self._state = None        # (high, low, x, last us) after the previous call

    def encode(self, events, triggers=None) -> bytes:
        _no_triggers(triggers, LIBCAER_CMP)
        events = validate_events(as_events(events, source="events"), source="events")
        n = events.size
        if n == 0:
            return b""
        _check_xy(events, 1 << 11, LIBCAER_CMP)
        us = _whole_us(events, self.time_base_ns, LIBCAER_CMP)
        if int(us[-1]) >= CMP_PERIOD_US:
            i = int(np.flatnonzero(us >= CMP_PERIOD_US)[0])
            raise InputError(f"{LIBCAER_CMP}: event {i} is {int(us[i])} us after the message's time_base; "
                             "libcaer_cmp carries 24-bit offsets (16.7 s): use shorter packets")
        if self._state is not None and int(us[0]) < self._state[3]:
            raise InputError(f"{LIBCAER_CMP} encoder: this chunk starts before the previous chunk's last event; "
                             "chunks must be in time order")
        high = us & ~np.int64(0xFFF)
        low = us & 0xFFF
        x = events["x"].astype(np.int64)
        y = events["y"].astype(np.int64)
        pol = (events["p"] > 0).astype(np.int64)
        yh, yl = y & ~np.int64(7), y & 7
        # groups: runs of equal (time, x, polarity, y & ~7) with strictly increasing y & 7
        new = np.ones(n, bool)
        new[1:] = ((us[1:] != us[:-1]) | (x[1:] != x[:-1]) | (pol[1:] != pol[:-1]) | (yh[1:] != yh[:-1])
                   | (yl[1:] <= yl[:-1]))
        g = np.flatnonzero(new)
        ng = g.size
        mask = np.bitwise_or.reduceat(np.int64(1) << yl, g)
        single = _POPCOUNT8[mask] == 1
        gh, gl, gx = high[g], low[g], x[g]
        prev_h, prev_l, prev_x = (0, 0, -1) if self._state is None else self._state[:3]
        th = np.empty(ng, bool)
        th[0] = gh[0] != prev_h
        th[1:] = gh[1:] != gh[:-1]
        tl = np.empty(ng, bool)
        tl[0] = gl[0] != prev_l
        tl[1:] = gl[1:] != gl[:-1]
        ax = np.empty(ng, bool)
        ax[0] = gx[0] != prev_x
        ax[1:] = gx[1:] != gx[:-1]
        ntok = th.astype(np.int64) + tl + ax + np.where(single, 1, 2)
        pos = np.cumsum(ntok) - ntok
        words = np.empty(int(ntok.sum()), np.uint16)
        p = pos.copy()
        for flag, value in ((th, (TIME_HIGH << 12) | (gh >> 12)), (tl, (TIME_LOW << 12) | gl),
                            (ax, (ADDR_X << 12) | gx)):
            words[p[flag]] = value[flag]
            p += flag
        gp, gyh, gy = pol[g], yh[g], y[g]
        words[p[single]] = ((ADDR_Y << 12) | (gp << 11) | gy)[single]
        vec = ~single
        words[p[vec]] = ((VECT_BASE_Y << 12) | (gp << 11) | gyh)[vec]
        words[p[vec] + 1] = ((VECT_8 << 12) | mask)[vec]
        self._state = (int(gh[-1]), int(gl[-1]), int(gx[-1]), int(us[-1]))
        return words.astype("<u2", copy=False).tobytes()
