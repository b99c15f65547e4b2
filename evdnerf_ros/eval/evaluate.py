"""Events metrics of a field on a training set's views (the paper's protocol).

`validation_eval(...)` returns the `eval_fn` the trainer calls periodically: it renders
dL_hat = log(B(t_k) + eps) - log(B(t_{k-1}) + eps) for the protocol windows of the
static validation views (training views when the set has none) and compares it with the
ground truth dL of the events (Eq. 5), continuous and quantised, next to the all-zero floor.

A moving view (validation views with a camera trajectory, e.g. `evdnerf simulate
--moving-views`) is scored the same way, with B(t) rendered at the camera's pose at t
(interpolated from its poses, as its pose topic's consumers do): every pixel may change,
so nothing is skipped for it. ``static_world`` says what the field shows outside its dynamic
region, as the publisher's parameter of that name: ``field`` (the field as trained), ``flat``
(nothing there, one constant grey, the region fading out at its boundary) or ``auto`` (the
default of ``run_eval`` / ``evdnerf eval``: flat for moving views of a run with a dynamic
region, what the publisher plays back for a moving camera; static views are scored as trained).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import InputError
from ..field.render import flat_background, render_image
from ..field.renderer import FieldRenderer, resolve_static_world
from ..limits import check_memory
from ..geometry.pose_track import PoseTrack
from ..train.rays import camera_of
from .metrics import brightness_align, event_metrics, psnr
from .truth import TrueScene, margin_closed, on_render_grid
from .windows import scored_windows, window_changes


def evaluate_views(field, train_set, views, n_windows: int, *, windows=None, truth=None,
                   truth_metrics=None, **kw):
    """(pred (K, H, W), gt (K, H, W), metrics) over `views` x the chosen windows of one window
    count (``evaluate_window_counts``; ``windows``: the indices scored, default the protocol's).

    With `truth` (a TrueScene), metrics also hold "truth" (the true scene scored by the same
    protocol; pass `truth_metrics` to reuse an earlier score of the same views and windows)
    and "margin_closed": (field - floor) / (truth - floor) of PSNR, continuous and quantised
    (the protocol's mean over windows), and pooled (continuous, one MSE over all windows)."""
    [out] = evaluate_window_counts(field, train_set, views, [n_windows], windows=windows, truth=truth,
                                   truth_metrics=[truth_metrics], **kw)
    return out


def evaluate_window_counts(field, train_set, views, counts, *, box, n_samples: int,
                           log_eps: float, near: float = 0.0, far: float = float("inf"),
                           background: float = 0.0, occupancy=None, dynamic=None, windows=None, truth=None,
                           truth_metrics=None, static_world: str = "field", camera_grid: bool = True,
                           pixel_samples: int = 1) -> list:
    """``evaluate_views`` at each window count of ``counts`` (one (pred, gt, metrics) each),
    rendering the field and the true scene once per distinct window end of a view across the
    counts (``eval.windows``).  ``static_world``: auto, field or flat (module docstring; flat
    needs ``dynamic``); ``truth_metrics``: None or one earlier truth score (or None) per count.
    ``camera_grid``: a view whose camera drew the scene only on a grid of frame times (the virtual
    rig's twin, ``TrainingSet.frame_grid``) sees the field as that camera would: the frames around
    each window edge joined linearly in log, as the true-scene reference renders it (False: the
    field at the exact edge times)."""
    if static_world not in ("auto", "field", "flat"):
        raise InputError(f"static_world must be auto, field or flat, got {static_world!r}")
    if static_world == "flat" and dynamic is None:
        raise InputError("static_world flat keeps only the run's dynamic region, and this run has none; "
                         "use field or auto")
    t0, t1 = train_set.time_range
    scored = [scored_windows(t0, t1, int(n), windows) for n in counts]
    spans = [(int(edges[k]), int(edges[k + 1])) for edges, ks in scored for k in ks]
    splits = np.cumsum([len(ks) for _, ks in scored])[:-1]
    truth_metrics = list(truth_metrics) if truth_metrics is not None else [None] * len(counts)
    score_truth = truth is not None and any(tm is None for tm in truth_metrics)
    preds, gts, trues = [[] for _ in counts], [[] for _ in counts], [[] for _ in counts]
    for v in views:
        cam = camera_of(train_set.K(v), train_set.width, train_set.height)
        track = train_set.poses(v)
        pose_at = None if track is None else PoseTrack(*track, source=f"{train_set.path}: view {v} poses")
        flat = resolve_static_world(static_world, moving=pose_at is not None, has_region=dynamic is not None) == "flat"
        if pose_at is None:
            # a static camera: the pose's samples, the static field and the dynamic samples' space
            # features are planned once (the publisher's renderer), so each time costs only the
            # dynamic samples' time lookup (3.6x faster than rendering each time afresh; the same
            # images to 2.4e-7)
            static_camera = FieldRenderer(field, cam, box, duration_ns=int(t1 - t0), t_origin_ns=int(t0),
                                          n_samples=n_samples, near=near, far=far, background=background,
                                          occupancy=occupancy, dynamic=dynamic,
                                          static_world="flat" if flat else "field", pixel_samples=pixel_samples,
                                          source=f"{train_set.path}: view {v}")
            T = train_set.pose(v)

            def render(t: int):
                return static_camera.render(T, t)
        else:
            flat_grey = flat_background(field, background) if flat else None

            def render(t: int):
                tn = float(train_set.normalized_time(np.array([t], np.int64))[0])
                return render_image(field, cam, pose_at(t), tn, box, n_samples, near=near, far=far,
                                    background=background, occupancy=occupancy, dynamic=dynamic,
                                    flat_background=flat_grey, pixel_samples=pixel_samples)

        def log_render(t: int) -> np.ndarray:
            b = render(t)
            return np.log(np.asarray(b.detach().cpu().numpy() if hasattr(b, "detach") else b, np.float64) + log_eps)

        grid = train_set.frame_grid(v) if camera_grid else None
        log_image = log_render if grid is None else on_render_grid(log_render, *grid)
        changes = np.split(np.stack(window_changes(log_image, spans)).astype(np.float32), splits)
        true = np.split(truth.log_changes(v, spans), splits) if score_truth else [None] * len(counts)
        for c, (edges, ks) in enumerate(scored):
            preds[c].append(changes[c])
            gts[c].append(train_set.log_change_stack(v, edges)[ks])
            trues[c].append(true[c])
    c_pos, c_neg = train_set.thresholds
    out = []
    for c in range(len(counts)):
        pred, gt = np.concatenate(preds[c]), np.concatenate(gts[c])
        m = event_metrics(pred, gt, c_pos=c_pos, c_neg=c_neg)
        if truth is not None:
            tm = truth_metrics[c] or event_metrics(np.concatenate(trues[c]), gt, c_pos=c_pos, c_neg=c_neg)
            m["truth"] = tm
            floor = m["zero_floor"]["psnr"]
            m["margin_closed"] = {kind: margin_closed(m[kind]["psnr"], floor, tm[kind]["psnr"])
                                  for kind in ("continuous", "quantized")}
            # one MSE over all windows: defined where the per-window mean is not (a sparse set's
            # empty windows give the floor the 100 dB cap, and the true scene too rarely beats it)
            m["margin_closed"]["pooled"] = margin_closed(m["continuous"]["psnr_pooled"],
                                                         m["zero_floor"]["psnr_pooled"],
                                                         tm["continuous"]["psnr_pooled"])
        m["per_view"] = per_view_scores(views, preds[c], gts[c], trues[c], m["data_range"])
        out.append((pred, gt, m))
    return out


def per_view_scores(views, preds, gts, trues, data_range: float) -> dict:
    """{view: pooled events-PSNR of the field, the all-zero floor and (where its images were
    rendered) the true scene, and the margin closed}, each view's windows pooled and scored with
    the split's ``data_range``: which viewpoints a field gets wrong (a side of the object no
    training view lights, a camera far from every training view)."""
    out = {}
    for v, pred, gt, true in zip(views, preds, gts, trues):
        scores = {"psnr_pooled": psnr(pred, gt, data_range),
                  "zero_floor_pooled": psnr(np.zeros_like(gt), gt, data_range)}
        if true is not None:
            scores["truth_pooled"] = psnr(true, gt, data_range)
            scores["margin_closed_pooled"] = margin_closed(scores["psnr_pooled"], scores["zero_floor_pooled"],
                                                           scores["truth_pooled"])
        out[str(v)] = scores
    return out


def validation_eval(*, n_windows: int | None = None, max_views: int | None = None):
    """An `eval_fn(field, ctx)` for the trainer: val_psnr, its zero floor, SSIM, MAE, quantised PSNR.

    `n_windows` defaults to the trainer's current window count; `max_views` bounds the cost
    (that many validation views, spread evenly over the set: ``spread_views``).
    """
    truths: dict = {}       # the true scene's score per (views, windows): it never changes

    def eval_fn(field, ctx) -> dict:
        ts = ctx["train_set"]
        views = spread_views(static_views(ts, ts.val_views) or ts.train_views, max_views)
        windows = n_windows or ctx["windows"]
        if "scene" not in truths:
            truths["scene"] = TrueScene.of(ts)[0]
        key = (tuple(views), windows)
        _, _, m = evaluate_views(field, ts, views, windows, box=ctx["box"],
                                 n_samples=ctx["n_samples"], log_eps=ctx["log_eps"],
                                 near=ctx["near"], far=ctx["far"], background=ctx["background"],
                                 occupancy=ctx["occupancy"], dynamic=ctx.get("dynamic"),
                                 pixel_samples=ctx.get("pixel_samples", 1),
                                 truth=truths["scene"], truth_metrics=truths.get(key))
        out = {"val_psnr": m["continuous"]["psnr"], "val_psnr_zero_floor": m["zero_floor"]["psnr"],
               "val_psnr_quantized": m["quantized"]["psnr"], "val_ssim": m["continuous"]["ssim"],
               "val_mae": m["continuous"]["mae"], "val_views": len(views)}
        if "truth" in m:
            truths[key] = m["truth"]
            out.update(val_psnr_truth=m["truth"]["continuous"]["psnr"],
                       val_psnr_truth_quantized=m["truth"]["quantized"]["psnr"],
                       val_margin_closed=m["margin_closed"]["continuous"],
                       val_margin_closed_quantized=m["margin_closed"]["quantized"],
                       val_psnr_pooled=m["continuous"]["psnr_pooled"],
                       val_psnr_zero_floor_pooled=m["zero_floor"]["psnr_pooled"],
                       val_psnr_truth_pooled=m["truth"]["continuous"]["psnr_pooled"],
                       val_margin_closed_pooled=m["margin_closed"]["pooled"])
        return out

    return eval_fn


def intensity_renders(field, train_set, view, *, box, n_samples: int, near: float = 0.0,
                      far: float = float("inf"), background: float = 0.0, dynamic=None,
                      times: int = 3, pixel_samples: int = 1) -> dict:
    """Grey and depth renders of a static view at ``times`` of its blurred frames' mid-exposure
    times, each brightness-aligned (log space: a gain and gamma) to its frame, as in the
    paper's supplement: events fix intensity only up to that.  Returns {t_ns, frames, grey
    (aligned), depth, psnr (aligned grey vs frame, data range 1; the frames are motion-blurred
    so this is a rough check)}; None when the view has no frames."""
    fr = train_set.frames(view)
    if fr is None or not len(fr["t"]):
        return None
    cam = camera_of(train_set.K(view), train_set.width, train_set.height)
    T = train_set.pose(view)
    t0, t1 = train_set.time_range
    inside = np.flatnonzero((fr["t"] >= t0) & (fr["t"] < t1))
    if not inside.size:
        return None
    pick = inside[np.unique(np.linspace(0, inside.size - 1, times).round().astype(int))]
    out = {"t_ns": fr["t"][pick].tolist(), "frames": [], "grey": [], "depth": [], "psnr": []}
    for i in pick:
        tn = float(train_set.normalized_time(np.array([fr["t"][i]], np.int64))[0])
        grey, depth = (render_image(field, cam, T, tn, box, n_samples, near=near, far=far,
                                    background=background, dynamic=dynamic, key=key,
                                    pixel_samples=pixel_samples).cpu().numpy()
                       for key in ("grey", "depth"))
        frame = np.asarray(fr["frames"][i], np.float64)
        aligned, _, _ = brightness_align(np.clip(grey, 0, None), frame, space="log")
        out["frames"].append(frame)
        out["grey"].append(aligned)
        out["depth"].append(depth)
        out["psnr"].append(psnr(aligned, frame, data_range=1.0))
    return out


def static_views(train_set, views) -> list[str]:
    return [v for v in views if not train_set.info(v).moving]


def moving_views(train_set, views) -> list[str]:
    return [v for v in views if train_set.info(v).moving]


def spread_views(views, k: int | None) -> list[str]:
    """At most ``k`` of ``views`` (None or 0: all), evenly spread over the list, first and last
    included (a ring's views are in order: the first k would be neighbours, one arc of the ring;
    Jet-Down's first 4 of 18 validation views scored 72 % of the margin where all 18 score 68 %)."""
    views = list(views)
    if not k or k >= len(views):
        return views
    return [views[i] for i in np.unique(np.linspace(0, len(views) - 1, int(k)).round().astype(int))]


def run_eval(run_dir, train_h5, *, n_windows: int | None = None, max_views: int | None = None,
             train_views: int | None = 4, image_path=None, factors=(1, 4, 8), log=print, device="cpu",
             static_world: str = "auto") -> dict:
    """`evdnerf eval RUN TRAIN.h5`: events metrics on validation and training views at the
    trained window count and 4x / 8x finer windows; GT vs prediction event images.
    ``max_views`` bounds every split (that many of its views, spread evenly over it:
    ``spread_views``); ``train_views`` (None or 0: all) the training views scored, spread evenly
    too: they check the fit, the protocol's metric is the validation views'.
    ``device``: auto, cpu or cuda (``evdnerf_ros.device``): where the field is evaluated;
    ``static_world``: auto, field or flat (module docstring)."""
    import torch

    from ..device import resolve_device
    from ..io.trainingset import TrainingSet
    from ..train.run import TrainedRun
    from .figures import intensity_figure, side_by_side

    dev = resolve_device(device, f"{run_dir}: device")
    run = TrainedRun.load(run_dir)
    field, cfg, box, iteration = run.field.to(dev), run.config, run.box, run.iteration
    dynamic = None if run.dynamic is None else run.dynamic.to(dev)     # this load's own: moved once
    n = int(n_windows or cfg.windows[-1])
    result = {"run": str(run_dir), "train_set": str(train_h5), "iteration": iteration,
              "trained_windows": n, "device": str(dev), "static_world": static_world, "lpips": None,
              "lpips_note": "not computed: LPIPS needs AlexNet weights, which cannot be downloaded here"}
    with TrainingSet(train_h5) as ts, torch.no_grad():
        truth, why = TrueScene.of(ts)
        result["true_scene"] = truth.record["scene"] if truth is not None else None
        if truth is None:
            result["true_scene_note"] = why
        train_k = min(filter(None, (max_views, train_views)), default=None)     # None: every view
        splits = {"val": spread_views(static_views(ts, ts.val_views), max_views),
                  "train": spread_views(ts.train_views, train_k),
                  "moving": spread_views(moving_views(ts, ts.val_views), max_views)}
        for split, views in splits.items():
            if not views:
                continue
            # ground truth and prediction stacks of every window of every view, float32, plus metric copies
            # (every window count's stacks are held together: renders are shared across them)
            check_memory(4.0 * 4 * len(views) * n * sum(factors) * ts.width * ts.height,
                         f"{split}: {len(views)} views x {n * sum(factors)} windows of {ts.width}x{ts.height}",
                         "lower --windows or --max-views")
            scores = evaluate_window_counts(field, ts, views, [n * f for f in factors], box=box,
                                            n_samples=cfg.n_samples, log_eps=cfg.log_eps,
                                            near=cfg.near, far=cfg.far, background=cfg.background,
                                            dynamic=dynamic, truth=truth, static_world=static_world,
                                            pixel_samples=cfg.pixel_samples)
            for factor, (pred, gt, m) in zip(factors, scores):
                key = f"{split}_windows_x{factor}"
                result[key] = {name: {k: v for k, v in m[name].items() if k != "psnr_per_window"}
                               for name in ("continuous", "quantized", "zero_floor")}
                if "truth" in m:
                    result[key]["truth"] = {kind: {k: v for k, v in m["truth"][kind].items()
                                                   if k != "psnr_per_window"}
                                            for kind in ("continuous", "quantized")}
                    result[key]["margin_closed"] = m["margin_closed"]
                result[key]["views"] = len(views)
                result[key]["windows_per_view"] = int(pred.shape[0] // len(views))
                log(f"{key}: events PSNR {m['continuous']['psnr']:.2f} dB (quantised "
                    f"{m['quantized']['psnr']:.2f}, all-zero floor {m['zero_floor']['psnr']:.2f}), "
                    f"SSIM {m['continuous']['ssim']:.3f}, MAE {m['continuous']['mae']:.4f}" +
                    (f"; true scene {m['truth']['continuous']['psnr']:.2f} dB, margin closed "
                     f"{_percent(m['margin_closed']['continuous'])}; pooled: field "
                     f"{m['continuous']['psnr_pooled']:.2f}, floor {m['zero_floor']['psnr_pooled']:.2f}, "
                     f"true scene {m['truth']['continuous']['psnr_pooled']:.2f} dB, margin closed "
                     f"{_percent(m['margin_closed']['pooled'])}" if "truth" in m else ""))
                result[key]["per_view"] = m["per_view"]
                if len(views) > 1:
                    for v, pv in m["per_view"].items():
                        log(f"  {v}: pooled events PSNR {pv['psnr_pooled']:.2f} dB, floor {pv['zero_floor_pooled']:.2f}"
                            + (f", true scene {pv['truth_pooled']:.2f}, margin closed "
                               f"{_percent(pv['margin_closed_pooled'])}" if "truth_pooled" in pv else ""))
                if split == "val" and factor == 1 and image_path is not None:
                    side_by_side(gt, pred, image_path)
                    result["image"] = str(image_path)
        views = splits["val"] or splits["train"]
        renders = intensity_renders(field, ts, views[0], box=box, n_samples=cfg.n_samples,
                                    near=cfg.near, far=cfg.far, background=cfg.background,
                                    dynamic=dynamic, pixel_samples=cfg.pixel_samples) if views else None
        if renders is not None:
            result["intensity"] = {"view": views[0], "t_ns": renders["t_ns"],
                                   "aligned_psnr_vs_blurred_frames": renders["psnr"]}
            if image_path is not None:
                path = Path(image_path).with_name(Path(image_path).stem + "_intensity.png")
                intensity_figure(renders, path, title=f"view {views[0]}: blurred frame, "
                                 "brightness-aligned render, depth")
                result["intensity"]["image"] = str(path)
    return result


def _percent(fraction) -> str:
    return "n/a (no margin)" if fraction is None else f"{100 * fraction:.0f} %"
