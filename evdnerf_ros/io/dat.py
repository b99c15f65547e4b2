"""Prophesee DAT files (the older Metavision / ATIS `.dat`: N-CARS, the Gen1 automotive set): read only.

A text header of lines starting with `%` (`% Version 2`, `% Date ...`, optionally `% Width` /
`% Height`), then, from version 2 on, two bytes: the event type (0x00 Event2d, 0x0C EventCD) and
the event size (8). Each event: a little-endian uint32 time in microseconds and a uint32 with
x (bits 0-13), y (bits 14-27) and polarity (bits 28-31, 1 = ON). The 32-bit time wraps every
2**32 us (71.6 min): a step back of more than half of that counts one wrap. A file cut inside its
last event reads every complete event with a warning naming the byte offset (``strict`` refuses).
Without `% Width` / `% Height` the size comes from ``geometry`` (N-CARS: 120x100).
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from ..errors import FormatError
from ..events.codecs._common import TruncatedStreamWarning
from ..events.types import make_events, validate_events
from ..limits import check_memory

EVENT_TYPES = {0x00: "Event2d", 0x0C: "EventCD"}
EVENT_BYTES = 8
_WRAP = 1 << 32


def _header(data: bytes, path) -> tuple[dict[str, str], int]:
    """({key: value} of the `%` lines, the offset after them and the type / size bytes)."""
    fields, pos = {}, 0
    while pos < len(data) and data[pos:pos + 1] == b"%":
        end = data.find(b"\n", pos)
        if end < 0:
            raise FormatError("the header never ends (no line break after a '%' line)", source=str(path))
        key, _, value = data[pos + 1:end].decode("latin-1").strip().partition(" ")
        if key:
            fields[key.lower()] = value.strip()
        pos = end + 1
    version = fields.get("version", "1")
    if version.isdigit() and int(version) >= 2:
        if len(data) < pos + 2:
            raise FormatError("the header ends before its event type and size bytes", source=str(path))
        kind, size = data[pos], data[pos + 1]
        if kind not in EVENT_TYPES or size != EVENT_BYTES:
            raise FormatError(f"event type 0x{kind:02x} of {size} bytes is not a DAT CD event (types "
                              f"{ {f'0x{k:02x}': v for k, v in EVENT_TYPES.items()} }, 8 bytes)", source=str(path))
        pos += 2
    return fields, pos


def read_dat(path, *, geometry: tuple[int, int] | None = None, strict: bool = False):
    """(events, width, height) of a DAT file (module doc); width / height None when neither the
    header nor ``geometry`` gives them."""
    path = Path(path)
    size = path.stat().st_size
    check_memory(size * 6, f"{path}: {size // EVENT_BYTES} events", "use a machine with more memory")
    data = path.read_bytes()
    fields, start = _header(data, path)
    body = len(data) - start
    rest = body % EVENT_BYTES
    if rest:
        at = start + body - rest
        if strict:
            raise FormatError(f"{rest} dangling byte(s) at the end: DAT events are 8 bytes, so the file is "
                              "probably truncated (without --strict its complete events are read)",
                              source=str(path), offset=at)
        warnings.warn(f"{path}: ends inside an 8-byte DAT event at byte {at} ({rest} byte(s) dropped; every "
                      "complete event was read): the recording was cut", TruncatedStreamWarning, stacklevel=2)
    words = np.frombuffer(data, "<u4", count=(body - rest) // 4, offset=start).reshape(-1, 2)
    t = words[:, 0].astype(np.int64)
    t += _WRAP * np.concatenate([[0], np.cumsum(np.diff(t) < -(_WRAP // 2))])
    x, y, p = words[:, 1] & 0x3FFF, (words[:, 1] >> 14) & 0x3FFF, words[:, 1] >> 28
    if p.size and int(p.max()) > 1:
        raise FormatError(f"polarity values {np.unique(p)[:5].tolist()} are not 0/1", source=str(path))
    width, height = (None, None) if geometry is None else (int(geometry[0]), int(geometry[1]))
    if "width" in fields and "height" in fields:
        try:
            width, height = int(fields["width"]), int(fields["height"])
        except ValueError:
            raise FormatError(f"'% Width {fields['width']}' / '% Height {fields['height']}' are not integers",
                              source=str(path)) from None
    events = make_events(1000 * t, x, y, np.where(p > 0, 1, -1).astype(np.int8))
    validate_events(events, width=width, height=height, source=str(path))
    return events, width, height


__all__ = ["read_dat"]
