"""A camera's bytes into a bag: passed through untouched against decoded and re-encoded, and
EVT files of absolute (epoch) times: sensor time from zero against from the epoch.

    python bench/bench_packetizer.py [--quick] [--out bench/results]

Writes ``packetizer.json`` and ``packetizer.png`` into ``--out``.

* **Pass-through**: an EVT 3.0 stream as a Prophesee camera delivers it (1280 x 720, random
  events at ~10 Mev/s of sensor time, cut into 64 KiB USB buffers of whole words) recorded
  into an MCAP rosbag2 two ways, alternating, median of the repeats: each buffer wrapped in an
  EventPacket as it is (``write_raw_packet``: what the capture node does), and each buffer
  decoded (streaming decoder) and its events re-encoded into packets (``write_events``: the
  only way before the packetizer). Both bags are read back: their events must be identical,
  and the pass-through payloads byte-identical to the camera's buffers.
* **Absolute times**: 0.6 s of events at a 2023 epoch time written as EVT 3.0 / 2.0 RAW
  files by ``write_raw`` (sensor time starts near zero, the origin in ``% t0``) against the
  codec encoding from time zero (``time_base_ns=0``: a TIME_HIGH every 2^22 us since 1970);
  file sizes and write times. Both read back to the same events.
"""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path

import numpy as np

from _common import arg_parser, interleaved, load_average, machine, pyplot, save_figure, timed, write_results

from evdnerf_ros.events import make_events  # noqa: E402
from evdnerf_ros.events.codecs import encode, make_decoder  # noqa: E402
from evdnerf_ros.io.raw import read_raw, write_raw  # noqa: E402
from evdnerf_ros.io.rosbag2 import BagWriter, open_bag, read_events  # noqa: E402
from evdnerf_ros.topics import EVENTS  # noqa: E402

W, H = 1280, 720
USB_BUFFER = 64 << 10
EPOCH_NS = 1_700_000_000_000_000_000      # Nov 2023


def camera_events(n: int, rate_hz: float, t0_ns: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    t_us = np.cumsum(rng.exponential(1e6 / rate_hz, n)).astype(np.int64)
    return make_events(t0_ns + 1000 * t_us, rng.integers(0, W, n), rng.integers(0, H, n),
                       np.where(rng.random(n) < 0.5, 1, -1))


def usb_buffers(stream: bytes) -> list[bytes]:
    return [stream[i:i + USB_BUFFER] for i in range(0, len(stream), USB_BUFFER)]


def record_pass_through(path: Path, buffers: list[bytes], stamps: list[int]) -> None:
    with BagWriter(path) as bag:
        for buf, stamp in zip(buffers, stamps):
            bag.write_raw_packet(EVENTS, buf, encoding="evt3", width=W, height=H, stamp_ns=stamp)


def record_reencoded(path: Path, buffers: list[bytes]) -> None:
    dec = make_decoder("evt3")
    with BagWriter(path) as bag:
        for buf in buffers:
            out = dec.feed(buf)
            if out.events.size:
                bag.write_events(EVENTS, out.events, width=W, height=H)


def pass_through(n: int, repeats: int, tmp: Path) -> dict:
    ev = camera_events(n, 10e6, 0)
    stream = encode(ev, "evt3")
    buffers = usb_buffers(stream)
    # a camera's host stamp of each buffer: the time of its first event (as metavision_driver stamps)
    dec = make_decoder("evt3")
    stamps, last = [], int(ev["t"][0])
    for buf in buffers:
        out = dec.feed(buf)
        last = int(out.events["t"][0]) if out.events.size else last
        stamps.append(last)
    paths = {"pass_through": tmp / "raw_bag", "decode_reencode": tmp / "reencoded_bag"}

    def run(kind):
        def go():
            p = paths[kind]
            shutil.rmtree(p, ignore_errors=True)
            if kind == "pass_through":
                record_pass_through(p, buffers, stamps)
            else:
                record_reencoded(p, buffers)
        return go

    times = interleaved({k: run(k) for k in paths}, repeats)
    back = {k: read_events(p, EVENTS).events for k, p in paths.items()}
    with open_bag(paths["pass_through"]) as bag:
        payloads = [pk for pk in bag.read_messages(EVENTS)]
    identical = all(bytes(m.events) == b for (_, m), b in zip(payloads, buffers)) and len(payloads) == len(buffers)
    result = {"events": n, "stream_bytes": len(stream), "usb_buffers": len(buffers),
              "events_equal": bool(np.array_equal(back["pass_through"], ev) and
                                   np.array_equal(back["decode_reencode"], ev)),
              "payloads_byte_identical": bool(identical)}
    for k, p in paths.items():
        t = times[k]["median_s"]
        result[k] = {**times[k], "mev_per_s": n / t / 1e6, "bag_bytes": sum(f.stat().st_size for f in p.rglob("*"))}
    result["speedup"] = times["decode_reencode"]["median_s"] / times["pass_through"]["median_s"]
    return result


def absolute_times(n: int, tmp: Path, naive: bool) -> dict:
    ev = camera_events(n, n / 0.6, EPOCH_NS, seed=1)
    out = {"events": n, "span_s": float((ev["t"][-1] - ev["t"][0]) / 1e9), "first_ns": int(ev["t"][0])}
    for enc in ("evt3", "evt2"):
        path = tmp / f"epoch.{enc}.raw"
        wall, _ = timed(lambda: write_raw(path, ev, width=W, height=H, encoding=enc))
        back = read_raw(path)[0].events
        rec = {"origin_bytes": path.stat().st_size, "origin_write_s": wall, "exact": bool(np.array_equal(back, ev))}
        if naive:
            wall, data = timed(lambda: encode(ev, enc, time_base_ns=0))
            rec.update(naive_bytes=len(data), naive_encode_s=wall)
            rec["size_ratio"] = rec["naive_bytes"] / rec["origin_bytes"]
            del data
        out[enc] = rec
    return out


def plot(result: dict, path: Path) -> None:
    plt = pyplot()
    fig, ax = plt.subplots(1, 2, figsize=(10, 3.8))
    pt = result["pass_through"]
    names = ["pass_through", "decode_reencode"]
    ax[0].bar(names, [pt[k]["mev_per_s"] for k in names], color=["tab:green", "tab:gray"])
    ax[0].set_ylabel("Mev/s into an MCAP bag (median)")
    ax[0].set_title(f"EVT 3.0 camera buffers, {pt['events'] / 1e6:.0f} M events: x{pt['speedup']:.1f}",
                    fontsize=9)
    ab = result["absolute_times"]
    encs = ["evt3", "evt2"]
    x = np.arange(len(encs))
    ax[1].bar(x - 0.2, [ab[e]["origin_bytes"] / 1e6 for e in encs], 0.4, label="sensor time from ~0, % t0")
    if "naive_bytes" in ab["evt3"]:
        ax[1].bar(x + 0.2, [ab[e]["naive_bytes"] / 1e6 for e in encs], 0.4, label="from the epoch (before)")
    ax[1].set_xticks(x, encs)
    ax[1].set_yscale("log")
    ax[1].set_ylabel("file MB")
    ax[1].set_title(f"{ab['events']} events over {ab['span_s']:.1f} s at a 2023 epoch", fontsize=9)
    ax[1].legend(fontsize=8)
    save_figure(fig, path)


def main(argv=None) -> None:
    ap = arg_parser(__doc__)
    ap.add_argument("--repeats", type=int, default=None)
    args = ap.parse_args(argv)
    n, repeats = (500_000, 3) if args.quick else (4_000_000, 5)
    with tempfile.TemporaryDirectory() as td:
        result = {"benchmark": "packetizer", "machine": machine("rosbags"), "load_before": load_average(),
                  "pass_through": pass_through(n, args.repeats or repeats, Path(td)),
                  "absolute_times": absolute_times(100_000, Path(td), naive=not args.quick)}
    result["load_after"] = load_average()
    write_results(args.out, "packetizer_quick" if args.quick else "packetizer", result, plot)


if __name__ == "__main__":
    main()
