"""The ``device`` setting of training, evaluation and publishing: ``auto``, ``cpu`` or ``cuda``.

- ``auto``: ``cuda`` when ``torch.cuda.is_available()``, else ``cpu``;
- ``cpu``: always the CPU;
- ``cuda`` (or ``cuda:N``): the GPU; when this torch build has no CUDA, or no GPU is visible,
  :class:`DeviceError` says so and how to fix it. Nothing ever falls back silently: a run that
  asked for the GPU either gets it or stops.

``resolve_device(name)`` gives the ``torch.device``; every tensor of a job is created on it
(rays, samples, grids, the field's weights), and only finished images come back to the CPU
as numpy arrays.

The toolkit pins ``torch==2.13.0``; the wheel pip installs by default on Linux here is the CPU
build. The CUDA build of the same version comes from PyTorch's own index (pick the ``cuXYZ``
matching the machine's NVIDIA driver, see pytorch.org "Get started"): :data:`CUDA_INSTALL`.
"""

from __future__ import annotations

from .errors import InputError

#: The values the setting accepts (``cuda:N`` picks GPU N).
DEVICE_CHOICES = ("auto", "cpu", "cuda")
#: How to get the CUDA build of the pinned torch (into the project's .venv).
CUDA_INDEX_URL = "https://download.pytorch.org/whl/cu128"
CUDA_INSTALL = (f".venv/bin/python -m pip install --force-reinstall torch==2.13.0 --index-url {CUDA_INDEX_URL} "
                "(or the cuXYZ index matching your NVIDIA driver)")


class DeviceError(InputError):
    """A requested device that this machine or this torch build cannot give."""


def check_device_name(name, where: str = "device") -> str:
    """``name`` normalised (lower case) if it is auto, cpu, cuda or cuda:N; else a DeviceError."""
    if not isinstance(name, str):
        raise DeviceError(f"{where}: expected one of auto, cpu, cuda (or cuda:N), got {name!r}")
    s = name.strip().lower()
    if s in DEVICE_CHOICES:
        return s
    if s.startswith("cuda:") and s[5:].isdigit():
        return s
    raise DeviceError(f"{where}: unknown device {name!r}; use auto, cpu, cuda or cuda:N")


def resolve_device(name="auto", where: str = "device"):
    """The ``torch.device`` of the setting ``name`` (module docstring); DeviceError when CUDA is
    requested but absent (never a silent fallback to the CPU)."""
    import torch

    if isinstance(name, torch.device):
        name = str(name)
    s = check_device_name(name, where)
    if s == "cpu":
        return torch.device("cpu")
    available = torch.cuda.is_available()
    if s == "auto":
        return torch.device("cuda" if available else "cpu")
    if not available:
        build = torch.__version__
        why = (f"this torch ({build}) is a CPU-only build" if torch.version.cuda is None
               else f"this torch ({build}, CUDA {torch.version.cuda}) sees no GPU (driver missing, or "
                    "CUDA_VISIBLE_DEVICES hides it)")
        raise DeviceError(f"{where}: device {name!r} requested but {why}; install the CUDA build: "
                          f"{CUDA_INSTALL}; or use device cpu / auto")
    dev = torch.device(s)
    if dev.index is not None and dev.index >= torch.cuda.device_count():
        raise DeviceError(f"{where}: device {name!r} requested but only {torch.cuda.device_count()} GPU(s) "
                          f"are visible (cuda:0..cuda:{torch.cuda.device_count() - 1}); pick one of those")
    return dev


def module_device(module):
    """The device of a module's first parameter (CPU for a module without parameters)."""
    import torch

    for p in module.parameters():
        return p.device
    return torch.device("cpu")


__all__ = ["DEVICE_CHOICES", "CUDA_INDEX_URL", "CUDA_INSTALL", "DeviceError", "check_device_name",
           "resolve_device", "module_device"]
