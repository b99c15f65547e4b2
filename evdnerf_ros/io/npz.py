"""Events as .npz: arrays t (int64 ns), x, y (uint16), p (int8 +1/-1), scalars width, height;
optional trigger arrays trigger_t, trigger_id, trigger_value."""

from __future__ import annotations

import zipfile

import numpy as np

from ..atomic import atomic_output
from ..errors import InputError
from ..events.types import empty_triggers, make_events, make_triggers, validate_events


def read_npz(path):
    """Return (events, triggers, width, height) from an .npz written by `write_npz` or by hand."""
    try:
        data = np.load(path, allow_pickle=False)
    except (OSError, ValueError, zipfile.BadZipFile) as exc:
        raise InputError(f"{path}: not a readable .npz file ({exc})") from exc
    with data:
        missing = [k for k in ("t", "x", "y", "p", "width", "height") if k not in data.files]
        if missing:
            raise InputError(f"{path}: missing arrays {missing}; an event .npz holds t (int64 ns), "
                             "x, y, p (+1/-1) and scalars width, height")
        t = data["t"]
        if t.dtype.kind not in "iu":
            raise InputError(f"{path}: t has dtype {t.dtype}; store times as int64 nanoseconds, "
                             "not floats")
        n = t.shape[0]
        for k in ("x", "y", "p"):
            if data[k].shape != (n,):
                raise InputError(f"{path}: array {k} has shape {data[k].shape}, expected ({n},)")
        p = data["p"]
        if p.size and not np.all((p == 1) | (p == -1)):
            raise InputError(f"{path}: p must hold +1/-1 (found values {np.unique(p)[:5]})")
        width, height = int(data["width"]), int(data["height"])
        x, y = data["x"], data["y"]
        for name, v, limit in (("x", x, width), ("y", y, height)):
            if v.size and (v.min() < 0 or v.max() >= limit):
                raise InputError(f"{path}: {name} outside the declared {width}x{height} geometry "
                                 f"(range {v.min()}..{v.max()}); fix width/height or the data")
        events = make_events(t.astype(np.int64), x, y, p)
        triggers = empty_triggers()
        if "trigger_t" in data.files:
            triggers = make_triggers(data["trigger_t"], data["trigger_id"], data["trigger_value"])
    validate_events(events, width=width, height=height, source=str(path))
    return events, triggers, width, height


def write_npz(path, events, width: int, height: int, triggers=None, *, overwrite=False) -> None:
    validate_events(events, width=width, height=height, source=str(path))
    arrays = dict(t=events["t"], x=events["x"], y=events["y"], p=events["p"],
                  width=np.int64(width), height=np.int64(height))
    if triggers is not None and len(triggers):
        arrays.update(trigger_t=triggers["t"], trigger_id=triggers["id"],
                      trigger_value=triggers["value"])
    with atomic_output(path, overwrite=overwrite) as tmp:
        with open(tmp, "wb") as f:
            np.savez(f, **arrays)
