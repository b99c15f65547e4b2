"""Events as text, one event per line: `t x y p` (whitespace-separated), as the RPG Event Camera
Dataset's `events.txt` writes them (t in seconds with a decimal point and up to nanosecond
digits, p 0/1 with 1 = ON; also +1/-1). Read only.

The time unit is never guessed: a t column written with a decimal point is seconds (the RPG
format); whole numbers alone could be ns, us or s, so such a file needs ``time_unit`` (the CLI's
``--time-unit``) and is refused with that hint. Times are parsed exactly as text (integer and
fraction apart, never through a float), so nanosecond digits survive; a fraction finer than
nanoseconds is refused. Lines starting with ``#`` are comments. The file holds no sensor size:
``--geometry WxH`` gives it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import FormatError, InputError
from ..events.types import make_events, validate_events
from ..limits import check_memory
from .h5events import TIME_UNITS, time_unit_name

#: bytes of memory per byte of text while parsing (numpy's string columns), for the budget check
_PARSE_BYTES_PER_BYTE = 16


def read_text(path, *, time_unit: str | None = None, geometry: tuple[int, int] | None = None):
    """(events, width, height) of a text event file (module doc); width / height None without
    ``geometry``."""
    path = Path(path)
    size = path.stat().st_size
    check_memory(size * _PARSE_BYTES_PER_BYTE, f"{path}: {size} bytes of text events",
                 "convert it in parts, or on a machine with more memory")
    try:
        cols = np.loadtxt(path, dtype=[("t", "U40"), ("x", "i8"), ("y", "i8"), ("p", "i8")], comments="#",
                          ndmin=1)
    except ValueError as exc:
        raise FormatError(f"not a text event file of lines `t x y p` ({str(exc).splitlines()[0]})",
                          source=str(path)) from None
    t_text = cols["t"]
    decimal = np.char.find(t_text, ".") >= 0
    unit = None if time_unit is None else time_unit_name(time_unit, "--time-unit")
    if unit is None:
        if t_text.size and not decimal.all():
            raise InputError(f"{path}: the times are whole numbers, so their unit is unknown (ns, us or s); "
                             f"give it with --time-unit {'|'.join(TIME_UNITS)} (times with a decimal point are "
                             "read as seconds, as the RPG Event Camera Dataset writes them)")
        unit = "s"
    events = make_events(_exact_ns(t_text, TIME_UNITS[unit], path), cols["x"], cols["y"],
                         _polarity(cols["p"], path))
    width, height = (None, None) if geometry is None else (int(geometry[0]), int(geometry[1]))
    validate_events(events, width=width, height=height, source=str(path))
    return events, width, height


def _exact_ns(t_text: np.ndarray, ns_per_unit: int, path) -> np.ndarray:
    """Decimal text times in a unit of ``ns_per_unit`` ns, as int64 ns, exactly."""
    if not t_text.size:
        return np.zeros(0, np.int64)
    if np.any(np.char.startswith(t_text, "-")):
        raise FormatError("negative times; times count from the recording's clock zero", source=str(path))
    whole, _, frac = np.char.partition(t_text, ".").T
    digits = len(str(ns_per_unit)) - 1          # fraction digits a whole ns allows
    longest = int(np.char.str_len(frac).max())
    if longest > digits:
        trimmed = np.char.rstrip(frac, "0")
        if int(np.char.str_len(trimmed).max()) > digits:
            raise FormatError(f"times finer than a nanosecond ({longest} fraction digits in this unit); "
                              "round them first", source=str(path))
        frac = trimmed
    try:
        w = whole.astype(np.int64)
        f = np.char.ljust(frac, digits, "0").astype(np.int64) if digits else np.zeros(w.shape, np.int64)
    except ValueError:
        raise FormatError("a time is not a decimal number", source=str(path)) from None
    if int(w.max()) > (2**62 - 1) // ns_per_unit:
        raise FormatError("times beyond the int64 nanosecond range; check --time-unit", source=str(path))
    return w * ns_per_unit + f


def _polarity(p: np.ndarray, path) -> np.ndarray:
    """0/1 (1 = ON) or -1/+1 as int8 +1/-1; a file mixing the two is refused."""
    if p.size and np.any(p < 0) and np.any(p == 0):
        raise FormatError("polarity column mixes 0 and -1; use 0/1 or -1/+1", source=str(path))
    if p.size and not np.all((p == 0) | (p == 1) | (p == -1)):
        raise FormatError(f"polarity must be 0/1 or -1/+1 (found {np.unique(p)[:5].tolist()})", source=str(path))
    return np.where(p > 0, 1, -1).astype(np.int8)


__all__ = ["read_text"]
