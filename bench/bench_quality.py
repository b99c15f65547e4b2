"""Benchmark of training quality levers: fraction of the floor-to-truth margin closed against wall time.

Each lever is one change of the training config against the same baseline, trained for the
same wall-clock budget on the same simulated Jet-Down training set, each run in its own
process with the same torch thread count.  Every run logs, every ``eval_every`` iterations,
validation events-PSNR at 32 windows (the paper's protocol windows) on ``eval_views``
validation views spread over the ring (``spread_views``), its all-zero floor and the true scene's score, hence the
fraction of the floor-to-truth margin closed (``evdnerf_ros.eval.truth.margin_closed``).  At
the end each run is scored at 32 windows and at 4x / 8x finer windows (128, 256).

Proxy (default): Jet-Down 64x64, 12 training + 4 validation views, 90 s per lever, 1 torch
thread per run; ``--parallel 2`` runs two levers at a time (one core each).  ``--full``: the
issue's setting, Jet-Down 128x128, 18 + 18 views, 5 minutes per run, for the baseline and
the chosen combination.

``--demo``: the demo's simulated fork set (``evdnerf demo --source simulate``: 96x72, 4 training
+ 2 validation views and a moving camera), the demo's training config as the baseline, 2 minutes
per run; the final scores add the pooled margin and the moving camera (its static world as
``evdnerf eval`` resolves ``auto``: flat).  ``--views N`` puts N training views on the ring instead of 4 (the same validation views and
moving camera).  ``--sweeps N`` adds N training views whose camera
sweeps the ring (``evdnerf simulate --moving-train-views``); a lever
``"_static_training_only": true`` trains on the same set without them; a run that trained on
sweeps is scored on the moving camera with its own static world too (``moving_x1_field``).

``--rig TRAIN.h5``: a training set the demo made on the virtual rig (``evdnerf demo -o OUT`` writes
``OUT/train.h5``: 48x36, 17 training + 8 validation turntable views), the demo's training config
and field (``hinge``), 2 minutes per run, scored on every validation view (pooled, as the demo's
verdict). A lever may keep fewer training views (``"_training_views": N``, spread evenly along
the ring): the same capture and validation views with fewer training views.

Usage: python bench/bench_quality.py [--full | --default-path | --demo [--sweeps N] | --rig TRAIN.h5] [--levers a,b,...] [--seconds S]
       [--parallel N] [--replot]
       -> bench/results/quality_proxy.{json,png}, quality.{json,png}, quality_default_path.{json,png},
          quality_demo.{json,png},
          quality_demo_sweeps.{json,png} (--demo --sweeps N) or quality_rig.{json,png}
"""

from __future__ import annotations

import argparse
import hashlib
import json
import pickle
import resource
import subprocess
import sys
import time
from pathlib import Path

from _common import arg_parser, load_average, machine, pyplot, read_results, save_figure, write_results

#: The baseline every lever is compared with: the training defaults with the ``planes`` field (whose
#: levers most rows are; the default backbone, ``auto``, is a lever of its own), eval cadence aside.
BASE = {"backbone": "planes", "eval_every": 100, "checkpoint_every": 0, "log_every": 100}

#: lever name -> config changes against BASE.
LEVERS = {
    "baseline": {},
    "auto": {"backbone": "auto"},
    "before spans + background map + empty prior": {"span_fraction": 0.0, "background_cells": 0,
                                                      "background": 0.0, "empty_weight": 0.0},
    "no empty prior": {"empty_weight": 0.0},
    "empty-prior-1": {"empty_weight": 1.0},
    "no spans": {"span_fraction": 0.0},
    "no background map": {"background_cells": 0},
    "spans-0.8": {"span_fraction": 0.8},
    "background-cells-1024": {"background_cells": 1024},
    "time-res-32": {"field": {"time_resolution": 32}},
    "time-res-64": {"field": {"time_resolution": 64}},
    "density-bias-3": {"field": {"density_bias": -3.0}},
    "density-bias-5": {"field": {"density_bias": -5.0}},
    "lr-0.01": {"lr": 0.01},
    "lr-0.04": {"lr": 0.04},
    "lr-decay-0.1": {"lr_final": 0.1},
    "no-event-hinge": {"no_event_weight": 1.0},
    "time-l1-smooth": {"time_l1_weight": 1e-4, "time_smooth_weight": 1e-3},
    "samples-32": {"n_samples": 32},
    "samples-24": {"n_samples": 24},
    "rays-512": {"rays": 512},
    "rays-256": {"rays": 256},
    "samples-32-rays-512": {"n_samples": 32, "rays": 512},
    "event-rays-0.25": {"event_ray_fraction": 0.25},
    "event-rays-0": {"event_ray_fraction": 0.0},
    "windows-32": {"windows": [32], "window_switch": []},
    "space-res-128": {"field": {"resolutions": [16, 32, 64, 128]}},
    "samples-48": {"n_samples": 48},
    "event-rays-0.8": {"event_ray_fraction": 0.8},
    "lr-0.005": {"lr": 0.005},
    "hinge": {"backbone": "hinge"},
    "hinge-no-part-prior": {"backbone": "hinge", "part_empty_weight": 0.0},
    "hinge-part-prior-0.3": {"backbone": "hinge", "part_empty_weight": 0.3},
    "rigid": {"backbone": "rigid"},
    "rigid-pose-lr-0.03": {"backbone": "rigid", "field": {"pose_lr_scale": 0.03}},
    "rigid-pose-lr-0.3": {"backbone": "rigid", "field": {"pose_lr_scale": 0.3}},
    "rigid-fixed-track": {"backbone": "rigid", "field": {"pose_lr_scale": 0.0}},
    "rigid-no-shading": {"backbone": "rigid", "field": {"shading": False}},
    "rigid-space-res-128": {"backbone": "rigid", "field": {"resolutions": [16, 32, 64, 128]}},
    "rigid-samples-96": {"backbone": "rigid", "n_samples": 96},
    "rigid-lr-decay-0.1": {"backbone": "rigid", "lr_final": 0.1},
    "rigid-windows-32": {"backbone": "rigid", "windows": [32], "window_switch": []},
}
LEVERS.update({
    # the virtual rig's demo set (--rig): all its training views, or N of them spread evenly along
    # the ring (its ends kept), the validation views the same
    "rig-all-training-views": {"backbone": "hinge"},
    "rig-9-training-views": {"backbone": "hinge", "_training_views": 9},
    "rig-5-training-views": {"backbone": "hinge", "_training_views": 5},
    "rig-all-training-views-seed-1": {"backbone": "hinge", "seed": 1},
    "rig-9-training-views-seed-1": {"backbone": "hinge", "_training_views": 9, "seed": 1},
    "rig-5-training-views-seed-1": {"backbone": "hinge", "_training_views": 5, "seed": 1},
    # each window edge rendered as the twin's frame grid shows it (camera_grid) against at its exact
    # time (the default)
    "rig-camera-grid": {"backbone": "hinge", "camera_grid": True},
    "rig-camera-grid-seed-1": {"backbone": "hinge", "camera_grid": True, "seed": 1},
    # the demo's fork set with training sweeps (--demo --sweeps N): with and without them
    "hinge-with-sweeps": {"backbone": "hinge"},
    "hinge-static-views-only": {"backbone": "hinge", "_static_training_only": True},
    "hinge-with-sweeps-seed-1": {"backbone": "hinge", "seed": 1},
    "hinge-static-views-only-seed-1": {"backbone": "hinge", "_static_training_only": True, "seed": 1},
})
SWEEP_LEVERS = ["hinge-with-sweeps", "hinge-static-views-only", "hinge-with-sweeps-seed-1",
                "hinge-static-views-only-seed-1"]
RIG_LEVERS = ["rig-all-training-views", "rig-9-training-views", "rig-5-training-views",
              "rig-all-training-views-seed-1", "rig-9-training-views-seed-1", "rig-5-training-views-seed-1"]
#: --demo's levers by default (the demo's config already sets windows and 32 samples).
DEMO_LEVERS = ["baseline", "lr-0.01", "lr-0.005", "spans-0.8", "samples-48", "time-res-32", "event-rays-0.8"]

#: --default-path: what `evdnerf train` does with its defaults (auto against planes), 2 threads each.
DEFAULT_PATH = {"views": 18, "val_views": 4, "resolution": 64, "seconds": 180.0, "threads": 2,
                "eval_views": 4, "final_views": {1: 4, 4: 2, 8: 2}}
DEFAULT_PATH_LEVERS = ["auto", "baseline"]
PROXY = {"views": 12, "val_views": 4, "resolution": 64, "seconds": 90.0, "threads": 1,
         "eval_views": 4, "final_views": {1: 4, 4: 2, 8: 2}}
FULL = {"views": 18, "val_views": 18, "resolution": 128, "seconds": 300.0, "threads": 1,
        "eval_views": 4, "final_views": {1: 4, 4: 4, 8: 4}}
DEMO = {"scene": "fork-demo", "seconds": 120.0, "threads": 1, "eval_views": 2, "final_views": {1: 2, 4: 2},
        "moving": True}
RIG = {"seconds": 120.0, "threads": 1, "eval_views": 8, "final_views": {1: 8, 4: 8}}


def demo_setting(sweeps: int = 0, views: int | None = None) -> dict:
    from evdnerf_ros import demo

    o = demo.OPTIONS
    return {**DEMO, "views": int(views or o.views), "val_views": o.val_views, "resolution": list(o.resolution),
            "sweeps": int(sweeps), "base": dict(demo.TRAIN_CONFIG)}


def rig_setting(path: Path) -> dict:
    from evdnerf_ros import demo

    return {**RIG, "scene": "rig", "set": str(path.resolve()), "base": dict(demo.TRAIN_CONFIG)}


def with_training_views(work: Path, train_set: Path, keep: int | None = None, *,
                        static_only: bool = False) -> Path:
    """A copy of ``train_set`` (in WORK, made once) keeping ``keep`` of its training views, spread
    evenly over their order (the first and last kept), or (``static_only``) its static ones, and
    every validation view."""
    import shutil

    import h5py
    import numpy as np

    out = work / (f"{train_set.stem}-static-training-views.h5" if static_only else
                  f"{train_set.stem}-{int(keep)}-training-views.h5")
    if out.exists():
        return out
    part = out.with_suffix(".part")
    shutil.copyfile(train_set, part)
    with h5py.File(part, "r+") as f:
        names = json.loads(f.attrs["view_names"])
        train = [n for n in names if f["views"][n].attrs["split"] == "train"]
        if static_only:
            kept = {n for n in train if "poses" not in f["views"][n]}
        else:
            if not 2 <= keep <= len(train):
                raise SystemExit(f"{train_set}: cannot keep {keep} of its {len(train)} training views")
            kept = {train[i] for i in np.round(np.linspace(0, len(train) - 1, int(keep))).astype(int)}
        for n in train:
            if n not in kept:
                del f["views"][n]
        f.attrs["view_names"] = json.dumps([n for n in names if n in kept or n not in train])
    part.rename(out)
    return out


def build_set(work: Path, setting: dict) -> Path:
    from evdnerf_ros.session.convert import run_convert
    from evdnerf_ros.sim.simulate import SimulationOptions, simulate_session

    if setting.get("scene") == "rig":
        return Path(setting["set"])
    if setting.get("scene") == "fork-demo":
        import dataclasses

        from evdnerf_ros import demo

        sweeps, views = int(setting.get("sweeps", 0)), int(setting["views"])
        name = ("fork-demo" + (f"-{views}-views" if views != demo.OPTIONS.views else "")
                + (f"-{sweeps}-sweeps" if sweeps else ""))
        out = work / f"{name}.h5"
        if not out.exists():
            options = dataclasses.replace(demo.OPTIONS, views=views, moving_train_views=sweeps)
            simulate_session(demo.SCENE, work / f"session-{name}", options, log=lambda *_: None)
            run_convert(work / f"session-{name}", out, offsets="ground-truth", log=lambda *_: None)
        return out
    n, nv, res = setting["views"], setting["val_views"], setting["resolution"]
    out = work / f"jet-down-{res}-{n}+{nv}.h5"
    if out.exists():
        return out
    t = time.perf_counter()
    session = work / f"session-{res}-{n}+{nv}"
    simulate_session("jet-down", session, SimulationOptions(
        views=n, val_views=nv, resolution=(res, res), frame_rate_hz=30, blur_samples=4,
        gt_times=0, supersample=2, min_step_ns=2_000_000), log=lambda *_: None)
    run_convert(session, out, offsets="ground-truth", log=lambda *_: None)
    print(f"simulated + converted {n}+{nv} views at {res}x{res} in {time.perf_counter() - t:.0f} s",
          flush=True)
    return out


def merged(*cfgs: dict) -> dict:
    out: dict = {}
    for c in cfgs:
        for k, v in c.items():
            out[k] = {**out.get(k, {}), **v} if isinstance(v, dict) else v
    return out


def final_scores(field, ts, cfg, box, dynamic, final_views: dict, work: Path, set_stem: str,
                 moving: bool = False) -> dict:
    """{"x<factor>": events-PSNR, floor, true scene, margin closed} of a trained field on validation
    views spread over the set (``spread_views``) at 32 x factor windows ({factor: views}); the true
    scene's scores are cached in WORK (they never change for a set and its views)."""
    import torch

    from evdnerf_ros.eval.evaluate import evaluate_views, moving_views, spread_views, static_views
    from evdnerf_ros.eval.truth import TrueScene
    from evdnerf_ros.field.renderer import resolve_static_world

    truth = TrueScene.of(ts)[0]
    final = {}
    field = field.eval()
    splits = [(f"x{factor}", spread_views(static_views(ts, ts.val_views), int(nviews)), int(factor), "field")
              for factor, nviews in final_views.items()]
    if moving and moving_views(ts, ts.val_views):
        world = resolve_static_world("auto", moving=True, has_region=dynamic is not None)
        splits.append(("moving_x1", moving_views(ts, ts.val_views), 1, world))
        if world == "flat" and moving_views(ts, ts.train_views):
            # a run that saw its static world sweep past: that world beside auto's flat one
            splits.append(("moving_x1_field", moving_views(ts, ts.val_views), 1, "field"))
    with torch.no_grad():
        for key, views, factor, static_world in splits:
            which = hashlib.sha1(" ".join(views).encode()).hexdigest()[:8]     # the views themselves
            cache = work / f"truth-{set_stem}-{key}-{len(views)}-{which}.pkl"
            tm = pickle.loads(cache.read_bytes()) if cache.exists() else None
            _, _, m = evaluate_views(field, ts, views, 32 * factor, box=box,
                                     n_samples=cfg.n_samples, log_eps=cfg.log_eps, near=cfg.near,
                                     far=cfg.far, background=cfg.background, dynamic=dynamic,
                                     truth=truth, truth_metrics=tm, static_world=static_world,
                                     pixel_samples=cfg.pixel_samples)
            if tm is None and "truth" in m:
                cache.write_bytes(pickle.dumps(m["truth"]))
            final[key] = {
                "views": len(views), "windows": 32 * factor,
                "psnr": m["continuous"]["psnr"], "psnr_quantized": m["quantized"]["psnr"],
                "zero_floor": m["zero_floor"]["psnr"],
                "truth": m["truth"]["continuous"]["psnr"] if "truth" in m else None,
                "margin_closed": m.get("margin_closed", {}).get("continuous"),
                "margin_closed_quantized": m.get("margin_closed", {}).get("quantized"),
                "margin_closed_pooled": m.get("margin_closed", {}).get("pooled")}
    return final


def child(args) -> None:
    """One training run + its final evaluation, in this process; prints one JSON line."""
    import torch

    from evdnerf_ros.eval.evaluate import validation_eval
    from evdnerf_ros.io.trainingset import TrainingSet
    from evdnerf_ros.train.trainer import Trainer

    torch.set_num_threads(args.threads)
    setting = json.loads(args.setting)
    cfg = merged(BASE, setting.get("base", {}), json.loads(args.config))
    work = Path(args.work)
    keep = cfg.pop("_training_views", None)
    static_only = cfg.pop("_static_training_only", False)
    train_set = (with_training_views(work, Path(args.set), keep, static_only=static_only)
                 if keep or static_only else Path(args.set))
    with TrainingSet(train_set) as ts:
        tr = Trainer(ts, cfg, minutes=setting["seconds"] / 60.0,
                     eval_fn=validation_eval(n_windows=32, max_views=setting["eval_views"]),
                     log=lambda m: print(m, file=sys.stderr, flush=True))
        curve = []
        tr._write_metrics = curve.append          # metrics lines into memory (no run folder)
        summary = tr.train()
        final = final_scores(tr.field, ts, tr.cfg, tr.box, tr.dynamic,
                             {int(k): v for k, v in setting["final_views"].items()}, work,
                             train_set.stem, moving=bool(setting.get("moving")))
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(json.dumps({"lever": args.lever, "config": cfg, "iterations": summary["iterations"],
                      "train_s": summary["wall_s"],
                      "ms_per_iter": 1000 * summary["wall_s"] / max(1, summary["iterations"]),
                      "peak_rss_mb": peak_mb, "curve": curve, "final": final}, default=float))


def plot(result: dict, path: Path) -> None:
    plt = pyplot()
    fig, ax = plt.subplots(1, 2, figsize=(13, 4.8))
    colours = plt.get_cmap("tab20").colors         # more levers than the default cycle's 10
    for i, (name, r) in enumerate(result["runs"].items()):
        pts = [(m["wall_s"], 100 * m["val_margin_closed"]) for m in r["curve"]
               if m.get("val_margin_closed") is not None]
        colour = "k" if name == "baseline" else colours[(2 * i) % 20 + (2 * i) // 20 % 2]
        if pts:
            x, y = zip(*pts)
            ax[0].plot(x, y, marker=".", lw=2.2 if name == "baseline" else 1.2, color=colour,
                       label=f"{name} ({r['ms_per_iter']:.0f} ms/it)")
        pooled = [(m["wall_s"], 100 * m["val_margin_closed_pooled"]) for m in r["curve"]
                  if m.get("val_margin_closed_pooled") is not None]
        if pooled:                                  # one MSE over all windows (dashed)
            x, y = zip(*pooled)
            ax[0].plot(x, y, ls="--", lw=1.0, color=colour,
                       label=None if pts else f"{name} ({r['ms_per_iter']:.0f} ms/it), pooled")
    ax[0].axhline(0, color="grey", ls="--", lw=1)
    ax[0].set_xlabel(f"training wall time (s, {result['setting']['threads']} torch thread(s) per run)")
    ax[0].set_ylabel("margin closed (%, validation, 32 windows; dashed: pooled)")
    ax[0].set_title(result["title"], fontsize=10)
    ax[0].legend(fontsize=7, ncol=2)
    names = list(result["runs"])
    first = next(iter(result["runs"].values()))["final"]
    # (score key, margin kind): per-window mean for every key; pooled too where it was recorded
    bars = [(k, kind) for k in first for kind in ("margin_closed", "margin_closed_pooled")
            if kind == "margin_closed" or kind in first[k]]
    width = 0.8 / max(1, len(bars))
    for j, (k, kind) in enumerate(bars):
        vals = [100 * (result["runs"][n]["final"].get(k, {}).get(kind) or 0.0) for n in names]
        ax[1].bar([i + width * (j - (len(bars) - 1) / 2) for i in range(len(names))], vals, width=width,
                  label=f"{k}, {first[k]['windows']} windows" + (", pooled" if kind.endswith("pooled") else ""))
    ax[1].axhline(0, color="k", lw=1)
    low = min([0.0] + [b.get_height() for b in ax[1].patches])
    if low < -150:                                  # a margin of a few tenths of a dB explodes
        ax[1].set_ylim(bottom=-150)
        ax[1].text(0.01, 0.02, f"clipped at -150 % (lowest {low:.0f} %)", transform=ax[1].transAxes, fontsize=7)
    ax[1].set_xticks(range(len(names)), names, rotation=30, ha="right", fontsize=7)
    ax[1].set_ylabel("margin closed at the end (%)")
    ax[1].set_title("final, at the trained and finer windows", fontsize=10)
    ax[1].legend(fontsize=8)
    save_figure(fig, path, dpi=110)


def main(argv=None):
    ap = arg_parser(__doc__, quick="the proxy levers for 30 s each")
    ap.add_argument("--full", action="store_true", help="Jet-Down 128x128, 18+18 views, 5 minutes")
    ap.add_argument("--demo", action="store_true", help="the demo's fork set and training config, 2 minutes")
    ap.add_argument("--default-path", action="store_true",
                    help="Jet-Down 64x64, 18+4 views, 3 minutes, 2 threads: backbone auto against planes")
    ap.add_argument("--sweeps", type=int, default=0,
                    help="--demo: training views whose camera sweeps the ring (levers with and without them)")
    ap.add_argument("--views", type=int, default=None,
                    help="--demo: training views on the fork's ring (default the demo's 4), the same validation "
                         "views and moving camera")
    ap.add_argument("--rig", type=Path, default=None,
                    help="a virtual-rig demo's train.h5 (evdnerf demo -o OUT: OUT/train.h5), 2 minutes")
    ap.add_argument("--levers", default=None, help="comma-separated lever names (default: all)")
    ap.add_argument("--extra", default="{}", help="JSON {name: config} of further levers")
    ap.add_argument("--seconds", type=float, default=None, help="training seconds per run")
    ap.add_argument("--parallel", type=int, default=1, help="runs at a time")
    ap.add_argument("--work", default="/tmp/bench_quality")
    ap.add_argument("--stem", default=None)
    ap.add_argument("--replot", action="store_true", help="redraw the PNG from the JSON")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    for a in ("lever", "set", "config", "setting", "threads"):
        ap.add_argument(f"--{a}", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        args.threads = int(args.threads)
        return child(args)
    setting = (rig_setting(args.rig) if args.rig else demo_setting(args.sweeps, args.views) if args.demo
               else dict(FULL if args.full else DEFAULT_PATH if args.default_path else PROXY))
    if args.quick:
        setting["seconds"] = 30.0
    if args.seconds:
        setting["seconds"] = args.seconds
    stem = args.stem or ("quality_rig" if args.rig else "quality_demo_sweeps" if args.demo and args.sweeps
                         else "quality_demo" if args.demo
                         else "quality" if args.full else "quality_default_path" if args.default_path
                         else "quality_proxy")
    if args.replot:
        return plot(read_results(args.out, stem), args.out / f"{stem}.png")
    levers = {**LEVERS, **json.loads(args.extra)}
    names = (args.levers.split(",") if args.levers else RIG_LEVERS if args.rig else SWEEP_LEVERS
             if args.demo and args.sweeps else DEMO_LEVERS if args.demo
             else DEFAULT_PATH_LEVERS if args.default_path else list(LEVERS))
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    train_set = build_set(work, setting)
    result = {"machine": machine("torch"), "load_before": load_average(), "setting": setting,
              "parallel": args.parallel, "baseline": BASE,
              "title": (f"the virtual rig's demo set ({train_set.name}), 48x36, "
                        f"{setting['seconds']:.0f} s per run" if args.rig else
                        f"the demo's fork set, 96x72, {setting['views']}+{setting['val_views']} views + moving"
                        + (f", {setting['sweeps']} training sweeps" if setting.get("sweeps") else "") + ", "
                        f"{setting['seconds']:.0f} s per run" if args.demo else
                        f"Jet-Down {setting['resolution']}x{setting['resolution']}, "
                        f"{setting['views']}+{setting['val_views']} views, "
                        f"{setting['seconds']:.0f} s per run"),
              "runs": {}}
    partial = work / f"{stem}-partial.json"
    if partial.exists():
        result["runs"] = json.loads(partial.read_text())
    todo = [n for n in names if n not in result["runs"]]
    running: list = []

    def start(name):
        log = open(work / f"{stem}-{name}.log", "w")
        cmd = [sys.executable, __file__, "--child", "--lever", name, "--set", str(train_set),
               "--work", str(work), "--config", json.dumps(levers[name]),
               "--setting", json.dumps(setting), "--threads", str(setting["threads"])]
        return name, log, subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=log, text=True)

    while todo or running:
        while todo and len(running) < args.parallel:
            running.append(start(todo.pop(0)))
        name, log, proc = running.pop(0)
        out, _ = proc.communicate()
        log.close()
        if proc.returncode:
            raise SystemExit(f"lever {name} failed:\n{(work / f'{stem}-{name}.log').read_text()[-3000:]}")
        r = json.loads(out.strip().splitlines()[-1])
        result["runs"][name] = r
        partial.write_text(json.dumps(result["runs"]))
        fin = "  ".join(f"{k}: {100 * v['margin_closed']:.1f} %" for k, v in r["final"].items()
                        if v["margin_closed"] is not None)
        print(f"{name}: {r['iterations']} it, {r['ms_per_iter']:.0f} ms/it; margin closed {fin}",
              flush=True)
    result["load_after"] = load_average()
    result["summary"] = {n: {"ms_per_iter": r["ms_per_iter"], "iterations": r["iterations"],
                             **{f"margin_closed_{k}": v["margin_closed"] for k, v in r["final"].items()},
                             **{f"margin_closed_pooled_{k}": v.get("margin_closed_pooled")
                                for k, v in r["final"].items()},
                             **{f"psnr_{k}": v["psnr"] for k, v in r["final"].items()},
                             **{f"floor_{k}": v["zero_floor"] for k, v in r["final"].items()},
                             **{f"truth_{k}": v["truth"] for k, v in r["final"].items()}}
                         for n, r in result["runs"].items()}
    write_results(args.out, stem, result, plot)
    print(json.dumps(result["summary"], indent=1))


if __name__ == "__main__":
    main()
