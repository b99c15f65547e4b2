"""The training loop.

Per iteration: the schedule picks the crop warm-up (uniform rays from a centred crop for
the first ``crop_warmup_iters``), the window set (varied batching: ``windows[j]`` from
fraction ``window_switch[j-1]`` of the run on), the usable windows (time curriculum) and
the learning rate (linear warm-up); the sampler draws a ray batch of one window; both
window ends are rendered from the same samples (static-view reuse: ``render_rays`` with
[t0, t1]); dL_hat = log(B1 + eps) - log(B0 + eps) is compared with the GT dL; Adam steps
after global-norm gradient clipping.  With ``occupancy_resolution`` an occupancy grid
(max density over time) is refreshed every ``occupancy_every`` iterations after
``occupancy_warmup`` and skips empty samples.  A non-finite loss or gradient norm skips the step;
more than ``max_nonfinite_steps`` skips raise ``TrainingDivergedError``.

Run progress (for the schedules) is iteration / iters with an iteration budget, else
training seconds / (minutes * 60).  ``wall_s`` counts training seconds only (evaluation
and checkpoint writing excluded) and continues across resumes; ``elapsed_s`` is the same
including evaluation and checkpoints.

metrics.jsonl: one JSON object per ``eval_every`` iterations and at the end:
{iter, wall_s, elapsed_s, loss (mean since the previous line), lr, windows, skipped,
**eval_fn(field, context)}.

Interruption: Ctrl-C (SIGINT) and SIGTERM (which the CLI raises as a ``KeyboardInterrupt``)
are held while an iteration runs (``interrupts.DeferredInterrupts``), so they land between
iterations; ``train`` then writes a checkpoint of the last completed iteration (atomically)
and re-raises.  The checkpoint carries the loss sum since the last metrics line and whether
that iteration's line was still due, so a resumed run writes the same metrics.jsonl as an
uninterrupted one (wall-clock fields aside).  A second Ctrl-C during an iteration stops at
once and keeps the previous checkpoint.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import random
import time
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from ..errors import EvdnerfError, InputError
from ..field import DynamicRegion, OccupancyGrid, render_rays
from ..field.hinge import RESOLUTIONS as HINGE_RESOLUTIONS
from ..field.render import pixel_means
from ..limits import check_memory, check_number
from .checkpoint import (CheckpointError, global_rng_states, load_checkpoint, save_checkpoint,
                         set_global_rng_states)
from .auto import choose_backbone
from .config import AUTO, TrainConfig, _normal, field_from_config, resolve_config
from .joint import joint_from_training_set, part_box, part_box_pays
from .interrupts import DeferredInterrupts
from .losses import bin_loss, mse_loss, no_event_hinge
from .ranges import NUMBERS, carving_bytes, check_training_memory
from .run import TrainedRun, train_set_record
from .rundir import (CHECKPOINT_NAME, CONFIG_NAME, LOCK_NAME, METRICS_NAME, RunLock,
                     truncate_metrics, write_text)
from .rays import FrameSampler, RaySampler, default_box
from .thresholds import LearnedThresholds
from .track import track_from_events

DEFAULT_ITERS = 2000


class TrainingDivergedError(EvdnerfError):
    """Too many steps with a non-finite loss or gradient."""


def plane_regularisers(field, cfg: TrainConfig) -> torch.Tensor | None:
    """TV on space planes, time smoothness and L1(time planes - 1) (``planes`` only)."""
    if not hasattr(field, "space_planes") or not (cfg.tv_weight or cfg.time_smooth_weight
                                                  or cfg.time_l1_weight):
        return None
    total = torch.zeros((), device=field.time_planes[0].device)
    if cfg.tv_weight:
        for p in field.space_planes:
            total = total + cfg.tv_weight * (((p[..., 1:, :] - p[..., :-1, :]) ** 2).mean()
                                             + ((p[..., 1:] - p[..., :-1]) ** 2).mean())
    for p in field.time_planes:
        if cfg.time_smooth_weight and p.shape[2] >= 3:
            d2 = p[:, :, 2:] - 2 * p[:, :, 1:-1] + p[:, :, :-2]
            total = total + cfg.time_smooth_weight * (d2 ** 2).mean()
        if cfg.time_l1_weight:
            total = total + cfg.time_l1_weight * (p - 1.0).abs().mean()
    return total


class Trainer:
    def __init__(self, train_set, config=None, *, run_dir=None, iters: int | None = None,
                 minutes: float | None = None, eval_fn: Callable | None = None,
                 log: Callable = print, device="cpu"):
        """``device``: auto, cpu or cuda (``evdnerf_ros.device``): where the field, the
        batches and every grid live; a run-time choice, not part of the config, so a run may
        resume on another device."""
        from ..device import resolve_device

        self.cfg = resolve_config(config)
        cfg = self.cfg
        self.device = resolve_device(device, f"{run_dir or 'training'}: device")
        self.ts = train_set
        self.run_dir = Path(run_dir) if run_dir is not None else None
        self.log = log
        self.eval_fn = eval_fn
        iters = iters if iters is not None else (None if minutes is not None else cfg.iters)
        minutes = minutes if minutes is not None else (None if iters is not None else cfg.minutes)
        if iters is None and minutes is None:
            iters = DEFAULT_ITERS
        self.iters = check_budget(iters, "iters", "iters")
        self.minutes = check_budget(minutes, "minutes", "minutes")
        self.box = np.asarray(cfg.box, np.float64) if cfg.box is not None else \
            default_box(train_set, cfg.box_fraction)
        self.backbone_reason = None
        if cfg.backbone == AUTO:
            cfg = self.cfg = self._choose_backbone(cfg)
        # everything below allocates: size it first
        check_training_memory(cfg, views=len(train_set.train_views),
                              pixels=int(train_set.width) * int(train_set.height),
                              source=cfg.source)
        random.seed(cfg.seed)
        np.random.seed(cfg.seed % (1 << 32))
        torch.manual_seed(cfg.seed)
        self.dynamic = (DynamicRegion.from_event_footprint(
            train_set, self.box, resolution=cfg.dynamic_resolution,
            min_events=cfg.dynamic_min_events, dilate_px=cfg.dynamic_dilate_px,
            misses=cfg.dynamic_misses)
            if cfg.dynamic_region and cfg.supervision == "events" else None)
        # the set's joint (hinge) or the moving part's track (rigid) into a copy: a caller's
        # config object stays free of them
        if cfg.backbone == "hinge" and "joint" not in cfg.field:
            cfg = self.cfg = dataclasses.replace(
                cfg, field={**cfg.field, "joint": joint_from_training_set(train_set, self.box)})
        if cfg.part_box == "auto":
            finest = max(cfg.field.get("resolutions", HINGE_RESOLUTIONS))
            cfg = self.cfg = dataclasses.replace(cfg, part_box=self.dynamic is not None and part_box_pays(
                train_set, self.box, cfg.field["joint"], finest))
        if cfg.part_box and "part_box" not in cfg.field["joint"]:
            box = part_box(cfg.field["joint"], self.dynamic.mask.numpy())
            if box is None:
                raise InputError(f"{cfg.source}: part_box: the dynamic region is empty (no training view saw the "
                                 "part move), so no box holds the part; set part_box: false")
            cfg = self.cfg = dataclasses.replace(
                cfg, field={**cfg.field, "joint": {**cfg.field["joint"], "part_box": box}})
        if cfg.backbone == "rigid" and "track" not in cfg.field:
            cfg = self.cfg = dataclasses.replace(cfg, field={**cfg.field, "track": track_from_events(
                train_set, self.box, resolution=cfg.dynamic_resolution, min_events=cfg.dynamic_min_events,
                dilate_px=cfg.dynamic_dilate_px, misses=cfg.dynamic_misses)})
        self.field = field_from_config(cfg).to(self.device)
        groups = [{"params": [p for p in params if p.requires_grad], "lr_scale": scale}
                  for params, scale in self.field.param_groups()]
        self.params = [p for g in groups for p in g["params"]]
        self.c_pos, self.c_neg = (float(c) for c in train_set.thresholds)
        self.thresholds = None
        if cfg.learn_thresholds:
            self.thresholds = LearnedThresholds(self.c_pos, self.c_neg).to(self.device)
            groups.append({"params": list(self.thresholds.parameters()),
                           "lr_scale": cfg.threshold_lr / cfg.lr})
            self.params = self.params + list(self.thresholds.parameters())
        self.opt = torch.optim.Adam(groups, lr=cfg.lr)
        self.gen = torch.Generator(self.device).manual_seed(cfg.seed + 1)
        self.occupancy = (OccupancyGrid(cfg.occupancy_resolution).to(self.device)
                          if cfg.occupancy_resolution else None)
        self.sampler = RaySampler(train_set, event_ray_fraction=cfg.event_ray_fraction, camera_grid=cfg.camera_grid,
                                  seed=cfg.seed, dynamic=self.dynamic, box=self.box,
                                  keep_counts=cfg.learn_thresholds, pixel_samples=cfg.pixel_samples).to(self.device)
        if self.dynamic is not None:     # after the sampler picked its rays on the host
            self.dynamic.to(self.device)
        self.frame_sampler = (FrameSampler(train_set, seed=cfg.seed).to(self.device)
                              if cfg.supervision == "frames" else None)
        self.iteration = 0
        self.train_s = 0.0
        self.elapsed_s = 0.0
        self.skipped = 0
        self.last_loss = float("nan")
        self._loss_sum, self._loss_n = 0.0, 0    # losses since the last metrics line
        self._metrics_due = False      # this iteration's metrics line is not written yet
        self._mid_step = False         # an iteration is under way (state not consistent)

    def _choose_backbone(self, cfg: TrainConfig) -> TrainConfig:
        """``backbone: auto`` resolved from the training set (``train/auto.py``), logged."""
        r = cfg.dynamic_resolution                  # the track is carved before the field is sized
        check_memory(carving_bytes(r), f"{cfg.source}: backbone auto's track of the moving part ({r}^3 voxels)",
                     "lower dynamic_resolution")
        name, why, found = choose_backbone(self.ts, self.box, cfg)
        self.backbone_reason = why
        self.log(f"backbone auto: {name}, because {why}")
        try:
            return cfg.with_backbone(name, **found)
        except InputError as exc:
            raise InputError(f"{exc} (backbone auto chose {name}, because {why}; name the backbone "
                             "these options belong to)") from None

    # ------------------------------------------------------------------ schedules
    def progress(self) -> float:
        if self.iters is not None:
            return self.iteration / self.iters
        return self.train_s / (self.minutes * 60.0)

    def n_windows(self, progress: float | None = None) -> int:
        p = self.progress() if progress is None else progress
        j = sum(1 for f in self.cfg.window_switch if p >= f)
        return int(self.cfg.windows[j])

    def usable_windows(self, n: int, progress: float | None = None) -> int:
        cfg = self.cfg
        p = self.progress() if progress is None else progress
        if cfg.time_curriculum <= 0 or p >= cfg.time_curriculum:
            return n
        return max(min(cfg.time_curriculum_min, n), int(math.ceil(p / cfg.time_curriculum * n)))

    def lr(self) -> float:
        """Linear warm-up over ``lr_warmup_iters``, then exponential decay with run progress
        to ``lr_final`` x lr at the end of the budget."""
        cfg = self.cfg
        if cfg.lr_warmup_iters > 0 and self.iteration < cfg.lr_warmup_iters:
            f = cfg.lr_warmup_start + (1.0 - cfg.lr_warmup_start) * self.iteration / cfg.lr_warmup_iters
            return cfg.lr * f
        if cfg.lr_final >= 1.0:
            return cfg.lr
        return cfg.lr * cfg.lr_final ** min(1.0, max(0.0, self.progress()))

    def done(self) -> bool:
        if self.iters is not None and self.iteration >= self.iters:
            return True
        return self.minutes is not None and self.train_s >= self.minutes * 60.0

    # ------------------------------------------------------------------ one step
    def compute_loss(self, batch):
        cfg = self.cfg
        if self.frame_sampler is not None:
            r = render_rays(self.field, batch.origins, batch.dirs, batch.t, self.box, cfg.n_samples,
                            near=cfg.near, far=cfg.far, background=cfg.background,
                            perturb=cfg.perturb, generator=self.gen, occupancy=self.occupancy)
            loss = ((r["grey"] - batch.grey) ** 2).mean()
            reg = plane_regularisers(self.field, cfg)
            return loss if reg is None else loss + reg
        dl_hat = self.predicted_change(batch)
        c_pos, c_neg, dl = self.c_pos, self.c_neg, batch.dl
        if self.thresholds is not None:
            c_pos, c_neg = self.thresholds()
            dl = self.thresholds.log_change(batch.counts)
        if cfg.loss == "mse":
            loss = mse_loss(dl_hat, dl, cfg.mse_pred_scale, cfg.mse_target_scale)
        else:
            loss = bin_loss(dl_hat, dl, c_pos, c_neg, paper=cfg.loss == "bin_paper")
        if cfg.no_event_weight:
            loss = loss + cfg.no_event_weight * no_event_hinge(dl_hat, dl, c_pos, c_neg,
                                                                ~batch.on_event)
        reg = plane_regularisers(self.field, cfg)
        if reg is not None:
            loss = loss + reg
        if cfg.empty_weight:
            loss = loss + cfg.empty_weight * self.empty_prior()
        if cfg.part_empty_weight:
            loss = loss + cfg.part_empty_weight * self.part_empty_prior()
        return loss

    def predicted_change(self, batch) -> torch.Tensor:
        """(N,) the field's log change of each ray over the batch's window: a static view's ray
        rendered at both edges from shared samples (only what can change, with a dynamic region),
        a moving view's as two rays, the world whole (it sweeps past the camera)."""
        cfg = self.cfg
        render = functools.partial(
            render_rays, self.field, box=self.box, n_samples=cfg.n_samples, near=cfg.near,
            far=cfg.far, background=cfg.background, perturb=cfg.perturb, generator=self.gen,
            occupancy=self.occupancy, dynamic=self.dynamic)

        def log(r):                    # a pixel's brightness: its sub-pixel rays' mean
            return torch.log(pixel_means(r["grey"], batch.pixel_samples) + cfg.log_eps)

        def static_change(o, d):
            static = functools.partial(render, o.reshape(-1, 3), d.reshape(-1, 3),
                                       changes_only=self.dynamic is not None)
            if batch.grid_times is not None:
                # a frame-based camera: its log image at a window edge joins the frames around it
                times = list(batch.grid_times)
                logs = [log(r) for r in (static(times) if cfg.sample_reuse else [static(t) for t in times])]
                w0, w1 = batch.grid_weights
                return torch.lerp(logs[2], logs[3], w1) - torch.lerp(logs[0], logs[1], w0)
            r0, r1 = static([batch.t0, batch.t1]) if cfg.sample_reuse else (static(batch.t0), static(batch.t1))
            return log(r1) - log(r0)

        if batch.moving is None:
            return static_change(batch.origins, batch.dirs)
        dl_hat = torch.zeros(batch.origins.shape[0], dtype=torch.float32, device=batch.origins.device)
        moving = torch.nonzero(batch.moving, as_tuple=False).squeeze(1)
        fixed = torch.nonzero(~batch.moving, as_tuple=False).squeeze(1)
        if fixed.numel():
            dl_hat = dl_hat.index_put((fixed,), static_change(batch.origins[fixed], batch.dirs[fixed]))
        if moving.numel():
            r0 = render(batch.origins[moving].reshape(-1, 3), batch.dirs[moving].reshape(-1, 3), batch.t0)
            r1 = render(batch.origins_end[moving].reshape(-1, 3), batch.dirs_end[moving].reshape(-1, 3), batch.t1)
            dl_hat = dl_hat.index_put((moving,), log(r1) - log(r0))
        return dl_hat

    def _random_points(self) -> torch.Tensor:
        return torch.rand(self.cfg.empty_points, 3, generator=self.gen, device=self.device) * 2.0 - 1.0

    def _mean_opacity(self, density: torch.Tensor) -> torch.Tensor:
        """Mean opacity of ``density`` over one sample's length (box diagonal / n_samples)."""
        step = float(np.linalg.norm(self.box[1] - self.box[0])) / self.cfg.n_samples
        return (-torch.expm1(-density * step)).mean()

    def empty_prior(self) -> torch.Tensor:
        """The static field's mean opacity at ``empty_points`` uniform random points of the box
        (``empty_weight``)."""
        density, _ = self.field.decode_static(self.field.space_features(self._random_points()))
        return self._mean_opacity(density)

    def part_empty_prior(self) -> torch.Tensor:
        """The moving part's mean opacity over the scene box at ``empty_points`` uniform random
        points of its own frame, each at a uniform random time (``part_empty_weight``)."""
        x = self._random_points()
        t = torch.rand(x.shape[0], generator=self.gen, device=self.device)
        # over the scene box: a part bounded to its own box is empty outside it
        return self._mean_opacity(self.field.part_density(x, t)) * self.field.part_volume_fraction

    def step(self) -> float | None:
        """One iteration; returns the loss, or None when the step was skipped."""
        cfg = self.cfg
        n = self.n_windows()
        self.sampler.set_windows(n)
        lr = self.lr()
        for g in self.opt.param_groups:
            g["lr"] = lr * g["lr_scale"]
        crop = cfg.crop_fraction if self.iteration < cfg.crop_warmup_iters else None
        if self.frame_sampler is not None:
            batch = self.frame_sampler.sample(cfg.rays)
        else:
            batch = self.sampler.sample(cfg.rays, usable_windows=self.usable_windows(n), crop=crop,
                                        span_fraction=cfg.span_fraction)
        if (self.occupancy is not None and self.iteration >= cfg.occupancy_warmup
                and (self.iteration - cfg.occupancy_warmup) % cfg.occupancy_every == 0):
            self.occupancy.update(self.field, threshold=cfg.occupancy_threshold)
        self.opt.zero_grad(set_to_none=True)
        loss = self.compute_loss(batch)
        value = float(loss.detach())
        ok = math.isfinite(value)
        if ok and not loss.requires_grad:
            # nothing in this batch depends on the field (every ray crosses no dynamic
            # voxel): a valid step that changes nothing
            self.iteration += 1
            self.last_loss = value
            return value
        if ok:
            loss.backward()
            clip = cfg.grad_clip if cfg.grad_clip > 0 else float("inf")
            norm = torch.nn.utils.clip_grad_norm_(self.params, clip)
            ok = bool(torch.isfinite(norm))
        self.iteration += 1
        if not ok:
            self.opt.zero_grad(set_to_none=True)
            self.skipped += 1
            if self.skipped > cfg.max_nonfinite_steps:
                raise TrainingDivergedError(
                    f"training diverged: {self.skipped} steps had a non-finite loss or gradient "
                    f"(limit max_nonfinite_steps={cfg.max_nonfinite_steps}, last at iteration "
                    f"{self.iteration}); lower lr, raise log_eps or check the training set")
            return None
        self.opt.step()
        self.last_loss = value
        return value

    # ------------------------------------------------------------------ state
    def rng_state(self) -> dict:
        return {"global": global_rng_states(), "sampler": self.sampler.rng.bit_generator.state,
                "perturb": self.gen.get_state(), "perturb_device": self.device.type,
                "frames": None if self.frame_sampler is None
                else self.frame_sampler.rng.bit_generator.state}

    def save(self, path=None) -> Path:
        path = Path(path) if path is not None else self.run_dir / CHECKPOINT_NAME
        return save_checkpoint(path, field=self.field, optimizer=self.opt,
                               iteration=self.iteration, config=self.cfg.to_dict(),
                               backbone=self.cfg.backbone, rng=self.rng_state(), box=self.box,
                               extra={"occupied": None if self.occupancy is None
                                      else self.occupancy.occupied.clone(),
                                      "dynamic": None if self.dynamic is None
                                      else self.dynamic.mask.clone(),
                                      "train_s": self.train_s, "elapsed_s": self.elapsed_s,
                                      "thresholds": None if self.thresholds is None
                                      else self.thresholds.state_dict(),
                                      "skipped": self.skipped, "iters": self.iters,
                                      "minutes": self.minutes, "loss_sum": self._loss_sum,
                                      "loss_n": self._loss_n,
                                      "metrics_due": self._metrics_due,
                                      "last_loss": self.last_loss,
                                      "train_set": train_set_record(self.ts)})

    def resume(self, path, data: "dict | TrainedRun | None" = None) -> None:
        """Continue from a checkpoint of this very run (same config); ``data``: the
        checkpoint (or the ``TrainedRun``) already read from ``path``."""
        path = Path(path)
        run = data if isinstance(data, TrainedRun) else TrainedRun(
            path.parent, load_checkpoint(path) if data is None else data, checkpoint_path=path)
        data = run.checkpoint
        theirs = run.config
        diff = self.cfg.diff(theirs)
        if diff:
            their = data["config"]
            what = "; ".join(f"{k}: {their.get(k)!r} there, {getattr(self.cfg, k)!r} here"
                             for k in diff)
            raise CheckpointError(
                f"{path}: the checkpoint's config differs in {', '.join(diff)} ({what}); "
                "resume with the checkpoint's config, or start a new run")
        self.field.load_state_dict(data["field"])
        self.opt.load_state_dict(data["optimizer"])
        self.box = run.box
        self.iteration = run.iteration
        ex = run.extra
        self.train_s = float(ex.get("train_s", 0.0))
        self.elapsed_s = float(ex.get("elapsed_s", self.train_s))
        self.skipped = int(ex.get("skipped", 0))
        self._loss_sum = float(ex.get("loss_sum", 0.0))
        self._loss_n = int(ex.get("loss_n", 0))
        self._metrics_due = bool(ex.get("metrics_due", False))
        self.last_loss = float(ex.get("last_loss", float("nan")))
        if self.occupancy is not None and run.occupancy is not None:
            self.occupancy.occupied = run.occupancy.occupied.to(self.device)
        if self.thresholds is not None:
            self.thresholds.load_state_dict(ex["thresholds"])
        if run.dynamic is not None:
            self.dynamic = run.dynamic.to(self.device)
        rng = data["rng"]
        set_global_rng_states(rng["global"])
        self.sampler.rng.bit_generator.state = rng["sampler"]
        if self.frame_sampler is not None:
            self.frame_sampler.rng.bit_generator.state = rng["frames"]
        if rng.get("perturb_device", "cpu") == self.device.type:
            self.gen.set_state(rng["perturb"])
        else:
            # a CPU and a CUDA generator's states do not convert: the sample jitter restarts
            # from a seed of its own (the run goes on, no longer bit-exact with one device)
            self.gen.manual_seed(self.cfg.seed + 1 + self.iteration)
            self.log(f"{path}: trained on {rng.get('perturb_device', 'cpu')}, resumed on {self.device.type}: "
                     "the sample jitter is reseeded (the resumed run is not bit-exact)")

    def init_from(self, path) -> None:
        """Weights only (the paper's fork -> knife transfer); optimiser and counters fresh."""
        data = load_checkpoint(path)
        cfg = data.get("config") if isinstance(data.get("config"), dict) else {}
        if (data.get("backbone") != self.cfg.backbone
                or _normal(cfg.get("field", {})) != _normal(self.cfg.field)):
            raise CheckpointError(
                f"{path}: needs the same backbone and field sizes as this run (checkpoint: "
                f"{data.get('backbone')} {cfg.get('field')}; here: {self.cfg.backbone} {self.cfg.field})")
        try:
            self.field.load_state_dict(data["field"])
        except RuntimeError as exc:
            raise CheckpointError(f"{path}: weights do not fit this field ({exc})") from None

    # ------------------------------------------------------------------ loop
    def _metrics_line(self) -> dict:
        line = {"iter": self.iteration, "wall_s": round(self.train_s, 6),
                "elapsed_s": round(self.elapsed_s, 6),
                "loss": self._loss_sum / self._loss_n if self._loss_n else None,
                "lr": self.lr(), "windows": self.n_windows(), "skipped": self.skipped}
        if self.thresholds is not None:
            line["c_pos"], line["c_neg"] = self.thresholds.values()
        if self.eval_fn is not None:
            ctx = {"train_set": self.ts, "box": self.box, "n_samples": self.cfg.n_samples,
                   "pixel_samples": self.cfg.pixel_samples,
                   "near": self.cfg.near, "far": self.cfg.far, "background": self.cfg.background,
                   "log_eps": self.cfg.log_eps, "iteration": self.iteration,
                   "windows": self.n_windows(), "occupancy": self.occupancy,
                   "dynamic": self.dynamic}
            was = self.field.training
            self.field.eval()
            with torch.no_grad():
                extra = self.eval_fn(self.field, ctx) or {}
            self.field.train(was)
            line.update({k: (float(v) if isinstance(v, (np.floating, np.integer)) else v)
                         for k, v in extra.items()})
        return line

    def _write_metrics(self, line: dict) -> None:
        if self.run_dir is None:
            return
        with open(self.run_dir / METRICS_NAME, "a") as f:
            f.write(json.dumps(_finite(line), allow_nan=False, default=float) + "\n")

    def _emit_metrics(self) -> None:
        """The due metrics line: computed (evaluation may take a while and stays
        interruptible), then written and marked done as one step."""
        line = self._metrics_line()
        with DeferredInterrupts():
            self._write_metrics(line)
            self._loss_sum, self._loss_n = 0.0, 0
            self._metrics_due = False

    def _log_progress(self) -> None:
        it = self.iteration
        rate = (self.train_s / it) if it else 0.0
        if self.iters is not None:
            eta = rate * (self.iters - it)
        else:
            eta = max(0.0, self.minutes * 60 - self.train_s)
        self.log(f"iter {it}{'/' + str(self.iters) if self.iters else ''}  "
                 f"loss {self.last_loss:.5g}  lr {self.lr():.3g}  windows {self.n_windows()}  "
                 f"skipped {self.skipped}  {1000 * rate:.0f} ms/it  ETA {eta:.0f} s")

    def train(self, until: int | None = None) -> dict:
        """Run until the budget (or iteration ``until``) is reached; writes metrics and
        checkpoints into ``run_dir`` when set.  On KeyboardInterrupt (Ctrl-C, SIGTERM via
        the CLI) a checkpoint of the last completed iteration is written, then it re-raises."""
        cfg = self.cfg
        t_wall = time.perf_counter()
        elapsed0 = self.elapsed_s
        save_due = False

        def clock():
            self.elapsed_s = elapsed0 + time.perf_counter() - t_wall

        try:
            while True:
                if self._metrics_due:
                    self._emit_metrics()
                    clock()
                if save_due:
                    self.save()
                    save_due = False
                if self.done() or (until is not None and self.iteration >= until):
                    break
                with DeferredInterrupts():
                    self._mid_step = True
                    t0 = time.perf_counter()
                    value = self.step()
                    self.train_s += time.perf_counter() - t0
                    clock()
                    if value is not None:
                        self._loss_sum += value
                        self._loss_n += 1
                    it = self.iteration
                    self._metrics_due = bool(cfg.eval_every and it % cfg.eval_every == 0) or self.done()
                    save_due = bool(self.run_dir is not None and cfg.checkpoint_every
                                    and it % cfg.checkpoint_every == 0 and not self.done())
                    self._mid_step = False
                if cfg.log_every and self.iteration % cfg.log_every == 0:
                    self._log_progress()
        except KeyboardInterrupt:
            if self.run_dir is not None and not self._mid_step:
                clock()
                path = self.save()
                self.log(f"interrupted: checkpoint of iteration {self.iteration} written to {path}; "
                         "run the same command again to resume")
            raise
        clock()
        ckpt = self.save() if self.run_dir is not None else None
        return {"iterations": self.iteration, "wall_s": self.train_s, "elapsed_s": self.elapsed_s,
                "loss": self.last_loss, "skipped": self.skipped,
                "checkpoint": str(ckpt) if ckpt else None, "box": self.box.tolist(),
                "device": str(self.device)}


def check_budget(value, name: str, key: str):
    """``iters`` / ``minutes`` (named as the caller knows them) in the config's range."""
    low, high, kind, low_open = NUMBERS[key]
    value = check_number(value, name, low=low, high=high, low_open=low_open,
                         integer=kind == "int", allow_none=True)
    if value is None:
        return None
    return int(value) if kind == "int" else float(value)


def _finite(obj):
    """JSON-safe copy: non-finite floats become None (metrics.jsonl stays strict JSON)."""
    if isinstance(obj, dict):
        return {str(k): _finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_finite(v) for v in obj]
    if isinstance(obj, (float, np.floating)):
        return float(obj) if math.isfinite(float(obj)) else None
    if isinstance(obj, np.integer):
        return int(obj)
    return obj


# ---------------------------------------------------------------------- entry point
def run_train(train_h5, run_dir, *, config=None, minutes: float | None = None,
              iters: int | None = None, init=None, overwrite: bool = False,
              log: Callable = print, eval_fn: Callable | None = None, device="auto") -> dict:
    """Train on TRAIN.h5 into RUN (``evdnerf train``).

    RUN holds config.yaml, checkpoint.pt, metrics.jsonl and the lock file
    ``.evdnerf-train.lock`` (``rundir``): while a run lasts a second one into RUN fails at
    once.  A RUN with a checkpoint is resumed (its config is used when ``config`` is None;
    a different one is an error) and metrics.jsonl cut back to the checkpoint's iteration.
    A RUN that ``train`` made but that holds no checkpoint yet (a first start stopped
    early) starts again from iteration 0, replacing only those files.  ``overwrite`` starts
    afresh likewise, and the old files go only once the new run is built, so a bad config
    or training set destroys nothing.  ``init``: a checkpoint whose weights start the new
    run (fork -> knife transfer).  ``iters`` is the run's total iteration count (also on
    resume); ``minutes`` its total training minutes (both range-checked as ``--iters`` /
    ``--minutes``).  Ctrl-C or SIGTERM writes a checkpoint first (``Trainer.train``): the
    same command again resumes.  ``device``: auto, cpu or cuda (``evdnerf_ros.device``;
    checked before RUN is touched); checkpoints are device-independent.
    """
    from ..device import resolve_device

    iters = check_budget(iters, "--iters", "iters")
    minutes = check_budget(minutes, "--minutes", "minutes")
    run_dir = Path(run_dir)
    if run_dir.exists() and not run_dir.is_dir():
        raise InputError(f"{run_dir}: exists and is not a folder; choose a folder for the run")
    given = None if config is None else resolve_config(config)   # checked before RUN is touched
    device = resolve_device(device, "--device")
    created = not run_dir.exists()
    run_dir.mkdir(parents=True, exist_ok=True)
    with RunLock(run_dir, log=log) as lock:
        try:
            return _train_locked(train_h5, run_dir, lock, given, iters=iters, minutes=minutes,
                                 init=init, overwrite=overwrite, log=log, eval_fn=eval_fn,
                                 device=device)
        except BaseException:
            if created:
                _remove_if_empty(run_dir, lock)
            raise


def _remove_if_empty(run_dir: Path, lock: RunLock) -> None:
    """A run folder this call made and that holds nothing but the lock: leave none behind."""
    try:
        if [q.name for q in run_dir.iterdir()] == [LOCK_NAME]:
            lock.path.unlink()
            run_dir.rmdir()
    except OSError:
        pass


def _train_locked(train_h5, run_dir: Path, lock: RunLock, given, *, iters, minutes, init,
                  overwrite, log, eval_fn, device) -> dict:
    from ..io.trainingset import TrainingSet

    ckpt, metrics, config_path = (run_dir / n for n in (CHECKPOINT_NAME, METRICS_NAME, CONFIG_NAME))
    for p in (ckpt, metrics, config_path):
        if (p.exists() or p.is_symlink()) and not p.is_file():
            raise InputError(f"{p}: is not a regular file; remove it or choose another run folder")
    resume = ckpt.is_file() and not overwrite
    leftovers = [p.name for p in (config_path, metrics) if p.exists()]
    if not resume and not overwrite and leftovers and not lock.made_by_train:
        raise InputError(f"{run_dir}: holds {' and '.join(leftovers)} but no {CHECKPOINT_NAME}, and "
                         f"`evdnerf train` did not make this folder (no {LOCK_NAME}); remove them, "
                         "pass --overwrite to replace them, or choose another folder")
    if resume and init is not None:
        raise InputError(f"{run_dir}: already holds a checkpoint to resume; --init starts a new run "
                         "(choose another RUN or pass --overwrite)")
    run = None
    if resume:
        try:
            run = TrainedRun.load(run_dir)
        except CheckpointError as exc:
            raise CheckpointError(f"{exc}; or pass --overwrite to start {run_dir} afresh") from None
    if given is not None:
        cfg = given
    elif resume:
        cfg = run.config
    else:
        cfg = TrainConfig()
    with TrainingSet(train_h5) as ts:
        tr = Trainer(ts, cfg, run_dir=run_dir, iters=iters, minutes=minutes, eval_fn=eval_fn,
                     log=log, device=device)
        if resume:
            tr.resume(ckpt, run)
            dropped = truncate_metrics(metrics, tr.iteration)
            log(f"resuming {run_dir} at iteration {tr.iteration}" + (
                f" (dropped {dropped} metrics lines from after that checkpoint)" if dropped else ""))
        else:
            if init is not None:
                try:
                    tr.init_from(init)
                except CheckpointError as exc:
                    raise CheckpointError(f"--init {exc}") from None
                log(f"initialised weights from {init}")
            if leftovers and not overwrite:
                log(f"{run_dir}: no checkpoint from the earlier start; starting again from iteration 0")
            # the old run's files go only now that the new run is built
            for p in (ckpt, metrics):
                if p.exists():
                    p.unlink()
        chosen = (f"# backbone: auto chose {tr.cfg.backbone}, because {tr.backbone_reason}\n"
                  if tr.backbone_reason else "")
        write_text(config_path, chosen + tr.cfg.dump())   # as trained (a hinge run: with its joint)
        summary = tr.train()
    summary.update({"run_dir": str(run_dir), "resumed": resume, "metrics": str(metrics),
                    "backbone": tr.cfg.backbone, "backbone_reason": tr.backbone_reason})
    return summary


__all__ = ["Trainer", "TrainingDivergedError", "run_train", "plane_regularisers"]
