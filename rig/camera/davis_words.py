"""The iniVation DAVIS USB data words (libcaer's ``davis_common.h`` event translator), both ways.

A DAVIS (FX3: DAVIS346, 152a:841a) sends 16-bit little-endian words on bulk IN 0x82. They share
the DVXplorer's framing (timestamps, specials, wraps; :mod:`rig.camera.caer_words`) but not its
pixel addressing: a DAVIS sends one address word per event instead of 8-pixel group masks.

=======================  ======================================================================
``1ttt tttt tttt tttt``  timestamp: time (us) = wrap base + the 15 low bits
``0 000 dddd dddd dddd`` special, by data: 1 timestamp reset; 2 / 3 / 4 external input falling /
                         rising edge / pulse; 16 / 17 external generator falling / rising edge;
                         5 / 7 IMU sample start / end; 8 / 9 APS global / rolling shutter frame
                         start; 10 APS frame end; 11 / 12 APS reset / signal column start; 13 APS
                         column end; 14 / 15 APS exposure start / end
``0 001 dddd dddd dddd`` Y address: the row of the following X words (rows >= the sensor's are
                         skipped, the previous row kept)
``0 01p dddd dddd dddd`` X address: one DVS event at (x = data, the last Y) with polarity p
                         (code 3 = ON, code 2 = OFF); columns >= the sensor's are skipped
``0 100 dddd dddd dddd`` APS ADC sample (10 bits) of the next pixel of the current column
``0 101 cccc dddd dddd`` misc 8-bit data by c: 0 IMU sample byte, 1 / 2 APS ROI value high /
                         low byte (start column, start row, end column, end row, in that
                         order after a frame start), 3 IMU scale configuration
``0 110 ccdd dddd dddd`` misc 10-bit data: c = 0 the frame's exposure (10 bits at a time)
``0 111 dddd dddd dddd`` timestamp wrap: wrap base += data * 2**15 us (time = the new base)
=======================  ======================================================================

Orientation: libcaer swaps x and y of DVS events when the DVS orientation register (module 1,
parameter 2) has bit 2 set (``invert_xy``); it applies no flip to DVS events (the APS flips of
orientation bits 1 / 0 apply to frames only). A DAVIS346 reports 0 (no swap, no flip).

Triggers (TRIGGER_DTYPE): ``id`` TRIGGER_EDGE (value 1 rising, 0 falling), TRIGGER_PULSE
(value 1), TRIGGER_GENERATOR (value 1 rising, 0 falling), as for the DVXplorer.

APS frames (decoded only with ``aps=True``): a frame is a reset read (per column: reset column
start, one sample per row of the ROI, column end) and a signal read (the same with signal
column starts); each pixel's value is libcaer's correlated double sampling: 1023 when the reset
sample is below 384 or the signal sample is 0, else ``clip(reset - signal, 0, 1023)``, scaled to
16 bits (<< 6). A frame is kept when both reads have as many columns as the ROI (libcaer's
check); it carries the sensor times of its start, exposure start / end and end. APS words are
ignored after a timestamp reset until the next frame start (libcaer's ``ignoreEvents``).

Times: int64 ns = 1000 * the sensor's microseconds from its zero (the last timestamp reset),
unwrapped without limit. Both directions are numba kernels (one pass per chunk, no Python per
event); the decoder carries its whole state (time, wrap base, row, the APS frame in progress
and an odd trailing byte) across any chunk split.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from evdnerf_ros.errors import InputError
from evdnerf_ros.events.codecs._common import as_u8, kernel, readonly
from evdnerf_ros.events.types import EVENT_DTYPE, TRIGGER_DTYPE

from .caer_words import (SPECIAL_TS_RESET, TRIGGER_EDGE, TRIGGER_GENERATOR, TRIGGER_PULSE,
                         _trigger_codes)

__all__ = [
    "DAVIS_MODELS", "TRIGGER_EDGE", "TRIGGER_PULSE", "TRIGGER_GENERATOR", "ApsFrame", "DavisWordDecoder",
    "DavisWordEncoder", "decode_davis_words", "encode_davis_words",
]

#: Models whose USB words this codec speaks: (DVS columns, DVS rows).
DAVIS_MODELS = {"DAVIS346": (346, 260)}

# special-event data values (code 0) beyond the DVXplorer's
SPECIAL_APS_FRAME_START_GS = 8
SPECIAL_APS_FRAME_START_RS = 9
SPECIAL_APS_FRAME_END = 10
SPECIAL_APS_RESET_COLUMN_START = 11
SPECIAL_APS_SIGNAL_COLUMN_START = 12
SPECIAL_APS_COLUMN_END = 13
SPECIAL_APS_EXPOSURE_START = 14
SPECIAL_APS_EXPOSURE_END = 15

#: libcaer's CDS: a reset sample below this (or a signal sample of 0) reads as saturated white
APS_RESET_MIN = 384
APS_ADC_MAX = 1023

# decoder state slots
_S_WRAP, _S_CUR, _S_Y, _S_RESETS, _S_BAD, _S_IMU, _S_UNKNOWN, _S_WORDS, _S_APS = range(9)
_NSTATE = 9
# APS state slots
(_A_IGNORE, _A_TYPE, _A_CX0, _A_CX1, _A_CY0, _A_CY1, _A_EXPX, _A_EXPY, _A_POSX, _A_POSY, _A_SX, _A_SY,
 _A_TMP, _A_UPD, _A_TS0, _A_TSE0, _A_TSE1, _A_FLIPX, _A_FLIPY, _A_BAD, _A_GS, _A_FULLX, _A_FULLY,
 _A_EXPOSURE, _A_ENDC) = range(25)
_NAPS = 25

_EMPTY_EV = np.empty(0, EVENT_DTYPE)
_EMPTY_TR = np.empty(0, TRIGGER_DTYPE)


@dataclass(frozen=True)
class ApsFrame:
    """One APS frame: ``image`` (rows, columns) uint16 (10-bit CDS << 6), at pixel (x, y) of the
    sensor, with its sensor times (int64 ns from the sensor's zero)."""
    image: np.ndarray
    x: int
    y: int
    t_start_ns: int
    t_exposure_start_ns: int
    t_exposure_end_ns: int
    t_end_ns: int
    global_shutter: bool


def _check_model(model: str, width, height, invert_xy: bool = False):
    if model not in DAVIS_MODELS:
        raise InputError(f"DAVIS words: unknown model {model!r}; supported models are {', '.join(DAVIS_MODELS)}")
    cols, rows = DAVIS_MODELS[model]
    if invert_xy:
        cols, rows = rows, cols
    width = cols if width is None else int(width)
    height = rows if height is None else int(height)
    if not (0 < width <= 4096 and 0 < height <= 4096):
        raise InputError(f"DAVIS words: {model} geometry {width}x{height} is beyond what the words carry "
                         "(12-bit addresses: at most 4096)")
    return width, height


# =========================================================================== decoding


@kernel
def _count(w):
    """(events at most, triggers, frame ends) in the words."""
    nev = 0
    ntr = 0
    nfr = 0
    for i in range(w.shape[0]):
        v = np.int64(w[i])
        top = v & 0xF000
        if top == 0x2000 or top == 0x3000:
            nev += 1
        elif top == 0:
            d = v & 0xFFF
            if d == 2 or d == 3 or d == 4 or d == 16 or d == 17:
                ntr += 1
            elif d == 10:
                nfr += 1
    return nev, ntr, nfr


@kernel
def _decode(w, st, ev, tr, cols, rows, invert, aps_on, ast, pix, fimg, fmeta):
    """Decode words into ev / tr (and finished APS frames into fimg / fmeta when aps_on) with
    states st / ast; returns (events, triggers, frames)."""
    wrap = st[_S_WRAP]
    cur = st[_S_CUR]
    ly = st[_S_Y]
    bad = st[_S_BAD]
    k = 0
    kt = 0
    kf = 0
    n = w.shape[0]
    for i in range(n):
        v = np.int64(w[i])
        if v & 0x8000:
            cur = wrap + (v & 0x7FFF)
            continue
        code = v >> 12
        d = v & 0xFFF
        if code == 3 or code == 2:
            if d >= cols:
                bad += 1
                continue
            e = ev[k]
            e.t = cur * 1000
            if invert:
                e.x = ly
                e.y = d
            else:
                e.x = d
                e.y = ly
            e.p = np.int8(1) if code == 3 else np.int8(-1)
            k += 1
        elif code == 1:
            if d >= rows:
                bad += 1
            else:
                ly = d
        elif code == 4:
            if not aps_on:
                st[_S_APS] += 1
                continue
            if ast[_A_IGNORE]:
                continue
            rt = ast[_A_TYPE]
            cx = ast[_A_CX0 + rt]
            cy = ast[_A_CY0 + rt]
            ex = ast[_A_EXPX]
            ey = ast[_A_EXPY]
            if cx >= ex or cy >= ey:
                continue
            xp = ex - 1 - cx if ast[_A_FLIPX] else cx
            yp = ey - 1 - cy if ast[_A_FLIPY] else cy
            pos = yp * ast[_A_SX] + xp
            data = d & 0x3FF
            if rt == 0:
                pix[pos] = data
            else:
                rv = pix[pos]
                if rv < 384 or data == 0:
                    val = 1023
                else:
                    val = rv - data
                    if val < 0:
                        val = 0
                    if val > 1023:
                        val = 1023
                pix[pos] = val << 6
            ast[_A_CY0 + rt] = cy + 1
        elif code == 7:
            wrap += d * 32768
            cur = wrap
        elif code == 0:
            if d == 1:
                wrap = 0
                cur = 0
                st[_S_RESETS] += 1
                ast[_A_IGNORE] = 1
            elif d == 2 or d == 3 or d == 4 or d == 16 or d == 17:
                r = tr[kt]
                r.t = cur * 1000
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
                st[_S_IMU] += 1
            elif d >= 8 and d <= 15:
                if not aps_on:
                    st[_S_APS] += 1
                elif d == 8 or d == 9:
                    ast[_A_IGNORE] = 0
                    ast[_A_GS] = 1 if d == 8 else 0
                    ast[_A_TYPE] = 0
                    ast[_A_CX0] = 0
                    ast[_A_CX1] = 0
                    ast[_A_CY0] = 0
                    ast[_A_CY1] = 0
                    ast[_A_TMP] = 0
                    ast[_A_UPD] = 0
                    ast[_A_EXPOSURE] = 0
                    ast[_A_TS0] = cur
                    ast[_A_TSE0] = cur
                    ast[_A_TSE1] = cur
                elif ast[_A_IGNORE]:
                    pass
                elif d == 10:
                    ex = ast[_A_EXPX]
                    if ast[_A_CX0] == ex and ast[_A_CX1] == ex:
                        npx = ast[_A_SX] * ast[_A_SY]
                        for j in range(npx):
                            fimg[kf, j] = pix[j]
                        m = fmeta[kf]
                        m[0] = ast[_A_TS0]
                        m[1] = ast[_A_TSE0]
                        m[2] = ast[_A_TSE1]
                        m[3] = cur
                        m[4] = ast[_A_POSX]
                        m[5] = ast[_A_POSY]
                        m[6] = ast[_A_SX]
                        m[7] = ast[_A_SY]
                        m[8] = ast[_A_GS]
                        kf += 1
                    else:
                        ast[_A_BAD] += 1
                    ast[_A_IGNORE] = 1
                elif d == 11 or d == 12:
                    rt = d - 11
                    ast[_A_TYPE] = rt
                    ast[_A_CY0 + rt] = 0
                elif d == 13:
                    ast[_A_CX0 + ast[_A_TYPE]] += 1
                elif d == 14:
                    ast[_A_TSE0] = cur
                else:
                    ast[_A_TSE1] = cur
            else:
                st[_S_UNKNOWN] += 1
        elif code == 5:
            c8 = (d >> 8) & 0xF
            d8 = d & 0xFF
            if c8 == 0 or c8 == 3:
                st[_S_IMU] += 1
            elif c8 == 1 or c8 == 2:
                if not aps_on:
                    st[_S_APS] += 1
                elif c8 == 1:
                    ast[_A_TMP] = d8 << 8
                else:
                    val = ast[_A_TMP] | d8
                    u = ast[_A_UPD] & 3
                    if u == 0:
                        ast[_A_POSX] = val
                    elif u == 1:
                        ast[_A_POSY] = val
                    elif u == 2:
                        ast[_A_ENDC] = val
                    else:
                        sx = ast[_A_ENDC] + 1 - ast[_A_POSX]
                        sy = val + 1 - ast[_A_POSY]
                        if sx < 1 or sy < 1 or sx * sy > ast[_A_FULLX] * ast[_A_FULLY]:
                            ast[_A_BAD] += 1
                            ast[_A_IGNORE] = 1
                            sx = ast[_A_FULLX]
                            sy = ast[_A_FULLY]
                            ast[_A_POSX] = 0
                            ast[_A_POSY] = 0
                        ast[_A_SX] = sx
                        ast[_A_SY] = sy
                        ast[_A_EXPX] = sx
                        ast[_A_EXPY] = sy
                    ast[_A_UPD] += 1
            else:
                st[_S_UNKNOWN] += 1
        elif code == 6:
            if (d >> 10) == 0:
                if aps_on:
                    ast[_A_EXPOSURE] += 1
                else:
                    st[_S_APS] += 1
            else:
                st[_S_UNKNOWN] += 1
    st[_S_WRAP] = wrap
    st[_S_CUR] = cur
    st[_S_Y] = ly
    st[_S_BAD] = bad
    st[_S_WORDS] += n
    return k, kt, kf


class DavisWordDecoder:
    """Streaming decoder of DAVIS USB words: ``feed(data) -> (events, triggers)``; with ``aps=True``
    the finished APS frames collect in ``frames`` (``take_frames()`` hands them out).

    ``width`` / ``height``: the output geometry (default: the model's sensor); ``invert_xy`` (DVS
    orientation bit 2) swaps x and y as libcaer does; ``aps_flip_x`` / ``aps_flip_y`` are the APS
    orientation bits 1 / 0 (frames only). Any chunk boundary is fine, even inside a word."""

    def __init__(self, width: int | None = None, height: int | None = None, model: str = "DAVIS346", *,
                 invert_xy: bool = False, aps: bool = False, aps_size: tuple[int, int] | None = None,
                 aps_flip_x: bool = False, aps_flip_y: bool = False):
        self.model = model
        self.invert_xy = bool(invert_xy)
        self.width, self.height = _check_model(model, width, height, self.invert_xy)
        self._cols, self._rows = (self.height, self.width) if self.invert_xy else (self.width, self.height)
        self.aps = bool(aps)
        ax, ay = aps_size if aps_size is not None else DAVIS_MODELS[model]
        self._st = np.zeros(_NSTATE, np.int64)
        self._ast = np.zeros(_NAPS, np.int64)
        a = self._ast
        a[_A_IGNORE] = 1                                   # until the first frame start (libcaer)
        a[_A_FULLX], a[_A_FULLY] = int(ax), int(ay)
        a[_A_SX] = a[_A_EXPX] = int(ax)
        a[_A_SY] = a[_A_EXPY] = int(ay)
        a[_A_FLIPX], a[_A_FLIPY] = int(bool(aps_flip_x)), int(bool(aps_flip_y))
        self._pix = np.zeros(int(ax) * int(ay), np.int64)
        self._rest = b""
        self.frames: list[ApsFrame] = []

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
        """X / Y addresses outside the sensor that were skipped (libcaer logs them)."""
        return int(self._st[_S_BAD])

    @property
    def imu_words(self) -> int:
        return int(self._st[_S_IMU])

    @property
    def aps_words(self) -> int:
        """APS words skipped because APS decoding is off."""
        return int(self._st[_S_APS])

    @property
    def bad_frames(self) -> int:
        """APS frames dropped (wrong column count or an impossible ROI), as libcaer drops them."""
        return int(self._ast[_A_BAD])

    @property
    def unknown_words(self) -> int:
        return int(self._st[_S_UNKNOWN])

    @property
    def words(self) -> int:
        return int(self._st[_S_WORDS])

    @property
    def pending_bytes(self) -> int:
        return len(self._rest)

    def take_frames(self) -> list[ApsFrame]:
        out, self.frames = self.frames, []
        return out

    # decoding -------------------------------------------------------------------------
    def feed(self, data) -> tuple[np.ndarray, np.ndarray]:
        """Decode the whole words of ``data`` (after any byte left over from the previous call)."""
        u8 = as_u8(data, source=f"{self.model} USB data")
        if self._rest:
            u8 = np.concatenate([np.frombuffer(self._rest, np.uint8), u8])
        n = u8.size & ~1
        self._rest = u8[n:].tobytes()
        if n == 0:
            return _EMPTY_EV, _EMPTY_TR
        u8 = u8[:n]
        if u8.ctypes.data % 2:
            u8 = u8.copy()
        words = readonly(u8.view("<u2"))
        nev, ntr, nfr = _count(words)
        ev = np.empty(nev, EVENT_DTYPE)
        tr = np.empty(ntr, TRIGGER_DTYPE)
        nfr = nfr if self.aps else 0
        fimg = np.empty((nfr, self._pix.size), np.uint16)
        fmeta = np.empty((nfr, 9), np.int64)
        k, kt, kf = _decode(words, self._st, ev, tr, self._cols, self._rows, self.invert_xy, self.aps,
                            self._ast, self._pix, fimg, fmeta)
        for j in range(kf):
            t0, te0, te1, t1, x, y, sx, sy, gs = (int(v) for v in fmeta[j])
            self.frames.append(ApsFrame(fimg[j, :sx * sy].reshape(sy, sx).copy(), x, y, 1000 * t0, 1000 * te0,
                                        1000 * te1, 1000 * t1, bool(gs)))
        return (ev if k == nev else ev[:k]), tr[:kt]


def decode_davis_words(data, width: int | None = None, height: int | None = None, model: str = "DAVIS346",
                       *, invert_xy: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Decode a whole byte stream from its start (a trailing odd byte is ignored, as libcaer does)."""
    return DavisWordDecoder(width, height, model, invert_xy=invert_xy).feed(data)


# =========================================================================== encoding


@kernel
def _encode(us, x, y, on, tus, tcode, st, buf):
    """Words for events (in the given order, times sorted) and triggers (tus, tcode = special
    data; before the events of their microsecond). st = [wrap base us, current us, last row];
    returns the number of words written (-1: buf too short)."""
    cap = buf.shape[0]
    n = us.shape[0]
    nt = tus.shape[0]
    wrap = st[0]
    cur = st[1]
    ly = st[2]
    pos = 0
    i = 0
    ti = 0
    while i < n or ti < nt:
        if ti < nt and (i >= n or tus[ti] <= us[i]):
            t = tus[ti]
        else:
            t = us[i]
        hi = t >> 15
        while (wrap >> 15) < hi:                   # one wrap word per 2**15 us period, as the camera
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
        while i < n and us[i] == t:
            if pos + 2 > cap:
                return -1
            if y[i] != ly:
                ly = y[i]
                buf[pos] = 0x1000 | ly
                pos += 1
            buf[pos] = (0x3000 if on[i] else 0x2000) | x[i]
            pos += 1
            i += 1
    st[0] = wrap
    st[1] = cur
    st[2] = ly
    return pos


class DavisWordEncoder:
    """Events (sensor time, whole microseconds from the sensor's zero) -> DAVIS USB words.

    Successive ``encode`` calls continue one stream (times must not go back); events are written
    in the order given (a DAVIS sends each event as it is read out), a Y word only when the row
    changes. ``advance(until_us)`` writes the timestamp-wrap words a camera sends while nothing
    happens; ``reset()`` a timestamp reset. ``aps_begin`` / ``aps_end`` write a global-shutter APS
    frame (module doc) around the events of its exposure."""

    def __init__(self, width: int | None = None, height: int | None = None, model: str = "DAVIS346"):
        self.model = model
        self.width, self.height = _check_model(model, width, height)
        self._st = np.array([0, 0, -1], np.int64)        # wrap base, current time (us), last row
        self._last_us = 0
        self._aps_open: tuple[int, int, int, int] | None = None

    @property
    def time_us(self) -> int:
        return int(self._st[1])

    def reset(self) -> bytes:
        """A timestamp-reset word; later events count from a new zero."""
        self._st[0] = self._st[1] = 0
        self._last_us = 0
        self._aps_open = None
        return np.array([SPECIAL_TS_RESET], "<u2").tobytes()

    def _clock_to(self, t_us: int) -> list[int]:
        t_us = int(t_us)
        if t_us < self._last_us:
            raise InputError(f"{self.model} encoder: time {t_us} us is before the stream's {self._last_us} us; "
                             "write in time order")
        out = []
        while (int(self._st[0]) >> 15) < (t_us >> 15):
            out.append(0x7001)
            self._st[0] += 32768
            self._st[1] = self._st[0]
        if int(self._st[1]) != t_us:
            out.append(0x8000 | (t_us & 0x7FFF))
            self._st[1] = t_us
        self._last_us = t_us
        return out

    def advance(self, until_us: int) -> bytes:
        """Timestamp-wrap words bringing the clock to ``until_us``'s 2**15 us period (no events)."""
        until_us = int(until_us)
        if until_us < self._last_us:
            return b""
        k = max(0, (until_us >> 15) - (int(self._st[0]) >> 15))
        if k == 0:
            return b""
        self._st[0] += 32768 * k
        self._st[1] = self._st[0]
        self._last_us = max(self._last_us, int(self._st[1]))
        return np.full(k, 0x7001, "<u2").tobytes()

    def encode(self, events=None, triggers=None) -> bytes:
        ev = _EMPTY_EV if events is None else np.asarray(events)
        tr = _EMPTY_TR if triggers is None else np.asarray(triggers)
        if ev.dtype != EVENT_DTYPE:
            raise InputError(f"{self.model} encoder: events must have dtype {EVENT_DTYPE}, got {ev.dtype}")
        if tr.dtype != TRIGGER_DTYPE:
            raise InputError(f"{self.model} encoder: triggers must have dtype {TRIGGER_DTYPE}, got {tr.dtype}")
        if ev.size == 0 and tr.size == 0:
            return b""
        us = self._check_times(ev["t"], "event")
        if tr.size:
            tr = tr[np.argsort(tr["t"], kind="stable")]
        tus = self._check_times(tr["t"], "trigger")
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
        cap = 3 * ev.size + 2 * tr.size + ((last >> 15) - (int(self._st[0]) >> 15)) + 4
        buf = np.empty(cap, np.uint16)
        n = _encode(readonly(us), readonly(ev["x"].astype(np.int64)), readonly(ev["y"].astype(np.int64)),
                    readonly((ev["p"] > 0).astype(np.int64)), readonly(tus), readonly(tcode), self._st, buf)
        if n < 0:                                           # cannot happen: cap is an upper bound
            raise RuntimeError("DAVIS word encoder: output estimate too small")
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

    # --- APS ---------------------------------------------------------------------------
    #: the reset level the encoder's frames read (a valid CDS reset: >= APS_RESET_MIN)
    APS_RESET_LEVEL = 1023

    def aps_begin(self, t_us: int, x: int = 0, y: int = 0, width: int | None = None,
                  height: int | None = None) -> bytes:
        """Frame start (global shutter), the ROI, the reset read and the exposure start, at t_us."""
        if self._aps_open is not None:
            raise InputError(f"{self.model} encoder: aps_begin twice without aps_end")
        w = self.width - x if width is None else int(width)
        h = self.height - y if height is None else int(height)
        if x < 0 or y < 0 or w < 1 or h < 1 or x + w > self.width or y + h > self.height:
            raise InputError(f"{self.model} encoder: APS ROI x={x} y={y} w={w} h={h} is outside the "
                             f"{self.width}x{self.height} sensor")
        words = self._clock_to(t_us) + [SPECIAL_APS_FRAME_START_GS]
        for v in (x, y, x + w - 1, y + h - 1):
            words += [0x5100 | (v >> 8), 0x5200 | (v & 0xFF)]
        read = np.empty((w, h + 2), np.uint16)
        read[:, 0] = SPECIAL_APS_RESET_COLUMN_START
        read[:, 1:-1] = 0x4000 | self.APS_RESET_LEVEL
        read[:, -1] = SPECIAL_APS_COLUMN_END
        self._aps_open = (x, y, w, h)
        return (np.array(words, "<u2").tobytes() + read.reshape(-1).astype("<u2").tobytes()
                + np.array([SPECIAL_APS_EXPOSURE_START], "<u2").tobytes())

    def aps_end(self, t_us: int, adc) -> bytes:
        """Exposure end, the signal read of ``adc`` (h, w) counts 0..1022 (decoded as adc << 6)
        and the frame end, at t_us."""
        if self._aps_open is None:
            raise InputError(f"{self.model} encoder: aps_end without aps_begin")
        x, y, w, h = self._aps_open
        adc = np.asarray(adc)
        if adc.shape != (h, w):
            raise InputError(f"{self.model} encoder: APS image of shape {adc.shape}, the ROI is {(h, w)}")
        if adc.size and (int(adc.min()) < 0 or int(adc.max()) > self.APS_RESET_LEVEL - 1):
            raise InputError(f"{self.model} encoder: APS values must be 0..{self.APS_RESET_LEVEL - 1}")
        head = self._clock_to(t_us) + [SPECIAL_APS_EXPOSURE_END]
        read = np.empty((w, h + 2), np.uint16)
        read[:, 0] = SPECIAL_APS_SIGNAL_COLUMN_START
        read[:, 1:-1] = 0x4000 | (self.APS_RESET_LEVEL - adc.T.astype(np.int64))
        read[:, -1] = SPECIAL_APS_COLUMN_END
        self._aps_open = None
        return (np.array(head, "<u2").tobytes() + read.reshape(-1).astype("<u2").tobytes()
                + np.array([SPECIAL_APS_FRAME_END], "<u2").tobytes())


def encode_davis_words(events, triggers=None, model: str = "DAVIS346", *, width: int | None = None,
                       height: int | None = None) -> bytes:
    """One self-contained word stream (from sensor time 0) of sorted events and triggers."""
    return DavisWordEncoder(width, height, model).encode(events, triggers)
