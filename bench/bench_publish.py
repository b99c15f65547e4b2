"""Event publisher: real-time factor against resolution and render tolerance (with event error
against the exact generator at fine sampling), the saving of each leave-out switch, and DDS
throughput between two processes (raw-CDR fast path against the IdlStruct path).

    python bench/bench_publish.py [--quick] [--out bench/results]

Writes ``publish.json`` and ``publish.png`` into ``--out``.

* **RTF against resolution**: the fork scene (servo swinging the fork, scene time 150-250 ms,
  the camera static at the scene's first ring view), 64x64, 128x128, 346x260, adaptive
  sampling (tolerance 0.1 C), leave-out on, evt3 packets, no bag and no DDS (the node's
  compute path); RTF = trajectory seconds / wall seconds, median of repeats.
* **Error against run time**: 64x64, the same span; adaptive sampling over its tolerance
  (0.5 .. 0.02 C, min step 100 us) and over its min step (1 ms .. 50 us, tolerance 0.1 C), and
  fixed rates 500 Hz .. 10 kHz; reference: the same generator fed at 20 kHz (50 us steps). Error:
  relative L1 of the net-polarity event images over 10 windows of 10 ms
  (sum |N - N_ref| / sum |N_ref|), and the relative event-count error.
* **Leave-out savings** (128x128): screen-box prefiltering of the synthetic renderer on/off
  (ray-primitive tests and wall time; events identical); adaptive time steps against a fixed
  rate at the adaptive sampler's finest step (10 kHz), over a span where the fork moves and one
  where nothing moves
  (scene time 0-100 ms); for a trained field the occupancy-grid ray mask on/off (a
  randomly initialised planes field with a half-empty occupancy grid, 64x64: rays rendered
  and wall time; images identical).
* **Published against true events** (``--only published``): a fork run trained 2 minutes at
  64x64 publishes along a novel static view and along its orbit; each publisher lever (node
  parameters: leave-out, static reuse, static world, per-pixel sampling, min step, chunk,
  baking, tolerance) against the simulator's events along the same path (event-image PSNR, zero
  floor, true render, counts per polarity, first-event timing) and its RTF (a short publish's: the
  median of up to 5 runs within 3 s of publishing); RTF against
  resolution for the static view and the orbit. ``--backbone hinge``: the same with a ``hinge`` run (stored as
  ``published_vs_true_hinge``, drawn beside the planes run's).
* **Sampled ahead** (``--only render_ahead``): the same run's orbit (a moving camera, per-pixel
  sampling), 0.3 s, 64x64 and 128x128, the field itself and baked 64, with ``render_ahead`` 0 (one
  10 ms chunk at a time) / 50 / 100 / 200 ms: RTF (median of 3 interleaved runs), render calls,
  and whether the events equal one chunk at a time's.
* **DDS throughput**: a writer process and a reader process on loopback (Cyclone DDS,
  localhost only), EventPacket messages of 64 KiB and 1 MiB, reliable keep-last 64; the
  reader deserialises every message (rosbags on the fast path, IdlStruct on the slow
  path). MB/s = bytes received / (last - first arrival), median of repeats; the share of
  messages delivered is reported too (keep-last drops what a slow reader cannot take).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from _common import ROOT, arg_parser, machine, pyplot, read_results, save_figure, write_results

from evdnerf_ros.nodes.event_publisher import run_node  # noqa: E402

EVENTS = "/event_publisher/events"
SPAN = dict(scene_time_offset=0.15, duration=0.1, chunk=0.01, realtime_factor=0.0)


def _run(tmp, **params):
    """Node run bag-only (mono: ns exact) when events are needed, else without any output."""
    from evdnerf_ros.io.rosbag2 import read_events

    bag = None
    if params.pop("keep_events", False):
        bag = Path(tempfile.mkdtemp(dir=tmp)) / "bag"
        params.update(bag=str(bag), encoding="mono")
    rep = run_node(("--ros-args", "--log-level", "warn"), overrides=params, dds=False)
    ev = read_events(bag, EVENTS).events if bag else None
    return rep, ev


def _median_runs(tmp, repeats, **params):
    reps = [_run(tmp, **params)[0] for _ in range(repeats)]
    walls = [r.wall_seconds for r in reps]
    r = reps[int(np.argsort(walls)[len(walls) // 2])]
    return r, float(np.median(walls))


def _net_images(ev, w, h, t0, t1, n=10):
    edges = np.linspace(t0, t1, n + 1).astype(np.int64)
    out = np.zeros((n, h, w), np.int64)
    k = np.clip(np.searchsorted(edges, ev["t"], "right") - 1, 0, n - 1)
    np.add.at(out, (k, ev["y"], ev["x"]), ev["p"].astype(np.int64))
    return out


def bench_resolution(tmp, quick):
    rows = []
    for (w, h) in ([(64, 64), (128, 128)] if quick else [(64, 64), (128, 128), (346, 260)]):
        repeats = 1 if quick or w > 200 else 3
        rep, wall = _median_runs(tmp, repeats, **SPAN, **{"camera.width": w, "camera.height": h})
        rows.append({"width": w, "height": h, "rtf": rep.sim_seconds / wall, "wall_s": wall,
                     "sim_s": rep.sim_seconds, "events": rep.events, "renders": rep.renders,
                     "render_share": rep.render_seconds / rep.wall_seconds, "repeats": repeats})
        print(f"{w}x{h}: RTF {rows[-1]['rtf']:.4f} ({wall:.2f} s wall for {rep.sim_seconds:.2f} s, {rep.renders} "
              f"renders, {rep.events} events, rendering {rows[-1]['render_share']:.0%})", flush=True)
    return rows


def bench_tolerance(tmp, quick):
    w = h = 64
    base = {**SPAN, "camera.width": w, "camera.height": h, "keep_events": True}
    ref_rep, ref = _run(tmp, **base, adaptive=False, render_rate_hz=20000.0)
    t0, t1 = 0, int(SPAN["duration"] * 1e9)
    ref_img = _net_images(ref, w, h, t0, t1)
    curves = {"adaptive_tolerance": [], "adaptive_min_step": [], "fixed": []}
    knobs = {"adaptive_tolerance": [0.5, 0.1, 0.02] if quick else [0.5, 0.2, 0.1, 0.05, 0.02],
             "adaptive_min_step": [1_000_000, 200_000] if quick else [1_000_000, 500_000, 200_000, 100_000, 50_000],
             "fixed": [500.0, 2000.0] if quick else [500.0, 1000.0, 2000.0, 5000.0, 10000.0]}
    for mode, values in knobs.items():
        for v in values:
            extra = ({"adaptive": True, "tolerance_c": v} if mode == "adaptive_tolerance" else
                     {"adaptive": True, "min_step_ns": v} if mode == "adaptive_min_step" else
                     {"adaptive": False, "render_rate_hz": v})
            rep, ev = _run(tmp, **base, **extra)
            img = _net_images(ev, w, h, t0, t1)
            err = float(np.abs(img - ref_img).sum() / max(np.abs(ref_img).sum(), 1))
            cnt = abs(ev.size - ref.size) / max(ref.size, 1)
            curves[mode].append({"knob": v, "wall_s": rep.wall_seconds, "rtf": rep.sim_seconds / rep.wall_seconds,
                                 "renders": rep.renders, "events": int(ev.size), "image_l1_rel": err,
                                 "count_rel": cnt})
            print(f"{mode} {v:g}: {rep.wall_seconds:.2f} s (RTF {curves[mode][-1]['rtf']:.4f}), {rep.renders} renders, "
                  f"image error {err:.3f}, count error {cnt:.3f}", flush=True)
    return {"reference": {"rate_hz": 20000.0, "events": int(ref.size), "wall_s": ref_rep.wall_seconds,
                          "renders": ref_rep.renders}, "curves": curves, "width": w, "height": h}


def bench_leave_out(tmp, quick):
    res = {}
    size = {"camera.width": 64 if quick else 128, "camera.height": 64 if quick else 128}
    reps = 1 if quick else 3
    on, w_on = _median_runs(tmp, reps, **SPAN, **size)
    off, w_off = _median_runs(tmp, reps, **SPAN, **size, leave_out=False)
    res["scene_prefilter"] = {"wall_on_s": w_on, "wall_off_s": w_off, "speedup": w_off / w_on,
                              "tests_on": on.rays_rendered, "tests_off": off.rays_rendered,
                              "test_ratio": off.rays_rendered / max(on.rays_rendered, 1),
                              "events_equal": on.events == off.events}
    print(f"prefilter: x{w_off / w_on:.2f} faster, x{res['scene_prefilter']['test_ratio']:.1f} fewer tests", flush=True)
    for name, span in (("moving", SPAN), ("static", {**SPAN, "scene_time_offset": 0.0, "duration": 0.1})):
        ad, w_ad = _median_runs(tmp, reps, **span, **size)
        # fixed at the adaptive sampler's finest step (min_step_ns = 100 us): the same time resolution
        fx, w_fx = _median_runs(tmp, reps, **span, **size, adaptive=False, render_rate_hz=10000.0)
        res[f"adaptive_{name}"] = {"wall_adaptive_s": w_ad, "wall_fixed_10khz_s": w_fx, "speedup": w_fx / w_ad,
                                   "renders_adaptive": ad.renders, "renders_fixed": fx.renders,
                                   "events_adaptive": ad.events, "events_fixed": fx.events}
        print(f"adaptive ({name}): {ad.renders} renders vs {fx.renders} at 10 kHz, x{w_fx / w_ad:.2f} faster",
              flush=True)
    res["field_occupancy"] = bench_field(tmp)
    return res


def trained_fork_run(work: Path, minutes: float = 2.0, backbone: str = "planes") -> tuple[Path, Path]:
    """A small trained run for the published-vs-true curves: the fork simulated at 64x64 (8 + 2
    views, 2x2 supersampling, ground-truth offsets), trained ``minutes`` with the default config
    and ``backbone``. Reused when WORK already holds it."""
    from evdnerf_ros.session.convert import run_convert
    from evdnerf_ros.sim.simulate import SimulationOptions, simulate_session
    from evdnerf_ros.train.trainer import run_train

    work.mkdir(parents=True, exist_ok=True)
    h5, run = work / "fork64.h5", work / ("fork64_run" if backbone == "planes" else f"fork64_{backbone}_run")
    if not h5.exists():
        simulate_session("fork", work / "session", SimulationOptions(
            views=8, val_views=2, resolution=(64, 64), frame_rate_hz=20, blur_samples=2, gt_times=0,
            supersample=2, jobs=1, min_step_ns=2_000_000), log=lambda *_: None)
        run_convert(work / "session", h5, offsets="ground-truth", log=lambda *_: None)
    if not (run / "checkpoint.pt").exists():
        run_train(h5, run, config={"backbone": backbone}, minutes=minutes, overwrite=True, log=lambda *_: None)
    return h5, run


#: publisher levers of the published-vs-true sweep (node parameters)
LEVERS = {"plain (every ray, every sample)": {"leave_out": False, "reuse_static": False, "static_world": "field"},
          "leave-out (occupancy rays)": {"reuse_static": False, "static_world": "field"},
          "static reuse (default)": {},
          "static world field": {"static_world": "field"},
          "static world flat": {"static_world": "flat"},
          "min step 1 ms": {"min_step_ns": 1_000_000},
          "min step 5 ms": {"min_step_ns": 5_000_000},
          "baked 32": {"bake_resolution": 32}, "baked 64": {"bake_resolution": 64},
          "baked 96": {"bake_resolution": 96},
          "prefetch 3 (batched renders)": {"prefetch_levels": 3},
          "baked 64 prefetch 0": {"bake_resolution": 64, "prefetch_levels": 0},
          "static reuse, tolerance 0.5 C": {"tolerance_c": 0.5},
          "static reuse, tolerance 0.02 C": {"tolerance_c": 0.02},
          "whole images": {"per_pixel": "false"},
          "min step 2 ms": {"min_step_ns": 2_000_000},
          "chunk 50 ms": {"chunk": 0.05},
          "min step 1 ms, chunk 50 ms": {"min_step_ns": 1_000_000, "chunk": 0.05},
          "whole images, min step 5 ms": {"per_pixel": "false", "min_step_ns": 5_000_000},
          "no motion guard": {"max_travel_px": 0.0},
          "motion guard 1 px": {"max_travel_px": 1.0},
          "min step 1 ms, chunk 50 ms, no motion guard": {"min_step_ns": 1_000_000, "chunk": 0.05,
                                                          "max_travel_px": 0.0}}
#: levers that are the default on one path (static_world auto: field for a static camera, flat
#: for a moving one; per_pixel auto: whole images for a static camera, per pixel for a moving
#: one) or meaningless there (the static part's tolerance levers and batched whole images with a
#: moving camera, the motion guard with a static one)
SKIP = {"static": ("static world field", "whole images", "motion guard"),
        "orbit": ("static world flat", "tolerance", "prefetch")}
#: levers of the RTF-against-resolution sweep, per path (for the orbit, "static reuse (default)"
#: is the default: a moving camera has nothing to reuse)
RESOLUTION_LEVERS = {"static": ("static reuse (default)", "baked 64"), "orbit": ("static reuse (default)", "baked 64")}


#: Repeats of a short publish in the published-vs-true part (the median RTF is kept).
REPEATS, REPEAT_WALL_S = 5, 3.0


def bench_published(work: Path, quick: bool, threads: int, levers=None, span_s: float = 0.0,
                    backbone: str = "planes") -> dict:
    """Published events against the simulator's along the same path (eval.published), for each
    publisher lever (error against run time; ``levers``: names to run, default all) and against
    resolution (RTF); ``span_s``: seconds of events per publish (0: 0.1 quick, else 0.3)."""
    import torch

    from evdnerf_ros.eval.published import published_vs_true

    torch.set_num_threads(threads)
    h5, run = trained_fork_run(work, minutes=1.0 if quick else 2.0, backbone=backbone)
    span = int(round(span_s * 1e9)) or (100_000_000 if quick else 300_000_000)
    windows = 16
    # a moving camera re-plans at every pose (seconds per render on a CPU): at most 0.1 s of it
    spans = {"static": span, "orbit": min(span, 100_000_000)}
    out = {"threads": threads, "span_s": span / 1e9, "orbit_span_s": spans["orbit"] / 1e9, "windows": windows,
           "run": f"fork 64x64, 8 + 2 views, {'1' if quick else '2'} min of training, {backbone} field", "levers": {},
           "resolution": []}

    def one(path, params, ref, **kw):
        """One lever's publish, repeated (up to ``REPEATS`` runs within ``REPEAT_WALL_S`` of publishing)
        where a run is short enough for the machine's noise to matter: its RTF is the median."""
        def publish(reference, log):
            return published_vs_true(run, h5, n_windows=windows, static=path == "static", duration_ns=spans[path],
                                     publisher=params, true_reference=reference, log=log, **kw)

        r = publish(ref, lambda m: print(m, flush=True))
        rtfs, walls = [r["publisher"]["rtf"]], [r["publisher"]["wall_s"]]
        while len(rtfs) < REPEATS and sum(walls) < REPEAT_WALL_S:
            again = publish(r["reference"], lambda m: None)
            rtfs.append(again["publisher"]["rtf"])
            walls.append(again["publisher"]["wall_s"])
        r["publisher"].update(rtf=float(np.median(rtfs)), rtf_runs=rtfs)
        return r

    for path in ("static", "orbit"):
        ref, rows = None, []
        for name, params in LEVERS.items():
            if any(k in name for k in SKIP[path]) or (levers and name not in levers):
                continue
            r = one(path, params, ref)
            ref = r.pop("reference")
            rows.append({"lever": name, **{k: r[k] for k in ("published", "zero_floor", "true_render",
                         "margin_closed", "counts", "first_events", "publisher", "true_publisher")}})
        out["levers"][path] = rows
    for path, names in RESOLUTION_LEVERS.items():
        for size in ((32, 32), (64, 64)) if quick else ((32, 32), (64, 64), (128, 128)):
            ref = None
            for name in names:
                if levers and name not in levers:
                    continue
                r = one(path, LEVERS[name], ref, resolution=size)
                ref = r.pop("reference")
                out["resolution"].append({"path": path, "width": size[0], "height": size[1], "lever": name,
                                          "rtf": r["publisher"]["rtf"], "source_s": r["publisher"]["source_s"],
                                          "psnr": r["published"]["psnr"], "zero_floor": r["zero_floor"]["psnr"],
                                          "true_render": r["true_render"]["psnr"],
                                          "events_on": r["counts"]["published_on"]})
    return out


#: ``render_ahead`` values of the render-ahead part (s; 0: one chunk at a time)
AHEAD_S = (0.0, 0.05, 0.1, 0.2)


def bench_render_ahead(work: Path, quick: bool, threads: int) -> dict:
    """A moving camera (the orbit) sampled per pixel one chunk (10 ms) at a time against
    ``render_ahead`` spans of several chunks: the same events (checked), fewer and larger render
    calls; the publisher alone (``publisher_cost``), the field itself and baked 64, 64x64 and
    128x128, the median RTF of interleaved repeats."""
    import torch

    from evdnerf_ros.eval.published import publisher_cost

    torch.set_num_threads(threads)
    _, run = trained_fork_run(work, minutes=1.0 if quick else 2.0)
    span = 100_000_000 if quick else 300_000_000
    repeats = 1 if quick else 3
    rows = []
    for size in ((64, 64),) if quick else ((64, 64), (128, 128)):
        for source, extra in (("field", {}), ("baked 64", {"bake_resolution": 64})):
            runs = {a: [] for a in AHEAD_S}
            for _ in range(repeats):                     # interleaved: the machine's drift hits every value alike
                for a in AHEAD_S:
                    runs[a].append(publisher_cost(run, static=False, duration_ns=span, resolution=size,
                                                  publisher={**extra, "render_ahead": a}))
            for a, costs in runs.items():
                rtfs = [c["rtf"] for c in costs]
                row = {"width": size[0], "height": size[1], "source": source, "render_ahead_s": a,
                       "rtf": float(np.median(rtfs)), "rtf_runs": rtfs, "render_calls": costs[0]["render_calls"],
                       "renders": costs[0]["renders"], "pixels_rendered": costs[0]["pixels_rendered"],
                       "events": costs[0]["events"], "same_events_as_one_chunk": costs[0]["events"] == runs[0.0][0]["events"]}
                rows.append(row)
                print(f"render ahead {a:g} s, {source}, {size[0]}x{size[1]}: RTF {row['rtf']:.3f} "
                      f"({row['render_calls']} render calls, {row['events']} events)", flush=True)
    return {"threads": threads, "span_s": span / 1e9, "chunk_s": 0.01, "rows": rows}


def make_field_run(run_dir, *, half_empty=True):
    """A randomly initialised planes field saved as a run (checkpoint with box and occupancy)."""
    import torch

    from evdnerf_ros.train.checkpoint import save_checkpoint
    from evdnerf_ros.train.config import TrainConfig, field_from_config
    from evdnerf_ros.train.trainer import CHECKPOINT_NAME

    cfg = TrainConfig()
    torch.manual_seed(0)
    field = field_from_config(cfg)
    occ = torch.zeros((16, 16, 16), dtype=torch.bool)
    occ[4:12, 4:12, 4:12] = True if half_empty else occ[4:12, 4:12, 4:12]
    Path(run_dir).mkdir(parents=True, exist_ok=True)
    save_checkpoint(Path(run_dir) / CHECKPOINT_NAME, field=field, optimizer=None, iteration=0,
                    config=cfg.to_dict(), backbone=cfg.backbone, rng={}, box=[[-1, -1, -1], [1, 1, 1]],
                    extra={"occupied": occ})
    return run_dir


def bench_field(tmp):
    import yaml

    run = make_field_run(Path(tmp) / "field_run")
    from evdnerf_ros.geometry.camera import look_at
    from evdnerf_ros.geometry.rotations import matrix_to_quat, quat_to_ros

    T = look_at([0.0, -3.0, 0.5], [0.0, 0.0, 0.0])
    q = quat_to_ros(matrix_to_quat(T[:3, :3])).tolist()
    traj = Path(tmp) / "field_traj.yaml"
    traj.write_text(yaml.safe_dump({"poses": [{"t_ns": 0, "position": T[:3, 3].tolist(), "orientation": q},
                                              {"t_ns": 20_000_000, "position": T[:3, 3].tolist(), "orientation": q}]}))
    common = {"run_dir": str(run), "trajectory": str(traj), "camera.width": 64, "camera.height": 64,
              "adaptive": False, "render_rate_hz": 2000.0, "realtime_factor": 0.0, "field_duration": 1.0}
    _run(tmp, **common)                                    # warm-up (torch's first calls)
    walls = {True: [], False: []}
    for _ in range(3):                                     # interleaved, median
        for leave_out in (True, False):
            rep, _ = _run(tmp, **common, leave_out=leave_out)
            walls[leave_out].append(rep.wall_seconds)
            if leave_out:
                on = rep
            else:
                off = rep
    w_on, w_off = float(np.median(walls[True])), float(np.median(walls[False]))
    out = {"wall_on_s": w_on, "wall_off_s": w_off, "speedup": w_off / w_on,
           "rays_on": on.rays_rendered, "rays_off": off.rays_rendered, "events_equal": on.events == off.events,
           "note": "randomly initialised planes field, occupancy grid with 1/8 of the box occupied, 64x64, "
                   f"{on.renders} renders, median of 3 interleaved runs after a warm-up"}
    print(f"field occupancy mask: x{out['speedup']:.2f} faster, {on.rays_rendered} vs {off.rays_rendered} rays", flush=True)
    return out


# ----------------------------------------------------------------------------- DDS throughput

READER = r"""
import json, sys, time
from evdnerf_ros.ros.qos import LOOPBACK_XML, profile
from evdnerf_ros.ros.transport import DdsContext, DdsSubscription
domain, fast, n_expected = int(sys.argv[1]), sys.argv[2] == "fast", int(sys.argv[3])
ctx = DdsContext(domain, config=LOOPBACK_XML)
sub = DdsSubscription(ctx, "/bench/events", "event_camera_msgs/msg/EventPacket", profile("default", 64), fast=fast)
print("ready", flush=True)
got = nbytes = 0; first = last = None; deadline = time.monotonic() + 120
while time.monotonic() < deadline:
    if not sub.wait(0.5):
        if first is not None and time.monotonic() - last > 2.0:
            break
        continue
    msgs = sub.take(64)
    now = time.monotonic()
    for m in msgs:
        first = first or now
        last = now
        got += 1
        nbytes += len(m.events)
    if any(m.seq == n_expected - 1 for m in msgs):
        break
print(json.dumps({"received": got, "payload_bytes": nbytes, "seconds": (last - first) if got else 0.0}), flush=True)
"""


def dds_run(fast: bool, size: int, n: int, domain: int, cpus=None) -> dict:
    from evdnerf_ros.io.typestore import ros2_typestore
    from evdnerf_ros.ros.qos import LOOPBACK_XML, profile
    from evdnerf_ros.ros.transport import DdsContext, DdsPublisher
    from evdnerf_ros.io.messages import header

    pre = ["taskset", "-c", cpus[1]] if cpus else []
    reader = subprocess.Popen(pre + [sys.executable, "-c", READER, str(domain), "fast" if fast else "slow", str(n)],
                              stdout=subprocess.PIPE, text=True, cwd=ROOT)
    assert reader.stdout.readline().strip() == "ready"
    ctx = DdsContext(domain, config=LOOPBACK_XML)
    pub = DdsPublisher(ctx, "/bench/events", "event_camera_msgs/msg/EventPacket", profile("default", 64), fast=fast)
    if not pub.wait_for_subscribers(1, 20):
        raise RuntimeError("reader did not match")
    T = ros2_typestore().types
    payload = np.random.default_rng(0).integers(0, 256, size, dtype=np.uint8)
    t0 = time.perf_counter()
    for k in range(n):
        msg = T["event_camera_msgs/msg/EventPacket"](header=header(k), height=260, width=346, seq=k, time_base=0,
                                                     encoding="evt3", is_bigendian=False, events=payload)
        pub.publish(msg)
    pub.wait_for_acks(30.0)
    send_s = time.perf_counter() - t0
    out, _ = reader.communicate(timeout=180)
    res = json.loads(out.strip().splitlines()[-1])
    ctx.close()
    res.update(sent=n, message_bytes=size, send_s=send_s,
               mb_per_s=res["payload_bytes"] / res["seconds"] / 1e6 if res["seconds"] > 0 else None,
               delivered=res["received"] / n)
    return res


def bench_dds(quick, cpus):
    rows = []
    domain = 100 + os.getpid() % 100
    for size in ([1 << 16, 1 << 20]):
        for fast in (True, False):
            n = (200 if size == 1 << 20 else 2000) if fast else (10 if size == 1 << 20 else 100)
            if quick:
                n = max(5, n // 5)
            runs = [dds_run(fast, size, n, domain + i, cpus) for i in range(1 if quick else 3)]
            rates = [r["mb_per_s"] for r in runs if r["mb_per_s"]]
            row = {"path": "raw CDR (fast)" if fast else "IdlStruct (slow)", "message_bytes": size, "messages": n,
                   "mb_per_s_median": float(np.median(rates)) if rates else None,
                   "delivered_median": float(np.median([r["delivered"] for r in runs])), "runs": runs}
            rows.append(row)
            print(f"DDS {row['path']:17s} {size >> 10:5d} KiB: {row['mb_per_s_median']:.1f} MB/s, "
                  f"delivered {row['delivered_median']:.0%}", flush=True)
    return rows


def main(argv=None):
    ap = arg_parser(__doc__, quick="smaller sweep (smoke test)")
    ap.add_argument("--dds-cpus", default="0,1", help="cores of the DDS writer,reader ('' = no pinning)")
    ap.add_argument("--note", default="", help="free text stored in the JSON (e.g. machine load)")
    ap.add_argument("--only", choices=["resolution", "tolerance", "leave_out", "dds", "published", "render_ahead"],
                    action="append")
    ap.add_argument("--work", default="", help="folder for the published-vs-true run (kept; default: a temp folder)")
    ap.add_argument("--threads", type=int, default=1, help="torch threads of the published-vs-true part (1: shared "
                    "machine)")
    ap.add_argument("--levers", default="", help="published part: comma-separated lever names (default: all)")
    ap.add_argument("--backbone", default="planes", choices=["planes", "hinge"],
                    help="published part: the trained run's field (hinge: stored as published_vs_true_hinge)")
    ap.add_argument("--span", type=float, default=0.0, help="published part: seconds of events per publish "
                    "(0: 0.1 with --quick, else 0.3)")
    args = ap.parse_args(argv)
    cpus = args.dds_cpus.split(",") if args.dds_cpus else None
    parts = args.only or ["resolution", "tolerance", "leave_out", "dds", "published", "render_ahead"]
    name = "publish_quick" if args.quick else "publish"
    result = read_results(args.out, name, missing_ok=True) if args.only else {}   # update only the parts run now
    result.update({"benchmark": "publish", "quick": args.quick, "note": args.note,
                   "machine": machine("cyclonedds", "torch")})
    with tempfile.TemporaryDirectory() as tmp:
        if "resolution" in parts:
            result["rtf_vs_resolution"] = bench_resolution(tmp, args.quick)
        if "tolerance" in parts:
            result["error_vs_runtime"] = bench_tolerance(tmp, args.quick)
        if "leave_out" in parts:
            result["leave_out"] = bench_leave_out(tmp, args.quick)
    if "dds" in parts:
        result["dds_throughput"] = bench_dds(args.quick, cpus)
    if "published" in parts:
        with tempfile.TemporaryDirectory() as tmp:
            key = "published_vs_true" + ("" if args.backbone == "planes" else f"_{args.backbone}")
            result[key] = bench_published(Path(args.work or tmp), args.quick, args.threads,
                                          [n for n in args.levers.split(",") if n] or None, args.span,
                                          args.backbone)
    if "render_ahead" in parts:
        with tempfile.TemporaryDirectory() as tmp:
            result["render_ahead"] = bench_render_ahead(Path(args.work or tmp), args.quick, args.threads)
    write_results(args.out, name, result, plot)


def plot(result, path):
    pv = result.get("published_vs_true")
    ahead = result.get("render_ahead")
    fig, ax = pyplot().subplots(1, 7, figsize=(36, 4.6))
    if pv:
        hinge = result.get("published_vs_true_hinge", {"levers": {}})
        for path_name, mk, field_name, levers in (("static", "o", "planes", pv), ("orbit", "s", "planes", pv),
                                                  ("static", "P", "hinge", hinge), ("orbit", "X", "hinge", hinge)):
            rows = levers["levers"].get(path_name, [])
            if not rows:
                continue
            ax[4].plot([r["publisher"]["wall_s"] for r in rows], [r["published"]["psnr"] for r in rows], mk,
                       label=f"{path_name} camera, {field_name} field")
            for r in rows:
                ax[4].annotate(r["lever"], (r["publisher"]["wall_s"], r["published"]["psnr"]), fontsize=6)
            if rows:
                ax[4].axhline(rows[0]["zero_floor"]["psnr"], ls="--", lw=1, color="grey")
                ax[4].axhline(rows[0]["true_render"]["psnr"], ls=":", lw=1, color="k")
        ax[4].set_xscale("log")
        ax[4].set_xlabel(f"publisher wall s for {pv['span_s']:g} s (static) / {pv.get('orbit_span_s', pv['span_s']):g} s "
                         f"(orbit) of events ({pv['threads']} threads)")
        ax[4].set_ylabel("events PSNR vs true events (dB)")
        ax[4].set_title("published vs true (dashed: all-zero floor, dotted: true render)")
        ax[4].legend(fontsize=7)
        curves = dict.fromkeys((r.get("path", "static"), r["lever"]) for r in pv["resolution"])
        for (path_name, lever), mk in zip(curves, ("o-", "s--", "^-.", "d:")):
            rows = [r for r in pv["resolution"] if (r.get("path", "static"), r["lever"]) == (path_name, lever)]
            ax[5].plot([f"{r['width']}x{r['height']}" for r in rows], [r["rtf"] for r in rows], mk,
                       label=f"{path_name}: {lever}")
        ax[5].axhline(0.5, color="k", ls=":", lw=1)
        ax[5].set_yscale("log")
        ax[5].set_ylabel("real-time factor")
        ax[5].set_title("trained field, novel views: RTF vs resolution")
        ax[5].legend(fontsize=7)
    rows = result.get("rtf_vs_resolution", [])
    if rows:
        ax[0].bar([f"{r['width']}x{r['height']}" for r in rows], [r["rtf"] for r in rows], color="tab:blue")
        for i, r in enumerate(rows):
            ax[0].text(i, r["rtf"], f"{r['rtf']:.3g}", ha="center", va="bottom")
        ax[0].set_ylabel("real-time factor (trajectory s / wall s)")
        ax[0].set_title("publisher RTF, fork swinging, adaptive 0.1 C")
    err = result.get("error_vs_runtime")
    if err:
        for mode, mk, label in (("adaptive_tolerance", "o-", "adaptive, tolerance (C)"),
                                ("adaptive_min_step", "^-", "adaptive, min step (us)"),
                                ("fixed", "s--", "fixed rate (Hz)")):
            c = err["curves"][mode]
            ax[1].plot([p["wall_s"] for p in c], [p["image_l1_rel"] for p in c], mk, label=label)
            for p in c:
                k = p["knob"] / 1000 if mode == "adaptive_min_step" else p["knob"]
                ax[1].annotate(f"{k:g}", (p["wall_s"], p["image_l1_rel"]), fontsize=7)
        ax[1].set_xscale("log")
        ax[1].set_yscale("log")
        ax[1].set_xlabel("wall seconds for 0.1 s of events (64x64)")
        ax[1].set_ylabel("event-image error vs 20 kHz reference (rel. L1)")
        ax[1].set_title("error against run time (labels: the knob)")
        ax[1].legend()
    dds = result.get("dds_throughput", [])
    if dds:
        labels = [f"{r['path'].split()[0]}\n{r['message_bytes'] >> 10} KiB" for r in dds]
        vals = [r["mb_per_s_median"] or 0 for r in dds]
        ax[2].bar(labels, vals, color=["tab:green" if "fast" in r["path"] else "tab:red" for r in dds])
        for i, v in enumerate(vals):
            ax[2].text(i, v, f"{v:.0f}", ha="center", va="bottom")
        ax[2].axhline(500, color="k", ls=":", lw=1)
        ax[2].set_yscale("log")
        ax[2].set_ylabel("MB/s (two processes, loopback)")
        ax[2].set_title("DDS throughput: raw CDR vs IdlStruct")
    lo = result.get("leave_out")
    if lo:
        items = [("screen-box\nprefilter", lo["scene_prefilter"]["speedup"]),
                 ("adaptive steps\n(fork moving)", lo["adaptive_moving"]["speedup"]),
                 ("adaptive steps\n(nothing moves)", lo["adaptive_static"]["speedup"]),
                 ("field occupancy\nray mask", lo["field_occupancy"]["speedup"])]
        ax[3].bar([k for k, _ in items], [v for _, v in items], color="tab:purple")
        for i, (_, v) in enumerate(items):
            ax[3].text(i, v, f"x{v:.2f}", ha="center", va="bottom")
        ax[3].axhline(1.0, color="k", lw=1)
        ax[3].set_yscale("log")
        ax[3].set_ylabel("speed-up (wall time off / on)")
        ax[3].set_title("leave-out switches (adaptive vs fixed at its finest step)")
    if ahead:
        for (size, source), mk in zip(dict.fromkeys((r["width"], r["source"]) for r in ahead["rows"]),
                                      ("o-", "s--", "^-", "d--")):
            rows = [r for r in ahead["rows"] if (r["width"], r["source"]) == (size, source)]
            ax[6].plot([r["render_ahead_s"] * 1e3 for r in rows], [r["rtf"] for r in rows], mk,
                       label=f"{size}x{rows[0]['height']}, {source}")
            for r in rows:
                ax[6].annotate(f"{r['render_calls']}", (r["render_ahead_s"] * 1e3, r["rtf"]), fontsize=7)
        ax[6].set_yscale("log")
        ax[6].set_xlabel(f"render_ahead (ms; 0: one {ahead['chunk_s'] * 1e3:g} ms chunk at a time)")
        ax[6].set_ylabel("real-time factor")
        ax[6].set_title(f"moving camera per pixel: sampled ahead (labels: render calls per {ahead['span_s']:g} s; "
                        "same events)", fontsize=9)
        ax[6].legend(fontsize=7)
    for a in ax:
        if not a.has_data():
            a.set_visible(False)
    save_figure(fig, path, dpi=110)


if __name__ == "__main__":
    main()
