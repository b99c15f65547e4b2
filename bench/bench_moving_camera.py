"""What the demo's moving camera sees: its true events taken apart by the scene's pieces, against the field.

The demo's simulated fork set (``bench_quality.py --demo``'s) has a validation camera that moves
(it sweeps 190-210 degrees round the fork).  Its margin is hard to close for a field trained on
four static views, and this script says why, in the evaluation protocol's own terms (32
windows, continuous events-PSNR, per window and pooled, the all-zero floor, the true scene as
100 %).  Each row is a predictor of that camera's (and, for comparison, the static validation
views') log changes, scored against the recorded events:

- the true scene with pieces left out (the simulator rendering a copy of the scene file): the
  fork alone over an untextured backdrop, the fork over the textured backdrop, the fork with the
  table and servo over an untextured backdrop, and the same with the table and servo untextured;
- the field, trained for ``--seconds`` (the demo's config and ``hinge`` backbone), rendered as
  ``evdnerf eval`` does (``static_world: auto``: a flat world for the moving camera).

The printout adds each predictor's change energy (sum of dL squared over the scored pixels and
windows) and the field's moving part's mean opacity over the dynamic region.

Usage: python bench/bench_moving_camera.py [--seconds 120] [--seed 0] [--work DIR]
       -> bench/results/moving_camera.{json,png}
"""

from __future__ import annotations

import copy
import time
from pathlib import Path

from _common import arg_parser, machine, pyplot, save_figure, write_results

#: name -> (objects left out, objects drawn without texture, backdrop without texture)
VARIANTS = {
    "fork alone, plain backdrop": (("table", "servo"), (), True),
    "fork, textured backdrop": (("table", "servo"), (), False),
    "fork, table, servo, plain backdrop": ((), (), True),
    "fork, plain table and servo, plain backdrop": ((), ("table", "servo"), True),
}


def scene_variant(base: dict, drop, plain, plain_backdrop: bool) -> dict:
    scene = copy.deepcopy(base)
    scene["objects"] = [o for o in scene["objects"] if o["name"] not in drop]
    for o in scene["objects"]:
        if o["name"] in plain:
            o.pop("texture", None)
    if plain_backdrop:
        scene.get("background", {}).pop("texture", None)
    return scene


def part_opacity(trainer, points: int = 20000) -> float:
    """The trained part's mean opacity over one sample's length at random points of the dynamic
    region, at random times (a solid fork fills ~3 % of the demo set's region)."""
    import torch

    gen = torch.Generator().manual_seed(0)
    cells = torch.nonzero(trainer.dynamic.mask, as_tuple=False).to(torch.float32)
    res = torch.tensor(trainer.dynamic.resolution, dtype=torch.float32)
    x = (cells[torch.randint(cells.shape[0], (points,), generator=gen)] + torch.rand(points, 3, generator=gen)) / res * 2 - 1
    with torch.no_grad():
        return float(trainer._mean_opacity(trainer.field.part_density(x, torch.rand(points, generator=gen))))


def score(train_set, trainer, truth, scene_files: dict, log) -> dict:
    import numpy as np
    import torch

    from evdnerf_ros.eval.evaluate import evaluate_views, moving_views, static_views
    from evdnerf_ros.eval.metrics import event_metrics
    from evdnerf_ros.eval.truth import TrueScene, margin_closed
    from evdnerf_ros.eval.windows import scored_windows

    ts, tr = train_set, trainer
    t0, t1 = ts.time_range
    edges, ks = scored_windows(t0, t1, 32, None)
    spans = [(int(edges[k]), int(edges[k + 1])) for k in ks]
    out = {}
    for split, views in (("moving camera", moving_views(ts, ts.val_views)),
                         ("static validation views", static_views(ts, ts.val_views))):
        start = time.perf_counter()
        with torch.no_grad():
            field_dl, gt, _ = evaluate_views(tr.field.eval(), ts, views, 32, box=tr.box, n_samples=tr.cfg.n_samples,
                                             log_eps=tr.cfg.log_eps, near=tr.cfg.near, far=tr.cfg.far,
                                             background=tr.cfg.background, dynamic=tr.dynamic, static_world="auto")
        predictors = {"the field": field_dl}
        for name, path in {"true scene": None, **scene_files}.items():
            ref = truth if path is None else TrueScene(ts, {**truth.record, "scene": str(path)})
            predictors[name] = np.concatenate([ref.log_changes(v, spans) for v in views])
        metrics = {k: event_metrics(p, gt, c_pos=ts.thresholds[0], c_neg=ts.thresholds[1]) for k, p in predictors.items()}
        floor = metrics["true scene"]["zero_floor"]
        true = metrics["true scene"]["continuous"]
        rows = {}
        for name, m in metrics.items():
            rows[name] = {"psnr": m["continuous"]["psnr"], "psnr_pooled": m["continuous"]["psnr_pooled"],
                          "margin_closed": margin_closed(m["continuous"]["psnr"], floor["psnr"], true["psnr"]),
                          "margin_closed_pooled": margin_closed(m["continuous"]["psnr_pooled"], floor["psnr_pooled"],
                                                                true["psnr_pooled"]),
                          "change_energy": float((np.asarray(predictors[name], np.float64) ** 2).sum())}
        out[split] = {"views": list(views), "windows": len(ks), "zero_floor": floor["psnr"],
                      "zero_floor_pooled": floor["psnr_pooled"], "predictors": rows,
                      "seconds": time.perf_counter() - start}
        for name, r in rows.items():
            log(f"{split}: {name:45s} margin closed {100 * r['margin_closed']:7.1f} % per window, "
                f"{100 * r['margin_closed_pooled']:7.1f} % pooled; change energy {r['change_energy']:8.1f}")
    return out


def plot(result: dict, path: Path) -> None:
    plt = pyplot()
    splits = list(result["splits"])
    fig, axes = plt.subplots(1, len(splits), figsize=(7 * len(splits), 4.2), squeeze=False)
    for ax, split in zip(axes[0], splits):
        rows = result["splits"][split]["predictors"]
        names = list(rows)
        y = range(len(names))
        ax.barh([i + 0.2 for i in y], [100 * rows[n]["margin_closed"] for n in names], height=0.4, label="per window")
        ax.barh([i - 0.2 for i in y], [100 * rows[n]["margin_closed_pooled"] for n in names], height=0.4, label="pooled")
        ax.set_yticks(list(y))
        ax.set_yticklabels(names, fontsize=8)
        ax.axvline(0, color="grey", lw=1)
        ax.axvline(100, color="grey", ls=":", lw=1)
        ax.invert_yaxis()
        ax.set_xlabel("margin closed (%; 0: no events, 100: the true scene)")
        ax.set_title(f"{split} (32 windows)", fontsize=10)
        ax.legend(fontsize=8)
    fig.suptitle(f"the demo's fork set: the field ({result['seconds']:g} s, seed {result['seed']}, part's mean "
                 f"opacity over the region {result['part_opacity']:.4f}) against the true scene's pieces", fontsize=10)
    save_figure(fig, path)


def main() -> None:
    ap = arg_parser(__doc__, quick=None)
    ap.add_argument("--seconds", type=float, default=120.0, help="training seconds (default 120: the demo's)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=2, help="torch threads")
    ap.add_argument("--work", default="/tmp/bench_quality", help="where the fork set is made once")
    args = ap.parse_args()
    import torch
    import yaml

    from bench_quality import build_set, demo_setting
    from evdnerf_ros import demo
    from evdnerf_ros.eval.truth import TrueScene
    from evdnerf_ros.io.trainingset import TrainingSet
    from evdnerf_ros.sim.scene import preset_path
    from evdnerf_ros.train.trainer import Trainer

    torch.set_num_threads(args.threads)
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    train_h5 = build_set(work, demo_setting())
    base = yaml.safe_load(Path(preset_path(demo.SCENE)).read_text())
    scene_files = {}
    for i, (name, spec) in enumerate(VARIANTS.items()):
        scene_files[name] = work / f"moving-camera-scene-{i}.yaml"
        scene_files[name].write_text(yaml.safe_dump(scene_variant(base, *spec)))
    with TrainingSet(train_h5) as ts:
        truth, why = TrueScene.of(ts)
        if truth is None:
            raise SystemExit(f"{train_h5}: {why}")
        config = dict(demo.TRAIN_CONFIG, backbone="hinge", seed=args.seed, eval_every=0, checkpoint_every=0,
                      log_every=0)
        trainer = Trainer(ts, config, minutes=args.seconds / 60.0, log=lambda *_: None)
        trainer.train()
        print(f"trained {trainer.iteration} iterations in {args.seconds:g} s", flush=True)
        result = {"machine": machine("torch"), "set": train_h5.name, "seconds": args.seconds, "seed": args.seed,
                  "iterations": trainer.iteration, "part_opacity": part_opacity(trainer),
                  "splits": score(ts, trainer, truth, scene_files, lambda s: print(s, flush=True))}
    write_results(Path(args.out), "moving_camera", result, plot)


if __name__ == "__main__":
    main()
