"""Checks that run before any allocation: numeric ranges and memory estimates.

Every numeric flag, config key and file header value that sizes work goes through
`check_number`; every allocation that scales with input (bins, pixels, windows, a file's
declared shape) is estimated first with `check_memory`, so an absurd value ends in one
clear line naming the flag to change instead of the kernel killing the process.
"""

from __future__ import annotations

import math
import os

from .errors import InputError

# Memory one job may plan to allocate: this fraction of physical memory, unless
# EVDNERF_MEMORY_LIMIT (bytes, or with a K/M/G suffix) says otherwise.
MEMORY_FRACTION = 0.5
MEMORY_ENV = "EVDNERF_MEMORY_LIMIT"

_SUFFIX = {"": 1, "K": 1 << 10, "M": 1 << 20, "G": 1 << 30, "T": 1 << 40}


def memory_budget() -> int:
    """Bytes a single estimate may ask for (see MEMORY_FRACTION / EVDNERF_MEMORY_LIMIT)."""
    text = os.environ.get(MEMORY_ENV, "").strip().upper().removesuffix("B").removesuffix("I")
    if text:
        unit = text[-1] if text[-1] in _SUFFIX else ""
        try:
            value = float(text[: len(text) - len(unit)])
        except ValueError:
            raise InputError(f"{MEMORY_ENV}={os.environ[MEMORY_ENV]!r}: expected bytes, "
                             "e.g. 8G or 500M") from None
        if not math.isfinite(value) or value <= 0:
            raise InputError(f"{MEMORY_ENV}={os.environ[MEMORY_ENV]!r}: must be positive")
        return int(value * _SUFFIX[unit])
    try:
        total = os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        total = 8 << 30
    return int(total * MEMORY_FRACTION)


def format_bytes(n: float) -> str:
    for unit in ("B", "KiB", "MiB", "GiB", "TiB"):
        if abs(n) < 1024 or unit == "TiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    return f"{n:.1f} TiB"


def check_memory(nbytes: float, what: str, fix: str) -> None:
    """Raise InputError when `what` would need more than the memory budget.

    `what` says what is being sized ("--bin 1ns over 10 s: 1e10 rate bins"), `fix` which
    flag or key to change.
    """
    budget = memory_budget()
    if not math.isfinite(nbytes) or nbytes > budget:
        raise InputError(f"{what} needs about {format_bytes(nbytes) if math.isfinite(nbytes) else 'unbounded memory'}"
                         f", more than the {format_bytes(budget)} allowed ({MEMORY_ENV} raises it); "
                         f"{fix}")


def check_number(value, name: str, *, low=None, high=None, low_open: bool = False,
                 integer: bool = False, allow_none: bool = False):
    """Return `value` if it is a finite number in [low, high] (or (low, high] with low_open).

    `name` is how the user wrote it (`--views`, `session.yaml: views[3].angle_deg`); the error
    names it, the range and the value. Booleans are not numbers here.
    """
    if value is None and allow_none:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)) and not hasattr(value, "__index__") \
            and not _is_numpy_number(value):
        raise InputError(f"{name}: expected a number, got {value!r}")
    if isinstance(value, int) and abs(value) > 10**300:
        # more digits than a float holds (a YAML or JSON integer can have any number)
        raise InputError(f"{name}: a {len(str(abs(value)))}-digit number is outside any valid range")
    if integer:
        if isinstance(value, float) or (_is_numpy_number(value) and not _is_numpy_integer(value)):
            if not math.isfinite(value) or value != int(value):
                raise InputError(f"{name}: expected a whole number, got {value!r}")
        value = int(value)
    elif not math.isfinite(float(value)):
        raise InputError(f"{name}: must be a finite number, got {value!r}")
    bad_low = low is not None and (value <= low if low_open else value < low)
    bad_high = high is not None and value > high
    if bad_low or bad_high:
        lo = "" if low is None else (f"> {low}" if low_open else f">= {low}")
        hi = "" if high is None else f"<= {high}"
        rng = " and ".join(s for s in (lo, hi) if s)
        raise InputError(f"{name}: must be {rng}, got {value!r}")
    return value


def _is_numpy_number(value) -> bool:
    try:
        import numpy as np
    except ImportError:  # pragma: no cover - numpy is a dependency
        return False
    return isinstance(value, np.number)


def _is_numpy_integer(value) -> bool:
    import numpy as np

    return isinstance(value, np.integer)
