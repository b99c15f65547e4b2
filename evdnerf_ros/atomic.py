"""Atomic outputs: write to a hidden temporary sibling, rename into place only on success.

Every writer in the toolkit goes through `atomic_output`, so an interrupted or failed job
never leaves a half-written file or bag directory behind. The rules it keeps:

- What exists is never replaced unless the caller passes ``overwrite`` (the user's
  ``--overwrite``), and then only what the toolkit itself makes there: a *file* where a file
  is expected, a *folder carrying our marker* (``.evdnerf-output``, written into every folder
  output) where a folder is expected. A folder is never replaced by a file, a file never by a
  folder, and a folder we did not make is never deleted.
- The temporary sibling is ``.<name>.<pid>.<random>.partial``. A job killed outright
  (SIGKILL, power loss) cannot remove it; the next job writing the same output finds it,
  sees that its process is gone, removes it and says so on stderr. The exception is a
  killed recording whose bag already holds flushed messages: that is data, so it is kept
  and the note says how to salvage it (`evdnerf salvage-bag`).
- `check_output` runs the same checks up front, so a command can refuse a bad output path
  before it spends minutes (or a recording) on work that could not be saved.
"""

from __future__ import annotations

import os
import shutil
import sys
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

from .errors import InputError, OutputExistsError

# Written into every folder output: what lets --overwrite replace a folder we made and
# nothing else.
MARKER = ".evdnerf-output"
PARTIAL_SUFFIX = ".partial"


def check_output(path, *, overwrite: bool = False, directory: bool = False) -> Path:
    """Raise unless `path` may be written: its folder exists and is writable, and nothing is
    there, or (with `overwrite`) only something of the kind we would write there."""
    path = Path(path)
    if path.exists() or path.is_symlink():
        if not overwrite:
            raise OutputExistsError(path)
        if directory and not path.is_dir():
            raise InputError(f"{path}: exists and is not a folder; remove it or choose another path "
                             "(--overwrite replaces only a folder this toolkit wrote)")
        if directory and not (path / MARKER).is_file():
            raise InputError(f"{path}: this folder was not written by evdnerf (no {MARKER} in it), so "
                             "--overwrite will not delete it; remove it yourself or choose another path")
        if not directory and (path.is_dir() or not path.is_file()):
            raise InputError(f"{path}: is a folder (or not a regular file), and a file is to be written "
                             "here; --overwrite never deletes folders; choose a file path")
    parent = _parent(path)
    if not parent.is_dir():
        raise InputError(f"{path}: parent folder {parent} does not exist; create it first")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise InputError(f"{path}: cannot write into {parent} (permission denied or read-only); "
                         "choose another path")
    return path


@contextmanager
def atomic_output(path, *, overwrite: bool = False, directory: bool = False) -> Iterator[Path]:
    """Yield a temporary path next to `path`; on clean exit rename it to `path`.

    The temporary path does not exist yet when yielded when `directory` is True (writers
    such as rosbags create the directory themselves); otherwise it is an empty file.
    """
    path = check_output(path, overwrite=overwrite, directory=directory)
    parent = _parent(path)
    remove_stale_partials(parent, path.name)
    tmp_dir = Path(tempfile.mkdtemp(prefix=f".{path.name}.{os.getpid()}.", suffix=PARTIAL_SUFFIX,
                                    dir=parent))
    tmp = tmp_dir / path.name
    try:
        if not directory:
            tmp.touch()
        yield tmp
        if directory:
            if not tmp.is_dir():
                raise InputError(f"{path}: the writer made no folder; nothing was written")
            (tmp / MARKER).write_text("written by evdnerf_ros; --overwrite may replace this folder\n")
        if overwrite and (path.exists() or path.is_symlink()):
            check_output(path, overwrite=True, directory=directory)   # still ours?
            shutil.rmtree(path) if directory else path.unlink()
        _publish(tmp, path, no_clobber=not overwrite)
    except OSError as exc:
        name_output_error(exc, path)
        raise
    finally:
        shutil.rmtree(tmp_dir, ignore_errors=True)


def name_output_error(exc: BaseException, path) -> None:
    """A write through a file object fails without naming the file: name the output it was for."""
    # Only an errno-carrying OSError prints its filename; others keep their own message.
    if isinstance(exc, OSError) and exc.filename is None and exc.errno is not None:
        exc.filename = str(path)


def remove_stale_partials(parent: Path, name: str) -> list[Path]:
    """Remove `.<name>.<pid>.*.partial` siblings whose process no longer runs; report each."""
    removed = []
    prefix = f".{name}."
    try:
        entries = list(parent.iterdir())
    except OSError:
        return removed
    for entry in entries:
        n = entry.name
        if not (n.startswith(prefix) and n.endswith(PARTIAL_SUFFIX)):
            continue
        pid_text = n[len(prefix):].split(".", 1)[0]
        if not pid_text.isdigit() or _process_alive(int(pid_text)):
            continue
        if _holds_recording(entry):
            print(f"evdnerf: kept {entry}: the unfinished bag of a recording that was killed (process "
                  f"{pid_text}); `evdnerf salvage-bag {entry} -o BAG` writes out its messages, then "
                  "delete it", file=sys.stderr)
            continue
        shutil.rmtree(entry, ignore_errors=True)
        if not entry.exists():
            removed.append(entry)
            print(f"evdnerf: removed {entry}, the unfinished output of an earlier run (process "
                  f"{pid_text}) that was killed", file=sys.stderr)
    return removed


def _holds_recording(partial: Path) -> bool:
    """A killed recording's flushed MCAP chunks are data, not debris: never delete them."""
    try:
        return any(f.stat().st_size > 64 for f in partial.rglob("*.mcap"))
    except OSError:
        return False


def _process_alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:          # alive, owned by someone else
        return True
    return True


def _parent(path: Path) -> Path:
    return path.parent if str(path.parent) else Path(".")


def _publish(tmp: Path, path: Path, *, no_clobber: bool) -> None:
    """Move tmp to path; with no_clobber a file that appeared meanwhile is never replaced."""
    if no_clobber and tmp.is_file():
        try:
            os.link(tmp, path)            # fails if path exists: no race with another writer
            return
        except FileExistsError:
            raise OutputExistsError(path) from None
        except OSError:                   # file systems without hard links
            pass
    if no_clobber and (path.exists() or path.is_symlink()):
        raise OutputExistsError(path)
    os.replace(tmp, path)
