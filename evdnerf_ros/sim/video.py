"""video2events: a user's own high-speed video (frames + int64-ns times) to events.

Input file FRAMES.npz holds ``frames`` (N, H, W) and ``t`` (N,) int64 nanoseconds,
strictly increasing.

* Float frames are **linear intensity** (white = 1.0, any positive HDR value allowed);
  NaN, inf or negative values are refused (the message names the file and frame index).
* 8-bit frames (uint8, 0..255) are display-encoded, not linear; feeding them to a log
  would put the event thresholds in the wrong place, so they are refused unless
  ``gamma_8bit=True`` (CLI ``--gamma-8bit``). Then they are linearised with a pure power
  law ``I = (v / 255) ** 2.2``: the usual approximation of the sRGB transfer curve (the
  exact sRGB curve has a short linear toe below v = 10; the two differ by under 1 % of
  white). Black (v = 0) maps to I = 0, which the log's eps handles.
* Other integer types are refused: store linear float intensity.
* The file is checked before anything is allocated: each array's declared shape and dtype
  (its .npy header) must fit the bytes the archive holds and the memory budget; a
  corrupt, truncated or bit-flipped archive is one error naming the file.

Generator options and their ranges (the CLI flags): --c-pos / --c-neg in [0.01, 10],
--eps in (0, 1], --sigma / --interval-sigma in [0, 1], --refractory-ns in [0, 1e10],
--seed in [0, 2**63 - 1].
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from ..errors import InputError, OutputExistsError
from ..options import check_value, flag_name, option, option_fields
from .generator import _MAX_INTERVAL_NS, _MAX_SIDE, EventGenerator
from ..events.logmap import LOG_EPS, check_intensity
from .noise import DEFAULT_THRESHOLD, MIN_THRESHOLD

#: Frame times lie within +-2**62 ns (146 years), so every difference fits in int64.
MAX_ABS_TIME_NS = 1 << 62


#: Exponent of the 8-bit linearisation (sRGB-style display gamma).
GAMMA_8BIT = 2.2


def linearize_8bit(frames: np.ndarray) -> np.ndarray:
    """uint8 display values -> linear intensity ``(v / 255) ** 2.2`` (float32, white = 1.0)."""
    lut = ((np.arange(256, dtype=np.float64) / 255.0) ** GAMMA_8BIT).astype(np.float32)
    return lut[frames]


def check_times(t, n_frames: int, *, source: str) -> np.ndarray:
    t = np.asarray(t)
    if t.dtype.kind not in "iu":
        raise InputError(f"{source}: t has dtype {t.dtype}; store frame times as int64 "
                         "nanoseconds, not floats (e.g. np.round(seconds * 1e9).astype(np.int64))")
    if t.shape != (n_frames,):
        raise InputError(f"{source}: t has shape {t.shape}, expected ({n_frames},) - one time "
                         "per frame")
    if t.size and (int(t.min()) < -MAX_ABS_TIME_NS or int(t.max()) > MAX_ABS_TIME_NS):
        raise InputError(f"{source}: frame times must lie within +-2**62 ns (146 years); got "
                         f"{int(t.min())} .. {int(t.max())} ns")
    t = t.astype(np.int64)
    back = np.flatnonzero(np.diff(t) <= 0)
    if back.size:
        i = int(back[0]) + 1
        raise InputError(f"{source}: frame {i} time {t[i]} ns is not after frame {i - 1}'s "
                         f"{t[i - 1]} ns; frame times must increase strictly")
    gap = np.flatnonzero(np.diff(t) > _MAX_INTERVAL_NS)
    if gap.size:
        i = int(gap[0]) + 1
        raise InputError(f"{source}: frame {i} comes {t[i] - t[i - 1]} ns after frame {i - 1}; "
                         "frames may be at most 2**53 ns (104 days) apart")
    return t


def check_frames(frames, t, *, source: str = "frames", gamma_8bit: bool = False):
    """Validate (frames, t); return (float frames, int64 t). Errors name `source` and the frame."""
    frames = np.asarray(frames)
    if frames.ndim != 3:
        raise InputError(f"{source}: frames have shape {frames.shape}; expected (N, H, W) grey "
                         "images")
    n, h, w = frames.shape
    if n == 0 or h == 0 or w == 0:
        raise InputError(f"{source}: frames have shape {frames.shape}; need at least one frame "
                         "of at least 1x1 pixels")
    if h > _MAX_SIDE or w > _MAX_SIDE:
        raise InputError(f"{source}: frames are {w}x{h} pixels; event coordinates allow at "
                         f"most {_MAX_SIDE} per side")
    t = check_times(t, n, source=source)
    kind = frames.dtype.kind
    if kind in "iub":
        if frames.dtype != np.uint8:
            raise InputError(f"{source}: frames have dtype {frames.dtype}; store linear float "
                             "intensity (white = 1.0), or uint8 display values with --gamma-8bit")
        if not gamma_8bit:
            raise InputError(f"{source}: frames are 8-bit (uint8) display values, not linear "
                             "intensity; pass --gamma-8bit to linearise them with gamma 2.2, or "
                             "store linear float frames")
        return linearize_8bit(frames), t
    if kind != "f":
        raise InputError(f"{source}: frames have dtype {frames.dtype}; expected float linear "
                         "intensity")
    if gamma_8bit:
        raise InputError(f"{source}: --gamma-8bit applies only to uint8 frames; these are "
                         f"{frames.dtype} (already linear)")
    for i in range(n):
        check_intensity(frames[i], where=f"{source}: frame {i} at t={t[i]} ns")
    return frames, t


def load_frames_npz(path, *, gamma_8bit: bool = False):
    """Read FRAMES.npz -> (frames (N, H, W) float linear intensity, t (N,) int64 ns)."""
    from ..io.npz import load_npz

    arrays = load_npz(path, ("frames", "t"), what="FRAMES.npz (frames (N, H, W) linear intensity, t (N,) int64 ns)")
    return check_frames(arrays["frames"], arrays["t"], source=str(path), gamma_8bit=gamma_8bit)


def video_to_events(frames, t, **generator_options) -> np.ndarray:
    """Events of a video (N, H, W) linear intensity at times t (N,) int64 ns.

    `generator_options` are :class:`EventGenerator`'s keyword arguments (c_pos, c_neg, eps,
    threshold_sigma, interval_sigma, refractory_ns, shot_noise_rate_hz, leak_rate_hz, seed).
    """
    frames, t = check_frames(frames, t)
    _, h, w = frames.shape
    return EventGenerator(w, h, **generator_options).generate(frames, t)


@dataclass(frozen=True)
class VideoOptions:
    """Every knob of `evdnerf video2events` (flags, --config keys and library defaults)."""

    c_pos: float = option(DEFAULT_THRESHOLD, "positive contrast threshold C+", low=MIN_THRESHOLD, high=10.0)
    c_neg: float = option(DEFAULT_THRESHOLD, "negative contrast threshold C-", low=MIN_THRESHOLD, high=10.0)
    eps: float = option(LOG_EPS, "log offset: L = log(I + eps), white = 1", low=0.0, high=1.0, low_open=True)
    sigma: float = option(0.0, "per-pixel threshold mismatch std (v2e's sigma), fixed from --seed",
                          low=0.0, high=1.0)
    interval_sigma: float = option(0.0, "per-interval threshold noise std, ESIM's model", low=0.0, high=1.0)
    refractory_ns: int = option(0, "refractory period in ns", low=0, high=10_000_000_000)
    seed: int = option(0, "noise seed", low=0, high=2**63 - 1)
    gamma_8bit: bool = option(False, "accept 8-bit gamma-encoded frames and linearise them ((v/255)^2.2)")


def run_video2events(frames_path, out_path, options: VideoOptions | None = None, **fields) -> int:
    """The whole ``evdnerf video2events FRAMES.npz OUT`` job; returns the number of events.

    `sigma` is the per-pixel threshold mismatch (v2e's sigma, fixed from `seed`);
    `interval_sigma` is ESIM's per-interval threshold noise; `fields` replace single options.
    OUT's container follows its suffix (see :mod:`evdnerf_ros.io.event_files`); an existing OUT
    is refused (checked before any work) and nothing is half-written on failure (the writers are
    atomic).
    """
    from ..events.types import empty_triggers
    from ..io.event_files import EventFile, container_kind, write_event_file

    o = replace(options or VideoOptions(), **fields)
    for f, spec in option_fields(VideoOptions):
        check_value(getattr(o, f.name), f, spec, flag_name(f, spec))
    out_path = Path(out_path)
    kind = container_kind(out_path)           # unknown suffix: fail before any work
    if out_path.exists():
        raise OutputExistsError(out_path)
    frames, t = load_frames_npz(frames_path, gamma_8bit=o.gamma_8bit)
    _, h, w = frames.shape
    gen = EventGenerator(w, h, c_pos=o.c_pos, c_neg=o.c_neg, eps=o.eps, threshold_sigma=o.sigma,
                         interval_sigma=o.interval_sigma, refractory_ns=o.refractory_ns, seed=o.seed)
    events = gen.generate(frames, t)
    write_event_file(out_path, EventFile(events, empty_triggers(), w, h, kind))
    return int(events.size)
