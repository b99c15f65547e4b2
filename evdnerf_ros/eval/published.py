"""The product's own metric: events *published* from a trained run against the events the
simulator emits along the same trajectory (training sets converted from `simulate`).

``published_vs_true(RUN, TRAIN.h5)`` runs the event publisher node twice along one camera
path, with the same camera, contrast thresholds (the training set's) and time sampling:

- *published*: the trained field (``run_dir``), as ``evdnerf publish --run`` does;
- *true*: the simulator's scene (the ``truth`` record ``evdnerf convert`` keeps: scene and
  supersampling), at scene time = the training set's common clock + the view's recorded scene
  time at the origin, so both see the same moment of the motion.

The default path is the run's orbit (once round its training views over the training span,
``TrainedRun.orbit``: poses between the views are novel); ``static=True`` holds the camera at
the pose halfway along that orbit between two training views (a novel static view).
With ``--downsample`` sets the truth is rendered at the training camera itself (not at the
source size binned), a small difference from the training events.

Scores per window (``n_windows`` equal windows of the span), all against the true events'
image E = C+ N+ - C- N- (Eq. 5):

- ``published``: PSNR / SSIM / MAE of the published events' image (``eval.metrics``:
  data range 2 max|E|), next to the all-zero floor (``zero_floor``);
- ``true_render``: the true scene's continuous log change dL rendered at each window's ends,
  scored the same way (what a perfect field would reach: events are quantised), and
  ``margin_closed`` = (published - floor) / (true_render - floor) of PSNR;
- ``counts``: events per polarity, published and true, and their relative differences;
- ``first_events``: per window, pixel and polarity, the time of the first event (when an
  edge first reaches the pixel): of the (window, pixel, polarity) cells with events in
  either stream, the share with events in both (``matched``), and the median / 90th
  percentile of |t_published - t_true| over those (microseconds).

- ``split``: the same pooled scores on two parts of the (window, pixel) cells: ``moving_parts``,
  where the scene's own motion changes the true log intensity during the window (``MOTION_DL``; the true scene rendered at each window's end with the motion held at the
  window's start, against it rendered at the end: what static training views can teach), and
  ``static_world``, the rest (the world sweeping past a moving camera, which static views never
  record: a still camera sees no events of it). Each with its cells' share, its true and
  published events, PSNR pooled against the floor and the true render, and the margin closed.

The publisher's own cost is reported too (wall seconds, real-time factor, renders, field
evaluations), so a benchmark can plot error against run time for each speed-up.  The result also
holds both event-image stacks (``images``: true and published, (windows, H, W)), which
``side_by_side`` draws for the windows with the most true events.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np

from ..errors import InputError
from .metrics import event_metrics, psnr
from .truth import margin_closed

NS = 1_000_000_000
#: Windows ``side_by_side`` draws.
PICTURE_WINDOWS = 4
#: The scene's own motion changes a cell's log intensity by more than this during the window: a
#: moving part's cell (``split``). Far above the render's rounding, far below any threshold: on the
#: tiny test scene seen by a still camera, 95 % of the true events fall in such cells (the rest are
#: placed by the simulator's interpolation between samples just past a window's end).
MOTION_DL = 1e-3


def _write_trajectory(path: Path, t, T) -> Path:
    import yaml

    from ..geometry.rotations import matrix_to_quat, quat_to_ros

    poses = [{"t_ns": int(ti), "position": [float(v) for v in Ti[:3, 3]],
              "orientation": [float(v) for v in quat_to_ros(matrix_to_quat(Ti[:3, :3]))]}
             for ti, Ti in zip(t, T)]
    path.write_text(yaml.safe_dump({"poses": poses}))
    return path


def _collect(overrides: dict):
    """Run the publisher node (no DDS, no bag) and return (report, events)."""
    from ..nodes.event_publisher import EventPublisher

    chunks = []
    node = EventPublisher(("--ros-args", "--log-level", "warn"), overrides=overrides, dds=False)
    with node:
        rep = node.run(on_events=lambda ev: chunks.append(ev.copy()) if ev.size else None)
    return rep, np.concatenate(chunks) if chunks else _empty()


def _empty():
    from ..events.types import empty_events

    return empty_events()


def _cells(ev, edges: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Each event's flat (window, y, x) cell index, and which events fall in a window."""
    k = np.searchsorted(edges, ev["t"], "right") - 1
    ok = (k >= 0) & (k < len(edges) - 1)
    return (k[ok] * height + ev["y"][ok].astype(np.int64)) * width + ev["x"][ok], ok


def event_image_stack(ev, edges: np.ndarray, width: int, height: int, c_pos: float, c_neg: float) -> np.ndarray:
    """(K, H, W) float32: C+ N+ - C- N- of the events in each window [edges[k], edges[k+1])."""
    k_count = len(edges) - 1
    out = np.zeros(k_count * height * width, np.float64)
    if ev.size:
        idx, ok = _cells(ev, edges, width, height)
        w = np.where(ev["p"][ok] > 0, c_pos, -c_neg)
        out += np.bincount(idx, weights=w, minlength=out.size)
    return out.reshape(k_count, height, width).astype(np.float32)


def split_scores(moving: np.ndarray, pub_img: np.ndarray, true_img: np.ndarray, true_dl: np.ndarray,
                 data_range: float, pub, true, edges: np.ndarray) -> dict:
    """Pooled scores on the moving parts' cells (``moving``, (K, H, W) bool) and on the rest."""
    height, width = true_img.shape[1:]
    pub_cells, _ = _cells(pub, edges, width, height)
    true_cells, _ = _cells(true, edges, width, height)
    flat = moving.reshape(-1)
    out = {}
    for name, sel in (("moving_parts", flat), ("static_world", ~flat)):
        t, p, d = (a.reshape(-1)[sel].astype(np.float64) for a in (true_img, pub_img, true_dl))
        scores = {"cells": float(sel.mean()), "true_events": int(sel[true_cells].sum()),
                  "published_events": int(sel[pub_cells].sum())}
        if t.size:
            pooled = {"published": psnr(p, t, data_range), "zero_floor": psnr(np.zeros_like(t), t, data_range),
                      "true_render": psnr(d, t, data_range)}
            scores.update({f"{k}_psnr_pooled": v for k, v in pooled.items()},
                          margin_closed=margin_closed(pooled["published"], pooled["zero_floor"],
                                                      pooled["true_render"]))
        out[name] = scores
    return out


def first_event_timing(pub, true, edges: np.ndarray, width: int, height: int) -> dict:
    """First event per (window, pixel, polarity) in both streams: matched share and |dt| (us)."""
    def firsts(ev):
        if not ev.size:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        k = np.clip(np.searchsorted(edges, ev["t"], "right") - 1, 0, len(edges) - 2)
        key = ((k * height + ev["y"].astype(np.int64)) * width + ev["x"]) * 2 + (ev["p"] > 0)
        order = np.argsort(key, kind="stable")            # events are time-sorted: stable keeps the first
        keys, first = np.unique(key[order], return_index=True)
        return keys, ev["t"][order[first]]

    kp, tp = firsts(pub)
    kt, tt = firsts(true)
    both, ip, it = np.intersect1d(kp, kt, assume_unique=True, return_indices=True)
    either = len(kp) + len(kt) - len(both)
    dt = np.abs(tp[ip] - tt[it]) / 1e3
    return {"cells_published": int(len(kp)), "cells_true": int(len(kt)), "cells_both": int(len(both)),
            "matched": float(len(both) / either) if either else 1.0,
            "median_abs_dt_us": float(np.median(dt)) if dt.size else None,
            "p90_abs_dt_us": float(np.percentile(dt, 90)) if dt.size else None}


def _comparison_path(run_dir, train_h5, *, static: bool, duration_ns: int | None, resolution) -> dict:
    """What both publishers of the comparison share: the run, its set's truth record and clock
    (t0, t1, thresholds, the first view's scene time at the origin, eps), the camera, the span,
    the path (times, poses) and the node parameters common to both runs."""
    from ..io.trainingset import TrainingSet
    from ..train.run import TrainedRun

    run = TrainedRun.load(run_dir)
    if train_h5 is None:
        train_h5 = (run.extra.get("train_set") or {}).get("path")
        if not train_h5:
            raise InputError(f"{run_dir}: does not record its training set; give TRAIN.h5")
    with TrainingSet(train_h5) as ts:
        record = ts.provenance.get("truth")
        if not record:
            raise InputError(f"{train_h5}: no true scene recorded (not converted from a simulated session); "
                             "the published-vs-true comparison needs one")
        t0, t1 = (int(v) for v in ts.time_range)
        c_pos, c_neg = (float(v) for v in ts.thresholds)
        views = list(ts.train_views)
        origin = int(record["scene_time_at_origin_ns"].get(views[0], next(iter(
            record["scene_time_at_origin_ns"].values()))))
        eps = float(ts.eps) if ts.eps is not None else 1e-3
    cam = run.train_camera
    if cam is None:
        raise InputError(f"{run_dir}: does not record its training camera; retrain with this version")
    if resolution is not None:
        from ..geometry.camera import PinholeCamera

        w, h = (int(v) for v in resolution)
        sx, sy = w / cam.width, h / cam.height
        cam = PinholeCamera(w, h, cam.K[0, 0] * sx, cam.K[1, 1] * sy, (cam.K[0, 2] + 0.5) * sx - 0.5,
                            (cam.K[1, 2] + 0.5) * sy - 0.5)
    span = int(duration_ns or (t1 - t0))
    t, T = run.orbit(t1 - t0)
    if static:
        from ..geometry.pose_track import PoseTrack

        Tm = PoseTrack(t, T, source=f"{run_dir}: orbit")(int((t[0] + t[1]) // 2))
        t, T = np.array([0, span], np.int64), np.stack([Tm, Tm])
    K = cam.K
    common = {"camera.width": cam.width, "camera.height": cam.height,
              "camera.K": [float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])],
              "c_pos": c_pos, "c_neg": c_neg, "duration": span / NS, "realtime_factor": 0.0,
              "trajectory_max_gap": max(0.5, float(np.diff(t).max()) / NS * 1.01)}
    return {"train_h5": train_h5, "record": record, "t0": t0, "t1": t1, "c_pos": c_pos, "c_neg": c_neg,
            "origin": origin, "eps": eps, "cam": cam, "span": span, "t": t, "T": T, "common": common}


def _publish_run(run_dir, path: dict, traj: Path, publisher: dict | None):
    """The run published along the comparison's path: (report, events)."""
    return _collect({**path["common"], "run_dir": str(run_dir), "trajectory": str(traj),
                     "field_duration": (path["t1"] - path["t0"]) / NS, "scene_time_offset": 0.0,
                     **(publisher or {})})


def _cost(rep, publisher: dict | None) -> dict:
    """The publisher's own cost from its report."""
    return {"wall_s": rep.wall_seconds, "rtf": rep.rtf, "source_s": rep.source_seconds,
            "renders": rep.renders, "render_calls": rep.render_calls, "pixels_rendered": rep.pixels_rendered,
            "render_s": rep.render_seconds, "rays_rendered": rep.rays_rendered,
            "rays_total": rep.rays_total, "samples_evaluated": rep.samples_evaluated,
            "samples_total": rep.samples_total, "events": rep.events,
            "params": dict(publisher or {})}


def publisher_cost(run_dir, train_h5=None, *, static: bool = False, duration_ns: int | None = None,
                   resolution=None, publisher: dict | None = None) -> dict:
    """The run published along the comparison's path alone, without the truth (which costs far
    more than publishing on a GPU): its cost (wall seconds, real-time factor, renders, ...) for
    spans too long to simulate the truth over in a benchmark."""
    path = _comparison_path(run_dir, train_h5, static=static, duration_ns=duration_ns, resolution=resolution)
    with tempfile.TemporaryDirectory() as tmp:
        rep, _ = _publish_run(run_dir, path, _write_trajectory(Path(tmp) / "trajectory.yaml", path["t"], path["T"]),
                              publisher)
    return _cost(rep, publisher)


def published_vs_true(run_dir, train_h5=None, *, n_windows: int = 32, static: bool = False,
                      duration_ns: int | None = None, resolution=None, publisher: dict | None = None,
                      truth_publisher: dict | None = None, true_reference=None, log=print) -> dict:
    """Publish from the run and from the true scene along one path and compare (module docstring).

    ``publisher``: extra node parameters of the published run (the speed-up switches, sampling
    tolerance, device); ``truth_publisher``: extra parameters of the true run (default: the
    same sampling).  ``true_reference``: a previous result's ``"reference"`` entry for the same
    run, path and windows, to skip re-simulating the truth (the benchmark's sweep).
    """
    from ..sim.render import SceneRenderer
    from ..sim.scene import load_scene

    if n_windows < 1:
        raise InputError(f"n_windows must be >= 1, got {n_windows}")
    path = _comparison_path(run_dir, train_h5, static=static, duration_ns=duration_ns, resolution=resolution)
    train_h5, record, t0, origin, eps = (path[k] for k in ("train_h5", "record", "t0", "origin", "eps"))
    c_pos, c_neg, cam, span, t, T, common = (path[k] for k in ("c_pos", "c_neg", "cam", "span", "t", "T", "common"))
    edges = np.linspace(0, span, n_windows + 1).round().astype(np.int64)
    with tempfile.TemporaryDirectory() as tmp:
        traj = _write_trajectory(Path(tmp) / "trajectory.yaml", t, T)
        rep, pub = _publish_run(run_dir, path, traj, publisher)
        if true_reference is None:
            true_params = {**common, "scene": record["scene"], "trajectory": str(traj),
                           "supersample": int(record.get("supersample", 1)),
                           "scene_time_offset": (t0 + origin) / NS, **(truth_publisher or {})}
            trep, true = _collect(true_params)
            # the true scene's continuous dL at the windows' ends (the reference a perfect field reaches)
            from ..geometry.pose_track import PoseTrack

            track = PoseTrack(t, T, source="published-vs-true path")
            scene = load_scene(record["scene"], check_cameras=False)
            sr = SceneRenderer(scene, cam, int(record.get("supersample", 1)))
            logs = [np.log(np.asarray(sr.render(track(int(e)), int(e) + t0 + origin), np.float64) + eps)
                    for e in edges]
            true_dl = np.stack([logs[k + 1] - logs[k] for k in range(n_windows)]).astype(np.float32)
            # the scene's own motion during each window: its end rendered with the motion held at the start
            held = [np.log(np.asarray(sr.render(track(int(edges[k + 1])), int(edges[k]) + t0 + origin), np.float64)
                           + eps) for k in range(n_windows)]
            motion_dl = np.stack([logs[k + 1] - held[k] for k in range(n_windows)]).astype(np.float32)
            true_img = event_image_stack(true, edges, cam.width, cam.height, c_pos, c_neg)
            ref_m = event_metrics(true_dl, true_img, c_pos=c_pos, c_neg=c_neg)
            true_reference = {"events": true, "image": true_img, "dl": true_dl, "motion_dl": motion_dl, "metrics": ref_m,
                              "wall_s": trep.wall_seconds, "renders": trep.renders}
        true, true_img, ref_m = (true_reference[k] for k in ("events", "image", "metrics"))
    pub_img = event_image_stack(pub, edges, cam.width, cam.height, c_pos, c_neg)
    m = event_metrics(pub_img, true_img, c_pos=c_pos, c_neg=c_neg)

    def strip(d):
        return {k: v for k, v in d.items() if k != "psnr_per_window"}

    counts = {"published_on": int((pub["p"] > 0).sum()), "published_off": int((pub["p"] < 0).sum()),
              "true_on": int((true["p"] > 0).sum()), "true_off": int((true["p"] < 0).sum())}
    for pol in ("on", "off"):
        tr = counts[f"true_{pol}"]
        counts[f"rel_diff_{pol}"] = (counts[f"published_{pol}"] - tr) / tr if tr else None
    result = {"run": str(run_dir), "train_set": str(train_h5), "path": "static" if static else "orbit",
              "width": cam.width, "height": cam.height, "span_s": span / NS, "windows": n_windows,
              "thresholds": [c_pos, c_neg],
              "published": strip(m["continuous"]), "zero_floor": strip(m["zero_floor"]),
              "true_render": strip(ref_m["continuous"]),
              "margin_closed": margin_closed(m["continuous"]["psnr"], m["zero_floor"]["psnr"],
                                             ref_m["continuous"]["psnr"]),
              "split": split_scores(np.abs(true_reference["motion_dl"]) > MOTION_DL, pub_img, true_img, true_reference["dl"],
                                    m["data_range"], pub, true, edges),
              "counts": counts, "first_events": first_event_timing(pub, true, edges, cam.width, cam.height),
              "publisher": _cost(rep, publisher),
              "true_publisher": {"wall_s": true_reference["wall_s"], "renders": true_reference["renders"]},
              "reference": true_reference, "images": {"true": true_img, "published": pub_img}}
    log(f"published vs true ({result['path']}, {cam.width}x{cam.height}, {n_windows} windows): events PSNR "
        f"{m['continuous']['psnr']:.2f} dB (all-zero floor {m['zero_floor']['psnr']:.2f}, true render "
        f"{ref_m['continuous']['psnr']:.2f}), MAE {m['continuous']['mae']:.4f}; events ON "
        f"{counts['published_on']} vs {counts['true_on']}, OFF {counts['published_off']} vs {counts['true_off']}; "
        f"first events matched {result['first_events']['matched']:.0%}; publisher RTF {rep.rtf:.3g} "
        f"({rep.wall_seconds:.2f} s wall)")
    parts = result["split"]
    log("  pooled, on the moving parts' cells ({:.1%} of them, {} true events): margin closed {}; on the static "
        "world's ({} true events): {}".format(
            parts["moving_parts"]["cells"], parts["moving_parts"]["true_events"],
            _share(parts["moving_parts"].get("margin_closed")), parts["static_world"]["true_events"],
            _share(parts["static_world"].get("margin_closed"))))
    return result


def _share(value) -> str:
    return "n/a (no margin)" if value is None else f"{value:.0%}"


def side_by_side(result: dict, path, *, windows: int = PICTURE_WINDOWS, upscale: int = 4) -> Path:
    """A PNG of ``published_vs_true``'s ``windows`` windows with the most true change (in time
    order): the true events' image on top, the published events' below, on one colour scale (the
    largest |E| of the true windows shown; red ON, blue OFF)."""
    from ..events import save_png
    from ..events.images import signed_to_rgb

    true_img, pub_img = (np.asarray(result["images"][k], np.float32) for k in ("true", "published"))
    energy = np.abs(true_img).reshape(len(true_img), -1).sum(1)
    picked = np.sort(np.argsort(-energy, kind="stable")[:max(1, int(windows))])
    vmax = float(np.abs(true_img[picked]).max()) or 1.0
    height, width = true_img.shape[1:]
    gap_v = np.full((height, 2, 3), 128, np.uint8)
    rows = []
    for stack in (true_img, pub_img):
        tiles = [x for k in picked for x in (signed_to_rgb(stack[k], vmax=vmax), gap_v)][:-1]
        rows.extend([np.concatenate(tiles, axis=1), np.full((2, len(picked) * (width + 2) - 2, 3), 128, np.uint8)])
    return save_png(path, np.concatenate(rows[:-1], axis=0), upscale=upscale)


__all__ = ["side_by_side", "published_vs_true", "publisher_cost", "event_image_stack", "first_event_timing",
           "split_scores"]
