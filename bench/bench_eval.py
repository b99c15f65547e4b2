"""`evdnerf eval` wall time on the Jet-Down 64x64 set, and the error of scoring fewer training views.

The set: Jet-Down simulated at 64x64, 18 training + 4 validation views (the issue's eval
setting), converted with ground-truth offsets; a run trained on it for one minute with the
default config (128 windows at the end, so x1 / x4 / x8 score 128 / 512 / 1024 windows, every
4th). Both are built once into ``--work`` and reused.

* **Wall time** of ``run_eval`` (the command's library call, one process, 2 torch threads),
  interleaved, median of ``--repeats``:
  - ``default``: every validation view, 4 training views spread over the ring (``--train-views 4``);
  - ``every training view``: ``--train-views 0`` (18);
  - ``counts apart``: the default's views, but x1, x4 and x8 each evaluated by its own call, so
    no render is shared across the counts (what eval did before the shared window ends).
* **Error against run time**: the training split's scores from 4 spread views against those
  from all 18 (PSNR and margin closed per window count): what the cheaper default gives up.
  Validation scores are the same views in every setting and must agree exactly.

Usage: python bench/bench_eval.py [--quick] [--repeats N] [--work DIR]
       -> bench/results/eval.{json,png}
"""

from __future__ import annotations

import time
from pathlib import Path

from _common import arg_parser, load_average, machine, pyplot, save_figure, write_results

FACTORS = (1, 4, 8)


def build(work: Path, quick: bool) -> tuple[Path, Path]:
    from evdnerf_ros.session.convert import run_convert
    from evdnerf_ros.sim.simulate import SimulationOptions, simulate_session
    from evdnerf_ros.train.trainer import run_train

    views = 6 if quick else 18
    h5, run = work / f"jet-down-64-{views}+4.h5", work / f"run-64-{views}+4"
    work.mkdir(parents=True, exist_ok=True)
    if not h5.exists():
        t = time.perf_counter()
        simulate_session("jet-down", work / f"session-{views}", SimulationOptions(
            views=views, val_views=4, resolution=(64, 64), frame_rate_hz=30, blur_samples=4,
            gt_times=0, supersample=2, min_step_ns=2_000_000), log=lambda *_: None, overwrite=True)
        run_convert(work / f"session-{views}", h5, offsets="ground-truth", log=lambda *_: None)
        print(f"simulated + converted in {time.perf_counter() - t:.0f} s", flush=True)
    if not (run / "checkpoint.pt").exists():
        run_train(h5, run, minutes=0.25 if quick else 1.0, overwrite=True, log=lambda *_: None)
    return h5, run


def scores(result: dict, split: str) -> dict:
    return {f"x{f}": {"psnr": result[f"{split}_windows_x{f}"]["continuous"]["psnr"],
                      "margin_closed": result[f"{split}_windows_x{f}"].get("margin_closed", {}).get("continuous"),
                      "views": result[f"{split}_windows_x{f}"]["views"]}
            for f in FACTORS if f"{split}_windows_x{f}" in result}


def main(argv=None):
    import torch

    from evdnerf_ros.eval.evaluate import run_eval

    ap = arg_parser(__doc__, quick="6 + 4 views, a 15 s run, one repeat")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--work", default="/tmp/bench_eval")
    args = ap.parse_args(argv)
    torch.set_num_threads(2)
    h5, run = build(Path(args.work), args.quick)
    repeats = 1 if args.quick else args.repeats

    def default():
        return run_eval(run, h5, log=lambda *_: None)

    def every_training_view():
        return run_eval(run, h5, train_views=0, log=lambda *_: None)

    def counts_apart():
        out = {}
        for f in FACTORS:
            out.update(run_eval(run, h5, factors=(f,), log=lambda *_: None))
        return out

    settings = {"default": default, "every training view": every_training_view, "counts apart": counts_apart}
    walls = {name: [] for name in settings}
    results = {}
    load_before = load_average()
    for _ in range(repeats):
        for name, fn in settings.items():           # interleaved: the machine's drift hits all alike
            t = time.perf_counter()
            results[name] = fn()
            walls[name].append(time.perf_counter() - t)
    med = {n: sorted(w)[len(w) // 2] for n, w in walls.items()}
    val = {n: scores(r, "val") for n, r in results.items()}
    if any(val[n] != val["default"] for n in val):
        raise SystemExit(f"validation scores differ between settings: {val}")
    train = {n: scores(r, "train") for n, r in results.items()}
    ref = train["every training view"]
    error = {f"x{f}": {"psnr_db": train["default"][f"x{f}"]["psnr"] - ref[f"x{f}"]["psnr"],
                       "margin_closed": (None if ref[f"x{f}"]["margin_closed"] is None
                                         or train["default"][f"x{f}"]["margin_closed"] is None else
                                         train["default"][f"x{f}"]["margin_closed"] - ref[f"x{f}"]["margin_closed"])}
             for f in FACTORS}
    result = {"benchmark": "eval", "quick": args.quick, "machine": machine("torch"),
              "load_before": load_before, "load_after": load_average(), "threads": 2,
              "set": h5.name, "run": run.name, "repeats": repeats,
              "wall_s": walls, "wall_s_median": med,
              "speedup_shared_counts": med["counts apart"] / med["default"],
              "validation": val["default"], "train": train,
              "train_error_of_4_spread_views": error}
    print("eval wall s (median): " + ", ".join(f"{n} {w:.1f}" for n, w in med.items()), flush=True)
    write_results(args.out, "eval_quick" if args.quick else "eval", result, plot)


def plot(result: dict, path: Path) -> None:
    plt = pyplot()
    fig, ax = plt.subplots(1, 2, figsize=(12, 4.4))
    names = list(result["wall_s_median"])
    ax[0].bar(names, [result["wall_s_median"][n] for n in names], color=["C0", "C1", "C2"])
    ax[0].axhline(60, color="k", ls=":", lw=1, label="goal: one minute")
    ax[0].set_ylabel(f"evdnerf eval wall s (median of {result['repeats']}, {result['threads']} threads)")
    ax[0].set_title(f"{result['set']}: x1 / x4 / x8")
    ax[0].legend(fontsize=8)
    for name, mk in (("default", "o"), ("every training view", "s")):
        r = result["train"][name]
        ax[1].plot([result["wall_s_median"][name]] * len(r), [v["psnr"] for v in r.values()], mk, ls="",
                   label=f"{name} ({next(iter(r.values()))['views']} training views)")
        for k, v in r.items():
            ax[1].annotate(k, (result["wall_s_median"][name], v["psnr"]), fontsize=7)
    ax[1].set_xlabel("eval wall s")
    ax[1].set_ylabel("training split events PSNR (dB)")
    ax[1].set_title("training views scored: error against run time")
    ax[1].legend(fontsize=8)
    save_figure(fig, path, dpi=110)


if __name__ == "__main__":
    main()
