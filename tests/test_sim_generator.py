"""The event generator against the eleven checks of notes/simulator.md, stiff cases, bad input.

The oracle `esim_reference` below is ESIM's per-pixel loop written plainly in Python (slow,
obviously right); the vectorised generator must match it exactly in counts and to 1 ns.
"""

from __future__ import annotations

import math
from fractions import Fraction

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from evdnerf_ros.errors import InputError
from evdnerf_ros.events.types import EVENT_DTYPE
from evdnerf_ros.sim import LOG_EPS, EventGenerator, generate_events, log_intensity

EPS = LOG_EPS


def esim_reference(logs, t, c_pos, c_neg):
    """ESIM's loop, per pixel, in Python: list of (t, x, y, p) per pixel (dict)."""
    n, h, w = logs.shape
    out = {}
    for y in range(h):
        for x in range(w):
            ref = logs[0, y, x]
            evs = []
            for i in range(1, n):
                L0, L1 = logs[i - 1, y, x], logs[i, y, x]
                if L1 == L0:
                    continue
                pol = 1 if L1 > L0 else -1
                c = np.broadcast_to(c_pos if pol > 0 else c_neg, (h, w))[y, x]
                cur = ref
                while True:
                    cur = cur + pol * c
                    if (pol > 0 and L0 < cur <= L1) or (pol < 0 and L1 <= cur < L0):
                        dt = int(t[i]) - int(t[i - 1])
                        off = max(1, int(round((cur - L0) * dt / (L1 - L0))))
                        evs.append((int(t[i - 1]) + off, pol))
                        ref = cur
                    else:
                        break
            out[(x, y)] = evs
    return out


def per_pixel(events, width, height):
    out = {(x, y): [] for y in range(height) for x in range(width)}
    for e in events:
        out[(int(e["x"]), int(e["y"]))].append((int(e["t"]), int(e["p"])))
    return out


def assert_same_events(got, want, tol_ns=1):
    assert got.keys() == want.keys()
    for key in want:
        g, w = got[key], want[key]
        assert len(g) == len(w), (key, len(g), len(w))
        if w:
            assert [p for _, p in g] == [p for _, p in w], key
            assert np.max(np.abs(np.array([t for t, _ in g]) - [t for t, _ in w])) <= tol_ns, key


def random_video(rng, n=8, h=5, w=6, lo=0.05, hi=2.0):
    frames = rng.uniform(lo, hi, (n, h, w))
    t = np.cumsum(rng.integers(1, 5_000_000, n)).astype(np.int64)
    return frames, t


def ramp_frames(slopes, times_ns, L0=0.0, eps=EPS):
    """Intensity frames (N, 1, P) whose log(I + eps) is L0 + slope * t (t in seconds)."""
    s = np.asarray(times_ns, np.float64)[:, None] * 1e-9
    return (np.exp(L0 + np.asarray(slopes)[None, :] * s) - eps)[:, None, :]


# ---------------------------------------------------------------- 1. log-linear ramps
def test_log_linear_ramps_exact_counts_and_times():
    slopes = np.array([1.0, -2.0, 3.7, -0.9, 25.0, 0.05])  # log units per second
    c_pos, c_neg = 0.2, 0.15
    rng = np.random.default_rng(1)
    t = np.concatenate([[0], np.unique(rng.integers(1, 999_999_999, 30)),
                        [999_999_999]]).astype(np.int64)
    frames = ramp_frames(slopes, t, L0=0.3)
    ev = generate_events(frames, t, c_pos=c_pos, c_neg=c_neg)
    for i, a in enumerate(slopes):
        mine = ev[ev["x"] == i]
        c = c_pos if a > 0 else c_neg
        n = math.floor(abs(a) * 0.999999999 / c)
        assert len(mine) == n
        assert np.all(mine["p"] == np.sign(a))
        k = np.arange(1, n + 1)
        exact = k * c / abs(a) * 1e9
        assert np.max(np.abs(mine["t"] - exact), initial=0) <= 1.0


# ---------------------------------------------------------------- 2. mid frames, streaming
def test_inserting_interpolated_mid_frames_changes_nothing(rng):
    frames, t = random_video(rng, n=6)
    base = generate_events(frames, t)
    logs = log_intensity(frames)
    tm = (t[:-1] + t[1:]) // 2
    w = ((tm - t[:-1]) / (t[1:] - t[:-1]))[:, None, None]
    mid_logs = logs[:-1] + (logs[1:] - logs[:-1]) * w
    mid = np.exp(mid_logs) - EPS
    all_f = np.empty((len(t) + len(tm),) + frames.shape[1:])
    all_f[0::2], all_f[1::2] = frames, mid
    all_t = np.empty(len(t) + len(tm), np.int64)
    all_t[0::2], all_t[1::2] = t, tm
    more = generate_events(all_f, all_t)
    assert_same_events(per_pixel(more, 6, 5), per_pixel(base, 6, 5))


@settings(deadline=None, max_examples=8)
@given(seed=st.integers(0, 2**31))
def test_streaming_equals_batch_bit_exact(seed):
    rng = np.random.default_rng(seed)
    frames, t = random_video(rng, n=12, lo=0.0, hi=3.0)
    opts = dict(c_pos=0.17, c_neg=0.23, threshold_sigma=0.03, interval_sigma=0.02,
                refractory_ns=200_000, shot_noise_rate_hz=50.0, leak_rate_hz=20.0, seed=seed)
    batch = generate_events(frames, t, **opts)
    gen = EventGenerator(6, 5, **opts)
    pieces = [gen.step(frames[0], t[0])]
    for i in range(1, 12):
        pieces.append(gen.step(frames[i], t[i]))
    stream = np.concatenate(pieces)
    assert stream.dtype == EVENT_DTYPE
    assert stream.tobytes() == batch.tobytes()
    # A second batch run on the same generator (reset) is identical too.
    assert gen.generate(frames, t).tobytes() == batch.tobytes()


def test_matches_plain_esim_loop_on_random_videos(rng):
    for sigma in (0.0, 0.05, 0.0):
        frames, t = random_video(rng, n=10, lo=0.0, hi=4.0)
        gen = EventGenerator(6, 5, c_pos=0.21, c_neg=0.13, threshold_sigma=sigma, seed=11)
        ev = gen.generate(frames, t)
        cp, cn = gen.thresholds
        want = esim_reference(log_intensity(frames), t, cp, cn)
        assert_same_events(per_pixel(ev, 6, 5), want)


# ---------------------------------------------------------------- 3. triangles, constant
def test_triangle_waves_exact_counts_without_drift():
    # log swings between L_lo and L_lo + A; the bottom frames are the first frame exactly.
    amps = np.array([0.9, 0.45, 1.33, 0.21])
    c = 0.2
    periods = 500
    lo = np.full(4, 0.2)
    hi = np.exp(np.log(lo + EPS) + amps) - EPS
    frames = np.empty((2 * periods + 1, 1, 4))
    frames[0::2, 0] = lo
    frames[1::2, 0] = hi
    t = np.arange(2 * periods + 1, dtype=np.int64) * 1_000_000
    ev = generate_events(frames, t, c_pos=c, c_neg=c)
    for i, a in enumerate(amps):
        mine = ev[ev["x"] == i]
        n = math.floor(a / c)
        assert (mine["p"] == 1).sum() == n * periods
        assert (mine["p"] == -1).sum() == n * periods


def test_triangle_with_different_thresholds_matches_exact_arithmetic():
    # C+ = 0.3, C- = 0.2 on a triangle of amplitude 0.95 in log; exact count with Fractions.
    cp, cn = Fraction(3, 10), Fraction(2, 10)
    amp = Fraction(95, 100)
    L = [Fraction(0), amp] * 40 + [Fraction(0)]
    ref, on, off = Fraction(0), 0, 0
    for L0, L1 in zip(L[:-1], L[1:]):
        if L1 > L0:
            while ref + cp <= L1:
                ref += cp
                on += 1
        else:
            while ref - cn >= L1:
                ref -= cn
                off += 1
    lo = 0.5
    frames = np.array([[[lo if v == 0 else np.exp(np.log(lo + EPS) + 0.95) - EPS]] for v in L])
    t = np.arange(len(L), dtype=np.int64) * 1000
    ev = generate_events(frames, t, c_pos=0.3, c_neg=0.2)
    assert ((ev["p"] == 1).sum(), (ev["p"] == -1).sum()) == (on, off)


def test_constant_and_subthreshold_input_give_no_events(rng):
    still = np.repeat(rng.uniform(0, 2, (1, 7, 9)), 20, axis=0)
    t = np.arange(20, dtype=np.int64) * 10_000_000
    gen = EventGenerator(9, 7)
    assert gen.generate(still, t).size == 0
    assert gen.pixels_processed == 0  # nothing changed: nothing processed
    L0 = np.log(rng.uniform(0.1, 2, (7, 9)) + EPS)
    wobble = np.array([np.exp(L0 + 0.19 * np.sin(k)) - EPS for k in range(40)])
    assert generate_events(wobble, np.arange(40, dtype=np.int64)).size == 0


# ---------------------------------------------------------------- 4. C+ != C-
def test_separate_on_and_off_thresholds():
    t = np.array([0, 1_000_000, 2_000_000], np.int64)
    # up by 1.0 then down to 0.05 in log
    frames = np.exp(np.array([0.0, 1.0, 0.05]))[:, None, None] - EPS
    ev = generate_events(frames, t, c_pos=0.3, c_neg=0.15)
    on, off = ev[ev["p"] == 1], ev[ev["p"] == -1]
    assert len(on) == 3                       # 0.3, 0.6, 0.9
    assert len(off) == 5                      # 0.75, 0.6, 0.45, 0.3, 0.15
    assert np.all(on["t"] <= 1_000_000) and np.all(off["t"] > 1_000_000)


# ---------------------------------------------------------------- 6. time offset
def test_1e4_second_offset_leaves_relative_times_bit_identical(rng):
    frames, t = random_video(rng, n=10, lo=0.0, hi=4.0)
    a = generate_events(frames, t, refractory_ns=50_000, interval_sigma=0.01, seed=3)
    off = 10_000 * 1_000_000_000
    b = generate_events(frames, t + off, refractory_ns=50_000, interval_sigma=0.01, seed=3)
    assert a.size > 100
    assert np.array_equal(b["t"] - off, a["t"])
    assert np.array_equal(a[["x", "y", "p"]], b[["x", "y", "p"]])


# ---------------------------------------------------------------- 7. step from 0
@pytest.mark.parametrize("c", [0.2, 0.05, 0.5])
def test_step_from_black(c):
    levels = np.array([1e-4, 1e-3, 0.01, 0.37, 1.0, 7.5, 100.0, 1e4])
    frames = np.stack([np.zeros((1, 8)), levels[None, :]])
    ev = generate_events(frames, np.array([0, 10_000], np.int64), c_pos=c, c_neg=c)
    counts = np.bincount(ev["x"], minlength=8)
    want = np.floor(np.log((levels + EPS) / EPS) / c).astype(int)
    assert counts.tolist() == want.tolist()
    assert np.all(ev["p"] == 1)


# ---------------------------------------------------------------- 8. scale invariance
@pytest.mark.parametrize("scale", [1000.0, 2.0**-7])
def test_scaling_radiance_and_eps_together_changes_nothing(rng, scale):
    frames, t = random_video(rng, n=8, lo=0.0, hi=3.0)
    a = generate_events(frames, t)
    b = generate_events(frames * scale, t, eps=EPS * scale)
    assert_same_events(per_pixel(b, 6, 5), per_pixel(a, 6, 5))


# ---------------------------------------------------------------- 9. refractory
def test_refractory_spacing_and_reference_still_moves():
    refr = 250_000
    # Pixel 0: 10 levels crossed in 1 ms (100 us apart), then 3 more slowly.
    t = np.array([0, 1_000_000, 11_000_000], np.int64)
    L = np.array([[0.0, 0.0], [2.01, 1.1], [2.61, 1.1]])
    frames = (np.exp(L) - EPS)[:, None, :]
    free = generate_events(frames, t)
    held = generate_events(frames, t, refractory_ns=refr)
    # Greedy filter of the free events per pixel = ESIM's rule.
    for x in (0, 1):
        ts = free["t"][free["x"] == x]
        keep, last = [], None
        for v in ts:
            if last is None or v - last >= refr:
                keep.append(v)
                last = v
        assert held["t"][held["x"] == x].tolist() == keep
    ts = held["t"][held["x"] == 0]
    assert np.all(np.diff(ts) >= refr)
    # The suppressed crossings still moved the reference: the slow part fires at the same
    # levels as without refractory (3 events after t = 1 ms).
    assert (ts > 1_000_000).sum() == 3 == (free["t"][free["x"] == 0] > 1_000_000).sum()


def test_refractory_spacing_on_random_video(rng):
    frames, t = random_video(rng, n=10, lo=0.0, hi=8.0)
    refr = 400_000
    ev = generate_events(frames, t, refractory_ns=refr, shot_noise_rate_hz=200.0, seed=5)
    pix = ev["y"].astype(np.int64) * 6 + ev["x"]
    order = np.lexsort((ev["t"], pix))
    same = pix[order][1:] == pix[order][:-1]
    assert np.all(np.diff(ev["t"][order])[same] >= refr)


# ---------------------------------------------------------------- 10. evlib peer
def test_per_pixel_counts_agree_with_evlib(rng):
    pytest.importorskip("torch")
    esim_mod = pytest.importorskip("evlib.simulation.esim")
    from evlib.simulation.config import ESIMConfig

    for _ in range(3):
        frames, t = random_video(rng, n=12, h=9, w=11, lo=0.0, hi=3.0)
        ev = generate_events(frames, t, c_pos=0.2, c_neg=0.25)
        mine = np.zeros((9, 11), int)
        np.add.at(mine, (ev["y"], ev["x"]), 1)
        sim = esim_mod.ESIMSimulator(ESIMConfig(positive_threshold=0.2, negative_threshold=0.25,
                                                refractory_period_ms=0.0, log_floor=1e-12,
                                                device="cpu", dtype="float64"))
        theirs = np.zeros((9, 11), int)
        for f, ti in zip(frames, t):
            # evlib computes log(max(v / 255, floor)); feed 255 * (I + eps) for log(I + eps).
            x, y, _, _ = sim.process_frame((f + EPS) * 255.0, ti * 1e-9)
            np.add.at(theirs, (np.asarray(y, int), np.asarray(x, int)), 1)
        assert mine.sum() > 200
        assert np.max(np.abs(mine - theirs)) <= 1


# ---------------------------------------------------------------- 11. monotone, in (t0, t1]
def test_timestamps_monotone_per_pixel_and_inside_interval(rng):
    frames, t = random_video(rng, n=15, lo=0.0, hi=5.0)
    gen = EventGenerator(6, 5, threshold_sigma=0.05, shot_noise_rate_hz=100.0, seed=2)
    gen.reset(frames[0], t[0])
    allev = []
    for i in range(1, 15):
        ev = gen.step(frames[i], t[i])
        assert np.all(ev["t"] > t[i - 1]) and np.all(ev["t"] <= t[i])
        assert np.all(np.diff(ev["t"]) >= 0)
        allev.append(ev)
    ev = np.concatenate(allev)
    pix = ev["y"].astype(int) * 6 + ev["x"]
    for p in np.unique(pix):
        assert np.all(np.diff(ev["t"][pix == p]) >= 0)


def test_ties_keep_pixel_order():
    # Every pixel crosses exactly once at the same instant: output in row-major order.
    frames = np.stack([np.full((3, 4), 0.5), np.full((3, 4), 0.5 * np.exp(0.3))])
    ev = generate_events(frames, np.array([0, 2], np.int64))
    assert (ev["y"].astype(int) * 4 + ev["x"]).tolist() == list(range(12))


# ---------------------------------------------------------------- stiff and extreme cases
def test_one_millisecond_flash():
    t = np.array([0, 10_000_000, 10_500_000, 11_000_000, 11_500_000, 30_000_000], np.int64)
    lvl = np.array([0.1, 0.1, 10.0, 10.0, 0.1, 0.1])
    frames = np.broadcast_to(lvl[:, None, None], (6, 2, 3)).copy()
    ev = generate_events(frames, t)
    n = math.floor(np.log((10 + EPS) / (0.1 + EPS)) / 0.2)
    on, off = ev[ev["p"] == 1], ev[ev["p"] == -1]
    assert len(on) == 6 * n and len(off) == 6 * n
    assert np.all((on["t"] > 10_000_000) & (on["t"] <= 10_500_000))
    assert np.all((off["t"] > 11_000_000) & (off["t"] <= 11_500_000))


def test_edge_moving_100_px_per_ms():
    w, dt = 200, 10_000              # 10 us per frame = 1 px per frame at 100 px/ms
    n = w + 1
    t = np.arange(n, dtype=np.int64) * dt
    x = np.arange(w)
    frames = np.where(x[None, :] < np.arange(n)[:, None], 1.0, 0.05)[:, None, :]
    ev = generate_events(frames, t)
    per = math.floor(np.log((1 + EPS) / (0.05 + EPS)) / 0.2)
    assert np.bincount(ev["x"], minlength=w).tolist() == [per] * w
    # pixel x flips between frame x and frame x + 1
    assert np.all(ev["t"] > ev["x"].astype(np.int64) * dt)
    assert np.all(ev["t"] <= (ev["x"].astype(np.int64) + 1) * dt)


def test_hdr_scene():
    levels = np.logspace(-4, 4, 17)
    f0 = levels[None, :]
    f1 = levels[::-1][None, :]
    ev = generate_events(np.stack([f0, f1, f0]), np.array([0, 1_000, 2_000], np.int64))
    d = np.abs(np.log((levels[::-1] + EPS) / (levels + EPS)))
    want = np.floor(d / 0.2 + 1e-12).astype(int)
    counts = np.bincount(ev["x"][ev["t"] <= 1_000], minlength=17)
    assert counts.tolist() == want.tolist()
    assert len(ev) == 2 * want.sum()


def test_one_pixel_crossing_1000_thresholds_in_one_interval():
    c = 0.01
    frames = np.exp(np.array([0.0, 10.005]))[:, None, None] - EPS
    for refr in (0, 1):
        ev = generate_events(frames, np.array([0, 10_005_000], np.int64), c_pos=c, c_neg=c,
                             refractory_ns=refr)
        assert len(ev) == 1000
        exact = np.arange(1, 1001) * 10_000   # 10 us per level
        assert np.max(np.abs(ev["t"] - exact)) <= 1


def test_black_pixels():
    f = np.zeros((5, 2, 2))
    f[3:, 0, 0] = 1.0
    ev = generate_events(f, np.arange(5, dtype=np.int64) * 100)
    assert len(ev) == math.floor(np.log(1.001 / 0.001) / 0.2) == 34
    assert np.all((ev["x"] == 0) & (ev["y"] == 0))


def test_skip_unchanged_gives_identical_events(rng):
    frames, t = random_video(rng, n=10, lo=0.0, hi=4.0)
    frames[3:6, 2:] = frames[2, 2:]           # partly static stretch
    a = generate_events(frames, t, threshold_sigma=0.04, seed=9)
    b = generate_events(frames, t, threshold_sigma=0.04, seed=9, skip_unchanged=False)
    assert a.tobytes() == b.tobytes()


def test_threshold_mismatch_is_fixed_by_seed_and_floored():
    g1 = EventGenerator(50, 40, threshold_sigma=0.05, seed=4)
    g2 = EventGenerator(50, 40, threshold_sigma=0.05, seed=4)
    assert np.array_equal(g1.thresholds[0], g2.thresholds[0])
    assert abs(g1.thresholds[0].std() - 0.05) < 0.01
    g3 = EventGenerator(50, 40, threshold_sigma=1.0, seed=4)
    assert g3.thresholds[1].min() == 0.01


def test_reference_stays_on_integer_lattice_over_many_events():
    # A pixel ramping up and down a million thresholds keeps its reference exactly on
    # base + k*C (no drift): it ends exactly where it started.
    c = 0.001
    L = np.array([0.0, 500.0005, 0.0, 500.0005, 0.0])
    frames = np.exp(L - 250)[:, None, None]      # keep intensities finite
    gen = EventGenerator(1, 1, c_pos=c, c_neg=c, eps=1e-300)
    ev = gen.generate(frames, np.arange(5, dtype=np.int64) * 10**9)
    assert len(ev) == 4 * 500_000
    assert gen.reference()[0, 0] == gen.last_log()[0, 0]


# ---------------------------------------------------------------- bad input
def test_bad_input_errors():
    gen = EventGenerator(4, 3)
    good = np.ones((3, 4))
    gen.reset(good, 0)
    bad = good.copy()
    bad[1, 2] = np.nan
    with pytest.raises(InputError, match=r"frame 1 at t=10 ns.*\(1, 2\).*not finite"):
        gen.step(bad, 10)
    bad[1, 2] = -0.5
    with pytest.raises(InputError, match=r"frame 1 at t=10 ns.*negative"):
        gen.step(bad, 10)
    bad[1, 2] = np.inf
    with pytest.raises(InputError, match="not finite"):
        gen.step(bad, 10)
    with pytest.raises(InputError, match="shape"):
        gen.step(np.ones((4, 3)), 10)
    with pytest.raises(InputError, match="not after"):
        gen.step(good, 0)
    with pytest.raises(InputError, match="not an integer"):
        gen.step(good, 10.0)
    frames = np.ones((4, 3, 4))
    frames[2, 0, 0] = np.nan
    with pytest.raises(InputError, match="frame 2 at t=20 ns"):
        gen.generate(frames, np.array([0, 10, 20, 30]))
    with pytest.raises(InputError, match="frame 2: time 10"):
        gen.generate(np.ones((3, 3, 4)), np.array([0, 10, 10]))
    with pytest.raises(InputError, match="integer"):
        gen.generate(np.ones((2, 3, 4)), np.array([0.0, 1.0]))
    for kw in (dict(c_pos=0), dict(c_neg=-1), dict(eps=0), dict(threshold_sigma=-1),
               dict(refractory_ns=-5), dict(shot_noise_rate_hz=np.nan), dict(c_pos="x"),
               dict(seed=-1), dict(refractory_ns=1.5)):
        with pytest.raises(InputError):
            EventGenerator(4, 3, **kw)
    with pytest.raises(InputError, match="width"):
        EventGenerator(0, 3)


def test_refractory_boundary_is_inclusive_like_esim():
    # Exact dyadic logs: crossings at exactly 100, 200, 300, 400 us.
    for refr, want in ((100_000, [100_000, 200_000, 300_000, 400_000]),
                       (100_001, [100_000, 300_000])):
        gen = EventGenerator(1, 1, c_pos=0.25, refractory_ns=refr)
        gen.reset_log(np.zeros((1, 1)), 0)
        assert gen.step_log(np.ones((1, 1)), 400_000)["t"].tolist() == want


def test_crossing_just_after_t0_is_stamped_inside_the_interval():
    gen = EventGenerator(1, 1, c_pos=0.25)
    gen.reset_log(np.zeros((1, 1)), 0)
    assert gen.step_log(np.full((1, 1), 0.2499999999), 1000).size == 0
    ev = gen.step_log(np.full((1, 1), 1.2499999999), 1010)   # level 0.25 at t0 + 1e-9 ns
    assert ev["t"].tolist() == [1001, 1003, 1005, 1008]


def test_mixing_log_and_intensity_frames_and_huge_intervals():
    frames = np.exp(np.array([0.0, 0.5, 1.0, 1.5]))[:, None, None] - EPS
    a = generate_events(frames, np.arange(4, dtype=np.int64) * 1000)
    gen = EventGenerator(1, 1)
    gen.reset(frames[0], 0)
    parts = [gen.step_log(log_intensity(frames[1]), 1000), gen.step(frames[2], 2000),
             gen.step(frames[3], 3000)]
    assert np.concatenate(parts).tobytes() == a.tobytes()
    with pytest.raises(InputError, match="2\\*\\*53"):
        gen.step(frames[0], 3000 + 2**53 + 1)


# ---------------------------------------------------------------- per-pixel knots (step_knots)
def _random_knots(rng, n_pix, t_end, max_knots=7, scale=1.0):
    pix, t, L = [], [], []
    for p in range(n_pix):
        k = int(rng.integers(0, max_knots + 1))
        times = np.sort(rng.choice(np.arange(1, t_end + 1), size=k, replace=False))
        pix += [p] * k
        t += times.tolist()
        L += rng.normal(0.0, scale, k).tolist()
    return np.array(pix, np.int64), np.array(t, np.int64), np.array(L)


def test_knots_give_each_pixel_exactly_the_events_of_its_own_frames(rng):
    """Each pixel's events are those of frames at its own knot times only (a 1-pixel generator fed
    them), bit for bit; the whole is sorted by time, ties in pixel order; a pixel holds its last
    knot's value, one without knots its value. Stiff values among them: black (log eps), HDR, a
    jump of hundreds of thresholds in one segment."""
    w, h, t_end = 7, 3, 2_000_000
    opts = dict(c_pos=0.17, c_neg=0.23, refractory_ns=3_000)
    for _ in range(5):
        pix, t, L = _random_knots(rng, w * h, t_end)
        L[pix == 0] = np.log(EPS)                         # black
        L[pix == 1] = np.log(1e6 + EPS)                   # HDR
        L[(pix == 2) & (t == t[pix == 2].max(initial=0))] = 60.0
        start = rng.normal(0.0, 1.0, w * h)
        gen = EventGenerator(w, h, **opts)
        gen.reset_log(start.reshape(h, w), 0)
        ev = gen.step_knots(pix, t, L, t_end)
        assert np.all(np.diff(ev["t"].astype(np.int64)) >= 0) and gen.t_ns == t_end
        key = ev["t"].astype(np.int64) * (w * h) + ev["y"].astype(np.int64) * w + ev["x"]
        assert np.all(np.diff(key) >= 0)                  # ties: pixel order
        for p in range(w * h):
            one = EventGenerator(1, 1, **opts)
            one.reset_log(np.array([[start[p]]]), 0)
            mine = pix == p
            want = [one.step_log(np.array([[v]]), int(tt)) for tt, v in zip(t[mine], L[mine])]
            want = np.concatenate(want) if want else np.empty(0, EVENT_DTYPE)
            got = ev[(ev["x"] == p % w) & (ev["y"] == p // w)]
            assert np.array_equal(got["t"], want["t"]) and np.array_equal(got["p"], want["p"]), p
            assert gen.last_log().ravel()[p] == (L[mine][-1] if mine.any() else start[p])
    assert ev[(ev["x"] == 2) & (ev["y"] == 0)].size > 100


def test_knots_at_common_times_are_the_frames_bit_for_bit(rng):
    """Every pixel with knots at the same times: step_knots is step_log at those frames, noise of
    the thresholds (mismatch, per interval) and refractory included."""
    frames, t = random_video(rng, n=9)
    logs = np.log(frames + EPS)
    opts = dict(c_pos=0.15, c_neg=0.21, threshold_sigma=0.03, interval_sigma=0.02, refractory_ns=100_000, seed=4)
    a = EventGenerator(6, 5, **opts)
    a.reset_log(logs[0], int(t[0]))
    want = np.concatenate([a.step_log(logs[i], int(t[i])) for i in range(1, len(t))])
    b = EventGenerator(6, 5, **opts)
    b.reset_log(logs[0], int(t[0]))
    pix = np.tile(np.arange(30), len(t) - 1)
    got = b.step_knots(pix, np.repeat(t[1:], 30), logs[1:].reshape(-1), int(t[-1]))
    assert want.size > 0 and got.tobytes() == want.tobytes()
    assert np.array_equal(a.reference(), b.reference())


def test_knots_noise_is_drawn_over_the_whole_interval():
    """Shot and leak noise: one draw over (t, t_end] at the configured rates; still pixels."""
    gen = EventGenerator(20, 10, shot_noise_rate_hz=500.0, leak_rate_hz=200.0, seed=1)
    gen.reset_log(np.zeros((10, 20)), 1_000)
    ev = gen.step_knots(np.empty(0, np.int64), np.empty(0, np.int64), np.empty(0), 1_000 + 2_000_000_000)
    expect_on, expect_off = (250.0 + 200.0) * 200 * 2.0, 250.0 * 200 * 2.0
    on, off = int((ev["p"] > 0).sum()), int((ev["p"] < 0).sum())
    assert abs(on - expect_on) < 5 * np.sqrt(expect_on) and abs(off - expect_off) < 5 * np.sqrt(expect_off)
    assert ev["t"].min() > 1_000 and ev["t"].max() <= 1_000 + 2_000_000_000
    assert np.all(np.diff(ev["t"].astype(np.int64)) >= 0)


def test_knots_bad_input_is_refused_and_changes_nothing():
    gen = EventGenerator(4, 2)
    ok = (np.array([0, 1]), np.array([10, 20]), np.array([0.5, -0.5]))
    with pytest.raises(InputError, match="no frame yet"):
        gen.step_knots(*ok, 20)
    gen.reset_log(np.zeros((2, 4)), 0)
    bad = [((np.array([0]), np.array([10, 20]), np.array([0.5, 0.1])), 20, "three 1-D arrays"),
           ((np.array([0]), np.array([10.0]), np.array([0.5])), 20, "integers"),
           ((np.array([0]), np.array([10]), np.array([np.nan])), 20, "finite"),
           ((np.array([8]), np.array([10]), np.array([0.5])), 20, r"outside 0\.\.7"),
           ((np.array([0]), np.array([0]), np.array([0.5])), 20, r"outside \(0, 20\]"),
           ((np.array([0]), np.array([30]), np.array([0.5])), 20, r"outside \(0, 20\]"),
           ((np.array([3, 3]), np.array([5, 5]), np.array([0.5, 0.6])), 20, "two knots at one time"),
           (ok, 0, "not after")]
    for args, t_end, match in bad:
        with pytest.raises(InputError, match=match):
            gen.step_knots(*args, t_end)
        assert gen.t_ns == 0 and not gen.last_log().any() and gen.frames_processed == 1
    assert gen.step_knots(*ok, 20).size == 4


def test_knots_are_sorted_alike_by_one_key_and_over_spans_too_long_for_it():
    """Knots sort pixel-major, then by time, by one int64 key; over a span too long for that key
    (pixels x span >= 2**62) by two keys: the same order and the same refusal of a repeated knot."""
    rng = np.random.default_rng(3)
    pix = rng.integers(0, 8, 200)
    t = rng.permutation(np.arange(1, 201, dtype=np.int64))
    L = rng.normal(size=200)
    out = []
    for t_end in (1_000, 1 << 61):                               # 8 x 2**61 >= 2**62: the two-key sort
        gen = EventGenerator(4, 2)
        gen.reset_log(np.zeros((2, 4)), 0)
        out.append(gen._check_knots(pix, t, L, t_end))
        with pytest.raises(InputError, match="two knots at one time"):
            gen._check_knots(np.r_[pix, pix[7]], np.r_[t, t[7]], np.r_[L, 0.0], t_end)
    for a, b in zip(*out):
        np.testing.assert_array_equal(a, b)
    assert np.all(np.diff(out[0][0]) >= 0) and np.all(np.diff(out[0][1])[np.diff(out[0][0]) == 0] > 0)


def test_knots_at_the_extremes_of_time():
    """A 1 ns segment crossing ten levels stamps them all at its end; a segment of 2**53 ns (the
    longest interval) places its crossings within a few ns of the exact times."""
    gen = EventGenerator(2, 1, c_pos=0.2, c_neg=0.2)
    gen.reset_log(np.zeros((1, 2)), 0)
    span = 1 << 53
    ev = gen.step_knots(np.array([0, 0, 1]), np.array([1, 2, span]), np.array([2.0 + 1e-9, 0.0, 1.0 + 1e-9]), span)
    fast, slow = ev[ev["x"] == 0], ev[ev["x"] == 1]
    assert fast["t"].tolist() == [1] * 10 + [2] * 10 and fast["p"].tolist() == [1] * 10 + [-1] * 10
    exact = np.array([Fraction(k, 5) / (1 + Fraction(1, 10**9)) * span for k in range(1, 6)], dtype=object)
    assert slow.size == 5 and np.all(slow["p"] == 1)
    assert max(abs(int(t) - float(e)) for t, e in zip(slow["t"], exact)) <= 4
