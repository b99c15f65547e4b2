"""Atomic checkpoints that resume bit-exactly.

A checkpoint (``torch.save`` of a dict, written through ``atomic_output``) holds:
``format``, ``software_version``, ``iteration``, ``config`` (TrainConfig as a dict),
``backbone``, ``field`` (state dict), ``optimizer`` (state dict), ``rng`` (torch, numpy
and python global states plus the trainer's own sampler/sample generators), ``box`` and
``extra`` (counters such as training seconds and skipped steps).

Loading checks the format and that the software major version matches this one; a
resuming run must have the same config (apart from logging cadence and budget).
"""

from __future__ import annotations

import random
from pathlib import Path

import numpy as np
import torch

from .. import __version__
from ..atomic import atomic_output
from ..errors import InputError

FORMAT = "evdnerf_ros.checkpoint"
FORMAT_VERSION = 1


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


def save_checkpoint(path, *, field, optimizer, iteration: int, config: dict, backbone: str,
                    rng: dict, box, extra: dict | None = None) -> Path:
    path = Path(path)
    data = {"format": FORMAT, "format_version": FORMAT_VERSION, "software_version": __version__,
            "iteration": int(iteration), "config": dict(config), "backbone": backbone,
            "field": field.state_dict(),
            "optimizer": optimizer.state_dict() if optimizer is not None else None,
            "rng": rng, "box": np.asarray(box, np.float64).tolist(), "extra": dict(extra or {})}
    with atomic_output(path, overwrite=True) as tmp:
        torch.save(data, tmp)
    return path


def load_checkpoint(path) -> dict:
    """Read and check a checkpoint (format, software major version)."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"{path}: no such checkpoint")
    try:
        data = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as exc:  # noqa: BLE001 - any unpickling failure means a bad file
        raise CheckpointError(f"{path}: not a readable checkpoint ({type(exc).__name__}: {exc})") from None
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        raise CheckpointError(f"{path}: not an evdnerf_ros training checkpoint")
    if int(data.get("format_version", -1)) != FORMAT_VERSION:
        raise CheckpointError(f"{path}: checkpoint format version {data.get('format_version')} is not "
                              f"supported (this software reads {FORMAT_VERSION})")
    theirs = str(data.get("software_version"))
    if major(theirs) != major(__version__):
        raise CheckpointError(f"{path}: written by evdnerf_ros {theirs}, major version "
                              f"{major(theirs)}; this is {__version__} (major {major(__version__)}); "
                              "retrain, or use the matching software version")
    return data
