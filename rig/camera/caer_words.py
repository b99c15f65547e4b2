"""The iniVation DVXplorer USB data words (libcaer's ``dvxplorer.c`` event translator), both ways.

A DVXplorer sends 16-bit little-endian words on bulk IN 0x82:

=================  ===========================================================================
``1ttt tttt tttt tttt``  timestamp: time (us) = wrap base + the 15 low bits
``0 000 dddd dddd dddd`` special, by data: 1 timestamp reset (time and wrap base back to 0);
                   2 / 3 / 4 external input falling edge / rising edge / pulse; 16 / 17
                   external generator falling / rising edge; 5 / 7 IMU sample start / end
``0 001 s.xx xxxx xxxx`` column address x = bits 9-0 (bit 11: start-of-frame marker)
``0 010 .... pmmm mmmm`` 8-pixel group 2: an event at (x, y2 + i) for each set bit i of the
                   mask (bits 7-0); polarity bit 8: 0 = ON, 1 = OFF
``0 011 .... pmmm mmmm`` 8-pixel group 1: the same from y1
``0 100 sooo oogg gggg`` group addresses: y1 = 8 * g (bits 5-0), y2 = 8 * (g -/+ o) (offset
                   bits 10-6, subtracted when bit 11 is set)
``0 101 cccc dddd dddd`` misc 8-bit data (IMU samples, IMU scale config)
``0 111 dddd dddd dddd`` timestamp wrap: wrap base += data * 2**15 us (time = the new base)
=================  ===========================================================================

Column and group addresses outside the sensor (columns >= its width, groups >= its height) are
skipped and the previous address kept, as libcaer does (counted in ``bad_addresses``). IMU words
are skipped (counted in ``imu_words``). External input / generator events become triggers
(TRIGGER_DTYPE): ``id`` :data:`TRIGGER_EDGE` (value 1 rising, 0 falling), :data:`TRIGGER_PULSE`
(value 1) or :data:`TRIGGER_GENERATOR` (value 1 rising, 0 falling).

Times: int64 ns = 1000 * the sensor's microseconds from its zero (the last timestamp reset),
unwrapped without limit (libcaer folds it into a 31-bit counter plus an overflow count; here it
is simply int64). A timestamp reset makes the time restart at 0 (``resets`` counts them).

The order of events on the wire, which :func:`canonical_order` gives and the encoder writes:
by time, then column x, then group (y // 8), then polarity (ON first), then y. Decoding
what :func:`encode_caer_words` wrote gives back ``canonical_order(events)`` bit for bit.

Both directions are numba kernels (no Python per event). The decoder makes two passes per chunk,
a sizing pass (two table lookups per word: the exact event and trigger counts) and the decoding
pass, and carries its state (time, wrap base, addresses and an odd trailing byte) across any
chunk split. The encoder makes one pass.
"""

from __future__ import annotations

import numpy as np

from evdnerf_ros.errors import InputError
from evdnerf_ros.events.codecs._common import as_u8, kernel, readonly
from evdnerf_ros.events.types import EVENT_DTYPE, TRIGGER_DTYPE

__all__ = [
    "MODELS", "TRIGGER_EDGE", "TRIGGER_PULSE", "TRIGGER_GENERATOR", "CaerWordDecoder", "CaerWordEncoder",
    "canonical_order", "decode_caer_words", "encode_caer_words",
]

#: Models whose USB words this codec speaks, with their sensor size (columns, rows).
MODELS = {"DVXplorer": (640, 480), "DVXplorerLite": (320, 240)}

#: TRIGGER_DTYPE ids: external input edges (value 1 rising, 0 falling) ...
TRIGGER_EDGE = 0
#: ... external input pulses (value 1) ...
TRIGGER_PULSE = 1
#: ... and the external signal generator's edges (value 1 rising, 0 falling).
TRIGGER_GENERATOR = 2

TS_WRAP_US = 1 << 15

# special-event data values (code 0)
SPECIAL_TS_RESET = 1
SPECIAL_EXT_FALLING = 2
SPECIAL_EXT_RISING = 3
SPECIAL_EXT_PULSE = 4
SPECIAL_IMU_START = 5
SPECIAL_IMU_END = 7
SPECIAL_GEN_FALLING = 16
SPECIAL_GEN_RISING = 17

# decoder state slots (_S_PEND: the low byte of a word split across chunks, -1: none)
_S_WRAP, _S_CUR, _S_X, _S_YG1, _S_YG2 = range(5)
_S_RESETS, _S_BAD_ADDR, _S_IMU, _S_UNKNOWN, _S_WORDS, _S_PEND = range(5, 11)
_NSTATE = 11

_EMPTY_EV = np.empty(0, EVENT_DTYPE)
_EMPTY_TR = np.empty(0, TRIGGER_DTYPE)


def _check_model(model: str, width, height, invert_xy: bool = False):
    if model not in MODELS:
        raise InputError(f"caer words: unknown model {model!r}; supported models are {', '.join(MODELS)}")
    cols, rows = MODELS[model]
    if invert_xy:
        cols, rows = rows, cols
    width = cols if width is None else int(width)
    height = rows if height is None else int(height)
    sensor_w, sensor_h = (height, width) if invert_xy else (width, height)
    if not (0 < sensor_w <= 1024 and 0 < sensor_h <= 512):
        raise InputError(f"caer words: {model} geometry {width}x{height} is beyond what the words carry "
                         "(columns <= 1024 in 10 bits, rows <= 512 in 64 groups of 8)")
    return width, height


# =========================================================================== decoding


# Sizing tables: a word's events are the set bits of its low byte when its high byte is a mask
# word's (codes 2 and 3): two lookups per word and no branch to mispredict (vectorised
# arithmetic popcounts and a 64 K-entry word table measured slower).
_POP8 = np.array([bin(i).count("1") for i in range(256)], np.uint8)
_MASK_HI = np.array([0xFF if (h >> 5) == 1 else 0 for h in range(256)], np.uint8)
# the lowest set bit of each mask byte: the mask loop takes one set bit per step
_LOW_BIT = np.array([(i & -i).bit_length() - 1 if i else 0 for i in range(256)], np.uint8)


@kernel
def _count(b):
    """(events, triggers) the words of the bytes b decode to, exactly (a bad address is
    skipped, but the mask words after it still give their events)."""
    pop = _POP8
    sel = _MASK_HI
    nev = 0
    ntr = 0
    for i in range(b.shape[0] >> 1):
        lo = b[2 * i]
        hi = b[2 * i + 1]
        nev += pop[lo & sel[hi]]
        if hi < 0x10:                           # specials: rare, so this branch costs nothing
            d = np.int64(lo) | (np.int64(hi) << 8)
            if d == 2 or d == 3 or d == 4 or d == 16 or d == 17:
                ntr += 1
    return nev, ntr


@kernel
def _decode(b, st, ev, tr, cols, rows, invert):
    """Decode the words of the bytes b into ev (EVENT_DTYPE) / tr (TRIGGER_DTYPE) with state st;
    an odd last byte is kept in the state. Returns (events, triggers)."""
    low = _LOW_BIT
    wrap = st[_S_WRAP]
    cur = st[_S_CUR]
    lx = st[_S_X]
    yg1 = st[_S_YG1]
    yg2 = st[_S_YG2]
    resets = st[_S_RESETS]
    bad = st[_S_BAD_ADDR]
    imu = st[_S_IMU]
    unknown = st[_S_UNKNOWN]
    nb = b.shape[0]
    n = nb >> 1
    t = cur * 1000
    k = 0
    kt = 0
    for i in range(n):
        v = np.int64(b[2 * i]) | (np.int64(b[2 * i + 1]) << 8)
        if v & 0x8000:
            cur = wrap + (v & 0x7FFF)
            t = cur * 1000
            continue
        code = v >> 12
        d = v & 0xFFF
        if (code >> 1) == 1:                    # 8-pixel group: codes 2 (from y2) and 3 (from y1)
            m = d & 0xFF
            base = yg1 if code == 3 else yg2
            p = np.int8(1 - ((d >> 7) & 2))     # bit 8: 0 = ON (+1), 1 = OFF (-1)
            while m:                            # one step per set bit (mostly one per word)
                y = base + low[m]
                m &= m - 1
                e = ev[k]
                e.t = t
                if invert:
                    e.x = y
                    e.y = lx
                else:
                    e.x = lx
                    e.y = y
                e.p = p
                k += 1
        elif code == 4:
            g1 = d & 0x3F
            off = (d >> 6) & 0x1F
            g2 = g1 - off if d & 0x800 else g1 + off
            if g1 * 8 >= rows or g2 < 0 or g2 * 8 >= rows:
                bad += 1
            else:
                yg1 = g1 * 8
                yg2 = g2 * 8
        elif code == 1:
            x = d & 0x3FF
            if x >= cols:
                bad += 1
            else:
                lx = x
        elif code == 7:
            wrap += d * 32768
            cur = wrap
            t = cur * 1000
        elif code == 0:
            if d == 1:
                wrap = 0
                cur = 0
                t = 0
                resets += 1
            elif d == 2 or d == 3 or d == 4 or d == 16 or d == 17:
                r = tr[kt]
                r.t = t
                if d >= 16:
                    r.id = 2
                    r.value = d - 16
                elif d == 4:
                    r.id = 1
                    r.value = 1
                else:
                    r.id = 0
                    r.value = d - 2
                kt += 1
            elif d == 5 or d == 7:
                imu += 1
            else:
                unknown += 1
        elif code == 5:
            imu += 1
        else:
            unknown += 1
    st[_S_WRAP] = wrap
    st[_S_CUR] = cur
    st[_S_X] = lx
    st[_S_YG1] = yg1
    st[_S_YG2] = yg2
    st[_S_RESETS] = resets
    st[_S_BAD_ADDR] = bad
    st[_S_IMU] = imu
    st[_S_UNKNOWN] = unknown
    st[_S_WORDS] += n
    # an odd byte left over is the low byte of the next chunk's first word
    st[_S_PEND] = b[nb - 1] if nb & 1 else -1
    return k, kt


class CaerWordDecoder:
    """Streaming decoder of DVXplorer USB words: ``feed(data) -> (events, triggers)``.

    ``width`` / ``height``: the output geometry (default: the model's sensor); with
    ``invert_xy`` (the sensor's orientation info bit 2) x and y are swapped on output, as libcaer
    does, and addresses are checked against the sensor's own columns / rows (height / width).
    Any chunk boundary is fine, even inside a word (the odd byte waits for the next chunk)."""

    def __init__(self, width: int | None = None, height: int | None = None, model: str = "DVXplorer", *,
                 invert_xy: bool = False):
        self.model = model
        self.invert_xy = bool(invert_xy)
        self.width, self.height = _check_model(model, width, height, self.invert_xy)
        self._cols, self._rows = (self.height, self.width) if self.invert_xy else (self.width, self.height)
        self._st = np.zeros(_NSTATE, np.int64)
        self._st[_S_PEND] = -1

    # counters -------------------------------------------------------------------------
    @property
    def time_us(self) -> int:
        """The sensor time (us from its zero) after the last whole word decoded."""
        return int(self._st[_S_CUR])

    @property
    def resets(self) -> int:
        return int(self._st[_S_RESETS])

    @property
    def bad_addresses(self) -> int:
        """Column / group addresses outside the sensor that were skipped (libcaer logs them)."""
        return int(self._st[_S_BAD_ADDR])

    @property
    def imu_words(self) -> int:
        return int(self._st[_S_IMU])

    @property
    def unknown_words(self) -> int:
        """Words of reserved codes / special values (libcaer logs and ignores them)."""
        return int(self._st[_S_UNKNOWN])

    @property
    def words(self) -> int:
        return int(self._st[_S_WORDS])

    @property
    def pending_bytes(self) -> int:
        """Bytes of a partial word kept for the next feed (0 or 1)."""
        return int(self._st[_S_PEND] >= 0)

    # decoding -------------------------------------------------------------------------
    def feed(self, data) -> tuple[np.ndarray, np.ndarray]:
        """Decode the whole words of ``data`` (after any byte left over from the previous call)."""
        u8 = as_u8(data, source=f"{self.model} USB data")
        pend = self._st[_S_PEND]
        if pend >= 0:                   # a word split by the last chunk: rare (USB sends whole words)
            u8 = np.concatenate([np.array([pend], np.uint8), u8])
        if u8.size == 0:
            return _EMPTY_EV, _EMPTY_TR
        if u8.flags.writeable:          # one kernel specialisation: read-only bytes
            u8 = readonly(u8)
        nev, ntr = _count(u8)
        ev = np.empty(nev, EVENT_DTYPE)
        tr = np.empty(ntr, TRIGGER_DTYPE)
        k, kt = _decode(u8, self._st, ev, tr, self._cols, self._rows, self.invert_xy)
        if k != nev or kt != ntr:       # cannot happen: _count is exact
            raise RuntimeError(f"caer word decoder: sized {nev} events / {ntr} triggers, decoded {k} / {kt}")
        return ev, tr


def decode_caer_words(data, width: int | None = None, height: int | None = None, model: str = "DVXplorer",
                      *, invert_xy: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Decode a whole byte stream from its start (a trailing odd byte is ignored, as libcaer does)."""
    return CaerWordDecoder(width, height, model, invert_xy=invert_xy).feed(data)


# =========================================================================== encoding


def canonical_order(events) -> np.ndarray:
    """The events as a DVXplorer's words carry them (module doc): in wire order, and with
    repeats of one (microsecond, pixel, polarity) collapsed into one event (a pixel's bit in a
    group mask is set once per readout)."""
    ev = np.asarray(events)
    if ev.dtype != EVENT_DTYPE:
        raise InputError(f"caer words: events must have dtype {EVENT_DTYPE}, got {ev.dtype}")
    if ev.size < 2:
        return ev.copy()
    key = _order_key(ev)
    if not np.all(key[1:] >= key[:-1]):
        order = np.argsort(key, kind="stable")
        ev, key = ev[order], key[order]
    else:
        ev = ev.copy()
    same = key[1:] == key[:-1]
    if same.any():
        ev = ev[np.concatenate(([True], ~same))]
    return ev


def _order_key(ev):
    t = ev["t"] // 1000
    t = t - t[0]
    y = ev["y"].astype(np.int64)
    return ((t << 26) | (ev["x"].astype(np.int64) << 16) | ((y >> 3) << 8)
            | ((ev["p"] < 0).astype(np.int64) << 7) | (y & 7))


@kernel
def _encode(us, x, y, off, tus, tcode, st, buf):
    """Words for events (canonical order; us, x, y, off = polarity bit) and triggers (tus, tcode =
    special data), triggers first within their microsecond. st = [wrap base us, current us];
    returns the number of words written to buf (-1: buf too short)."""
    cap = buf.shape[0]
    n = us.shape[0]
    nt = tus.shape[0]
    wrap = st[0]
    cur = st[1]
    pos = 0
    i = 0
    ti = 0
    while i < n or ti < nt:
        if ti < nt and (i >= n or tus[ti] <= us[i]):
            t = tus[ti]
        else:
            t = us[i]
        # clock: wrap words up to t's 2**15 us period, then a timestamp word if needed
        hi = t >> 15
        while (wrap >> 15) < hi:                   # one wrap word per period, as the camera
            if pos >= cap:
                return -1
            buf[pos] = 0x7001
            pos += 1
            wrap += 32768
            cur = wrap
        if cur != t:
            if pos >= cap:
                return -1
            buf[pos] = 0x8000 | (t & 0x7FFF)
            pos += 1
            cur = t
        while ti < nt and tus[ti] == t:
            if pos >= cap:
                return -1
            buf[pos] = tcode[ti]
            pos += 1
            ti += 1
        # the events of this microsecond, column by column
        while i < n and us[i] == t:
            cx = x[i]
            if pos >= cap:
                return -1
            buf[pos] = 0x1000 | cx
            pos += 1
            # slots (group, polarity) of this column, paired two per address word
            while i < n and us[i] == t and x[i] == cx:
                g1 = y[i] >> 3
                p1 = off[i]
                m1 = 0
                while i < n and us[i] == t and x[i] == cx and (y[i] >> 3) == g1 and off[i] == p1:
                    m1 |= 1 << (y[i] & 7)
                    i += 1
                has2 = False
                g2 = g1
                p2 = 0
                m2 = 0
                j = i
                if j < n and us[j] == t and x[j] == cx:
                    g = y[j] >> 3
                    if g - g1 < 32:
                        has2 = True
                        g2 = g
                        p2 = off[j]
                        while j < n and us[j] == t and x[j] == cx and (y[j] >> 3) == g2 and off[j] == p2:
                            m2 |= 1 << (y[j] & 7)
                            j += 1
                        i = j
                if pos + 3 > cap:
                    return -1
                buf[pos] = 0x4000 | ((g2 - g1) << 6) | g1
                buf[pos + 1] = 0x3000 | (p1 << 8) | m1
                pos += 2
                if has2:
                    buf[pos] = 0x2000 | (p2 << 8) | m2
                    pos += 1
    st[0] = wrap
    st[1] = cur
    return pos


@kernel
def _advance(until, st, buf):
    """Wrap words so that the stream's clock reaches until's 2**15 us period; returns words."""
    wrap = st[0]
    pos = 0
    hi = until >> 15
    while (wrap >> 15) < hi and pos < buf.shape[0]:
        buf[pos] = 0x7001
        pos += 1
        wrap += 32768
        st[1] = wrap
    st[0] = wrap
    return pos


class CaerWordEncoder:
    """Events (sensor time, whole microseconds from the sensor's zero) -> DVXplorer USB words.

    Successive ``encode`` calls continue one stream (times must not go back). Events are
    written in :func:`canonical_order`; within a column, consecutive (group, polarity) slots
    share a group-address word when their groups are less than 32 apart, as the sensor's
    MGROUP compression does. ``advance(until_us)`` writes the timestamp-wrap words a camera
    sends while nothing happens; ``reset()`` writes a timestamp reset (the clock restarts at 0).
    """

    def __init__(self, width: int | None = None, height: int | None = None, model: str = "DVXplorer"):
        self.model = model
        self.width, self.height = _check_model(model, width, height)
        self._st = np.zeros(2, np.int64)       # wrap base, current time (us)
        self._last_us = 0

    @property
    def time_us(self) -> int:
        return int(self._st[1])

    def reset(self) -> bytes:
        """A timestamp-reset word; later events count from a new zero."""
        self._st[:] = 0
        self._last_us = 0
        return np.array([SPECIAL_TS_RESET], "<u2").tobytes()

    def advance(self, until_us: int) -> bytes:
        """Timestamp-wrap words bringing the clock to ``until_us``'s 2**15 us period (no events)."""
        until_us = int(until_us)
        if until_us < self._last_us:
            return b""
        buf = np.empty(max(1, (until_us >> 15) - (int(self._st[0]) >> 15) + 1), np.uint16)
        n = _advance(np.int64(until_us), self._st, buf)
        self._last_us = max(self._last_us, int(self._st[1]))
        return buf[:n].astype("<u2", copy=False).tobytes()

    def encode(self, events=None, triggers=None) -> bytes:
        ev = _EMPTY_EV if events is None else np.asarray(events)
        tr = _EMPTY_TR if triggers is None else np.asarray(triggers)
        if ev.dtype != EVENT_DTYPE:
            raise InputError(f"{self.model} encoder: events must have dtype {EVENT_DTYPE}, got {ev.dtype}")
        if tr.dtype != TRIGGER_DTYPE:
            raise InputError(f"{self.model} encoder: triggers must have dtype {TRIGGER_DTYPE}, got {tr.dtype}")
        if ev.size == 0 and tr.size == 0:
            return b""
        ev = canonical_order(ev) if ev.size else ev
        us = self._check_times(ev["t"], "event")
        tus = self._check_times(np.sort(tr["t"], kind="stable"), "trigger")
        if tr.size:
            tr = tr[np.argsort(tr["t"], kind="stable")]
        if ev.size:
            if int(ev["x"].max()) >= self.width or int(ev["y"].max()) >= self.height:
                i = int(np.flatnonzero((ev["x"] >= self.width) | (ev["y"] >= self.height))[0])
                raise InputError(f"{self.model} encoder: event at x={int(ev['x'][i])}, y={int(ev['y'][i])} is "
                                 f"outside the {self.width}x{self.height} sensor")
            if np.any(ev["p"] == 0):
                raise InputError(f"{self.model} encoder: polarity must be +1 or -1, got 0")
        tcode = _trigger_codes(tr, self.model)
        first = min(int(us[0]) if us.size else 1 << 62, int(tus[0]) if tus.size else 1 << 62)
        if first < self._last_us:
            raise InputError(f"{self.model} encoder: this chunk starts at {first} us, before the stream's "
                             f"{self._last_us} us; chunks must be in time order")
        last = max(int(us[-1]) if us.size else -1, int(tus[-1]) if tus.size else -1)
        # per event: a timestamp, a column, an address and a group word at most; per trigger a
        # timestamp and its word; plus one wrap word per 2**15 us period crossed
        cap = 4 * ev.size + 2 * tr.size + ((last >> 15) - (int(self._st[0]) >> 15)) + 4
        buf = np.empty(cap, np.uint16)
        n = _encode(readonly(us), readonly(ev["x"].astype(np.int64)), readonly(ev["y"].astype(np.int64)),
                    readonly((ev["p"] < 0).astype(np.int64)), readonly(tus), readonly(tcode), self._st, buf)
        if n < 0:                                           # cannot happen: cap is an upper bound
            raise RuntimeError("caer word encoder: output estimate too small")
        self._last_us = last
        return buf[:n].astype("<u2", copy=False).tobytes()

    def _check_times(self, t, what):
        t = np.asarray(t, np.int64)
        if t.size == 0:
            return np.empty(0, np.int64)
        us, rest = np.divmod(t, 1000)
        if np.any(rest) or int(t[0]) < 0:
            i = int(np.flatnonzero((rest != 0) | (t < 0))[0])
            raise InputError(f"{self.model} encoder: {what} time {int(t[i])} ns is not a whole microsecond >= 0 "
                             "of sensor time; the camera counts whole microseconds from its zero")
        if t.size > 1 and np.any(t[1:] < t[:-1]):
            raise InputError(f"{self.model} encoder: {what} times must be sorted")
        return us


def _trigger_codes(tr, model):
    if tr.size == 0:
        return np.empty(0, np.int64)
    ids = tr["id"].astype(np.int64)
    val = tr["value"].astype(np.int64)
    code = np.full(tr.size, -1, np.int64)
    code[(ids == TRIGGER_EDGE) & (val == 1)] = SPECIAL_EXT_RISING
    code[(ids == TRIGGER_EDGE) & (val == 0)] = SPECIAL_EXT_FALLING
    code[(ids == TRIGGER_PULSE) & (val == 1)] = SPECIAL_EXT_PULSE
    code[(ids == TRIGGER_GENERATOR) & (val == 1)] = SPECIAL_GEN_RISING
    code[(ids == TRIGGER_GENERATOR) & (val == 0)] = SPECIAL_GEN_FALLING
    if np.any(code < 0):
        i = int(np.flatnonzero(code < 0)[0])
        raise InputError(f"{model} encoder: trigger id {int(ids[i])} value {int(val[i])} has no word; valid are "
                         f"id {TRIGGER_EDGE} (edge, value 0/1), {TRIGGER_PULSE} (pulse, value 1), "
                         f"{TRIGGER_GENERATOR} (generator edge, value 0/1)")
    return code


def encode_caer_words(events, triggers=None, model: str = "DVXplorer", *, width: int | None = None,
                      height: int | None = None) -> bytes:
    """One self-contained word stream (from sensor time 0) of sorted events and triggers."""
    return CaerWordEncoder(width, height, model).encode(events, triggers)
