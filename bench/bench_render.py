"""Renderer benchmark: frames/s per preset, the bounding-box prefilter saving, and the
antialiasing error-against-run-time curve.

    python bench/bench_render.py [--quick] [--size 128] [--out bench/results]

Writes ``render.json`` and ``render.png`` into ``--out``.

* **frames/s**: for each preset, supersample 1 and 2, the wall time per frame (each frame
  the best of 3 runs, then the mean over several views and times) at ``--size`` x
  ``--size``; the camera stays put within a view (as the event generator uses it), so the
  textured background is computed once per view ("first frame" time is reported
  separately).  Best-of-N keeps bursts of load from other processes out of the numbers.
* **prefilter**: the same frames with the screen-space bounding-box prefilter turned off
  (every ray tested against every primitive); images are identical, the saving is the
  ratio of times and of ray x primitive tests.
* **error against run time**: for s = 1, 2, 3, 4 the mean absolute intensity error and the
  RMS log-intensity error (log(I), the quantity events threshold) against an s = 8
  reference, plotted against seconds per frame.
* **kernel backend**: one intersection kernel (65k rays x an ellipsoid) in numpy float64
  vs torch CPU float64 / float32, to justify the numpy choice.
"""

from __future__ import annotations

import os

import numpy as np

from _common import arg_parser, best_of, machine, pyplot, save_figure, write_results

from evdnerf_ros.geometry.camera import PinholeCamera  # noqa: E402
from evdnerf_ros.sim.render import SceneRenderer  # noqa: E402
from evdnerf_ros.sim.scene import list_presets, load_scene  # noqa: E402


def frame_times(sc, cam, configs, views, times, reps=3):
    """Per config: mean over frames of the best-of-``reps`` seconds per frame (warm: the
    camera already rendered once from this pose; first: background cache cleared), and ray x
    primitive tests per frame.  Configs are timed interleaved frame by frame and each frame
    takes the best of ``reps`` runs, so that bursts of load from other processes on a shared
    machine do not land in the numbers."""
    rs = {k: SceneRenderer(sc, cam, s, prefilter=pf) for k, (s, pf) in configs.items()}
    poses = sc.camera_poses()
    first = {k: [] for k in rs}
    warm = {k: [] for k in rs}
    tests = {k: 0 for k in rs}
    for v in views:
        for i, t in enumerate(times):
            for k, r in rs.items():
                n0 = r.stats.tests
                r(poses[v], t)
                tests[k] += r.stats.tests - n0
                clear = (lambda r=r: setattr(r, "_bg_cache", None)) if i == 0 else None
                (first if i == 0 else warm)[k].append(
                    best_of(lambda r=r: r(poses[v], t), reps, clear))
    n = len(views) * len(times)
    return {k: (float(np.mean(warm[k])), float(np.mean(first[k])), tests[k] / n) for k in rs}


def kernel_backend(n=65536, reps=20):
    from evdnerf_ros.sim.geometry import Ellipsoid

    rng = np.random.default_rng(0)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o = np.array([0.0, 0.0, -4.0])
    e = Ellipsoid([0.5, 0.3, 0.2])

    def warm_best_ms(f):
        f()
        return best_of(f, reps) * 1e3

    out = {"rays": n, "numpy_float64_ms": warm_best_ms(lambda: e.intersect(o, d))}
    try:
        import torch
    except ImportError:
        return out
    threads = min(2, os.cpu_count() or 1)
    for dt, name, nth in ((torch.float64, "torch_float64_1thread_ms", 1),
                          (torch.float64, f"torch_float64_{threads}threads_ms", threads),
                          (torch.float32, f"torch_float32_{threads}threads_ms", threads)):
        torch.set_num_threads(nth)
        D = torch.tensor(d, dtype=dt)
        O = torch.tensor(o, dtype=dt)
        ir = torch.tensor(1.0 / np.array([0.5, 0.3, 0.2]), dtype=dt)

        def f():
            ds, os_ = D * ir, O * ir
            a = (ds * ds).sum(1)
            b = ds @ os_
            c = (os_ * os_).sum() - 1
            disc = b * b - a * c
            t = (-b - torch.sqrt(disc.clamp(min=0))) / a
            return torch.where(disc >= 0, t, torch.full_like(t, float("inf")))
        out[name] = warm_best_ms(f)
    return out


def main(argv=None):
    ap = arg_parser(__doc__, quick="fewer views/frames, 64 px")
    ap.add_argument("--size", type=int, default=None, help="image size (default 128; 64 quick)")
    args = ap.parse_args(argv)
    size = args.size or (64 if args.quick else 128)
    views = [0, 5] if args.quick else [0, 4, 9, 13]
    nt = 3 if args.quick else 5

    presets = {}
    for name in list_presets():
        sc = load_scene(name)
        cam = PinholeCamera.from_fov(size, size, sc.cameras.fov_deg)
        times = np.linspace(sc.start_ns, sc.end_ns, nt + 1).astype(np.int64)[1:].tolist()
        m = frame_times(sc, cam, {"s1": (1, True), "s2": (2, True),
                                  "s2_no_prefilter": (2, False)}, views, times)
        row = {k: {"fps": 1.0 / w, "s_per_frame": w, "first_frame_s": f, "tests_per_frame": n}
               for k, (w, f, n) in m.items()}
        warm_np, tests_np = m["s2_no_prefilter"][0], m["s2_no_prefilter"][2]
        row["prefilter_speedup"] = warm_np / row["s2"]["s_per_frame"]
        row["prefilter_test_ratio"] = tests_np / row["s2"]["tests_per_frame"]
        row["primitives"] = len(sc.leaves)
        presets[name] = row
        print(f"{name:11s} {len(sc.leaves):2d} prims  s1 {row['s1']['fps']:7.1f} fps  "
              f"s2 {row['s2']['fps']:7.1f} fps  (no prefilter {row['s2_no_prefilter']['fps']:6.1f}"
              f" fps, x{row['prefilter_speedup']:.2f} faster, x{row['prefilter_test_ratio']:.1f} "
              f"fewer tests)  first frame s2 {row['s2']['first_frame_s'] * 1e3:.0f} ms", flush=True)

    curves = {}
    for name in (["jet-down", "multi"] if args.quick else ["jet-down", "multi", "fork"]):
        sc = load_scene(name)
        cam = PinholeCamera.from_fov(size, size, sc.cameras.fov_deg)
        T = sc.camera_poses()[4]
        t = (sc.start_ns + sc.end_ns) // 2
        ref = SceneRenderer(sc, cam, 8)(T, t).astype(np.float64)
        pts = []
        for s in (1, 2, 3, 4):
            r = SceneRenderer(sc, cam, s)
            img = r(T, t).astype(np.float64)
            sec = best_of(lambda: r(T, t), 3 if args.quick else 7)
            pts.append({"supersample": s, "s_per_frame": sec,
                        "mae": float(np.abs(img - ref).mean()),
                        "max_abs": float(np.abs(img - ref).max()),
                        "rms_log": float(np.sqrt(np.mean((np.log(img) - np.log(ref)) ** 2)))})
            print(f"  {name:9s} s={s}: {sec * 1e3:6.1f} ms/frame  MAE {pts[-1]['mae']:.5f}  "
                  f"RMS dlogI {pts[-1]['rms_log']:.5f}", flush=True)
        curves[name] = pts

    backend = kernel_backend()
    print("kernel backend (ms):", {k: round(v, 2) if isinstance(v, float) else v
                                   for k, v in backend.items()})

    result = {"benchmark": "render", "size": [size, size], "quick": bool(args.quick),
              "views": views, "frames_per_view": nt,
              "machine": machine("torch"),
              "presets": presets, "supersample_error_vs_time": curves,
              "kernel_backend": backend}
    write_results(args.out, "render", result, plot)


def plot(result, path):
    presets, curves = result["presets"], result["supersample_error_vs_time"]
    size = result["size"][0]
    fig, ax = pyplot().subplots(1, 3, figsize=(16, 4.6))
    names = list(presets)
    x = np.arange(len(names))
    ax[0].bar(x - 0.27, [presets[n]["s1"]["fps"] for n in names], 0.27, label="s=1")
    ax[0].bar(x, [presets[n]["s2"]["fps"] for n in names], 0.27, label="s=2")
    ax[0].bar(x + 0.27, [presets[n]["s2_no_prefilter"]["fps"] for n in names], 0.27,
              label="s=2, no bbox prefilter")
    ax[0].set_xticks(x, names, rotation=20)
    ax[0].set_ylabel("frames / s")
    ax[0].set_title(f"renderer throughput, {size}x{size}, {result['machine']['cpus']} CPUs")
    ax[0].set_ylim(0, 1.35 * max(presets[n]["s1"]["fps"] for n in names))
    ax[0].legend(fontsize=8, ncol=3, loc="upper center")
    for name, pts in curves.items():
        sec = [p["s_per_frame"] for p in pts]
        ax[1].loglog(sec, [p["mae"] for p in pts], "o-", label=name)
        ax[2].loglog(sec, [p["rms_log"] for p in pts], "o-", label=name)
        for p in pts:
            ax[1].annotate(f"s={p['supersample']}", (p["s_per_frame"], p["mae"]), fontsize=7)
    ax[1].set(xlabel="seconds / frame", ylabel="mean |I - I_ref(s=8)|",
              title="antialiasing: error against run time")
    ax[2].set(xlabel="seconds / frame", ylabel="RMS log-intensity error",
              title="same, in log intensity (what events see)")
    for a in ax[1:]:
        a.legend()
        a.grid(True, which="both", alpha=0.3)
    save_figure(fig, path, dpi=110)


if __name__ == "__main__":
    main()
