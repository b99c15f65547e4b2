"""Prophesee EVT 2.0: 32-bit little-endian words, type in bits 31-28.

    0x0 CD_OFF / 0x1 CD_ON  ts_lsb = bits 27-22, x = bits 21-11, y = bits 10-0
    0x8 TIME_HIGH           bits 27-0 = time >> 6
    0xA EXT_TRIGGER         ts_lsb = bits 27-22, id = bits 12-8, value = bit 0
    0xE OTHERS, 0xF CONTINUED and reserved types: skipped

Time in microseconds = (time_high << 6) | ts_lsb: 34 bits, unwrapped by counting TIME_HIGH
wrap-arounds (a drop of more than half the 28-bit range). Whole-array numpy throughout.
"""

from __future__ import annotations

import numpy as np

from ...errors import FormatError
from ..types import EVENT_DTYPE, TRIGGER_DTYPE
from ._common import (
    MAX_SENSOR_US, ChunkedEncoder, StreamDecoderBase, arange, concat_triggers, time_high_fillers,
)

NAME = "EVT 2.0"
_TH_BITS = 28
_TH_MASK = (1 << _TH_BITS) - 1
_HALF = 1 << (_TH_BITS - 1)
_FILL_SPACING = 1 << (_TH_BITS - 2)
BLOCK_WORDS = 1 << 18


class Evt2Decoder(StreamDecoderBase):
    """Streaming EVT 2.0 decoder; state carries across feed() calls of any byte size."""

    WORD = 4
    DTYPE = np.dtype("<u4")
    NAME = NAME
    DROP_REASON = ("that came before the stream's first TIME_HIGH word (no valid time yet; "
                   "normal when a recording starts mid-stream)")

    def __init__(self, *, time_base_ns: int = 0, source: str = "<stream>", offset: int = 0):
        super().__init__(time_base_ns=time_base_ns, source=source, offset=offset)
        self._high = -1        # unwrapped time_high (units of 64 us); -1 before the first TIME_HIGH
        self._last_t = None    # ns time of the last decoded event (order check across blocks)
        self._last_tr = None

    def _count(self, words) -> int:
        # at most one event per word; the few control words leave untouched (never paged-in)
        # slack at the end of the output, which is cheaper than a counting pass
        return int(words.shape[0])

    def _decode_into(self, words, offset, out):
        pos = 0
        trigs = []
        d_ev = d_tr = 0
        for s in range(0, words.shape[0], BLOCK_WORDS):
            k, tr, de, dt = self._block(words[s:s + BLOCK_WORDS], offset + 4 * s, out[pos:])
            pos += k
            d_ev += de
            d_tr += dt
            if tr.size:
                trigs.append(tr)
        return pos, concat_triggers(trigs), d_ev, d_tr

    def _block(self, w, off, out):
        is_ne = w >= _CTRL                           # not a CD event
        ne_pos = np.flatnonzero(is_ne)               # few in EVT 2.0
        k = ne_pos.shape[0]
        r = w.shape[0] - k
        nw = w.take(ne_pos)
        nty = nw >> 28
        th_sel = np.flatnonzero(nty == 8)
        kh = th_sel.shape[0]

        h0 = self._high
        hext = np.empty(kh + 1, np.int64)
        hext[0] = h0
        if kh:
            hv = (nw.take(th_sel) & _TH_MASK).astype(np.int64)
            prev = np.empty_like(hv)
            prev[0] = (h0 & _TH_MASK) if h0 >= 0 else hv[0]
            prev[1:] = hv[:-1]
            dec = prev - hv
            wrap = dec > _HALF
            back = (dec > 0) & ~wrap
            if back.any():
                i = int(np.flatnonzero(back)[0])
                wi = int(ne_pos[th_sel[i]])
                raise FormatError(
                    f"TIME_HIGH word 0x{int(w[wi]):08x} sets time >> 6 to {int(hv[i])} after "
                    f"{int(prev[i])}: time goes backwards (a drop of at most half the 28-bit range "
                    "is not a wrap-around); the stream is corrupt or not EVT 2.0",
                    source=self.source, offset=off + 4 * wi)
            q = np.cumsum(wrap)
            if h0 >= 0:
                q += h0 >> _TH_BITS
            hext[1:] = (q << _TH_BITS) | hv
            if hext[-1] > MAX_SENSOR_US >> 6:
                raise FormatError("time wraps around so often that nanoseconds overflow; the stream "
                                  "is corrupt", source=self.source,
                                  offset=off + 4 * int(ne_pos[th_sel[-1]]))
            self._high = int(hext[-1])
        base = self.time_base_ns
        hns = hext * 64000
        hns += base
        if h0 < 0:
            hns[0] = _INVALID

        # triggers
        d_tr = 0
        trig = _NO_TRIGGERS
        if kh != k:
            tr_sel = np.flatnonzero(nty == 10)
            if tr_sel.size:
                trw = nw.take(tr_sel)
                tb = hns.take(np.searchsorted(th_sel, tr_sel))
                ok = tb != _INVALID
                if not ok.all():
                    d_tr = int(tr_sel.size - np.count_nonzero(ok))
                    trw, tb = trw[ok], tb[ok]
                trig = np.empty(trw.shape[0], TRIGGER_DTYPE)
                trig["t"] = tb + ((trw >> 22) & 63).astype(np.int64) * 1000
                trig["id"] = (trw >> 8) & 0x1F
                trig["value"] = trw & 1
                tr_pos = ne_pos.take(tr_sel)[ok] if d_tr else ne_pos.take(tr_sel)
                self._last_tr = self._check_order(trig["t"], self._last_tr, lambda: tr_pos, w, off,
                                                  "trigger")
        if r == 0:
            return 0, trig, 0, d_tr

        ew = w[~is_ne] if k else w
        # time of lsb 0 for each event: the TIME_HIGH period it falls in
        if kh * 8 <= r:
            counts = np.empty(kh + 1, np.int64)
            if kh:
                c = ne_pos.take(th_sel) - th_sel       # events before each TIME_HIGH
                counts[0] = c[0]
                np.subtract(c[1:], c[:-1], out=counts[1:-1])
                counts[-1] = r - c[-1]
            else:
                counts[0] = r
            t = np.repeat(hns, counts)
        else:                                          # sparse events: rank by cumulative count
            is_th = np.zeros(w.shape[0], bool)
            is_th[ne_pos.take(th_sel)] = True
            t = hns.take(np.cumsum(is_th)[~is_ne])
        d_ev = 0
        if h0 < 0:
            bad = int(np.count_nonzero(t == _INVALID))
            if bad:
                d_ev = bad
                t, ew = t[bad:], ew[bad:]
                if ew.size == 0:
                    return 0, trig, d_ev, d_tr
        m = ew.shape[0]
        o = out[:m]
        scratch = ew >> 22                            # ts_lsb -> ns, added to its period's base
        scratch &= 63
        scratch *= 1000
        t += scratch
        if k:
            ev_pos = lambda: np.flatnonzero(~is_ne)[d_ev:]
        else:
            ev_pos = lambda: arange(r)[d_ev:]
        self._last_t = self._check_order(t, self._last_t, ev_pos, w, off, "event")
        o["t"] = t
        # x (bits 21-11) and y (bits 10-0) in one uint32 store at record offset 8
        np.bitwise_and(ew, np.uint32(0x3FFFFF), out=scratch)
        xy = scratch << 16
        scratch >>= 11
        xy |= scratch
        xy &= np.uint32(0x07FF07FF)
        np.ndarray((m,), "<u4", buffer=o, offset=8, strides=(o.strides[0],))[...] = xy
        np.right_shift(ew, 27, out=scratch)           # polarity bit 28 -> bit 1
        scratch &= 2
        np.subtract(scratch, 1, out=o["p"], casting="unsafe")
        return m, trig, d_ev, d_tr

    def _check_order(self, t, last, positions, w, off, what):
        """Raise FormatError at the first word whose time is before the one preceding it;
        return the last time."""
        if t.size == 0:
            return last
        if last is not None and t[0] < last:
            i, prev = 0, last
        elif (t[1:] < t[:-1]).any():
            i = int(np.flatnonzero(t[1:] < t[:-1])[0]) + 1
            prev = int(t[i - 1])
        else:
            return int(t[-1])
        wi = int(positions()[i])
        raise FormatError(
            f"{what} time goes backwards from {prev - self.time_base_ns} ns to "
            f"{int(t[i]) - self.time_base_ns} ns after the time base (word 0x{int(w[wi]):08x}); "
            f"EVT 2.0 {what}s must come in time order; the stream is corrupt or not EVT 2.0",
            source=self.source, offset=off + 4 * wi)


_CTRL = np.uint32(0x2 << 28)
# the decoder stores x and y with one uint32 write at byte offset 8 of each record
assert EVENT_DTYPE.fields["x"][1] == 8 and EVENT_DTYPE.fields["y"][1] == 10 \
    and EVENT_DTYPE.fields["x"][0] == np.dtype("<u2") == EVENT_DTYPE.fields["y"][0]
_INVALID = np.iinfo(np.int64).min
_NO_TRIGGERS = np.empty(0, TRIGGER_DTYPE)


class Evt2Encoder(ChunkedEncoder):
    """Streaming EVT 2.0 encoder; every call starts with a TIME_HIGH word, later ones follow
    whenever time >> 6 changes (and at least every 2**32 us, so wraps stay detectable)."""

    NAME = NAME
    MAX_TRIGGER_ID = 32
    WORD_DTYPE = np.dtype("<u4")

    @staticmethod
    def encode_words(us, x, y, p, tus, tid, tval, prev_high, carry):
        return encode_words(us, x, y, p, tus, tid, tval, prev_high, carry)


def encode_words(us, x, y, p, tus, tid, tval, prev_high, carry=None):
    """EVT 2.0 words for sorted events and triggers; see evt3.encode_words for prev_high /
    carry. Returns (uint32 words, new prev_high, new carry)."""
    n = us.shape[0]
    ntr = tus.shape[0]
    ev_words = (((p > 0).astype(np.uint32) << 28) | ((us & 63).astype(np.uint32) << 22)
                | (x.astype(np.uint32) << 11) | y.astype(np.uint32))
    if ntr:
        ins = np.searchsorted(us, tus, side="right")
        pos_tr = ins + np.arange(ntr)
        pos_ev = np.arange(n) + np.searchsorted(ins, np.arange(n), side="right")
        M = n + ntr
        m_us = np.empty(M, np.int64)
        m_us[pos_ev] = us
        m_us[pos_tr] = tus
        body = np.empty(M, np.uint32)
        body[pos_ev] = ev_words
        body[pos_tr] = ((np.uint32(0xA) << 28) | ((tus & 63).astype(np.uint32) << 22)
                        | (tid.astype(np.uint32) << 8) | tval.astype(np.uint32))
    else:
        M = n
        m_us = us
        body = ev_words
    hi = m_us >> 6
    hchg = np.empty(M, bool)
    hchg[0] = carry is None or hi[0] != carry["us"] >> 6
    np.not_equal(hi[1:], hi[:-1], out=hchg[1:])
    th_idx = np.flatnonzero(hchg)
    fcounts, fvals = time_high_fillers(hi[th_idx], prev_high, _FILL_SPACING)
    cm = np.ones(M, np.int64)
    cm[th_idx] += 1 + fcounts
    end = np.cumsum(cm)
    out = np.empty(int(end[-1]), np.uint32)
    out[end - 1] = body
    start = end - cm
    out[start[th_idx] + fcounts] = (np.uint32(0x8) << 28) | (hi[th_idx] & _TH_MASK).astype(np.uint32)
    if fvals.size:
        nzi = np.flatnonzero(fcounts)
        owner_start = np.repeat(start[th_idx[nzi]], fcounts[nzi])
        first = np.repeat(np.cumsum(fcounts[nzi]) - fcounts[nzi], fcounts[nzi])
        fpos = owner_start + (np.arange(fvals.size) - first)
        out[fpos] = (np.uint32(0x8) << 28) | (fvals & _TH_MASK).astype(np.uint32)
    last_high = int(hi[th_idx[-1]]) if th_idx.size else prev_high
    return out, last_high, {"us": int(m_us[-1])}
