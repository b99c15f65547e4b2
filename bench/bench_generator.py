"""Event generator benchmark: throughput against evlib, and the changed-pixel saving.

    python bench/bench_generator.py [--quick] [--out bench/results]

Writes ``generator.json`` and ``generator.png`` into ``--out``.

* **Throughput** at 346 x 260 (DAVIS346): a drifting sinusoidal texture, 100 frames at
  1 kHz (~5.8 M events at C = 0.2). Ours (`EventGenerator.step` per frame, numpy, one thread,
  exact interpolated int64-ns times, sorted output) against evlib's `ESIMSimulator`
  (torch CPU float64, every event stamped at the frame time) on identical frames in the
  same run, alternating, median of 5; both are driven frame by frame with the per-frame
  outputs kept in a list (counting and concatenation happen outside the timed loop). evlib is fed ``255 * (I + eps)`` (prepared before
  timing) so that its ``log(max(v / 255, floor))`` is our ``log(I + eps)``; per-pixel
  counts are compared too. evlib runs with torch's default thread count and with one
  thread (ours is single-threaded numpy).
* **Per-pixel knots** (the publisher's per-pixel sampling, ``sim.sampling.simulate_pixels``): a
  disc sweeping across a textured image at 64 x 64 and 128 x 128, 10 ms chunks at 0.1 ms
  resolution; the knots each chunk's bisection renders are captured, then fed to fresh
  generators in the same run both ways: ``EventGenerator.step_knots`` (each pixel on its own
  segments, only those reaching a level worked out) and one frame per distinct knot time with
  every pixel interpolated between its own knots (the feed it replaces). Per-pixel counts and
  polarities must agree; times differ where a frame splits a nearly flat segment at a rounded
  point (~4e-16 in log over a slope of ~1e-11 per 5 ms: tens of ns): reported as the largest
  difference and the share of events more than 1 ns apart (step_knots is exact on the knots).
* **Changed-pixel skipping** on a mostly static video (textured background, one 24 x 24
  square moving 2 px per frame) and on a fully static one: the same generator with
  ``skip_unchanged=False`` (every pixel processed every frame). Outputs are checked to be
  identical.
"""

from __future__ import annotations

import sys

import numpy as np

from _common import arg_parser, load_average, machine, pyplot, save_figure, timed, write_results

from evdnerf_ros.sim import LOG_EPS, EventGenerator  # noqa: E402

W, H = 346, 260


def texture_video(n, w=W, h=H):
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    frames = np.empty((n, h, w), np.float32)
    for i in range(n):
        s = 2.0 * i
        frames[i] = 0.5 + 0.45 * np.sin((xx - s) / 7.0) * np.cos((yy + 0.5 * s) / 9.0)
    return frames


def static_video(n, moving=True, w=W, h=H):
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    bg = (0.3 + 0.25 * np.sin(xx / 5.0) * np.sin(yy / 6.0)).astype(np.float32)
    frames = np.repeat(bg[None], n, axis=0)
    if moving:
        for i in range(n):
            x0 = 20 + 2 * i
            frames[i, 100:124, x0:x0 + 24] = 1.0
    return frames


def run_ours(frames, t, **kw):
    """Streaming, as evlib is driven: one call per frame, outputs kept in a list (the
    concatenation into one array happens after timing, as for evlib)."""
    gen = EventGenerator(frames.shape[2], frames.shape[1], **kw)

    def stream():
        gen.reset(frames[0], int(t[0]))
        return [gen.step(frames[i], int(t[i])) for i in range(1, len(t))]

    dt, parts = timed(stream)
    return dt, np.concatenate(parts), gen


def run_evlib(evlib_frames, t, threads):
    import torch
    from evlib.simulation.config import ESIMConfig
    from evlib.simulation.esim import ESIMSimulator

    old = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        sim = ESIMSimulator(ESIMConfig(positive_threshold=0.2, negative_threshold=0.2,
                                       refractory_period_ms=0.0, log_floor=1e-12, device="cpu",
                                       dtype="float64"))
        dt, parts = timed(lambda: [sim.process_frame(f, ti * 1e-9) for f, ti in zip(evlib_frames, t)])
    finally:
        torch.set_num_threads(old)
    counts = np.zeros(evlib_frames[0].shape, np.int64)
    n = 0
    for x, y, _, _ in parts:
        n += len(x)
        if len(x):
            np.add.at(counts, (np.asarray(y, np.int64), np.asarray(x, np.int64)), 1)
    return dt, n, counts


def throughput(n_frames, reps):
    frames = texture_video(n_frames)
    t = np.arange(n_frames, dtype=np.int64) * 1_000_000
    out = {"width": W, "height": H, "frames": n_frames, "reps": reps}
    try:
        import torch

        default_threads = torch.get_num_threads()
        evlib_frames = [(f.astype(np.float64) + LOG_EPS) * 255.0 for f in frames]
        peer_error = None
    except Exception as exc:  # noqa: BLE001 - report why the peer could not run
        peer_error = f"{type(exc).__name__}: {exc}"
    ours, ev_default, ev_one = [], [], []
    ev = None
    for _ in range(reps):
        if peer_error is None:
            try:
                d, n_evlib, counts_evlib = run_evlib(evlib_frames, t, default_threads)
                ev_default.append(d)
                ev_one.append(run_evlib(evlib_frames, t, 1)[0])
            except Exception as exc:  # noqa: BLE001
                peer_error = f"{type(exc).__name__}: {exc}"
        d, ev, _ = run_ours(frames, t)
        ours.append(d)
    med = float(np.median(ours))
    out["ours"] = {"seconds": ours, "median_s": med, "events": int(ev.size),
                   "mev_per_s": ev.size / med / 1e6, "frames_per_s": (n_frames - 1) / med}
    if peer_error is None:
        mine = np.zeros((H, W), np.int64)
        np.add.at(mine, (ev["y"].astype(np.int64), ev["x"].astype(np.int64)), 1)
        for key, times, th in (("evlib", ev_default, default_threads), ("evlib_1thread", ev_one, 1)):
            m = float(np.median(times))
            out[key] = {"seconds": times, "median_s": m, "events": int(n_evlib),
                        "torch_threads": th, "mev_per_s": n_evlib / m / 1e6,
                        "frames_per_s": (n_frames - 1) / m,
                        "ratio_evlib_time_over_ours": m / med}
        diff = np.abs(mine - counts_evlib)
        out["per_pixel_count_agreement"] = {"max_abs_diff": int(diff.max()),
                                            "pixels_differing": int((diff > 0).sum())}
    else:
        out["evlib_error"] = peer_error
    return out


def skipping(n_frames, reps):
    t = np.arange(n_frames, dtype=np.int64) * 1_000_000
    res = {}
    for name, frames in (("mostly_static", static_video(n_frames, True)),
                         ("static", static_video(n_frames, False))):
        on, off = [], []
        for _ in range(reps):
            d_on, ev_on, g_on = run_ours(frames, t)
            d_off, ev_off, g_off = run_ours(frames, t, skip_unchanged=False)
            on.append(d_on)
            off.append(d_off)
        assert ev_on.tobytes() == ev_off.tobytes()
        m_on, m_off = float(np.median(on)), float(np.median(off))
        res[name] = {
            "events": int(ev_on.size), "frames": n_frames,
            "skip_on": {"median_s": m_on, "frames_per_s": (n_frames - 1) / m_on,
                        "pixels_processed": int(g_on.pixels_processed)},
            "skip_off": {"median_s": m_off, "frames_per_s": (n_frames - 1) / m_off,
                         "pixels_processed": int(g_off.pixels_processed)},
            "speedup": m_off / m_on,
            "fraction_of_pixel_intervals_processed":
                g_on.pixels_processed / max(1, g_off.pixels_processed),
        }
    return res


def disc_scene(w, h, speed_px_per_ms=2.0):
    """render_pixels(t_ns, pixels) of a bright soft-edged disc sweeping over a texture."""
    yy, xx = np.divmod(np.arange(w * h), w)
    texture = 0.3 + 0.2 * np.sin(xx / 3.0) * np.sin(yy / 4.0)

    def render(t_ns, pix):
        cx = 0.2 * w + speed_px_per_ms * (np.asarray(t_ns, np.float64) * 1e-6)
        r = np.hypot(xx[pix] - cx, yy[pix] - 0.5 * h)
        inside = 1.0 / (1.0 + np.exp((r - 0.25 * h) / 0.7))
        return texture[pix] * (1.0 - inside) + 0.9 * inside
    return render


def feed_frames(gen, pix, t, L, t_end):
    """The replaced feed (vectorised as it was): one frame per distinct knot time, each pixel
    linear between its own knots (its value now before its first, its last after it)."""
    n = gen.n_pixels
    order = np.lexsort((t, pix))
    pix, t, L = pix[order], t[order], L[order]
    # every pixel gets a knot now (its value) and at t_end (its last value)
    last = np.ones(pix.size, bool)
    last[:-1] = pix[1:] != pix[:-1]
    ends = np.setdiff1d(np.arange(n), pix[last][t[last] == t_end])
    end_L = gen.last_log().ravel().copy()
    end_L[pix[last]] = L[last]
    pix = np.concatenate([np.arange(n), pix, ends])
    t = np.concatenate([np.full(n, gen.t_ns, np.int64), t, np.full(ends.size, t_end, np.int64)])
    L = np.concatenate([gen.last_log().ravel(), L, end_L[ends]])
    by_pixel = np.lexsort((t, pix))
    nxt = np.empty_like(by_pixel)                 # each knot's successor along its pixel
    nxt[by_pixel[:-1]] = by_pixel[1:]
    nxt[by_pixel[-1]] = by_pixel[-1]
    cut = pix[by_pixel[1:]] != pix[by_pixel[:-1]]
    nxt[by_pixel[:-1][cut]] = by_pixel[:-1][cut]
    by_time = np.argsort(t, kind="stable")
    rows, starts = np.unique(t[by_time], return_index=True)
    bounds = np.append(starts, by_time.size)
    left_t, left_L = np.empty(n, np.int64), np.empty(n)
    right_t, right_L = np.empty(n, np.int64), np.empty(n)
    out = []
    for r in range(rows.size):
        k = by_time[bounds[r]:bounds[r + 1]]
        p, s = pix[k], nxt[k]
        left_t[p], left_L[p] = rows[r], L[k]
        right_t[p], right_L[p] = t[s], L[s]
        if r == 0:
            continue
        span = right_t - left_t
        frame = left_L + (right_L - left_L) * ((rows[r] - left_t) / np.where(span > 0, span, 1))
        out.append(gen.step_log(frame.reshape(gen.height, gen.width), int(rows[r])))
    return np.concatenate(out) if out else np.empty(0)


def knots(reps, chunk_ns=10_000_000, chunks=5):
    from evdnerf_ros.sim import sampling

    res = {}
    for w in (64, 128):
        render = disc_scene(w, w)
        captured = []
        real = sampling._feed_knots

        def capture(generator, pix, j, L, j_end, times, *rest):
            later = j != j.min()
            captured.append((generator.t_ns, pix[later].copy(), times(j[later]), L[later].copy()))
            return real(generator, pix, j, L, j_end, times, *rest)

        sampling._feed_knots = capture
        try:
            g = EventGenerator(w, w)
            for c in range(chunks):
                sampling.simulate_pixels(render, c * chunk_ns, (c + 1) * chunk_ns, g, min_step_ns=100_000,
                                         max_step_ns=chunk_ns)
        finally:
            sampling._feed_knots = real
        start = np.log(render(np.zeros(w * w, np.int64), np.arange(w * w)) + LOG_EPS).reshape(w, w)

        def run(step):
            gen = EventGenerator(w, w)
            gen.reset_log(start, 0)
            return [step(gen, pix, t, L, (i + 1) * chunk_ns) for i, (_, pix, t, L) in enumerate(captured)]

        by_knots, by_frames = [], []
        for _ in range(reps):
            d, ev_k = timed(lambda: run(lambda g, *a: g.step_knots(*a)))
            by_knots.append(d)
            d, ev_f = timed(lambda: run(feed_frames))
            by_frames.append(d)
        ev_k, ev_f = np.concatenate(ev_k), np.concatenate(ev_f)
        key_k = np.lexsort((ev_k["t"], ev_k["x"], ev_k["y"]))
        key_f = np.lexsort((ev_f["t"], ev_f["x"], ev_f["y"]))
        a, b = ev_k[key_k], ev_f[key_f]
        assert a.size == b.size and np.array_equal(a["x"], b["x"]) and np.array_equal(a["p"], b["p"])
        assert np.array_equal(a["y"], b["y"])
        diff = np.abs(a["t"].astype(np.int64) - b["t"].astype(np.int64))
        mk, mf = float(np.median(by_knots)), float(np.median(by_frames))
        res[f"{w}x{w}"] = {
            "chunks": chunks, "chunk_ms": chunk_ns / 1e6, "knots": int(sum(c[1].size for c in captured)),
            "distinct_times": int(sum(np.unique(c[2]).size for c in captured)), "events": int(a.size),
            "step_knots": {"seconds": by_knots, "median_s": mk},
            "frames": {"seconds": by_frames, "median_s": mf},
            "speedup": mf / mk,
            "max_time_difference_ns": int(diff.max(initial=0)),
            "share_more_than_1ns_apart": float((diff > 1).mean()) if diff.size else 0.0,
        }
    return res


def plot(result, path):
    fig, axes = pyplot().subplots(1, 3, figsize=(15, 4))
    tp = result["throughput"]
    names, vals = ["ours (numpy, 1 thread)"], [tp["ours"]["mev_per_s"]]
    for key in ("evlib", "evlib_1thread"):
        if key in tp:
            names.append(f"evlib ({tp[key]['torch_threads']} thr)")
            vals.append(tp[key]["mev_per_s"])
    ax = axes[0]
    ax.bar(names, vals, color=["C0", "C1", "C2"][:len(vals)])
    ax.set_ylabel("M events / s")
    ax.set_title(f"{W}x{H}, {tp['frames']} frames, {tp['ours']['events'] / 1e6:.1f} M events "
                 f"(median of {tp['reps']})", fontsize=9)
    for i, v in enumerate(vals):
        ax.text(i, v, f"{v:.1f}", ha="center", va="bottom")
    ax = axes[1]
    sk = result["skipping"]
    labels = list(sk)
    x = np.arange(len(labels))
    ax.bar(x - 0.2, [sk[k]["skip_on"]["frames_per_s"] for k in labels], 0.4,
           label="changed pixels only")
    ax.bar(x + 0.2, [sk[k]["skip_off"]["frames_per_s"] for k in labels], 0.4,
           label="every pixel")
    ax.set_xticks(x, [f"{k}\n(x{sk[k]['speedup']:.1f})" for k in labels])
    ax.set_ylabel("frames / s")
    ax.set_yscale("log")
    ax.legend(fontsize=8)
    ax.set_title("changed-pixel skipping", fontsize=9)
    ax = axes[2]
    kn = result["per_pixel_knots"]
    labels = list(kn)
    x = np.arange(len(labels))
    per_s = lambda k, way: kn[k]["chunks"] * kn[k]["chunk_ms"] / 1e3 / kn[k][way]["median_s"]   # noqa: E731
    ax.bar(x - 0.2, [per_s(k, "step_knots") for k in labels], 0.4, label="step_knots (each pixel alone)")
    ax.bar(x + 0.2, [per_s(k, "frames") for k in labels], 0.4, label="a frame per knot time")
    ax.set_xticks(x, [f"{k}, {kn[k]['knots'] / 1e3:.0f} k knots\n(x{kn[k]['speedup']:.1f})" for k in labels])
    ax.set_ylabel("real-time factor of the feed")
    ax.set_yscale("log")
    ax.legend(fontsize=8)
    ax.set_title("per-pixel sampling's knots into events", fontsize=9)
    save_figure(fig, path, dpi=110)


def main(argv=None):
    ap = arg_parser(__doc__, quick="fewer frames and repetitions")
    args = ap.parse_args(argv)
    n_frames, reps = (20, 3) if args.quick else (100, 5)
    result = {
        "benchmark": "event generator",
        "quick": args.quick,
        "machine": {**machine("evlib", "torch"), "load_average_before": load_average()},
        "throughput": throughput(n_frames, reps),
        "skipping": skipping(n_frames, reps),
        "per_pixel_knots": knots(reps),
    }
    result["machine"]["load_average_after"] = load_average()
    write_results(args.out, "generator", result, plot)
    tp = result["throughput"]
    print(f"ours: {tp['ours']['median_s']:.3f} s, {tp['ours']['mev_per_s']:.2f} Mev/s, "
          f"{tp['ours']['frames_per_s']:.0f} frames/s")
    for key in ("evlib", "evlib_1thread"):
        if key in tp:
            print(f"{key}: {tp[key]['median_s']:.3f} s, ratio evlib/ours "
                  f"{tp[key]['ratio_evlib_time_over_ours']:.2f}")
    if "evlib_error" in tp:
        print("evlib could not run:", tp["evlib_error"])
    for k, v in result["skipping"].items():
        print(f"{k}: skip {v['skip_on']['frames_per_s']:.0f} fps vs all "
              f"{v['skip_off']['frames_per_s']:.0f} fps (x{v['speedup']:.1f})")
    for k, v in result["per_pixel_knots"].items():
        print(f"knots {k}: step_knots {v['step_knots']['median_s'] * 1e3:.1f} ms vs frames "
              f"{v['frames']['median_s'] * 1e3:.1f} ms (x{v['speedup']:.1f}), {v['knots']} knots, "
              f"max |dt| {v['max_time_difference_ns']} ns, {100 * v['share_more_than_1ns_apart']:.3f} % > 1 ns")
    return 0


if __name__ == "__main__":
    sys.exit(main())
