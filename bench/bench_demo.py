"""Benchmark of `evdnerf demo`: its wall time by stage, and what its learned simulator scores.

Runs the demo (``run_demo``, default options: the virtual rig where it can run, else the
simulator; 1200 training iterations) into a temporary folder and records from its summary.json:
the wall seconds of each stage (session, round trips, sync, pictures, convert, train, eval,
publish), the iterations and which budget stopped them, the backbone ``auto`` chose, the
validation margin closed at the trained windows (per window, quantised and pooled) with the
field's, the all-zero floor's and the true scene's pooled PSNR, and the published trajectory's
score against the true events (margin closed, events published against true). ``--quick``: 100 iterations.

Usage: python bench/bench_demo.py [--quick] [--source auto|virtual-rig|simulate] [--replot]
       -> bench/results/demo.{json,png}
"""

from __future__ import annotations

import tempfile
from pathlib import Path

from _common import arg_parser, load_average, machine, pyplot, read_results, save_figure, write_results


def run(quick: bool, source: str) -> dict:
    from evdnerf_ros.demo import DemoOptions, run_demo

    options = DemoOptions(source=source, **({"train_iterations": 100} if quick else {}))
    with tempfile.TemporaryDirectory() as tmp:
        summary = run_demo(Path(tmp) / "demo", options, log=lambda *_: None)
    training, published = summary["training"], summary["published"]
    val = training["val"]
    return {"source": summary["source"], "views": summary["views"], "wall_s": summary["wall_seconds"],
            "stage_s": summary["stage_seconds"], "backbone": summary["backbone"],
            "iterations": training["iterations"], "stopped_by": training["stopped_by"],
            "train_s": training["train_seconds"], "val_margin_closed": val["margin_closed"],
            "val_psnr_pooled": val["psnr_pooled"], "published": published}


def summarise(result: dict) -> dict:
    """The headline figures (bench/README.md)."""
    pub = result["published"]
    return {"wall_s": result["wall_s"], "train_s": result["train_s"], "iterations": result["iterations"],
            "publish_s": result["stage_s"]["publish"],
            "val_margin_closed_pooled": (result["val_margin_closed"] or {}).get("pooled"),
            "published_margin_closed": pub.get("margin_closed"), "published_events": pub["events"],
            "true_events": pub.get("true_events")}


def plot(result: dict, path: Path) -> None:
    plt = pyplot()
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(12, 4))
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
