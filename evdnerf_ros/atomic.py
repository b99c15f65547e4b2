"""Atomic outputs: write to a hidden temporary sibling, rename into place only on success.

Every writer in the toolkit goes through `atomic_output`, so an interrupted or failed job
never leaves a half-written file or bag directory behind.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

from .errors import InputError, OutputExistsError


@contextmanager
def atomic_output(path, *, overwrite: bool = False, directory: bool = False) -> Iterator[Path]:
    """Yield a temporary path next to `path`; on clean exit rename it to `path`.

    The temporary path does not exist yet when yielded when `directory` is True (writers
    such as rosbags create the directory themselves); otherwise it is an empty file.
    """
    path = Path(path)
    if path.exists() and not overwrite:
        raise OutputExistsError(path)
    parent = path.parent if str(path.parent) else Path(".")
    if not parent.is_dir():
        raise InputError(f"{path}: parent folder {parent} does not exist; create it first")
    tmp_dir = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".partial", dir=parent))
    tmp = tmp_dir / path.name
    if not directory:
        tmp.touch()
    try:
        yield tmp
        if overwrite and path.exists():
            shutil.rmtree(path) if path.is_dir() else path.unlink()
        _publish(tmp, path, no_clobber=not overwrite)
    finally:
        shutil.rmtree(tmp_dir, ignore_errors=True)


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
    if no_clobber and path.exists():
        raise OutputExistsError(path)
    os.replace(tmp, path)
