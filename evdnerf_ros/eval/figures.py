"""Figures and the error-against-run-time report (the engine behind `evdnerf report RUN...`).

RUN/metrics.jsonl holds one JSON object per line.  Every line needs ``iter`` and ``wall_s``;
evaluation lines carry ``val_psnr`` together with ``val_psnr_zero_floor`` (and optionally
``label``).  Lines without ``val_psnr`` (e.g. training-loss records) are skipped; blank lines
are ignored; anything else malformed raises InputError naming the file and line.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from ..atomic import atomic_output, check_output
from ..errors import InputError
from ..events.images import signed_to_rgb
from ..events.rate import save_figure

METRICS_FILE = "metrics.jsonl"


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def side_by_side(gt_stack, pred_stack, path, *, vmax: float | None = None,
                 titles=None, max_windows: int = 8, title: str | None = None) -> Path:
    """PNG grid: top row ground-truth event images, bottom row predictions (red +, blue -).

    Both rows share one colour scale, vmax = max|gt| by default (falls back to max|pred|, then
    to 1 for all-zero data), so a prediction brighter than the ground truth saturates.
    At most `max_windows` columns (evenly spread over the stack) are drawn.
    """
    gt = np.asarray(gt_stack, np.float64)
    pred = np.asarray(pred_stack, np.float64)
    if gt.ndim == 2 and pred.ndim == 2:
        gt, pred = gt[None], pred[None]
    if gt.ndim != 3 or gt.shape != pred.shape:
        raise InputError(f"side_by_side needs two (K, H, W) stacks of one shape, got "
                         f"{gt.shape} and {pred.shape}")
    if gt.shape[0] == 0:
        raise InputError("side_by_side: no windows to draw")
    if not (np.all(np.isfinite(gt)) and np.all(np.isfinite(pred))):
        raise InputError("side_by_side: event images contain NaN or inf")
    if vmax is None:
        vmax = float(np.max(np.abs(gt))) or float(np.max(np.abs(pred))) or 1.0
    k = gt.shape[0]
    cols = np.unique(np.linspace(0, k - 1, min(k, max(1, int(max_windows)))).round().astype(int))
    if titles is None:
        titles = [f"window {i}" for i in range(k)]
    plt = _pyplot()
    n = len(cols)
    fig, axes = plt.subplots(2, n, figsize=(1.9 * n + 0.6, 4.0), squeeze=False)
    for j, i in enumerate(cols):
        for row, (img, name) in enumerate(((gt[i], "ground truth"), (pred[i], "prediction"))):
            ax = axes[row, j]
            ax.imshow(signed_to_rgb(img, vmax=vmax), interpolation="nearest")
            ax.set_xticks([])
            ax.set_yticks([])
            if row == 0:
                ax.set_title(str(titles[i]), fontsize=8)
            if j == 0:
                ax.set_ylabel(name, fontsize=8)
    fig.suptitle(title or f"event images (dL), shared scale |dL| <= {vmax:.3g}", fontsize=9)
    fig.tight_layout()
    return save_figure(fig, path)


def intensity_figure(renders: dict, path, *, title: str = "") -> Path:
    """PNG grid, one column per time: blurred frame, brightness-aligned grey render, depth."""
    plt = _pyplot()
    n = len(renders["t_ns"])
    fig, axes = plt.subplots(3, n, figsize=(2.2 * n + 0.6, 6.4), squeeze=False)
    for j in range(n):
        rows = ((renders["frames"][j], "blurred frame", "gray", (0, 1)),
                (renders["grey"][j], f"render ({renders['psnr'][j]:.1f} dB)", "gray", (0, 1)),
                (renders["depth"][j], "depth (m)", "viridis", (None, None)))
        for row, (img, name, cmap, (lo, hi)) in enumerate(rows):
            ax = axes[row, j]
            ax.imshow(img, cmap=cmap, vmin=lo, vmax=hi, interpolation="nearest")
            ax.set_xticks([])
            ax.set_yticks([])
            ax.set_ylabel(name if j == 0 or row == 1 else "", fontsize=8)
            if row == 0:
                ax.set_title(f"t = {renders['t_ns'][j] / 1e9:.3f} s", fontsize=8)
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    return save_figure(fig, path)


def _number(obj: dict, key: str, where: str) -> float:
    if key not in obj:
        raise InputError(f"{where}: missing key {key!r}")
    v = obj[key]
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise InputError(f"{where}: {key!r} must be a finite number, got {v!r}")
    return float(v)


def read_metrics(run_dir) -> dict:
    """Evaluation records of one run: {label, path, iter, wall_s, val_psnr, floor} (arrays)."""
    run_dir = Path(run_dir)
    path = run_dir / METRICS_FILE
    if not path.is_file():
        raise InputError(f"{path}: no such file; is {run_dir} a training run folder?")
    rows, label = [], None
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: cannot read: {exc}") from None
    for n, line in enumerate(lines, start=1):
        if not line.strip():
            continue
        where = f"{path}: line {n}"
        try:
            obj = json.loads(line)
        except json.JSONDecodeError as exc:
            raise InputError(f"{where}: not valid JSON ({exc.msg})") from None
        if not isinstance(obj, dict):
            raise InputError(f"{where}: expected a JSON object, got {type(obj).__name__}")
        it = _number(obj, "iter", where)
        wall = _number(obj, "wall_s", where)
        if "val_psnr" not in obj:
            continue
        rows.append((it, wall, _number(obj, "val_psnr", where),
                     _number(obj, "val_psnr_zero_floor", where),
                     _optional_number(obj, "val_psnr_truth", where),
                     _optional_number(obj, "val_margin_closed", where),
                     _optional_number(obj, "val_margin_closed_pooled", where)))
        if label is None and isinstance(obj.get("label"), str) and obj["label"]:
            label = obj["label"]
    if not rows:
        raise InputError(f"{path}: no evaluation records (lines with 'val_psnr')")
    rows.sort(key=lambda r: (r[1], r[0]))
    a = np.array(rows, np.float64)
    return {"label": label or run_dir.resolve().name, "path": str(path),
            "iter": a[:, 0].astype(np.int64), "wall_s": a[:, 1], "val_psnr": a[:, 2],
            "floor": a[:, 3], "truth": a[:, 4], "margin": a[:, 5], "margin_pooled": a[:, 6]}


def _optional_number(obj: dict, key: str, where: str) -> float:
    """A metric only some runs log (the true scene's score, the margin closed): NaN when absent
    or null (a static scene has no margin)."""
    return float("nan") if obj.get(key) is None else _number(obj, key, where)


def _load_all(run_dirs) -> list[dict]:
    run_dirs = list(run_dirs)
    if not run_dirs:
        raise InputError("report needs at least one run folder")
    return [read_metrics(d) for d in run_dirs]


def _summary(r: dict) -> dict:
    return {"run": r["label"], "metrics": r["path"], "iterations": int(r["iter"].max()),
            "wall_s": float(r["wall_s"].max()), "best_psnr": float(r["val_psnr"].max()),
            "final_psnr": float(r["val_psnr"][-1]), "zero_floor": float(r["floor"][-1]),
            "true_scene": _finite_or_none(r["truth"][-1]), "margin_closed": _finite_or_none(r["margin"][-1]),
            "margin_closed_pooled": _finite_or_none(r["margin_pooled"][-1]),
            "n_evals": int(r["iter"].size)}


def _finite_or_none(x) -> float | None:
    return float(x) if np.isfinite(x) else None


def plot_runs(run_dirs, path, *, title: str = "validation events-PSNR against wall time") -> Path:
    """One figure: events-PSNR (solid) and its all-zero floor (dashed) vs wall seconds per run."""
    return _plot(_load_all(run_dirs), path, title)


def _plot(runs: list[dict], path, title: str, *, overwrite: bool = True) -> Path:
    plt = _pyplot()
    margins = any(np.isfinite(r[k]).any() for r in runs for k in ("margin", "margin_pooled"))
    fig, axes = plt.subplots(1, 2 if margins else 1, figsize=(12 if margins else 7, 4), squeeze=False)
    ax = axes[0, 0]
    for i, r in enumerate(runs):
        colour = f"C{i % 10}"
        ax.plot(r["wall_s"], r["val_psnr"], "-o", color=colour, markersize=3, label=r["label"])
        ax.plot(r["wall_s"], r["floor"], "--", color=colour, linewidth=1,
                label=f"{r['label']} zero floor")
        if np.isfinite(r["truth"]).any():
            ax.plot(r["wall_s"], r["truth"], ":", color=colour, linewidth=1.5,
                    label=f"{r['label']} true scene")
        if margins and np.isfinite(r["margin"]).any():
            axes[0, 1].plot(r["wall_s"], 100 * r["margin"], "-o", color=colour, markersize=3, label=r["label"])
        if margins and np.isfinite(r["margin_pooled"]).any():
            axes[0, 1].plot(r["wall_s"], 100 * r["margin_pooled"], "--", color=colour, linewidth=1,
                            label=f"{r['label']} pooled")
    ax.set_xlabel("wall time [s]")
    ax.set_ylabel("events PSNR [dB]")
    ax.set_title(title, fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    if margins:
        m = axes[0, 1]
        m.axhline(0, color="k", linewidth=0.8)
        m.axhline(100, color="k", linewidth=0.8, linestyle=":")
        m.set_xlabel("wall time [s]")
        m.set_ylabel("floor-to-truth margin closed [%]")
        m.set_title("(field - floor) / (true scene - floor): mean over windows (solid), pooled (dashed)",
                    fontsize=9)
        m.grid(alpha=0.3)
        m.legend(fontsize=7)
    fig.tight_layout()
    return save_figure(fig, path, overwrite=overwrite)


def _table(summaries: list[dict]) -> str:
    lines = ["| run | iterations | wall time [s] | best PSNR [dB] | final PSNR [dB] | zero floor [dB] "
             "| true scene [dB] | margin closed | margin closed, pooled |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for s in summaries:
        name = s["run"].replace("|", "\\|")
        truth = "–" if s["true_scene"] is None else f"{s['true_scene']:.2f}"
        margin, pooled = ("–" if s[k] is None else f"{100 * s[k]:.0f} %"
                          for k in ("margin_closed", "margin_closed_pooled"))
        lines.append(f"| {name} | {s['iterations']} | {s['wall_s']:.1f} | {s['best_psnr']:.2f} "
                     f"| {s['final_psnr']:.2f} | {s['zero_floor']:.2f} | {truth} | {margin} | {pooled} |")
    return "\n".join(lines) + "\n"


def markdown_table(run_dirs) -> str:
    """Markdown table: run, iterations, wall time, best PSNR, final PSNR, zero floor."""
    return _table([_summary(r) for r in _load_all(run_dirs)])


def run_report(run_dirs, out_dir, *, overwrite: bool = False) -> dict:
    """Write OUT/report.png and OUT/report.md (atomically); return paths and per-run summaries.

    Existing report files are replaced only with `overwrite` (and never a folder of that name).
    """
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise InputError(f"{out_dir}: exists and is not a folder; give a folder for report.png / report.md")
    png, md = out_dir / "report.png", out_dir / "report.md"
    if out_dir.is_dir():
        for path in (png, md):
            check_output(path, overwrite=overwrite)
    runs = _load_all(run_dirs)
    out_dir.mkdir(parents=True, exist_ok=True)
    summaries = [_summary(r) for r in runs]
    _plot(runs, png, "validation events-PSNR against wall time", overwrite=overwrite)
    text = ("# Events-PSNR against wall time\n\n"
            "![events-PSNR against wall time](report.png)\n\n"
            "Solid: validation events-PSNR; dashed: the all-zero-prediction floor; dotted: the true "
            "scene (simulated sessions), with the fraction of the floor-to-truth margin closed.\n\n"
            + _table(summaries))
    with atomic_output(md, overwrite=overwrite) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return {"png": str(png), "md": str(md), "runs": summaries}
