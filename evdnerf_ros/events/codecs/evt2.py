"""Prophesee EVT 2.0: 32-bit little-endian words, type in bits 31-28.

    0x0 CD_OFF / 0x1 CD_ON  ts_lsb = bits 27-22, x = bits 21-11, y = bits 10-0
    0x8 TIME_HIGH           bits 27-0 = time >> 6
    0xA EXT_TRIGGER         ts_lsb = bits 27-22, id = bits 12-8, value = bit 0
    0xE OTHERS, 0xF CONTINUED and reserved types: skipped

Time in microseconds = (time_high << 6) | ts_lsb: 34 bits, unwrapped by counting TIME_HIGH
wrap-arounds (a drop of more than half the 28-bit range). Decoding and encoding are numba
kernels (see _common.kernel), one pass per chunk, with the stream state carried across
feed() calls in a small int64 array.
"""

from __future__ import annotations

import numpy as np

from ...errors import FormatError
from ._common import (
    MAX_SENSOR_US, ChunkedEncoder, StreamDecoderBase, kernel, readonly, run_decode_kernel,
)

NAME = "EVT 2.0"
_TH_BITS = 28
_TH_MASK = (1 << _TH_BITS) - 1
_HALF = 1 << (_TH_BITS - 1)
_FILL_SPACING = 1 << (_TH_BITS - 2)
_MAX_HIGH = MAX_SENSOR_US >> 6
_INVALID = np.iinfo(np.int64).min
_MAX_I64 = np.iinfo(np.int64).max

# decoder state slots (int64 array kept between feeds)
_S_HIGH = 0        # unwrapped time_high (units of 64 us); -1 before the first TIME_HIGH
_S_LAST_EV = 1     # ns time of the last decoded event (order check)
_S_LAST_TR = 2     # ns time of the last decoded trigger
_S_BASE = 3        # time_base_ns
_N_STATE = 4

# kernel report slots
_R_ERR, _R_AT, _R_A, _R_B, _R_DROP_EV, _R_DROP_TR = range(6)
_N_REPORT = 6
_E_HIGH_BACK = 1   # TIME_HIGH drops by at most half its range: A = new, B = previous
_E_OVERFLOW = 2    # time beyond MAX_SENSOR_US
_E_EVENT_BACK = 3  # event before the previous event: A = time, B = previous (ns)
_E_TRIG_BACK = 4   # trigger before the previous trigger: A = time, B = previous (ns)
_E_OUT_FULL = 5    # output array shorter than the word count (caller bug)


class Evt2Decoder(StreamDecoderBase):
    """Streaming EVT 2.0 decoder; state carries across feed() calls of any byte size."""

    WORD = 4
    DTYPE = np.dtype("<u4")
    NAME = NAME
    DROP_REASON = ("that came before the stream's first TIME_HIGH word (no valid time yet; "
                   "normal when a recording starts mid-stream)")

    def __init__(self, *, time_base_ns: int = 0, source: str = "<stream>", offset: int = 0):
        super().__init__(time_base_ns=time_base_ns, source=source, offset=offset)
        self._state = np.array([-1, _INVALID, _INVALID, self.time_base_ns], np.int64)

    def _count(self, words) -> int:
        # at most one event per word; the few control words leave untouched (never paged-in)
        # slack at the end of the output, which is cheaper than a counting pass
        return int(words.shape[0])

    def _decode_into(self, words, offset, out):
        rep = np.zeros(_N_REPORT, np.int64)
        k, trig = run_decode_kernel(_decode, words, out, self._state, rep)
        if rep[_R_ERR]:
            self._raise(rep, words, offset)
        return k, trig, int(rep[_R_DROP_EV]), int(rep[_R_DROP_TR])

    def _raise(self, rep, w, off):
        code, wi, a, b = (int(v) for v in rep[:4])
        word = int(w[wi])
        if code == _E_HIGH_BACK:
            msg = (f"TIME_HIGH word 0x{word:08x} sets time >> 6 to {a} after {b}: time goes "
                   "backwards (a drop of at most half the 28-bit range is not a wrap-around); the "
                   "stream is corrupt or not EVT 2.0")
        elif code == _E_OVERFLOW:
            msg = "time wraps around so often that nanoseconds overflow; the stream is corrupt"
        elif code in (_E_EVENT_BACK, _E_TRIG_BACK):
            what = "event" if code == _E_EVENT_BACK else "trigger"
            base = self.time_base_ns
            msg = (f"{what} time goes backwards from {b - base} ns to {a - base} ns after the time "
                   f"base (word 0x{word:08x}); EVT 2.0 {what}s must come in time order; the stream "
                   "is corrupt or not EVT 2.0")
        else:
            raise ValueError("EVT 2.0 decoder: output array shorter than count_events()")
        raise FormatError(msg, source=self.source, offset=off + 4 * wi)


@kernel
def _decode(w, start, out, k, trig, st, rep):
    """Decode EVT 2.0 words w[start:] into out[k:] (EVENT_DTYPE, a slot per word) and
    `trig` (TRIGGER_DTYPE).

    Updates the state array `st` and the report `rep` (error code, word index and details,
    dropped counts); returns (next word, events written, triggers written). Stops at the
    first error, or before a trigger that does not fit in `trig`.
    """
    high = st[_S_HIGH]
    last_ev = st[_S_LAST_EV]
    last_tr = st[_S_LAST_TR]
    base = st[_S_BASE]
    hns = base + 64000 * high if high >= 0 else _INVALID
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
    if out.shape[0] - k < n - start:                     # at most one event per word
        rep[_R_ERR] = _E_OUT_FULL
        return i, k, ntr
    while i < n:
        v = np.int64(w[i])
        i += 1
        ty = v >> 28
        if ty < 2:                                       # CD_OFF / CD_ON
            if high < 0:
                d_ev += 1
                continue
            t = hns + ((v >> 22) & 63) * 1000
            if t < last_ev:
                err, at, ea, eb = _E_EVENT_BACK, i - 1, t, last_ev
                break
            last_ev = t
            e = out[k]
            e.t = t
            e.x = (v >> 11) & 0x7FF
            e.y = v & 0x7FF
            e.p = 2 * ty - 1
            k += 1
        elif ty == 8:                                    # TIME_HIGH
            hv = v & _TH_MASK
            if high >= 0:
                prev = high & _TH_MASK
                d = prev - hv
                if d > _HALF:
                    high += 1 << _TH_BITS                # wrap-around
                elif d > 0:
                    err, at, ea, eb = _E_HIGH_BACK, i - 1, hv, prev
                    break
                high = (high & ~_TH_MASK) | hv
            else:
                high = hv
            if high > _MAX_HIGH:
                err, at = _E_OVERFLOW, i - 1
                break
            hns = base + 64000 * high
        elif ty == 10:                                   # EXT_TRIGGER
            if high < 0:
                d_tr += 1
                continue
            if ntr == n_tr:                              # buffer full: resume here later
                i -= 1
                break
            t = hns + ((v >> 22) & 63) * 1000
            if t < last_tr:
                err, at, ea, eb = _E_TRIG_BACK, i - 1, t, last_tr
                break
            last_tr = t
            r = trig[ntr]
            r.t = t
            r.id = (v >> 8) & 0x1F
            r.value = v & 1
            ntr += 1
    st[_S_HIGH] = high
    st[_S_LAST_EV] = last_ev
    st[_S_LAST_TR] = last_tr
    rep[_R_ERR] = err
    rep[_R_AT] = at
    rep[_R_A] = ea
    rep[_R_B] = eb
    rep[_R_DROP_EV] = d_ev
    rep[_R_DROP_TR] = d_tr
    return i, k, ntr


class Evt2Encoder(ChunkedEncoder):
    """Streaming EVT 2.0 encoder; every call starts with a TIME_HIGH word, later ones follow
    whenever time >> 6 changes (and at least every 2**32 us, so wraps stay detectable)."""

    NAME = NAME
    MAX_TRIGGER_ID = 32
    WORD_DTYPE = np.dtype("<u4")

    @staticmethod
    def encode_words(us, events, tus, triggers, prev_high, carry):
        return encode_words(us, events, tus, triggers, prev_high, carry)


def encode_words(us, events, tus, triggers, prev_high, carry=None):
    """EVT 2.0 words for sorted events and triggers; see evt3.encode_words for the arguments,
    prev_high and carry. Returns (uint32 words, new prev_high, new carry)."""
    st = np.array([-1 if prev_high is None else prev_high,
                   -1 if carry is None else carry["us"]], np.int64)
    # numpy allocates the output (huge pages for big buffers: fewer page faults than numba's
    # allocator): 2 words per event or trigger at most, plus the filler TIME_HIGH words,
    # which step from prev_high (0 if none) towards the last time >> 6 at most _FILL_SPACING
    # apart (see evt3._word_bound)
    last = max(int(us[-1]) if us.shape[0] else 0, int(tus[-1]) if tus.shape[0] else 0)
    prev = prev_high if prev_high is not None else 0
    buf = np.empty(2 * (us.shape[0] + tus.shape[0]) + max((last >> 6) - prev, 0) // _FILL_SPACING
                   + 16, np.uint32)
    nw = _encode(readonly(us), readonly(events), readonly(tus), readonly(triggers), st, buf)
    if nw < 0:   # pragma: no cover - the size above is an upper bound
        raise RuntimeError("EVT 2.0 encoder: output bound too small")
    buf.resize(nw, refcheck=False)       # give back the unused tail (realloc, no copy)
    return buf, None if st[0] < 0 else int(st[0]), {"us": int(st[1])}


@kernel
def _encode(us, ev, tus, trig, st, buf):
    """EVT 2.0 words for one chunk; st = [prev_high, last time] (-1: none), updated.

    Each event or trigger (triggers after the events of their microsecond) is one word,
    preceded by a TIME_HIGH when time >> 6 changes, itself preceded by filler TIME_HIGH
    words so that no two TIME_HIGH values are more than _FILL_SPACING apart (counting from
    0 when prev_high is -1). Writes to `buf`; returns the number of words written (-1 if
    `buf` is too short).
    """
    cap = buf.shape[0]
    n = us.shape[0]
    ntr = tus.shape[0]
    pos = 0
    prev_high = st[0]
    cur_hi = st[1] >> 6 if st[1] >= 0 else -1
    last = st[1]
    i = 0
    ti = 0
    while i < n or ti < ntr:
        if ti < ntr and (i >= n or tus[ti] < us[i]):     # a trigger comes next
            u = tus[ti]
            word = ((0xA << 28) | ((u & 63) << 22) | (np.int64(trig[ti].id) << 8)
                    | trig[ti].value)
            ti += 1
        else:
            u = us[i]
            e = ev[i]
            word = ((np.int64(e.p > 0) << 28) | ((u & 63) << 22) | (np.int64(e.x) << 11)
                    | np.int64(e.y))
            i += 1
        hi = u >> 6
        if hi != cur_hi:
            prev = prev_high if prev_high >= 0 else 0
            gap = hi - prev
            k0 = 1
            k1 = 0
            if gap > _FILL_SPACING:
                k1 = (gap - 1) // _FILL_SPACING
                if prev_high < 0:
                    k0 = 0                               # make the virtual TIME_HIGH 0 real
            if pos + (k1 - k0 + 1) + 2 > cap:
                return -1
            for k in range(k0, k1 + 1):
                buf[pos] = (8 << 28) | ((prev + k * _FILL_SPACING) & _TH_MASK)
                pos += 1
            buf[pos] = (8 << 28) | (hi & _TH_MASK)
            pos += 1
            prev_high = hi
            cur_hi = hi
        elif pos >= cap:
            return -1
        buf[pos] = word
        pos += 1
        last = u
    st[0] = prev_high
    st[1] = last
    return pos
