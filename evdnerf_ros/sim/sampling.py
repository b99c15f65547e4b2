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

* A finest step of "whatever max_step / 2**k first falls below 2 * min_step" would move
  with max_step, and with it which brief features are caught (a tine's top face,
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

``simulate_pixels`` is the adaptive mode refined pixel by pixel, for renderers that can draw
single pixels at many times in one call (a trained field): the same grid and midpoint test on
each pixel's own signal, each bisection level one call (see its docstring).

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
from .motion import travels
from ..events.logmap import log_intensity

#: Default largest step: ESIM renders at least at 30 Hz.
DEFAULT_MAX_STEP_NS = 33_333_333
#: Default smallest step of the adaptive mode (1 us).
DEFAULT_MIN_STEP_NS = 1_000
#: Default motion guard: an accepted piece lets nothing move further than this (pixels).
DEFAULT_MAX_TRAVEL_PX = 1.0
#: Per-pixel mode: top pieces are refined together while they hold at most this many pixels.
PIXEL_BATCH = 1 << 18


@dataclass
class SamplingStats:
    """What a :func:`simulate_renderer` call cost and did."""

    mode: str
    renders: int = 0            # distinct times rendered (each time rendered once)
    render_calls: int = 0       # calls to the renderer (a batch of times or pixels is one)
    frames_fed: int = 0         # frames given to the generator after the start frame
    intervals: int = 0          # accepted adaptive pieces (fixed mode: frame intervals)
    at_min_step: int = 0        # pieces of one grid step (min_step_ns), fed without a test
    motion_splits: int = 0      # pieces split because travel_px exceeded max_travel_px
    smallest_step_ns: int = 0   # shortest interval fed to the generator
    largest_step_ns: int = 0    # longest interval fed to the generator
    max_deviation_c: float = 0.0  # largest accepted midpoint deviation, in units of C
    pixels_rendered: int = 0    # per-pixel mode: pixel values rendered (image modes: 0)
    pixels_held: int = 0        # per-pixel mode: pixel pieces out of reach_px, held without a render
    events: int = 0
    render_seconds: float = 0.0
    wall_seconds: float = 0.0


def _positive_int(name, value) -> int:
    v = _as_time(value, name)
    if v <= 0:
        raise InputError(f"{name} must be > 0 ns (got {value})")
    return v


def _travel_limit(max_travel_px) -> float:
    limit = float(max_travel_px)
    if not np.isfinite(limit) or limit <= 0:
        raise InputError(f"max_travel_px must be > 0 (got {max_travel_px!r})")
    return limit


def _adaptive_settings(tolerance_c, max_dlog_c, min_step_ns, max_step_ns) -> tuple[float, int, int]:
    """Checked (tolerance, min step, max step) of adaptive sampling."""
    tol = float(tolerance_c)
    if not np.isfinite(tol) or tol <= 0:
        raise InputError(f"tolerance_c must be > 0 (got {tolerance_c!r})")
    if max_dlog_c is not None and (not np.isfinite(max_dlog_c) or max_dlog_c <= 0):
        raise InputError(f"max_dlog_c must be > 0 or None (got {max_dlog_c!r})")
    min_step = _positive_int("min_step_ns", min_step_ns)
    max_step = _positive_int("max_step_ns", max_step_ns)
    if min_step > max_step:
        raise InputError(f"min_step_ns {min_step} is larger than max_step_ns {max_step}")
    return tol, min_step, max_step


def simulate_renderer(render: Callable[[int], np.ndarray], t_start, t_end,
                      generator: EventGenerator, *, mode: str = "adaptive",
                      rate_hz: float | None = None, tolerance_c: float = 0.1,
                      max_dlog_c: float | None = None,
                      min_step_ns: int = DEFAULT_MIN_STEP_NS,
                      max_step_ns: int = DEFAULT_MAX_STEP_NS,
                      travel_px: Callable[[int, int], float] | None = None,
                      max_travel_px: float = DEFAULT_MAX_TRAVEL_PX,
                      progress: Callable[[int], None] | None = None,
                      render_many: Callable[[np.ndarray], np.ndarray] | None = None,
                      prefetch_levels: int = 0):
    """Render on (t_start, t_end] and return ``(events, SamplingStats)``.

    If `generator` has no frame yet, ``render(t_start)`` starts it; otherwise it must be
    at ``t_start`` already (a continued stream) and its last frame is reused. A renderer
    with a pose argument plugs in as ``lambda t: renderer(T_world_cam, t)``.
    `travel_px(a, b)`, if given, bounds how far (pixels) anything in the image can move
    during [a, b]; adaptive pieces travelling further than `max_travel_px` are split without
    trusting the midpoint test (see the module notes). `progress`, if given, is called with
    the time (ns) of every frame fed to the generator.
    ``render_many(times)`` -> (K, H, W) with ``prefetch_levels`` L > 0 (adaptive mode): each
    top piece's first L levels of midpoints (up to 2^L - 1 frames, and its end) are rendered
    ahead in one batch, whether the refinement then needs them all or not (on a GPU a batch
    costs about one render); the same frames are fed, so the same events.
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

    def as_log(img, where: str) -> np.ndarray:
        img = np.asarray(img)
        if img.shape != shape:
            raise InputError(f"{where}: image shape {img.shape} does not match the generator's "
                             f"(height, width) = {shape}")
        return log_intensity(img, eps, where=where)

    def render_log(t: int) -> np.ndarray:
        r0 = time.perf_counter()
        img = render(t)
        stats.render_seconds += time.perf_counter() - r0
        stats.renders += 1
        stats.render_calls += 1
        return as_log(img, f"render at t={t} ns")

    def render_logs(times: list[int]) -> list[np.ndarray]:
        r0 = time.perf_counter()
        imgs = render_many(np.asarray(times, np.int64))
        stats.render_seconds += time.perf_counter() - r0
        stats.renders += len(times)
        stats.render_calls += 1
        return [as_log(img, f"render at t={t} ns") for t, img in zip(times, imgs)]

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
        tol, min_step, max_step = _adaptive_settings(tolerance_c, max_dlog_c, min_step_ns, max_step_ns)
        if travel_px is not None:
            travel_limit = _travel_limit(max_travel_px)
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
        levels = int(prefetch_levels) if render_many is not None else 0

        def prefetch(lo, hi, depth):
            """The grid points the refinement of [lo, hi] reaches within ``depth`` levels."""
            if depth == 0 or hi - lo < 2:
                return []
            mid = (lo + hi) // 2
            return prefetch(lo, mid, depth - 1) + [mid] + prefetch(mid, hi, depth - 1)

        for first in range(0, n, top):
            last = min(first + top, n)
            if levels > 0:
                want = [at(j) for j in [last, *prefetch(first, last, levels)]]
                want = [t for t in want if t not in cache]
                if want:
                    cache.update(zip(want, render_logs(want)))
            stack = [(first, last)]
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
            if levels > 0:                          # prefetched frames the refinement did not need
                for t in [t for t in cache if t != at(last)]:
                    del cache[t]
    events = np.concatenate(chunks) if chunks else empty_events()
    stats.events = int(events.size)
    stats.wall_seconds = time.perf_counter() - wall0
    return events, stats


def pixel_grid_size(t_start: int, t_end: int, min_step_ns: int) -> int:
    """Points of ``simulate_pixels``' grid over [t_start, t_end] but the last: ``t_start + j
    min_step_ns`` for j < this, then ``t_end`` (``pixel_grid_times``)."""
    return -(-(int(t_end) - int(t_start)) // int(min_step_ns))


def pixel_grid_times(j: np.ndarray, t_start: int, t_end: int, min_step_ns: int) -> np.ndarray:
    """(…,) int64 times of ``simulate_pixels``' grid points ``j`` over [t_start, t_end] (a caller
    making its camera poses ahead, as the publisher does, asks for the same times)."""
    n = pixel_grid_size(t_start, t_end, min_step_ns)
    return np.where(j >= n, t_end, t_start + np.asarray(j, np.int64) * min_step_ns).astype(np.int64)


def simulate_pixels(render_pixels: Callable[[np.ndarray, np.ndarray], np.ndarray], t_start, t_end,
                    generator: EventGenerator, *, tolerance_c: float = 0.1, max_dlog_c: float | None = None,
                    min_step_ns: int = DEFAULT_MIN_STEP_NS, max_step_ns: int = DEFAULT_MAX_STEP_NS,
                    travel_px: Callable[[int, int], float] | None = None,
                    max_travel_px: float = DEFAULT_MAX_TRAVEL_PX,
                    reach_px: Callable[[np.ndarray, np.ndarray], np.ndarray | None] | None = None,
                    progress: Callable[[int], None] | None = None):
    """Adaptive sampling refined pixel by pixel; ``(events, SamplingStats)`` as
    :func:`simulate_renderer` (``travel_px`` / ``max_travel_px``: its motion guard: a piece
    travelling further is split for every pixel, whatever its midpoint says; with
    ``reach_px(a, b)`` -> (N, 4) x0 y0 x1 y1 per piece [a[k], b[k]] (``motion.ImageTravel.reach``:
    the image box outside which no pixel changes during it) only for the pixels in that box).
    ``reach_px`` also leaves out what cannot change: a pixel outside the box of a top piece holds
    its value over it and is not rendered (``pixels_held``), with or without the guard.

    ``render_pixels(t_ns, pixels)`` -> linear intensity of row-major pixel ``pixels[i]`` at
    time ``t_ns[i]`` (both (M,) int64; many times in one call).  The grid, the top pieces and
    the midpoint test are those of the ``"adaptive"`` mode, applied to each pixel's own log
    signal: a pixel whose piece passes keeps it while its neighbours are split further, and
    every level of the bisection (all failed pixels' midpoints, at many times; top pieces are
    refined together up to ``PIXEL_BATCH`` pixels) is one call.  So
    a moving camera, where every image fails somewhere (each moving edge), renders only the
    pixels along the edges at the finer levels, in a few batched calls instead of one image per
    grid time.  Every rendered value is fed (as the image mode feeds ``a -> m -> b``), each pixel
    on its own (``EventGenerator.step_knots``): its events are exactly those of its own
    piecewise-linear signal, and only the segments that reach a pixel's next level are worked
    out (no frame per time any pixel was rendered at, no interpolation of the others).  Each
    pixel's signal is accepted by the same bound as an image mode's piece (``tolerance_c``);
    it is not refined where only *other* pixels needed it (the difference from that mode).
    ``renders`` counts the distinct times rendered, ``pixels_rendered`` the values.
    """
    wall0 = time.perf_counter()
    t_start = _as_time(t_start, "t_start")
    t_end = _as_time(t_end, "t_end")
    if t_end <= t_start:
        raise InputError(f"t_end {t_end} ns must be after t_start {t_start} ns")
    tol, min_step, max_step = _adaptive_settings(tolerance_c, max_dlog_c, min_step_ns, max_step_ns)
    travel_limit = _travel_limit(max_travel_px) if travel_px is not None else None
    stats = SamplingStats(mode="per-pixel")
    n_pix = generator.n_pixels
    every = np.arange(n_pix)
    c_ref = min(generator.c_pos, generator.c_neg)
    limit = tol * c_ref
    dlog_limit = None if max_dlog_c is None else float(max_dlog_c) * c_ref
    n = pixel_grid_size(t_start, t_end, min_step)          # grid points, as in the image mode

    def times(j: np.ndarray) -> np.ndarray:
        return pixel_grid_times(j, t_start, t_end, min_step)

    def render_log(j: np.ndarray, pix: np.ndarray) -> np.ndarray:
        t = times(j)
        where = f"render of {pix.size} pixel(s) at t={int(t.min())}..{int(t.max())} ns"
        r0 = time.perf_counter()
        vals = np.asarray(render_pixels(t, pix))
        stats.render_seconds += time.perf_counter() - r0
        if vals.shape != pix.shape:
            raise InputError(f"{where}: got values of shape {vals.shape}, expected {pix.shape}")
        stats.renders += int(np.count_nonzero(np.bincount(j, minlength=n + 1)))     # distinct grid times
        stats.render_calls += 1
        stats.pixels_rendered += int(pix.size)
        return log_intensity(vals, generator.eps, where=where)

    if generator.initialized:
        if generator.t_ns != t_start:
            raise InputError(f"generator is at t={generator.t_ns} ns, not at t_start={t_start} ns; "
                             "continue from its time or use a fresh generator")
        L_now = generator.last_log().ravel()
    else:
        L_now = render_log(np.zeros(n_pix, np.int64), every)
        generator.reset_log(L_now.reshape(generator.height, generator.width), t_start)

    chunks: list[np.ndarray] = []
    top = max_step // min_step
    group = top * max(1, PIXEL_BATCH // n_pix)     # grid steps of the top pieces refined together
    for g0 in range(0, n, group):
        firsts = np.arange(g0, min(g0 + group, n), top)
        lasts = np.minimum(firsts + top, n)
        pix, lo, hi = np.tile(every, firsts.size), np.repeat(firsts, n_pix), np.repeat(lasts, n_pix)
        mid = (lo + hi) // 2
        wide = hi - lo > 1
        # a pixel out of its top piece's reach keeps its value over it: nothing rendered for it
        seen = _in_reach(reach_px, times(firsts), times(lasts), generator.width, n_pix)
        at_hi, at_mid = seen, seen & wide
        both = render_log(np.concatenate([hi[at_hi], mid[at_mid]]), np.concatenate([pix[at_hi], pix[at_mid]]))
        kp, kj, kL = [every, pix[at_hi], pix[at_mid]], [lo[:n_pix], hi[at_hi], mid[at_mid]], [L_now, both]  # knots
        n_hi = int(at_hi.sum())
        Lb = np.empty(pix.size)
        Lb[at_hi] = both[:n_hi]
        _hold(Lb.reshape(firsts.size, n_pix), ~seen.reshape(firsts.size, n_pix), L_now)
        La = np.concatenate([L_now, Lb[:-n_pix]])
        stats.at_min_step += int((~wide & seen).sum())
        stats.pixels_held += int((~seen).sum())
        stats.intervals += int((~at_mid).sum())
        pix, lo, hi, La, Lb, Lm = pix[at_mid], lo[at_mid], hi[at_mid], La[at_mid], Lb[at_mid], both[n_hi:]
        while pix.size:
            mid = (lo + hi) // 2
            ta, tb, tm = times(lo), times(hi), times(mid)
            w = (tm - ta) / (tb - ta)
            dev = np.abs(Lm - (La + (Lb - La) * w))
            ok = dev < limit
            if dlog_limit is not None:
                ok &= np.abs(Lb - La) <= dlog_limit
            if travel_limit is not None:
                # one travel per distinct piece (a flat key: np.unique along an axis is slow)
                keys, which = np.unique(lo * np.int64(n + 1) + hi, return_inverse=True)
                ta, tb = times(keys // (n + 1)), times(keys % (n + 1))
                far = travels(travel_px, ta, tb) > travel_limit
                stats.motion_splits += int(far.sum())
                forced = far[which.ravel()]
                box = reach_px(ta, tb) if reach_px is not None and forced.any() else None
                if box is not None:                 # a pixel the content cannot reach stays flat
                    forced &= _inside(pix, generator.width, box[which.ravel()])
                ok &= ~forced
            if ok.any():
                stats.intervals += int(ok.sum())
                stats.max_deviation_c = max(stats.max_deviation_c, float(dev[ok].max()) / c_ref)
            bad = ~ok
            # the failed pieces' halves; one grid step is the finest there is
            lo, hi = np.concatenate([lo[bad], mid[bad]]), np.concatenate([mid[bad], hi[bad]])
            pix = np.concatenate([pix[bad], pix[bad]])
            La, Lb = np.concatenate([La[bad], Lm[bad]]), np.concatenate([Lm[bad], Lb[bad]])
            finest = hi - lo == 1
            stats.at_min_step += int(finest.sum())
            stats.intervals += int(finest.sum())
            split = ~finest
            pix, lo, hi, La, Lb = pix[split], lo[split], hi[split], La[split], Lb[split]
            if pix.size:
                Lm = render_log((lo + hi) // 2, pix)
                kp.append(pix)
                kj.append((lo + hi) // 2)
                kL.append(Lm)
        L_now = _feed_knots(generator, np.concatenate(kp), np.concatenate(kj), np.concatenate(kL),
                            int(lasts[-1]), times, chunks, stats, progress)
    events = np.concatenate(chunks) if chunks else empty_events()
    stats.events = int(events.size)
    stats.wall_seconds = time.perf_counter() - wall0
    return events, stats


def _in_reach(reach_px, a: np.ndarray, b: np.ndarray, width: int, n_pix: int) -> np.ndarray:
    """(pieces * n_pix,) bool, piece-major: the pixels inside ``reach_px``'s box of each piece
    [a[k], b[k]] (all without ``reach_px`` or where it has no boxes)."""
    box = reach_px(a, b) if reach_px is not None else None
    if box is None:
        return np.ones(a.size * n_pix, bool)
    return _inside(np.tile(np.arange(n_pix), a.size), width, np.repeat(box, n_pix, axis=0))


def _inside(pix: np.ndarray, width: int, box: np.ndarray) -> np.ndarray:
    """Whether row-major pixel ``pix[i]`` lies in ``box[i]`` (x0 y0 x1 y1, inclusive)."""
    x, y = pix % width, pix // width
    return (x >= box[:, 0]) & (x <= box[:, 2]) & (y >= box[:, 1]) & (y <= box[:, 3])


def _hold(Lb: np.ndarray, held: np.ndarray, L_start: np.ndarray) -> None:
    """Pieces' end values (pieces, n_pix), in place: a held pixel's is its value at the piece's
    start (the previous piece's end, ``L_start`` for the first)."""
    prev = L_start
    for k in range(Lb.shape[0]):
        row = Lb[k]
        row[held[k]] = prev[held[k]]
        prev = row


def _feed_knots(generator: EventGenerator, pix, j, L, j_end: int, times, chunks, stats, progress) -> np.ndarray:
    """Step the generator to grid index ``j_end`` along the knots ``(pix, j, L)`` (every pixel has
    one at the first grid index, its value now), each pixel linear between its own knots and
    holding its last (``EventGenerator.step_knots``: no other pixel's time splits its segments);
    return the last frame (flat). ``frames_fed`` and the steps count the distinct knot times
    after the first and ``j_end``, as a feed of one frame per time would."""
    rows = np.flatnonzero(np.bincount(j, minlength=j_end + 1))      # the distinct grid indices (0 <= j <= j_end)
    if not rows.size or rows[-1] != j_end:
        rows = np.append(rows, j_end)
    t_rows = times(rows)
    later = j != rows[0]
    ev = generator.step_knots(pix[later], times(j[later]), L[later], int(t_rows[-1]))
    if ev.size:
        chunks.append(ev)
    if rows.size > 1:
        steps = np.diff(t_rows)
        smallest = int(steps.min())
        stats.smallest_step_ns = smallest if stats.frames_fed == 0 else min(stats.smallest_step_ns, smallest)
        stats.largest_step_ns = max(stats.largest_step_ns, int(steps.max()))
        stats.frames_fed += rows.size - 1
    if progress is not None:
        for t in t_rows[1:].tolist():
            progress(t)
    return generator.last_log().ravel()
