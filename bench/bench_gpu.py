"""Train, eval and publish on a GPU (the ``device`` setting), against the CPU of the same machine.

Runs where a CUDA GPU is present (``--device cuda``; ``--device cpu`` runs the same script on a
CPU, e.g. to check it).  Data: the quality benchmark's Jet-Down set (128x128, 18 + 18 views,
``bench_quality.build_set``; ``--quick``: 64x64, 12 + 4 views).

1. **Step time**: ms per training iteration of each config below on the device and on the CPU
   (all of the machine's cores), after a warm-up, same data and seed.
2. **Quality against wall time on the device**: each config trained ``--seconds`` with the
   periodic validation (32 windows, 4 validation views: events-PSNR, its all-zero floor, the true
   scene's score, the fraction of the floor-to-truth margin closed), then scored at 32 / 128 /
   256 windows (``bench_quality.final_scores``); and the wall time of ``evdnerf eval`` (x1).
3. **Publisher**: from the default config's run, published events against the simulator's along
   the same path (``eval.published``) at several resolutions, a static novel view and the
   training ring (orbit); the publisher's real-time factor on the device (the truth is simulated
   on the CPU and not timed), for the field itself and for the field baked into a grid
   (``--bakes``: the publisher's ``bake_resolution``, 0 = the field itself).
4. **Publisher, steady state** (part ``rtf``): the same publishes without the truth over a longer
   span (``--rtf-span``, default 1 s), after one untimed publish that loads what the first one
   compiles: the real-time factor a stream keeps, with renders, render calls and render seconds;
   the static camera with and without its batched renders (``--prefetch``: the publisher's
   ``prefetch_levels``), the orbit sampled one chunk at a time or ahead (``--ahead``:
   ``render_ahead``) with rays per batch ``--ray-chunks`` (``ray_chunk``).

Usage: python bench/bench_gpu.py [--device cuda] [--seconds S] [--quick] [--work DIR]
       -> bench/results/gpu.{json,png}
"""

from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path

from _common import arg_parser, machine, pyplot, read_results, save_figure, write_json, write_results

#: configs compared (changes against the training defaults); a GPU gives more rays per step
#: nearly for free, so a bigger batch is the first thing worth measuring there.
CONFIGS = {"default": {}, "rays-4096": {"rays": 4096}}
BASE = {"eval_every": 100, "checkpoint_every": 0, "log_every": 0}


def step_times(train_set, device: str, cfg: dict, steps: int) -> dict:
    """Median and mean ms per iteration of ``steps`` iterations after 5 warm-up ones."""
    import numpy as np
    import torch

    from evdnerf_ros.train.trainer import Trainer

    tr = Trainer(train_set, {**BASE, **cfg, "eval_every": 0}, iters=steps + 5, log=lambda *_: None, device=device)
    for _ in range(5):
        tr.step()
    times = []
    for _ in range(steps):
        if tr.device.type == "cuda":
            torch.cuda.synchronize()
        t = time.perf_counter()
        tr.step()                      # float(loss) inside waits for the GPU
        times.append(time.perf_counter() - t)
    return {"device": str(tr.device), "median_ms": 1000 * float(np.median(times)),
            "mean_ms": 1000 * float(np.mean(times)), "steps": steps}


def main(argv=None):
    ap = arg_parser(__doc__, quick="64x64 Jet-Down, short runs (a check of the script)")
    ap.add_argument("--device", default="cuda", help="auto, cpu or cuda (default cuda)")
    ap.add_argument("--seconds", type=float, default=None, help="training seconds per config (default 90, quick 20)")
    ap.add_argument("--steps", type=int, default=None, help="timed iterations per config and device (default 10)")
    ap.add_argument("--resolutions", default=None, help="publisher sizes, comma-separated (default 64,128,256)")
    ap.add_argument("--span", type=float, default=0.1, help="published span in seconds (default 0.1)")
    ap.add_argument("--rtf-span", type=float, default=1.0,
                    help="published span of the steady-state part rtf, seconds (default 1)")
    ap.add_argument("--prefetch", default="0,3",
                    help="the publisher's prefetch_levels compared for the static camera in part rtf (default 0,3)")
    ap.add_argument("--ahead", default="0,0.05,0.2",
                    help="the publisher's render_ahead (s) compared for the orbit in part rtf (default 0,0.05,0.2)")
    ap.add_argument("--ray-chunks", default="16384,131072",
                    help="the publisher's ray_chunk compared for the orbit in part rtf (default 16384,131072)")
    ap.add_argument("--bakes", default="0,64", help="publisher bake_resolution values, comma-separated "
                                                    "(0: the field itself; default 0,64)")
    ap.add_argument("--work", default="/tmp/bench_gpu")
    ap.add_argument("--set", default=None, help="an existing Jet-Down TRAIN.h5 (default: build it in --work)")
    ap.add_argument("--configs", default=None, help="JSON {name: config changes} instead of the default pair")
    ap.add_argument("--parts", default="steps,train,eval,publish,rtf", help="which parts to run (comma-separated)")
    ap.add_argument("--factors", default="1,4,8", help="window factors of the final scores")
    ap.add_argument("--publish-from", default="default",
                    help="the config whose run is evaluated and published (default: default)")
    ap.add_argument("--stem", default="gpu", help="results file name")
    ap.add_argument("--replot", action="store_true", help="redraw the PNG from the JSON")
    args = ap.parse_args(argv)
    if args.replot:
        return plot(read_results(args.out, args.stem), args.out / f"{args.stem}.png")
    configs = json.loads(args.configs) if args.configs else CONFIGS
    parts = set(args.parts.split(","))
    import torch

    import bench_quality
    from evdnerf_ros.device import resolve_device
    from evdnerf_ros.eval.evaluate import run_eval, validation_eval
    from evdnerf_ros.eval.published import published_vs_true, publisher_cost
    from evdnerf_ros.io.trainingset import TrainingSet
    from evdnerf_ros.train.run import TrainedRun
    from evdnerf_ros.train.trainer import run_train

    dev = resolve_device(args.device, "--device")
    torch.set_num_threads(os.cpu_count() or 1)
    seconds = args.seconds or (20.0 if args.quick else 90.0)
    steps = args.steps or 10
    sizes = [int(s) for s in (args.resolutions or ("32,64" if args.quick else "64,128,256")).split(",")]
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    setting = dict(bench_quality.PROXY if args.quick else bench_quality.FULL)
    factors = {int(f) for f in args.factors.split(",")}
    final_views = {f: v for f, v in setting["final_views"].items() if int(f) in factors}
    train_h5 = Path(args.set) if args.set else bench_quality.build_set(work, setting)
    result = {"machine": machine("torch"), "device": str(dev),
              "gpu": torch.cuda.get_device_name(dev) if dev.type == "cuda" else None,
              "torch_cuda": torch.version.cuda, "set": str(train_h5.name), "seconds": seconds,
              "configs": configs, "steps": {}, "runs": {}, "publisher": [], "steady": []}
    log = lambda m: print(m, flush=True)  # noqa: E731

    with TrainingSet(train_h5) as ts:
        for name, cfg in configs.items() if "steps" in parts else ():
            for d in dict.fromkeys([str(dev), "cpu"]):
                r = step_times(ts, d, cfg, steps)
                result["steps"].setdefault(name, {})[d] = r
                log(f"step time {name} on {d}: {r['median_ms']:.1f} ms (median of {steps})")
    partial = args.out / f"{args.stem}.partial.json"          # what a run cut short still leaves
    write_json(partial, result)

    for name, cfg in configs.items() if "train" in parts else ():
        run = work / f"run-{name}"
        summary = run_train(train_h5, run, config={**BASE, **cfg}, minutes=seconds / 60.0, overwrite=True,
                            eval_fn=validation_eval(n_windows=32, max_views=4), log=lambda *_: None, device=str(dev))
        trained = TrainedRun.load(run)
        with TrainingSet(train_h5) as ts:
            final = bench_quality.final_scores(trained.field.to(dev), ts, trained.config, trained.box,
                                               trained.dynamic, final_views, work, train_h5.stem)
        curve = [json.loads(x) for x in (run / "metrics.jsonl").read_text().splitlines()]
        result["runs"][name] = {
            "iterations": summary["iterations"], "train_s": summary["wall_s"],
            "ms_per_iter": 1000 * summary["wall_s"] / max(1, summary["iterations"]),
            "curve": [{k: m.get(k) for k in ("iter", "wall_s", "loss", "val_psnr", "val_psnr_zero_floor",
                                             "val_psnr_truth", "val_margin_closed")} for m in curve],
            "final": final}
        log(f"{name}: {summary['iterations']} it in {summary['wall_s']:.0f} s; margin closed "
            + ", ".join(f"{k} {100 * v['margin_closed']:.1f} %" for k, v in final.items()
                        if v["margin_closed"] is not None))
        write_json(partial, result)
    # `evdnerf eval` as a user runs it (validation, training and moving splits at the trained
    # windows; the true scene is scored on the CPU either way)
    run = work / f"run-{args.publish_from}"
    result["published_run"] = args.publish_from
    if "eval" in parts:
        t = time.perf_counter()
        run_eval(run, train_h5, max_views=4, factors=(1,), log=lambda *_: None, device=str(dev))
        result["eval_s_x1"] = time.perf_counter() - t
        log(f"evdnerf eval (x1, 4 views per split) on {dev}: {result['eval_s_x1']:.1f} s")

    bakes = [int(b) for b in args.bakes.split(",")]
    for path, size, bake in [(p, s, b) for b in bakes for p, s in
                             [("static", s) for s in sizes] + [("orbit", sizes[min(1, len(sizes) - 1)])]
                             if "publish" in parts]:
        r = published_vs_true(run, train_h5, n_windows=16, static=path == "static",
                              duration_ns=int(args.span * 1e9), resolution=(size, size),
                              publisher={"device": str(dev), "bake_resolution": bake}, log=lambda *_: None)
        row = {"path": path, "bake": bake, "width": size, "height": size, "rtf": r["publisher"]["rtf"],
               "wall_s": r["publisher"]["wall_s"], "psnr": r["published"]["psnr"],
               "zero_floor": r["zero_floor"]["psnr"], "true_render": r["true_render"]["psnr"],
               "margin_closed": r["margin_closed"]}
        result["publisher"].append(row)
        log(f"publish {path} {size}x{size}{f' baked {bake}' if bake else ''} on {dev}: RTF {row['rtf']:.3g}, events PSNR {row['psnr']:.2f} dB "
            f"(floor {row['zero_floor']:.2f}, true render {row['true_render']:.2f})")
        write_json(partial, result)
    if "rtf" in parts:
        publisher_cost(run, train_h5, static=True, duration_ns=int(0.01e9), resolution=(sizes[0], sizes[0]),
                       publisher={"device": str(dev), "bake_resolution": bakes[-1]})     # untimed: warm-up
    prefetch = [int(v) for v in args.prefetch.split(",")]
    ahead = [float(v) for v in args.ahead.split(",")]
    ray_chunks = [int(v) for v in args.ray_chunks.split(",")]
    # static camera: batched renders or not; orbit: sampled ahead or not, rays per batch
    variants = {"static": [{"prefetch_levels": lv} for lv in prefetch],
                "orbit": [{"render_ahead": a, "ray_chunk": rc} for a in ahead for rc in ray_chunks]}
    for path, size, bake, extra in [(p, s, b, v) for b in bakes for p, s in
                                    [("static", s) for s in sizes] + [("orbit", s) for s in sizes]
                                    for v in variants[p] if "rtf" in parts]:
        c = publisher_cost(run, train_h5, static=path == "static", duration_ns=int(args.rtf_span * 1e9),
                           resolution=(size, size), publisher={"device": str(dev), "bake_resolution": bake, **extra})
        row = {"path": path, "bake": bake, "width": size, "height": size, "span_s": args.rtf_span,
               "prefetch_levels": extra.get("prefetch_levels", 0), **extra,
               **{k: c[k] for k in ("rtf", "wall_s", "source_s", "renders", "render_calls", "render_s",
                                    "pixels_rendered", "events")}}
        result["steady"].append(row)
        log(f"steady {path} {size}x{size}{f' baked {bake}' if bake else ''} {extra} on {dev}, {args.rtf_span:g} s: "
            f"RTF {row['rtf']:.3g} ({row['renders']} renders in {row['render_calls']} calls, {row['render_s']:.2f} "
            f"of {row['wall_s']:.2f} s rendering, {row['events']} events)")
        write_json(partial, result)
    write_results(args.out, args.stem, result, plot)
    partial.unlink()


def plot(result: dict, path: Path) -> None:
    training = bool(result["runs"] or result["steps"])      # else the publisher's parts alone: one panel
    fig, ax = pyplot().subplots(1, 3 if training else 1, figsize=(17, 4.8) if training else (9, 5.2))
    if training:
        plot_training(ax[0], result)
        plot_steps(ax[1], result)
    plot_publisher(ax[-1] if training else ax, result)
    save_figure(fig, path, dpi=110)


def plot_training(ax, result: dict) -> None:
    for name, r in result["runs"].items():
        pts = [(m["wall_s"], 100 * m["val_margin_closed"]) for m in r["curve"] if m.get("val_margin_closed") is not None]
        if pts:
            x, y = zip(*pts)
            ax.plot(x, y, marker=".", label=f"{name} ({r['ms_per_iter']:.1f} ms/it)")
    ax.axhline(0, color="grey", ls="--", lw=1)
    ax.set_xlabel(f"training wall time on {result['device']} (s)")
    ax.set_ylabel("floor-to-truth margin closed (%, 32 windows)")
    ax.set_title(f"{result['set']} on {result.get('gpu') or result['device']}", fontsize=9)
    if ax.get_legend_handles_labels()[0]:
        ax.legend(fontsize=8)


def plot_steps(ax, result: dict) -> None:
    names = list(result["steps"])
    devs = sorted({d for v in result["steps"].values() for d in v})
    for j, d in enumerate(devs):
        ax.bar([i + 0.4 * (j - (len(devs) - 1) / 2) for i in range(len(names))],
               [result["steps"][n].get(d, {}).get("median_ms", 0) for n in names], width=0.4, label=d)
    ax.set_xticks(range(len(names)), names)
    ax.set_yscale("log")
    ax.set_ylabel("ms per training iteration (median)")
    ax.set_title(f"step time, CPU = {result['machine']['cpus']} cores", fontsize=9)
    if ax.get_legend_handles_labels()[0]:
        ax.legend(fontsize=8)


def plot_publisher(ax, result: dict) -> None:
    for bake in sorted({r.get("bake", 0) for r in result["publisher"]}):
        for camera, marker in (("static", "o"), ("orbit", "s")):
            rows = [r for r in result["publisher"] if r["path"] == camera and r.get("bake", 0) == bake]
            if rows:
                ax.plot([r["width"] for r in rows], [r["rtf"] for r in rows], marker=marker,
                        ls="--" if bake else "-",
                        label=f"{camera} camera, " + (f"baked {bake}" if bake else "the field itself"))
    steady = result.get("steady", [])
    def variant(r):        # rows without render_ahead or ray_chunk ran one chunk at a time, 16384 rays
        return (r["bake"], r["path"], r.get("prefetch_levels", 0), r.get("render_ahead", 0.0), r.get("ray_chunk", 16384))

    for bake, camera, levels, ahead, ray_chunk in sorted({variant(r) for r in steady}):
        rows = [r for r in steady if variant(r) == (bake, camera, levels, ahead, ray_chunk)]
        ax.plot([r["width"] for r in rows], [r["rtf"] for r in rows], marker="o" if camera == "static" else "s",
                lw=2.5, alpha=0.6, ls="--" if bake else "-",
                label=f"{camera}, " + (f"baked {bake}" if bake else "field")
                + (f", prefetch {levels}" if camera == "static" else f", ahead {ahead:g} s, {ray_chunk} rays a batch")
                + f", {rows[0]['span_s']:g} s steady")
    ax.axhline(1, color="k", ls="--", lw=1, label="real time")
    ax.set_xscale("log", base=2)
    ax.set_yscale("log")
    ax.set_xlabel("resolution (square, px)")
    ax.set_ylabel("publisher real-time factor")
    ax.set_title(f"publishing from the trained run ({result.get('gpu') or result['device']})", fontsize=9)
    ax.legend(fontsize=7, loc="lower left")


if __name__ == "__main__":
    sys.exit(main())
