"""Benchmark of `evdnerf convert`: throughput and peak memory, end to end, up to 1e8 events.

Simulating 1e8 events through the renderer would take hours, so the session is synthesised
directly: 4 views of an EVK4-class 1280x720 sensor, each one rosbag2 (MCAP, EventPacket
evt3, whole-µs times, epoch-like clock with its own offset) with CameraInfo and a static
pose, and a session.yaml with sync records (no motion end: convert finds it from the event
rate, the full code path). Each view: 0.3 s of background noise (50 k ev/s), then 2 s of
"streaky" motion (70 % of the events on the two edges of a bar sweeping across the image,
+ on the leading edge, - on the trailing one, 30 % uniform noise), then 0.3 s of noise.

Measured for several session sizes (events summed over the 4 views; the recording length is
fixed, so the event rate grows with the size: 1e6 events per view is 0.4 M ev/s, ~400 events
per 1 ms packet; 25e6 is 9.6 M ev/s): the end-to-end
`convert_session` wall time (open bags, decode, shift, crop, index, compress, write, find
the motion end, truncate, publish) in a fresh subprocess, and that subprocess's peak RSS
(``resource.getrusage(RUSAGE_SELF).ru_maxrss``), next to the RSS of a subprocess that only
imports the same modules and decodes one packet (the fixed cost). Also: decode-only
throughput (iterating the bags' packets, no output), the gzip alternative at one size, and
TrainingSet reads on the largest set (random 1 ms windows, dL images of 1/32 of the span,
event-pixel indices). Goals: >= 10 M events/s end to end; <= 2 GB peak for 1e8 events.
The timed convert includes its cold start in a fresh process (lazy imports, loading the
compiled codec kernels: ~0.7 s), which dominates the small sizes.

Usage:  python bench/bench_convert.py [--quick] [--sizes 1e6 5e6 25e6] [--tmp DIR]
        -> bench/results/convert.json + convert.png (--quick: convert.quick.*)
"""

from __future__ import annotations

import json
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from _common import ROOT, arg_parser, describe, load_average, machine, pyplot, read_results, save_figure, write_results

from evdnerf_ros.events.types import EVENT_DTYPE  # noqa: E402
from evdnerf_ros.io.messages import camera_info, pose_stamped  # noqa: E402
from evdnerf_ros.io.rosbag2 import BagWriter  # noqa: E402
from evdnerf_ros.session.layout import SESSION_FORMAT, SESSION_FORMAT_VERSION  # noqa: E402

W, H = 1280, 720
K = [[900.0, 0.0, 639.5], [0.0, 900.0, 359.5], [0.0, 0.0, 1.0]]
VIEWS = 4
EPOCH = 1_700_000_000 * 10**9
PRE_NS, MOTION_NS, POST_NS = 300_000_000, 2_000_000_000, 300_000_000
NOISE_RATE = 50_000.0
CHUNK = 2_000_000
GOAL_MEV_S = 10.0
GOAL_GB = 2.0


# --------------------------------------------------------------------------- synthetic session


def _noise(rng, n, a_us, b_us):
    ev = np.empty(n, EVENT_DTYPE)
    ev["t"] = np.sort(rng.integers(a_us, b_us, n))
    ev["x"] = rng.integers(0, W, n)
    ev["y"] = rng.integers(0, H, n)
    ev["p"] = np.where(rng.random(n) < 0.5, 1, -1)
    return ev


def _motion_chunk(rng, n, a_us, b_us):
    """Events of [a_us, b_us) µs (relative to the motion start): a bar sweeping back and forth."""
    t = np.sort(rng.integers(a_us, b_us, n))
    phase = 0.5 - 0.5 * np.cos(2 * np.pi * t / (MOTION_NS // 1000))          # 0 -> 1 -> 0 over the motion
    centre = W * (0.15 + 0.7 * phase)
    half = 40.0
    on_edge = rng.random(n) < 0.7
    side = np.where(rng.random(n) < 0.5, -1.0, 1.0)
    direction = np.sign(np.sin(2 * np.pi * t / (MOTION_NS // 1000)) + 1e-12)
    x_edge = centre + side * half + rng.normal(0, 2.5, n)
    x = np.where(on_edge, x_edge, rng.integers(0, W, n))
    ev = np.empty(n, EVENT_DTYPE)
    ev["t"] = t
    ev["x"] = np.clip(np.round(x), 0, W - 1)
    ev["y"] = np.where(on_edge, rng.integers(120, 600, n), rng.integers(0, H, n))
    ev["p"] = np.where(on_edge, np.where(side * direction > 0, 1, -1), np.where(rng.random(n) < 0.5, 1, -1))
    return ev


def write_session(root: Path, events_per_view: int, seed: int = 0) -> dict:
    """Write the synthetic session; returns {events, seconds}."""
    rng = np.random.default_rng(seed)
    root.mkdir(parents=True)
    views, total = [], 0
    t0 = time.perf_counter()
    for v in range(VIEWS):
        clock = EPOCH + int(rng.integers(0, 5 * 10**9)) // 1000 * 1000      # the view's clock at common -PRE
        onset = clock + PRE_NS                                             # view clock at the motion onset
        n_noise = int(NOISE_RATE * PRE_NS / 1e9)
        n_motion = max(1, events_per_view - 2 * n_noise)
        name = f"view_{v:02d}"
        T = np.eye(4)
        a = 2 * np.pi * v / VIEWS
        T[:3, :3] = [[-np.sin(a), 0, -np.cos(a)], [np.cos(a), 0, -np.sin(a)], [0, -1, 0]]
        T[:3, 3] = [4 * np.cos(a), 4 * np.sin(a), 0.0]
        with BagWriter(root / name) as bag:
            bag.write("/event_camera/camera_info", "sensor_msgs/msg/CameraInfo",
                      camera_info(W, H, K, stamp_ns=clock), clock)
            bag.write("/rig/camera_pose", "geometry_msgs/msg/PoseStamped", pose_stamped(T, clock), clock)

            def put(ev_us, base):
                ev = ev_us.copy()
                ev["t"] = base + 1000 * ev_us["t"]
                bag.write_events("/event_camera/events", ev, width=W, height=H)

            put(_noise(rng, n_noise, 0, PRE_NS // 1000), clock)
            n_chunks = max(1, -(-n_motion // CHUNK))
            span_us = MOTION_NS // 1000
            for c in range(n_chunks):
                a_us, b_us = span_us * c // n_chunks, span_us * (c + 1) // n_chunks
                k = n_motion * (c + 1) // n_chunks - n_motion * c // n_chunks
                put(_motion_chunk(rng, k, a_us, b_us), onset)
            put(_noise(rng, n_noise, 0, POST_NS // 1000), onset + MOTION_NS)
        total += 2 * n_noise + n_motion
        views.append({"name": name, "bag": name, "split": "train" if v < VIEWS - 1 else "val",
                      "T_world_cam": T.tolist(), "sync": {"offset_ns": onset, "method": "synthetic"}})
    data = {"format": SESSION_FORMAT, "format_version": SESSION_FORMAT_VERSION,
            "source": {"kind": "synthetic benchmark"},
            "camera": {"width": W, "height": H, "K": K, "D": [0.0] * 5},
            "thresholds": {"c_pos": 0.2, "c_neg": 0.2}, "time": {}, "views": views}
    import yaml

    (root / "session.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
    return {"events": total, "seconds": time.perf_counter() - t0,
            "bag_bytes": sum(f.stat().st_size for f in root.rglob("*.mcap"))}


# --------------------------------------------------------------------------- measurements

_CHILD = r"""
import json, resource, sys, time
sys.path.insert(0, {root!r})
mode, session, out, compression = sys.argv[1:5]
from evdnerf_ros.session.convert import ConvertOptions, convert_session
from evdnerf_ros.io.rosbag2 import open_bag
import h5py
if mode == "baseline":
    with open_bag(session + "/view_00") as bag:
        next(iter(bag.iter_event_packets("/event_camera/events")))
    wall, summary = 0.0, {{}}
elif mode == "decode":
    t0 = time.perf_counter()
    n = 0
    for v in range(4):
        with open_bag(session + f"/view_{{v:02d}}") as bag:
            for pk in bag.iter_event_packets("/event_camera/events"):
                n += pk.events.size
    wall, summary = time.perf_counter() - t0, {{"events_decoded": n}}
else:
    t0 = time.perf_counter()
    summary = convert_session(session, out, ConvertOptions(compression=compression), log=lambda *a: None)
    wall = time.perf_counter() - t0
print(json.dumps({{"wall_s": wall, "maxrss_kb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss,
                   "summary": summary}}))
"""


def child(mode: str, session: Path, out: Path, compression: str = "scaleoffset") -> dict:
    code = _CHILD.format(root=str(ROOT))
    r = subprocess.run([sys.executable, "-c", code, mode, str(session), str(out), compression],
                       capture_output=True, text=True, check=False)
    if r.returncode != 0:
        raise RuntimeError(f"child {mode} failed:\n{r.stderr[-3000:]}")
    return json.loads(r.stdout.strip().splitlines()[-1])


def read_bench(path: Path, seed: int = 0) -> dict:
    from evdnerf_ros.io.trainingset import TrainingSet

    rng = np.random.default_rng(seed)
    out = {}
    with TrainingSet(path) as ts:
        v = ts.views[0]
        t0, t1 = ts.time_range
        starts = rng.integers(t0, t1 - 1_000_000, 200)
        a = time.perf_counter()
        n = sum(ts.events(v, int(s), int(s) + 1_000_000).size for s in starts)
        dt = time.perf_counter() - a
        out["events_1ms_windows_per_s"] = len(starts) / dt
        out["events_per_1ms_window_mean"] = n / len(starts)
        span = (t1 - t0) // 32
        starts = rng.integers(t0, t1 - span, 8)
        a = time.perf_counter()
        n = 0
        for s in starts:
            n += int(np.count_nonzero(ts.log_change(v, int(s), int(s) + span)))
        dt = time.perf_counter() - a
        out["log_change_1_32_span_per_s"] = len(starts) / dt
        out["log_change_window_ns"] = int(span)
        starts = rng.integers(t0, t1 - 1_000_000, 100)
        a = time.perf_counter()
        for s in starts:
            ts.event_pixels(v, int(s), int(s) + 1_000_000)
        out["event_pixels_1ms_per_s"] = len(starts) / (time.perf_counter() - a)
        a = time.perf_counter()
        n = sum(b.size for b in ts.iter_events(v))
        out["full_view_stream_mev_s"] = n / (time.perf_counter() - a) / 1e6
        out["view_events"] = n
    return out


def plot(result: dict, path: Path) -> None:
    rows = [r for r in result["runs"] if r["compression"] == "scaleoffset"]
    gz = [r for r in result["runs"] if r["compression"] == "gzip"]
    ev = np.array([r["events"] for r in rows], float)
    fig, ax = pyplot().subplots(1, 2, figsize=(11, 4.2))
    ax[0].plot(ev, [r["convert_mev_s"] for r in rows], "o-", label="convert, scaleoffset (default)")
    if gz:
        ax[0].plot([r["events"] for r in gz], [r["convert_mev_s"] for r in gz], "s", label="convert, gzip")
    ax[0].plot(ev, [r["decode_only_mev_s"] for r in rows], "^--", label="decode only (no output)")
    ax[0].axhline(GOAL_MEV_S, color="r", ls=":", label=f"goal {GOAL_MEV_S:g} Mev/s")
    ax[0].set_xscale("log")
    ax[0].set_xlabel("events in the session (4 views x 2.6 s: the rate grows with the size)")
    ax[0].set_ylabel("M events / s (end to end)")
    ax[0].set_title("convert throughput")
    ax[0].legend(fontsize=8)
    ax[1].plot(ev, [r["peak_rss_mb"] for r in rows], "o-", label="peak RSS of the convert process")
    ax[1].axhline(result["baseline_rss_mb"], color="gray", ls="--", label="imports + one packet (fixed cost)")
    ax[1].axhline(GOAL_GB * 1024, color="r", ls=":", label=f"goal {GOAL_GB:g} GB at 1e8 events")
    ax[1].set_xscale("log")
    ax[1].set_yscale("log")
    ax[1].set_xlabel("events in the session (4 views x 2.6 s: the rate grows with the size)")
    ax[1].set_ylabel("MB")
    ax[1].set_title("peak memory")
    ax[1].legend(fontsize=8)
    fig.suptitle(f"evdnerf convert: {W}x{H}, 4 views, MCAP evt3 -> TRAIN.h5 ({result['meta']['machine']})",
                 fontsize=10)
    save_figure(fig, path, dpi=110)


def main(argv=None) -> int:
    ap = arg_parser(__doc__, quick="sizes 2e5 and 1e6 events per view")
    ap.add_argument("--sizes", type=float, nargs="+", default=None, help="events per view (default 1e6 5e6 25e6)")
    ap.add_argument("--tmp", type=Path, default=None, help="scratch folder (needs ~1.2 GB for 1e8 events)")
    ap.add_argument("--replot", action="store_true", help="only redraw the PNG from the existing JSON")
    args = ap.parse_args(argv)
    stem = "convert.quick" if args.quick else "convert"
    if args.replot:
        plot(read_results(args.out, stem), args.out / f"{stem}.png")
        return 0
    sizes = args.sizes or ([2e5, 1e6] if args.quick else [1e6, 5e6, 25e6])
    sizes = [int(s) for s in sizes]
    gzip_size = sizes[len(sizes) // 2] if len(sizes) > 1 else sizes[0]
    scratch = Path(tempfile.mkdtemp(prefix="bench_convert.", dir=args.tmp))
    host = machine("h5py")
    result = {"meta": {"machine": describe(host), "python": host["python"],
                       "numpy": host["numpy"], "h5py": host["h5py"], "date": time.strftime("%Y-%m-%d %H:%M:%S"),
                       "sensor": [W, H], "views": VIEWS, "motion_s": MOTION_NS / 1e9,
                       "goal_mev_s": GOAL_MEV_S, "goal_gb_at_1e8": GOAL_GB,
                       "load_average_at_start": load_average()}, "runs": []}
    try:
        for i, per_view in enumerate(sizes):
            sess = scratch / f"s{i}"
            gen = write_session(sess, per_view, seed=i)
            print(f"session {i}: {gen['events']} events written in {gen['seconds']:.1f} s "
                  f"({gen['bag_bytes'] / gen['events']:.2f} B/event in the bags)", flush=True)
            if i == 0:
                base = child("baseline", sess, scratch / "none.h5")
                result["baseline_rss_mb"] = base["maxrss_kb"] / 1024
            dec = child("decode", sess, scratch / "none.h5")
            for comp in ("scaleoffset", "gzip"):
                if comp == "gzip" and per_view != gzip_size:
                    continue
                out = scratch / f"train{i}_{comp}.h5"
                r = child("convert", sess, out, comp)
                s = r["summary"]
                row = {"events_per_view": per_view, "events": gen["events"], "compression": comp,
                       "events_written": s["events"], "window_ns": [s["t_start"], s["t_end"]],
                       "window_source": s["window_source"], "convert_s": r["wall_s"],
                       "convert_mev_s": gen["events"] / r["wall_s"] / 1e6,
                       "decode_only_s": dec["wall_s"], "decode_only_mev_s": gen["events"] / dec["wall_s"] / 1e6,
                       "peak_rss_mb": r["maxrss_kb"] / 1024,
                       "peak_rss_above_baseline_mb": (r["maxrss_kb"] / 1024) - result["baseline_rss_mb"],
                       "h5_bytes_per_event": out.stat().st_size / max(1, s["events"]),
                       "bag_bytes_per_event": gen["bag_bytes"] / gen["events"]}
                result["runs"].append(row)
                print(f"  {comp}: {row['convert_s']:.1f} s = {row['convert_mev_s']:.1f} Mev/s, "
                      f"peak RSS {row['peak_rss_mb']:.0f} MB, {row['h5_bytes_per_event']:.2f} B/event; "
                      f"decode only {row['decode_only_mev_s']:.1f} Mev/s", flush=True)
                if i == len(sizes) - 1 and comp == "scaleoffset":
                    result["reads_on_largest"] = read_bench(out)
                    print(f"  reads: {result['reads_on_largest']}", flush=True)
                out.unlink()
            shutil.rmtree(sess)
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    big = max((r for r in result["runs"] if r["compression"] == "scaleoffset"), key=lambda r: r["events"])
    per_ev = (big["peak_rss_mb"] - result["baseline_rss_mb"]) / big["events"]
    result["summary"] = {
        "largest_events": big["events"], "largest_convert_mev_s": big["convert_mev_s"],
        "largest_peak_rss_mb": big["peak_rss_mb"],
        "extrapolated_peak_rss_mb_at_1e8": result["baseline_rss_mb"] + per_ev * 1e8,
        "meets_throughput_goal": big["convert_mev_s"] >= GOAL_MEV_S,
        "meets_memory_goal": (result["baseline_rss_mb"] + per_ev * max(1e8, big["events"])) <= GOAL_GB * 1024,
    }
    result["meta"]["load_average_at_end"] = load_average()
    result["meta"]["self_maxrss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    write_results(args.out, stem, result, plot)
    print(json.dumps(result["summary"], indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
