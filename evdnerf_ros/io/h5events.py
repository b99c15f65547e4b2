"""Events as HDF5 (h5py): datasets events/{t,x,y,p} (int64 ns, uint16, uint16, int8 +1/-1),
attributes width and height, optional triggers/{t,id,value}; chunked and compressed.

Reading checks the layout (ranks, dtypes, lengths, attributes) before reading anything and
the declared sizes against the memory budget; a damaged file is a FormatError naming it.
Writing goes through evdnerf_ros.io.guard, so a full disk ends in one error naming the output.

Also an index `events/ms_to_idx` (first event index at or after each whole millisecond from
the first event) so a reader can slice time without scanning; `read_h5_window` uses it.
"""

from __future__ import annotations

import numpy as np

from ..atomic import atomic_output
from ..errors import FormatError, InputError
from ..events.types import (EVENT_DTYPE, TRIGGER_DTYPE, empty_triggers, make_events, make_triggers,
                            validate_events)
from ..limits import check_memory
from .guard import h5_close, h5_create, h5_dataset, h5_memory, h5_number, h5_open, h5_reading

CHUNK = 1 << 18
LAYOUT_VERSION = 1


def write_h5(path, events, width: int, height: int, triggers=None, *, overwrite=False) -> None:
    validate_events(events, width=width, height=height, source=str(path))
    t = events["t"]
    if t.size:   # the ms index has one entry per millisecond of the recording
        span = int(t[-1]) - int(t[0])
        check_memory(16 * (span // 1_000_000 + 2), f"{path}: a 1 ms time index over {span} ns of events",
                     "the events span an implausible time; check their timestamps")
    with atomic_output(path, overwrite=overwrite) as tmp:
        f, guard = h5_create(tmp, display=path)
        try:
            _write_layout(f, events, width, height, triggers)
        except BaseException as exc:
            h5_close(f, guard, check=False)
            if isinstance(exc, Exception):
                guard.check()              # a full disk is the better explanation
            raise
        h5_close(f, guard)


def _write_layout(f, events, width, height, triggers) -> None:
    f.attrs.update(width=int(width), height=int(height), layout="evdnerf_ros.events",
                   layout_version=LAYOUT_VERSION, time_unit="ns")
    g = f.create_group("events")
    for name in ("t", "x", "y", "p"):
        col = np.ascontiguousarray(events[name])
        g.create_dataset(name, data=col, chunks=(min(CHUNK, max(1, col.size)),),
                         compression="gzip", compression_opts=1, shuffle=True)
    t = events["t"]
    t0 = int(t[0]) if t.size else 0
    n_ms = (int(t[-1]) - t0) // 1_000_000 + 2 if t.size else 1
    ms_edges = t0 + 1_000_000 * np.arange(n_ms, dtype=np.int64)
    g.create_dataset("ms_to_idx", data=np.searchsorted(t, ms_edges).astype(np.int64))
    g.attrs["t0"] = t0
    if triggers is not None and len(triggers):
        tg = f.create_group("triggers")
        for name in ("t", "id", "value"):
            tg.create_dataset(name, data=np.ascontiguousarray(triggers[name]))


def _columns(f, group: str, names, path) -> list:
    """The 1-D integer datasets group/names, of one length (checked before any read)."""
    import h5py

    g = f.get(group) if group in f else None
    if not isinstance(g, h5py.Group):
        return []
    cols = [h5_dataset(g, k, path, ndim=1, what=f"{group}/{k}") for k in names]
    n = cols[0].shape[0]
    for k, c in zip(names, cols):
        if c.shape[0] != n:
            raise FormatError(f"{group}/{k} has {c.shape[0]} elements but {group}/{names[0]} has {n}; "
                              "the file is damaged", source=str(path))
    return cols


def read_h5(path):
    """Return (events, triggers, width, height)."""
    f = h5_open(path)
    with f, h5_reading(path):
        if "events" not in f or not all(k in f["events"] for k in ("t", "x", "y", "p")):
            raise InputError(f"{path}: no events/{{t,x,y,p}} datasets; this reader expects the "
                             "layout written by `evdnerf convert-events` (see docs/formats.md)")
        width = h5_number(f.attrs, "width", path, low=1, high=65535, integer=True)
        height = h5_number(f.attrs, "height", path, low=1, high=65535, integer=True)
        cols = _columns(f, "events", ("t", "x", "y", "p"), path)
        n = cols[0].shape[0]
        h5_memory(2 * n * EVENT_DTYPE.itemsize, path, f"{n} events")
        t, x, y, p = (c[()] for c in cols)
        tcols = _columns(f, "triggers", ("t", "id", "value"), path) if "triggers" in f else []
        if tcols:
            h5_memory(2 * tcols[0].shape[0] * TRIGGER_DTYPE.itemsize, path, f"{tcols[0].shape[0]} triggers")
            tt, tid, tv = (c[()] for c in tcols)
    if t.dtype == np.uint64 and n and int(t.max()) >= 2**63:
        raise FormatError("events/t holds values beyond int64 nanoseconds", source=str(path))
    for name, v, limit in (("x", x, width), ("y", y, height)):
        if v.size and (int(v.min()) < 0 or int(v.max()) >= limit):
            raise FormatError(f"events/{name} lies outside the declared {width}x{height} geometry "
                              f"(range {v.min()}..{v.max()}); fix the width/height attributes or the data",
                              source=str(path))
    if p.size and not np.all((p == 1) | (p == -1)):
        raise FormatError(f"events/p must hold +1/-1 (found {np.unique(p)[:5].tolist()})", source=str(path))
    events = make_events(t.astype(np.int64), x, y, p)
    triggers = empty_triggers()
    if tcols:
        if tt.size and (int(tt.min()) < 0 or int(tid.min()) < 0 or int(tid.max()) > 255
                        or np.any((tv != 0) & (tv != 1)) or np.any(tt[1:] < tt[:-1])):
            raise FormatError("triggers/{t,id,value} out of range (sorted int64 ns >= 0, ids 0..255, "
                              "values 0/1)", source=str(path))
        triggers = make_triggers(tt.astype(np.int64), tid, tv)
    validate_events(events, width=width, height=height, source=str(path))
    return events, triggers, width, height


def read_h5_window(path, t_start: int, t_end: int) -> np.ndarray:
    """Events with t_start <= t < t_end, reading only the chunks the ms index points at."""
    f = h5_open(path)
    with f, h5_reading(path):
        cols = _columns(f, "events", ("t", "x", "y", "p"), path)
        if not cols:
            raise InputError(f"{path}: no events/{{t,x,y,p}} datasets")
        n = cols[0].shape[0]
        index = h5_dataset(f["events"], "ms_to_idx", path, ndim=1, what="events/ms_to_idx")
        h5_memory(index.shape[0] * 8, path, f"events/ms_to_idx of {index.shape[0]} entries")
        ms_to_idx = index[()].astype(np.int64)
        t0 = h5_number(f["events"].attrs, "t0", path, integer=True, low=-2**63, high=2**63 - 1)
        if ms_to_idx.size == 0 or np.any(np.diff(ms_to_idx) < 0) or ms_to_idx[0] < 0 or ms_to_idx[-1] > n:
            raise FormatError("events/ms_to_idx is not a valid time index; the file is damaged",
                              source=str(path))

        def bound(t_ns: int, upper: bool) -> int:
            k = (int(t_ns) - t0) // 1_000_000 + (1 if upper else 0)
            return int(ms_to_idx[min(max(k, 0), ms_to_idx.size - 1)]) if k < ms_to_idx.size else n

        lo, hi = bound(t_start, False), max(bound(t_start, False), bound(t_end, True))
        h5_memory((hi - lo) * 2 * EVENT_DTYPE.itemsize, path, f"{hi - lo} events")
        t = cols[0][lo:hi]
        i0, i1 = np.searchsorted(t, [t_start, t_end])
        sl = slice(lo + int(i0), lo + int(i1))
        return make_events(*(c[sl] for c in cols))
