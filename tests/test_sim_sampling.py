"""Time sampling of analytic renderers: O(dt^2) fixed-rate convergence, adaptive tolerance."""

from __future__ import annotations

import numpy as np
import pytest

from evdnerf_ros.errors import InputError
from evdnerf_ros.sim import LOG_EPS, EventGenerator, simulate_renderer

C = 0.2
SEC = 1_000_000_000


class Parabola:
    """Pixel x: L(s) = L0 + b_x * s^2 (s in seconds), rising; exact crossing times known."""

    def __init__(self, n=48, seed=0):
        rng = np.random.default_rng(seed)
        self.b = np.sort(rng.uniform(2.0, 4.0, n))
        self.L0 = -1.0
        self.calls = []

    def log(self, t_ns):
        s = np.asarray(t_ns, np.float64) * 1e-9
        return self.L0 + self.b * s**2

    def __call__(self, t_ns):
        self.calls.append(int(t_ns))
        return (np.exp(self.log(t_ns)) - LOG_EPS)[None, :]

    def exact_times(self, x, n):
        k = np.arange(1, n + 1)
        return np.sqrt(k * C / self.b[x]) * 1e9

    def timing_errors(self, ev):
        errs = []
        for x in range(self.b.size):
            mine = ev["t"][ev["x"] == x]
            n = int(np.floor(self.b[x] / C))
            assert mine.size == n          # monotone signal: counts are exact at any rate
            errs.append(np.abs(mine - self.exact_times(x, n)))
        return np.concatenate(errs)


class SigmoidEdge:
    """Pixel x: L = L_lo + A * sigmoid((t - tc_x) / tau), a fast edge sweeping the row."""

    def __init__(self, n=40, tau_ns=2_000_000, span=100_000_000, amp=2.1):
        self.tc = np.linspace(0.1, 0.9, n) * span
        self.tau, self.amp, self.lo = tau_ns, amp, -2.0

    def log(self, t_ns):
        z = (np.asarray(t_ns, np.float64)[..., None] - self.tc) / self.tau
        return self.lo + self.amp / (1.0 + np.exp(-z))

    def __call__(self, t_ns):
        return (np.exp(self.log(t_ns)) - LOG_EPS)[None, :]


def test_fixed_rate_error_falls_as_dt_squared():
    scene = Parabola()
    rates = np.array([16.0, 32.0, 64.0, 128.0])
    worst = []
    for r in rates:
        gen = EventGenerator(scene.b.size, 1)
        ev, stats = simulate_renderer(scene, 0, SEC, gen, mode="fixed", rate_hz=r)
        assert stats.renders == int(r) + 1
        worst.append(scene.timing_errors(ev).max())
    slope = np.polyfit(np.log(1.0 / rates), np.log(worst), 1)[0]
    assert 1.8 < slope < 2.2, (slope, worst)


def _log_errors(scene, ev, lo):
    """|L_true(t_event) - level crossed| for the rising (ON) events of each pixel."""
    out = []
    for x in range(scene.tc.size if hasattr(scene, "tc") else scene.b.size):
        on = ev["t"][(ev["x"] == x) & (ev["p"] == 1)]
        levels = lo[x] + C * np.arange(1, on.size + 1)
        out.append(np.abs(scene.log(on)[:, x] - levels) if on.size else np.zeros(0))
    return np.concatenate(out)


@pytest.mark.parametrize("tol", [0.1, 0.02])
def test_adaptive_sampler_meets_its_tolerance_on_parabola(tol):
    scene = Parabola()
    gen = EventGenerator(scene.b.size, 1)
    ev, stats = simulate_renderer(scene, 0, SEC, gen, tolerance_c=tol, max_step_ns=SEC // 4)
    scene.timing_errors(ev)            # exact counts
    err = np.array([np.abs(scene.log(e["t"])[e["x"]] - (scene.L0 + C * k))
                    for e, k in zip(ev, _crossing_index(ev))])
    assert err.max() <= tol * C
    assert stats.max_deviation_c < tol
    assert len(set(scene.calls)) == len(scene.calls) == stats.renders  # memoised


def _crossing_index(ev):
    """1-based index of each event among its pixel's events (events of one pixel in time order)."""
    idx = np.empty(ev.size, int)
    seen = {}
    for i, x in enumerate(ev["x"]):
        seen[x] = seen.get(x, 0) + 1
        idx[i] = seen[x]
    return idx


@pytest.mark.parametrize("tol", [0.1, 0.02])
def test_adaptive_sampler_meets_its_tolerance_on_fast_sigmoid_edge(tol):
    scene = SigmoidEdge()
    gen = EventGenerator(scene.tc.size, 1)
    ev, stats = simulate_renderer(scene, 0, 100_000_000, gen, tolerance_c=tol)
    n_on = int(np.floor(scene.amp / C))
    assert np.bincount(ev["x"][ev["p"] == 1], minlength=scene.tc.size).tolist() == \
        [n_on] * scene.tc.size
    lo = scene.log(0)          # each pixel's starting (reference) level
    assert _log_errors(scene, ev, lo).max() <= tol * C
    assert stats.max_deviation_c < tol


def test_adaptive_on_log_linear_input_uses_the_largest_steps_and_is_exact():
    slopes = np.array([3.0, -5.0, 0.7])
    render = lambda t: (np.exp(slopes * t * 1e-9) - LOG_EPS)[None, :]  # noqa: E731
    gen = EventGenerator(3, 1)
    ev, stats = simulate_renderer(render, 0, SEC, gen, max_step_ns=SEC // 8)
    assert stats.renders == 1 + 8 * 2 and stats.at_min_step == 0
    for x, a in enumerate(slopes):
        t = ev["t"][ev["x"] == x]
        k = np.arange(1, t.size + 1)
        assert t.size == int(abs(a) / C)
        assert np.max(np.abs(t - k * C / abs(a) * 1e9)) <= 1


def test_min_step_is_respected_at_a_discontinuity():
    render = lambda t: np.full((2, 2), 0.1 if t < 400_000_123 else 5.0)  # noqa: E731
    gen = EventGenerator(2, 2)
    ev, stats = simulate_renderer(render, 0, SEC, gen, min_step_ns=10_000)
    assert stats.at_min_step >= 1
    assert stats.smallest_step_ns >= 10_000
    assert stats.renders < 200
    assert ev.size == 4 * int(np.log(5.001 / 0.101) / C)
    assert np.all(np.abs(ev["t"] - 400_000_123) <= 20_000)


def test_fixed_rate_chunks_continue_a_stream_bit_exactly():
    scene = Parabola(n=8)
    g1 = EventGenerator(8, 1)
    whole, _ = simulate_renderer(scene, 0, SEC, g1, mode="fixed", rate_hz=100)
    g2 = EventGenerator(8, 1)
    a, _ = simulate_renderer(scene, 0, SEC // 2, g2, mode="fixed", rate_hz=100)
    b, s2 = simulate_renderer(scene, SEC // 2, SEC, g2, mode="fixed", rate_hz=100)
    assert s2.renders == 50                # the start frame is reused, not re-rendered
    assert np.concatenate([a, b]).tobytes() == whole.tobytes()


def test_bad_renderers_and_arguments():
    gen = EventGenerator(3, 2)

    def nan_at_7ms(t):
        img = np.ones((2, 3))
        if t >= 7_000_000:
            img[1, 1] = np.nan
        return img

    with pytest.raises(InputError, match=r"render at t=\d+ ns.*not finite"):
        simulate_renderer(nan_at_7ms, 0, 20_000_000, gen, mode="fixed", rate_hz=1000)
    with pytest.raises(InputError, match="shape"):
        simulate_renderer(lambda t: np.ones((3, 2)), 0, 10, EventGenerator(3, 2))
    with pytest.raises(InputError, match="mode"):
        simulate_renderer(lambda t: np.ones((2, 3)), 0, 10, EventGenerator(3, 2), mode="x")
    with pytest.raises(InputError, match="rate_hz"):
        simulate_renderer(lambda t: np.ones((2, 3)), 0, 10, EventGenerator(3, 2), mode="fixed")
    with pytest.raises(InputError, match="t_end"):
        simulate_renderer(lambda t: np.ones((2, 3)), 10, 10, EventGenerator(3, 2))
    with pytest.raises(InputError, match="min_step_ns"):
        simulate_renderer(lambda t: np.ones((2, 3)), 0, 10, EventGenerator(3, 2),
                          min_step_ns=100, max_step_ns=10)
    g = EventGenerator(3, 2)
    g.reset(np.ones((2, 3)), 5)
    with pytest.raises(InputError, match="not at t_start"):
        simulate_renderer(lambda t: np.ones((2, 3)), 0, 10, g)


class Swing:
    """An edge 0.3 px wide sweeps 12 px right and back twice over `span`: the images at 0,
    span / 2 and span are identical (a servo's there-and-back swing)."""

    def __init__(self, span, w=16):
        self.span, self.x = span, np.arange(w)[None, :]
        self.speed_px_per_ns = 12.0 * 2.0 * np.pi / span     # max |d/dt| of the edge

    def __call__(self, t):
        edge = 2.0 + 12.0 * np.sin(2.0 * np.pi * t / self.span) ** 2
        return np.exp(-2.0 + 0.7 / (1.0 + np.exp(-(edge - self.x) / 0.3))) - LOG_EPS

    def travel(self, a, b):
        return self.speed_px_per_ns * (b - a)


def _counts(ev, w):
    return np.bincount(ev["x"].astype(np.int64), minlength=w)


def test_motion_guard_keeps_a_there_and_back_swing_whatever_max_step():
    span, w = 100_000_000, 16
    min_step = span // 256
    scene = Swing(span, w)
    fine, fs = simulate_renderer(scene, 0, span, EventGenerator(w, 1), min_step_ns=min_step,
                                 max_step_ns=min_step)
    assert fine.size > 100 and fs.at_min_step == 256
    # Without the guard three identical images say "nothing moves": the bug the guard fixes.
    blind, _ = simulate_renderer(scene, 0, span, EventGenerator(w, 1), min_step_ns=min_step,
                                 max_step_ns=span)
    assert blind.size == 0
    for max_step in (span, span // 2, span // 16):
        ev, st = simulate_renderer(scene, 0, span, EventGenerator(w, 1), min_step_ns=min_step,
                                   max_step_ns=max_step, travel_px=scene.travel)
        assert st.motion_splits > 0
        assert _counts(ev, w).tolist() == _counts(fine, w).tolist(), max_step


def test_every_max_step_refines_to_the_same_grid():
    """Frames fed to the generator lie on t_start + j * min_step (or t_end), whatever
    max_step is; a run with max_step = min_step feeds every grid point."""
    span, min_step, t0 = 10_000_003, 100_000, 7
    scene = SigmoidEdge(n=8, tau_ns=300_000, span=span)
    for max_step in (min_step, 3 * min_step, 64 * min_step, span):
        fed = []
        simulate_renderer(scene, t0, t0 + span, EventGenerator(8, 1), min_step_ns=min_step,
                          max_step_ns=max_step, progress=fed.append)
        fed = np.array(fed) - t0
        assert fed[-1] == span and np.all((fed[:-1] % min_step) == 0) and np.all(np.diff(fed) > 0)
        if max_step == min_step:
            assert fed.size == -(-span // min_step)


def test_motion_guard_arguments():
    with pytest.raises(InputError, match="max_travel_px"):
        simulate_renderer(lambda t: np.ones((2, 3)), 0, 10_000, EventGenerator(3, 2),
                          travel_px=lambda a, b: 0.0, max_travel_px=float("nan"))


# ----------------------------------------------------------------- per-pixel adaptive sampling
def _edge_pixels(edge):
    """SigmoidEdge as a per-pixel renderer: pixel x at time t (both (M,))."""
    def render_pixels(t, pix):
        z = (np.asarray(t, np.float64) - edge.tc[pix]) / edge.tau
        return np.exp(edge.lo + edge.amp / (1.0 + np.exp(-z))) - LOG_EPS
    return render_pixels


def test_per_pixel_sampling_of_one_signal_everywhere_is_the_image_mode():
    """Every pixel the same signal: each pixel's decisions are the image's, so are the events."""
    from evdnerf_ros.sim.sampling import simulate_pixels

    edge = SigmoidEdge(n=1)
    one = _edge_pixels(edge)
    a, sa = simulate_renderer(lambda t: np.full((3, 4), one(np.array([t]), np.array([0]))[0]), 0,
                              100_000_000, EventGenerator(4, 3), min_step_ns=100_000, max_step_ns=10_000_000)
    b, sb = simulate_pixels(lambda t, pix: one(t, np.zeros_like(pix)), 0, 100_000_000, EventGenerator(4, 3),
                            min_step_ns=100_000, max_step_ns=10_000_000)
    assert a.size > 0 and a.tobytes() == b.tobytes()
    assert (sa.renders, sa.frames_fed, sa.smallest_step_ns) == (sb.renders, sb.frames_fed, sb.smallest_step_ns)
    assert sb.pixels_rendered == 12 * sb.renders and sb.mode == "per-pixel"


def test_per_pixel_sampling_refines_each_pixel_on_its_own():
    """Each pixel's events are those of the image mode run on that pixel alone (exactly: no other
    pixel's time splits its segments), for far fewer values."""
    from evdnerf_ros.sim.sampling import simulate_pixels

    edge = SigmoidEdge(n=12)
    render_pixels = _edge_pixels(edge)
    ev, st = simulate_pixels(render_pixels, 0, 100_000_000, EventGenerator(12, 1), min_step_ns=100_000,
                             max_step_ns=10_000_000)
    assert st.pixels_rendered < 0.4 * 12 * st.renders          # only the pixels that need a time render it
    for x in range(12):
        alone, _ = simulate_renderer(lambda t: render_pixels(np.array([t]), np.array([x]))[None, :], 0,
                                     100_000_000, EventGenerator(1, 1), min_step_ns=100_000,
                                     max_step_ns=10_000_000)
        mine = ev[ev["x"] == x]
        assert mine.size == alone.size > 0
        assert np.array_equal(mine["p"], alone["p"])
        assert np.array_equal(mine["t"], alone["t"])
    assert np.all(np.diff(ev["t"].astype(np.int64)) >= 0)


def test_per_pixel_sampling_continues_a_stream_and_batches_without_changing_events(monkeypatch):
    from evdnerf_ros.sim import sampling
    from evdnerf_ros.sim.sampling import simulate_pixels

    render_pixels = _edge_pixels(SigmoidEdge(n=6))
    kw = dict(min_step_ns=100_000, max_step_ns=10_000_000)
    whole, _ = simulate_pixels(render_pixels, 0, 100_000_000, EventGenerator(6, 1), **kw)
    g = EventGenerator(6, 1)
    a, _ = simulate_pixels(render_pixels, 0, 50_000_000, g, **kw)       # a top pieces' boundary
    b, sb = simulate_pixels(render_pixels, 50_000_000, 100_000_000, g, **kw)
    assert np.concatenate([a, b]).tobytes() == whole.tobytes()
    assert sb.pixels_rendered < whole.size * 100                       # the start frame is reused
    monkeypatch.setattr(sampling, "PIXEL_BATCH", 1)                      # one top piece at a time
    one_by_one, _ = simulate_pixels(render_pixels, 0, 100_000_000, EventGenerator(6, 1), **kw)
    assert one_by_one.tobytes() == whole.tobytes()


def test_per_pixel_sampling_extremes_and_errors():
    from evdnerf_ros.sim.sampling import simulate_pixels

    edge = SigmoidEdge(n=4)
    moving = _edge_pixels(edge)

    def scene(t, pix):               # pixels 0-3: the edge; 4: black; 5: HDR constant; 6: HDR ramp
        out = np.zeros(pix.size)
        e = pix < 4
        out[e] = moving(t[e], pix[e])
        out[pix == 5] = 1e6
        ramp = pix == 6
        out[ramp] = 1e5 * np.exp(8.5 * t[ramp] * 1e-9)
        return out

    ev, st = simulate_pixels(scene, 0, 100_000_000, EventGenerator(7, 1), min_step_ns=100_000,
                             max_step_ns=10_000_000)
    counts = np.bincount(ev["x"], minlength=7)
    assert counts[4] == counts[5] == 0 and counts[:4].min() > 0
    assert counts[6] == int(8.5 * 0.1 / C)                      # log-linear: exact count at the coarsest step
    tiny, st = simulate_pixels(scene, 7, 8, EventGenerator(7, 1))    # a 1 ns window: one frame
    assert st.frames_fed == 1 and st.smallest_step_ns == 1
    bad_shape = lambda t, pix: np.ones(pix.size + 1)                 # noqa: E731
    with pytest.raises(InputError, match="render of 2 pixel"):
        simulate_pixels(bad_shape, 0, 10, EventGenerator(2, 1))
    nan = lambda t, pix: np.where(t > 5, np.nan, 1.0)                # noqa: E731
    with pytest.raises(InputError, match="not finite|NaN|finite"):
        simulate_pixels(nan, 0, 10, EventGenerator(2, 1), min_step_ns=1, max_step_ns=4)
    with pytest.raises(InputError, match="t_end"):
        simulate_pixels(scene, 10, 10, EventGenerator(7, 1))
    with pytest.raises(InputError, match="tolerance_c"):
        simulate_pixels(scene, 0, 10, EventGenerator(7, 1), tolerance_c=0.0)
    with pytest.raises(InputError, match="min_step_ns .* larger"):
        simulate_pixels(scene, 0, 10, EventGenerator(7, 1), min_step_ns=5, max_step_ns=2)
    g = EventGenerator(7, 1)
    simulate_pixels(scene, 0, 10, g)
    with pytest.raises(InputError, match="not at t_start"):
        simulate_pixels(scene, 20, 30, g)


def test_per_pixel_motion_guard_keeps_a_there_and_back_swing():
    """The swing per pixel: without the guard each pixel's three samples say "nothing moves";
    with it every pixel's events are those of the finest step."""
    from evdnerf_ros.sim.sampling import simulate_pixels

    span, w = 100_000_000, 16
    min_step = span // 256
    scene = Swing(span, w)

    def pixels(t, pix):
        return np.array([scene(int(tt))[0, p] for tt, p in zip(t, pix)])

    fine, _ = simulate_renderer(scene, 0, span, EventGenerator(w, 1), min_step_ns=min_step, max_step_ns=min_step)
    blind, _ = simulate_pixels(pixels, 0, span, EventGenerator(w, 1), min_step_ns=min_step, max_step_ns=span)
    assert blind.size == 0
    ev, st = simulate_pixels(pixels, 0, span, EventGenerator(w, 1), min_step_ns=min_step, max_step_ns=span,
                             travel_px=scene.travel)
    assert st.motion_splits > 0
    assert _counts(ev, w).tolist() == _counts(fine, w).tolist()
    with pytest.raises(InputError, match="max_travel_px"):
        simulate_pixels(pixels, 0, 10_000, EventGenerator(w, 1), travel_px=scene.travel, max_travel_px=0.0)


def test_box_travel_bounds_what_a_moving_camera_sees_move():
    """``box_travel`` (a trained field's guard): nothing for a static camera; a pure rotation
    moves a background at infinity by the angle times the magnification, and a box ahead by at
    least as much as any of its points really moves in the image."""
    from evdnerf_ros.geometry.camera import PinholeCamera, look_at
    from evdnerf_ros.sim.motion import _magnification, box_travel

    cam = PinholeCamera.from_fov(64, 48, 40.0)
    box = np.array([[-0.3, -0.3, -0.3], [0.3, 0.3, 0.3]])
    times = np.arange(0, 11, dtype=np.int64) * 1_000_000
    still = np.stack([look_at([0.0, -3.0, 0.0], [0.0, 0.0, 0.0])] * times.size)
    assert box_travel(box, cam, times, still).total_px == 0.0
    turning = still.copy()
    for k, a in enumerate(np.radians(np.linspace(0.0, 2.0, times.size))):      # 2 deg about the camera's y
        c, s = np.cos(a), np.sin(a)
        turning[k, :3, :3] = still[0, :3, :3] @ np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    far = box_travel(box, cam, times, turning, infinity=True).total_px
    assert far >= np.radians(2.0) * _magnification(cam) * (1 - 1e-9)
    # a point of the box, projected at each pose: its real image travel is within the bound
    travel = box_travel(box, cam, times, turning, infinity=False)
    p = np.array([0.3, 0.3, -0.3, 1.0])
    uv = []
    for T in turning:
        x = np.linalg.inv(T) @ p
        uv.append([cam.fx * x[0] / x[2] + cam.cx, cam.fy * x[1] / x[2] + cam.cy])
    real = np.linalg.norm(np.diff(np.array(uv), axis=0), axis=1).sum()
    assert 0.0 < real <= travel.total_px
    assert travel(2_000_000, 5_000_000) <= travel.total_px
    # a camera beside a long rod, inside its bounding sphere but 0.9 m from the rod: a finite bound (the
    # distance to the box, not to its sphere), still above what the rod's points really travel
    rod = np.array([[-2.0, -0.05, -0.05], [2.0, 0.05, 0.05]])
    sliding = np.stack([look_at([0.01 * k, -0.95, 0.0], [0.01 * k, 0.0, 0.0]) for k in range(times.size)])
    beside = box_travel(rod, cam, times, sliding, infinity=False)
    assert 0.0 < beside.total_px < np.pi * _magnification(cam) / 10
    pts = np.concatenate([np.stack(np.meshgrid(*zip(*rod), indexing="ij"), -1).reshape(8, 3),
                          np.c_[np.linspace(-0.5, 0.5, 11), np.zeros(11), np.zeros(11)]])
    uv = []
    for T in sliding:
        x = (np.c_[pts, np.ones(len(pts))] @ np.linalg.inv(T).T)[:, :3]             # camera frame
        uv.append(np.c_[cam.fx * x[:, 0] / x[:, 2] + cam.cx, cam.fy * x[:, 1] / x[:, 2] + cam.cy])
    seen = (np.array(uv)[0, :, 0] > 0) & (np.array(uv)[0, :, 0] < cam.width)
    real = np.linalg.norm(np.diff(np.array(uv)[:, seen], axis=0), axis=2).sum(axis=0).max()
    assert 0.0 < real <= beside.total_px
    # many pieces at once (the per-pixel sampler's guard) equal the pieces one by one, and a plain
    # callable is asked piece by piece
    from evdnerf_ros.sim.motion import travels

    a = np.array([0, 1_500_000, 2_000_000, 9_000_000, 10_000_000], np.int64)
    b = np.array([10_000_000, 1_600_000, 5_000_000, 10_000_000, 10_000_000], np.int64)
    one_by_one = [travel(int(x), int(y)) for x, y in zip(a, b)]
    np.testing.assert_array_equal(travels(travel, a, b), one_by_one)
    np.testing.assert_array_equal(travels(lambda x, y: travel(x, y), a, b), one_by_one)
    assert travels(travel, a[:0], b[:0]).shape == (0,)


def test_per_pixel_motion_guard_splits_only_where_the_content_can_reach():
    """``reach_px``: a piece that travels too far is split for the pixels in its reach box only;
    pixels the moving content cannot reach (here a flat strip beside the swing) keep their long
    pieces, with the same events and fewer values rendered. A box that misses the content
    (a wrong caller) loses the swing: the box is what decides."""
    from evdnerf_ros.sim.sampling import simulate_pixels

    span, w, strip = 100_000_000, 16, 8
    min_step = span // 256
    scene = Swing(span, w)

    def pixels(t, pix):
        flat = np.exp(-1.5) - LOG_EPS
        return np.array([scene(int(tt))[0, p] if p < w else flat for tt, p in zip(t, pix)])

    def run(reach=None):
        return simulate_pixels(pixels, 0, span, EventGenerator(w + strip, 1), min_step_ns=min_step,
                               max_step_ns=span, travel_px=scene.travel, reach_px=reach)

    def box(x0, x1):
        return lambda a, b: np.tile([x0, 0.0, x1, 0.0], (np.size(a), 1))

    everywhere, st_all = run()
    ev, st = run(box(0.0, w - 1.0))
    assert ev.size > 0 and np.array_equal(ev, everywhere)
    assert st.pixels_rendered < st_all.pixels_rendered
    wrong, _ = run(box(float(w), w + strip - 1.0))
    assert wrong.size < ev.size / 2
    unbounded, st_inf = run(lambda a, b: np.tile([-np.inf, -np.inf, np.inf, np.inf], (np.size(a), 1)))
    assert np.array_equal(unbounded, everywhere) and st_inf.pixels_rendered == st_all.pixels_rendered
    # without the guard too: a pixel out of a top piece's reach holds its value, never rendered
    # after the start frame (the strip: 2 values per top piece saved), the same events
    kw = dict(min_step_ns=min_step, max_step_ns=span // 4)
    free, st_free = simulate_pixels(pixels, 0, span, EventGenerator(w + strip, 1), **kw)
    held, st_held = simulate_pixels(pixels, 0, span, EventGenerator(w + strip, 1), reach_px=box(0.0, w - 1.0), **kw)
    assert free.size > 0 and np.array_equal(held, free)
    assert st_held.pixels_held == strip * 4 and st_free.pixels_held == 0
    assert st_held.pixels_rendered == st_free.pixels_rendered - strip * 4 * 2


def test_box_reach_holds_every_point_of_the_box_while_the_camera_moves():
    """``ImageTravel.reach``: every point of the box, projected at any time of a piece, lies in the
    piece's reach box; a box reaching behind the camera is unbounded; with a background at
    infinity there is no reach box (anything may change anywhere)."""
    from evdnerf_ros.geometry.camera import PinholeCamera, look_at
    from evdnerf_ros.sim.motion import box_travel

    cam = PinholeCamera.from_fov(64, 48, 40.0)
    box = np.array([[-0.2, -0.2, -0.2], [0.2, 0.2, 0.2]])
    times = np.arange(0, 101, dtype=np.int64) * 100_000
    poses = np.stack([look_at([3.0 * np.sin(a), -3.0 * np.cos(a), 0.5], [0.3, 0.0, 0.0])
                      for a in np.radians(np.linspace(0.0, 30.0, times.size))])
    travel = box_travel(box, cam, times, poses, infinity=False)
    rng = np.random.default_rng(0)
    points = np.c_[rng.uniform(box[0], box[1], (200, 3)), np.ones(200)]
    for a, b in ((0, 2_000_000), (3_050_000, 3_450_000), (5_000_000, 10_000_000)):
        [(x0, y0, x1, y1)] = travel.reach(np.array([a]), np.array([b]))
        assert x1 - x0 < 64 or b - a > 4_000_000         # bounded where the motion is short
        for k in np.flatnonzero((times >= a) & (times <= b)):
            x = (np.linalg.inv(poses[k]) @ points.T)[:3]
            u, v = cam.fx * x[0] / x[2] + cam.cx, cam.fy * x[1] / x[2] + cam.cy
            assert np.all((u >= x0) & (u <= x1) & (v >= y0) & (v <= y1))
    inside = np.stack([look_at([0.0, 0.0, 0.0], [0.0, 1.0, 0.0])] * 3)          # the camera in the box
    [(x0, _, x1, _)] = box_travel(box, cam, times[:3], inside, infinity=False).reach(np.array([0]), np.array([1]))
    assert x0 == -np.inf and x1 == np.inf
    assert box_travel(box, cam, times, poses, infinity=True).reach(np.array([0]), np.array([1])) is None


@pytest.mark.parametrize("levels", [1, 3, 6])
def test_batched_prefetch_feeds_the_same_frames_and_events(levels):
    """``render_many`` with ``prefetch_levels``: the same frames fed at the same times, so the
    same events; more renders (some ahead of need), in fewer calls; the batch's times are grid
    points of the piece and none is rendered twice."""
    span, min_step = 50_000_000, 100_000
    scene = SigmoidEdge(n=12, tau_ns=1_000_000, span=span)
    runs = {}
    for k in (0, levels):
        fed, batches = [], []

        def many(times):
            batches.append(np.asarray(times).copy())
            return np.stack([scene(t) for t in times])

        ev, st = simulate_renderer(scene, 0, span, EventGenerator(12, 1), min_step_ns=min_step,
                                   max_step_ns=6_400_000, progress=fed.append, render_many=many,
                                   prefetch_levels=k)
        runs[k] = (ev, st, fed, batches)
    (ev0, st0, fed0, b0), (evk, stk, fedk, bk) = runs[0], runs[levels]
    assert ev0.size > 0 and not b0                              # 0 levels: no batch at all
    np.testing.assert_array_equal(evk, ev0)
    assert fedk == fed0
    assert stk.renders >= st0.renders and len(bk) > 0
    times = np.concatenate(bk)
    assert np.all(times % min_step == 0) and np.unique(times).size == times.size
    assert all(b.size <= 2 ** levels for b in bk)               # 2^L - 1 midpoints and the end
