"""Events throughput over Zenoh (rmw_zenoh's conventions) against DDS (Cyclone, raw CDR) on loopback.

One publisher (this process) and one subscriber (a separate process, our own subscription
class for each transport) on loopback: DDS with the loopback-only Cyclone config on a private
domain, Zenoh in peer mode (the reader listens on a free tcp/127.0.0.1 port, the writer
connects; no router, no multicast). The message is one evt3 EventPacket of a fixed number of
events (real events, Packetizer-encoded), published ``n`` times as raw CDR; the reader takes
raw samples (writer and reader keep-last as deep as the run: history drops nothing). Mev/s and MB/s =
received events / payload bytes over (last - first arrival); ``delivered`` = received / sent.
Median of several runs, transports interleaved, per packet size.
"""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import time

import numpy as np

from _common import ROOT, arg_parser, machine, pyplot, save_figure, write_results

TOPIC, MSGTYPE = "/bench/events", "event_camera_msgs/msg/EventPacket"

READER = r"""
import json, sys, time
from evdnerf_ros.ros.qos import LOOPBACK_XML, profile
kind, domain, port, n_expected = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4])
if kind == "zenoh":
    from evdnerf_ros.ros.zenoh_transport import ZenohContext, ZenohSubscription as Sub
    cfg = json.dumps({"mode": "peer", "scouting": {"multicast": {"enabled": False}},
                      "listen": {"endpoints": [f"tcp/127.0.0.1:{port}"]}})
    ctx = ZenohContext(domain, config=cfg, node_name="bench_reader")
else:
    from evdnerf_ros.ros.transport import DdsContext, DdsSubscription as Sub
    ctx = DdsContext(domain, config=LOOPBACK_XML)
sub = Sub(ctx, "/bench/events", "event_camera_msgs/msg/EventPacket", profile("default", max(64, n_expected)))
print("ready", flush=True)
got = nbytes = 0; first = last = None; deadline = time.monotonic() + 120
while time.monotonic() < deadline and got < n_expected:
    if not sub.wait(0.5):
        if first is not None and time.monotonic() - last > 2.0:
            break
        continue
    items = sub.take_raw(64)
    now = time.monotonic()
    for data, _ in items:
        first = first or now
        last = now
        got += 1
        nbytes += len(data)
print(json.dumps({"received": got, "payload_bytes": nbytes, "seconds": (last - first) if got > 1 else 0.0}),
      flush=True)
ctx.close()
"""


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def make_packet(n_events: int) -> bytes:
    """One evt3 EventPacket (CDR) holding n_events real events, 346x260."""
    from evdnerf_ros.events import make_events
    from evdnerf_ros.io.packetizer import Packetizer

    rng = np.random.default_rng(0)
    t = 1_000_000_000 + np.sort(rng.integers(0, 50_000, n_events)) * 1000      # whole µs (evt3)
    ev = make_events(t, rng.integers(0, 346, n_events), rng.integers(0, 260, n_events),
                     np.where(rng.random(n_events) < 0.5, 1, -1))
    packets = []
    Packetizer(lambda topic, msgtype, data, stamp: packets.append(bytes(data))).write_events(
        TOPIC, ev, width=346, height=260, packet_ns=10**12)
    assert len(packets) == 1, len(packets)
    return packets[0]


def run_once(kind: str, packet: bytes, n: int, domain: int, cpus=None) -> dict:
    from evdnerf_ros.ros.qos import LOOPBACK_XML, profile

    port = _free_port()
    pre = ["taskset", "-c", cpus[1]] if cpus else []
    reader = subprocess.Popen(pre + [sys.executable, "-c", READER, kind, str(domain), str(port), str(n)],
                              stdout=subprocess.PIPE, text=True, cwd=ROOT)
    assert reader.stdout.readline().strip() == "ready"
    if kind == "zenoh":
        from evdnerf_ros.ros.zenoh_transport import ZenohContext, ZenohPublisher as Pub

        cfg = json.dumps({"mode": "peer", "scouting": {"multicast": {"enabled": False}},
                          "listen": {"endpoints": ["tcp/127.0.0.1:0"]},
                          "connect": {"endpoints": [f"tcp/127.0.0.1:{port}"]}})
        ctx = ZenohContext(domain, config=cfg, node_name="bench_writer")
    else:
        from evdnerf_ros.ros.transport import DdsContext, DdsPublisher as Pub

        ctx = DdsContext(domain, config=LOOPBACK_XML)
    pub = Pub(ctx, TOPIC, MSGTYPE, profile("default", max(64, n)))     # history drops nothing
    if not pub.wait_for_subscribers(1, 20):
        raise RuntimeError(f"{kind}: reader did not match")
    time.sleep(0.2)
    t0 = time.perf_counter()
    for _ in range(n):
        pub.publish_raw(packet)
    pub.wait_for_acks(30.0)
    send_s = time.perf_counter() - t0
    out, _ = reader.communicate(timeout=180)
    ctx.close()
    res = json.loads(out.strip().splitlines()[-1])
    res.update(sent=n, send_s=send_s, delivered=res["received"] / n)
    return res


def main(argv=None):
    ap = arg_parser(__doc__)
    ap.add_argument("--cpus", default="0,1", help="cores of the writer,reader ('' = no pinning)")
    ap.add_argument("--runs", type=int, default=5, help="runs per transport and size (median)")
    ap.add_argument("--note", default="", help="free text stored in the JSON (e.g. machine load)")
    args = ap.parse_args(argv)
    cpus = args.cpus.split(",") if args.cpus else None
    if cpus:
        os.sched_setaffinity(0, {int(cpus[0])})
    runs = 2 if args.quick else args.runs
    sizes = [(10_000, 300 if args.quick else 1500), (200_000, 30 if args.quick else 150)]
    domain = 100 + os.getpid() % 100
    rows = []
    for n_events, n in sizes:
        packet = make_packet(n_events)
        per = {"zenoh": [], "dds": []}
        for i in range(runs):
            for kind in ("zenoh", "dds"):                # interleaved
                r = run_once(kind, packet, n, domain + (i % 50), cpus)
                r["mev_per_s"] = (r["received"] * n_events / r["seconds"] / 1e6) if r["seconds"] > 0 else None
                r["mb_per_s"] = (r["payload_bytes"] / r["seconds"] / 1e6) if r["seconds"] > 0 else None
                per[kind].append(r)
        for kind, rs in per.items():
            mev = [r["mev_per_s"] for r in rs if r["mev_per_s"]]
            mb = [r["mb_per_s"] for r in rs if r["mb_per_s"]]
            row = {"transport": kind, "events_per_message": n_events, "message_bytes": len(packet),
                   "messages": n, "mev_per_s_median": float(np.median(mev)) if mev else None,
                   "mb_per_s_median": float(np.median(mb)) if mb else None,
                   "delivered_median": float(np.median([r["delivered"] for r in rs])), "runs": rs}
            rows.append(row)
            print(f"{kind:5s} {n_events:7d} events/msg ({len(packet) / 1e3:.0f} kB): "
                  f"{row['mev_per_s_median'] or 0:.1f} Mev/s, {row['mb_per_s_median'] or 0:.0f} MB/s, "
                  f"delivered {row['delivered_median']:.0%}", flush=True)
    result = {"benchmark": "ros_zenoh", "quick": args.quick, "note": args.note, "runs_per_point": runs,
              "cpus": args.cpus, "machine": machine("eclipse-zenoh", "cyclonedds", "rosbags"), "throughput": rows}
    write_results(args.out, "ros_zenoh_quick" if args.quick else "ros_zenoh", result, plot)


def plot(result, path):
    rows = result["throughput"]
    sizes = sorted({r["events_per_message"] for r in rows})
    fig, ax = pyplot().subplots(1, 2, figsize=(11, 4.2))
    w = 0.38
    for j, (key, label) in enumerate((("mev_per_s_median", "Mev/s"), ("mb_per_s_median", "MB/s"))):
        for k, (kind, color) in enumerate((("zenoh", "tab:purple"), ("dds", "tab:blue"))):
            vals = [next((r[key] or 0 for r in rows if r["transport"] == kind and r["events_per_message"] == s), 0)
                    for s in sizes]
            xs = np.arange(len(sizes)) + (k - 0.5) * w
            ax[j].bar(xs, vals, w, color=color, label="Zenoh (rmw_zenoh format)" if kind == "zenoh" else
                      "DDS (Cyclone, raw CDR)")
            for x, v in zip(xs, vals):
                ax[j].text(x, v, f"{v:.3g}", ha="center", va="bottom", fontsize=8)
        ax[j].set_xticks(np.arange(len(sizes)), [f"{s // 1000}k events/msg" for s in sizes])
        ax[j].set_ylabel(label)
        ax[j].set_title(f"events throughput on loopback ({label}), median of {result['runs_per_point']}")
        ax[j].legend()
    save_figure(fig, path)


if __name__ == "__main__":
    main()
