"""Benchmarks of `evdnerf simulate` on the presets.

1. Full session: `simulate jet-down` with 18 + 18 views at 128x128 — wall time and peak
   memory (goal: under 2 minutes on 2 cores).
2. Leave out what the scene does not need: the fork preset is static for 0.2 s of its
   1.2 s; rendering that span through the sampler versus one render for it (renders, time).
3. Error against run time on a rendered scene (jet-down, 64x64, 0.2 s of motion): event
   images over 1 ms windows against a 20 kHz fixed-rate reference, for fixed-rate sampling
   at several rates and adaptive sampling at several finest steps — error against renders
   and against seconds.

Usage: python bench/bench_simulate.py [--quick]   -> bench/results/simulate.{json,png}
"""

from __future__ import annotations

import json
import resource
import tempfile
from pathlib import Path

import numpy as np

from _common import arg_parser, machine, pyplot, read_results, save_figure, timed, write_results

from evdnerf_ros.events import log_change_stack, window_edges  # noqa: E402
from evdnerf_ros.sim.generator import EventGenerator  # noqa: E402
from evdnerf_ros.sim.render import SceneRenderer  # noqa: E402
from evdnerf_ros.sim.sampling import simulate_renderer  # noqa: E402
from evdnerf_ros.sim.scene import load_scene  # noqa: E402
from evdnerf_ros.sim.simulate import SimulationOptions, simulate_session  # noqa: E402



def full_session(views: int, resolution: int) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        wall, session = timed(lambda: simulate_session("jet-down", Path(tmp) / "s", SimulationOptions(
            views=views, val_views=views, resolution=(resolution, resolution)), log=lambda *_: None))
    peak_children = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024
    peak_self = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return {"scene": "jet-down", "views": 2 * views, "resolution": resolution,
            "wall_seconds": round(wall, 2),
            "events": int(sum(v["events"] for v in session["views"])),
            "renders": int(sum(v["simulation"]["renders"] for v in session["views"])),
            "peak_rss_mb_main": round(peak_self, 1),
            "peak_rss_mb_largest_worker": round(peak_children, 1),
            "goal_seconds": 120}


def static_span_saving(resolution: int) -> dict:
    scene = load_scene("fork")
    cam = scene.camera.resized(resolution, resolution)
    T = scene.camera_poses("train")[0]
    out = {}
    for name, skip in (("one render per static span", True), ("sampler over static spans", False)):
        renderer = SceneRenderer(scene, cam, 2)
        gen = EventGenerator(cam.width, cam.height)

        def simulate(skip=skip, renderer=renderer, gen=gen):
            """(events, renders)"""
            if skip:
                m0, m1 = scene.motion_span_ns()
                gen.reset(renderer(T, scene.start_ns), scene.start_ns)
                gen.step_log(gen.last_log(), m0)
                ev, st = simulate_renderer(lambda t: renderer(T, t), m0, m1, gen,
                                           min_step_ns=1_000_000, max_step_ns=10_000_000)
                gen.step_log(gen.last_log(), scene.end_ns)
                return ev, st.renders + 1
            ev, st = simulate_renderer(lambda t: renderer(T, t), scene.start_ns, scene.end_ns,
                                       gen, min_step_ns=1_000_000, max_step_ns=10_000_000)
            return ev, st.renders

        sec, (ev, renders) = timed(simulate)
        out[name] = {"renders": renders, "seconds": round(sec, 3), "events": int(ev.size)}
    a, b = out["one render per static span"], out["sampler over static spans"]
    out["renders_saved"] = b["renders"] - a["renders"]
    out["time_ratio"] = round(b["seconds"] / a["seconds"], 3)
    return out


def error_vs_runtime(resolution: int, quick: bool) -> dict:
    scene = load_scene("jet-down")
    cam = scene.camera.resized(resolution, resolution)
    T = scene.camera_poses("train")[0]
    t_start, t_end = 400_000_000, 600_000_000
    # 1 ms windows, offset by 0.37 ms so that no sampling grid below lines up with them (an
    # aligned grid would put every interpolated event in the right window by construction).
    edges = window_edges(t_start + 370_000, t_end - 630_000, 199)

    def run(**kw):
        renderer = SceneRenderer(scene, cam, 2)
        gen = EventGenerator(cam.width, cam.height)
        sec, (ev, st) = timed(lambda: simulate_renderer(lambda t: renderer(T, t), t_start, t_end, gen, **kw))
        return ev, st.renders, sec

    ref_rate = 5_000 if quick else 20_000
    ref, ref_renders, _ = run(mode="fixed", rate_hz=ref_rate)
    ref_img = log_change_stack(ref, edges, cam.width, cam.height, 0.2, 0.2)
    scale = float(np.abs(ref_img).sum())

    def error(ev):
        img = log_change_stack(ev, edges, cam.width, cam.height, 0.2, 0.2)
        return float(np.abs(img - ref_img).sum() / scale)

    rates = [250, 500, 1000, 2000] + ([] if quick else [5000])
    steps = [4_000_000, 2_000_000, 1_000_000, 500_000] + ([] if quick else [200_000])
    curves = {"fixed rate": [], "adaptive (tolerance 0.1 C)": []}
    for hz in rates:
        ev, renders, sec = run(mode="fixed", rate_hz=hz)
        curves["fixed rate"].append({"rate_hz": hz, "renders": renders, "seconds": round(sec, 3),
                                     "relative_error": round(error(ev), 5), "events": int(ev.size)})
    for step in steps:
        ev, renders, sec = run(mode="adaptive", tolerance_c=0.1, min_step_ns=step,
                               max_step_ns=max(step, 10_000_000))
        curves["adaptive (tolerance 0.1 C)"].append({
            "min_step_ns": step, "renders": renders, "seconds": round(sec, 3),
            "relative_error": round(error(ev), 5), "events": int(ev.size)})
    return {"scene": "jet-down", "resolution": resolution, "span_ns": [t_start, t_end],
            "window_ns": 1_000_000, "reference": {"mode": "fixed", "rate_hz": ref_rate,
                                                  "renders": ref_renders, "events": int(ref.size)},
            "metric": "sum |dL - dL_ref| over 1 ms event images / sum |dL_ref|",
            "curves": curves}


def plot(result: dict, path: Path) -> None:
    fig, axes = pyplot().subplots(1, 2, figsize=(10, 3.8))
    for name, pts in result["error_vs_runtime"]["curves"].items():
        for ax, key in zip(axes, ("renders", "seconds")):
            ax.loglog([p[key] for p in pts], [max(p["relative_error"], 1e-6) for p in pts],
                      "o-", label=name)
    axes[0].set_xlabel("renders")
    axes[1].set_xlabel("wall seconds")
    from matplotlib.ticker import NullFormatter

    for ax in axes:
        ax.xaxis.set_minor_formatter(NullFormatter())
        ax.set_ylabel("relative event-image error (1 ms windows)")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    full = result["full_session"]
    fig.suptitle(f"simulate: error against run time (jet-down 64x64, 0.2 s) — full session "
                 f"{full['views']} views @ {full['resolution']}^2 in {full['wall_seconds']} s",
                 fontsize=9)
    save_figure(fig, path, dpi=110)


def main(argv=None) -> None:
    ap = arg_parser(__doc__, quick="small sizes for a smoke run")
    ap.add_argument("--parts", default="error,static,full",
                    help="comma-separated parts to run; others are kept from the last results in --out")
    args = ap.parse_args(argv)
    parts = set(args.parts.split(","))
    result = read_results(args.out, "simulate", missing_ok=True) if parts != {"error", "static", "full"} else {}
    result["machine"] = machine()
    if "error" in parts:
        result["error_vs_runtime"] = error_vs_runtime(32 if args.quick else 64, args.quick)
    if "static" in parts:
        result["static_span_saving"] = static_span_saving(32 if args.quick else 128)
    if "full" in parts:
        result["full_session"] = full_session(2 if args.quick else 18, 32 if args.quick else 128)
    write_results(args.out, "simulate", result, plot)
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
