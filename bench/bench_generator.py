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


def plot(result, path):
    fig, axes = pyplot().subplots(1, 2, figsize=(11, 4))
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
    return 0


if __name__ == "__main__":
    sys.exit(main())
