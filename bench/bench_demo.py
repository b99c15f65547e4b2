"""Benchmark of `evdnerf demo`: its wall time by stage, and what its learned simulator scores.

Runs the demo (``run_demo``, default options: the virtual rig where it can run, else the
simulator; 1200 training iterations) into a temporary folder and records from its summary.json:
the wall seconds of each stage (session, round trips, sync, pictures, convert, train, eval,
publish), the iterations and which budget stopped them, the backbone ``auto`` chose, the
validation margin closed at the trained windows (per window, quantised and pooled) with the
field's, the all-zero floor's and the true scene's pooled PSNR, and the published trajectory's
score against the true events (margin closed, events published against true). ``--quick``: 100 iterations.

Then, on the demo's own run and set, the true scene's events along the published orbit simulated at
each finest step ``TRUTH_STEPS_MS`` (the error-against-run-time curve behind the demo's
``TRUTH_MIN_STEP_NS``): the truth publisher's wall seconds and renders, the true events, the true
event images' PSNR against the finest step's, and the published run's margin closed against each.

Usage: python bench/bench_demo.py [--quick] [--source auto|virtual-rig|simulate] [--replot]
       -> bench/results/demo.{json,png}
"""

from __future__ import annotations

import tempfile
from pathlib import Path

from _common import arg_parser, load_average, machine, pyplot, read_results, save_figure, write_results


#: Finest steps (ms) of the true scene's simulation along the orbit, finest first (the reference).
TRUTH_STEPS_MS = (0.1, 0.25, 0.5, 1.0, 2.0)


def truth_sampling(out: Path) -> list[dict]:
    """The truth along the demo's published orbit at each of ``TRUTH_STEPS_MS`` (module doc)."""
    import numpy as np

    from evdnerf_ros.demo import PUBLISH_BAKE, PUBLISH_WINDOWS
    from evdnerf_ros.eval.metrics import psnr
    from evdnerf_ros.eval.published import published_vs_true

    rows, finest = [], None
    for ms in TRUTH_STEPS_MS:
        r = published_vs_true(out / "run", out / "train.h5", n_windows=PUBLISH_WINDOWS,
                              publisher={"bake_resolution": PUBLISH_BAKE},
                              truth_publisher={"min_step_ns": int(round(ms * 1e6))}, log=lambda *_: None)
        img = r["images"]["true"]
        finest = img if finest is None else finest
        rows.append({"min_step_ms": ms, "wall_s": r["true_publisher"]["wall_s"], "renders": r["true_publisher"]["renders"],
                     "true_events": r["counts"]["true_on"] + r["counts"]["true_off"],
                     "psnr_vs_finest_db": psnr(img, finest, 2 * float(np.abs(finest).max()) or 1.0),
                     "published_margin_closed": r["margin_closed"]})
    return rows


def run(quick: bool, source: str) -> dict:
    from evdnerf_ros.demo import DemoOptions, run_demo

    options = DemoOptions(source=source, **({"train_iterations": 100} if quick else {}))
    with tempfile.TemporaryDirectory() as tmp:
        summary = run_demo(Path(tmp) / "demo", options, log=lambda *_: None)
        sampling = truth_sampling(Path(tmp) / "demo") if summary["published"].get("scored") else []
    training, published = summary["training"], summary["published"]
    val = training["val"]
    return {"source": summary["source"], "views": summary["views"], "wall_s": summary["wall_seconds"],
            "stage_s": summary["stage_seconds"], "backbone": summary["backbone"],
            "iterations": training["iterations"], "stopped_by": training["stopped_by"],
            "train_s": training["train_seconds"], "val_margin_closed": val["margin_closed"],
            "val_psnr_pooled": val["psnr_pooled"], "published": published, "truth_sampling": sampling}


def summarise(result: dict) -> dict:
    """The headline figures (bench/README.md)."""
    pub = result["published"]
    return {"wall_s": result["wall_s"], "train_s": result["train_s"], "iterations": result["iterations"],
            "publish_s": result["stage_s"]["publish"],
            "val_margin_closed_pooled": (result["val_margin_closed"] or {}).get("pooled"),
            "published_margin_closed": pub.get("margin_closed"), "published_events": pub["events"],
            "true_events": pub.get("true_events"),
            "truth_sampling_wall_s": {f"{r['min_step_ms']:g} ms": round(r["wall_s"], 1)
                                      for r in result.get("truth_sampling") or []}}


def plot(result: dict, path: Path) -> None:
    plt = pyplot()
    fig, (ax, bx, cx) = plt.subplots(1, 3, figsize=(18, 4))
    stages = result["stage_s"]
    ax.barh(list(stages), list(stages.values()), color="tab:blue")
    ax.invert_yaxis()
    ax.set_xlabel("wall seconds")
    ax.set_title(f"evdnerf demo ({result['source']}, {result['views']} views): {result['wall_s']:.0f} s, "
                 f"{result['iterations']} iterations")
    pub = result["published"]
    bars = {"validation, pooled": (result["val_margin_closed"] or {}).get("pooled"),
            "published path": pub.get("margin_closed")}
    names = [k for k, v in bars.items() if v is not None]
    bx.bar(names, [100 * bars[k] for k in names], color=["tab:green", "tab:orange"][:len(names)])
    bx.axhline(0, color="grey", lw=0.8)
    bx.set_ylabel("margin closed (%)")
    title = f"backbone {result['backbone']['chosen']}"
    if pub.get("scored"):
        title += f"; published {pub['events']} events, {pub['true_events']} true"
    bx.set_title(title)
    rows = result.get("truth_sampling") or []
    if rows:
        cx.plot([r["wall_s"] for r in rows[1:]], [r["psnr_vs_finest_db"] for r in rows[1:]], "o-")
        for r in rows[1:]:
            cx.annotate(f"{r['min_step_ms']:g} ms", (r["wall_s"], r["psnr_vs_finest_db"]), fontsize=8)
        cx.set_xlabel("truth simulation wall seconds")
        cx.set_ylabel(f"true event images, PSNR against {rows[0]['min_step_ms']:g} ms steps (dB)")
        cx.set_title(f"true events along the orbit ({rows[0]['min_step_ms']:g} ms: {rows[0]['wall_s']:.0f} s)")
    save_figure(fig, path)


def main(argv=None):
    ap = arg_parser(__doc__, quick="100 training iterations")
    ap.add_argument("--source", default="auto", choices=["auto", "virtual-rig", "simulate"])
    ap.add_argument("--replot", action="store_true", help="redraw the PNG and the summary from the JSON")
    args = ap.parse_args(argv)
    stem = "demo_quick" if args.quick else "demo"
    if args.replot:
        result = read_results(args.out, stem)
    else:
        result = {"machine": machine("torch"), "load_before": load_average(), **run(args.quick, args.source),
                  "load_after": load_average()}
    result["summary"] = summarise(result)
    write_results(args.out, stem, result, plot)


if __name__ == "__main__":
    main()
