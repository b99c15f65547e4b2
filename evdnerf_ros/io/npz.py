"""Events as .npz: arrays t (int64 ns), x, y (uint16), p (int8 +1/-1), scalars width, height;
optional trigger arrays trigger_t, trigger_id, trigger_value.

Every .npz the toolkit reads goes through :func:`load_npz`: each array's .npy header is read
first and its declared shape x itemsize checked against the bytes its zip member holds and
against the memory budget, so a crafted header cannot ask for terabytes; a damaged zip (bad
CRC, truncated, bit-flipped) or a pickled object array is a FormatError naming the file and
the array.
"""

from __future__ import annotations

import math
import os
import struct
import zipfile
import zlib

import numpy as np

from ..atomic import atomic_output
from ..errors import FormatError, InputError
from ..events.types import empty_triggers, make_events, make_triggers, validate_events
from ..limits import check_memory, check_number
from .guard import writing

#: What zipfile / zlib / numpy raise on a damaged archive or .npy header.
_NPZ_ERRORS = (zipfile.BadZipFile, zlib.error, EOFError, OSError, ValueError, TypeError, SyntaxError,
               struct.error, NotImplementedError, RuntimeError, OverflowError, UnicodeError)
_FIX = "the file is damaged or truncated; write it again"


def _npy_header(f, source: str, name: str):
    """(shape, fortran_order, dtype) from the .npy header at the start of `f`."""
    fmt = np.lib.format
    version = fmt.read_magic(f)
    if version == (1, 0):
        return fmt.read_array_header_1_0(f)
    if version == (2, 0):
        return fmt.read_array_header_2_0(f)
    raise FormatError(f"{'array ' + name + ': ' if name else ''}.npy format version {version} is not supported",
                      source=source)


def check_npy_file(path, *, loads: bool = True) -> None:
    """Refuse a .npy file whose header declares more data than the file holds, or (with
    `loads`: the array will be read into memory) more than the memory budget, before
    np.load allocates it. Object arrays (pickles) cannot be sized from their header."""
    source = str(path)
    try:
        with open(path, "rb") as f:
            shape, _fortran, dtype = _npy_header(f, source, "")
            header_len = f.tell()
            size = os.fstat(f.fileno()).st_size
    except FormatError:
        raise
    except _NPZ_ERRORS as exc:
        raise FormatError(f"unreadable .npy header ({exc}); {_FIX}", source=source) from None
    if dtype.hasobject:
        return
    nbytes = math.prod(shape) * dtype.itemsize
    if nbytes > size - header_len:
        raise FormatError(f"declares shape {shape} of {dtype} ({nbytes} bytes) but holds {size - header_len} "
                          f"bytes after its header; {_FIX}", source=source)
    if loads:
        check_memory(nbytes, f"{source}: array of shape {shape}", "it needs a machine with more memory")


def _is_npy(path) -> bool:
    try:
        with open(path, "rb") as f:
            return f.read(6) == b"\x93NUMPY"
    except OSError:
        return False


def load_npz(path, names, *, optional=(), what: str = "arrays") -> dict[str, np.ndarray]:
    """The arrays `names` (all required) and those of `optional` that exist, from an .npz.

    Headers are checked before any array is allocated (see the module doc). `what` says in
    messages what the file is for ("an event .npz", "a frames file").
    """
    source = str(path)
    names, optional = list(names), list(optional)
    try:
        zf = zipfile.ZipFile(path)
    except FileNotFoundError:
        raise InputError(f"{source}: no such file") from None
    except IsADirectoryError:
        raise InputError(f"{source}: is a folder, not an .npz file") from None
    except _NPZ_ERRORS as exc:
        if _is_npy(path):
            raise FormatError(f"is a single .npy array, not an .npz archive; {what} holds {names}",
                              source=source) from None
        raise FormatError(f"not a readable .npz file ({exc}); {_FIX}", source=source) from None
    with zf:
        try:
            members = {i.filename[:-4]: i for i in zf.infolist() if i.filename.endswith(".npy")}
        except _NPZ_ERRORS as exc:
            raise FormatError(f"not a readable .npz file ({exc}); {_FIX}", source=source) from None
        missing = [k for k in names if k not in members]
        if missing:
            raise InputError(f"{source}: missing arrays {missing}; {what} holds {names}")
        wanted = names + [k for k in optional if k in members]
        total = 0
        for name in wanted:
            info = members[name]
            try:
                with zf.open(info) as f:
                    shape, _fortran, dtype = _npy_header(f, source, name)
                    header_len = f.tell()
            except FormatError:
                raise
            except _NPZ_ERRORS as exc:
                raise FormatError(f"array {name}: unreadable .npy header ({exc}); {_FIX}", source=source) from None
            if dtype.hasobject:
                raise FormatError(f"array {name} holds Python objects (a pickle), which are never loaded; "
                                  "store plain numeric arrays", source=source)
            nbytes = math.prod(shape) * dtype.itemsize
            if nbytes != info.file_size - header_len:
                raise FormatError(f"array {name} declares shape {shape} of {dtype} ({nbytes} bytes) but its "
                                  f"zip member holds {info.file_size - header_len} bytes; {_FIX}", source=source)
            total += nbytes
        check_memory(total, f"{source}: arrays {', '.join(wanted)}",
                     "the file declares more data than this machine can hold (crafted or damaged), or "
                     "needs a machine with more memory")
        out = {}
        for name in wanted:
            try:
                with zf.open(members[name]) as f:
                    out[name] = np.lib.format.read_array(f, allow_pickle=False)
            except _NPZ_ERRORS as exc:
                raise FormatError(f"array {name} cannot be read ({exc}); {_FIX}", source=source) from None
    return out


def npz_scalar_int(arr: np.ndarray, name: str, *, low: int, high: int) -> int:
    """A one-element integer array (e.g. width) checked against [low, high]; `name` names it."""
    arr = np.asarray(arr)
    if arr.size != 1 or arr.dtype.kind not in "iu":
        raise InputError(f"{name}: expected one integer, got an array of shape {arr.shape} and dtype {arr.dtype}")
    return check_number(arr.reshape(()).item(), name, low=low, high=high, integer=True)


def _column(data: dict, key: str, n: int | None, source: str, kinds: str = "iu") -> np.ndarray:
    a = data[key]
    if a.ndim != 1 or (n is not None and a.shape[0] != n):
        want = "(N,)" if n is None else f"({n},)"
        raise InputError(f"{source}: array {key} has shape {a.shape}, expected {want}")
    if a.dtype.kind not in kinds:
        raise InputError(f"{source}: array {key} has dtype {a.dtype}; expected integers")
    return a


def read_npz(path):
    """Return (events, triggers, width, height) from an .npz written by `write_npz` or by hand."""
    source = str(path)
    data = load_npz(path, ("t", "x", "y", "p", "width", "height"),
                    optional=("trigger_t", "trigger_id", "trigger_value"),
                    what="an event .npz (t int64 ns, x, y, p +1/-1, scalars width, height)")
    t = data["t"]
    if t.ndim == 1 and t.dtype.kind == "f":
        raise InputError(f"{source}: t has dtype {t.dtype}; store times as int64 nanoseconds, not floats")
    t = _column(data, "t", None, source)
    n = t.shape[0]
    x, y = _column(data, "x", n, source), _column(data, "y", n, source)
    p = _column(data, "p", n, source, "iub")
    width = npz_scalar_int(data["width"], f"{source}: width", low=1, high=65535)
    height = npz_scalar_int(data["height"], f"{source}: height", low=1, high=65535)
    if t.dtype == np.uint64 and n and int(t.max()) >= 2**63:
        raise InputError(f"{source}: t holds values beyond int64 nanoseconds (max {int(t.max())})")
    if p.size and p.dtype.kind != "b" and not np.all((p == 1) | (p == -1)):
        raise InputError(f"{source}: p must hold +1/-1 (found values {np.unique(p)[:5]})")
    for name, v, limit in (("x", x, width), ("y", y, height)):
        if v.size and (int(v.min()) < 0 or int(v.max()) >= limit):
            raise InputError(f"{source}: {name} outside the declared {width}x{height} geometry "
                             f"(range {v.min()}..{v.max()}); fix width/height or the data")
    events = make_events(t.astype(np.int64), x, y, p)
    triggers = empty_triggers()
    present = [k for k in ("trigger_t", "trigger_id", "trigger_value") if k in data]
    if present:
        if len(present) != 3:
            raise InputError(f"{source}: has {present} but triggers need all of trigger_t, trigger_id, "
                             "trigger_value")
        tt = _column(data, "trigger_t", None, source)
        ti = _column(data, "trigger_id", tt.shape[0], source)
        tv = _column(data, "trigger_value", tt.shape[0], source, "iub")
        if tt.size and (int(tt.min()) < 0 or int(tt.max()) >= 2**63 or int(ti.min()) < 0
                        or int(ti.max()) > 255 or np.any((tv != 0) & (tv != 1))):
            raise InputError(f"{source}: trigger arrays out of range (times int64 ns >= 0, ids 0..255, "
                             "values 0/1)")
        if np.any(tt[1:] < tt[:-1]):
            raise InputError(f"{source}: trigger_t is not sorted by time")
        triggers = make_triggers(tt.astype(np.int64), ti, tv)
    validate_events(events, width=width, height=height, source=source)
    return events, triggers, width, height


def write_npz(path, events, width: int, height: int, triggers=None, *, overwrite=False) -> None:
    validate_events(events, width=width, height=height, source=str(path))
    arrays = dict(t=events["t"], x=events["x"], y=events["y"], p=events["p"],
                  width=np.int64(width), height=np.int64(height))
    if triggers is not None and len(triggers):
        arrays.update(trigger_t=triggers["t"], trigger_id=triggers["id"],
                      trigger_value=triggers["value"])
    with atomic_output(path, overwrite=overwrite) as tmp, writing(path):
        with open(tmp, "wb") as f:
            np.savez(f, **arrays)
