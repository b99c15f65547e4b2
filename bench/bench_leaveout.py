"""Benchmark: what each leave-out switch of training saves, per step.

Data: the Jet-Down 128x128 18+18-view set of ``bench_train.py`` (built if missing); the
field starts from that benchmark's trained ``planes-fixed-32`` checkpoint when present, so
that the occupancy grid has real empty space to skip (an untrained field is dense).

Variants (32 windows, 1024 rays, 48 samples per ray, same seeds):
- ``all``: the defaults — dynamic region (exact: no time work, and no ray at all, where no
  training view saw an event) and static-view sample reuse (both window ends share samples
  and space features);
- ``no-region``, ``no-reuse``: one switch off;
- ``+occupancy``: the defaults plus a 64^3 occupancy grid (max density over time; skips
  samples in empty cells — approximate: it drops density below its threshold);
- ``none``: every ray, every sample, both ends evaluated separately.

The variants' steps are interleaved round-robin (this machine is noisy) and each reports
the median ms per step and the field work per step: points whose space features were
computed, and points decoded (per time).

Usage: python bench/bench_leaveout.py [--rounds R] [--steps S]  -> bench/results/leaveout.{json,png}
"""

from __future__ import annotations

import json
import statistics
import time
from pathlib import Path

from _common import arg_parser, machine, pyplot, save_figure, write_results

BASE = {"windows": [32], "window_switch": [], "time_curriculum": 0, "lr_warmup_iters": 0,
        "log_every": 0, "eval_every": 0, "checkpoint_every": 0}
VARIANTS = {
    "all": {},
    "no-region": {"dynamic_region": False},
    "no-reuse": {"sample_reuse": False},
    "+occupancy": {"occupancy_resolution": 64, "occupancy_warmup": 0, "occupancy_every": 10**9},
    "none": {"dynamic_region": False, "sample_reuse": False},
}


class WorkCounter:
    """Counts the points the field computes space features for and decodes."""

    def __init__(self, field):
        self.space = self.decoded = 0
        for name, attr in (("space_features", "space"), ("decode", "decoded"),
                           ("decode_static", "decoded")):
            self._wrap(field, name, attr)

    def _wrap(self, field, name, attr):
        inner = getattr(field, name)

        def counted(x, *rest):
            n = x.shape[0] if attr == "space" else _rows(x)
            setattr(self, attr, getattr(self, attr) + n)
            return inner(x, *rest)
        setattr(field, name, counted)


def _rows(features) -> int:
    if isinstance(features, (list, tuple)):
        return _rows(features[0])
    return int(features.shape[0])


def main(argv=None):
    import torch

    from bench_train import build_set
    from evdnerf_ros.io.trainingset import TrainingSet
    from evdnerf_ros.train.trainer import Trainer

    ap = arg_parser(__doc__, quick=None)
    ap.add_argument("--work", default="/tmp/bench_train")
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--steps", type=int, default=6, help="steps per variant per round")
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    train_h5 = build_set(work, quick=False)
    init = work / "planes-fixed-32" / "checkpoint.pt"
    ts = TrainingSet(train_h5)
    trainers, counters = {}, {}
    for name, cfg in VARIANTS.items():
        tr = Trainer(ts, {**BASE, **cfg}, iters=10**9, log=lambda *_: None)
        if init.exists():
            tr.init_from(init)
        for _ in range(2):                     # warm-up (and the occupancy grid's first update)
            tr.step()
        trainers[name], counters[name] = tr, WorkCounter(tr.field)
    times = {n: [] for n in VARIANTS}
    for _ in range(args.rounds):
        for name, tr in trainers.items():
            for _ in range(args.steps):
                t = time.perf_counter()
                tr.step()
                times[name].append(1000 * (time.perf_counter() - t))
    n_steps = args.rounds * args.steps
    rows = {}
    for name in VARIANTS:
        c = counters[name]
        rows[name] = {"ms_per_step_median": statistics.median(times[name]),
                      "space_points_per_step": c.space / n_steps,
                      "decoded_points_per_step": c.decoded / n_steps}
    ref = rows["all"]["ms_per_step_median"]
    for r in rows.values():
        r["time_vs_all"] = r["ms_per_step_median"] / ref
    result = {"machine": {**machine("torch"), "threads": args.threads},
              "data": "jet-down 128x128, 18 training views, 32 windows, 1024 rays, 48 samples",
              "field_init": str(init) if init.exists() else "untrained",
              "steps_per_variant": n_steps, "variants": rows,
              "savings": {"dynamic_region": rows["no-region"]["ms_per_step_median"] / ref,
                          "sample_reuse": rows["no-reuse"]["ms_per_step_median"] / ref,
                          "occupancy_extra": ref / rows["+occupancy"]["ms_per_step_median"],
                          "all_vs_none": rows["none"]["ms_per_step_median"] / ref}}
    ts.close()
    write_results(args.out, "leaveout", result, plot)
    print(json.dumps(result, indent=1))


def plot(result: dict, path: Path) -> None:
    rows = result["variants"]
    names = list(rows)
    fig, ax = pyplot().subplots(1, 2, figsize=(10, 3.6))
    ax[0].bar(names, [rows[n]["ms_per_step_median"] for n in names], color="tab:blue")
    ax[0].set_ylabel("ms per training step (median)")
    ax[1].bar(names, [rows[n]["space_points_per_step"] / 1e3 for n in names], label="space features")
    ax[1].bar(names, [rows[n]["decoded_points_per_step"] / 1e3 for n in names], alpha=0.5,
              label="decoded (all times)")
    ax[1].set_ylabel("field points per step (thousands)")
    ax[1].legend()
    for a in ax:
        a.tick_params(axis="x", rotation=20)
    fig.suptitle("Leave-out switches of training (Jet-Down 128x128, 18 views)")
    save_figure(fig, path, dpi=110)


if __name__ == "__main__":
    main()
