"""Events as HDF5 (h5py): datasets events/{t,x,y,p} (int64 ns, uint16, uint16, int8 +1/-1),
attributes width and height, optional triggers/{t,id,value}; chunked and compressed.

Also an index `events/ms_to_idx` (first event index at or after each whole millisecond from
the first event) so a reader can slice time without scanning; `read_h5_window` uses it.
"""

from __future__ import annotations

import numpy as np

from ..atomic import atomic_output
from ..errors import InputError
from ..events.types import empty_triggers, make_events, make_triggers, validate_events

CHUNK = 1 << 18
LAYOUT_VERSION = 1


def _h5py():
    import h5py

    return h5py


def write_h5(path, events, width: int, height: int, triggers=None, *, overwrite=False) -> None:
    validate_events(events, width=width, height=height, source=str(path))
    h5py = _h5py()
    with atomic_output(path, overwrite=overwrite) as tmp:
        with h5py.File(tmp, "w") as f:
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


def read_h5(path):
    """Return (events, triggers, width, height)."""
    h5py = _h5py()
    try:
        f = h5py.File(path, "r")
    except OSError as exc:
        raise InputError(f"{path}: not a readable HDF5 file ({exc})") from exc
    with f:
        if "events" not in f or not all(k in f["events"] for k in ("t", "x", "y", "p")):
            raise InputError(f"{path}: no events/{{t,x,y,p}} datasets; this reader expects the "
                             "layout written by `evdnerf convert-events` (see README)")
        for key in ("width", "height"):
            if key not in f.attrs:
                raise InputError(f"{path}: missing attribute {key!r} (sensor geometry)")
        g = f["events"]
        if g["t"].dtype.kind not in "iu":
            raise InputError(f"{path}: events/t has dtype {g['t'].dtype}; expected int64 ns")
        events = make_events(g["t"][:].astype(np.int64), g["x"][:], g["y"][:], g["p"][:])
        triggers = empty_triggers()
        if "triggers" in f:
            tg = f["triggers"]
            triggers = make_triggers(tg["t"][:], tg["id"][:], tg["value"][:])
        width, height = int(f.attrs["width"]), int(f.attrs["height"])
    validate_events(events, width=width, height=height, source=str(path))
    return events, triggers, width, height


def read_h5_window(path, t_start: int, t_end: int) -> np.ndarray:
    """Events with t_start <= t < t_end, reading only the chunks the ms index points at."""
    h5py = _h5py()
    with h5py.File(path, "r") as f:
        g = f["events"]
        ms_to_idx, t0 = g["ms_to_idx"][:], int(g.attrs["t0"])
        n = g["t"].shape[0]

        def bound(t_ns: int, upper: bool) -> int:
            k = (int(t_ns) - t0) // 1_000_000 + (1 if upper else 0)
            return int(ms_to_idx[min(max(k, 0), ms_to_idx.size - 1)]) if k < ms_to_idx.size else n

        lo, hi = bound(t_start, False), bound(t_end, True)
        t = g["t"][lo:hi]
        i0, i1 = np.searchsorted(t, [t_start, t_end])
        sl = slice(lo + int(i0), lo + int(i1))
        return make_events(g["t"][sl], g["x"][sl], g["y"][sl], g["p"][sl])
