"""The `mono` encoding of event_camera_msgs/EventPacket: one 64-bit little-endian word per event.

    bit 63       polarity (1 = ON = +1)
    bits 62-48   y (15 bits)
    bits 47-32   x (16 bits)
    bits 31-0    dt in nanoseconds, added to the packet's time_base

No triggers. Times are nanoseconds, so no rounding is involved.
"""

from __future__ import annotations

import numpy as np

from ...errors import FormatError, InputError
from ..types import TRIGGER_DTYPE, as_events, validate_events
from ._common import StreamDecoderBase, check_coords, check_time_base

NAME = "mono"
_DT_LIMIT = 1 << 32


class MonoDecoder(StreamDecoderBase):
    WORD = 8
    DTYPE = np.dtype("<u8")
    NAME = NAME

    def __init__(self, *, time_base_ns: int = 0, source: str = "<stream>", offset: int = 0):
        super().__init__(time_base_ns=time_base_ns, source=source, offset=offset)
        self._last_t = None

    def _count(self, words) -> int:
        return int(words.shape[0])

    def _decode_into(self, words, offset, out):
        n = words.shape[0]
        for s in range(0, n, _BLOCK):
            w = words[s:s + _BLOCK]
            o = out[s:s + w.shape[0]]
            t = (w & np.uint64(0xFFFFFFFF)).astype(np.int64)
            t += self.time_base_ns
            if self._last_t is not None and t[0] < self._last_t:
                self._raise_order(0, self._last_t, int(t[0]), offset + 8 * s)
            back = t[1:] < t[:-1]
            if back.any():
                i = int(np.flatnonzero(back)[0]) + 1
                self._raise_order(i, int(t[i - 1]), int(t[i]), offset + 8 * s)
            self._last_t = int(t[-1])
            o["t"] = t
            hi = (w >> np.uint64(32)).astype(np.uint32)
            np.bitwise_and(hi, 0xFFFF, out=o["x"], casting="unsafe")
            yy = hi >> 16
            np.bitwise_and(yy, 0x7FFF, out=o["y"], casting="unsafe")
            yy >>= 14                      # polarity bit 63 -> bit 1
            yy &= 2
            np.subtract(yy, 1, out=o["p"], casting="unsafe")
        return n, np.empty(0, TRIGGER_DTYPE), 0, 0

    def _raise_order(self, i, prev, cur, off):
        raise FormatError(
            f"event time goes backwards from dt={prev - self.time_base_ns} ns to "
            f"dt={cur - self.time_base_ns} ns; mono events must be in time order "
            "(is this really the mono encoding?)", source=self.source, offset=off + 8 * i)


_BLOCK = 1 << 17


class MonoEncoder:
    """Encode events relative to one time base; every dt must fit in 32 bits of nanoseconds."""

    def __init__(self, *, time_base_ns: int = 0):
        self.time_base_ns = check_time_base(time_base_ns)
        self._last_t = None

    def encode(self, events, triggers=None) -> bytes:
        if triggers is not None and np.asarray(triggers).size:
            raise InputError("mono: the mono encoding carries no triggers; send triggers in a "
                             "separate message (or use evt3 / evt2)")
        events = validate_events(as_events(events, source="events"), source="events")
        if events.size == 0:
            return b""
        check_coords(events, 1 << 16, 1 << 15, NAME, "events")
        t = events["t"]
        if self._last_t is not None and t[0] < self._last_t:
            raise InputError(f"mono encoder: this chunk starts at t={int(t[0])} ns, before the previous "
                             f"chunk's last time {self._last_t} ns; chunks must be in time order")
        dt = t - np.int64(self.time_base_ns)
        if dt[0] < 0 or dt[-1] >= _DT_LIMIT:
            bad = int(np.flatnonzero((dt < 0) | (dt >= _DT_LIMIT))[0])
            raise InputError(
                f"mono: event {bad} at t={int(t[bad])} ns is {int(dt[bad])} ns after time_base_ns="
                f"{self.time_base_ns}; mono carries dt in [0, 2**32) ns (about 4.29 s), so split the "
                "events into packets with their own time base")
        words = dt.astype(np.uint64)
        words |= events["x"].astype(np.uint64) << np.uint64(32)
        words |= events["y"].astype(np.uint64) << np.uint64(48)
        words |= (events["p"] > 0).astype(np.uint64) << np.uint64(63)
        self._last_t = int(t[-1])
        return words.astype("<u8", copy=False).tobytes()
