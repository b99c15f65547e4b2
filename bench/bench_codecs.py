"""Benchmark our EVT 3.0 / EVT 2.0 codecs against expelliarmus (C) on the same RAW files.

    python bench/bench_codecs.py [--events N] [--quick] [--repeats R]

Writes bench/results/codecs.json and bench/results/codecs.png. The stream is synthetic
(half dense row bursts, half uniform scatter, 1 event/us on average, whole microseconds),
written to EVT 3.0 and EVT 2.0 RAW files by expelliarmus itself. Every decoder's output is
checked against the source array before anything is timed. Timings are medians of R runs,
ours and the peer's interleaved in the same process. Throughput = source events / second.

Our codecs run as numba kernels; their compile / load cost is measured separately (cold
start): fresh processes that import the codecs and time their first decode / encode calls,
once with the on-disk kernel cache and once with an empty cache (full compilation).

Peer note: expelliarmus' EVT 3.0 writer emits no TIME_HIGH words after the first, so its
EVT 3.0 file is read here with time_low_carry=True (see tests/test_codec_peer_expelliarmus.py).
A second EVT 3.0 file written by us (spec-conforming, with vectors) is timed as well; the
peer decodes the same count and x / y / p from it but misreads its times.
"""

from __future__ import annotations

import json
import os
import shutil
import statistics
import subprocess
import sys
from pathlib import Path

import numpy as np

from _common import (ROOT, TESTS, arg_parser, interleaved, load_average, machine, peak_traced_bytes, pyplot,
                     save_figure, write_results)

sys.path.insert(0, str(TESTS))     # synthetic_events: a test-only generator

from evdnerf_ros.events.codecs import decode, encode  # noqa: E402
from evdnerf_ros.io.raw import read_raw, write_raw  # noqa: E402
from synthetic_events import synthetic_events  # noqa: E402

PEER_DTYPE = np.dtype([("t", "<i8"), ("x", "<i2"), ("y", "<i2"), ("p", "u1")])


def to_peer(ev):
    a = np.empty(ev.size, PEER_DTYPE)
    a["t"] = ev["t"] // 1000
    a["x"], a["y"] = ev["x"], ev["y"]
    a["p"] = ev["p"] > 0
    return a


def same_as_source(ev, src) -> bool:
    return bool(np.array_equal(ev, src))


def peer_matches(arr, src, *, times=True) -> bool:
    ref = to_peer(src)
    keys = ("t", "x", "y", "p") if times else ("x", "y", "p")
    return arr is not None and arr.size == src.size and all(np.array_equal(arr[k], ref[k]) for k in keys)


def machine_info() -> dict:
    import expelliarmus  # noqa: F401 - fail here, before anything is written, when the peer is missing

    info = machine("numba", "expelliarmus")
    info.update(logical_cpus=info["cpus"], loadavg_start=load_average())
    return info


COLD_START_CODE = r"""
import json, sys, time
t0 = time.perf_counter()
sys.path.insert(0, sys.argv[1])
sys.path.insert(0, sys.argv[1] + "/tests")
from evdnerf_ros.events.codecs import decode, encode
from synthetic_events import synthetic_events
t1 = time.perf_counter()
ev = synthetic_events(1000, seed=0)
blobs = {enc: open(f"{sys.argv[2]}/{enc}.bin", "rb").read() for enc in ("evt3", "evt2")}
out = {"import_s": t1 - t0}
for enc in ("evt3", "evt2"):
    t = time.perf_counter()
    decode(blobs[enc], enc)
    out[f"first_decode_{enc}_s"] = time.perf_counter() - t
    t = time.perf_counter()
    decode(blobs[enc], enc)
    out[f"second_decode_{enc}_s"] = time.perf_counter() - t
for enc in ("evt3", "evt2"):
    t = time.perf_counter()
    encode(ev, enc)
    out[f"first_encode_{enc}_s"] = time.perf_counter() - t
print(json.dumps(out))
"""


def cold_start(tmp: Path, repeats: int = 3) -> dict:
    """Import + first-call times in fresh processes: with the kernel cache numba keeps on disk
    (populated by this run), and with an empty cache directory (every kernel compiles).
    The first kernel call of a process also pays numba's one-time code generator setup.
    Medians over `repeats` processes; decode calls get 1000-event streams."""
    src = synthetic_events(1000, seed=0)
    for enc in ("evt3", "evt2"):
        (tmp / f"{enc}.bin").write_bytes(encode(src, enc))
    res = {}
    for mode in ("cached", "no_cache"):
        runs = []
        for _ in range(repeats):
            env = dict(os.environ)
            empty = None
            if mode == "no_cache":
                empty = tmp / f"numba_cache_{len(runs)}"
                shutil.rmtree(empty, ignore_errors=True)
                env["NUMBA_CACHE_DIR"] = str(empty)
            r = subprocess.run([sys.executable, "-c", COLD_START_CODE, str(ROOT), str(tmp)], env=env,
                               capture_output=True, text=True, check=True)
            runs.append(json.loads(r.stdout.strip().splitlines()[-1]))
            if empty is not None:
                shutil.rmtree(empty, ignore_errors=True)
        res[mode] = {k: statistics.median(r[k] for r in runs) for k in runs[0]}
    return res


def main(argv=None):
    ap = arg_parser(__doc__, quick="~2e5 events, for a smoke run", out_aliases=("--out-dir",))
    ap.add_argument("--events", type=int, default=5_000_000)
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args(argv)
    n = 200_000 if args.quick else args.events
    from expelliarmus import Wizard

    out_dir = args.out
    tmp = out_dir / "tmp"
    tmp.mkdir(parents=True, exist_ok=True)
    info = machine_info()
    print(f"machine: {info['cpu']} x{info['logical_cpus']}, numpy {info['numpy']}, "
          f"expelliarmus {info['expelliarmus']}, load {info['loadavg_start']}")

    src = synthetic_events(n, duration_us=n, width=1280, height=720, seed=2024)
    gaps = np.diff(src["t"]) // 1000
    assert gaps.max(initial=0) < 4096, "stream too sparse for the peer's EVT 3.0 writer"
    files = {
        "evt3_peer": tmp / "peer_evt3.raw",
        "evt2_peer": tmp / "peer_evt2.raw",
        "evt3_ours": tmp / "ours_evt3.raw",
        "evt2_ours": tmp / "ours_evt2.raw",
    }
    for p in files.values():
        if p.exists():
            p.unlink()
    peer_src = to_peer(src)
    Wizard(encoding="evt3").save(str(files["evt3_peer"]), peer_src)
    Wizard(encoding="evt2").save(str(files["evt2_peer"]), peer_src)
    write_raw(files["evt3_ours"], src, width=1280, height=720, encoding="evt3")
    write_raw(files["evt2_ours"], src, width=1280, height=720, encoding="evt2")

    def peer_read(path, enc):
        w = Wizard(encoding=enc)
        w.set_file(str(path))
        return w.read()

    cases = {
        # name: (file, encoding, our read kwargs, peer values must match the source)
        "evt3 (peer-written file)": (files["evt3_peer"], "evt3", {"time_low_carry": True}, True),
        "evt2 (peer-written file)": (files["evt2_peer"], "evt2", {}, True),
        "evt3 (our file, vectors)": (files["evt3_ours"], "evt3", {}, False),
        "evt2 (our file)": (files["evt2_ours"], "evt2", {}, True),
    }
    results = {"events": n, "machine": info, "decode": {}, "encode": {}, "memory": {}}
    for name, (path, enc, kw, peer_exact) in cases.items():
        ours_d, _ = read_raw(path, **kw)
        theirs = peer_read(path, enc)
        check = {
            "ours_equals_source": same_as_source(ours_d.events, src),
            "peer_count_equals_source": bool(theirs is not None and theirs.size == n),
            "peer_values_equal_source": peer_matches(theirs, src, times=True),
            "peer_xyp_equal_source": peer_matches(theirs, src, times=False),
        }
        if not check["ours_equals_source"] or not check["peer_count_equals_source"]:
            raise SystemExit(f"{name}: verification failed: {check}")
        if peer_exact and not check["peer_values_equal_source"]:
            raise SystemExit(f"{name}: peer output differs from source: {check}")
        del ours_d, theirs
        tm = interleaved({                      # warm-up call each (page cache, allocator)
            "ours": lambda: read_raw(path, **kw),
            "peer": lambda: peer_read(path, enc),
        }, args.repeats, collect=True)
        row = {
            "file": path.name, "file_bytes": path.stat().st_size,
            "bytes_per_event": round(path.stat().st_size / n, 3), "checks": check,
            "ours_mev_s": n / tm["ours"]["median_s"] / 1e6,
            "peer_mev_s": n / tm["peer"]["median_s"] / 1e6,
            "timings": tm,
        }
        row["ratio_ours_over_peer"] = row["ours_mev_s"] / row["peer_mev_s"]
        results["decode"][name] = row
        print(f"decode {name:28s} ours {row['ours_mev_s']:7.1f} Mev/s  peer {row['peer_mev_s']:7.1f} "
              f"Mev/s  ratio {row['ratio_ours_over_peer']:.2f}")

    # encode: ours in memory and to a RAW file, the peer's save (to a file)
    for enc in ("evt3", "evt2"):
        scratch = {k: tmp / f"enc_{k}_{enc}.raw" for k in ("ours", "peer")}

        def ours_file():
            scratch["ours"].unlink(missing_ok=True)
            write_raw(scratch["ours"], src, width=1280, height=720, encoding=enc)

        def peer_file():
            Wizard(encoding=enc).save(str(scratch["peer"]), peer_src)

        assert np.array_equal(decode(encode(src, enc), enc).events, src)
        tm = interleaved({"ours_bytes": lambda: encode(src, enc), "ours_file": ours_file,
                          "peer_file": peer_file}, args.repeats, collect=True)
        row = {k: n / v["median_s"] / 1e6 for k, v in tm.items()}
        row = {f"{k}_mev_s": v for k, v in row.items()}
        row["ratio_ours_file_over_peer_file"] = row["ours_file_mev_s"] / row["peer_file_mev_s"]
        row["timings"] = tm
        results["encode"][enc] = row
        print(f"encode {enc}: ours(bytes) {row['ours_bytes_mev_s']:.1f}  ours(file) "
              f"{row['ours_file_mev_s']:.1f}  peer(file) {row['peer_file_mev_s']:.1f} Mev/s")
        for p in scratch.values():
            p.unlink(missing_ok=True)

    # memory: peak traced bytes (numpy allocations are traced) per million events
    mev = n / 1e6
    peer_itemsize = int(peer_read(files["evt2_peer"], "evt2").dtype.itemsize)
    mem = {}
    mem["decode evt3 (peer file) ours"] = peak_traced_bytes(lambda: read_raw(files["evt3_peer"], time_low_carry=True))
    mem["decode evt3 (peer file) peer"] = peak_traced_bytes(lambda: peer_read(files["evt3_peer"], "evt3"))
    mem["decode evt2 (peer file) ours"] = peak_traced_bytes(lambda: read_raw(files["evt2_peer"]))
    mem["decode evt2 (peer file) peer"] = peak_traced_bytes(lambda: peer_read(files["evt2_peer"], "evt2"))
    mem["decode evt3 (our file) ours"] = peak_traced_bytes(lambda: read_raw(files["evt3_ours"]))
    mem["encode evt3 bytes ours"] = peak_traced_bytes(lambda: encode(src, "evt3"))
    mem["encode evt2 bytes ours"] = peak_traced_bytes(lambda: encode(src, "evt2"))
    results["memory"] = {
        "method": "tracemalloc peak over the call (numpy buffers are traced; excludes the "
                  "input array already in memory; the numba kernels write into numpy-allocated "
                  "buffers and allocate nothing per event themselves)",
        "output_bytes_per_event": {"ours": 13, "peer": peer_itemsize},
        "peak_mb_per_mev": {k: v / 1e6 / mev for k, v in mem.items()},
    }
    for k, v in results["memory"]["peak_mb_per_mev"].items():
        print(f"memory {k:34s} {v:6.1f} MB per Mev")
    results["cold_start"] = cold_start(tmp)
    for mode, row in results["cold_start"].items():
        print(f"cold start ({mode}): import {1e3 * row['import_s']:.0f} ms, first decode evt3 "
              f"{1e3 * row['first_decode_evt3_s']:.0f} ms / evt2 {1e3 * row['first_decode_evt2_s']:.0f} ms, "
              f"first encode evt3 {1e3 * row['first_encode_evt3_s']:.0f} ms / evt2 "
              f"{1e3 * row['first_encode_evt2_s']:.0f} ms")
    results["machine"]["loadavg_end"] = load_average()
    results["summary"] = {
        "decode_ratio_evt3_peer_file": results["decode"]["evt3 (peer-written file)"]["ratio_ours_over_peer"],
        "decode_ratio_evt2_peer_file": results["decode"]["evt2 (peer-written file)"]["ratio_ours_over_peer"],
        "decode_ratio_evt3_our_file": results["decode"]["evt3 (our file, vectors)"]["ratio_ours_over_peer"],
        "decode_ratio_evt2_our_file": results["decode"]["evt2 (our file)"]["ratio_ours_over_peer"],
    }

    write_results(out_dir, "codecs", results, plot)
    shutil.rmtree(tmp, ignore_errors=True)
    return results


def plot(results, path):
    plt = pyplot()
    dec = results["decode"]
    enc = results["encode"]
    labels = [f"decode\n{k}" for k in dec] + [f"encode {k}\n(to RAW file)" for k in enc]
    ours = [r["ours_mev_s"] for r in dec.values()] + [r["ours_file_mev_s"] for r in enc.values()]
    peer = [r["peer_mev_s"] for r in dec.values()] + [r["peer_file_mev_s"] for r in enc.values()]
    x = np.arange(len(labels))
    fig, ax = plt.subplots(figsize=(11, 4.8))
    b1 = ax.bar(x - 0.2, ours, 0.4, label="evdnerf_ros (numba)")
    b2 = ax.bar(x + 0.2, peer, 0.4, label="expelliarmus (C)")
    for bars in (b1, b2):
        for b in bars:
            ax.annotate(f"{b.get_height():.0f}", (b.get_x() + b.get_width() / 2, b.get_height()),
                        ha="center", va="bottom", fontsize=8)
    ax.set_xticks(x, labels, fontsize=8)
    ax.set_ylabel("million events / s (median)")
    m = results["machine"]
    ax.set_title(f"RAW codec throughput, {results['events'] / 1e6:g} M events, same files, "
                 f"{m['cpu']} x{m['logical_cpus']}", fontsize=10)
    ax.legend()
    note = ("single-threaded numba kernels vs C; the peer-written EVT3 file is read with "
            "time_low_carry=True (its writer omits TIME_HIGH); the peer misreads the times of "
            "our (conforming) EVT3 file")
    cs = results.get("cold_start", {})
    if cs:
        c, u = cs["cached"], cs["no_cache"]
        note += (f"\nfresh process: import {1e3 * c['import_s']:.0f} ms, first EVT3 decode "
                 f"{1e3 * c['first_decode_evt3_s']:.0f} ms with cached kernels, "
                 f"{1e3 * u['first_decode_evt3_s']:.0f} ms compiling them (empty numba cache)")
    fig.text(0.01, 0.01, note, fontsize=7)
    save_figure(fig, path, dpi=120, layout={"rect": (0, 0.05, 1, 1)})


if __name__ == "__main__":
    main()
