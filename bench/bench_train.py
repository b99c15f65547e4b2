"""Benchmark of `evdnerf train`: validation events-PSNR against training wall time.

Data: Jet-Down simulated at 128x128 (2x2 supersampling), 18 training + 18 validation views
(validation 10 degrees off), 30 Hz blurred frames, ground-truth clock offsets.

Runs, one after another on this machine, each in its own process (peak RSS measured):
- ``planes``: the default config (varied batching 32 -> 64 -> 128 windows, dynamic region);
- ``planes-fixed-32``, ``planes-fixed-32-4min``: the no-varied-batching ablation (32
  windows throughout) for 2 minutes, and for the default run's 4 minutes;
- ``planes-no-region``: the leave-out switch off (no dynamic region: every ray and sample
  evaluated at both window ends);
- ``planes-frames``: the blurred-frames baseline (frame supervision, no events; the paper
  uses the D-NeRF backbone for it, which is ~60x slower per step here: see docs/training.md);
- ``dnerf``: the paper's backbone (8x256 MLPs, lr 5e-4), with the dynamic region, for 60
  minutes (the issue's comparison: does ``planes`` reach dnerf's 60-minute best in 2 minutes?).
Every run logs validation events-PSNR (32 windows, the paper's protocol windows, the first
``--eval-views`` validation views) against training seconds (evaluation excluded); each
is then evaluated at 32 / 128 / 256 windows (x1, x4, x8) on more views.

Every run gets the same ``--threads`` torch threads; pin the whole benchmark to cores with
``taskset`` so that nothing else shares them (each run's stderr goes to WORK/RUN.log).

Usage: python bench/bench_train.py [--quick] [--minutes-scale S] [--threads N] [--replot]
       -> bench/results/train.{json,png}
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
from pathlib import Path

from _common import arg_parser, machine, pyplot, read_results, save_figure, write_results

RUNS = {
    # name: (minutes, config, eval views during training, eval views at the end, window factors)
    "planes": (4.0, {"eval_every": 150}, 4, 4, (1, 4, 8)),
    "planes-fixed-32": (2.0, {"windows": [32], "window_switch": [], "eval_every": 150}, 4, 4, (1, 4, 8)),
    "planes-fixed-32-4min": (4.0, {"windows": [32], "window_switch": [], "eval_every": 150}, 4, 4,
                             (1, 4, 8)),
    "planes-no-region": (2.0, {"dynamic_region": False, "eval_every": 100}, 2, 2, (1,)),
    "planes-frames": (2.0, {"supervision": "frames", "eval_every": 150}, 4, 4, (1,)),
    "dnerf": (60.0, {"backbone": "dnerf", "lr": 5e-4, "lr_warmup_iters": 10, "eval_every": 100,
                     "checkpoint_every": 100, "log_every": 5}, 1, 1, (1,)),
}


def build_set(work: Path, quick: bool) -> Path:
    from evdnerf_ros.session.convert import run_convert
    from evdnerf_ros.sim.simulate import SimulationOptions, simulate_session

    out = work / "jet-down.h5"
    if out.exists():
        return out
    n, res = (6, 64) if quick else (18, 128)
    t = time.perf_counter()
    simulate_session("jet-down", work / "session", SimulationOptions(
        views=n, val_views=n, resolution=(res, res), frame_rate_hz=30, blur_samples=4,
        gt_times=0, supersample=2, min_step_ns=2_000_000), log=lambda *_: None)
    run_convert(work / "session", out, offsets="ground-truth", log=lambda *_: None)
    print(f"simulated + converted {n}+{n} views at {res}x{res} in {time.perf_counter() - t:.0f} s",
          flush=True)
    return out


def child(args) -> None:
    """One training run + its final evaluation, in this process; prints one JSON line."""
    import torch

    from evdnerf_ros.eval.evaluate import run_eval, validation_eval
    from evdnerf_ros.train.trainer import run_train

    torch.set_num_threads(args.threads)
    minutes, cfg, ev_train, ev_final, factors = RUNS[args.run]
    minutes *= args.minutes_scale
    run_dir = Path(args.work) / args.run
    summary = run_train(args.set, run_dir, config=dict(cfg), minutes=minutes, overwrite=True,
                        eval_fn=validation_eval(n_windows=32, max_views=ev_train),
                        log=lambda m: print(m, file=sys.stderr, flush=True))
    final = run_eval(run_dir, args.set, n_windows=32, max_views=ev_final, factors=factors,
                     image_path=run_dir / "eval_events.png", log=lambda *_: None)
    metrics = [json.loads(x) for x in (run_dir / "metrics.jsonl").read_text().splitlines()]
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(json.dumps({"run": args.run, "minutes": minutes, "config": cfg,
                      "iterations": summary["iterations"], "train_s": summary["wall_s"],
                      "ms_per_iter": 1000 * summary["wall_s"] / max(1, summary["iterations"]),
                      "peak_rss_mb": peak_mb, "curve": metrics, "final": final}))


def plot(result: dict, path: Path) -> None:
    fig, ax = pyplot().subplots(1, 2, figsize=(12, 4.5))
    for name, r in result["runs"].items():
        # each run relative to its own all-zero floor (the dnerf and no-region runs are
        # evaluated on fewer views, whose floors differ)
        pts = [(m["wall_s"], m["val_psnr"] - m["val_psnr_zero_floor"]) for m in r["curve"]
               if "val_psnr" in m]
        if pts:
            x, y = zip(*pts)
            ax[0].plot(x, y, marker=".", label=f"{name} ({r['ms_per_iter']:.0f} ms/it)")
    ax[0].axhline(0, color="k", ls="--", lw=1, label="all-zero prediction")
    ax[0].set_xscale("log")
    ax[0].set_xlabel(f"training wall time (s, {result.get('threads', 2)} torch thread(s))")
    ax[0].set_ylabel("validation events PSNR - all-zero floor (dB, 32 windows)")
    ax[0].set_title("error against run time, Jet-Down 128x128, 18+18 views")
    ax[0].legend(fontsize=8)
    names = list(result["runs"])
    for j, f in enumerate((1, 4, 8)):
        gains = [result["runs"][n]["final"][f"val_windows_x{f}"]["continuous"]["psnr"]
                 - result["runs"][n]["final"][f"val_windows_x{f}"]["zero_floor"]["psnr"]
                 if f"val_windows_x{f}" in result["runs"][n]["final"] else 0.0 for n in names]
        ax[1].bar([i + 0.27 * (j - 1) for i in range(len(names))], gains, width=0.27,
                  label=f"{32 * f} windows (x{f})")
    ax[1].axhline(0, color="k", lw=1)
    ax[1].set_xticks(range(len(names)), names, rotation=20, fontsize=8)
    ax[1].set_ylabel("validation PSNR - all-zero floor (dB)")
    ax[1].set_title("final, at the trained and finer windows")
    ax[1].legend(fontsize=8)
    save_figure(fig, path, dpi=110)


def main(argv=None):
    ap = arg_parser(__doc__, quick="6+6 views at 64x64, minutes x0.1")
    ap.add_argument("--minutes-scale", type=float, default=None)
    ap.add_argument("--work", default="/tmp/bench_train")
    ap.add_argument("--runs", default=",".join(RUNS))
    ap.add_argument("--threads", type=int, default=2, help="torch threads of every run")
    ap.add_argument("--replot", action="store_true", help="redraw the PNG from the JSON")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--run", help=argparse.SUPPRESS)
    ap.add_argument("--set", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.minutes_scale is None:
        args.minutes_scale = 0.1 if args.quick else 1.0
    if args.child:
        return child(args)
    stem = "train_quick" if args.quick else "train"
    if args.replot:
        return plot(read_results(args.out, stem), args.out / f"{stem}.png")
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    train_set = build_set(work, args.quick)
    result = {"machine": machine("torch"),
              "threads": args.threads,
              "data": {"scene": "jet-down", "views": "6+6 at 64x64" if args.quick else "18+18 at 128x128"},
              "runs": {}}
    partial = work / "partial.json"
    if partial.exists():
        result["runs"] = json.loads(partial.read_text())
    for name in args.runs.split(","):
        if name in result["runs"]:
            continue
        t = time.perf_counter()
        log_path = work / f"{name}.log"
        with open(log_path, "w") as log:
            proc = subprocess.run([sys.executable, __file__, "--child", "--run", name, "--set",
                                   str(train_set), "--work", str(work), "--minutes-scale",
                                   str(args.minutes_scale), "--threads", str(args.threads)],
                                  stdout=subprocess.PIPE, stderr=log, text=True)
        if proc.returncode:
            raise SystemExit(f"run {name} failed:\n{log_path.read_text()[-3000:]}")
        result["runs"][name] = json.loads(proc.stdout.strip().splitlines()[-1])
        partial.write_text(json.dumps(result["runs"]))
        r = result["runs"][name]
        print(f"{name}: {r['iterations']} it in {r['train_s']:.0f} s ({r['ms_per_iter']:.0f} ms/it), "
              f"peak {r['peak_rss_mb']:.0f} MB, final val x1 "
              f"{r['final']['val_windows_x1']['continuous']['psnr']:.2f} dB (floor "
              f"{r['final']['val_windows_x1']['zero_floor']['psnr']:.2f}); "
              f"{time.perf_counter() - t:.0f} s with evaluation", flush=True)
    result["summary"] = summarise(result["runs"])
    write_results(args.out, stem, result, plot)
    print(json.dumps(result["summary"], indent=1))


def summarise(runs: dict) -> dict:
    """Headline comparisons, computed from the curves."""
    def curve(name):
        return [(m["wall_s"], m["val_psnr"]) for m in runs[name]["curve"] if "val_psnr" in m]

    s = {}
    if "planes" in runs and "dnerf" in runs:
        dnerf_s, best_dnerf = max(curve("dnerf"), key=lambda c: c[1])
        reach = [w for w, p in curve("planes") if p >= best_dnerf]
        s["dnerf_best_psnr"] = best_dnerf
        s["dnerf_s_to_best"] = dnerf_s
        s["dnerf_train_s"] = runs["dnerf"]["train_s"]
        s["planes_s_to_reach_dnerf_best"] = reach[0] if reach else None
        s["speedup_to_dnerf_best"] = (dnerf_s / reach[0]) if reach else None
        s["final_val_psnr"] = {n: runs[n]["final"]["val_windows_x1"]["continuous"]["psnr"]
                               for n in ("planes", "dnerf")}
        s["ms_per_iter"] = {n: r["ms_per_iter"] for n, r in runs.items()}
    if "planes" in runs and "planes-no-region" in runs:
        a, b = runs["planes"]["ms_per_iter"], runs["planes-no-region"]["ms_per_iter"]
        s["dynamic_region_speedup_per_iter"] = b / a
    if "planes" in runs and "planes-fixed-32-4min" in runs:   # equal budgets
        s["varied_batching_gain_db"] = {
            f"x{f}": runs["planes"]["final"][f"val_windows_x{f}"]["continuous"]["psnr"]
            - runs["planes-fixed-32-4min"]["final"][f"val_windows_x{f}"]["continuous"]["psnr"]
            for f in (1, 4, 8)}
    s["peak_rss_mb"] = {n: r["peak_rss_mb"] for n, r in runs.items()}
    return s


if __name__ == "__main__":
    main()
