"""The one project-wide log-intensity rule: ``L = log(I + eps)``.

Every part of the toolkit that turns linear intensity into log intensity (the event
generator, the adaptive sampler, the radiance-field losses, the metrics) calls
:func:`log_intensity`, so the simulator, the model and the evaluation agree exactly.

Intensities are linear radiance on a scale where **white is 1.0** (a well-exposed diffuse
white surface). Any positive value is accepted, including HDR values far above 1.

Why ``LOG_EPS = 1e-3``
    ESIM's default. Relative to white = 1.0 it puts the "dark floor" 60 dB (1000x) below
    white: above ~1e-3 the response is logarithmic (a contrast step of ``exp(C)`` gives
    the same number of events whatever the brightness), below it the response flattens,
    as a real DVS photoreceptor does in the dark. A tiny eps would make black pixels
    absurdly sensitive: with ``eps = 1e-10`` a black pixel brightening to 1e-3 fires ~80
    events at C = 0.2. With 1e-3 a black-to-white step (0 -> 1) fires
    ``floor(log(1.001 / 0.001) / C)`` = 34 events at C = 0.2.
    If your data use another white level ``w``, pass ``eps = 1e-3 * w``: scaling radiance
    and eps together leaves every event unchanged.

NaN, inf and negative radiance are bad data, never clamped: they raise
:class:`~evdnerf_ros.errors.InputError` naming where they came from.
"""

from __future__ import annotations

import numpy as np

from ..errors import InputError

#: Default eps of ``L = log(I + eps)``, relative to a white level of 1.0 (ESIM's value).
LOG_EPS = 1e-3


def check_eps(eps) -> float:
    """Return eps as a float after checking that it is finite and > 0."""
    try:
        value = float(eps)
    except (TypeError, ValueError) as exc:
        raise InputError(f"log eps {eps!r} is not a number") from exc
    if not np.isfinite(value) or value <= 0:
        raise InputError(f"log eps must be finite and > 0 (got {eps!r}); the default is "
                         f"{LOG_EPS} for a white level of 1.0")
    return value


def check_intensity(image, *, where: str = "image") -> np.ndarray:
    """Return `image` as an array after checking it is finite and non-negative.

    Raises InputError naming `where` (e.g. "frame 12 at t=400000 ns") and the first bad pixel.
    """
    arr = np.asarray(image)
    if arr.dtype.kind not in "fiu":
        raise InputError(f"{where}: intensity has dtype {arr.dtype}; expected real numbers "
                         "(linear intensity, white = 1.0)")
    if arr.dtype.kind == "f":
        bad = ~np.isfinite(arr)
        if bad.any():
            pos = np.unravel_index(int(np.flatnonzero(bad.ravel())[0]), arr.shape)
            raise InputError(f"{where}: intensity {arr[pos]} at pixel (row, col) "
                             f"{tuple(int(i) for i in pos)} is not finite; radiance must be "
                             "finite and >= 0")
    neg = arr < 0
    if neg.any():
        pos = np.unravel_index(int(np.flatnonzero(neg.ravel())[0]), arr.shape)
        raise InputError(f"{where}: intensity {arr[pos]} at pixel (row, col) "
                         f"{tuple(int(i) for i in pos)} is negative; radiance must be >= 0 "
                         "(linear, not log, intensity)")
    return arr


def log_intensity(image, eps: float = LOG_EPS, *, where: str = "image") -> np.ndarray:
    """``log(I + eps)`` in float64, after validating I (finite, >= 0) and eps (> 0)."""
    eps = check_eps(eps)
    arr = check_intensity(image, where=where)
    return np.log(arr.astype(np.float64, copy=False) + eps)


def intensity_from_log(log_image, eps: float = LOG_EPS) -> np.ndarray:
    """Inverse of :func:`log_intensity`: ``exp(L) - eps`` (float64; may round below 0 near the floor)."""
    return np.exp(np.asarray(log_image, dtype=np.float64)) - check_eps(eps)
