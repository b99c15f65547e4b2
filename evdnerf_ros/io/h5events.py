"""Events as HDF5 (h5py): datasets events/{t,x,y,p} (int64 ns, uint16, uint16, int8 +1/-1),
attributes width and height, optional triggers/{t,id,value}; chunked and compressed.

Reading other writers' files (DSEC's and v2e's `events/{t,x,y,p}`): the time unit is never
guessed. A `time_unit` attribute (on events/t, the events group or the file; ns, us, ms or s;
this module writes `time_unit: ns` on the file) is honoured; a file without one needs
``time_unit`` (the CLI's ``--time-unit``), and is refused with that hint (DSEC and v2e store
microseconds). Polarity +1/-1, or in other writers' files 0/1 (DSEC's: 1 = ON; no file mixes
the two). A file without
width / height attributes takes ``geometry`` (the CLI's ``--geometry WxH``).

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
from .guard import h5_close, h5_create, h5_dataset, h5_memory, h5_number, h5_open, h5_reading, h5_text

CHUNK = 1 << 18
LAYOUT, LAYOUT_VERSION = "evdnerf_ros.events", 1


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
    f.attrs.update(width=int(width), height=int(height), layout=LAYOUT,
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


#: ns per unit of the time units a file's `time_unit` attribute (or --time-unit) may name.
TIME_UNITS = {"ns": 1, "us": 1_000, "ms": 1_000_000, "s": 1_000_000_000}
_UNIT_SPELLINGS = {"µs": "us", "μs": "us", "microseconds": "us", "nanoseconds": "ns", "milliseconds": "ms",
                   "seconds": "s"}


def time_unit_name(text: str, what: str) -> str:
    """A time unit as one of TIME_UNITS (``what`` names where it came from in the error)."""
    unit = _UNIT_SPELLINGS.get(str(text).strip().lower(), str(text).strip().lower())
    if unit not in TIME_UNITS:
        raise InputError(f"{what}: time unit {text!r} is not one of {', '.join(TIME_UNITS)}")
    return unit


def _file_time_unit(f, path) -> str | None:
    """The `time_unit` attribute of events/t, the events group or the file (the first found)."""
    for holder in (f["events"]["t"], f["events"], f):
        if "time_unit" in holder.attrs:
            return time_unit_name(h5_text(holder.attrs, "time_unit", path), f"{path}: attribute time_unit")
    return None


def read_h5(path, *, time_unit: str | None = None, geometry: tuple[int, int] | None = None):
    """Return (events, triggers, width, height); ``time_unit`` / ``geometry`` for files that do
    not say (module doc)."""
    f = h5_open(path)
    with f, h5_reading(path):
        if "events" not in f or not all(k in f["events"] for k in ("t", "x", "y", "p")):
            raise InputError(f"{path}: no events/{{t,x,y,p}} datasets; this reader expects the "
                             "layout written by `evdnerf convert-events` (see docs/formats.md)")
        said = _file_time_unit(f, path)
        given = None if time_unit is None else time_unit_name(time_unit, "--time-unit")
        if said is not None and given is not None and said != given:
            raise InputError(f"{path}: its time_unit attribute says {said}, --time-unit says {given}; drop "
                             "--time-unit (the file's own unit is used)")
        unit = said or given
        ours = f.attrs.get("layout") == LAYOUT       # our own files hold +1/-1 only
        if unit is None:
            raise InputError(f"{path}: events/t has no time_unit attribute, so its unit is unknown (DSEC and "
                             "v2e write microseconds, this toolkit nanoseconds with time_unit: ns); give it "
                             f"with --time-unit {'|'.join(TIME_UNITS)}")
        if "width" in f.attrs or "height" in f.attrs or geometry is None:
            if "width" not in f.attrs and "height" not in f.attrs:
                raise InputError(f"{path}: no width / height attributes (the sensor size); give it with "
                                 "--geometry WxH (DSEC's cameras: 640x480)")
            width = h5_number(f.attrs, "width", path, low=1, high=65535, integer=True)
            height = h5_number(f.attrs, "height", path, low=1, high=65535, integer=True)
        else:
            width, height = (int(v) for v in geometry)
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
    scale = TIME_UNITS[unit]
    if scale != 1:
        limit = (2**63 - 1) // scale
        if n and (int(t.max()) > limit or int(t.min()) < -limit):
            raise FormatError(f"events/t in {unit} reaches beyond int64 nanoseconds; check --time-unit",
                              source=str(path))
        if tcols and tt.size and (int(tt.max()) > limit or int(tt.min()) < -limit):
            raise FormatError(f"triggers/t in {unit} reaches beyond int64 nanoseconds; check --time-unit",
                              source=str(path))
        t = t.astype(np.int64) * scale
    if not ours and p.size and not np.any(p < 0) and np.any(p == 0):
        p = np.where(p > 0, 1, -1).astype(np.int8)       # 0/1 polarity (DSEC's): 1 = ON
    for name, v, limit in (("x", x, width), ("y", y, height)):
        if v.size and (int(v.min()) < 0 or int(v.max()) >= limit):
            raise FormatError(f"events/{name} lies outside the declared {width}x{height} geometry "
                              f"(range {v.min()}..{v.max()}); fix the width/height attributes or the data",
                              source=str(path))
    if p.size and not np.all((p == 1) | (p == -1)):
        raise FormatError(f"events/p must hold +1/-1 or 0/1 (found {np.unique(p)[:5].tolist()})", source=str(path))
    events = make_events(t.astype(np.int64), x, y, p)
    triggers = empty_triggers()
    if tcols:
        if tt.size and (int(tt.min()) < 0 or int(tid.min()) < 0 or int(tid.max()) > 255
                        or np.any((tv != 0) & (tv != 1)) or np.any(tt[1:] < tt[:-1])):
            raise FormatError("triggers/{t,id,value} out of range (sorted int64 ns >= 0, ids 0..255, "
                              "values 0/1)", source=str(path))
        triggers = make_triggers(tt.astype(np.int64) * scale, tid, tv)
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
