"""The run folder of ``evdnerf train``: its lock, and keeping metrics.jsonl in step with
the checkpoint.

Lock: ``RUN/.evdnerf-train.lock``, held with ``flock`` (exclusive, non-blocking) for the
whole run, holding the owner's pid.  A second ``train`` into the same folder fails at once
naming that pid.  The kernel drops the lock when its process dies however it dies, so
the file a killed run leaves behind never blocks the next one; it stays in RUN and marks
the folder as one ``train`` made (an interrupted first start, with config.yaml and
metrics.jsonl but no checkpoint yet, is then simply started again).

Metrics: on resume, lines past the checkpoint's iteration (written after it, before the
run stopped) and lines cut short by a kill are dropped, the file rewritten atomically, so
a resumed run's metrics.jsonl holds each line once, as an uninterrupted run's would.
"""

from __future__ import annotations

import errno
import json
import os
from pathlib import Path

from ..atomic import atomic_output
from ..errors import InputError
from ..limits import check_memory

LOCK_NAME = ".evdnerf-train.lock"
#: The files of a run folder (``train/run.py`` reads them back as a ``TrainedRun``).
CHECKPOINT_NAME = "checkpoint.pt"
METRICS_NAME = "metrics.jsonl"
CONFIG_NAME = "config.yaml"
_LOCK_TEXT = "evdnerf_ros train"
# file systems that cannot lock: run unlocked rather than not at all
_NO_LOCKING = (errno.ENOLCK, errno.EOPNOTSUPP, errno.ENOSYS)

try:
    import fcntl
except ImportError:  # pragma: no cover - not on POSIX
    fcntl = None


class RunLock:
    """Exclusive lock of a run folder (module docstring).  ``made_by_train``: the lock file
    was already there, written by an earlier ``train``."""

    def __init__(self, run_dir, *, log=print):
        self.run_dir = Path(run_dir)
        self.path = self.run_dir / LOCK_NAME
        self.log = log
        self.fd = None
        self.made_by_train = False

    def __enter__(self) -> "RunLock":
        for _ in range(100):       # retried only when the file is replaced under us
            existed = True
            try:
                fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_EXCL | os.O_CLOEXEC, 0o644)
                existed = False
            except FileExistsError:
                try:
                    fd = os.open(self.path, os.O_RDWR | os.O_CLOEXEC)
                except FileNotFoundError:
                    continue
            if not self._lock(fd):
                continue
            self.made_by_train = existed and _read(fd).startswith(_LOCK_TEXT)
            os.ftruncate(fd, 0)
            os.pwrite(fd, f"{_LOCK_TEXT} pid {os.getpid()}\n".encode(), 0)
            self.fd = fd
            return self
        raise InputError(f"{self.path}: could not be locked (it keeps being replaced); "
                         "is another program deleting files in the run folder?")

    def _lock(self, fd) -> bool:
        """True once locked; False if the path now names another file (retry)."""
        if fcntl is not None:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                holder = _read(fd).removeprefix(_LOCK_TEXT).strip() or "pid unknown"
                os.close(fd)
                raise InputError(f"{self.run_dir}: another train process ({holder}) is using this "
                                 "run folder; wait for it to finish or stop it, or choose another "
                                 "folder") from None
            except OSError as exc:
                if exc.errno not in _NO_LOCKING:
                    os.close(fd)
                    raise
                self.log(f"warning: {self.path}: this file system cannot lock files; nothing "
                         "stops a second train process from using the same folder")
        try:
            same = os.fstat(fd).st_ino == os.stat(self.path).st_ino
        except FileNotFoundError:
            same = False
        if not same:
            os.close(fd)
        return same

    def __exit__(self, *exc) -> bool:
        if self.fd is not None:
            os.close(self.fd)          # releases the lock
            self.fd = None
        return False


def _read(fd) -> str:
    try:
        return os.pread(fd, 256, 0).decode("utf-8", "replace")
    except OSError:
        return ""


def truncate_metrics(path, iteration: int) -> int:
    """Drop lines of a metrics.jsonl past ``iteration`` or unreadable; return how many."""
    path = Path(path)
    if not path.is_file():
        return 0
    check_memory(2.0 * path.stat().st_size, f"{path}: reading", "remove or shorten it")
    raw = path.read_bytes()
    keep, dropped = [], 0
    for line in raw.split(b"\n"):
        if not line.strip():
            continue
        try:
            it = json.loads(line).get("iter")
        except (ValueError, AttributeError):          # cut short by a kill, or not ours
            it = None
        if isinstance(it, int) and not isinstance(it, bool) and it <= iteration:
            keep.append(line + b"\n")
        else:
            dropped += 1
    if dropped or (raw and not raw.endswith(b"\n")):
        with atomic_output(path, overwrite=True) as tmp:
            tmp.write_bytes(b"".join(keep))
    return dropped


def write_text(path, text: str) -> None:
    """Replace a small text file of the run atomically."""
    with atomic_output(path, overwrite=True) as tmp:
        tmp.write_text(text)
