"""Exact parsing of user-facing times into int64 nanoseconds (no float rounding)."""

from __future__ import annotations

from decimal import Decimal, InvalidOperation

from .errors import InputError

# Every time and duration the user types stays within this, so sums and differences of
# two of them still fit int64.
MAX_TIME_NS = 1 << 62

_UNITS = {"ns": 1, "us": 1_000, "µs": 1_000, "ms": 1_000_000, "s": 1_000_000_000}


def parse_duration_ns(text: str, *, name: str = "time") -> int:
    """'1.5' or '1.5s' -> 1500000000; also 'ms', 'us', 'ns' suffixes; must be whole ns."""
    s = str(text).strip()
    unit = "s"
    for suffix in sorted(_UNITS, key=len, reverse=True):
        if s.endswith(suffix):
            s, unit = s[: -len(suffix)].strip(), suffix
            break
    try:
        value = Decimal(s) * _UNITS[unit]
    except InvalidOperation:
        raise InputError(f"{name}: cannot read {text!r} as a time; write e.g. 0.5, 0.5s, 20ms, "
                         "150us or 1000ns") from None
    if not value.is_finite():
        raise InputError(f"{name}: {text!r} is not a finite time")
    if abs(value) > MAX_TIME_NS:
        raise InputError(f"{name}: {text!r} is beyond +-2**62 ns (146 years); int64 nanosecond "
                         "times must stay far from overflow")
    if value != value.to_integral_value():
        raise InputError(f"{name}: {text!r} is not a whole number of nanoseconds")
    return int(value)


def format_ns(t_ns: int) -> str:
    """Human-readable seconds with full ns precision (display only)."""
    sign = "-" if t_ns < 0 else ""
    s, ns = divmod(abs(int(t_ns)), 1_000_000_000)
    return f"{sign}{s}.{ns:09d} s"
