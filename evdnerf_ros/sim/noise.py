"""Sensor non-idealities of the event generator: threshold mismatch, per-interval threshold
noise, shot noise and leak events. All draws come from numpy Generators seeded from the
generator's `seed`, so a simulation is reproducible bit for bit.

Models (and what they are not):

* **Threshold mismatch** (`threshold_sigma`): each pixel's C+ and C- are drawn once, from
  N(c_pos, sigma) and N(c_neg, sigma) independently, and kept for the generator's life
  (v2e's model; v2e's default sigma is 0.03).
* **Per-interval threshold noise** (`interval_sigma`): ESIM's model. For every pixel that
  changes in an interval, the interval's C is redrawn from N(C_pixel, sigma).
* Both draws are floored at :data:`MIN_THRESHOLD` = 0.01 log units. That floor is part of
  the noise *model* (ESIM does exactly this: a threshold must stay positive or the pixel
  would fire without end); it never touches input data.
* **Shot noise** (`shot_noise_rate_hz`): each pixel fires spurious events as a Poisson
  process of that rate, polarity +1 or -1 with equal probability, times uniform on the
  integer nanoseconds of the interval. (v2e makes the rate grow in the dark; here it is
  uniform, which is the simple, documented choice.)
* **Leak events** (`leak_rate_hz`): each pixel fires spurious ON events as a Poisson
  process of that rate (the reset switch's junction leakage slowly lowers the stored
  reference, so ON events appear without any change in light).
* Noise events do not move the crossing reference (a real leak/shot event resets the
  pixel to the *current* light level, which is where the reference lattice already
  is to within one threshold). They do respect the refractory period like any event.
"""

from __future__ import annotations

import numpy as np

#: Smallest threshold any noise draw may produce (ESIM's floor), in log units.
MIN_THRESHOLD = 0.01
#: Default contrast thresholds C+ = C- (log units) of the simulator, video2events and the publisher.
DEFAULT_THRESHOLD = 0.2


def _rngs(seed: int):
    """Independent streams: (mismatch, per-interval thresholds, shot/leak noise)."""
    return (np.random.default_rng([int(seed), 0]), np.random.default_rng([int(seed), 1]),
            np.random.default_rng([int(seed), 2]))


def mismatch_thresholds(n_pixels: int, c: float, sigma: float, rng: np.random.Generator):
    """Per-pixel thresholds N(c, sigma) floored at MIN_THRESHOLD; the scalar c when sigma == 0."""
    if sigma <= 0:
        return c
    return np.maximum(c + sigma * rng.standard_normal(n_pixels), MIN_THRESHOLD)


def interval_thresholds(c, sigma: float, rng: np.random.Generator, n: int):
    """This interval's thresholds for `n` pixels: N(c, sigma) floored at MIN_THRESHOLD."""
    return np.maximum(c + sigma * rng.standard_normal(n), MIN_THRESHOLD)


def poisson_events(rng: np.random.Generator, rate_hz: float, n_pixels: int, dt_ns: int,
                   polarity: int | None):
    """Spurious events in one interval (t0, t0 + dt_ns]: (pixel, time offset ns, polarity).

    `polarity` None draws +1/-1 with equal probability (shot noise); +1 gives leak events.
    """
    lam = rate_hz * (dt_ns * 1e-9) * n_pixels
    n = int(rng.poisson(lam)) if lam > 0 else 0
    pix = rng.integers(0, n_pixels, n)
    off = rng.integers(1, dt_ns + 1, n, dtype=np.int64)
    if polarity is None:
        pol = (rng.integers(0, 2, n) * 2 - 1).astype(np.int8)
    else:
        pol = np.full(n, polarity, np.int8)
    return pix, off, pol
