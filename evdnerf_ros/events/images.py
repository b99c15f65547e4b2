"""Event images: red = positive, blue = negative on white (the paper's figure style), PNG out."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..atomic import atomic_output
from ..errors import InputError
from .accumulate import polarity_counts

WHITE = np.array([255, 255, 255], np.float32)
RED = np.array([220, 30, 30], np.float32)
BLUE = np.array([30, 60, 220], np.float32)


def event_image(events: np.ndarray, width: int, height: int, *, saturation: int = 1) -> np.ndarray:
    """(H, W, 3) uint8: pixels with net positive events red, net negative blue, others white.

    `saturation` is the |net count| at which the colour is full; fewer events are paler.
    """
    n = polarity_counts(events, width, height)
    return signed_to_rgb((n[0] - n[1]).astype(np.float32), vmax=float(saturation))


def signed_to_rgb(image: np.ndarray, vmax: float | None = None) -> np.ndarray:
    """Map a signed image (net counts or dL) to red/white/blue; vmax = max |image| if None."""
    image = np.asarray(image, np.float32)
    if vmax is None:
        vmax = float(np.max(np.abs(image))) if image.size else 0.0
    if not np.isfinite(vmax) or vmax < 0:
        raise InputError(f"colour scale vmax must be finite and >= 0, got {vmax}")
    if vmax == 0:
        return np.full(image.shape + (3,), 255, np.uint8)
    a = np.clip(image / vmax, -1.0, 1.0)[..., None]  # display scaling only; data untouched
    rgb = np.where(a > 0, WHITE + a * (RED - WHITE), WHITE + (-a) * (BLUE - WHITE))
    return np.rint(rgb).astype(np.uint8)


def save_png(path, rgb: np.ndarray, *, overwrite: bool = True, upscale: int = 1) -> Path:
    """Write an (H, W, 3) uint8 image atomically; `upscale` repeats pixels for viewing."""
    import matplotlib.image

    if upscale < 1:
        raise InputError(f"upscale must be >= 1, got {upscale}")
    if upscale > 1:
        rgb = np.repeat(np.repeat(rgb, upscale, axis=0), upscale, axis=1)
    with atomic_output(path, overwrite=overwrite) as tmp:
        matplotlib.image.imsave(tmp, rgb, format="png")
    return Path(path)
