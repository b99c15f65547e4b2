"""Interop with a real ROS 2 Jazzy (rclpy 7.1.3, rmw_cyclonedds_cpp on Debian's Cyclone 0.10.2):
events throughput and latency between our nodes (Python cyclonedds, raw CDR) and rclpy nodes,
against rclpy -> rclpy on the same messages in the same run, and the time a new node takes to
appear in the ROS graph (``ros2 node list``).

    python bench/bench_ros2_interop.py [--quick] [--out bench/results]

Writes ``ros2_interop.json`` and ``ros2_interop.png`` into ``--out``. Needs ``../shared/ros2``'s
Jazzy (``tests/real_ros2.py``: without it the script exits with the reason); the package is built
into a fresh colcon overlay as the docs/ros2.md recipe does, and every rclpy process runs in that
overlay's environment (its venv Python). Our processes run this checkout with this Python.
Every process: ``ROS_LOCALHOST_ONLY=1``, ``RMW_IMPLEMENTATION=rmw_cyclonedds_cpp`` and a
``ROS_DOMAIN_ID`` drawn at random from 100..200, a fresh one for each run.

* **Messages**: ``event_camera_msgs/msg/EventPacket``, evt3, 1280x720, 1k / 10k / 100k events
  per message. The payloads are one real evt3 stream (random pixels at 5 Mev/s, encoded by our
  Packetizer, about 4.4 bytes per event), cut into consecutive packets, so that a decoding
  subscriber (``evdnerf echo``) sees a valid stream; both publishers send the same packets.
* **Publishers**: ours = ``Node.create_publisher`` and ``Packetizer.write_raw_packet`` (the
  camera-driver path: payload bytes wrapped as they are, CDR built by our prefix code, sent with
  ``publish_raw``); rclpy = a new ``EventPacket`` per send, ``msg.events = payload`` and
  ``Publisher.publish``. Each stamps ``header.stamp`` with ``time.time_ns()`` just before the send
  and sets ``seq`` to the message index. QoS both ways: reliable, volatile, keep-last as deep as
  the run's message count (the history drops nothing: any loss is counted as a loss).
* **Subscribers**: rclpy = a typed subscription (``msg.header.stamp`` in the callback, one
  ``spin_once`` executor loop); ours = ``Node.create_subscription`` with ``take_raw`` and our
  EventPacket parser (stamp and seq, no event decoding); ``evdnerf echo --count N --json``
  (decodes and keeps every event: a shorter burst, throughput only, from its own report's
  first-to-last-receipt rate, compared with rclpy->rclpy's rate timed the same way; its event
  count is checked against what was sent).
* **Runs**: the subscriber starts first; the publisher waits until it matches the subscriber and
  the subscriber reports that it matches the publisher (echo cannot say so: then 1 s after the
  publisher matched), then sends (a) ``paced`` messages one every 20 ms: **latency** = the
  subscriber's ``time.time_ns()`` on receipt minus the stamp (CLOCK_REALTIME, one host), median
  and p90 over all repeats' samples; then (b) a **burst** of ``burst`` messages back to back:
  **throughput** = burst messages received / (last receipt - first burst send), as msg/s, Mev/s
  and MB/s of serialised message (median over repeats). Pairs per size, interleaved in every
  repeat (order reversed on odd repeats): rclpy->rclpy (the reference of both directions),
  ours->rclpy, rclpy->ours, rclpy->echo (burst only). Ratios are ours / rclpy->rclpy: of the
  medians over repeats, and the median of the per-repeat ratios. Losses, duplicates and
  reordering are counted per run; a run that fails (no match, no report) is recorded with the
  error and the processes' stderr, and left out of the medians.
* **Discovery**: one long-lived rclpy observer polls ``node.get_node_names_and_namespaces()``
  every 10 ms (what ``ros2 node list`` reads); a new process then creates one node (ours:
  ``Node``; rclpy: ``rclpy.init()`` + ``create_node``), alternating ours / rclpy. Times on
  CLOCK_MONOTONIC: from spawning the process, and from the start of node construction (after
  the imports), to the observer's first listing of the node. Median of the repeats.
"""

from __future__ import annotations

import json
import os
import random
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from _common import ROOT, TESTS, arg_parser, describe, load_average, machine, pyplot, save_figure, write_results

TOPIC = "/bench/events"
MSGTYPE = "event_camera_msgs/msg/EventPacket"
WIDTH, HEIGHT = 1280, 720
RATE_MEV = 5.0
PERIOD_S = 0.02
ARMS = ("rclpy_rclpy", "ours_rclpy", "rclpy_ours", "rclpy_echo")
LABELS = {"rclpy_rclpy": "rclpy -> rclpy", "ours_rclpy": "ours -> rclpy", "rclpy_ours": "rclpy -> ours",
          "rclpy_echo": "rclpy -> evdnerf echo (decodes; first-last receipt)"}
COLORS = {"rclpy_rclpy": "tab:gray", "ours_rclpy": "tab:blue", "rclpy_ours": "tab:green", "rclpy_echo": "tab:olive"}

# --------------------------------------------------------------------------- child scripts
# Each gets: payload file (npz: data, offsets), paced count, burst count, depth on argv.


#: The publishers' common loop: `paced` messages `period` s apart (latency), then a burst (throughput).
SEND_LOOP = r"""
for i in range(paced):
    send(i)
    time.sleep(period)
time.sleep(0.3 if paced else 0.0)
t0 = time.time_ns()
for i in range(paced, paced + burst):
    send(i)
t1 = time.time_ns()
"""

RCLPY_PUB = r"""
import sys, time, json
import numpy as np
import rclpy
from rclpy.qos import QoSProfile, ReliabilityPolicy, DurabilityPolicy, HistoryPolicy
from event_camera_msgs.msg import EventPacket
path, paced, burst, depth, period = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4]), float(sys.argv[5])
z = np.load(path)
data, off = z["data"], z["offsets"]
payloads = [data[off[i]:off[i + 1]].tobytes() for i in range(len(off) - 1)]
w, h = int(z["width"]), int(z["height"])
rclpy.init()
node = rclpy.create_node("bench_rclpy_pub")
qos = QoSProfile(depth=depth, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE,
                 history=HistoryPolicy.KEEP_LAST)
pub = node.create_publisher(EventPacket, "/bench/events", qos)
deadline = time.monotonic() + 30
while pub.get_subscription_count() < 1 and time.monotonic() < deadline:
    time.sleep(0.01)
print("matched" if pub.get_subscription_count() else "unmatched", flush=True)
if sys.stdin.readline().strip() != "go":
    sys.exit(0)

def send(i):
    msg = EventPacket()
    msg.header.frame_id = "event_camera"
    msg.height, msg.width, msg.seq, msg.time_base, msg.encoding = h, w, i, 0, "evt3"
    msg.events = payloads[i % len(payloads)]
    t = time.time_ns()
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(t, 1_000_000_000)
    pub.publish(msg)

""" + SEND_LOOP + r"""acked = pub.wait_for_all_acked(rclpy.duration.Duration(seconds=60))
print(json.dumps({"burst_t0_ns": t0, "burst_send_s": (t1 - t0) / 1e9, "acked": bool(acked)}), flush=True)
sys.stdin.read()
node.destroy_node()
rclpy.shutdown()
"""

OURS_PUB = r"""
import sys, time, json
import numpy as np
sys.path.insert(0, sys.argv[6])
from evdnerf_ros.io.packetizer import Packetizer
from evdnerf_ros.ros.node import Node
from evdnerf_ros.ros.qos import QosProfile
path, paced, burst, depth, period = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4]), float(sys.argv[5])
z = np.load(path)
data, off = z["data"], z["offsets"]
payloads = [data[off[i]:off[i + 1]].tobytes() for i in range(len(off) - 1)]
w, h = int(z["width"]), int(z["height"])
node = Node(name="bench_ours_pub")
pub = node.create_publisher("/bench/events", "event_camera_msgs/msg/EventPacket", QosProfile("reliable", "volatile", depth))
pk = Packetizer(lambda topic, msgtype, data, stamp: pub.publish_raw(data, stamp))
print("matched" if pub.dds.wait_for_subscribers(1, 30) else "unmatched", flush=True)
if sys.stdin.readline().strip() != "go":
    sys.exit(0)

def send(i):
    pk.write_raw_packet("/bench/events", payloads[i % len(payloads)], encoding="evt3", width=w, height=h,
                        stamp_ns=time.time_ns(), seq=i)

""" + SEND_LOOP + r"""acked = pub.dds.wait_for_acks(60.0)
print(json.dumps({"burst_t0_ns": t0, "burst_send_s": (t1 - t0) / 1e9, "acked": bool(acked)}), flush=True)
sys.stdin.read()
node.shutdown()
"""

#: prints "matched" once it matches a publisher, then one JSON line: per message (seq, stamp, receipt).
RCLPY_SUB = r"""
import sys, time, json
import rclpy
from rclpy.qos import QoSProfile, ReliabilityPolicy, DurabilityPolicy, HistoryPolicy
from rclpy.executors import SingleThreadedExecutor
from event_camera_msgs.msg import EventPacket
total, depth, idle = int(sys.argv[1]), int(sys.argv[2]), float(sys.argv[3])
rclpy.init()
node = rclpy.create_node("bench_rclpy_sub")
qos = QoSProfile(depth=depth, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE,
                 history=HistoryPolicy.KEEP_LAST)
rows, nbytes = [], [0]
def cb(msg):
    now = time.time_ns()
    s = msg.header.stamp
    rows.append((msg.seq, s.sec * 1_000_000_000 + s.nanosec, now))
    nbytes[0] += len(msg.events)
sub = node.create_subscription(EventPacket, "/bench/events", cb, qos)
ex = SingleThreadedExecutor()
ex.add_node(node)
deadline = time.monotonic() + 30
while sub.get_publisher_count() < 1 and time.monotonic() < deadline:
    ex.spin_once(timeout_sec=0.01)
print("matched" if sub.get_publisher_count() else "unmatched", flush=True)
last = time.monotonic()
deadline = last + 300
while len(rows) < total and time.monotonic() < deadline:
    n = len(rows)
    ex.spin_once(timeout_sec=0.05)
    if len(rows) > n:
        last = time.monotonic()
    elif time.monotonic() - last > idle:
        break
print(json.dumps({"rows": rows, "payload_bytes": nbytes[0]}), flush=True)
node.destroy_node()
rclpy.shutdown()
"""

OURS_SUB = r"""
import sys, time, json
sys.path.insert(0, sys.argv[4])
from evdnerf_ros.io.event_messages import parse_event_packet
from evdnerf_ros.ros.node import Node
total, depth, idle = int(sys.argv[1]), int(sys.argv[2]), float(sys.argv[3])
node = Node(name="bench_ours_sub")
sub = node.create_subscription("/bench/events", "event_camera_msgs/msg/EventPacket", "default", depth=depth)
deadline = time.monotonic() + 30
while sub.matched() < 1 and time.monotonic() < deadline:
    time.sleep(0.01)
print("matched" if sub.matched() else "unmatched", flush=True)
rows, nbytes = [], 0
last = time.monotonic()
deadline = last + 300
while len(rows) < total and time.monotonic() < deadline:
    if not sub.wait(0.05):
        if time.monotonic() - last > idle:
            break
        continue
    items = sub.take_raw(256)
    now = time.time_ns()
    last = time.monotonic()
    for data, _ in items:
        f = parse_event_packet(data)
        rows.append((f.seq, f.stamp_ns, now))
        nbytes += len(f.events)
print(json.dumps({"rows": rows, "payload_bytes": nbytes}), flush=True)
node.shutdown()
"""

#: Prints "seen <ns/name> <monotonic ns>" the first time each node is listed, polling every 10 ms.
OBSERVER = r"""
import sys, time
import rclpy
rclpy.init()
node = rclpy.create_node("bench_observer")
print("ready", flush=True)
known = set()
while True:
    now = time.monotonic_ns()
    names = {(ns.rstrip("/") + "/" + n) for n, ns in node.get_node_names_and_namespaces()}
    for full in sorted(names - known):
        print("seen", full, now, flush=True)
    known = names
    time.sleep(0.01)
"""

DISC_OURS = r"""
import time
t_start = time.monotonic_ns()
import sys
sys.path.insert(0, sys.argv[2])
from evdnerf_ros.ros.node import Node
t_ctor = time.monotonic_ns()
node = Node(name=sys.argv[1])
t_made = time.monotonic_ns()
print(t_start, t_ctor, t_made, flush=True)
sys.stdin.read()
node.shutdown()
"""

DISC_RCLPY = r"""
import time
t_start = time.monotonic_ns()
import sys
import rclpy
t_ctor = time.monotonic_ns()
rclpy.init()
node = rclpy.create_node(sys.argv[1])
t_made = time.monotonic_ns()
print(t_start, t_ctor, t_made, flush=True)
sys.stdin.read()
node.destroy_node()
rclpy.shutdown()
"""


# --------------------------------------------------------------------------- set-up


class Domains:
    """ROS_DOMAIN_IDs from 100..200 in a random order, a fresh one per call (wraps after 101)."""

    def __init__(self):
        self._ids = list(range(100, 201))
        random.shuffle(self._ids)
        self._i = 0

    def next(self) -> int:
        d = self._ids[self._i % len(self._ids)]
        self._i += 1
        return d


def ros_env(domain: int) -> dict:
    return {"ROS_DOMAIN_ID": str(domain), "ROS_LOCALHOST_ONLY": "1", "RMW_IMPLEMENTATION": "rmw_cyclonedds_cpp",
            "PYTHONUNBUFFERED": "1"}


def our_env(domain: int) -> dict:
    """This environment without ROS / Cyclone settings, plus the run's ROS variables."""
    env = {k: v for k, v in os.environ.items()
           if not k.startswith(("ROS_", "RMW_", "CYCLONEDDS", "AMENT_", "COLCON_", "PYTHONPATH"))}
    return {**env, **ros_env(domain)}


def write_payloads(path: Path, n_events: int, n_packets: int) -> dict:
    """n_packets consecutive evt3 packets of n_events each (one stream), stored as data + offsets."""
    from evdnerf_ros.events import make_events
    from evdnerf_ros.io.event_messages import parse_event_packet
    from evdnerf_ros.io.packetizer import Packetizer

    rng = np.random.default_rng(n_events)
    packets = []
    pk = Packetizer(lambda topic, msgtype, data, stamp: packets.append(bytes(data)))
    t0 = 0
    span_us = max(1.0, n_events / RATE_MEV)
    for _ in range(n_packets):
        t = t0 + np.sort(rng.integers(0, int(span_us), n_events)) * 1000
        ev = make_events(t, rng.integers(0, WIDTH, n_events), rng.integers(0, HEIGHT, n_events),
                         np.where(rng.random(n_events) < 0.5, 1, -1))
        before = len(packets)
        pk.write_events(TOPIC, ev, width=WIDTH, height=HEIGHT, packet_ns=10**15, max_packet_events=n_events)
        assert len(packets) == before + 1, len(packets) - before
        t0 = int(t[-1]) + 1000
    payloads = [bytes(parse_event_packet(p).events) for p in packets]
    offsets = np.cumsum([0] + [len(p) for p in payloads])
    np.savez(path, data=np.frombuffer(b"".join(payloads), np.uint8), offsets=offsets, width=WIDTH, height=HEIGHT)
    return {"payload_bytes_mean": float(np.mean([len(p) for p in payloads])),
            "message_bytes_mean": float(np.mean([len(p) for p in packets])),
            "bytes_per_event": float(np.mean([len(p) for p in payloads]) / n_events),
            "stream_seconds": t0 / 1e9}


def _reader(proc, sink: list):
    def run():
        for line in proc.stdout:
            sink.append(line)
    th = threading.Thread(target=run, daemon=True)
    th.start()
    return th


def _wait_line(lines: list, pred, proc, timeout: float):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        for ln in lines:
            if pred(ln):
                return ln
        if proc.poll() is not None:
            time.sleep(0.05)
            for ln in lines:
                if pred(ln):
                    return ln
            return None
        time.sleep(0.005)
    return None


def _tail(path: Path, n: int = 1500) -> str:
    try:
        return path.read_text(errors="replace")[-n:]
    except OSError:
        return ""


def _kill(proc):
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(5)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5)


# --------------------------------------------------------------------------- one pair


def run_pair(arm: str, ov, payload_file: Path, n_events: int, paced: int, burst: int, domain: int,
             logdir: Path) -> dict:
    """One publisher and one subscriber process; returns the run's record (``error`` when it failed)."""
    pub_kind, sub_kind = arm.split("_")
    depth = paced + burst
    total = paced + burst
    idle = 10.0
    tag = f"{arm}_{n_events}_{domain}"
    sub_err, pub_err = open(logdir / f"{tag}.sub.err", "w"), open(logdir / f"{tag}.pub.err", "w")
    if sub_kind == "rclpy":
        sub = ov.popen([ov.python, "-c", RCLPY_SUB, str(total), str(depth), str(idle)], env=ros_env(domain),
                       stdout=subprocess.PIPE, stderr=sub_err, cwd=logdir)
    elif sub_kind == "ours":
        sub = subprocess.Popen([sys.executable, "-c", OURS_SUB, str(total), str(depth), str(idle), str(ROOT)],
                               env=our_env(domain), stdout=subprocess.PIPE, stderr=sub_err, text=True, cwd=ROOT)
    else:                                                          # evdnerf echo
        sub = subprocess.Popen([sys.executable, "-m", "evdnerf_ros", "echo", TOPIC, "--count", str(total),
                                "--depth", str(depth), "--idle", str(30.0), "--json"],
                               env=our_env(domain), stdout=subprocess.PIPE, stderr=sub_err, text=True, cwd=ROOT)
    pub_args = [str(payload_file), str(paced), str(burst), str(depth), str(PERIOD_S)]
    if pub_kind == "rclpy":
        pub = ov.popen([ov.python, "-c", RCLPY_PUB, *pub_args], env=ros_env(domain), stdin=subprocess.PIPE,
                       stdout=subprocess.PIPE, stderr=pub_err, cwd=logdir)
    else:
        pub = subprocess.Popen([sys.executable, "-c", OURS_PUB, *pub_args, str(ROOT)], env=our_env(domain),
                               stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=pub_err, text=True, cwd=ROOT)
    sub_lines, pub_lines = [], []
    threads = [_reader(sub, sub_lines), _reader(pub, pub_lines)]
    rec = {"arm": arm, "events_per_message": n_events, "paced": paced, "burst": burst, "domain": domain}
    t_spawn = time.monotonic()
    try:
        pm = _wait_line(pub_lines, lambda ln: ln.strip() in ("matched", "unmatched"), pub, 40)
        if sub_kind != "echo":
            sm = _wait_line(sub_lines, lambda ln: ln.strip() in ("matched", "unmatched"), sub, 40)
        else:
            sm = "matched (not reported by echo)"
            time.sleep(1.0)
        rec["match_s"] = time.monotonic() - t_spawn
        if not pm or pm.strip() != "matched" or not sm or sm.strip() == "unmatched":
            rec["error"] = f"no match: publisher said {pm!r}, subscriber said {sm!r}"
            return rec
        pub.stdin.write("go\n")
        pub.stdin.flush()
        budget = 60 + total * PERIOD_S + burst * n_events / 2e5
        sub.wait(timeout=budget)
        threads[0].join(5)
        sub_out = [ln for ln in sub_lines if ln.lstrip().startswith("{")] if sub_kind != "echo" else \
            ["".join(sub_lines[sub_lines.index(next(ln for ln in sub_lines if ln.startswith("{"))):])] \
            if any(ln.startswith("{") for ln in sub_lines) else []
        pres = _wait_line(pub_lines, lambda ln: ln.startswith("{"), pub, 60)
        if not sub_out:
            rec["error"] = f"subscriber gave no report (exit {sub.returncode}): {_tail(Path(sub_err.name))}"
            return rec
        if pres is None:
            rec["error"] = f"publisher gave no report (exit {pub.poll()}): {_tail(Path(pub_err.name))}"
            return rec
        p = json.loads(pres)
        s = json.loads(sub_out[-1])
        rec.update(burst_send_s=p["burst_send_s"], acked=p["acked"])
        if sub_kind == "echo":
            rec.update(received=s["messages"], received_burst=s["messages"], echo_events=s["events"],
                       echo_seconds=s["seconds"], echo_rate_hz=s["rate_hz"], payload_bytes=None)
            # echo's report times first to last receipt: compared with the others' msg_per_s_receipts
            rec["msg_per_s_receipts"] = s["rate_hz"] if s["seconds"] > 0 else None
            rec["lost"] = total - s["messages"]
            return rec
        rows = s["rows"]
        seqs = [r[0] for r in rows]
        rec["received"] = len(rows)
        rec["duplicates"] = len(seqs) - len(set(seqs))
        rec["lost"] = total - len(set(seqs))
        rec["out_of_order"] = int(sum(1 for a, b in zip(seqs, seqs[1:]) if b < a))
        rec["payload_bytes"] = s["payload_bytes"]
        paced_rows = [r for r in rows if r[0] < paced]
        burst_rows = [r for r in rows if r[0] >= paced]
        rec["lost_paced"] = paced - len({r[0] for r in paced_rows})
        rec["lost_burst"] = burst - len({r[0] for r in burst_rows})
        rec["latency_paced_ms"] = [(r[2] - r[1]) / 1e6 for r in paced_rows]
        rec["latency_burst_ms_median"] = (statistics.median((r[2] - r[1]) / 1e6 for r in burst_rows)
                                          if burst_rows else None)
        rec["received_burst"] = len(burst_rows)
        if burst_rows:
            recv = sorted(r[2] for r in burst_rows)
            rec["msg_per_s_receipts"] = (len(recv) - 1) / ((recv[-1] - recv[0]) / 1e9) if recv[-1] > recv[0] else None
            span = (recv[-1] - p["burst_t0_ns"]) / 1e9
            rec["burst_span_s"] = span
            rec["msg_per_s"] = len(burst_rows) / span if span > 0 else None
        return rec
    finally:
        for proc in (pub, sub):
            if proc.stdin:
                try:
                    proc.stdin.close()
                except OSError:
                    pass
        for proc in (pub, sub):
            try:
                proc.wait(15)
            except subprocess.TimeoutExpired:
                _kill(proc)
        sub_err.close()
        pub_err.close()
        if "error" in rec:
            rec["stderr_sub"] = _tail(Path(sub_err.name))
            rec["stderr_pub"] = _tail(Path(pub_err.name))


# --------------------------------------------------------------------------- discovery


def discovery(ov, repeats: int, domain: int, logdir: Path) -> dict:
    obs_err = open(logdir / "observer.err", "w")
    obs = ov.popen([ov.python, "-c", OBSERVER], env=ros_env(domain), stdout=subprocess.PIPE, stderr=obs_err,
                   cwd=logdir)
    lines = []
    _reader(obs, lines)
    out = {"ours": [], "rclpy": []}
    try:
        if _wait_line(lines, lambda ln: ln.strip() == "ready", obs, 30) is None:
            return {"error": f"observer did not start: {_tail(logdir / 'observer.err')}"}
        time.sleep(1.0)
        for i in range(repeats):
            for kind in ("ours", "rclpy"):                          # interleaved
                name = f"bench_disc_{kind}_{i}"
                err = open(logdir / f"disc_{name}.err", "w")
                t_spawn = time.monotonic_ns()
                if kind == "ours":
                    child = subprocess.Popen([sys.executable, "-c", DISC_OURS, name, str(ROOT)], env=our_env(domain),
                                             stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=err, text=True,
                                             cwd=ROOT)
                else:
                    child = ov.popen([ov.python, "-c", DISC_RCLPY, name], env=ros_env(domain), stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, stderr=err, cwd=logdir)
                child_lines = []
                _reader(child, child_lines)
                seen = _wait_line(lines, lambda ln: ln.startswith(f"seen /{name} "), obs, 30)
                got = _wait_line(child_lines, lambda ln: len(ln.split()) == 3, child, 10)
                stamps = got.split() if got else []
                child.stdin.close()
                try:
                    child.wait(15)
                except subprocess.TimeoutExpired:
                    _kill(child)
                err.close()
                row = {"name": name, "seen": seen is not None}
                if seen is not None and len(stamps) == 3:
                    t_seen = int(seen.split()[2])
                    t_start, t_ctor, t_made = map(int, stamps)
                    row.update(spawn_to_seen_ms=(t_seen - t_spawn) / 1e6, ctor_to_seen_ms=(t_seen - t_ctor) / 1e6,
                               spawn_to_ctor_ms=(t_ctor - t_spawn) / 1e6, ctor_ms=(t_made - t_ctor) / 1e6,
                               made_to_seen_ms=(t_seen - t_made) / 1e6)
                else:
                    row["stderr"] = _tail(logdir / f"disc_{name}.err")
                out[kind].append(row)
                time.sleep(0.5)
    finally:
        _kill(obs)
        obs_err.close()
    return out


# --------------------------------------------------------------------------- statistics


def _stats(xs) -> dict:
    xs = [float(x) for x in xs if x is not None and x == x]
    if not xs:
        return {"n": 0}
    s = sorted(xs)
    return {"n": len(s), "median": statistics.median(s), "p90": s[min(len(s) - 1, int(0.9 * len(s)))],
            "min": s[0], "max": s[-1]}


def summarise(runs: list, sizes: list, info: dict) -> list:
    rows = []
    for n_events in sizes:
        per = {a: [r for r in runs if r["arm"] == a and r["events_per_message"] == n_events] for a in ARMS}
        ref = per["rclpy_rclpy"]
        for arm in ARMS:
            rs = per[arm]
            ok = [r for r in rs if "error" not in r]
            key = "msg_per_s_receipts" if arm == "rclpy_echo" else "msg_per_s"    # echo times receipts only
            mps = [r.get(key) for r in ok]
            lat = [x for r in ok for x in r.get("latency_paced_ms", [])]
            row = {"arm": arm, "events_per_message": n_events,
                   "message_bytes": info[n_events]["message_bytes_mean"], "runs": len(rs),
                   "failed_runs": len(rs) - len(ok),
                   "lost_messages": sum(r.get("lost", 0) for r in ok), "sent_messages": sum(r["paced"] + r["burst"] for r in ok),
                   "throughput_basis": key, "msg_per_s": _stats(mps),
                   "msg_per_s_receipts": _stats([r.get("msg_per_s_receipts") for r in ok]),
                   "latency_paced_ms": _stats(lat),
                   "latency_paced_run_medians_ms": [statistics.median(r["latency_paced_ms"]) for r in ok
                                                    if r.get("latency_paced_ms")],
                   "latency_burst_ms_median": _stats([r.get("latency_burst_ms_median") for r in ok])["median"]
                   if ok and arm != "rclpy_echo" else None}
            m = row["msg_per_s"].get("median")
            row["mev_per_s"] = m * n_events / 1e6 if m else None
            row["mev_per_s_runs"] = [x * n_events / 1e6 for x in mps if x]
            row["mb_per_s"] = m * info[n_events]["message_bytes_mean"] / 1e6 if m else None
            if arm == "rclpy_echo":
                row["echo_events_ok"] = all(r.get("echo_events") == (r["paced"] + r["burst"]) * n_events for r in ok)
            if arm != "rclpy_rclpy":
                refm = _stats([r.get(key) for r in ref if "error" not in r]).get("median")
                reflat = _stats([x for r in ref if "error" not in r for x in r.get("latency_paced_ms", [])])
                row["throughput_ratio"] = m / refm if m and refm else None
                paired = [a[key] / b[key] for a, b in zip(rs, ref)
                          if a.get(key) and b.get(key) and "error" not in a and "error" not in b]
                row["throughput_ratio_paired_median"] = statistics.median(paired) if paired else None
                if lat and reflat.get("n"):
                    row["latency_median_ratio"] = row["latency_paced_ms"]["median"] / reflat["median"]
                    row["latency_p90_ratio"] = row["latency_paced_ms"]["p90"] / reflat["p90"]
            rows.append(row)
    return rows


# --------------------------------------------------------------------------- plot


def plot(res: dict, path: Path) -> None:
    plt = pyplot()
    from matplotlib.ticker import ScalarFormatter

    rows = res["summary"]
    sizes = res["sizes"]
    fig, ax = plt.subplots(1, 3, figsize=(16, 5), gridspec_kw={"width_ratios": [1.3, 1.1, 0.8]})
    xs = np.arange(len(sizes))
    w = 0.2
    size_labels = [f"{s // 1000}k ev\n{res['payloads'][str(s)]['message_bytes_mean'] / 1e3:.0f} kB" for s in sizes]

    def get(arm, s, key):
        return next((r for r in rows if r["arm"] == arm and r["events_per_message"] == s), {}).get(key)

    for k, arm in enumerate(ARMS):
        vals = [get(arm, s, "mev_per_s") or 0 for s in sizes]
        bx = xs + (k - 1.5) * w
        ax[0].bar(bx, vals, w, color=COLORS[arm], label=LABELS[arm])
        for x, s in zip(bx, sizes):
            pts = get(arm, s, "mev_per_s_runs") or []
            ax[0].scatter(np.full(len(pts), x), pts, s=8, color="black", zorder=3,
                          label="runs" if k == 0 and s == sizes[0] else None)
        for x, v, s in zip(bx, vals, sizes):
            ratio = get(arm, s, "throughput_ratio")
            txt = f"{v:.3g}" + (f"\n×{ratio:.2f}" if ratio else "")
            ax[0].text(x, max([v] + (get(arm, s, "mev_per_s_runs") or [])), txt, ha="center", va="bottom", fontsize=7)
    ax[0].set_yscale("log")
    ax[0].yaxis.set_major_formatter(ScalarFormatter())
    ax[0].set_xticks(xs, size_labels)
    ax[0].set_ylabel("Mevents/s (burst, received)")
    ax[0].set_title(f"throughput, median of {res['repeats']} (×: / rclpy->rclpy)", fontsize=10)
    ax[0].legend(fontsize=8, loc="upper left")
    lo, hi = ax[0].get_ylim()
    ax[0].set_ylim(lo, hi * 6)

    w = 0.27
    for k, arm in enumerate(ARMS[:3]):
        med = [get(arm, s, "latency_paced_ms").get("median", np.nan) for s in sizes]
        p90 = [get(arm, s, "latency_paced_ms").get("p90", np.nan) for s in sizes]
        bx = xs + (k - 1) * w
        ax[1].bar(bx, med, w, color=COLORS[arm], label=LABELS[arm])
        ax[1].scatter(bx, p90, marker="_", s=120, color="black", zorder=3, label="p90" if k == 0 else None)
        for x, v, s in zip(bx, med, sizes):
            ratio = get(arm, s, "latency_median_ratio")
            ax[1].text(x, v, f"{v:.2g}" + (f"\n×{ratio:.2f}" if ratio else ""), ha="center", va="bottom", fontsize=7)
    lo, hi = ax[1].get_ylim()
    ax[1].set_ylim(0, hi * 1.35)
    ax[1].set_xticks(xs, size_labels)
    ax[1].set_ylabel("ms, receipt - header.stamp")
    ax[1].set_title(f"latency, one message per {PERIOD_S * 1e3:.0f} ms (bar median, – p90)", fontsize=10)
    ax[1].legend(fontsize=8, loc="upper left")

    disc = res.get("discovery", {})
    labels, vals, colors = [], [], []
    for kind, color in (("ours", "tab:blue"), ("rclpy", "tab:gray")):
        for key, what in (("spawn_to_seen_ms", "from spawn"), ("ctor_to_seen_ms", "from node\nconstruction")):
            v = [r[key] for r in disc.get(kind, []) if key in r]
            if v:
                labels.append(f"{'ours' if kind == 'ours' else 'rclpy'}\n{what}")
                vals.append(v)
                colors.append(color)
    for i, (v, c) in enumerate(zip(vals, colors)):
        med = statistics.median(v)
        ax[2].bar(i, med, 0.6, color=c, alpha=0.6)
        ax[2].scatter(np.full(len(v), i) + np.linspace(-0.15, 0.15, len(v)), v, s=10, color="black", zorder=3)
        ax[2].text(i, max(v), f"{med:.0f}", ha="center", va="bottom", fontsize=8)
    ax[2].set_xticks(range(len(labels)), labels, fontsize=8)
    ax[2].set_ylabel("ms until listed by get_node_names_and_namespaces")
    ax[2].set_title(f"discovery in the ROS graph ({res['discovery_repeats']} runs, bar: median)", fontsize=10)
    fig.suptitle(f"ROS 2 Jazzy interop (rmw_cyclonedds_cpp, loopback, {describe(res['machine'])}"
                 f"{', quick' if res['quick'] else ''})", fontsize=11)
    save_figure(fig, path)


# --------------------------------------------------------------------------- main


def main(argv=None):
    ap = arg_parser(__doc__)
    ap.add_argument("--repeats", type=int, help="interleaved repeats per pair and size (default 2 quick, 4 full)")
    args = ap.parse_args(argv)
    sys.path.insert(0, str(TESTS))
    import real_ros2

    why = real_ros2.missing()
    if why is not None:
        raise SystemExit(f"bench_ros2_interop: no real ROS 2 here: {why}")
    repeats = args.repeats or (2 if args.quick else 4)
    paced = 20 if args.quick else 60
    bursts = {1_000: 1000, 10_000: 400, 100_000: 60} if args.quick else {1_000: 5000, 10_000: 2000, 100_000: 300}
    #: echo decodes (and keeps) every event: shorter bursts, so that its runs take seconds, not minutes
    echo_bursts = {1_000: 500, 10_000: 150, 100_000: 30} if args.quick else {1_000: 2000, 10_000: 600, 100_000: 100}
    disc_repeats = 3 if args.quick else 7
    sizes = sorted(bursts)
    domains = Domains()
    t_all = time.monotonic()
    res = {"benchmark": "ros2_interop", "quick": args.quick, "machine": machine("cyclonedds", "rosbags"),
           "load_before": load_average(), "repeats": repeats, "paced": paced, "period_s": PERIOD_S,
           "bursts": {str(k): v for k, v in bursts.items()}, "echo_bursts": {str(k): v for k, v in echo_bursts.items()},
           "sizes": sizes, "discovery_repeats": disc_repeats}
    with tempfile.TemporaryDirectory(prefix="bench_ros2_") as tmpdir:
        tmp = Path(tmpdir)
        logdir = tmp / "logs"
        logdir.mkdir()
        t0 = time.monotonic()
        ov = real_ros2.overlay(tmp / "ws", symlink=False)
        res["overlay_build_s"] = time.monotonic() - t0
        prefix = real_ros2.ros_prefix()
        res["ros"] = {pkg: _package_version(prefix, pkg) for pkg in
                      ("rclpy", "rmw_cyclonedds_cpp", "event_camera_msgs", "rcl")}
        res["ros"]["cyclonedds_c"] = _dpkg_version("libddsc0debian")
        info = {}
        for n_events in sizes:
            f = tmp / f"payload_{n_events}.npz"
            info[n_events] = write_payloads(f, n_events, paced + bursts[n_events])
        res["payloads"] = {str(k): v for k, v in info.items()}
        print("payloads: " + ", ".join(f"{k} ev = {v['message_bytes_mean'] / 1e3:.1f} kB "
                                       f"({v['bytes_per_event']:.2f} B/event)" for k, v in info.items()), flush=True)

        res["discovery"] = discovery(ov, disc_repeats, domains.next(), logdir)
        res["discovery_summary"] = {k: {key: _stats([r.get(key) for r in v]) for key in
                                        ("spawn_to_seen_ms", "ctor_to_seen_ms", "spawn_to_ctor_ms", "ctor_ms")}
                                    for k, v in res["discovery"].items() if isinstance(v, list)}
        for kind, d in res["discovery_summary"].items():
            print(f"discovery {kind:5s}: spawn->listed {d['spawn_to_seen_ms'].get('median', float('nan')):.0f} ms, "
                  f"construction->listed {d['ctor_to_seen_ms'].get('median', float('nan')):.0f} ms "
                  f"(seen {d['ctor_to_seen_ms']['n']}/{disc_repeats})", flush=True)

        runs = []
        for i in range(repeats):
            for n_events in sizes:
                order = list(ARMS) if i % 2 == 0 else list(reversed(ARMS))        # interleaved, alternating order
                for arm in order:
                    pac, bur = (0, echo_bursts[n_events]) if arm == "rclpy_echo" else (paced, bursts[n_events])
                    f = tmp / f"payload_{n_events}.npz"
                    r = run_pair(arm, ov, f, n_events, pac, bur, domains.next(), logdir)
                    r["repeat"] = i
                    runs.append(r)
                    lat = r.get("latency_paced_ms") or []
                    print(f"[{i}] {n_events:6d} ev {arm:12s} " +
                          (f"ERROR {r['error'][:300]}" if "error" in r else
                           f"{r.get('msg_per_s') or r.get('msg_per_s_receipts') or 0:8.0f} msg/s, lost {r.get('lost')}"
                           + (f", latency median {statistics.median(lat):.2f} ms" if lat else "")
                           + (f", echo events {r.get('echo_events')}" if arm == "rclpy_echo" else "")), flush=True)
        runs.sort(key=lambda r: (r["events_per_message"], ARMS.index(r["arm"]), r["repeat"]))
        res["summary"] = summarise(runs, sizes, info)
        res["runs"] = runs
    res["load_after"] = load_average()
    res["wall_s"] = time.monotonic() - t_all
    for row in res["summary"]:
        lat = row["latency_paced_ms"]
        print(f"{row['events_per_message']:6d} ev {row['arm']:12s} {row['mev_per_s'] or 0:6.2f} Mev/s "
              f"{row['mb_per_s'] or 0:7.1f} MB/s" +
              (f"  latency median {lat['median']:.2f} p90 {lat['p90']:.2f} ms" if lat.get("n") else "") +
              (f"  x{row['throughput_ratio']:.2f} thr" if row.get("throughput_ratio") else "") +
              (f" x{row['latency_median_ratio']:.2f} lat" if row.get("latency_median_ratio") else "") +
              (f"  lost {row['lost_messages']}/{row['sent_messages']}" if row["lost_messages"] else "") +
              (f"  FAILED {row['failed_runs']}/{row['runs']}" if row["failed_runs"] else ""))
    write_results(args.out, "ros2_interop", res, plot)


def _package_version(prefix: Path, pkg: str) -> str | None:
    import re

    try:
        text = (prefix / "share" / pkg / "package.xml").read_text()
    except OSError:
        return None
    m = re.search(r"<version>([^<]+)</version>", text)
    return m.group(1) if m else None


def _dpkg_version(pkg: str) -> str | None:
    try:
        r = subprocess.run(["dpkg-query", "-W", "-f", "${Version}", pkg], capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.SubprocessError):
        return None
    return r.stdout.strip() or None


if __name__ == "__main__":
    main()
