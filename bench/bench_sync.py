"""Benchmark of `evdnerf sync`: sync error against bin size and run time.

1. Event rate (the curve): a simulated Jet-Down session with a quiet lead-in (a sudden
   onset, as the paper's "sudden peak"), copied with sensor imperfections — background
   noise (2 Hz per pixel), 3 hot pixels at 1 kHz, 2 bursts of pre-motion jitter, recordings
   that start at random sub-ms moments — for several noise seeds. For rate bins from 10 ms
   down to 50 µs: onset only (`--method onset`) and refined (`--method rate`), the error of
   every view's offset relative to the reference view against the injected clock offsets
   (median, 90th percentile, max, in µs), and the run time of the whole `sync` (reading the
   bags included).
2. Better sources, on the servo scene (fork): the EXT_TRIGGER edge and the START message
   (exact), and how far rate-based sync is off on a motion that starts smoothly (the
   firmware's minimum-jerk profile) — the reason the rig records triggers.

Usage: python bench/bench_sync.py [--quick]   -> bench/results/sync.{json,png}
"""

from __future__ import annotations

import shutil
import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np
import yaml

from _common import arg_parser, machine, pyplot, save_figure, timed, write_results

from evdnerf_ros.session.sync import SyncOptions, sync_session  # noqa: E402
from evdnerf_ros.sim.perturb import perturb_session  # noqa: E402
from evdnerf_ros.sim.scene import preset_path  # noqa: E402
from evdnerf_ros.sim.simulate import SimulationOptions, simulate_session  # noqa: E402

BINS_NS = [10_000_000, 5_000_000, 2_000_000, 1_000_000, 500_000, 200_000, 100_000, 50_000]
QUICK_BINS_NS = [10_000_000, 1_000_000, 100_000]
LEAD_S = 0.15


def jet_with_lead_in(path: Path) -> Path:
    """Jet-Down with LEAD_S of stillness first: a recording must begin before the motion."""
    scene = yaml.safe_load(Path(preset_path("jet-down")).read_text())
    scene["time"] = {"start_s": 0.0, "end_s": scene["time"]["end_s"] + LEAD_S + 0.1}
    for obj in scene["objects"]:
        for kf in (obj.get("motion") or {}).get("keyframes", []):
            kf["t_s"] = round(kf["t_s"] + LEAD_S, 6)
    path.write_text(yaml.safe_dump(scene))
    return path


def relative_errors_us(result, session_dir: Path) -> np.ndarray:
    data = yaml.safe_load((session_dir / "session.yaml").read_text())
    gt = {v["name"]: v["ground_truth"]["clock_offset_ns"] for v in data["views"]}
    ref = result.summary["reference_view"]
    off = {n: r["offset_ns"] for n, r in result.views.items()}
    return np.array([((off[n] - off[ref]) - (gt[n] - gt[ref])) / 1e3 for n in gt if n != ref])


def run(session_dir: Path, options: SyncOptions, work: Path):
    """One sync on a scratch copy (session.yaml is rewritten); (result, seconds)."""
    copy = work / "run"
    if copy.exists():
        shutil.rmtree(copy)
    shutil.copytree(session_dir, copy)
    opts = replace(options, plot_path=work / "sync.png", overwrite=True)   # one plot path for every run
    sec, res = timed(lambda: sync_session(copy, opts))
    return res, sec, copy


def summarise(errs: list[np.ndarray], secs: list[float], bin_ns: int) -> dict:
    e = np.abs(np.concatenate(errs))
    return {"bin_ns": bin_ns, "views": int(e.size),
            "median_abs_us": round(float(np.median(e)), 1),
            "p90_abs_us": round(float(np.percentile(e, 90)), 1),
            "max_abs_us": round(float(e.max()), 1),
            "within_one_bin": round(float(np.mean(e <= bin_ns / 1e3)), 3),
            "within_100us": round(float(np.mean(e <= 100)), 3),
            "seconds": round(float(np.median(secs)), 3)}


def rate_curve(work: Path, quick: bool) -> dict:
    views, val, res = (3, 1, (48, 36)) if quick else (8, 2, (96, 72))
    seeds = [1] if quick else [1, 2, 3]
    sim = SimulationOptions(views=views, val_views=val, resolution=res, frame_rate_hz=0, gt_times=0,
                            supersample=1, jobs=2, min_step_ns=2_000_000)
    scene = jet_with_lead_in(work / "jet-down-lead.yaml")
    sim_sec, _ = timed(lambda: simulate_session(str(scene), work / "jet", sim, log=lambda *_: None))
    noisy = []
    for seed in seeds:
        noisy.append(perturb_session(work / "jet", work / f"jet_noisy_{seed}", noise_hz=2.0, hot=3,
                                     hot_rate_hz=1000.0, bursts=2, lead_ns=20_000_000, seed=seed))
    curves = {"onset": [], "refined": []}
    hot_found = []
    for bin_ns in (QUICK_BINS_NS if quick else BINS_NS):
        for name, opts in (("onset", SyncOptions(bin_ns=bin_ns, method="onset", refine=False)),
                           ("refined", SyncOptions(bin_ns=bin_ns, method="rate"))):
            errs, secs = [], []
            for s in noisy:
                result, sec, copy = run(s, opts, work)
                errs.append(relative_errors_us(result, copy))
                secs.append(sec)
                hot_found += [r["excluded_hot_pixels"] for r in result.views.values()]
            curves[name].append(summarise(errs, secs, bin_ns))
            print(f"  {name:8s} bin {bin_ns / 1e3:7.0f} us: median {curves[name][-1]['median_abs_us']:8.1f} us, "
                  f"max {curves[name][-1]['max_abs_us']:9.1f} us, {curves[name][-1]['seconds']:.2f} s")
    return {"scene": "jet-down with a 0.15 s lead-in", "views": views + val, "resolution": list(res),
            "simulate_seconds": round(sim_sec, 1), "noise_seeds": seeds,
            "perturbation": {"noise_hz_per_pixel": 2.0, "hot_pixels": 3, "hot_rate_hz": 1000.0,
                             "bursts": 2, "burst_events": 200, "burst_ns": 3_000_000,
                             "recording_start_jitter_ns": 20_000_000},
            "hot_pixels_excluded": {"min": int(min(hot_found)), "max": int(max(hot_found))},
            "metric": "|(offset_v - offset_ref) - (clock_offset_v - clock_offset_ref)| over non-reference views",
            "curves": curves}


def sources(work: Path, quick: bool) -> dict:
    views, res = (3, (48, 36)) if quick else (6, (96, 72))
    sim = SimulationOptions(views=views, val_views=1, resolution=res, frame_rate_hz=0, gt_times=0,
                            supersample=1, jobs=2, min_step_ns=2_000_000)
    simulate_session("fork", work / "fork", sim, log=lambda *_: None)
    out = {"scene": "fork (servo, minimum-jerk start)", "views": views + 1, "resolution": list(res)}
    for name, opts in (("trigger", SyncOptions(method="trigger")), ("start", SyncOptions(method="start")),
                       ("rate", SyncOptions(method="rate")), ("onset", SyncOptions(method="onset"))):
        result, sec, copy = run(work / "fork", opts, work)
        e = np.abs(relative_errors_us(result, copy))
        out[name] = {"median_abs_us": round(float(np.median(e)), 3), "max_abs_us": round(float(e.max()), 3),
                     "seconds": round(sec, 3)}
        if name == "trigger":
            out["max_disagreement_us"] = result.summary["max_disagreement_us"]
        print(f"  fork {name:8s}: max {out[name]['max_abs_us']:10.3f} us, {sec:.2f} s")
    return out


def plot(results: dict, path: Path) -> None:
    curves = results["rate"]["curves"]
    fig, (ax1, ax2) = pyplot().subplots(1, 2, figsize=(11, 4.2))
    for name, marker in (("onset", "o"), ("refined", "s")):
        pts = curves[name]
        b = np.array([p["bin_ns"] for p in pts]) / 1e3
        med = np.array([p["median_abs_us"] for p in pts])
        p90 = np.array([p["p90_abs_us"] for p in pts])
        mx = np.array([p["max_abs_us"] for p in pts])
        sec = np.array([p["seconds"] for p in pts])
        label = "onset only" if name == "onset" else "refined (cross-correlation)"
        line, = ax1.plot(b, med, marker=marker, label=f"{label}: median")
        ax1.fill_between(b, med, p90, color=line.get_color(), alpha=0.2)
        ax1.plot(b, mx, linestyle=":", color=line.get_color(), label=f"{label}: max")
        ax2.plot(sec, med, marker=marker, color=line.get_color(), label=label)
        for x, y, bb in zip(sec, med, b):
            ax2.annotate(f"{bb:g}", (x, y), fontsize=6, textcoords="offset points", xytext=(3, 3))
    ax1.plot(b, b, color="grey", linewidth=0.8, linestyle="--", label="one bin")
    ax1.axhline(100, color="k", linewidth=0.6, linestyle="-.", label="100 µs")
    for ax in (ax1, ax2):
        ax.set_yscale("log")
        ax.set_ylabel("sync error vs injected offsets [µs]")
    ax1.set_xscale("log")
    ax1.set_xlabel("rate bin [µs]")
    ax1.set_title("error against bin size (band: median..p90)", fontsize=9)
    ax2.set_xlabel("sync run time [s] (labels: bin in µs)")
    ax2.set_title("error against run time (median)", fontsize=9)
    ax1.legend(fontsize=6)
    ax2.legend(fontsize=7)
    r = results["rate"]
    fig.suptitle(f"evdnerf sync: {r['scene']}, {r['views']} views at {r['resolution'][0]}x{r['resolution'][1]}, "
                 "noise + hot pixels + jitter", fontsize=9)
    save_figure(fig, path, dpi=110)


def main(argv=None) -> None:
    ap = arg_parser(__doc__, quick="small session, three bins (a smoke run)")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        print("event rate: error against bin size")
        rate = rate_curve(work, args.quick)
        print("better sources")
        src = sources(work, args.quick)
    results = {"machine": machine(),
               "quick": bool(args.quick), "rate": rate, "sources": src}
    name = "sync_quick" if args.quick else "sync"
    write_results(args.out, name, results, plot)


if __name__ == "__main__":
    main()
