"""N-MNIST / N-Caltech101 `.bin` event files (the ATIS recordings of Orchard et al. 2015): read only.

Each event is 40 bits, 5 bytes: x (8 bits), y (8 bits), then one 24-bit big-endian word whose top
bit is the polarity (1 = ON) and whose other 23 bits are the time in microseconds. A record with
y = 240 is no event but a time overflow: every later time is 2**13 us later (the datasets'
published reader, Read_Ndataset.m, does the same). The file gives no sensor size (N-MNIST 34x34;
N-Caltech101 up to 240x180): ``--geometry WxH``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import FormatError
from ..events.types import make_events, validate_events
from ..limits import check_memory

RECORD_BYTES = 5
#: y of a time-overflow record, and the time it adds to every later event (us)
OVERFLOW_Y, OVERFLOW_US = 240, 1 << 13


def read_atis_bin(path, *, geometry: tuple[int, int] | None = None):
    """(events, width, height) of an N-MNIST-style .bin file (module doc); width / height None
    without ``geometry``."""
    path = Path(path)
    size = path.stat().st_size
    if size % RECORD_BYTES:
        raise FormatError(f"{size} bytes is not a whole number of {RECORD_BYTES}-byte events: not an "
                          "N-MNIST-style .bin file, or a damaged one", source=str(path))
    check_memory(size * 8, f"{path}: {size // RECORD_BYTES} events", "use a machine with more memory")
    raw = np.fromfile(path, np.uint8).reshape(-1, RECORD_BYTES).astype(np.int64)
    x, y = raw[:, 0], raw[:, 1]
    word = (raw[:, 2] << 16) | (raw[:, 3] << 8) | raw[:, 4]
    overflow = y == OVERFLOW_Y
    t_us = (word & 0x7FFFFF) + OVERFLOW_US * np.cumsum(overflow)
    keep = ~overflow
    events = make_events(1000 * t_us[keep], x[keep], y[keep], np.where(word[keep] >> 23, 1, -1).astype(np.int8))
    width, height = (None, None) if geometry is None else (int(geometry[0]), int(geometry[1]))
    validate_events(events, width=width, height=height, source=str(path))
    return events, width, height


__all__ = ["read_atis_bin"]
