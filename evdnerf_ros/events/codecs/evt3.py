"""Prophesee EVT 3.0: 16-bit little-endian words, type in bits 15-12.

    0x0 ADDR_Y       y = bits 10-0 (bit 11 = system type, ignored)
    0x2 ADDR_X       x = bits 10-0, polarity = bit 11 -> one event at the current y
    0x3 VECT_BASE_X  base x = bits 10-0, vector polarity = bit 11
    0x4 VECT_12      bits 11-0 mask: event at base_x + i for each set bit i, then base_x += 12
    0x5 VECT_8       bits 7-0 mask, then base_x += 8
    0x6 TIME_LOW     time bits 11-0
    0x8 TIME_HIGH    time bits 23-12 (resets bits 11-0 to 0)
    0xA EXT_TRIGGER  value = bit 0, id = bits 11-8
    0x7 CONTINUED_4, 0xD IMU, 0xE OTHERS, 0xF CONTINUED_12 and reserved types: skipped

Time is 24 bits of microseconds and wraps every 2**24 us; the decoder counts wraps (a
TIME_HIGH that drops by more than half its range) and rejects time going backwards: a
TIME_HIGH that drops by more than 10 units without a wrap, or a time word that gives the
following event words an earlier time than earlier event words got. Real cameras write two
harmless anomalies, decoded as OpenEB and event_camera_codecs do and counted
(`time_anomalies`): a TIME_LOW at once replaced by a lower one with no event between (a
Gen4.1 does it about once per ms; the latest wins), and a TIME_HIGH stepping back by a few
units without a wrap.

Decoding and encoding are numba kernels (see _common.kernel), one pass over the words or
events of a chunk each; the decoder's state (time, row, vector base, last times) lives in a
small int64 array that carries across feed() calls, so any chunking decodes identically.
Events that come before the stream's first TIME_HIGH / ADDR_Y / VECT_BASE_X are dropped and
counted (the caller warns).
"""

from __future__ import annotations

import numpy as np
from numba.cpython.unsafe.numbers import trailing_zeros

from ...errors import FormatError
from ._common import (
    MAX_SENSOR_US, ChunkedEncoder, StreamDecoderBase, kernel, readonly, run_decode_kernel,
)

NAME = "EVT 3.0"
_INVALID_T = np.iinfo(np.int64).min      # ns time meaning "no valid time yet"
_MAX_I64 = np.iinfo(np.int64).max
_HALF = 2048                             # half the TIME_HIGH range (12 bits)
# A TIME_HIGH this many units (of 4096 us) below the previous one is a sensor glitch that real
# cameras write, not a wrap and not corruption (event_camera_codecs tolerates the same).
_HIGH_STEP_BACK = 10
_FILL_SPACING = 1024                     # encoder: at most 2**22 us between TIME_HIGH words

# decoder state slots (an int64 array the decoder keeps between feeds)
_S_TIME = 0        # current time in us (unwrapped); -1 before the first TIME_HIGH
_S_Y = 1           # current row; -1 before the first ADDR_Y
_S_BX = 2          # vector base x; -1 before the first VECT_BASE_X
_S_VP = 3          # vector polarity bit
_S_LAST_EV = 4     # ns time of the last event word with a valid time (order check)
_S_LAST_TR = 5     # ns time of the last trigger decoded
_S_BASE = 6        # time_base_ns
_S_CARRY = 7       # time_low_carry (0 / 1)
_S_LOW_BACK = 8    # TIME_LOW words below the previous low bits with no TIME_HIGH between (count)
_S_HIGH_BACK = 9   # TIME_HIGH words a few units below the previous one, not a wrap (count)
_N_STATE = 10

# kernel report slots
_R_ERR = 0         # error code (_E_*), 0 = none
_R_AT = 1          # index of the word the error is reported at (-1: before this chunk)
_R_A = 2           # error details
_R_B = 3
_R_DROP_EV = 4     # events dropped for lack of a valid time / row / vector base
_R_DROP_TR = 5     # triggers dropped for lack of a valid time
_R_TIME_WORD = 6   # index of the chunk's last time word (-1: none)
_N_REPORT = 7

_E_HIGH_BACK = 1   # TIME_HIGH drops by more than _HIGH_STEP_BACK, less than a wrap: A = new, B = previous
# (2 was TIME_LOW going back; that is tolerated now and only counted: _S_LOW_BACK)
_E_OVERFLOW = 3    # time beyond MAX_SENSOR_US
_E_EVENT_BACK = 4  # event words get an earlier time than before: A = time, B = previous (ns)
_E_TRIG_BACK = 5   # trigger earlier than the previous trigger: A = time, B = previous (ns)
_E_X_RANGE = 6     # vector event beyond x = 2047: A = x
_E_OUT_FULL = 7    # output array shorter than the count (caller bug)


# --------------------------------------------------------------------------------------
# decoder
# --------------------------------------------------------------------------------------

class Evt3Decoder(StreamDecoderBase):
    """Streaming EVT 3.0 decoder; state carries across feed() calls of any byte size.

    time_low_carry=True accepts streams that omit TIME_HIGH words and let TIME_LOW wrap
    (a TIME_LOW below the previous one, with no TIME_HIGH in between, then advances time by
    the 4096 us carry instead of raising FormatError). expelliarmus (<= 1.1.12) writes EVT 3.0
    files like that; conforming streams decode identically either way.
    """

    WORD = 2
    DTYPE = np.dtype("<u2")
    NAME = NAME
    DROP_REASON = ("that came before the stream's first TIME_HIGH / ADDR_Y / VECT_BASE_X word "
                   "(no valid time or address yet; normal when a recording starts mid-stream)")

    def __init__(self, *, time_base_ns: int = 0, source: str = "<stream>", offset: int = 0,
                 time_low_carry: bool = False):
        super().__init__(time_base_ns=time_base_ns, source=source, offset=offset)
        self.time_low_carry = bool(time_low_carry)
        st = np.zeros(_N_STATE, np.int64)
        st[[_S_TIME, _S_Y, _S_BX]] = -1
        st[[_S_LAST_EV, _S_LAST_TR]] = _INVALID_T
        st[_S_BASE] = self.time_base_ns
        st[_S_CARRY] = self.time_low_carry
        self._state = st
        self._time_off = None        # byte offset of the word that set the current time

    @property
    def time_anomalies(self) -> dict[str, int]:
        """Counts of the harmless time-word anomalies real cameras write (module doc)."""
        return {"time_low_back": int(self._state[_S_LOW_BACK]),
                "time_high_back": int(self._state[_S_HIGH_BACK])}

    def _count(self, words) -> int:
        return int(_count_events(readonly(words)))

    def _decode_into(self, words, offset, out):
        rep = np.zeros(_N_REPORT, np.int64)
        rep[_R_TIME_WORD] = -1
        k, trig = run_decode_kernel(_decode, words, out, self._state, rep)
        if rep[_R_ERR]:
            self._raise(rep, words, offset)
        if rep[_R_TIME_WORD] >= 0:
            self._time_off = offset + 2 * int(rep[_R_TIME_WORD])
        return k, trig, int(rep[_R_DROP_EV]), int(rep[_R_DROP_TR])

    def _raise(self, rep, w, off):
        code, wi, a, b = (int(v) for v in rep[:4])
        where = off + 2 * wi
        word = int(w[wi]) if wi >= 0 else 0
        if code == _E_HIGH_BACK:
            msg = (f"TIME_HIGH word 0x{word:04x} sets time bits 23-12 to {a} after {b}: "
                   "time goes backwards (a drop of at most half the 12-bit range is not a 24-bit "
                   "wrap-around); the stream is corrupt or not EVT 3.0")
        elif code == _E_OVERFLOW:
            msg = (f"time passes {MAX_SENSOR_US} us after so many TIME_HIGH wrap-arounds "
                   "that nanoseconds overflow; the stream is corrupt")
        elif code == _E_EVENT_BACK:
            if wi < 0:
                where = self._time_off
                what = "the time word before this block"
            else:
                what = f"{'TIME_HIGH' if word >= 0x8000 else 'TIME_LOW'} word 0x{word:04x}"
            base = self.time_base_ns
            msg = (f"{what} gives the following events time {(a - base) // 1000} us, before earlier "
                   f"events at {(b - base) // 1000} us: time goes backwards (a TIME_HIGH that "
                   "repeats its value resets the low time bits); the stream is corrupt or not EVT 3.0")
            if wi >= 0 and word >> 12 == 6 and not self.time_low_carry:
                msg += ("; expelliarmus writes EVT 3.0 files without TIME_HIGH words: read those with "
                        "time_low_carry=True")
        elif code == _E_TRIG_BACK:
            msg = (f"EXT_TRIGGER word 0x{word:04x} gets time {a} ns, before the previous trigger "
                   f"at {b} ns; the time went backwards")
        elif code == _E_X_RANGE:
            msg = (f"vector word 0x{word:04x} puts an event at x={a}, beyond the 11-bit address "
                   "range; the stream is corrupt (VECT_BASE_X missing or too many vectors)")
        else:
            raise ValueError("EVT 3.0 decoder: output array shorter than count_events()")
        raise FormatError(msg, source=self.source, offset=where)


@kernel
def _count_events(w):
    """Events the words decode to at most: one per ADDR_X, one per set vector mask bit."""
    total = 0
    for i in range(w.shape[0]):
        v = np.int64(w[i])
        ty = v >> 12
        m = v & (0xFFF if ty == 4 else 0xFF)
        m = m - ((m >> 1) & 0x555)           # popcount of 12 bits (SWAR)
        m = (m & 0x333) + ((m >> 2) & 0x333)
        m = (m + (m >> 4)) & 0xF0F
        m = (m + (m >> 8)) & 0x1F
        total += (ty == 2) + ((ty >> 1) == 2) * m
    return total


@kernel
def _decode(w, start, out, k, trig, st, rep):
    """Decode EVT 3.0 words w[start:] into out[k:] (EVENT_DTYPE, room for _count_events)
    and `trig` (TRIGGER_DTYPE).

    Updates the state array `st` and the report `rep` (error code and position, dropped
    counts, last time word); returns (next word, events written, triggers written). Stops
    at the first error, or before a trigger that does not fit in `trig`.
    """
    n_out = out.shape[0]
    time = st[_S_TIME]
    y = st[_S_Y]
    bx = st[_S_BX]
    vp = st[_S_VP]
    last_ev = st[_S_LAST_EV]
    last_tr = st[_S_LAST_TR]
    base = st[_S_BASE]
    carry = st[_S_CARRY] != 0
    tns = base + 1000 * time if time >= 0 else _INVALID_T
    time_word = rep[_R_TIME_WORD]
    d_ev = rep[_R_DROP_EV]
    d_tr = rep[_R_DROP_TR]
    n_tr = trig.shape[0]
    ntr = 0
    err = 0
    at = 0
    ea = 0
    eb = 0
    i = start
    n = w.shape[0]
    while i < n:
        v = np.int64(w[i])
        i += 1
        ty = v >> 12
        if ty == 2:                                      # ADDR_X
            if time >= 0:
                if tns < last_ev:
                    err, at, ea, eb = _E_EVENT_BACK, time_word, tns, last_ev
                    break
                last_ev = tns
                if y >= 0:
                    if k >= n_out:
                        err, at = _E_OUT_FULL, i - 1
                        break
                    e = out[k]
                    e.t = tns
                    e.x = v & 0x7FF
                    e.y = y
                    e.p = ((v >> 10) & 2) - 1
                    k += 1
                    continue
            d_ev += 1
        elif ty == 4 or ty == 5:                         # VECT_12 / VECT_8
            m = v & (0xFFF if ty == 4 else 0xFF)
            if time >= 0:
                if tns < last_ev:
                    err, at, ea, eb = _E_EVENT_BACK, time_word, tns, last_ev
                    break
                last_ev = tns
            if time >= 0 and y >= 0 and bx >= 0:
                if m:
                    if bx > 2047 - 11:                   # near the end of the 11-bit range
                        lo = max(2048 - bx, 0)
                        if m >> lo:
                            err, at = _E_X_RANGE, i - 1
                            ea = bx + lo + trailing_zeros(m >> lo)
                            break
                    if k + 12 > n_out:
                        c = 0
                        mm = m
                        while mm:
                            mm &= mm - 1
                            c += 1
                        if k + c > n_out:
                            err, at = _E_OUT_FULL, i - 1
                            break
                    p = 2 * vp - 1
                    while m:
                        e = out[k]
                        e.t = tns
                        e.x = bx + trailing_zeros(m)
                        e.y = y
                        e.p = p
                        k += 1
                        m &= m - 1
            else:
                while m:
                    m &= m - 1
                    d_ev += 1
            if bx >= 0:
                bx += 12 if ty == 4 else 8
        elif ty == 0:                                    # ADDR_Y
            y = v & 0x7FF
        elif ty == 6:                                    # TIME_LOW
            time_word = i - 1
            if time >= 0:
                lo = v & 0xFFF
                prev_lo = time & 0xFFF
                if lo < prev_lo:
                    if carry:
                        time += 4096
                    else:
                        # Real Gen4.1 sensors write a TIME_LOW and at once a lower one (about
                        # once per ms): the latest wins, as in OpenEB and event_camera_codecs;
                        # only an event whose time goes backwards is an error (checked there).
                        st[_S_LOW_BACK] += 1
                time = (time & ~0xFFF) | lo
                if time > MAX_SENSOR_US:
                    err, at = _E_OVERFLOW, i - 1
                    break
                tns = base + 1000 * time
        elif ty == 8:                                    # TIME_HIGH
            time_word = i - 1
            hv = v & 0xFFF
            if time >= 0:
                high = time >> 12
                prev_hv = high & 0xFFF
                d = prev_hv - hv
                if d > _HALF:
                    high += 4096                         # 24-bit wrap-around
                elif d > _HIGH_STEP_BACK:
                    err, at, ea, eb = _E_HIGH_BACK, i - 1, hv, prev_hv
                    break
                elif d > 0:
                    st[_S_HIGH_BACK] += 1                # a small step back: events decide
                time = ((high & ~0xFFF) | hv) << 12
            else:
                time = hv << 12
            if time > MAX_SENSOR_US:
                err, at = _E_OVERFLOW, i - 1
                break
            tns = base + 1000 * time
        elif ty == 3:                                    # VECT_BASE_X
            bx = v & 0x7FF
            vp = (v >> 11) & 1
        elif ty == 10:                                   # EXT_TRIGGER
            if time < 0:
                d_tr += 1
                continue
            if ntr == n_tr:                              # buffer full: resume here later
                i -= 1
                break
            if tns < last_tr:
                err, at, ea, eb = _E_TRIG_BACK, i - 1, tns, last_tr
                break
            last_tr = tns
            r = trig[ntr]
            r.t = tns
            r.id = (v >> 8) & 0xF
            r.value = v & 1
            ntr += 1
    st[_S_TIME] = time
    st[_S_Y] = y
    st[_S_BX] = bx
    st[_S_VP] = vp
    st[_S_LAST_EV] = last_ev
    st[_S_LAST_TR] = last_tr
    rep[_R_ERR] = err
    rep[_R_AT] = at
    rep[_R_A] = ea
    rep[_R_B] = eb
    rep[_R_DROP_EV] = d_ev
    rep[_R_DROP_TR] = d_tr
    rep[_R_TIME_WORD] = time_word
    return i, k, ntr


# --------------------------------------------------------------------------------------
# encoder
# --------------------------------------------------------------------------------------

class Evt3Encoder(ChunkedEncoder):
    """Streaming EVT 3.0 encoder; successive encode() outputs concatenate into one stream.

    Every call starts with a full TIME_HIGH + TIME_LOW (+ ADDR_Y at its first event), so a
    chunk decodes on its own except for the count of earlier 24-bit wraps. Runs of events
    with one time, row and polarity and increasing x become VECT_BASE_X + VECT_12 / VECT_8
    words (12-wide windows), single events ADDR_X. TIME_HIGH words are inserted so that no
    two are more than 2**22 us apart, which keeps every wrap-around detectable.
    """

    NAME = NAME
    MAX_TRIGGER_ID = 16
    WORD_DTYPE = np.dtype("<u2")

    @staticmethod
    def encode_words(us, events, tus, triggers, prev_high, carry):
        return encode_words(us, events, tus, triggers, prev_high, carry)


def encode_words(us, events, tus, triggers, prev_high, carry=None):
    """Encode sorted events (times `us`, x / y / p from the EVENT_DTYPE `events`) and sorted
    triggers (times `tus`, id / value from the TRIGGER_DTYPE `triggers`) into EVT 3.0 words.

    `prev_high`: full time-high value of the last TIME_HIGH already in the stream (None at
    its start). `carry`: None to start a self-contained chunk (TIME_HIGH, TIME_LOW and ADDR_Y
    written up front), or the dict returned by the previous call to continue seamlessly.
    Returns (uint16 words, new prev_high, new carry).
    """
    st = np.array([-1 if prev_high is None else prev_high,
                   -1 if carry is None else carry["us"],
                   -1 if carry is None or carry["y"] is None else carry["y"]], np.int64)
    buf = np.empty(_word_bound(us, tus, prev_high), np.uint16)
    nw = _encode(readonly(us), readonly(events), readonly(tus), readonly(triggers), st, buf)
    if nw < 0:   # pragma: no cover - _word_bound is an upper bound
        raise RuntimeError("EVT 3.0 encoder: output bound too small")
    buf.resize(nw, refcheck=False)       # give back the unused tail (realloc, no copy)
    return (buf, None if st[0] < 0 else int(st[0]),
            {"us": int(st[1]), "y": None if st[2] < 0 else int(st[2])})


def _word_bound(us, tus, prev_high) -> int:
    """Most words _encode can write: 4 per event (TIME_HIGH, TIME_LOW, ADDR_Y, ADDR_X; a
    vector window adds VECT_BASE_X + VECT but spans two or more events), 3 per trigger, plus
    the filler TIME_HIGH words. Those step from prev_high (0 if none) towards the last
    time-high value at most _FILL_SPACING apart, so there are at most
    (last - prev) // _FILL_SPACING + 1 of them.

    The output buffer is allocated here by numpy (huge pages for big buffers: fewer page
    faults than numba's allocator) and never grows inside the kernel.
    """
    last = max(int(us[-1]) if us.shape[0] else 0, int(tus[-1]) if tus.shape[0] else 0)
    prev = prev_high if prev_high is not None else 0
    return 4 * us.shape[0] + 3 * tus.shape[0] + max((last >> 12) - prev, 0) // _FILL_SPACING + 16


@kernel
def _encode(us, ev, tus, trig, st, buf):
    """EVT 3.0 words for one chunk; st = [prev_high, last time, last row] (-1: none), updated.

    The stream is a sequence of elements in time order: triggers, and runs of events (same
    time, row and polarity, increasing x), a trigger after the events of its microsecond.
    Before an element come a TIME_HIGH when time bits 23+ change (preceded by fillers so that
    no two TIME_HIGH values are more than _FILL_SPACING apart, counting from 0 when
    prev_high is -1) and a TIME_LOW when the time changes; before a run an ADDR_Y when the
    row changes. A run of one event is an ADDR_X, a longer one VECT_BASE_X + one VECT_12 per
    12-wide window of x (VECT_8 for the run's last window when it fits in 8 bits), with a
    new VECT_BASE_X wherever windows skip. Writes to `buf` (room for _word_bound words);
    returns the number of words written (-1 if `buf` is too short).
    """
    cap = buf.shape[0]
    n = us.shape[0]
    ntr = tus.shape[0]
    pos = 0
    prev_high = st[0]
    cur_us = st[1]
    cur_y = st[2]
    i = 0
    ti = 0
    while True:
        u = us[i] if i < n else _MAX_I64
        is_trig = ti < ntr and tus[ti] < u
        if is_trig:
            u = tus[ti]
            j = i
        elif i < n:
            e = ev[i]
            yy = np.int64(e.y)
            pp = e.p
            xp = np.int64(e.x)
            j = i + 1                                    # run end
            while j < n:
                f = ev[j]
                if (us[j] != u) | (f.y != yy) | (f.p != pp) | (f.x <= xp):
                    break
                xp = np.int64(f.x)
                j += 1
        else:
            break
        if u != cur_us:                                  # time words
            hi = u >> 12
            if cur_us < 0 or hi != cur_us >> 12:
                prev = prev_high if prev_high >= 0 else 0
                gap = hi - prev
                k0 = 1
                k1 = 0
                if gap > _FILL_SPACING:
                    k1 = (gap - 1) // _FILL_SPACING
                    if prev_high < 0:
                        k0 = 0                           # make the virtual TIME_HIGH 0 real
                if pos + (k1 - k0 + 1) + 2 > cap:
                    return -1
                for k in range(k0, k1 + 1):
                    buf[pos] = 0x8000 | ((prev + k * _FILL_SPACING) & 0xFFF)
                    pos += 1
                buf[pos] = 0x8000 | (hi & 0xFFF)
                pos += 1
                prev_high = hi
            elif pos >= cap:
                return -1
            buf[pos] = 0x6000 | (u & 0xFFF)
            pos += 1
            cur_us = u
        if is_trig:
            if pos >= cap:
                return -1
            buf[pos] = 0xA000 | (np.int64(trig[ti].id) << 8) | trig[ti].value
            pos += 1
            ti += 1
            continue
        if pos + 1 + 2 * (j - i) > cap:
            return -1
        if yy != cur_y:
            buf[pos] = yy
            pos += 1
            cur_y = yy
        x0 = np.int64(ev[i].x)
        pbit = 0x800 if pp > 0 else 0
        if j == i + 1:                                   # single event
            buf[pos] = 0x2000 | pbit | x0
            pos += 1
        else:
            s = i
            prev_win = -2
            while s < j:
                win = (np.int64(ev[s].x) - x0) // 12
                lo = x0 + 12 * win
                mask = 0
                while s < j:
                    off = np.int64(ev[s].x) - lo
                    if off >= 12:
                        break
                    mask |= 1 << off
                    s += 1
                if win - prev_win != 1:                  # first window or a skip
                    buf[pos] = 0x3000 | pbit | lo
                    pos += 1
                prev_win = win
                buf[pos] = (0x5000 if s == j and mask < 256 else 0x4000) | mask
                pos += 1
        i = j
    st[0] = prev_high
    st[1] = cur_us
    st[2] = cur_y
    return pos
