"""Benchmark the USB camera drivers, one section per camera model.

    python bench/bench_camera.py [--quick] [--events N] [--repeats R]

Writes bench/results/camera.json and bench/results/camera.png (only at the end).

DVXplorer (iniVation, libcaer words):

* decode only: rig.camera.caer_words decoding the same bytes (a synthetic stream encoded by the
  twin's encoder: half readout-like bursts, half uniform scatter, checked against the source
  before timing), as one buffer and in the driver's 8 KiB transfers; medians of R runs;
* through the twin: rig.camera.virtual.dvxplorer.VirtualDVXplorer (not realtime: it streams as
  fast as the host reads) served by umockdev, our driver in a child process reading the whole
  stream (libcaer's 8 x 8 KiB transfers, and neuromorphic-drivers' 32 x 128 KiB), zero drops
  required; rate = events / wall seconds from start() to the last event, CPU = the child's
  process time per Mev; then neuromorphic-drivers (PyPI, Rust) reading the same twin in the
  same run: the ratio ours / theirs. The emulation caps transfers at ~1.5-3.5 k/s (see
  ../shared/notes/usb-virtual.md), so the twin rates say more about the emulation than about
  the decoders: the decode-only rate is the decoder's own.
"""

from __future__ import annotations

import json
import sys
import tempfile
import textwrap
from pathlib import Path

import numpy as np

from _common import arg_parser, describe, interleaved, load_average, machine, pyplot, save_figure, write_results

from evdnerf_ros.events.types import EVENT_DTYPE  # noqa: E402
from rig.camera.caer_words import CaerWordDecoder, canonical_order, encode_caer_words  # noqa: E402


def synthetic(n: int, span_us: int, seed: int = 0) -> np.ndarray:
    """Half readout-like bursts (same microsecond and column, neighbouring rows), half scatter."""
    rng = np.random.default_rng(seed)
    ev = np.empty(n, EVENT_DTYPE)
    t = np.sort(rng.integers(0, span_us, n))
    burst = rng.random(n) < 0.5
    ev["t"] = t * 1000
    ev["x"] = np.where(burst, (t * 7) % 640, rng.integers(0, 640, n))
    ev["y"] = np.where(burst, rng.integers(0, 60, n) * 8 + rng.integers(0, 8, n), rng.integers(0, 480, n))
    ev["p"] = rng.choice(np.array([-1, 1], np.int8), n)
    return canonical_order(ev)


# --------------------------------------------------------------------------- DVXplorer
def dvx_decode(n: int, repeats: int) -> dict:
    ev = synthetic(n, span_us=max(1, n // 4))          # ~4 Mev/s of sensor time
    data = encode_caer_words(ev)
    out, _ = CaerWordDecoder().feed(data)
    if not np.array_equal(out, ev):
        raise SystemExit("DVXplorer decode check failed: the decoder does not give back the source events")

    def whole():
        CaerWordDecoder().feed(data)

    def chunked():
        dec = CaerWordDecoder()
        for i in range(0, len(data), 8192):
            dec.feed(data[i:i + 8192])

    t = interleaved({"whole": whole, "chunks_8KiB": chunked}, repeats)
    return {"events": int(ev.size), "bytes": len(data), "bytes_per_event": len(data) / ev.size,
            "mev_s": {k: ev.size / v["median_s"] / 1e6 for k, v in t.items()},
            "best_mev_s": {k: ev.size / v["min_s"] / 1e6 for k, v in t.items()}, "timings": t}


OURS = """
import json, sys, time
import numpy as np
from rig.camera.dvxplorer import DVXplorer
n, transfers, size = int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4])
t0, c0 = time.monotonic(), time.process_time()
cam = DVXplorer(transfers=transfers, transfer_size=size, queue_chunks=65536).open()
cam.start()
got, t_first, t_last = 0, None, None
while got < n and time.monotonic() - t0 < 120:
    c = cam.read(2.0)
    if c is None:
        break
    if c.events.size:
        t_last = time.monotonic()
        t_first = t_first or t_last
        got += c.events.size
c1 = time.process_time()
s = cam.stats.as_dict()
cam.stop(); cam.close()
json.dump({"events": got, "open_to_first_s": t_first - t0, "open_to_last_s": t_last - t0,
           "stream_s": t_last - t_first, "cpu_s": c1 - c0, "dropped_chunks": s["dropped_chunks"],
           "transfers": s["transfers"]}, open(sys.argv[1], "w"))
"""

PEER = """
import json, sys, time
import neuromorphic_drivers as nd
n = int(sys.argv[2])
got, t_first, t_last = 0, None, None
t0, c0 = time.monotonic(), time.process_time()
with nd.open(iterator_timeout=0.5) as device:
    for status, packet in device:
        now = time.monotonic()
        if packet is not None and packet.polarity_events is not None and len(packet.polarity_events):
            t_last = now
            t_first = t_first or now
            got += len(packet.polarity_events)
        if got >= n or (t_last is not None and now - t_last > 2.0) or now - t0 > 120:
            break
    c1 = time.process_time()
json.dump({"events": got, "open_to_first_s": t_first - t0, "open_to_last_s": t_last - t0,
           "stream_s": t_last - t_first, "cpu_s": c1 - c0}, open(sys.argv[1], "w"))
"""


def dvx_twin(n: int) -> dict:
    from rig.camera.virtual.dvxplorer import VirtualDVXplorer
    from rig.camera.virtual.usb import VirtualUsbBus, run_child, umockdev_available

    ok, why = umockdev_available()
    if not ok:
        return {"skipped": why}
    ev = synthetic(n, span_us=max(1, n // 2), seed=1)      # 2 Mev/s of sensor time
    n = int(ev.size)                                        # repeats of a pixel in one us collapsed
    runs = {}
    with tempfile.TemporaryDirectory() as tmp:
        for name, code, args, kw in (
                ("ours_8x8KiB", OURS, [n, 8, 8192], {}),
                ("ours_32x128KiB", OURS, [n, 32, 131072], {}),
                ("neuromorphic_drivers", PEER, [n], {"firmware": 9, "logic_patch": 4})):
            twin = VirtualDVXplorer(ev, realtime=False, step_us=20_000, idle_wraps=False, **kw)
            with VirtualUsbBus() as bus:
                bus.add(twin)
                script = Path(tmp) / f"child_{name}.py"
                script.write_text(textwrap.dedent(code))
                out = Path(tmp) / f"{name}.json"
                res = run_child([sys.executable, str(script), str(out), *map(str, args)], bus, timeout=300)
                if res.returncode != 0:
                    raise SystemExit(f"{name} failed:\n{res.stdout}\n{res.stderr[-3000:]}")
                r = json.loads(out.read_text())
                r["twin_events"] = int(twin.emitted_events().size)
                r["twin_bytes"] = twin.bytes_streamed
                r["mev_s"] = r["events"] / r["open_to_last_s"] / 1e6          # open + start included
                r["stream_mev_s"] = r["events"] / max(r["stream_s"], 1e-9) / 1e6  # first to last event
                r["complete"] = r["events"] == n
                r["cpu_s_per_mev"] = r["cpu_s"] / max(r["events"], 1) * 1e6
                runs[name] = r
    for k in ("ours_8x8KiB", "ours_32x128KiB"):
        if not runs[k]["complete"] or runs[k]["dropped_chunks"]:
            raise SystemExit(f"{k}: {runs[k]['events']} of {n} events, {runs[k]['dropped_chunks']} drops")
    peer = runs["neuromorphic_drivers"]["mev_s"]
    return {"events": n, "runs": runs,
            "ratio_vs_peer": {k: runs[k]["mev_s"] / peer for k in ("ours_8x8KiB", "ours_32x128KiB")}}


def plot(result, path):
    plt = pyplot()
    d = result["dvxplorer"]
    fig, ax = plt.subplots(1, 2, figsize=(10, 4))
    dec = d["decode"]["mev_s"]
    ax[0].bar(list(dec), list(dec.values()), color="tab:blue")
    ax[0].axhline(50, color="k", ls="--", lw=1, label="goal 50 Mev/s")
    ax[0].set_ylabel("Mev/s")
    ax[0].set_title("DVXplorer word decode (same bytes)")
    ax[0].legend()
    tw = d["twin"]
    if "runs" in tw:
        names = list(tw["runs"])
        ax[1].bar(names, [tw["runs"][k]["mev_s"] for k in names], color=["tab:blue", "tab:blue", "tab:gray"])
        ax[1].set_title("through the umockdev twin (zero drops)")
        ax[1].set_ylabel("Mev/s")
        ax[1].tick_params(axis="x", labelrotation=15)
    else:
        ax[1].text(0.5, 0.5, tw.get("skipped", "skipped"), ha="center", wrap=True)
    fig.suptitle(f"camera drivers ({describe(result['machine'])})")
    save_figure(fig, path)


def main() -> None:
    ap = arg_parser(__doc__)
    ap.add_argument("--events", type=int, default=None, help="decode benchmark events (default 4M, quick 500k)")
    ap.add_argument("--repeats", type=int, default=None)
    args = ap.parse_args()
    n = args.events or (500_000 if args.quick else 4_000_000)
    reps = args.repeats or (3 if args.quick else 7)
    info = machine("numba", "neuromorphic-drivers", "libusb1")
    info["loadavg_start"] = load_average()
    result = {"machine": info, "dvxplorer": {}}
    result["dvxplorer"]["decode"] = dvx_decode(n, reps)
    print("DVXplorer decode Mev/s:", {k: round(v, 1) for k, v in result["dvxplorer"]["decode"]["mev_s"].items()})
    result["dvxplorer"]["twin"] = dvx_twin(200_000 if args.quick else 4_000_000)
    tw = result["dvxplorer"]["twin"]
    if "runs" in tw:
        print("DVXplorer twin Mev/s:", {k: round(v["mev_s"], 2) for k, v in tw["runs"].items()},
              "ratio:", {k: round(v, 2) for k, v in tw["ratio_vs_peer"].items()})
    info["loadavg_end"] = load_average()
    write_results(args.out, "camera", result, plot)


if __name__ == "__main__":
    main()
