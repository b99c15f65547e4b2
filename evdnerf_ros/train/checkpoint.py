"""Atomic, checksummed checkpoints that resume bit-exactly.

A checkpoint holds a dict: ``format``, ``format_version``, ``software_version``,
``iteration``, ``config`` (TrainConfig as a dict), ``backbone``, ``field`` (state dict),
``optimizer`` (state dict), ``rng`` (torch, numpy and python global states plus the
trainer's own sampler/sample generators), ``box`` and ``extra`` (counters such as training
seconds and skipped steps, the losses since the last metrics line).

File layout (format 2): one ASCII header line, then the ``torch.save`` bytes of that dict::

    EVDNERF_ROS-CHECKPOINT 2 sha256=<64 hex digits>\\n<payload>

The SHA-256 covers every payload byte, so any damage (a flipped bit, a truncated copy)
is found before a byte is unpickled, and one to the header line makes it unreadable as
ours.  Read checkpoints with ``load_checkpoint`` (``torch.load`` does not read this
layout).  Files are written through ``atomic_output`` (a hidden sibling, synced to disk,
renamed into place), so a crash or Ctrl-C mid-write leaves the previous checkpoint intact.
Format 1 files (a bare ``torch.save``, before checksums) are still read, unverified.

Loading checks the checksum, the format and that the software major version matches this
one; a resuming run must have the same config (apart from logging cadence and budget).
"""

from __future__ import annotations

import hashlib
import io
import os
import random
from pathlib import Path

import numpy as np
import torch

from .. import __version__
from ..atomic import atomic_output
from ..errors import InputError
from ..limits import check_memory

FORMAT = "evdnerf_ros.checkpoint"
FORMAT_VERSION = 2
MAGIC = b"EVDNERF_ROS-CHECKPOINT"
_ZIP = b"PK\x03\x04"                   # how a bare torch.save file (format 1) starts
_HEADER_MAX = 128
DAMAGED_HINT = "restore it from a copy or remove it"


class CheckpointError(InputError):
    """A checkpoint that cannot be used here (damaged, other version, other config)."""


def major(version: str) -> int:
    try:
        return int(str(version).split(".")[0])
    except ValueError:
        return -1


def global_rng_states() -> dict:
    return {"torch": torch.get_rng_state(), "numpy": np.random.get_state(),
            "python": random.getstate()}


def set_global_rng_states(states: dict) -> None:
    torch.set_rng_state(states["torch"])
    np.random.set_state(states["numpy"])
    random.setstate(states["python"])


def header(payload) -> bytes:
    return MAGIC + b" %d sha256=%s\n" % (FORMAT_VERSION, hashlib.sha256(payload).hexdigest().encode())


def save_checkpoint(path, *, field, optimizer, iteration: int, config: dict, backbone: str,
                    rng: dict, box, extra: dict | None = None) -> Path:
    path = Path(path)
    data = {"format": FORMAT, "format_version": FORMAT_VERSION, "software_version": __version__,
            "iteration": int(iteration), "config": dict(config), "backbone": backbone,
            "field": field.state_dict(),
            "optimizer": optimizer.state_dict() if optimizer is not None else None,
            "rng": rng, "box": np.asarray(box, np.float64).tolist(), "extra": dict(extra or {})}
    buf = io.BytesIO()
    torch.save(data, buf)
    payload = buf.getbuffer()
    with atomic_output(path, overwrite=True) as tmp:
        with open(tmp, "wb") as f:
            f.write(header(payload))
            f.write(payload)
            f.flush()
            os.fsync(f.fileno())       # on disk before the rename makes it the checkpoint
    return path


def load_checkpoint(path) -> dict:
    """Read and check a checkpoint: checksum, format, software major version."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"{path}: no such checkpoint")
    with open(path, "rb") as f:
        start = f.read(_HEADER_MAX)
    if start.startswith(MAGIC):
        data = _read_checked(path, start)
    elif start.startswith(_ZIP):
        data = _read_bare(path)
    else:
        raise CheckpointError(f"{path}: not an evdnerf_ros training checkpoint")
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        raise CheckpointError(f"{path}: not an evdnerf_ros training checkpoint")
    theirs = str(data.get("software_version"))
    if major(theirs) != major(__version__):
        raise CheckpointError(f"{path}: written by evdnerf_ros {theirs}, major version "
                              f"{major(theirs)}; this is {__version__} (major {major(__version__)}); "
                              "retrain, or use the matching software version")
    version = data.get("format_version")
    if start.startswith(_ZIP) and version != 1:
        # a current-format dict without the checksummed header: not a file we wrote
        raise CheckpointError(f"{path}: checkpoint format version {version!r} without its "
                              f"checksum header: damaged or not written by evdnerf_ros; {DAMAGED_HINT}")
    if version not in (1, FORMAT_VERSION):
        raise CheckpointError(f"{path}: checkpoint format version {version!r} is not supported "
                              f"(this software reads 1 and {FORMAT_VERSION})")
    return data


def _read_checked(path: Path, start: bytes) -> dict:
    line, newline, _ = start.partition(b"\n")
    fields = line.split(b" ")
    if (not newline or len(fields) != 3 or not fields[2].startswith(b"sha256=")
            or len(fields[2]) != 7 + 64):
        raise CheckpointError(f"{path}: damaged checkpoint header; {DAMAGED_HINT}")
    if fields[1] != b"%d" % FORMAT_VERSION:
        raise CheckpointError(f"{path}: checkpoint format version {fields[1].decode(errors='replace')!r} "
                              f"is not supported (this software reads {FORMAT_VERSION}): written by "
                              f"another software version, or damaged; {DAMAGED_HINT}")
    size = path.stat().st_size
    # the bytes, then the tensors unpickled from them
    check_memory(3.0 * size, f"{path}: reading this {size}-byte checkpoint", "free memory")
    raw = path.read_bytes()
    payload = memoryview(raw)[len(line) + 1:]
    if hashlib.sha256(payload).hexdigest().encode() != fields[2][7:]:
        raise CheckpointError(f"{path}: damaged checkpoint (its SHA-256 checksum does not match "
                              f"its contents); {DAMAGED_HINT}")
    try:
        return torch.load(io.BytesIO(payload), map_location="cpu", weights_only=False)
    except Exception as exc:  # noqa: BLE001 - checksum fine but unreadable: another writer
        raise CheckpointError(f"{path}: not a readable checkpoint ({type(exc).__name__}: {exc}); "
                              f"{DAMAGED_HINT}") from None


def _read_bare(path: Path) -> dict:
    """Format 1: a plain torch.save file (no checksum)."""
    try:
        return torch.load(path, map_location="cpu", weights_only=False)
    except Exception as exc:  # noqa: BLE001 - any unpickling failure means a bad file
        raise CheckpointError(f"{path}: not a readable checkpoint ({type(exc).__name__}: "
                              f"{' '.join(str(exc).split())[:200]}); {DAMAGED_HINT}") from None
