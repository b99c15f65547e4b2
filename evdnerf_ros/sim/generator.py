"""The event generator: ESIM's algorithm done exactly, vectorised with numpy.

Model (Rebecq et al., ESIM, CoRL 2018), per pixel:

* ``L = log(I + eps)`` in float64 (:mod:`evdnerf_ros.events.logmap`); between two frames
  ``(t0, L0) -> (t1, L1)`` the log intensity is taken to be linear in time.
* The pixel keeps a *reference* level. Moving up it fires an ON event each time L reaches
  ``reference + C+`` (and the reference moves there); moving down, an OFF event each time
  it reaches ``reference - C-``. A level exactly equal to L1 fires in this interval;
  a level equal to L0 does not (it fired in the previous one): events lie in (t0, t1].
* Each crossing is stamped with its linearly interpolated time
  ``t0 + (level - L0) * (t1 - t0) / (L1 - L0)``, computed in float64 on the int64
  difference ``t1 - t0`` and rounded to the nearest integer nanosecond (a crossing less
  than half a nanosecond after t0 is stamped t0 + 1 ns so that it stays inside the
  interval). Absolute time never enters a float, so a 1e4 s offset changes nothing.
* The reference is stored as ``base + (n_on * C+ - n_off * C-)`` with integer counts
  ``n_on``, ``n_off`` (separately, so it is one fixed lattice per pixel and cannot drift
  over millions of events); every comparison uses that same expression.
* Refractory period (ESIM's rule): a crossing less than ``refractory_ns`` after the pixel's
  last *emitted* event is not emitted, but the reference still moves.
* The first frame (``reset``) only sets the references. Afterwards only pixels whose
  value changed are processed: ``np.flatnonzero(I1 != I0)`` on the raw frame, before the
  log, so unchanged pixels are neither logged nor re-validated (``L1 != L0`` for log
  frames); of those, only pixels that reach their next level up or down (cached per
  pixel) go through the crossing arithmetic. Static parts cost almost nothing.
* Output per call: EVENT_DTYPE, sorted by t; equal times keep pixel order (row-major),
  then crossing order. State is carried between calls, so feeding frames one by one
  gives bit-for-bit the batch result.

Noise options (threshold mismatch, ESIM's per-interval threshold noise, shot and leak
noise) are described in :mod:`evdnerf_ros.sim.noise`. With per-interval noise the lattice
is re-based at each changed pixel's current reference every interval (the step C changes),
and a level that a smaller redrawn C would put at or behind L0 is not emitted
retroactively: crossing continues from the first level inside (L0, L1]. (ESIM itself
stalls in that case until the signal passes the old level; we do not copy that.)
"""

from __future__ import annotations

import operator
from typing import Sequence

import numpy as np

from ..errors import InputError
from ..events.types import EVENT_DTYPE, empty_events
from . import noise as _noise
from ..events.logmap import LOG_EPS, check_eps, check_intensity

#: "No event yet" in the per-pixel last-event-time array (never compared by subtraction).
_NEVER = np.iinfo(np.int64).min

#: Longest frame interval: float64 holds every integer ns up to 2**53 (104 days).
_MAX_INTERVAL_NS = 1 << 53

#: Largest sensor side the event dtype (uint16 coordinates) can address.
_MAX_SIDE = 65535


def _as_time(t, where: str) -> int:
    if isinstance(t, (bool, np.bool_)):
        raise InputError(f"{where}: time {t!r} is not an integer number of nanoseconds")
    try:
        return operator.index(t)
    except TypeError:
        raise InputError(f"{where}: time {t!r} ({type(t).__name__}) is not an integer; "
                         "times are int64 nanoseconds (e.g. np.int64(round(seconds * 1e9)))"
                         ) from None


def _number(name: str, value) -> float:
    try:
        return float(value)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be a number (got {value!r})") from None


def _positive(name: str, value) -> float:
    v = _number(name, value)
    if not np.isfinite(v) or v <= 0:
        raise InputError(f"{name} must be finite and > 0 (got {value!r})")
    return v


def _non_negative(name: str, value) -> float:
    v = _number(name, value)
    if not np.isfinite(v) or v < 0:
        raise InputError(f"{name} must be finite and >= 0 (got {value!r})")
    return v


class EventGenerator:
    """Turns a stream of linear-intensity frames with int64-ns times into events.

    Parameters
    ----------
    width, height : sensor size in pixels; frames are (height, width).
    c_pos, c_neg : nominal ON / OFF contrast thresholds (log units).
    eps : the eps of ``L = log(I + eps)`` (default :data:`LOG_EPS`, white = 1.0).
    threshold_sigma : per-pixel threshold mismatch, fixed from `seed`.
    interval_sigma : ESIM's per-interval threshold noise.
    refractory_ns : refractory period (int ns, >= 0).
    shot_noise_rate_hz, leak_rate_hz : per-pixel rates of spurious events.
    seed : seeds every random draw.
    skip_unchanged : process only pixels whose L changed (default; False exists for
        benchmarking the saving; results are identical).
    """

    def __init__(self, width: int, height: int, *, c_pos: float = _noise.DEFAULT_THRESHOLD, c_neg: float = _noise.DEFAULT_THRESHOLD,
                 eps: float = LOG_EPS, threshold_sigma: float = 0.0,
                 interval_sigma: float = 0.0, refractory_ns: int = 0,
                 shot_noise_rate_hz: float = 0.0, leak_rate_hz: float = 0.0, seed: int = 0,
                 skip_unchanged: bool = True):
        for name, v in (("width", width), ("height", height)):
            if not isinstance(v, (int, np.integer)) or isinstance(v, bool) or not 0 < v <= _MAX_SIDE:
                raise InputError(f"sensor {name} must be an integer in 1..{_MAX_SIDE} (got {v!r})")
        self.width, self.height = int(width), int(height)
        self.n_pixels = self.width * self.height
        self.c_pos = _positive("c_pos", c_pos)
        self.c_neg = _positive("c_neg", c_neg)
        self.eps = check_eps(eps)
        self.threshold_sigma = _non_negative("threshold_sigma", threshold_sigma)
        self.interval_sigma = _non_negative("interval_sigma", interval_sigma)
        self.refractory_ns = _as_time(refractory_ns, "refractory_ns")
        if self.refractory_ns < 0:
            raise InputError(f"refractory_ns must be >= 0 (got {refractory_ns})")
        self.shot_noise_rate_hz = _non_negative("shot_noise_rate_hz", shot_noise_rate_hz)
        self.leak_rate_hz = _non_negative("leak_rate_hz", leak_rate_hz)
        self.seed = _as_time(seed, "seed")
        if self.seed < 0:
            raise InputError(f"seed must be >= 0 (got {seed})")
        self.skip_unchanged = bool(skip_unchanged)
        rng_mismatch, _, _ = _noise._rngs(self.seed)
        # Scalars when there is no mismatch (cheaper); per-pixel float64 arrays otherwise.
        self._cp = _noise.mismatch_thresholds(self.n_pixels, self.c_pos, self.threshold_sigma,
                                              rng_mismatch)
        self._cn = _noise.mismatch_thresholds(self.n_pixels, self.c_neg, self.threshold_sigma,
                                              rng_mismatch)
        flat = np.arange(self.n_pixels)
        self._xs = (flat % self.width).astype(np.uint16)
        self._ys = (flat // self.width).astype(np.uint16)
        self._initialized = False
        self.frames_processed = 0       # frames given since the last reset (which counts as one)
        self.pixels_processed = 0       # pixel-intervals processed since the last reset

    # ------------------------------------------------------------------ state
    @property
    def initialized(self) -> bool:
        return self._initialized

    @property
    def t_ns(self) -> int | None:
        """Time of the last frame given (None before the first)."""
        return self._t if self._initialized else None

    @property
    def thresholds(self) -> tuple[np.ndarray, np.ndarray]:
        """Per-pixel (C+, C-) maps, (height, width) float64."""
        shape = (self.height, self.width)
        return (np.broadcast_to(self._cp, (self.n_pixels,)).reshape(shape).copy(),
                np.broadcast_to(self._cn, (self.n_pixels,)).reshape(shape).copy())

    def reference(self) -> np.ndarray:
        """Each pixel's current reference log level, (height, width) float64."""
        self._need_state()
        ref = self._base + (self._n_on * self._cp - self._n_off * self._cn)
        return ref.reshape(self.height, self.width)

    def last_log(self) -> np.ndarray:
        """The log frame last given, (height, width) float64."""
        self._need_state()
        return self._L.reshape(self.height, self.width).copy()

    def _need_state(self):
        if not self._initialized:
            raise InputError("event generator: no frame yet; call reset(frame, t_ns) first")

    def _check_log_frame(self, L, where: str) -> np.ndarray:
        L = np.asarray(L)
        if L.shape != (self.height, self.width):
            raise InputError(f"{where}: shape {L.shape} does not match the sensor "
                             f"(height, width) = ({self.height}, {self.width})")
        return L

    def _log(self, frame, where: str) -> np.ndarray:
        frame = self._check_log_frame(frame, where)
        check_intensity(frame, where=where)
        return np.log(frame.astype(np.float64, copy=False) + self.eps).ravel()

    def _changed_log(self, frame, where: str):
        """(idx, L1 of idx) for the pixels of `frame` that differ from the previous frame.

        Pixels are compared in intensity, before the log (L is a function of I, so equal I
        means equal L), and only the changed ones are validated and logged: a NaN is never
        equal to anything, so bad values always land among the changed pixels.
        """
        frame = self._check_log_frame(frame, where)
        if frame.dtype.kind not in "fiu":
            check_intensity(frame, where=where)     # raises with the dtype
        flat = frame.ravel()
        prev = self._I
        if not self.skip_unchanged or prev is None or prev.dtype != flat.dtype:
            check_intensity(frame, where=where)
            L = np.log(flat.astype(np.float64) + self.eps)
            self._I = flat.copy()
            if not self.skip_unchanged:
                return np.arange(self.n_pixels), L
            idx = np.flatnonzero(L != self._L)
            return idx, L[idx]
        idx = np.flatnonzero(flat != prev)
        vals = flat if idx.size == self.n_pixels else flat[idx]
        if vals.dtype.kind == "f":
            bad = np.flatnonzero(~np.isfinite(vals) | (vals < 0))
        else:
            bad = np.flatnonzero(vals < 0)
        if bad.size:
            pos = np.unravel_index(int(idx[bad[0]]), frame.shape)
            v = frame[pos]
            what = "is negative" if np.isfinite(v) else "is not finite"
            raise InputError(f"{where}: intensity {v} at pixel (row, col) "
                             f"{tuple(int(i) for i in pos)} {what}; radiance must be finite "
                             "and >= 0 (linear, not log, intensity)")
        prev[idx] = vals
        return idx, np.log(vals.astype(np.float64) + self.eps)

    def _changed_checked_log(self, L, where: str):
        L = self._checked_log(L, where)
        self._I = None   # intensities unknown from here on: compare in log next time
        if not self.skip_unchanged:
            return np.arange(self.n_pixels), L
        idx = np.flatnonzero(L != self._L)
        return idx, (L if idx.size == self.n_pixels else L[idx])

    def _checked_log(self, L, where: str) -> np.ndarray:
        L = self._check_log_frame(L, where)
        if L.dtype.kind != "f" or not np.all(np.isfinite(L)):
            bad = np.flatnonzero(~np.isfinite(L.ravel())) if L.dtype.kind == "f" else []
            raise InputError(f"{where}: log frame must be finite float"
                             + (f" (pixel {int(bad[0])} is {L.ravel()[bad[0]]})" if len(bad) else ""))
        return np.array(L, dtype=np.float64).ravel()

    # ------------------------------------------------------------------ reset
    def reset(self, frame, t_ns) -> None:
        """Start (or restart) at `frame` (linear intensity) at `t_ns`: references set, no events."""
        t = _as_time(t_ns, "reset")
        L = self._log(frame, f"frame 0 at t={t} ns")
        self._reset_log(L, t)
        self._I = np.asarray(frame).ravel().copy()

    def reset_log(self, log_frame, t_ns) -> None:
        """:meth:`reset` from a log frame ``log(I + eps)`` (float64, as :func:`log_intensity` gives)."""
        t = _as_time(t_ns, "reset")
        self._reset_log(self._checked_log(log_frame, f"frame 0 at t={t} ns"), t)
        self._I = None

    def _reset_log(self, L: np.ndarray, t: int) -> None:
        n = self.n_pixels
        self._L = L.copy()
        self._base = L.copy()
        self._n_on = np.zeros(n, np.int64)
        self._n_off = np.zeros(n, np.int64)
        self._last = np.full(n, _NEVER, np.int64)
        self._next_up = np.empty(n)
        self._next_dn = np.empty(n)
        self._cache_levels(slice(None))
        self._t = t
        _, self._rng_interval, self._rng_noise = _noise._rngs(self.seed)
        self._initialized = True
        self.frames_processed = 1
        self.pixels_processed = 0

    def _cache_levels(self, where) -> None:
        """Recompute the next lattice levels above / below the reference of pixels `where`."""
        cp = self._cp if np.ndim(self._cp) == 0 else self._cp[where]
        cn = self._cn if np.ndim(self._cn) == 0 else self._cn[where]
        base, a, b = self._base[where], self._n_on[where], self._n_off[where]
        self._next_up[where] = base + ((a + 1) * cp - b * cn)
        self._next_dn[where] = base + (a * cp - (b + 1) * cn)

    # ------------------------------------------------------------------ step
    def _check_time(self, t_ns) -> int:
        where = f"frame {self.frames_processed}"
        t = _as_time(t_ns, where)
        if t <= self._t:
            raise InputError(f"{where}: time {t} ns is not after the previous frame's {self._t} ns; "
                             "frame times must increase strictly")
        if t - self._t > _MAX_INTERVAL_NS:
            raise InputError(f"{where}: {t - self._t} ns after the previous frame; one interval "
                             f"may span at most 2**53 ns (104 days) for exact ns interpolation")
        return t

    def step(self, frame, t_ns) -> np.ndarray:
        """Feed the next frame; return the events of (previous t, t_ns], sorted by t.

        On a generator that has no frame yet this is :meth:`reset` and returns no events.
        """
        if not self._initialized:
            self.reset(frame, t_ns)
            return empty_events()
        t = self._check_time(t_ns)
        idx, L1 = self._changed_log(frame, f"frame {self.frames_processed} at t={t} ns")
        return self._step(idx, L1, t)

    def step_log(self, log_frame, t_ns) -> np.ndarray:
        """:meth:`step` from a log frame ``log(I + eps)`` computed with this generator's eps."""
        if not self._initialized:
            self.reset_log(log_frame, t_ns)
            return empty_events()
        t = self._check_time(t_ns)
        idx, L1 = self._changed_checked_log(log_frame, f"frame {self.frames_processed} at t={t} ns")
        return self._step(idx, L1, t)

    def step_knots(self, pix, t_ns, log_values, t_end) -> np.ndarray:
        """Advance every pixel to ``t_end`` along its own piecewise-linear log signal; return the
        events of (previous t, t_end], sorted by t (ties: pixel order, then crossing order).

        Knot i says pixel ``pix[i]`` has log value ``log_values[i]`` at time ``t_ns[i]`` (int64,
        in (previous t, t_end]). A pixel is linear from its value now to its first knot and
        between its knots, and holds its last knot's value after it; a pixel without knots holds
        its value. Each pixel's events are exactly those that frames at its own knot times give
        it through :meth:`step_log`, whatever the other pixels' knots: no other pixel's time
        splits its segments (feeding one frame per knot time would interpolate every pixel at
        every time, and shift its crossings by the rounding of those split points). Only
        segments that reach the pixel's next level up or down are worked out, one per pixel per
        round. Shot and leak noise are drawn once over the whole interval; with per-interval
        threshold noise (``interval_sigma``) each segment of a pixel is its own interval.
        """
        self._need_state()
        t1 = self._check_time(t_end)
        pix, t, L = self._check_knots(pix, t_ns, log_values, t1)
        t0_all, dt_all = self._t, t1 - self._t
        first = np.ones(pix.size, bool)
        np.not_equal(pix[1:], pix[:-1], out=first[1:])
        seg_t0 = np.empty_like(t)
        seg_t0[first] = t0_all
        seg_t0[~first] = t[:-1][~first[1:]]
        seg_L0 = np.empty_like(L)
        seg_L0[first] = self._L[pix[first]]
        seg_L0[~first] = L[:-1][~first[1:]]
        self.pixels_processed += pix.size
        parts = self._segment_crossings(pix, seg_t0, seg_L0, t, L)
        noisy = False
        for rate, polarity in ((self.shot_noise_rate_hz, None), (self.leak_rate_hz, 1)):
            if rate > 0:
                npix, noff, npol = _noise.poisson_events(self._rng_noise, rate, self.n_pixels, dt_all, polarity)
                if npix.size:
                    noisy = True
                    parts.append((npix, noff + t0_all, npol))
        last = np.ones(pix.size, bool)
        np.not_equal(pix[1:], pix[:-1], out=last[:-1])
        self._L[pix[last]] = L[last]
        self._I = None                  # intensities unknown from here on: compare in log next time
        self._t = t1
        self.frames_processed += 1
        if not parts:
            return empty_events()
        ep = np.concatenate([q[0] for q in parts])
        et = np.concatenate([q[1] for q in parts])
        epol = np.concatenate([q[2] for q in parts])
        # pixel-major, time order (stable: a pixel's rounds come in time order, crossings in order)
        order = np.lexsort((et, ep)) if noisy else np.argsort(ep, kind="stable")
        ep, et, epol = ep[order], et[order], epol[order]
        if self.refractory_ns > 0:
            keep = self._refractory(ep, et)
            ep, et, epol = ep[keep], et[keep], epol[keep]
        order = _stable_argsort_offsets(et - t0_all, dt_all)
        out = np.empty(ep.size, EVENT_DTYPE)
        out["t"] = et[order]
        ps = ep[order]
        out["x"] = self._xs[ps]
        out["y"] = self._ys[ps]
        out["p"] = epol[order]
        return out

    def _check_knots(self, pix, t_ns, log_values, t_end: int):
        """(pix, t, L) of :meth:`step_knots`, checked, sorted pixel-major then by time."""
        where = f"knots up to t={t_end} ns"
        pix, t, L = np.asarray(pix), np.asarray(t_ns), np.asarray(log_values)
        if not (pix.ndim == t.ndim == L.ndim == 1 and pix.size == t.size == L.size):
            raise InputError(f"{where}: pixels, times and log values must be three 1-D arrays of one length "
                             f"(got shapes {pix.shape}, {t.shape}, {L.shape})")
        if pix.dtype.kind not in "iu" or t.dtype.kind not in "iu":
            raise InputError(f"{where}: pixel indices and times must be integers (got {pix.dtype}, {t.dtype}); "
                             "times are int64 nanoseconds")
        if L.dtype.kind != "f" or not np.all(np.isfinite(L)):
            raise InputError(f"{where}: log values must be finite floats (log(I + eps))")
        if pix.size and (pix.min() < 0 or pix.max() >= self.n_pixels):
            raise InputError(f"{where}: a pixel index is outside 0..{self.n_pixels - 1}")
        t = t.astype(np.int64)
        if t.size and (t.min() <= self._t or t.max() > t_end):
            raise InputError(f"{where}: a knot time lies outside ({self._t}, {t_end}] ns")
        pix = pix.astype(np.int64)
        span = int(t_end) - int(self._t)                # knot times lie in (self._t, t_end]
        if self.n_pixels * (span + 1) < 1 << 62:
            # one int64 key, pixel-major then time: one sort, 2-3x faster than lexsort's two keys
            key = pix * np.int64(span + 1) + (t - np.int64(self._t))
            order = np.argsort(key, kind="stable")
            key = key[order]
            twice = np.any(key[1:] == key[:-1])
        else:
            order = np.lexsort((t, pix))
            p, tt = pix[order], t[order]
            twice = np.any((p[1:] == p[:-1]) & (tt[1:] == tt[:-1]))
        if twice:
            raise InputError(f"{where}: a pixel has two knots at one time")
        return pix[order], t[order], L[order].astype(np.float64)

    def _segment_crossings(self, pix, t0, L0, t1, L1) -> list:
        """The crossings of the segments (pix, t0, L0) -> (t1, L1), pixel-major and in time order
        per pixel, as [(pixel, absolute time, polarity)] per round. A segment can fire only if it
        reaches the pixel's next level up or down, and those move only when it fires: each round
        works out the first such segment of every pixel that has one (later segments of a pixel
        wait for its new levels); per-interval noise redraws C at every moving segment."""
        out = []
        seg = np.flatnonzero(L1 != L0)          # a flat segment never fires
        stop = np.empty(self.n_pixels, np.int64)
        while seg.size:
            p = pix[seg]
            if self.interval_sigma == 0:
                hit = seg[(L1[seg] >= self._next_up[p]) | (L1[seg] <= self._next_dn[p])]
            else:
                hit = seg
            if not hit.size:
                break
            hp = pix[hit]
            head = np.ones(hit.size, bool)
            np.not_equal(hp[1:], hp[:-1], out=head[1:])
            now = hit[head]                     # each pixel's first segment that fires
            cp, ct, cpol = self._crossings(pix[now], L1[now], t1[now] - t0[now], L0[now])
            if cp.size:
                at = np.empty(self.n_pixels, np.int64)
                at[pix[now]] = t0[now]
                out.append((cp, at[cp] + ct, cpol))
            # only the later segments of the pixels that fired can fire next (against new levels)
            stop[p] = np.iinfo(np.int64).max
            stop[pix[now]] = now
            seg = seg[seg > stop[p]]
        return out

    def generate(self, frames, t_ns) -> np.ndarray:
        """Batch helper: reset at frames[0] / t_ns[0], step through the rest, return all events."""
        t = np.asarray(t_ns)
        if t.ndim != 1 or t.dtype.kind not in "iu":
            raise InputError(f"frame times must be a 1-D integer array of ns (got shape {t.shape}, "
                             f"dtype {t.dtype})")
        if len(frames) != t.shape[0]:
            raise InputError(f"{len(frames)} frames but {t.shape[0]} times")
        if t.shape[0] == 0:
            raise InputError("no frames given")
        back = np.flatnonzero(np.diff(t.astype(np.int64)) <= 0)
        if back.size:
            i = int(back[0]) + 1
            raise InputError(f"frame {i}: time {t[i]} ns is not after frame {i - 1}'s {t[i - 1]} ns; "
                             "frame times must increase strictly")
        self.reset(frames[0], int(t[0]))
        out = [self.step(frames[i], int(t[i])) for i in range(1, t.shape[0])]
        return np.concatenate(out) if out else empty_events()

    # ------------------------------------------------------------------ core
    def _step(self, idx: np.ndarray, L1: np.ndarray, t1: int) -> np.ndarray:
        """Advance to t1, where the pixels `idx` have log values `L1` (the rest are unchanged)."""
        t0 = self._t
        dt = t1 - t0
        self.pixels_processed += idx.size
        pix_parts, t_parts, p_parts = [], [], []
        if idx.size:
            pix, toff, pol = self._crossings(idx, L1, dt)
            pix_parts.append(pix)
            t_parts.append(toff)
            p_parts.append(pol)
        noisy = False
        for rate, polarity in ((self.shot_noise_rate_hz, None), (self.leak_rate_hz, 1)):
            if rate > 0:
                npix, noff, npol = _noise.poisson_events(self._rng_noise, rate, self.n_pixels, dt,
                                                         polarity)
                if npix.size:
                    noisy = True
                    pix_parts.append(npix)
                    t_parts.append(noff)
                    p_parts.append(npol)
        if idx.size == self.n_pixels:
            self._L = L1
        else:
            self._L[idx] = L1
        self._t = t1
        self.frames_processed += 1
        if not pix_parts:
            return empty_events()
        if len(pix_parts) == 1:
            pix, toff, pol = pix_parts[0], t_parts[0], p_parts[0]
        else:
            pix, toff, pol = (np.concatenate(pix_parts), np.concatenate(t_parts),
                              np.concatenate(p_parts))
        if noisy:
            # Merge the noise into pixel-major order (crossings of a pixel stay in their order).
            order = np.lexsort((toff, pix))
            pix, toff, pol = pix[order], toff[order], pol[order]
        if self.refractory_ns > 0:
            keep = self._refractory(pix, toff + t0)
            pix, toff, pol = pix[keep], toff[keep], pol[keep]
        order = _stable_argsort_offsets(toff, dt)
        out = np.empty(pix.size, EVENT_DTYPE)
        out["t"] = toff[order] + t0
        ps = pix[order]
        out["x"] = self._xs[ps]
        out["y"] = self._ys[ps]
        out["p"] = pol[order]
        return out

    def _crossings(self, idx: np.ndarray, L1: np.ndarray, dt, L0: np.ndarray | None = None):
        """All threshold crossings of the pixels `idx` (new log values `L1`): (pixel, time offset
        in (0, dt], polarity), pixel-major (ascending pixel, then crossing order). Updates the
        reference counts; the caller updates the stored log frame afterwards. ``dt`` and the
        values the pixels move from, ``L0`` (default: the stored log frame), may be per pixel."""
        full = idx.size == self.n_pixels
        cp = self._cp if np.ndim(self._cp) == 0 or full else self._cp[idx]
        cn = self._cn if np.ndim(self._cn) == 0 or full else self._cn[idx]
        if self.interval_sigma > 0:
            # ESIM's per-interval noise: new C for this interval; re-base the lattice on the
            # current reference so that the lattice step is this interval's C.
            ref = self._base[idx] + (self._n_on[idx] * cp - self._n_off[idx] * cn)
            self._base[idx] = ref
            self._n_on[idx] = 0
            self._n_off[idx] = 0
            cp = _noise.interval_thresholds(cp, self.interval_sigma, self._rng_interval, idx.size)
            cn = _noise.interval_thresholds(cn, self.interval_sigma, self._rng_interval, idx.size)
        base = self._base if full else self._base[idx]
        a = self._n_on if full else self._n_on[idx]
        b = self._n_off if full else self._n_off[idx]
        # Cheap exact pre-filter: a pixel fires only if L1 reaches the next lattice level above
        # (base + ((a+1) C+ - b C-)) or below (base + (a C+ - (b+1) C-)) its reference. Without
        # per-interval noise those levels are cached per pixel.
        if self.interval_sigma > 0:
            cand = L1 >= base + ((a + 1) * cp - b * cn)
            cand |= L1 <= base + (a * cp - (b + 1) * cn)
        elif full:
            cand = L1 >= self._next_up
            cand |= L1 <= self._next_dn
        else:
            cand = L1 >= self._next_up[idx]
            cand |= L1 <= self._next_dn[idx]
        sel = np.flatnonzero(cand)
        if sel.size == 0:
            return (np.empty(0, np.int64), np.empty(0, np.int64), np.empty(0, np.int8))
        pidx = idx[sel]
        L1 = L1[sel]
        L0 = self._L[pidx] if L0 is None else L0[sel]
        if np.ndim(dt):
            dt = dt[sel]
        base, a, b = base[sel], a[sel], b[sel]
        if np.ndim(cp):
            cp = cp[sel]
        if np.ndim(cn):
            cn = cn[sel]
        up = L1 > L0
        # Level j along the moving direction: base + (j * step + fixed), which equals the
        # lattice expression base + (a * C+ - b * C-) bit for bit (x - y == x + (-y) in IEEE).
        step = np.where(up, cp, -cn)
        fixed = np.where(up, -(b * cn), a * cp)
        j0 = np.where(up, a, b)

        def reached(j, x):
            lv = base + (j * step + fixed)
            return np.where(up, lv <= x, lv >= x)

        def last_reached(x):
            # Largest j whose level x has reached (or passed); estimate, then fix rounding.
            j = np.floor((x - base - fixed) / step).astype(np.int64)
            j += reached(j + 1, x)
            j -= ~reached(j, x)
            return j

        hi = last_reached(L1)
        lo = j0 if self.interval_sigma == 0 else np.maximum(j0, last_reached(L0))
        n = hi - lo
        moved = n > 0
        if not moved.all():
            keep = np.flatnonzero(moved)
            pidx, L0, L1, up, step, fixed, base, lo, hi, n, a, b = (
                v[keep] for v in (pidx, L0, L1, up, step, fixed, base, lo, hi, n, a, b))
            if np.ndim(dt):
                dt = dt[keep]
            if np.ndim(cp):
                cp = cp[keep]
            if np.ndim(cn):
                cn = cn[keep]
            if n.size == 0:
                return (np.empty(0, np.int64), np.empty(0, np.int64), np.empty(0, np.int8))
        a = np.where(up, hi, a)
        b = np.where(up, b, hi)
        self._n_on[pidx] = a
        self._n_off[pidx] = b
        if self.interval_sigma == 0:
            # the same expressions as _cache_levels, on values at hand
            self._next_up[pidx] = base + ((a + 1) * cp - b * cn)
            self._next_dn[pidx] = base + (a * cp - (b + 1) * cn)
        total = int(n.sum())
        # Crossing k (0-based) of a pixel is lattice level lo + 1 + k. Its time offset is
        # (level - L0) * dt / (L1 - L0); the levels are evenly spaced by `step`, so the offset
        # is first + k * spacing (the first level is the exact lattice value; the spacing
        # form differs from evaluating each level by ~1e-16 * dt, far below 1 ns).
        scale = np.asarray(dt, np.float64) / (L1 - L0)
        first = (base + ((lo + 1) * step + fixed) - L0) * scale
        spacing = step * scale
        starts = np.cumsum(n) - n
        k = np.arange(total, dtype=np.float64)
        k -= np.repeat(starts.astype(np.float64), n)
        k *= np.repeat(spacing, n)
        k += np.repeat(first, n)
        toff = np.rint(k, out=k)
        # Guard against round-off only: the exact offset is in (0, dt] by construction.
        np.clip(toff, 1, np.repeat(dt, n) if np.ndim(dt) else dt, out=toff)
        pol = np.repeat(np.where(up, 1, -1).astype(np.int8), n)
        return np.repeat(pidx, n), toff.astype(np.int64), pol

    def _refractory(self, pix: np.ndarray, t: np.ndarray) -> np.ndarray:
        """ESIM's refractory rule on candidates in pixel-major, time order; returns the keep mask
        and updates the last emitted time per pixel."""
        n = pix.size
        keep = np.zeros(n, bool)
        if n == 0:
            return keep
        new = np.empty(n, bool)
        new[0] = True
        np.not_equal(pix[1:], pix[:-1], out=new[1:])
        starts = np.flatnonzero(new)
        rank = np.arange(n) - np.repeat(starts, np.diff(np.append(starts, n)))
        by_rank = np.argsort(rank, kind="stable")
        counts = np.bincount(rank)
        last = self._last
        refr = self.refractory_ns
        o = 0
        # One pass per crossing rank (a pixel appears at most once per rank).
        for c in counts:
            ids = by_rank[o:o + c]
            o += c
            p = pix[ids]
            tt = t[ids]
            ok = last[p] <= tt - refr
            emit = ids[ok]
            keep[emit] = True
            last[p[ok]] = tt[ok]
        return keep


def _stable_argsort_offsets(toff: np.ndarray, dt: int) -> np.ndarray:
    """Stable argsort of time offsets in [0, dt]: LSD radix on 16-bit digits (numpy's stable
    sort of uint16 is a radix sort) when dt < 2**32, else numpy's stable sort."""
    if toff.size < 2:
        return np.arange(toff.size)
    if dt < 1 << 16:
        return np.argsort(toff.astype(np.uint16), kind="stable")
    if dt < 1 << 32:
        order = np.argsort((toff & 0xFFFF).astype(np.uint16), kind="stable")
        hi = (toff >> 16).astype(np.uint16)
        return order[np.argsort(hi[order], kind="stable")]
    return np.argsort(toff, kind="stable")


def generate_events(frames: Sequence[np.ndarray] | np.ndarray, t_ns, **options) -> np.ndarray:
    """One call: build an EventGenerator for frames (N, H, W) and return all events."""
    frames_arr = frames if isinstance(frames, np.ndarray) else None
    if frames_arr is not None:
        if frames_arr.ndim != 3:
            raise InputError(f"frames must be (N, H, W); got shape {frames_arr.shape}")
        h, w = frames_arr.shape[1:]
    else:
        if not len(frames):
            raise InputError("no frames given")
        h, w = np.shape(frames[0])
    return EventGenerator(w, h, **options).generate(frames, t_ns)
