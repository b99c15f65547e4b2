"""Time sampling that drives any renderer through the event generator.

The interface is only ``render(t_ns) -> (H, W) float linear intensity`` (white = 1.0): the
synthetic scene renderer and a trained radiance field both plug in. Two modes:

* ``"fixed"``: render at a fixed rate (frame times on the integer-ns grid
  ``t_start + i * span // n``, both ends included).
* ``"adaptive"``: bisection on a fixed grid. Grid point j is ``t_start + j * min_step_ns``
  (the last one is t_end). The span is cut into top pieces of ``max_step_ns // min_step_ns``
  grid steps. For a piece [a, b] the sampler renders both ends and the grid point m
  halfway between them and accepts the piece when the midpoint's log image deviates
  from the linear interpolation of the ends by less than ``tolerance_c * C`` at every
  pixel (C = the smaller of the generator's nominal C+ and C-) and, when ``max_dlog_c`` is
  given, when no pixel's log changes by more than ``max_dlog_c * C`` across the piece.
  Otherwise it splits the piece in two. A piece of one grid step is fed as is (counted in
  ``stats.at_min_step``). Accepted pieces are fed to the generator in time order as two
  steps (a -> m -> b), since m was rendered anyway. Renders are memoised: every time is
  rendered once.

Why a grid, and why a motion guard (a simulated fork lost all its events with a 1 s max
step, and 4-8 % at 100-500 ms):

* The finest step used to be "whatever max_step / 2**k first falls below 2 * min_step", so
  it moved with max_step, and with it which brief features were caught (a tine's top face,
  seen edge-on, covers a pixel for 0.2 ms). On the grid every max_step refines to the same frames:
  a coarser max_step can only leave out grid points where the midpoint test vouches for
  linearity, never move them.
* Three images cannot see a motion that goes there and back between them: the fork's
  servo swing 90 -> 135 -> 45 -> 90 deg looks identical at its start, middle and end. No
  test on a black-box renderer can be sound over pieces longer than the fastest such
  motion, so the step must be bounded there: a caller that knows its motion passes
  ``travel_px(a, b)``, a bound on how far anything in the image moves during [a, b]
  (`evdnerf_ros.sim.motion` computes it for scenes), and pieces travelling more than
  ``max_travel_px`` (1 pixel) are split without trusting the test. Within an accepted
  piece a there-and-back motion is then sub-pixel. Without ``travel_px`` (a trained field
  in ``publish``) it is ``max_step_ns`` that must stay below the shortest there-and-back
  motion of the scene.

The event generator interpolates log intensity linearly between the frames it gets, so
the midpoint test bounds exactly the error it makes: for a smooth signal the log error
between fed frames is about a quarter of the accepted midpoint deviation, and the timing
error of an event is that log error divided by the local slope |dL/dt|.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Callable

import numpy as np

from ..errors import InputError
from ..events.types import empty_events
from .generator import EventGenerator, _as_time
from ..events.logmap import log_intensity

#: Default largest step: ESIM renders at least at 30 Hz.
DEFAULT_MAX_STEP_NS = 33_333_333
#: Default smallest step of the adaptive mode (1 us).
DEFAULT_MIN_STEP_NS = 1_000
#: Default motion guard: an accepted piece lets nothing move further than this (pixels).
DEFAULT_MAX_TRAVEL_PX = 1.0


@dataclass
class SamplingStats:
    """What a :func:`simulate_renderer` call cost and did."""

    mode: str
    renders: int = 0            # calls to render (each time rendered once)
    frames_fed: int = 0         # frames given to the generator after the start frame
    intervals: int = 0          # accepted adaptive pieces (fixed mode: frame intervals)
    at_min_step: int = 0        # pieces of one grid step (min_step_ns), fed without a test
    motion_splits: int = 0      # pieces split because travel_px exceeded max_travel_px
    smallest_step_ns: int = 0   # shortest interval fed to the generator
    largest_step_ns: int = 0    # longest interval fed to the generator
    max_deviation_c: float = 0.0  # largest accepted midpoint deviation, in units of C
    events: int = 0
    render_seconds: float = 0.0
    wall_seconds: float = 0.0


def _positive_int(name, value) -> int:
    v = _as_time(value, name)
    if v <= 0:
        raise InputError(f"{name} must be > 0 ns (got {value})")
    return v


def simulate_renderer(render: Callable[[int], np.ndarray], t_start, t_end,
                      generator: EventGenerator, *, mode: str = "adaptive",
                      rate_hz: float | None = None, tolerance_c: float = 0.1,
                      max_dlog_c: float | None = None,
                      min_step_ns: int = DEFAULT_MIN_STEP_NS,
                      max_step_ns: int = DEFAULT_MAX_STEP_NS,
                      travel_px: Callable[[int, int], float] | None = None,
                      max_travel_px: float = DEFAULT_MAX_TRAVEL_PX,
                      progress: Callable[[int], None] | None = None):
    """Render on (t_start, t_end] and return ``(events, SamplingStats)``.

    If `generator` has no frame yet, ``render(t_start)`` starts it; otherwise it must be
    at ``t_start`` already (a continued stream) and its last frame is reused. A renderer
    with a pose argument plugs in as ``lambda t: renderer(T_world_cam, t)``.
    `travel_px(a, b)`, if given, bounds how far (pixels) anything in the image can move
    during [a, b]; adaptive pieces travelling further than `max_travel_px` are split without
    trusting the midpoint test (see the module notes). `progress`, if given, is called with
    the time (ns) of every frame fed to the generator.
    """
    wall0 = time.perf_counter()
    t_start = _as_time(t_start, "t_start")
    t_end = _as_time(t_end, "t_end")
    if t_end <= t_start:
        raise InputError(f"t_end {t_end} ns must be after t_start {t_start} ns")
    if mode not in ("adaptive", "fixed"):
        raise InputError(f"sampling mode {mode!r} is not one of 'adaptive', 'fixed'")
    stats = SamplingStats(mode=mode)
    eps = generator.eps
    shape = (generator.height, generator.width)
    c_ref = min(generator.c_pos, generator.c_neg)

    def render_log(t: int) -> np.ndarray:
        where = f"render at t={t} ns"
        r0 = time.perf_counter()
        img = render(t)
        stats.render_seconds += time.perf_counter() - r0
        stats.renders += 1
        img = np.asarray(img)
        if img.shape != shape:
            raise InputError(f"{where}: image shape {img.shape} does not match the generator's "
                             f"(height, width) = {shape}")
        return log_intensity(img, eps, where=where)

    if generator.initialized:
        if generator.t_ns != t_start:
            raise InputError(f"generator is at t={generator.t_ns} ns, not at t_start={t_start} ns; "
                             "continue from its time or use a fresh generator")
        L_start = generator.last_log()
    else:
        L_start = render_log(t_start)
        generator.reset_log(L_start, t_start)

    chunks: list[np.ndarray] = []

    def feed(L, t_prev, t):
        ev = generator.step_log(L, t)
        if ev.size:
            chunks.append(ev)
        stats.frames_fed += 1
        dt = t - t_prev
        if stats.frames_fed == 1 or dt < stats.smallest_step_ns:
            stats.smallest_step_ns = dt
        stats.largest_step_ns = max(stats.largest_step_ns, dt)
        if progress is not None:
            progress(t)

    span = t_end - t_start
    if mode == "fixed":
        if rate_hz is None or not np.isfinite(rate_hz) or rate_hz <= 0:
            raise InputError(f"fixed-rate sampling needs rate_hz > 0 (got {rate_hz!r})")
        n = max(1, math.ceil(span * float(rate_hz) / 1e9))
        prev = t_start
        for i in range(1, n + 1):
            t = t_start + (i * span) // n
            if t == prev:
                continue
            feed(render_log(t), prev, t)
            prev = t
        stats.intervals = stats.frames_fed
    else:
        tol = float(tolerance_c)
        if not np.isfinite(tol) or tol <= 0:
            raise InputError(f"tolerance_c must be > 0 (got {tolerance_c!r})")
        if max_dlog_c is not None and (not np.isfinite(max_dlog_c) or max_dlog_c <= 0):
            raise InputError(f"max_dlog_c must be > 0 or None (got {max_dlog_c!r})")
        min_step = _positive_int("min_step_ns", min_step_ns)
        max_step = _positive_int("max_step_ns", max_step_ns)
        if min_step > max_step:
            raise InputError(f"min_step_ns {min_step} is larger than max_step_ns {max_step}")
        if travel_px is not None:
            travel_limit = float(max_travel_px)
            if not np.isfinite(travel_limit) or travel_limit <= 0:
                raise InputError(f"max_travel_px must be > 0 (got {max_travel_px!r})")
        limit = tol * c_ref
        dlog_limit = None if max_dlog_c is None else float(max_dlog_c) * c_ref
        cache = {t_start: L_start}

        def get(t):
            L = cache.get(t)
            if L is None:
                L = cache[t] = render_log(t)
            return L

        # The grid: point j at t_start + j * min_step (the last one at t_end). Pieces are
        # runs of whole grid steps, so every max_step refines to the same frames: a coarser
        # max_step can only leave grid points out, never move them.
        n = -(-span // min_step)

        def at(j):
            return t_end if j >= n else t_start + j * min_step

        top = max_step // min_step                  # grid steps per top piece
        for first in range(0, n, top):
            stack = [(first, min(first + top, n))]
            while stack:
                lo, hi = stack.pop()
                a, b = at(lo), at(hi)
                if hi - lo == 1:                    # one grid step: the finest there is
                    stats.at_min_step += 1
                    stats.intervals += 1
                    feed(get(b), a, b)
                    del cache[a]
                    continue
                mid = (lo + hi) // 2
                if travel_px is not None and travel_px(a, b) > travel_limit:
                    # Something may move further than the midpoint test can vouch for.
                    stats.motion_splits += 1
                    stack.append((mid, hi))
                    stack.append((lo, mid))
                    continue
                m = at(mid)
                La, Lb, Lm = get(a), get(b), get(m)
                w = (m - a) / (b - a)
                dev = float(np.max(np.abs(Lm - (La + (Lb - La) * w))))
                ok = dev < limit
                if ok and dlog_limit is not None:
                    ok = float(np.max(np.abs(Lb - La))) <= dlog_limit
                if ok:
                    stats.intervals += 1
                    stats.max_deviation_c = max(stats.max_deviation_c, dev / c_ref)
                    feed(Lm, a, m)
                    feed(Lb, m, b)
                    del cache[a], cache[m]
                else:
                    stack.append((mid, hi))
                    stack.append((lo, mid))
    events = np.concatenate(chunks) if chunks else empty_events()
    stats.events = int(events.size)
    stats.wall_seconds = time.perf_counter() - wall0
    return events, stats
