"""The event and trigger record types shared by every module, and their validation.

Time is int64 nanoseconds everywhere; events are sorted by t (ties keep stream order).
"""

from __future__ import annotations

import numpy as np

from ..errors import InputError

#: One change-detection event: time (ns), pixel column, pixel row, polarity (+1 / -1).
EVENT_DTYPE = np.dtype([("t", "<i8"), ("x", "<u2"), ("y", "<u2"), ("p", "i1")])

#: One external-trigger edge: time (ns), trigger channel id, edge value (1 rising, 0 falling).
TRIGGER_DTYPE = np.dtype([("t", "<i8"), ("id", "u1"), ("value", "u1")])

#: Largest coordinate any of our codecs can carry (11 bits in EVT2/EVT3).
MAX_SENSOR_SIZE = 2048


def make_events(t, x, y, p) -> np.ndarray:
    """Pack column arrays into an EVENT_DTYPE array (polarity given as +1/-1 or as 1/0)."""
    t = np.asarray(t)
    n = t.shape[0]
    out = np.empty(n, EVENT_DTYPE)
    out["t"] = t
    out["x"] = x
    out["y"] = y
    p = np.asarray(p)
    out["p"] = np.where(p > 0, 1, -1) if p.dtype.kind in "bu" else p
    return out


def make_triggers(t, trigger_id, value) -> np.ndarray:
    out = np.empty(np.asarray(t).shape[0], TRIGGER_DTYPE)
    out["t"], out["id"], out["value"] = t, trigger_id, value
    return out


def empty_events() -> np.ndarray:
    return np.empty(0, EVENT_DTYPE)


def empty_triggers() -> np.ndarray:
    return np.empty(0, TRIGGER_DTYPE)


def as_events(arr, *, source: str = "events") -> np.ndarray:
    """Return `arr` as EVENT_DTYPE (a copy only when the layout differs)."""
    arr = np.asarray(arr)
    if arr.dtype == EVENT_DTYPE:
        return arr
    names = arr.dtype.names or ()
    if not {"t", "x", "y", "p"} <= set(names):
        raise InputError(f"{source}: expected fields t, x, y, p; got {names or arr.dtype}")
    return make_events(arr["t"], arr["x"], arr["y"], arr["p"])


def validate_events(events: np.ndarray, *, width: int | None = None, height: int | None = None,
                    source: str = "events") -> np.ndarray:
    """Check dtype, time order, polarity and bounds; return the events unchanged.

    Raises InputError naming `source` and the first offending index.
    """
    if events.dtype != EVENT_DTYPE:
        raise InputError(f"{source}: dtype {events.dtype} is not the event dtype {EVENT_DTYPE}; "
                         "convert with evdnerf_ros.events.as_events()")
    if events.size == 0:
        return events
    t = events["t"]
    back = np.flatnonzero(t[1:] < t[:-1])
    if back.size:
        i = int(back[0]) + 1
        raise InputError(f"{source}: timestamps not sorted: event {i} at t={t[i]} ns comes after "
                         f"t={t[i - 1]} ns; sort by t (np.argsort(t, kind='stable')) first")
    p = events["p"]
    bad = np.flatnonzero((p != 1) & (p != -1))
    if bad.size:
        i = int(bad[0])
        raise InputError(f"{source}: event {i} has polarity {p[i]}; polarity must be +1 or -1")
    for axis, limit in (("x", width), ("y", height)):
        if limit is None:
            continue
        out = np.flatnonzero(events[axis] >= limit)
        if out.size:
            i = int(out[0])
            raise InputError(f"{source}: event {i} has {axis}={events[axis][i]} outside the declared "
                             f"{width}x{height} geometry; give the sensor's real width and height")
    return events


def sort_events(events: np.ndarray) -> np.ndarray:
    """Stable sort by time (events at equal time keep their order)."""
    if events.size and np.all(events["t"][1:] >= events["t"][:-1]):
        return events
    return events[np.argsort(events["t"], kind="stable")]
