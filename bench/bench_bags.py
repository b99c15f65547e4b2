"""Bag write / read throughput of event topics (and memory), against rosbags' per-object path.

    python bench/bench_bags.py [--events 5e6] [--rate 5e6] [--sparse-events 2e6 --sparse-rate 1e5] [--quick]

Cases (each timed as the median of --repeats runs, whole bag write incl. close / whole
topic read incl. open): EventPacket evt3 and mono (MCAP), dvs_msgs EventArray on MCAP,
sqlite3 and ROS 1. The peer is rosbags' own per-message path for an EventArray: building
one Event object per event and calling ``serialize_cdr`` (write) / ``deserialize_cdr`` +
converting the Event objects to numpy (read), measured on a small subset and extrapolated
per Mev (labelled as such). Peak memory (tracemalloc, one separate run) is reported per
million events. A second, sparse scenario (default 2e6 events at 1e5 ev/s: 100 events per
1 ms packet, 20 s, crossing the 16.8 s EVT3 time wrap) shows the per-message costs.
Writes bench/results/bags.json and bench/results/bags.png.
"""

from __future__ import annotations

import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from _common import (arg_parser, describe, interleaved, load_average, machine, peak_traced_bytes, pyplot,
                     save_figure, write_results)

from evdnerf_ros.events.types import make_events  # noqa: E402
from evdnerf_ros.io.rosbag1 import Rosbag1Writer  # noqa: E402
from evdnerf_ros.io.rosbag2 import BagWriter, read_events  # noqa: E402
from evdnerf_ros.io.typestore import DVS_EVENT_ARRAY, ros2_typestore  # noqa: E402

W, H = 1280, 720  # an EVK4-class sensor
T0 = 1_700_000_000_000_000_000
TOPIC = "/event_camera/events"
GOAL_MEV_S = 20.0

CASES = [  # name, encoding, storage
    ("EventPacket evt3 / mcap", "evt3", "mcap"),
    ("EventPacket mono / mcap", "mono", "mcap"),
    ("EventArray / mcap", "array", "mcap"),
    ("EventArray / sqlite3", "array", "sqlite3"),
    ("EventArray / ROS 1 bag", "array", "ros1"),
]


def synth_events(n: int, rate: float, seed: int = 0) -> np.ndarray:
    """n events at about `rate` ev/s on the µs grid (what a Prophesee sensor delivers)."""
    rng = np.random.default_rng(seed)
    span_us = max(1, int(n / rate * 1e6))
    t = T0 + np.sort(rng.integers(0, span_us, n)) * 1000
    return make_events(t, rng.integers(0, W, n), rng.integers(0, H, n), rng.random(n) < 0.5)


def write_bag(path: Path, events, encoding: str, storage: str, packet_ns: int) -> None:
    if storage == "ros1":
        with Rosbag1Writer(path) as w:
            w.write_events(TOPIC, events, width=W, height=H, encoding=encoding, packet_ns=packet_ns)
    else:
        with BagWriter(path, storage=storage) as w:
            w.write_events(TOPIC, events, width=W, height=H, encoding=encoding, packet_ns=packet_ns)


def bag_bytes(path: Path) -> int:
    if path.is_dir():
        return sum(f.stat().st_size for f in path.iterdir())
    return path.stat().st_size


def peak_mb(fn) -> float:
    return peak_traced_bytes(fn) / 2**20


def bench_case(tmp: Path, events, encoding, storage, repeats, packet_ns, *, memory=True):
    n = events.size
    suffix = ".bag" if storage == "ros1" else ""
    wt, rt = [], []
    path = None
    for i in range(repeats):
        path = tmp / f"{encoding}_{storage}_{i}{suffix}"
        t0 = time.perf_counter()
        write_bag(path, events, encoding, storage, packet_ns)
        wt.append(time.perf_counter() - t0)
        if i < repeats - 1:
            shutil.rmtree(path) if path.is_dir() else path.unlink()
    for _ in range(repeats):
        t0 = time.perf_counter()
        got = read_events(path, TOPIC)
        rt.append(time.perf_counter() - t0)
    if not np.array_equal(got.events, events):
        raise AssertionError(f"{encoding}/{storage}: read-back events differ")
    messages, size = got.message_count, bag_bytes(path)
    del got
    shutil.rmtree(path) if path.is_dir() else path.unlink()
    w, r = statistics.median(wt), statistics.median(rt)
    out = {
        "write_s": wt, "read_s": rt, "write_s_median": w, "read_s_median": r,
        "write_mev_s": n / w / 1e6, "read_mev_s": n / r / 1e6,
        "messages": messages, "events_per_message": n / messages, "bytes_per_event": size / n,
    }
    if memory:
        mpath = tmp / f"mem_{encoding}_{storage}{suffix}"
        mem_w = peak_mb(lambda: write_bag(mpath, events, encoding, storage, packet_ns))
        mem_r = peak_mb(lambda: read_events(mpath, TOPIC))
        shutil.rmtree(mpath) if mpath.is_dir() else mpath.unlink()
        out["peak_mem_write_mb_per_mev"] = mem_w / (n / 1e6)
        out["peak_mem_read_mb_per_mev"] = mem_r / (n / 1e6)
    return out


def bench_peer(events, repeats, packet_ns):
    """rosbags' per-object path for dvs_msgs/msg/EventArray on a subset (extrapolated per Mev)."""
    from evdnerf_ros.io import event_messages as em

    ts = ros2_typestore()
    T = ts.types
    Time, Event, Header = T["builtin_interfaces/msg/Time"], T["dvs_msgs/msg/Event"], T["std_msgs/msg/Header"]
    bounds = em.packet_bounds(events["t"], packet_ns)
    n = events.size

    def write():
        out = []
        t, x, y, p = (events[k].tolist() for k in ("t", "x", "y", "p"))
        for a, b in zip(bounds[:-1].tolist(), bounds[1:].tolist()):
            evs = [Event(x=x[i], y=y[i], ts=Time(sec=t[i] // 10**9, nanosec=t[i] % 10**9), polarity=p[i] > 0)
                   for i in range(a, b)]
            msg = T[DVS_EVENT_ARRAY](header=Header(stamp=Time(sec=t[a] // 10**9, nanosec=t[a] % 10**9),
                                                   frame_id="event_camera"), height=H, width=W, events=evs)
            out.append(bytes(ts.serialize_cdr(msg, DVS_EVENT_ARRAY)))
        return out

    raws = write()

    def read():
        parts = []
        for raw in raws:
            msg = ts.deserialize_cdr(raw, DVS_EVENT_ARRAY)
            e = msg.events
            parts.append(make_events(np.array([v.ts.sec * 10**9 + v.ts.nanosec for v in e], np.int64),
                                     np.array([v.x for v in e]), np.array([v.y for v in e]),
                                     np.array([v.polarity for v in e])))
        return np.concatenate(parts)

    assert np.array_equal(read(), events)
    tm = interleaved({"write": write, "read": read}, repeats, warmup=False)   # both ran above
    wt, rt = tm["write"]["runs_s"], tm["read"]["runs_s"]
    w, r = tm["write"]["median_s"], tm["read"]["median_s"]
    return {
        "label": f"rosbags per-object Event[] serialize_cdr / deserialize_cdr, {n} events "
                 "(serialisation only, no bag I/O), extrapolated per Mev",
        "subset_events": n, "write_s": wt, "read_s": rt,
        "write_mev_s": n / w / 1e6, "read_mev_s": n / r / 1e6,
        "extrapolated_write_s_per_mev": w / n * 1e6, "extrapolated_read_s_per_mev": r / n * 1e6,
    }


def _panel(ax, cases, peer, title):
    names = [c["case"] for c in cases if "error" not in c]
    wr = [c["write_mev_s"] for c in cases if "error" not in c]
    rd = [c["read_mev_s"] for c in cases if "error" not in c]
    if peer is not None:
        names.append("peer: rosbags per-object\n(EventArray, extrapolated)")
        wr.append(peer["write_mev_s"])
        rd.append(peer["read_mev_s"])
    x = np.arange(len(names))
    b1 = ax.bar(x - 0.2, wr, 0.4, label="write", color="#3a7dc9")
    b2 = ax.bar(x + 0.2, rd, 0.4, label="read", color="#e07b39")
    for bars in (b1, b2):
        for b in bars:
            ax.annotate(f"{b.get_height():.3g}", (b.get_x() + b.get_width() / 2, b.get_height()),
                        ha="center", va="bottom", fontsize=7)
    ax.axhline(GOAL_MEV_S, color="gray", ls="--", lw=1, label=f"goal {GOAL_MEV_S:g} Mev/s")
    ax.set_yscale("log")
    ax.set_xticks(x, [n.replace(" / ", "\n") for n in names], fontsize=7)
    ax.set_title(title, fontsize=9)


def plot(result, path: Path):
    m = result["meta"]
    sparse = result.get("sparse")
    fig, axes = pyplot().subplots(1, 2 if sparse else 1, figsize=(16 if sparse else 11, 5.5), squeeze=False,
                                  gridspec_kw={"width_ratios": [6, 5] if sparse else [1]})
    _panel(axes[0, 0], result["cases"], result["peer"],
           f"dense: {m['events']:.3g} events at {m['rate_ev_s']:.3g} ev/s = "
           f"{m['rate_ev_s'] * m['packet_ns'] / 1e9:.0f} events per {m['packet_ns'] / 1e6:g} ms packet")
    axes[0, 0].set_ylabel("throughput (million events / s, log scale)")
    axes[0, 0].legend(fontsize=8)
    if sparse:
        sm = sparse["meta"]
        _panel(axes[0, 1], sparse["cases"], None,
               f"sparse: {sm['events']:.3g} events at {sm['rate_ev_s']:.3g} ev/s over {sm['span_s']:.0f} s "
               f"{'(crosses the EVT3 wrap) ' if sm['span_s'] > 16.78 else ''}= {sm['rate_ev_s'] * m['packet_ns'] / 1e9:.0f} events per packet")
    fig.suptitle(f"Event topics in bags, median of {m['repeats']} (sparse: {sparse['meta']['repeats'] if sparse else ''}) "
                 f"runs on {m['machine']}; load average {m['load_average_at_start'][0]:.2f} at start", fontsize=10)
    failed = [f"{c['case']}: {c['error'][:110]}" for c in result["cases"] + (sparse["cases"] if sparse else [])
              if "error" in c]
    if failed:
        fig.text(0.01, 0.01, "FAILED (not shown): " + " | ".join(failed), fontsize=7, color="crimson")
    save_figure(fig, path, dpi=110, layout={"rect": (0, 0.04 if failed else 0, 1, 1)})


def run_cases(events, repeats, packet_ns, *, memory=True):
    out, failed = [], False
    with tempfile.TemporaryDirectory(prefix="bench_bags_") as tmp:
        for name, encoding, storage in CASES:
            print(f"{name} ...", flush=True)
            entry = {"case": name, "encoding": encoding, "storage": storage,
                     "msgtype": DVS_EVENT_ARRAY if encoding == "array" else "event_camera_msgs/msg/EventPacket"}
            try:
                entry.update(bench_case(Path(tmp), events, encoding, storage, repeats, packet_ns, memory=memory))
                mem = (f", peak {entry['peak_mem_write_mb_per_mev']:.0f} / {entry['peak_mem_read_mb_per_mev']:.0f} "
                       "MB per Mev (write / read)") if memory else ""
                print(f"   write {entry['write_mev_s']:.1f} Mev/s, read {entry['read_mev_s']:.1f} Mev/s, "
                      f"{entry['bytes_per_event']:.2f} B/ev, {entry['messages']} messages{mem}", flush=True)
            except Exception as exc:  # noqa: BLE001 - recorded, the other cases still run
                entry["error"] = f"{type(exc).__name__}: {exc}"
                failed = True
                print(f"   FAILED: {entry['error']}", flush=True)
            out.append(entry)
    return out, failed


def main(argv=None):
    ap = arg_parser(__doc__, quick="2e5 events, 3 repeats, 5e3 peer events, small sparse run")
    ap.add_argument("--events", type=float, default=5e6, help="events per case (default 5e6)")
    ap.add_argument("--rate", type=float, default=5e6, help="event rate in ev/s (sets events per 1 ms packet)")
    ap.add_argument("--sparse-events", type=float, default=2e6,
                    help="events of the sparse scenario (0 skips it)")
    ap.add_argument("--sparse-rate", type=float, default=1e5, help="event rate of the sparse scenario")
    ap.add_argument("--packet-ns", type=int, default=1_000_000)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--peer-events", type=float, default=2e4)
    args = ap.parse_args(argv)
    if args.quick:
        args.events, args.repeats, args.peer_events, args.sparse_events = 2e5, 3, 5e3, 2e5
    n = int(args.events)
    events = synth_events(n, args.rate)
    host = machine("rosbags")
    meta = {
        "events": n, "rate_ev_s": args.rate, "span_s": (int(events["t"][-1]) - int(events["t"][0])) / 1e9,
        "width": W, "height": H, "packet_ns": args.packet_ns, "repeats": args.repeats,
        "machine": describe(host), "python": host["python"], "numpy": host["numpy"], "rosbags": host["rosbags"],
        "date": time.strftime("%Y-%m-%d %H:%M:%S"), "goal_mev_s": GOAL_MEV_S, "load_average_at_start": load_average(),
    }
    result = {"meta": meta}
    print(f"dense: {n} events at {args.rate:g} ev/s", flush=True)
    result["cases"], failed = run_cases(events, args.repeats, args.packet_ns)
    print("peer (rosbags per-object EventArray) ...", flush=True)
    result["peer"] = bench_peer(events[: int(args.peer_events)], args.repeats, args.packet_ns)
    p = result["peer"]
    print(f"   write {p['write_mev_s']:.3f} Mev/s, read {p['read_mev_s']:.3f} Mev/s "
          f"({p['subset_events']} events, extrapolated)")
    del events
    if args.sparse_events:
        ns = int(args.sparse_events)
        sev = synth_events(ns, args.sparse_rate, seed=1)
        srep = max(1, min(3, args.repeats))
        print(f"sparse: {ns} events at {args.sparse_rate:g} ev/s", flush=True)
        cases, sfailed = run_cases(sev, srep, args.packet_ns, memory=False)
        failed |= sfailed
        result["sparse"] = {"meta": {"events": ns, "rate_ev_s": args.sparse_rate, "repeats": srep,
                                     "span_s": (int(sev["t"][-1]) - int(sev["t"][0])) / 1e9},
                            "cases": cases}
    meta["load_average_at_end"] = load_average()
    ok = [c for c in result["cases"] if "error" not in c and c["encoding"] == "array" and c["storage"] == "mcap"]
    if ok:
        result["speedup_event_array_mcap_vs_peer"] = {"write": ok[0]["write_mev_s"] / p["write_mev_s"],
                                                      "read": ok[0]["read_mev_s"] / p["read_mev_s"]}
    write_results(args.out, "bags", result, plot)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
