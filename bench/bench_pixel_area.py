"""How much of the floor-to-truth margin a renderer can close when each pixel is one ray.

A simulated training set's events come from images rendered with ``supersample`` x
``supersample`` sub-pixels per pixel (the light a pixel's area gathers).  This script scores the
true scene itself, rendered with 1, 2 and 4 sub-pixel rays per side, by the evaluation protocol
(``evaluate``'s event metrics: the same views and windows the quality benchmark scores) against
the set's events: the share of the margin closed at each ray count, and the wall time of those
renders.  A field rendered one ray per pixel centre (``pixel_samples: 1``) faces the first
column's ceiling unless it learns a blurred scene; ``pixel_samples`` > 1 renders as the events'
camera saw.

Usage: python bench/bench_pixel_area.py [--sets A.h5,B.h5] [--work DIR]
       -> bench/results/pixel_area.{json,png}
Default sets: the quality benchmark's (``bench_quality.py --demo`` / ``--full``), made in WORK
once.
"""

from __future__ import annotations

import time
from pathlib import Path

from _common import arg_parser, machine, pyplot, save_figure, write_results

RAYS_PER_SIDE = (1, 2, 4)
FACTORS = (1, 4)


def score_set(path: Path, views_per_factor: dict) -> dict:
    import numpy as np

    from evdnerf_ros.eval.evaluate import static_views
    from evdnerf_ros.eval.metrics import event_metrics
    from evdnerf_ros.eval.truth import TrueScene, margin_closed
    from evdnerf_ros.eval.windows import scored_windows
    from evdnerf_ros.io.trainingset import TrainingSet

    with TrainingSet(path) as ts:
        truth, why = TrueScene.of(ts)
        if truth is None:
            raise SystemExit(f"{path}: {why}")
        events_ss = truth.supersample
        out = {"set": path.name, "size": [ts.width, ts.height], "events_supersample": events_ss, "factors": {}}
        t0, t1 = ts.time_range
        for factor in FACTORS:
            views = static_views(ts, ts.val_views)[:views_per_factor[factor]]
            edges, ks = scored_windows(t0, t1, 32 * factor, None)
            gt = np.concatenate([ts.log_change_stack(v, edges)[ks] for v in views])
            scores = {}
            for s in RAYS_PER_SIDE:
                truth.supersample = s
                start = time.perf_counter()
                pred = np.concatenate([truth.log_change_stack(v, edges, ks) for v in views])
                seconds = time.perf_counter() - start
                m = event_metrics(pred, gt, c_pos=ts.thresholds[0], c_neg=ts.thresholds[1])
                scores[s] = {"psnr": m["continuous"]["psnr"], "psnr_pooled": m["continuous"]["psnr_pooled"],
                             "render_s": seconds}
                floor, floor_pooled = m["zero_floor"]["psnr"], m["zero_floor"]["psnr_pooled"]
            ref = scores[events_ss]
            for s, sc in scores.items():
                sc["margin_closed"] = margin_closed(sc["psnr"], floor, ref["psnr"])
                sc["margin_closed_pooled"] = margin_closed(sc["psnr_pooled"], floor_pooled, ref["psnr_pooled"])
            out["factors"][factor] = {"views": len(views), "windows": len(ks), "zero_floor": floor, "rays": scores}
            print(f"{path.name} x{factor} ({len(views)} views, {len(ks)} windows): " + ", ".join(
                f"{s}x{s} rays {100 * sc['margin_closed']:.1f} % ({sc['render_s']:.1f} s)" for s, sc in scores.items()),
                flush=True)
    return out


def plot(result: dict, path: Path) -> None:
    plt = pyplot()
    sets = result["sets"]
    fig, axes = plt.subplots(1, len(sets), figsize=(5.5 * len(sets), 4.2), squeeze=False)
    for ax, r in zip(axes[0], sets):
        for factor, f in r["factors"].items():
            xs = [f["rays"][str(s) if str(s) in f["rays"] else s]["render_s"] for s in RAYS_PER_SIDE]
            ys = [100 * f["rays"][str(s) if str(s) in f["rays"] else s]["margin_closed"] for s in RAYS_PER_SIDE]
            ax.plot(xs, ys, marker="o", label=f"x{factor} windows")
            for s, x, y in zip(RAYS_PER_SIDE, xs, ys):
                ax.annotate(f"{s}x{s}", (x, y), textcoords="offset points", xytext=(4, 4), fontsize=8)
        ax.axhline(0, color="grey", ls="--", lw=1)
        ax.axhline(100, color="grey", ls=":", lw=1)
        ax.set_xscale("log")
        ax.set_xlabel("true-scene render time (s, all scored windows)")
        ax.set_ylabel("margin closed (%; 100: the events' own sub-pixels)")
        ax.set_title(f"{r['set']} ({r['size'][0]}x{r['size'][1]}; events at "
                     f"{r['events_supersample']}x{r['events_supersample']})", fontsize=9)
        ax.legend(fontsize=8)
    save_figure(fig, path)


def main() -> None:
    ap = arg_parser(__doc__, quick=None)
    ap.add_argument("--sets", default=None, help="comma-separated training sets (simulated or virtual-rig)")
    ap.add_argument("--work", default="/tmp/bench_quality")
    args = ap.parse_args()
    from bench_quality import DEMO, FULL, build_set, demo_setting

    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    if args.sets:
        jobs = [(Path(p), {1: 4, 4: 4}) for p in args.sets.split(",")]
    else:
        jobs = [(build_set(work, demo_setting()), DEMO["final_views"]),
                (build_set(work, FULL), FULL["final_views"])]
    result = {"machine": machine("torch"), "sets": [score_set(p, views) for p, views in jobs]}
    write_results(Path(args.out), "pixel_area", result, plot)


if __name__ == "__main__":
    main()
