"""Benchmark the readers of other writers' event files against independent readers, on the real
files of ../shared/data/real/ (skipped where absent), interleaved in one process.

    python bench/bench_readers.py [--repeats R]

- AEDAT 4.0 (`tonic/sample.aedat4`, DVXplorer): the two libraries' decoders side by side (the
  `aedat` package, which this toolkit reads with, and faery), and this toolkit's whole read
  (`read_event_file`: the `aedat` decode plus the conversion to int64 ns and checks); each must
  give the reference events (111 954, 55 023 ON).
- OpenEB RAW EVT 3.0 (`expelliarmus/evt3_sample.raw`): ours against faery's.
- Text `t x y p` (`events_viz/events_chunk.txt`): ours (exact, parsed as text) against
  numpy.loadtxt as float64 seconds rounded to ns (right on this file's small times; at epoch
  magnitudes float64 seconds resolve only ~0.2 us).
- N-MNIST `.bin` (`tonic/sample_nmnist.bin`): ours (the reference values are checked).
- Prophesee DAT (`expelliarmus/dat_sample.dat`, N-CARS): ours against expelliarmus' reader
  (faery refuses this file's `2d` type).

Per file: median and minimum seconds, events per second, and whether the reader matched the
reference. Writes bench/results/readers.{json,png}.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from _common import ROOT, arg_parser, interleaved, load_average, machine, pyplot, save_figure, write_results

REAL = Path(os.environ.get("EVDNERF_REAL_DATA", ROOT.parent / "shared" / "data" / "real"))


def _faery_events(path):
    import faery

    return np.concatenate([np.asarray(p) for p in faery.events_stream_from_file(str(path))])


def cases() -> dict:
    """name -> (path, {reader: fn() -> (count, on, first_t_ns, last_t_ns)}, reference)."""
    from evdnerf_ros.io.event_files import read_event_file

    def ours(path, **kw):
        def run():
            e = read_event_file(path, **kw).events
            return e.size, int((e["p"] > 0).sum()), int(e["t"][0]), int(e["t"][-1])
        return run

    def faery(path):
        def run():
            e = _faery_events(path)
            return e.size, int(e["on"].sum()), int(e["t"][0]) * 1000, int(e["t"][-1]) * 1000
        return run

    def aedat_decode(path):
        def run():
            import aedat

            e = np.concatenate([p["events"] for p in aedat.Decoder(str(path)) if "events" in p])
            return e.size, int(e["on"].sum()), int(e["t"][0]) * 1000, int(e["t"][-1]) * 1000
        return run

    def expelliarmus_dat(path):
        def run():
            from expelliarmus import Wizard

            e = Wizard(encoding="dat").read(str(path))
            return e.size, int((e["p"] > 0).sum()), int(e["t"][0]) * 1000, int(e["t"][-1]) * 1000
        return run

    def loadtxt(path):
        def run():
            a = np.loadtxt(path)
            t = np.round(a[:, 0] * 1e9).astype(np.int64)
            return a.shape[0], int((a[:, 3] > 0).sum()), int(t[0]), int(t[-1])
        return run

    aedat4, raw = REAL / "tonic" / "sample.aedat4", REAL / "expelliarmus" / "evt3_sample.raw"
    text, nmnist = REAL / "events_viz" / "events_chunk.txt", REAL / "tonic" / "sample_nmnist.bin"
    dat = REAL / "expelliarmus" / "dat_sample.dat"
    return {
        "aedat4": (aedat4, {"aedat package (decode)": aedat_decode(aedat4), "faery (decode)": faery(aedat4),
                            "ours (read_event_file)": ours(aedat4)},
                   (111_954, 55_023, 1_605_537_493_718_345_000, 1_605_537_494_308_262_000)),
        "raw_evt3": (raw, {"ours": ours(raw), "faery": faery(raw)}, None),
        "text": (text, {"ours (exact)": ours(text, geometry=(240, 180)), "numpy.loadtxt (float s)": loadtxt(text)},
                 (50_000, 21_147, 3_811_000, 174_156_000)),
        "nmnist_bin": (nmnist, {"ours": ours(nmnist, geometry=(34, 34))}, (4325, 2145, 654_000, 311_175_000)),
        "dat": (dat, {"ours": ours(dat, geometry=(120, 100)), "expelliarmus": expelliarmus_dat(dat)},
                (4407, 1671, 0, 99_937_000)),
    }


def run(repeats: int) -> dict:
    out = {}
    for name, (path, readers, reference) in cases().items():
        if not path.is_file():
            out[name] = {"skipped": f"{path} not found"}
            continue
        results = {k: f() for k, f in readers.items()}
        times = interleaved(readers, repeats)
        n = next(iter(results.values()))[0]
        out[name] = {"file": str(path.relative_to(REAL)), "events": n, "reference": reference,
                     "readers": {k: {"median_s": times[k]["median_s"], "min_s": times[k]["min_s"],
                                     "events_per_s": results[k][0] / times[k]["median_s"],
                                     "result": list(results[k]),
                                     "matches_reference": None if reference is None else tuple(results[k]) == reference}
                                 for k in readers}}
    return out


def plot(result: dict, path: Path) -> None:
    plt = pyplot()
    files = [k for k, v in result["files"].items() if "readers" in v]
    fig, axes = plt.subplots(1, len(files), figsize=(4 * len(files), 3.5), squeeze=False)
    for ax, name in zip(axes[0], files):
        readers = result["files"][name]["readers"]
        labels = list(readers)
        ax.barh(labels, [readers[k]["events_per_s"] / 1e6 for k in labels],
                color=["tab:blue" if k.startswith("ours") else "tab:grey" for k in labels])
        ax.set_xlabel("Mev/s (median)")
        ax.set_title(f"{name} ({result['files'][name]['events']} events)")
    save_figure(fig, path)


def main(argv=None):
    ap = arg_parser(__doc__, quick=None)
    ap.add_argument("--repeats", type=int, default=15)
    args = ap.parse_args(argv)
    files = run(args.repeats)
    summary = {f"{name}: {k}": round(v["events_per_s"] / 1e6, 2) for name, r in files.items()
               for k, v in (r.get("readers") or {}).items()}
    write_results(args.out, "readers", {"machine": machine("aedat", "faery"), "load_before": load_average(),
                                        "files": files, "summary": summary}, plot)


if __name__ == "__main__":
    main()
