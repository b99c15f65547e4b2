"""Benchmark the USB camera drivers, one section per camera model.

    python bench/bench_camera.py [--quick] [--events N] [--repeats R]

Writes bench/results/camera.json and bench/results/camera.png (only at the end).

DVXplorer (iniVation, libcaer words):

* decode only: rig.camera.caer_words decoding the same bytes (a synthetic stream encoded by the
  twin's encoder: half readout-like bursts, half uniform scatter, checked against the source
  before timing), as one buffer and in the driver's 8 KiB transfers; medians of R runs;
* through the twin (both cameras; EVK4: 32 x 128 KiB): rig.camera.virtual.dvxplorer.VirtualDVXplorer (not realtime: it streams as
  fast as the host reads) served by umockdev, our driver in a child process reading the whole
  stream (libcaer's 8 x 8 KiB transfers, and neuromorphic-drivers' 32 x 128 KiB), zero drops
  required; rate = events / wall seconds from start() to the last event, CPU = the child's
  process time per Mev; then neuromorphic-drivers (PyPI, Rust) reading the same twin in the
  same run: the ratio ours / theirs. The emulation caps transfers at ~1.5-3.5 k/s (see
  ../shared/notes/usb-virtual.md), so the twin rates say more about the emulation than about
  the decoders: the decode-only rate is the decoder's own.

EVK4 (Prophesee, EVT 3.0): decode only on the exact bytes the twin streamed to our driver (our
codec whole and in 128 KiB transfers vs expelliarmus: rate and event count only, its EVT3 times
are wrong), and the twin runs as above (ours vs neuromorphic-drivers, ratio and CPU per Mev).

Both cameras: start-up (open() to first event, median of 5 opens, 3 with --quick, ours and
neuromorphic-drivers on the same twin), and the clock-mapping error: the driver's ClockMap
(one-sided fit of chunk arrivals) against a realtime twin's truth (it emits sensor time t at host
monotonic time t0 + t; t0 read from the twin's ``_t0_ns``) after 0.5, 1, 2, 5 s of recording:
median / p95 / max |error| in us. --quick: ~1.5 min; full: a few minutes.
"""

from __future__ import annotations

import json
import sys
import tempfile
import textwrap
from pathlib import Path

import numpy as np

from _common import arg_parser, describe, interleaved, load_average, machine, pyplot, read_results, save_figure, write_results

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
n, transfers, size = int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4])
model = sys.argv[5] if len(sys.argv) > 5 else "dvx"
if model == "dvx":
    from rig.camera.dvxplorer import DVXplorer as Cam
    kw = {}
else:
    from rig.camera.evk4 import EVK4 as Cam
    kw = {"settle": False}
t0, c0 = time.monotonic(), time.process_time()
cam = Cam(transfers=transfers, transfer_size=size, queue_chunks=65536, **kw).open()
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


CLOCK = """
import json, sys, time
import numpy as np
model, lengths = sys.argv[2], [float(x) for x in sys.argv[3].split(",")]
if model == "dvx":
    from rig.camera.dvxplorer import DVXplorer as Cam
    kw = {}
else:
    from rig.camera.evk4 import EVK4 as Cam
    kw = {"settle": False}
cam = Cam(**kw).open()
cam.start()
t0 = time.monotonic()
fits, sensor = [], []
for L in lengths:
    while time.monotonic() - t0 < L:
        c = cam.read(0.5)
        if c is not None and c.events.size:
            sensor.append(int(c.events["t"][-1]))
    cm = cam.clock
    fits.append({"length_s": L, "offset_ns": cm.offset_ns, "scale": cm.scale, "device_ref_us": cm.device_ref_us,
                 "samples": cm.samples, "n_sensor": len(sensor)})
cam.stop(); cam.close()
json.dump({"fits": fits, "sensor_ns": sensor}, open(sys.argv[1], "w"))
"""


def _twin(model, ev, **kw):
    if model == "dvx":
        from rig.camera.virtual.dvxplorer import VirtualDVXplorer
        return VirtualDVXplorer(ev, **kw)
    from rig.camera.virtual.evk4 import VirtualEVK4
    kw.pop("idle_wraps", None)
    kw.pop("firmware", None)
    kw.pop("logic_patch", None)
    return VirtualEVK4(ev, **kw)


def _child(tmp, bus, name, code, args, timeout=300):
    from rig.camera.virtual.usb import run_child
    script = Path(tmp) / f"child_{name}.py"
    script.write_text(textwrap.dedent(code))
    out = Path(tmp) / f"{name}.json"
    res = run_child([sys.executable, str(script), str(out), *map(str, args)], bus, timeout=timeout)
    if res.returncode != 0:
        raise SystemExit(f"{name} failed:\n{res.stdout}\n{res.stderr[-3000:]}")
    return json.loads(out.read_text())


def synthetic_evk4(n: int, span_us: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    ev = np.empty(n, EVENT_DTYPE)
    ev["t"] = np.sort(rng.integers(0, span_us, n)) * 1000
    ev["x"] = rng.integers(0, 1280, n)
    ev["y"] = rng.integers(0, 720, n)
    ev["p"] = rng.choice(np.array([-1, 1], np.int8), n)
    return ev


def twin_rates(model: str, n: int) -> dict:
    """Sustained rate + CPU per Mev through the twin, ours vs neuromorphic-drivers, same run."""
    from rig.camera.virtual.usb import VirtualUsbBus, umockdev_available
    ok, why = umockdev_available()
    if not ok:
        return {"skipped": why}
    if model == "dvx":
        ev = synthetic(n, span_us=max(1, n // 2), seed=1)        # 2 Mev/s of sensor time
        cases = (("ours_8x8KiB", OURS, [8, 8192, "dvx"], {}),
                 ("ours_32x128KiB", OURS, [32, 131072, "dvx"], {}),
                 ("neuromorphic_drivers", PEER, [], {"firmware": 9, "logic_patch": 4}))
        twin_kw = {"realtime": False, "step_us": 20_000, "idle_wraps": False}
    else:
        ev = synthetic_evk4(n, span_us=max(1, n // 2), seed=1)
        cases = (("ours_32x128KiB", OURS, [32, 131072, "evk4"], {}),
                 ("neuromorphic_drivers", PEER, [], {}))
        twin_kw = {"realtime": False, "step_us": 20_000}
    n = int(ev.size)
    runs, streamed = {}, None
    with tempfile.TemporaryDirectory() as tmp:
        for name, code, args, kw in cases:
            twin = _twin(model, ev, **twin_kw, **kw)
            with VirtualUsbBus() as bus:
                bus.add(twin)
                r = _child(tmp, bus, f"{model}_{name}", code, [n, *args])
            r["twin_events"] = int(twin.emitted_events().size)
            r["twin_bytes"] = twin.bytes_streamed
            r["mev_s"] = r["events"] / r["open_to_last_s"] / 1e6          # open + start included
            r["stream_mev_s"] = r["events"] / max(r["stream_s"], 1e-9) / 1e6  # first to last event
            r["complete"] = r["events"] == n
            r["cpu_s_per_mev"] = r["cpu_s"] / max(r["events"], 1) * 1e6
            runs[name] = r
            if model == "evk4" and name.startswith("ours") and streamed is None:
                streamed = bytes(twin.streamed)
    ours = [k for k in runs if k.startswith("ours")]
    for k in ours:
        if not runs[k]["complete"] or runs[k]["dropped_chunks"]:
            raise SystemExit(f"{model} {k}: {runs[k]['events']} of {n} events, {runs[k]['dropped_chunks']} drops")
    peer = runs["neuromorphic_drivers"]
    out = {"events": n, "runs": runs,
           "ratio_vs_peer": {k: runs[k]["mev_s"] / peer["mev_s"] for k in ours},
           "cpu_ratio_vs_peer": {k: runs[k]["cpu_s_per_mev"] / peer["cpu_s_per_mev"] for k in ours}}
    if streamed is not None:
        out["_streamed"] = streamed
        out["_source"] = ev
    return out


def startup(model: str, repeats: int) -> dict:
    """open() to first event, median over `repeats` opens, ours and neuromorphic-drivers."""
    from rig.camera.virtual.usb import VirtualUsbBus, umockdev_available
    ok, why = umockdev_available()
    if not ok:
        return {"skipped": why}
    n = 20_000
    ev = synthetic(n, n, seed=2) if model == "dvx" else synthetic_evk4(n, n, seed=2)
    n = int(ev.size)
    size = (8, 8192) if model == "dvx" else (32, 131072)
    peer_kw = {"firmware": 9, "logic_patch": 4} if model == "dvx" else {}
    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        for name, code, args, kw in (("ours", OURS, [*size, model], {}),
                                     ("neuromorphic_drivers", PEER, [], peer_kw)):
            vals = []
            for i in range(repeats):
                twin = _twin(model, ev, realtime=False, step_us=20_000, idle_wraps=False, **kw)
                with VirtualUsbBus() as bus:
                    bus.add(twin)
                    vals.append(_child(tmp, bus, f"start_{model}_{name}_{i}", code, [n, *args])["open_to_first_s"])
            out[name] = {"median_s": float(np.median(vals)), "min_s": float(np.min(vals)),
                         "max_s": float(np.max(vals)), "runs_s": vals}
    out["ratio_vs_peer"] = out["ours"]["median_s"] / out["neuromorphic_drivers"]["median_s"]
    return out


def clock_error(model: str, lengths) -> dict:
    """The driver's ClockMap (fitted from chunk arrivals) against the twin's truth: a realtime
    twin emits sensor time t at host time t0 + t (t0 = its time-base start, monotonic ns,
    the clock the driver stamps arrivals with); error = map(t) - truth over the sensor times
    the driver saw, per recording length."""
    from rig.camera.virtual.usb import VirtualUsbBus, umockdev_available
    ok, why = umockdev_available()
    if not ok:
        return {"skipped": why}
    span = int(max(lengths) + 3) * 1_000_000
    n = span // 20                                        # 50 kev/s of sensor time
    ev = synthetic(n, span, seed=5) if model == "dvx" else synthetic_evk4(n, span, seed=5)
    twin = _twin(model, ev, realtime=True)
    with tempfile.TemporaryDirectory() as tmp, VirtualUsbBus() as bus:
        bus.add(twin)
        r = _child(tmp, bus, f"clock_{model}", CLOCK, [model, ",".join(map(str, lengths))])
    t0 = int(twin._t0_ns)                                 # the twin's host time of sensor time 0
    sensor = np.asarray(r["sensor_ns"], np.int64)
    curve = []
    for f in r["fits"]:
        s = sensor[:f["n_sensor"]]
        d = s - np.int64(f["device_ref_us"]) * 1000
        host = np.rint(f["offset_ns"] + f["scale"] * (d.astype(np.float64) / 1000.0)).astype(np.int64)
        truth = t0 + s                                    # +0..1 us: the twin stamps whole microseconds
        err_us = np.abs(host - truth) / 1000.0
        curve.append({"length_s": f["length_s"], "samples": f["samples"], "points": int(s.size),
                      "median_us": float(np.median(err_us)), "p95_us": float(np.percentile(err_us, 95)),
                      "max_us": float(err_us.max()), "signed_median_us": float(np.median(host - truth) / 1000.0),
                      "drift_ppm": (f["scale"] / 1000.0 - 1.0) * 1e6})
    return {"curve": curve}


def evk4_decode(streamed: bytes, source: np.ndarray, repeats: int) -> dict:
    """EVT 3.0 decode only on the bytes the twin streamed: ours vs expelliarmus (rate and count)."""
    from evdnerf_ros.events.codecs import make_decoder
    dec = make_decoder("evt3")
    ours = dec.feed(streamed).events
    if not np.array_equal(ours, source[:ours.size]) or ours.size != source.size:
        raise SystemExit(f"EVK4 decode check failed: {ours.size} of {source.size} events, or not equal")

    def whole():
        make_decoder("evt3").feed(streamed)

    def chunked():
        d = make_decoder("evt3")
        for i in range(0, len(streamed), 131072):
            d.feed(streamed[i:i + 131072])

    funcs = {"ours_whole": whole, "ours_chunks_128KiB": chunked}
    peer_note = None
    try:
        from expelliarmus import Wizard
        path = Path(tempfile.mkdtemp()) / "twin.raw"
        path.write_bytes(b"% evt 3.0\n% format EVT3;height=720;width=1280\n% end\n" + streamed)
        w = Wizard(encoding="evt3")
        w.set_file(str(path))
        peer_n = int(len(w.read()))

        def peer():
            w.read()
        funcs["expelliarmus"] = peer
    except Exception as exc:            # the peer is optional here
        peer_n, peer_note = None, f"expelliarmus unavailable: {exc}"
    t = interleaved(funcs, repeats)
    out = {"events": int(ours.size), "bytes": len(streamed), "bytes_per_event": len(streamed) / ours.size,
           "mev_s": {k: ours.size / v["median_s"] / 1e6 for k, v in t.items()},
           "peer_events": peer_n, "peer_count_matches": peer_n == ours.size, "timings": t,
           "note": "expelliarmus gets EVT3 times wrong (see bench_codecs); rate and count only"}
    if peer_note:
        out["peer_note"] = peer_note
    return out


def plot(result, path):
    plt = pyplot()
    fig, ax = plt.subplots(2, 3, figsize=(15, 8))
    d, e = result["dvxplorer"], result["evk4"]
    dec = d["decode"]["mev_s"]
    ax[0, 0].bar(list(dec), list(dec.values()), color="tab:blue")
    ax[0, 0].axhline(50, color="k", ls="--", lw=1, label="goal 50 Mev/s")
    ax[0, 0].set_ylabel("Mev/s")
    ax[0, 0].set_title("DVXplorer word decode (same bytes)")
    ax[0, 0].legend()
    if "mev_s" in e.get("decode", {}):
        ed = e["decode"]["mev_s"]
        ax[1, 0].bar(list(ed), list(ed.values()), color=["tab:orange", "tab:orange", "tab:gray"][:len(ed)])
        ax[1, 0].set_title("EVK4 EVT 3.0 decode (twin's bytes)")
        ax[1, 0].set_ylabel("Mev/s")
    for row, (label, sec) in enumerate((("DVXplorer", d), ("EVK4", e))):
        tw = sec.get("twin", {})
        a = ax[row, 1]
        if "runs" in tw:
            names = list(tw["runs"])
            x = np.arange(len(names))
            a.bar(x - 0.2, [tw["runs"][k]["mev_s"] for k in names], 0.4, label="Mev/s")
            a2 = a.twinx()
            a2.bar(x + 0.2, [tw["runs"][k]["cpu_s_per_mev"] for k in names], 0.4, color="tab:red",
                   label="CPU s / Mev")
            a2.set_ylabel("CPU s per Mev", color="tab:red")
            a.set_xticks(x, names, rotation=10, fontsize=8)
            a.set_ylabel("Mev/s")
            a.set_title(f"{label} through the twin (zero drops)")
        st = sec.get("startup", {})
        if "ours" in st:
            ax[row, 1].text(0.02, 0.95, f"open->first event: ours {st['ours']['median_s']*1e3:.0f} ms, "
                            f"peer {st['neuromorphic_drivers']['median_s']*1e3:.0f} ms",
                            transform=ax[row, 1].transAxes, fontsize=8, va="top")
        ck = sec.get("clock", {})
        a = ax[row, 2]
        if "curve" in ck:
            L = [c["length_s"] for c in ck["curve"]]
            for key in ("median_us", "p95_us", "max_us"):
                a.plot(L, [c[key] for c in ck["curve"]], "o-", label=key[:-3])
            a.set_xlabel("recording length (s)")
            a.set_ylabel("|clock map - truth| (us)")
            a.set_title(f"{label} clock mapping error")
            a.legend()
    fig.suptitle(f"camera drivers ({describe(result['machine'])})")
    fig.tight_layout()
    save_figure(fig, path)


def main() -> None:
    ap = arg_parser(__doc__)
    ap.add_argument("--events", type=int, default=None, help="decode benchmark events (default 4M, quick 500k)")
    ap.add_argument("--repeats", type=int, default=None)
    ap.add_argument("--only", choices=["dvx-decode"], help="rerun only this part; the other parts of the "
                    "existing results file are kept")
    args = ap.parse_args()
    n = args.events or (500_000 if args.quick else 4_000_000)
    reps = args.repeats or (3 if args.quick else 7)
    opens = 3 if args.quick else 5
    lengths = (0.5, 1.0, 2.0) if args.quick else (0.5, 1.0, 2.0, 5.0)
    info = machine("numba", "neuromorphic-drivers", "libusb1", "expelliarmus")
    info["loadavg_start"] = load_average()
    result = {"machine": info, "dvxplorer": {}, "evk4": {}}
    if args.only:
        result = {**read_results(args.out, "camera"), "machine_" + args.only: info}
    dv, e4 = result["dvxplorer"], result["evk4"]
    dv["decode"] = dvx_decode(n, reps)
    print("DVXplorer decode Mev/s:", {k: round(v, 1) for k, v in dv["decode"]["mev_s"].items()}, flush=True)
    if args.only:
        info["loadavg_end"] = load_average()
        write_results(args.out, "camera", result, plot)
        return
    dv["twin"] = twin_rates("dvx", 200_000 if args.quick else 2_000_000)
    e4["twin"] = twin_rates("evk4", 200_000 if args.quick else 2_000_000)
    for label, sec in (("DVXplorer", dv), ("EVK4", e4)):
        tw = sec["twin"]
        if "runs" in tw:
            print(f"{label} twin Mev/s:", {k: round(v["mev_s"], 2) for k, v in tw["runs"].items()},
                  "CPU s/Mev:", {k: round(v["cpu_s_per_mev"], 2) for k, v in tw["runs"].items()},
                  "ratio:", {k: round(v, 2) for k, v in tw["ratio_vs_peer"].items()}, flush=True)
    if "_streamed" in e4["twin"]:
        e4["decode"] = evk4_decode(e4["twin"].pop("_streamed"), e4["twin"].pop("_source"), reps)
        print("EVK4 decode Mev/s:", {k: round(v, 1) for k, v in e4["decode"]["mev_s"].items()},
              "peer count ok:", e4["decode"]["peer_count_matches"], flush=True)
    for label, model, sec in (("DVXplorer", "dvx", dv), ("EVK4", "evk4", e4)):
        sec["startup"] = startup(model, opens)
        if "ours" in sec["startup"]:
            print(f"{label} open->first event median s:", round(sec["startup"]["ours"]["median_s"], 3),
                  "peer:", round(sec["startup"]["neuromorphic_drivers"]["median_s"], 3), flush=True)
        sec["clock"] = clock_error(model, lengths)
        if "curve" in sec["clock"]:
            print(f"{label} clock error us (L: median/p95/max):",
                  [(c["length_s"], round(c["median_us"], 1), round(c["p95_us"], 1), round(c["max_us"], 1))
                   for c in sec["clock"]["curve"]], flush=True)
    info["loadavg_end"] = load_average()
    write_results(args.out, "camera", result, plot)


if __name__ == "__main__":
    main()
