"""ROS 2 graph presence and parameters: discovery time to a peer and the parameter-set round
trip, against our own (Cyclone DDS) client and an independent Fast DDS peer.

    python bench/bench_ros_graph.py [--quick] [--out bench/results]

Writes ``ros_graph.json`` and ``ros_graph.png`` into ``--out``. Everything on loopback
(Cyclone: ``LOOPBACK_XML``; Fast DDS: UDPv4 on 127.0.0.1 with unicast initial peers), one
fresh domain id per run.

* **Discovery**: an observer is already running (a Cyclone reader of ``ros_discovery_info``
  in this process, or the Fast DDS peer ``tests/fastdds_peer`` built here with cmake); then a
  node is created (participant, graph entry, /rosout, six parameter services) and the time
  from the start of its construction until the observer (a) knows the node's participant
  (Fast DDS: SPDP discovery callback) and (b) holds a ``ros_discovery_info`` sample that lists
  the node. Clock: CLOCK_MONOTONIC in both processes. Median of repeats (node created and
  destroyed each time, the observer kept).
* **Parameter-set round trip**: ``set_parameters`` of one double (a dynamic parameter, applied
  and announced on /parameter_events) from request write to matching reply, sequentially;
  our client (Python, rmw_cyclonedds header) and the Fast DDS peer (C++, same header).
  Median / p90 over the calls.
"""

from __future__ import annotations

import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from _common import ROOT, arg_parser, machine, pyplot, save_figure, write_results

PEER_SRC = ROOT / "tests" / "fastdds_peer"


def build_peer(tmp: Path) -> Path | None:
    if not (shutil.which("cmake") and shutil.which("c++") and Path("/usr/include/fastdds").is_dir()):
        print("Fast DDS peer skipped: needs cmake, a C++ compiler and libfastrtps-dev", file=sys.stderr)
        return None
    for cmd in (["cmake", "-S", str(PEER_SRC), "-B", str(tmp)], ["cmake", "--build", str(tmp), "-j", "2"]):
        subprocess.run(cmd, check=True, capture_output=True, timeout=600)
    return tmp / "fastdds_peer"


#: A child process that creates the node `repeats` times ("t0_ns gid" on stdout each time),
#: or once and keeps it until its stdin closes (repeats 0): the observer is in another process,
#: as in a real graph (in one process Cyclone delivers locally, which would flatter the numbers).
CHILD = r"""
import sys, time
sys.path.insert(0, sys.argv[1])
from bench_ros_graph import _node_class
from evdnerf_ros.ros.qos import LOOPBACK_XML
domain, repeats, gap = int(sys.argv[2]), int(sys.argv[3]), float(sys.argv[4])
Bench = _node_class()
if repeats == 0:
    node = Bench(domain_id=domain, dds_config=LOOPBACK_XML, log_stream=open("/dev/null", "w"))
    print("ready", flush=True)
    sys.stdin.read()
    print("gain", node.params["gain"], flush=True)
    node.shutdown()
else:
    for _ in range(repeats):
        t0 = time.monotonic_ns()
        node = Bench(domain_id=domain, dds_config=LOOPBACK_XML)
        print(t0, node.dds.gid.hex(), flush=True)
        time.sleep(gap)
        node.shutdown()
        time.sleep(0.5)
"""


def _child(domain: int, repeats: int, gap: float = 1.5, **kw):
    return subprocess.Popen([sys.executable, "-c", CHILD, str(Path(__file__).parent), str(domain), str(repeats),
                             str(gap)], stdout=subprocess.PIPE, text=True, **kw)


def _node_class():
    from evdnerf_ros.ros.node import Node
    from evdnerf_ros.ros.parameters import ParameterSpec as P

    class Bench(Node):
        NAME = "bench_node"
        PARAMETERS = [P("gain", 1.0, "a live double", dynamic=True, min=0.0, max=1e9)]

    return Bench


def discovery_cyclone(domain: int, repeats: int) -> list[float]:
    from evdnerf_ros.ros import rostypes
    from evdnerf_ros.ros.graph import DISCOVERY_QOS, PARTICIPANT_INFO, parse_discovery_info
    from evdnerf_ros.ros.qos import LOOPBACK_XML
    from evdnerf_ros.ros.transport import DdsContext, DdsSubscription

    ctx = DdsContext(domain, config=LOOPBACK_XML)
    sub = DdsSubscription(ctx, "/ros_discovery_info", PARTICIPANT_INFO, DISCOVERY_QOS,
                          dds_name="ros_discovery_info", idl=rostypes.idl_struct(PARTICIPANT_INFO))
    child = _child(domain, repeats)
    first = {}
    deadline = time.monotonic() + 30 + repeats * 2.5
    while child.poll() is None and time.monotonic() < deadline:
        sub.wait(0.001)
        now = time.monotonic_ns()
        for data, _ in sub.take_raw():
            info = parse_discovery_info(data)
            if info and info["nodes"]:
                first.setdefault(info["gid"], now)
    starts = [ln.split() for ln in child.communicate(timeout=30)[0].splitlines() if ln.strip()]
    ctx.close()
    return [(first[gid] - int(t0)) / 1e6 if gid in first else float("nan") for t0, gid in starts]


def discovery_fastdds(peer: Path, domain: int, repeats: int, tmp: Path) -> dict:
    from evdnerf_ros.ros import rostypes
    from evdnerf_ros.ros.graph import PARTICIPANT_INFO, parse_discovery_info
    from evdnerf_ros.ros.qos import LOOPBACK_XML

    outdir = tmp / "disc"
    outdir.mkdir()
    gap = 1.5
    proc = subprocess.Popen([str(peer), "--domain", str(domain), "--duration", str(3 + repeats * (gap + 1.0)),
                             "--out", str(outdir), "--sub", "ros_discovery_info",
                             rostypes.dds_type_name(PARTICIPANT_INFO), "reliable_transient"],
                            stdout=subprocess.PIPE, text=True, env={**os.environ, "PEER_TIMESTAMPS": "1"})
    time.sleep(1.0)
    child = _child(domain, repeats, gap)
    starts = [(int(t0), gid) for t0, gid in
              (ln.split() for ln in child.communicate(timeout=60 + repeats * 3)[0].splitlines() if ln.strip())]
    lines = proc.communicate(timeout=120)[0].splitlines()
    part, info = [], []
    for t0, gid in starts:
        tp = [int(ln.rsplit("t=", 1)[1]) for ln in lines if ln.startswith(f"participant {gid[:24]} ")]
        ti = []
        for ln in lines:
            if ln.startswith("sample 0 "):
                n = ln.split()[2]
                parsed = parse_discovery_info((outdir / f"sub0_{n}.bin").read_bytes())
                if parsed and parsed["gid"] == gid and parsed["nodes"]:
                    ti.append(int(ln.rsplit("t=", 1)[1]))
        part.append((min(tp) - t0) / 1e6 if tp else float("nan"))
        info.append((min(ti) - t0) / 1e6 if ti else float("nan"))
    return {"participant_ms": part, "discovery_info_ms": info}


def roundtrip_ours(domain: int, calls: int) -> list[float]:
    from evdnerf_ros.ros.param_services import ParameterClient
    from evdnerf_ros.ros.qos import LOOPBACK_XML
    from evdnerf_ros.ros.transport import DdsContext

    child = _child(domain, 0, stdin=subprocess.PIPE)
    assert child.stdout.readline().strip() == "ready"
    ctx = DdsContext(domain, config=LOOPBACK_XML)
    client = ParameterClient(ctx, "/bench_node")
    assert client.wait_for_service(10)
    client.set(gain=0.5)                      # warm-up
    out = []
    for i in range(calls):
        t0 = time.perf_counter()
        [(ok, why)] = client.set(gain=float(i))
        out.append((time.perf_counter() - t0) * 1e3)
        assert ok, why
    tail = child.communicate("", timeout=30)[0]
    assert f"gain {float(calls - 1)}" in tail, tail
    ctx.close()
    return out


def roundtrip_fastdds(peer: Path, domain: int, calls: int, tmp: Path) -> list[float]:
    from evdnerf_ros.ros import rostypes
    from evdnerf_ros.ros.param_services import join_reply, to_parameter_value

    child = _child(domain, 0, stdin=subprocess.PIPE)
    assert child.stdout.readline().strip() == "ready"
    srv = "rcl_interfaces/srv/SetParameters"
    req = rostypes.serialize(rostypes.message(srv + "_Request", parameters=[rostypes.message(
        "rcl_interfaces/msg/Parameter", name="gain", value=to_parameter_value(42.0))]), srv + "_Request")
    f = tmp / "set.bin"
    f.write_bytes(join_reply(0xBE7C4, 1, req))
    base = "/bench_node/set_parameters"
    r = subprocess.run([str(peer), "--domain", str(domain), "--duration", "30", "--out", str(tmp),
                        "--call", f"rq{base}Request", rostypes.dds_type_name(srv + "_Request"), f"rr{base}Reply",
                        rostypes.dds_type_name(srv + "_Response"), str(f), str(calls)],
                       capture_output=True, text=True, timeout=120)
    tail = child.communicate("", timeout=30)[0]
    assert "gain 42.0" in tail, tail + r.stdout[-2000:]
    rows = [ln.split() for ln in r.stdout.splitlines() if ln.startswith("reply ")]
    if len(rows) != calls:
        raise SystemExit(f"Fast DDS peer: {len(rows)} of {calls} replies:\n{r.stdout[-2000:]}")
    return [float(row[3]) / 1e3 for row in rows[1:]]   # the first call includes the peer's start-up


def _stats(xs: list[float]) -> dict:
    xs = [x for x in xs if x == x]
    if not xs:
        return {"n": 0}
    s = sorted(xs)
    return {"n": len(xs), "median": statistics.median(s), "p90": s[min(len(s) - 1, int(0.9 * len(s)))],
            "min": s[0], "max": s[-1], "values": xs}


def plot(res: dict, path: Path) -> None:
    plt = pyplot()
    fig, (a, b) = plt.subplots(1, 2, figsize=(10, 3.8))
    disc = res["discovery_ms"]
    labels, vals = [], []
    for key, label in (("cyclone_discovery_info", "Cyclone observer:\nros_discovery_info"),
                       ("fastdds_participant", "Fast DDS peer:\nparticipant"),
                       ("fastdds_discovery_info", "Fast DDS peer:\nros_discovery_info")):
        if disc.get(key, {}).get("n"):
            labels.append(label)
            vals.append(disc[key]["values"])
    if vals:
        a.boxplot(vals, tick_labels=labels)
    a.set_ylabel("ms from node construction")
    a.set_title("discovery of a new node")
    rt = res["set_roundtrip_ms"]
    labels, vals = [], []
    for key, label in (("ours", "our client\n(Python)"), ("fastdds", "Fast DDS peer\n(C++)")):
        if rt.get(key, {}).get("n"):
            labels.append(label)
            vals.append(rt[key]["values"])
    if vals:
        b.boxplot(vals, tick_labels=labels, showfliers=False)
    b.set_ylabel("ms per set_parameters call")
    b.set_title("parameter-set round trip (median line)")
    save_figure(fig, path)


def main(argv=None):
    ap = arg_parser(__doc__)
    args = ap.parse_args(argv)
    repeats, calls = (3, 50) if args.quick else (7, 300)
    domain = 1 + (os.getpid() * 53 + time.time_ns() // 1000) % 200
    res = {"machine": machine("cyclonedds", "rosbags"), "repeats": repeats, "calls": calls,
           "discovery_ms": {}, "set_roundtrip_ms": {}}
    with tempfile.TemporaryDirectory() as tmpdir:
        tmp = Path(tmpdir)
        peer = build_peer(tmp / "build")
        res["discovery_ms"]["cyclone_discovery_info"] = _stats(discovery_cyclone(domain, repeats))
        res["set_roundtrip_ms"]["ours"] = _stats(roundtrip_ours(domain + 1, calls))
        if peer is not None:
            fd = discovery_fastdds(peer, domain + 2, repeats, tmp)
            res["discovery_ms"]["fastdds_participant"] = _stats(fd["participant_ms"])
            res["discovery_ms"]["fastdds_discovery_info"] = _stats(fd["discovery_info_ms"])
            res["set_roundtrip_ms"]["fastdds"] = _stats(roundtrip_fastdds(peer, domain + 3, calls, tmp))
            res["fastdds"] = "libfastrtps 2.9 (Debian), tests/fastdds_peer"
    for group in ("discovery_ms", "set_roundtrip_ms"):
        for k, v in res[group].items():
            if v.get("n"):
                print(f"{group} {k}: median {v['median']:.2f} ms, p90 {v['p90']:.2f} ms (n={v['n']})")
    write_results(args.out, "ros_graph", res, plot)


if __name__ == "__main__":
    main()
