"""The file boundary: what every reader and writer of this package does with a damaged file,
a crafted header or a full disk, so that the user gets one line naming the file instead of
a traceback, a huge allocation or a crash inside HDF5.

Readers
    :func:`h5_reading` turns what h5py raises on a damaged file (OSError from a failed
    filter or read, KeyError from an object that cannot be opened, TypeError / ValueError
    from a damaged type or shape, ...) into :class:`FormatError` naming the file and the
    object. :func:`h5_dataset` checks an object is a dataset of the expected rank and dtype
    kind, and :func:`h5_number` checks an attribute, before anything is read.
    :func:`read_text` reads a YAML / JSON / CSV file as UTF-8, naming the byte offset of the
    first byte that is not.

Writers
    HDF5 buffers what it writes and may write it only when a dataset or the file is closed;
    when that write fails (disk full, file-size limit), libhdf5 2.0 segfaults on close. So
    HDF5 files are written through :class:`GuardedFile`: a file object that never reports a
    failed write to HDF5. It records the first failure and keeps what HDF5 writes after it in
    memory, so HDF5 closes cleanly; the writer checks :meth:`GuardedFile.check` after every
    step and raises :class:`OutputWriteError` naming the output (the atomic-output helper
    then removes the partial file, which nothing ever re-opens).
    :func:`check_free_space` refuses up front an output that clearly cannot fit.
"""

from __future__ import annotations

import errno
import io
import math
import os
from contextlib import contextmanager
from pathlib import Path

from ..errors import EvdnerfError, FormatError, InputError
from ..limits import check_memory, check_number, format_bytes

#: What h5py / libhdf5 raise on a damaged file or object (not on our own mistakes: those
#: are AttributeError / NameError and stay tracebacks).
H5_ERRORS = (OSError, KeyError, ValueError, TypeError, RuntimeError, IndexError, OverflowError,
             UnicodeError, MemoryError)

#: Text configuration files larger than this are not configuration files.
MAX_TEXT_BYTES = 64 << 20

DAMAGED_HINT = "the file is damaged or truncated; write it again"


class OutputWriteError(EvdnerfError, OSError):
    """An output could not be written (disk full, file-size limit, I/O error); nothing of it
    was left behind. Also an OSError, which is what it is."""


# =========================================================================== reading


@contextmanager
def h5_reading(path, what: str = "", hint: str = DAMAGED_HINT):
    """Turn h5py's errors on a damaged file into FormatError naming `path` and `what`."""
    try:
        yield
    except EvdnerfError:
        raise
    except MemoryError:
        raise FormatError(f"{what + ': ' if what else ''}reading needs more memory than is free; "
                          f"{hint}", source=str(path)) from None
    except H5_ERRORS as exc:
        raise FormatError(f"{what + ': ' if what else ''}cannot be read ({_short(exc)}); {hint}",
                          source=str(path)) from None


def h5_open(path, *, hint: str = DAMAGED_HINT, **kwargs):
    """h5py.File(path, "r") with its failures (not HDF5, truncated, a folder) named."""
    import h5py

    path = Path(path)
    if path.is_dir():
        raise InputError(f"{path}: is a folder, not an HDF5 file")
    if path.exists() and path.stat().st_size == 0:
        raise FormatError(f"file is empty (0 bytes); {hint}", source=str(path))
    try:
        return h5py.File(path, "r", **kwargs)
    except FileNotFoundError:
        raise InputError(f"{path}: no such file") from None
    except H5_ERRORS as exc:
        raise FormatError(f"not a readable HDF5 file ({_short(exc)}); {hint}", source=str(path)) from None


def h5_dataset(group, name: str, path, *, ndim: int | None = None, kinds: str = "iu",
               shape: tuple | None = None, what: str | None = None):
    """The dataset `name` of `group`, checked (rank, dtype kind, shape) before any read."""
    import h5py

    what = what or name
    with h5_reading(path, what):
        obj = group.get(name)
        if not isinstance(obj, h5py.Dataset):
            found = "missing" if obj is None else f"a {type(obj).__name__}, not a dataset"
            raise FormatError(f"{what} is {found}; {DAMAGED_HINT}", source=str(path))
        dshape, dtype = obj.shape, obj.dtype
    if dshape is None or (ndim is not None and len(dshape) != ndim):
        raise FormatError(f"{what} has shape {dshape}, expected {ndim} dimension(s); {DAMAGED_HINT}",
                          source=str(path))
    if shape is not None and tuple(dshape) != tuple(shape):
        raise FormatError(f"{what} has shape {tuple(dshape)}, expected {tuple(shape)}; {DAMAGED_HINT}",
                          source=str(path))
    if dtype.kind not in kinds or dtype.fields is not None:
        raise FormatError(f"{what} has dtype {dtype}, expected {_kind_names(kinds)}; {DAMAGED_HINT}",
                          source=str(path))
    return obj


def h5_memory(nbytes: int, path, what: str) -> None:
    """check_memory for an allocation sized by a file's declared shapes."""
    check_memory(nbytes, f"{path}: {what}",
                 "the file declares more data than this machine can hold; it is crafted or damaged, "
                 "or needs a machine with more memory")


_MISSING = object()


def _h5_attr(attrs, key: str, path, required: bool):
    """The raw attribute, or _MISSING when it is absent and not required."""
    try:
        if key not in attrs:
            if required:
                raise FormatError(f"attribute {key!r} is missing; {DAMAGED_HINT}", source=str(path))
            return _MISSING
        return attrs[key]
    except H5_ERRORS as exc:
        raise FormatError(f"attribute {key!r} cannot be read ({_short(exc)})", source=str(path)) from None


def h5_number(attrs, key: str, path, *, required: bool = True, default=None, **limits):
    """A numeric HDF5 attribute, checked with check_number (a one-element array counts as
    its element); InputError naming the file and the attribute."""
    import numpy as np

    name = f"{path}: attribute {key}"
    value = _h5_attr(attrs, key, path, required)
    if value is _MISSING:
        return default
    if isinstance(value, np.ndarray):
        if value.size != 1:
            raise FormatError(f"attribute {key!r} has shape {value.shape}, expected one number",
                              source=str(path))
        value = value.reshape(()).item() if value.dtype.kind in "iufb" else value
    if isinstance(value, np.generic):
        value = value.item()
    return check_number(value, name, **limits)


def h5_text(attrs, key: str, path, *, required: bool = True, default=None) -> str | None:
    """A string attribute (HDF5 stores them as str or bytes)."""
    value = _h5_attr(attrs, key, path, required)
    if value is _MISSING:
        return default
    if isinstance(value, bytes):
        try:
            value = value.decode("utf-8")
        except UnicodeDecodeError:
            raise FormatError(f"attribute {key!r} is not UTF-8 text", source=str(path)) from None
    if not isinstance(value, str):
        raise FormatError(f"attribute {key!r} is {type(value).__name__}, expected text", source=str(path))
    return value


def read_text(path, *, what: str = "file", max_bytes: int = MAX_TEXT_BYTES) -> str:
    """The UTF-8 text of a configuration file (YAML / JSON / CSV); errors name the file and,
    for bytes that are not UTF-8, their offset."""
    path = Path(path)
    try:
        size = path.stat().st_size
        if path.is_dir():
            raise InputError(f"{path}: is a folder, not a {what}")
        if size > max_bytes:
            raise InputError(f"{path}: {format_bytes(size)} is too large for a {what} (at most "
                             f"{format_bytes(max_bytes)}); is this the right file?")
        data = path.read_bytes()
    except FileNotFoundError:
        raise InputError(f"{path}: no such {what}") from None
    except PermissionError:
        raise InputError(f"{path}: cannot read the {what} (permission denied)") from None
    except OSError as exc:
        raise InputError(f"{path}: cannot read the {what} ({exc.strerror or exc})") from None
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = data.count(b"\n", 0, exc.start) + 1
        raise FormatError(f"byte {data[exc.start]:#04x} on line {line} is not UTF-8 text; save the "
                          f"{what} as UTF-8", source=str(path), offset=exc.start) from None
    return text.removeprefix("\ufeff")


def _short(exc: BaseException) -> str:
    text = str(exc).replace("\n", " ").strip() or type(exc).__name__
    return text if len(text) <= 200 else text[:197] + "..."


def _kind_names(kinds: str) -> str:
    names = {"i": "integers", "u": "unsigned integers", "f": "floats", "b": "booleans"}
    return " or ".join(names[k] for k in kinds if k in names)


# =========================================================================== writing


class GuardedFile(io.RawIOBase):
    """A binary file for h5py's file-object driver that never reports a failed write to
    HDF5 (see the module doc). After the first failure, writes land in an in-memory overlay
    that reads see, so HDF5 finishes and closes cleanly; the data written after the failure
    is bounded by one writer step (the writer checks :meth:`check` after each)."""

    def __init__(self, path, display=None):
        super().__init__()
        self.path = Path(path)
        self.display = Path(display) if display is not None else self.path
        self._fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_TRUNC, 0o666)
        self._pos = 0
        self.error: OSError | None = None
        self._overlay: list[tuple[int, bytes]] = []     # (offset, data), in write order
        self._overlay_end = 0

    # ----- io protocol
    def readable(self):
        return True

    def writable(self):
        return True

    def seekable(self):
        return True

    def tell(self):
        return self._pos

    def seek(self, offset, whence=os.SEEK_SET):
        if whence == os.SEEK_SET:
            self._pos = offset
        elif whence == os.SEEK_CUR:
            self._pos += offset
        else:
            self._pos = self._size() + offset
        return self._pos

    def _size(self) -> int:
        return max(os.fstat(self._fd).st_size, self._overlay_end)

    def readinto(self, buf):
        mv = memoryview(buf).cast("B")
        n = os.preadv(self._fd, [mv], self._pos)
        if self._overlay:
            end = self._pos + len(mv)
            for off, data in self._overlay:
                a, b = max(off, self._pos), min(off + len(data), end)
                if a < b:
                    mv[a - self._pos:b - self._pos] = data[a - off:b - off]
                    n = max(n, b - self._pos)
        self._pos += n
        return n

    def write(self, buf):
        data = bytes(buf)
        if self.error is None:
            done = 0
            try:
                while done < len(data):
                    k = os.pwrite(self._fd, data[done:], self._pos + done)
                    if k <= 0:
                        raise OSError(errno.EIO, "write made no progress")
                    done += k
                self._pos += done
                return done
            except OSError as exc:
                self.error = exc
        self._overlay.append((self._pos, data))
        self._overlay_end = max(self._overlay_end, self._pos + len(data))
        self._pos += len(data)
        return len(data)

    def truncate(self, size=None):
        size = self._pos if size is None else size
        if self.error is None:
            try:
                os.ftruncate(self._fd, size)
            except OSError as exc:
                self.error = exc
        return size

    def flush(self):
        pass

    def close(self):
        if not self.closed:
            self._overlay.clear()
            try:
                os.close(self._fd)
            except OSError as exc:    # a delayed write error (NFS, ...) shows up here
                if self.error is None:
                    self.error = exc
        super().close()

    # ----- for the writer
    def check(self) -> None:
        """Raise OutputWriteError naming the output if any write has failed."""
        if self.error is not None:
            raise write_error(self.display, self.error)


def write_error(output, exc: OSError) -> OutputWriteError:
    """The one-line error for a failed write of `output` (the temporary file is not named:
    it is removed)."""
    output = Path(output)
    reason = exc.strerror or str(exc) or type(exc).__name__
    if exc.errno == errno.EFBIG:
        reason += " (the file-size limit, ulimit -f, was reached)"
    free = free_bytes(output.parent if str(output.parent) else Path("."))
    where = f"; {format_bytes(free)} can be written in {output.parent}" if free is not None else ""
    return OutputWriteError(f"{output}: writing failed: {reason}{where}; nothing was written "
                            "(free some space or choose another folder, then run again)")


@contextmanager
def writing(output):
    """Turn an OSError raised while writing `output` into OutputWriteError naming it."""
    try:
        yield
    except OutputWriteError:
        raise
    except OSError as exc:
        raise write_error(output, exc) from None


def free_bytes(folder) -> int | None:
    """Bytes this process may still write into `folder`: free space, capped by the
    file-size limit (ulimit -f); None when unknown."""
    try:
        st = os.statvfs(folder)
    except OSError:
        return None
    free = st.f_bavail * st.f_frsize
    try:
        import resource

        soft, _ = resource.getrlimit(resource.RLIMIT_FSIZE)
        if soft != resource.RLIM_INFINITY:
            free = min(free, soft)
    except (ImportError, ValueError, OSError):
        pass
    return free


def check_free_space(output, nbytes: float, what: str) -> None:
    """Refuse up front an output that clearly cannot fit (`nbytes`: a lower estimate)."""
    output = Path(output)
    folder = output.parent if str(output.parent) else Path(".")
    free = free_bytes(folder)
    if free is not None and math.isfinite(nbytes) and free < nbytes:
        raise OutputWriteError(f"{output}: {what} needs at least about {format_bytes(nbytes)} but only "
                               f"{format_bytes(free)} can be written in {folder} (free space or ulimit -f); "
                               "free some space or choose another folder")


def h5_create(path, display=None):
    """(h5py.File, GuardedFile) for writing a new HDF5 file at `path` (a temporary path from
    the atomic-output helper; `display` is the output's real name for messages)."""
    import h5py

    guard = GuardedFile(path, display)
    try:
        f = h5py.File(guard, "w")
    except BaseException:
        guard.close()
        raise
    return f, guard


def h5_close(f, guard: GuardedFile, *, check: bool = True) -> None:
    """Close an HDF5 file made by :func:`h5_create`, then its guard; raise the first write
    failure unless `check` is False (an error is already on its way)."""
    try:
        if f is not None and f.id.valid:
            f.close()
    finally:
        guard.close()
    if check:
        guard.check()
