"""What every benchmark in bench/ shares: the import path, the command line, the machine
record, the results files and the timing helpers.

A script runs as ``python bench/bench_X.py`` (so bench/ is on ``sys.path``) and imports this
module before anything of the project: importing it puts the checkout's root first on
``sys.path``, so that ``evdnerf_ros`` and ``rig`` come from this tree, not from an installed
copy.

* ``arg_parser(__doc__)``: ``--quick`` and ``-o/--out`` (the results folder, default
  bench/results) on every script; the script adds its own options.
* ``machine()``: platform, Python, numpy, CPU model and count, affinity, git HEAD, plus the
  versions of the packages named; ``load_average()`` for before / after records.
* ``write_results(out, name, result, plot)``: ``<name>.json`` (written atomically: a reader
  never sees half a file) and ``<name>.png`` from ``plot(result, path)``; ``read_results``
  for the scripts that merge a partial run into the last results or redraw the plot.
* ``pyplot()`` / ``save_figure(fig, path)``: matplotlib without a display, figure written
  atomically and closed.
* ``timed(fn)``, ``best_of(fn, n)``, ``interleaved({name: fn}, n)``, ``peak_traced_bytes(fn)``:
  ``time.perf_counter`` wall times and tracemalloc peaks, nothing else; what is timed is the
  script's business.
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import platform
import statistics
import subprocess
import sys
import time
import tracemalloc
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "bench" / "results"
TESTS = ROOT / "tests"

if not sys.path or sys.path[0] != str(ROOT):
    sys.path.insert(0, str(ROOT))


# --------------------------------------------------------------------------- command line


def arg_parser(doc: str | None, *, quick: str | None = "a smaller, faster smoke run",
               out_aliases: tuple[str, ...] = ()) -> argparse.ArgumentParser:
    """The parser every benchmark starts from: its description is the first paragraph of the
    script's docstring; ``--quick`` (left out with ``quick=None``) and ``-o/--out`` (a Path,
    default bench/results; ``out_aliases`` keeps older spellings such as ``--out-dir``)."""
    first = (doc or "").strip().split("\n\n")[0]
    ap = argparse.ArgumentParser(description=" ".join(first.split()))
    if quick is not None:
        ap.add_argument("--quick", action="store_true", help=quick)
    ap.add_argument("-o", "--out", *out_aliases, dest="out", type=Path, default=RESULTS,
                    help=f"results folder (default {RESULTS.relative_to(ROOT)})")
    return ap


# --------------------------------------------------------------------------- machine record


def cpu_model() -> str:
    """The CPU's model name from /proc/cpuinfo (``platform.processor()`` elsewhere)."""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor()


def load_average() -> list[float] | None:
    """The 1 / 5 / 15 minute load averages now (None where the OS has none)."""
    return list(os.getloadavg()) if hasattr(os, "getloadavg") else None


def git_head() -> str | None:
    """The checkout's short HEAD commit (None outside git)."""
    try:
        r = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"],
                           capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.SubprocessError):
        return None
    return r.stdout.strip() or None


def package_version(name: str) -> str | None:
    """An installed distribution's version (None when it is not installed)."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version(name)
    except PackageNotFoundError:
        return None


def machine(*packages: str) -> dict:
    """What ran the benchmark: platform, python, numpy, cpu (model), cpus (logical),
    affinity (the cores this process may use), arch, git_head, and one key per package named
    with its installed version (None when absent)."""
    info = {
        "platform": platform.platform(),
        "python": platform.python_version(),
        "numpy": np.__version__,
        "cpu": cpu_model(),
        "cpus": os.cpu_count(),
        "affinity": sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None,
        "arch": platform.machine(),
        "git_head": git_head(),
    }
    info.update({p: package_version(p) for p in packages})
    return info


def describe(info: dict) -> str:
    """One line for plot titles and flat records: 'x86_64, 2 CPUs'."""
    return f"{info['arch']}, {info['cpus']} CPUs"


# --------------------------------------------------------------------------- results files


def _jsonable(obj):
    """numpy scalars and arrays (and anything else float() takes) in results JSON."""
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    return float(obj)


def _replace_atomically(path: Path, write) -> None:
    """write(tmp) then rename onto path: readers see the old file or the whole new one."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        write(tmp)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def write_json(path: Path, data) -> Path:
    """``data`` as indented JSON at ``path`` (folder created, written atomically)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    text = json.dumps(data, indent=2, default=_jsonable) + "\n"
    _replace_atomically(path, lambda tmp: tmp.write_text(text))
    return path


def write_results(out: Path, name: str, result: dict, plot=None) -> Path:
    """``out/<name>.json`` and, with ``plot(result, png_path)``, ``out/<name>.png``; prints
    what was written and returns the JSON path."""
    out = Path(out)
    path = write_json(out / f"{name}.json", result)
    if plot is not None:
        plot(result, out / f"{name}.png")
        print(f"wrote {path} and {out / (name + '.png')}")
    else:
        print(f"wrote {path}")
    return path


def read_results(out: Path, name: str, *, missing_ok: bool = False) -> dict:
    """``out/<name>.json`` as written by ``write_results`` ({} when absent and missing_ok)."""
    path = Path(out) / f"{name}.json"
    if not path.exists():
        if missing_ok:
            return {}
        raise SystemExit(f"{path}: no results to read; run the benchmark without --replot first")
    return json.loads(path.read_text())


def pyplot():
    """matplotlib.pyplot on the Agg backend (no display needed)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig, path: Path, *, dpi: int = 110, layout: dict | None = None) -> None:
    """tight_layout(**layout), save (atomically, format from the suffix) and close."""
    plt = pyplot()
    fig.tight_layout(**(layout or {}))
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        _replace_atomically(path, lambda tmp: fig.savefig(tmp, dpi=dpi, format=path.suffix.lstrip(".")))
    finally:
        plt.close(fig)


# --------------------------------------------------------------------------- timing


def timed(fn, *, collect: bool = False):
    """(wall seconds, return value) of one ``fn()`` (``time.perf_counter``); with ``collect``
    a ``gc.collect()`` first, outside the timed call."""
    if collect:
        gc.collect()
    t0 = time.perf_counter()
    value = fn()
    return time.perf_counter() - t0, value


def best_of(fn, repeats: int, before=None) -> float:
    """The least wall seconds of ``repeats`` calls of ``fn()``; ``before()`` (untimed) ahead of
    each: the minimum keeps bursts of load from other processes out of the number."""
    best = np.inf
    for _ in range(repeats):
        if before is not None:
            before()
        best = min(best, timed(fn)[0])
    return best


def interleaved(fns: dict, repeats: int, *, warmup: bool = True, collect: bool = False) -> dict:
    """The functions take turns in each of ``repeats`` rounds (so that load changes hit all of
    them alike); per name {"median_s", "min_s", "runs_s"}. ``warmup`` calls each once first,
    untimed; ``collect`` runs ``gc.collect()`` before every timed call."""
    if warmup:
        for f in fns.values():
            f()
    runs = {k: [] for k in fns}
    for _ in range(repeats):
        for k, f in fns.items():
            runs[k].append(timed(f, collect=collect)[0])
    return {k: {"median_s": statistics.median(v), "min_s": min(v), "runs_s": v} for k, v in runs.items()}


def peak_traced_bytes(fn) -> int:
    """Peak bytes traced by tracemalloc over one ``fn()`` (numpy buffers are traced; what was
    allocated before the call is not counted)."""
    gc.collect()
    tracemalloc.start()
    try:
        fn()
        return tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
