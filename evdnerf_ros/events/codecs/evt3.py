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
TIME_HIGH that drops by less, a TIME_LOW below the previous one with no TIME_HIGH in
between, or a time word that gives the following events an earlier time than earlier events.

Everything below is whole-array numpy, block by block. Decoder: the positions of the event
words (ADDR_X / VECT_*) and of all other words come from np.flatnonzero; the state after
every non-event word (time, row, vector base) is forward-filled over the non-event words with
cumulative sums and np.take, and each event word picks its state by its rank among them
(position minus index); vector masks expand through np.unpackbits + np.flatnonzero. Encoder:
events are grouped into runs and 12-wide windows with boundary masks, and every word is
scattered to a position computed by a cumulative sum of per-item word counts.
"""

from __future__ import annotations

import numpy as np

from ...errors import FormatError
from ..types import TRIGGER_DTYPE
from ._common import (
    MAX_SENSOR_US, ChunkedEncoder, StreamDecoderBase, arange, concat_triggers, time_high_fillers,
)

NAME = "EVT 3.0"
_INVALID_T = np.iinfo(np.int64).min      # time of events seen before the first TIME_HIGH
_NO_Y = 0xFFFF                           # row of events seen before the first ADDR_Y
_HALF = 2048                             # half the TIME_HIGH range (12 bits)
_FILL_SPACING = 1024                     # encoder: at most 2**22 us between TIME_HIGH words

# Internal block size (words): big enough to amortise per-call overhead, small enough to
# keep temporaries modest (measured best on the benchmark machine).
BLOCK_WORDS = 1 << 18
_COUNT_WORDS = 1 << 21


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
        self._time = -1      # current time in us (unwrapped); -1 before the first TIME_HIGH
        self._y = -1         # current row; -1 before the first ADDR_Y
        self._bx = -1        # vector base x; -1 before the first VECT_BASE_X
        self._vp = 0         # vector polarity bit
        self._last_ev = _INVALID_T   # ns time of the last event decoded (order check)
        self._last_tr = _INVALID_T   # ns time of the last trigger decoded
        self._time_off = None        # byte offset of the word that set the current time

    # ---- counting (stateless upper bound) -----------------------------------------------
    def _count(self, words) -> int:
        total = 0
        for s in range(0, words.shape[0], _COUNT_WORDS):
            w = words[s:s + _COUNT_WORDS]
            ty = w >> 12
            total += int(np.count_nonzero(ty == 2))
            vec = (ty & 14) == 4
            if vec.any():
                vw = w[vec]
                masks = vw & np.where(vw < 0x5000, np.uint16(0xFFF), np.uint16(0xFF))
                total += int(np.bitwise_count(masks).sum(dtype=np.int64))
        return total

    def _decode_into(self, words, offset, out):
        pos = 0
        trigs = []
        d_ev = d_tr = 0
        for s in range(0, words.shape[0], BLOCK_WORDS):
            k, tr, de, dt = self._block(words[s:s + BLOCK_WORDS], offset + 2 * s, out[pos:])
            pos += k
            d_ev += de
            d_tr += dt
            if tr.size:
                trigs.append(tr)
        return pos, concat_triggers(trigs), d_ev, d_tr

    # ---- one block of whole words ----------------------------------------------------------
    def _block(self, w, off, out):
        ty = w >> 12
        is_ev = ty == 2
        vec = (ty & 14) == 4                 # VECT_12 / VECT_8
        has_vec = bool(vec.any())
        if has_vec:
            is_ev |= vec
        ev_pos = np.flatnonzero(is_ev)
        ne_pos = np.flatnonzero(~is_ev)      # every other word: time, y, vector base, ...
        r = ev_pos.shape[0]
        k = ne_pos.shape[0]
        nw = w.take(ne_pos)
        nty = nw >> 12

        # time after each non-event word ----------------------------------------------------
        t0 = self._time
        is_t = (nty == 6) | (nty == 8)
        t_sel = np.flatnonzero(is_t)
        kt = t_sel.shape[0]
        tns_ext = np.empty(kt + 1, np.int64)
        tns_ext[0] = self.time_base_ns + 1000 * t0 if t0 >= 0 else _INVALID_T
        prev_time_off = self._time_off
        if kt:
            tcur = self._time_table(nw.take(t_sel), t0, w, ne_pos, t_sel, off)
            if tcur[-1] > MAX_SENSOR_US:
                raise FormatError(f"time passes {MAX_SENSOR_US} us after so many TIME_HIGH wrap-arounds "
                                  "that nanoseconds overflow; the stream is corrupt",
                                  source=self.source, offset=off + 2 * int(ne_pos[t_sel[-1]]))
            self._time = int(tcur[-1])
            self._time_off = off + 2 * int(ne_pos[t_sel[-1]])
            if t0 >= 0 or tcur[0] >= 0:
                np.multiply(tcur, 1000, out=tns_ext[1:])
                tns_ext[1:] += self.time_base_ns
            else:
                tns_ext[1:] = np.where(tcur >= 0, self.time_base_ns + 1000 * tcur, _INVALID_T)
        if r and (tns_ext[0] < self._last_ev or (kt and (tns_ext[1:] < tns_ext[:-1]).any())):
            # a TIME_HIGH reset (e.g. a repeated TIME_HIGH) may dip the time for a moment; only
            # the times that events actually get must not go backwards
            self._check_event_times(tns_ext, ne_pos, t_sel, r, w, off, prev_time_off)
        ct_ext = np.empty(k + 1, np.int64)
        ct_ext[0] = 0
        np.cumsum(is_t, out=ct_ext[1:])
        t_ne = tns_ext.take(ct_ext)          # t_ne[j]: time before non-event word j

        # row after each non-event word -------------------------------------------------------
        y0 = self._y if self._y >= 0 else _NO_Y
        is_y = nty == 0
        y_sel = np.flatnonzero(is_y)
        ky = y_sel.shape[0]
        y_ext = np.empty(ky + 1, np.uint16)
        y_ext[0] = y0
        np.bitwise_and(nw.take(y_sel), 0x7FF, out=y_ext[1:])
        if ky:
            self._y = int(y_ext[-1])
        if kt + ky == k:                     # only time and y words: y count = index - time count
            cy_ext = arange(k + 1) - ct_ext
        else:
            cy_ext = np.empty(k + 1, np.int64)
            cy_ext[0] = 0
            np.cumsum(is_y, out=cy_ext[1:])
        y_ne = y_ext.take(cy_ext)

        # triggers ------------------------------------------------------------------------
        d_tr = 0
        trig = _NO_TRIGGERS
        if kt + ky != k:
            tr_sel = np.flatnonzero(nty == 10)
            if tr_sel.size:
                tt = t_ne.take(tr_sel)
                trw = nw.take(tr_sel)
                ok = tt != _INVALID_T
                if not ok.all():
                    d_tr = int(tr_sel.size - np.count_nonzero(ok))
                    tt, trw = tt[ok], trw[ok]
                if tt.size:
                    prev = np.empty_like(tt)
                    prev[0] = self._last_tr
                    prev[1:] = tt[:-1]
                    back = tt < prev
                    if back.any():
                        i = int(np.flatnonzero(back)[0])
                        wi = int(ne_pos.take(tr_sel[ok] if d_tr else tr_sel)[i])
                        raise FormatError(
                            f"EXT_TRIGGER word 0x{int(w[wi]):04x} gets time {int(tt[i])} ns, before "
                            f"the previous trigger at {int(prev[i])} ns; the time went backwards",
                            source=self.source, offset=off + 2 * wi)
                    self._last_tr = int(tt[-1])
                trig = np.empty(tt.shape[0], TRIGGER_DTYPE)
                trig["t"] = tt
                trig["id"] = (trw >> 8) & 0xF
                trig["value"] = trw & 1

        if r == 0:
            if kt + ky != k:
                self._vector_state(nty, nw, ne_pos, _ZERO1, False)
            return 0, trig, 0, d_tr

        rank = ev_pos - arange(r)            # non-event words before each event word
        t_row = t_ne.take(rank)
        y_row = y_ne.take(rank)
        maybe_invalid = t0 < 0 or y0 == _NO_Y

        if not has_vec:
            xw = w.take(ev_pos)
            dropped = 0
            if maybe_invalid:
                ok = (t_row != _INVALID_T) & (y_row != _NO_Y)
                if not ok.all():
                    xw, t_row, y_row = xw[ok], t_row[ok], y_row[ok]
                    dropped = r - xw.shape[0]
            if kt + ky != k:
                self._vector_state(nty, nw, ne_pos, _ZERO1, False)
            m = xw.shape[0]
            if m:
                self._last_ev = int(t_row[-1])
            o = out[:m]
            o["t"] = t_row
            o["y"] = y_row
            np.bitwise_and(xw, 0x7FF, out=o["x"])
            pb = xw >> 10                    # polarity bit 11 -> bit 1
            pb &= 2
            np.subtract(pb, 1, out=o["p"], casting="unsafe")
            return m, trig, dropped, d_tr

        # vector path --------------------------------------------------------------------------
        ew = w.take(ev_pos)
        ety = (ew >> 12).astype(np.int16)    # 2 ADDR_X, 4 VECT_12, 5 VECT_8
        is_addr = ety == 2
        not_addr = ~is_addr
        v8 = ety & 1                         # 1 for VECT_8
        inc = 12 - 4 * v8                    # base x advance: 12 or 8 (0 for ADDR_X)
        inc *= not_addr
        ci_ext = np.empty(r + 1, np.int64)
        ci_ext[0] = 0
        np.cumsum(inc, out=ci_ext[1:])
        packed_ne, bx_known = self._vector_state(nty, nw, ne_pos, ci_ext, True)
        # blends below use arithmetic with 0/1 masks: much cheaper than np.where / copyto
        ia = is_addr.view(np.uint8)
        na = not_addr.view(np.uint8)
        packed = packed_ne.take(rank)                 # (base key << 1) | vector polarity
        p_row = (packed & 1).astype(np.int8)
        base_row = packed >> 1
        base_row += ci_ext[:r]
        base_ok = None if bx_known else base_row >= 0
        base_row *= na                                # ADDR_X rows: their own x instead
        base_row += (ew & 0x7FF) * ia
        p_row *= na
        p_row += ((ew >> 11) & 1).astype(np.int8) * ia
        # bit mask of the row's events: VECT_12 bits 11-0, VECT_8 bits 7-0, ADDR_X just bit 0
        payload = ew & (np.uint16(0xFFF) >> (v8 << 2).astype(np.uint16))
        payload *= na
        payload += ia
        bits = np.unpackbits(payload.view(np.uint8), bitorder="little").view(bool)
        f = np.flatnonzero(bits)
        row = f >> 4
        col = f & 15
        dropped = 0
        if maybe_invalid or base_ok is not None:
            ok_row = (t_row != _INVALID_T) & (y_row != _NO_Y)
            if base_ok is not None:
                ok_row &= base_ok | is_addr
            if not ok_row.all():
                ok_ev = ok_row.take(row)
                dropped = int(row.shape[0] - np.count_nonzero(ok_ev))
                row, col = row[ok_ev], col[ok_ev]
        x = base_row.take(row)
        x += col
        if x.size and int(x.max()) > 0x7FF:
            i = int(np.flatnonzero(x > 0x7FF)[0])
            wi = int(ev_pos[row[i]])
            raise FormatError(
                f"vector word 0x{int(w[wi]):04x} puts an event at x={int(x[i])}, beyond the 11-bit "
                "address range; the stream is corrupt (VECT_BASE_X missing or too many vectors)",
                source=self.source, offset=off + 2 * wi)
        m = row.shape[0]
        o = out[:m]
        o["t"] = t_row.take(row)
        if m:
            self._last_ev = int(o["t"][-1])
        o["y"] = y_row.take(row)
        o["x"] = x
        pr = p_row.take(row)
        pr <<= 1
        np.subtract(pr, 1, out=o["p"])
        return m, trig, dropped, d_tr

    def _vector_state(self, nty, nw, ne_pos, ci_ext, need_rows):
        """Track VECT_BASE_X over the block's non-event words.

        Returns (packed_ne, base_known_at_start) when need_rows, where packed_ne[j] is
        (key << 1) | vector polarity before non-event word j: the base x of a vector row i is
        key[rank[i]] + ci_ext[i], ci_ext holding the prefix sums of the vector increments
        (12 / 8) over the rows. Always advances the decoder's state.
        """
        bx0, vp0 = self._bx, self._vp
        b_sel = np.flatnonzero(nty == 3)
        total_inc = int(ci_ext[-1])
        nb = b_sel.shape[0]
        key_ext = np.empty(nb + 1, np.int64)
        pol_ext = np.empty(nb + 1, np.int8)
        key_ext[0] = bx0 if bx0 >= 0 else -(1 << 40)
        pol_ext[0] = vp0
        if nb:
            bw = nw.take(b_sel)
            key_ext[1:] = bw & 0x7FF
            if total_inc:
                key_ext[1:] -= ci_ext.take(ne_pos.take(b_sel) - b_sel)
            pol_ext[1:] = (bw >> 11) & 1
            self._bx = int(key_ext[-1] + total_inc)
            self._vp = int(pol_ext[-1])
        elif bx0 >= 0:
            self._bx = bx0 + total_inc
        if not need_rows:
            return None
        cb = np.empty(nty.shape[0] + 1, np.int64)
        cb[0] = 0
        np.cumsum(nty == 3, out=cb[1:])
        key_ext <<= 1
        key_ext |= pol_ext
        return key_ext.take(cb), bx0 >= 0

    def _time_table(self, tv, t0, w, ne_pos, t_sel, off):
        """Unwrapped time (us) after each time word; -1 while no TIME_HIGH has been seen.

        Raises FormatError for a TIME_HIGH that drops by at most half its range and (unless
        time_low_carry) for a TIME_LOW below the previous one with no TIME_HIGH in between.
        """
        k = tv.shape[0]
        is_h = tv >= 0x8000
        val = (tv & 0xFFF).astype(np.int64)
        known = t0 >= 0
        not_h = ~is_h
        low = val * not_h                    # low bits in force after each word (TIME_HIGH: 0)
        lp = np.empty(k, np.int64)           # ... and before it
        lp[0] = (t0 & 0xFFF) if known else 0
        lp[1:] = low[:-1]
        drop = (val < lp) & not_h
        h_idx = np.flatnonzero(is_h)
        if not known:                        # no valid low bits before the first TIME_HIGH
            drop[:h_idx[0] if h_idx.size else k] = False
        carry = self.time_low_carry
        if not carry and drop.any():
            i = int(np.flatnonzero(drop)[0])
            self._raise_backwards(w, ne_pos, t_sel, i, int(lp[i]), int(val[i]), False, off)
        if carry:
            cc = np.cumsum(drop)
        if h_idx.size == 0:
            if not known:
                return np.full(k, -1, np.int64)
            tcur = (t0 >> 12) + cc if carry else np.full(k, t0 >> 12, np.int64)
            tcur <<= 12
            tcur += val
            return tcur
        hv = val.take(h_idx)
        prev_v = np.empty_like(hv)
        prev_v[0] = ((t0 >> 12) & 0xFFF) if known else hv[0]
        prev_v[1:] = hv[:-1]
        if carry:
            c_at = cc.take(h_idx)
            prev_v[0] += c_at[0]
            prev_v[1:] += np.diff(c_at)
        d = (prev_v & 0xFFF) - hv
        wrap = d > _HALF
        back = (d > 0) & ~wrap
        if not known:
            back[0] = False
        if back.any():
            i = int(np.flatnonzero(back)[0])
            self._raise_backwards(w, ne_pos, t_sel, int(h_idx[i]), int(prev_v[i] & 0xFFF),
                                  int(hv[i]), True, off)
        inc = wrap.astype(np.int64)
        if carry:
            inc += prev_v >> 12
        if not known:
            inc[0] = 0
        q = np.cumsum(inc)
        q += (t0 >> 24) if known else 0
        hh_ext = np.empty(hv.shape[0] + 1, np.int64)
        hh_ext[0] = (t0 >> 12) if known else -1
        np.bitwise_or(q << 12, hv, out=hh_ext[1:])
        rank = np.cumsum(is_h)
        tcur = hh_ext.take(rank)
        if carry:
            c_ext = np.empty(hv.shape[0] + 1, np.int64)
            c_ext[0] = 0
            c_ext[1:] = c_at
            tcur += cc - c_ext.take(rank)
        tcur <<= 12
        tcur += low
        if not known:
            tcur[:h_idx[0]] = -1
        return tcur

    def _check_event_times(self, tns_ext, ne_pos, t_sel, r, w, off, prev_time_off):
        """Raise FormatError if the time given to some events is before earlier events' time."""
        kt = t_sel.shape[0]
        seg = np.empty(kt + 1, np.int64)     # events decoded under each time value
        if kt:
            rb = ne_pos.take(t_sel) - t_sel
            seg[0] = rb[0]
            np.subtract(rb[1:], rb[:-1], out=seg[1:-1])
            seg[-1] = r - rb[-1]
        else:
            seg[0] = r
        idx = np.flatnonzero((seg > 0) & (tns_ext != _INVALID_T))
        te = tns_ext.take(idx)
        prev = np.empty_like(te)
        if te.size:
            prev[0] = self._last_ev
            prev[1:] = te[:-1]
        bad = np.flatnonzero(te < prev)
        if not bad.size:
            return
        i = int(bad[0])
        s = int(idx[i])
        base = self.time_base_ns
        if s == 0:
            where = prev_time_off
            what = "the time word before this block"
        else:
            wi = int(ne_pos[t_sel[s - 1]])
            where = off + 2 * wi
            what = f"{'TIME_HIGH' if w[wi] >= 0x8000 else 'TIME_LOW'} word 0x{int(w[wi]):04x}"
        raise FormatError(
            f"{what} gives the following events time {(int(te[i]) - base) // 1000} us, before earlier "
            f"events at {(int(prev[i]) - base) // 1000} us: time goes backwards (a TIME_HIGH that "
            "repeats its value resets the low time bits); the stream is corrupt or not EVT 3.0",
            source=self.source, offset=where)

    def _raise_backwards(self, w, ne_pos, t_sel, i, prev_v, cur_v, is_high, off):
        wi = int(ne_pos[t_sel[i]])
        word = int(w[wi])
        if is_high:
            msg = (f"TIME_HIGH word 0x{word:04x} sets time bits 23-12 to {cur_v} after {prev_v}: "
                   "time goes backwards (a drop of at most half the 12-bit range is not a 24-bit "
                   "wrap-around); the stream is corrupt or not EVT 3.0")
        else:
            msg = (f"TIME_LOW word 0x{word:04x} sets time bits 11-0 to {cur_v} after {prev_v} with no "
                   "TIME_HIGH in between: time goes backwards; the stream is corrupt or not EVT 3.0 "
                   "(expelliarmus writes EVT 3.0 files without TIME_HIGH words: read those with "
                   "time_low_carry=True)")
        raise FormatError(msg, source=self.source, offset=off + 2 * wi)


_NO_TRIGGERS = np.empty(0, TRIGGER_DTYPE)
_ZERO1 = np.zeros(1, np.int64)


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
    def encode_words(us, x, y, p, tus, tid, tval, prev_high, carry):
        return encode_words(us, x, y, p, tus, tid, tval, prev_high, carry)


def encode_words(us, x, y, p, tus, tid, tval, prev_high, carry=None):
    """Encode sorted events (us, x, y, p) and sorted triggers into EVT 3.0 words.

    `prev_high`: full time-high value of the last TIME_HIGH already in the stream (None at
    its start). `carry`: None to start a self-contained chunk (TIME_HIGH, TIME_LOW and ADDR_Y
    written up front), or the dict returned by the previous call to continue seamlessly.
    Returns (uint16 words, new prev_high, new carry).
    """
    n = us.shape[0]
    x = x.astype(np.int64)
    # ---- event items: single events (ADDR_X) or 12-wide vector windows -----------------
    if n:
        brk = np.empty(n, bool)
        brk[0] = True
        np.not_equal(us[1:], us[:-1], out=brk[1:])
        brk[1:] |= y[1:] != y[:-1]
        brk[1:] |= p[1:] != p[:-1]
        brk[1:] |= x[1:] <= x[:-1]
        run_start = np.flatnonzero(brk)
        run_len = np.diff(np.append(run_start, n))
        x0 = np.repeat(x[run_start], run_len)
        off = x - x0
        win = off // 12
        newit = brk.copy()
        newit[1:] |= win[1:] != win[:-1]
        it_start = np.flatnonzero(newit)
        run_id = np.cumsum(brk) - 1
        it_run = run_id[it_start]
        single = run_len[it_run] == 1
        it_win = win[it_start]
        bitv = np.left_shift(1, off - 12 * win).astype(np.uint16)
        mask = np.bitwise_or.reduceat(bitv, it_start)
        first_in_run = brk[it_start]
        prev_win = np.empty_like(it_win)
        prev_win[0] = -2
        prev_win[1:] = it_win[:-1]
        need_base = ~single & (first_in_run | (it_win - prev_win != 1))
        last_in_run = np.empty_like(first_in_run)
        last_in_run[:-1] = first_in_run[1:]
        last_in_run[-1] = True
        use8 = ~single & last_in_run & (mask < 256)
        it_us = us[it_start]
        it_y = y[it_start].astype(np.uint16)
        pbit = (p[it_start] > 0).astype(np.uint16) << 11
        main = np.where(single, 0x2000 | pbit | x[it_start].astype(np.uint16),
                        np.where(use8, 0x5000, 0x4000) | mask).astype(np.uint16)
        base_word = (0x3000 | pbit | (x0[it_start] + 12 * it_win)).astype(np.uint16)
    else:
        it_us = np.empty(0, np.int64)
        it_y = np.empty(0, np.uint16)
        main = base_word = np.empty(0, np.uint16)
        need_base = np.empty(0, bool)
    n_it = it_us.shape[0]
    ntr = tus.shape[0]

    # ---- merge triggers (placed after the events of the same microsecond) ---------------
    if ntr:
        ins = np.searchsorted(it_us, tus, side="right")
        pos_tr = ins + np.arange(ntr)
        pos_it = np.arange(n_it) + np.searchsorted(ins, np.arange(n_it), side="right")
        M = n_it + ntr
        m_us = np.empty(M, np.int64)
        m_us[pos_it] = it_us
        m_us[pos_tr] = tus
    else:
        pos_it = None
        M = n_it
        m_us = it_us

    tchg = np.empty(M, bool)
    tchg[0] = carry is None or m_us[0] != carry["us"]
    np.not_equal(m_us[1:], m_us[:-1], out=tchg[1:])
    hi = m_us >> 12
    hchg = np.empty(M, bool)
    hchg[0] = carry is None or hi[0] != carry["us"] >> 12
    np.not_equal(hi[1:], hi[:-1], out=hchg[1:])
    th_idx = np.flatnonzero(hchg)
    fcounts, fvals = time_high_fillers(hi[th_idx], prev_high, _FILL_SPACING)
    Fm = np.zeros(M, np.int64)
    Fm[th_idx] = fcounts

    ychg = np.empty(n_it, bool)
    if n_it:
        ychg[0] = carry is None or carry["y"] is None or it_y[0] != carry["y"]
        np.not_equal(it_y[1:], it_y[:-1], out=ychg[1:])

    head = Fm + hchg + tchg               # words before the element's own words
    cm = head + 1
    item_extra = ychg.astype(np.int64) + need_base     # (bool + bool would be a logical or)
    if ntr:
        cm[pos_it] += item_extra
    else:
        cm += item_extra
    end = np.cumsum(cm)
    start = end - cm
    total = int(end[-1])
    out = np.empty(total, np.uint16)

    if fvals.size:
        nzi = np.flatnonzero(fcounts)
        owner_start = np.repeat(start[th_idx[nzi]], fcounts[nzi])
        first = np.repeat(np.cumsum(fcounts[nzi]) - fcounts[nzi], fcounts[nzi])
        fpos = owner_start + (np.arange(fvals.size) - first)
        out[fpos] = 0x8000 | (fvals & 0xFFF)
    out[start[th_idx] + Fm[th_idx]] = 0x8000 | (hi[th_idx] & 0xFFF)
    tl_idx = np.flatnonzero(tchg)
    out[start[tl_idx] + Fm[tl_idx] + hchg[tl_idx]] = 0x6000 | (m_us[tl_idx] & 0xFFF)
    if n_it:
        if ntr:
            s_it = start[pos_it] + head[pos_it]
            e_it = end[pos_it]
        else:
            s_it = start + head
            e_it = end
        out[s_it[ychg]] = it_y[ychg]
        out[(s_it + ychg)[need_base]] = base_word[need_base]
        out[e_it - 1] = main
    if ntr:
        out[end[pos_tr] - 1] = (0xA000 | (tid.astype(np.uint16) << 8) | tval.astype(np.uint16))
    last_high = int(hi[th_idx[-1]]) if th_idx.size else prev_high
    new_carry = {"us": int(m_us[-1]),
                 "y": int(it_y[-1]) if n_it else (carry["y"] if carry is not None else None)}
    return out, last_high, new_carry
