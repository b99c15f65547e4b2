"""Benchmark of the servo rig's serial link and motion start, in the virtual Arduino.

The real firmware runs in simavr paced to real time behind a pty (no USB in the path):

1. Command round trip: `PING` latency seen by the host (rig.servo.ServoClient), N pings.
2. Motion start over 50 RUNs of the stored fork swing (1 s):
   - host view: time from writing `RUN` to the motion's start, with the START device time
     mapped onto the host clock by the ping fit (offset + drift): this is what a host-timed
     sync would have to live with (a motion starts at the next 20 ms servo frame);
   - trigger view: the D8 trigger edge (simulated time) minus START's device time, per RUN;
     its spread is the jitter left once the trigger output is what the camera timestamps;
   - repeatability: DONE - START per RUN, and the largest difference of the D9 pulse width at
     the same frame index between any two RUNs.

Usage: python bench/bench_servo.py [--quick]   -> bench/results/servo.{json,png}
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from _common import arg_parser, machine, pyplot, save_figure, write_results

from rig import virtual_arduino as va_mod  # noqa: E402
from rig.servo import ServoClient  # noqa: E402

FRAME_NS = 20_000_000


def stats(x) -> dict:
    x = np.asarray(x, dtype=np.float64)
    return {"n": int(x.size), "median": round(float(np.median(x)), 3),
            "p90": round(float(np.percentile(x, 90)), 3), "min": round(float(x.min()), 3),
            "max": round(float(x.max()), 3), "std": round(float(x.std()), 3)}


def measure(runs: int, pings: int, work: Path) -> dict:
    with va_mod.VirtualArduino(pace=True, workdir=work) as va, ServoClient(va.port) as c:
        rtt_ms = []
        for _ in range(pings):
            _, t0, t1 = c.ping()
            rtt_ms.append((t1 - t0) / 1e6)
        c.sync_clock(pings=0)
        sent, motions = [], []
        for _ in range(runs):
            c.drain_events()
            t_send = time.monotonic_ns()
            c.command("RUN", retries=0)
            m = c.wait_motion("RUN", timeout=5)
            sent.append(t_send)
            motions.append(m)
            for _ in range(3):     # keep the clock fit fresh between runs
                c.ping()
            c.sync_clock(pings=0)
        clock = c.clock
        time.sleep(0.1)
        log = va.pin_log()
    start_us = np.array([m.start.device_us for m in motions], dtype=np.int64)
    done_us = np.array([m.end.device_us for m in motions], dtype=np.int64)
    host_start = np.array([clock.to_host_ns(int(s)) for s in start_us])
    cmd_to_start_ms = (host_start - np.array(sent)) / 1e6
    trig = va_mod.pulses(log, va_mod.PIN_TRIGGER)
    servo = va_mod.pulses(log, va_mod.PIN_SERVO)
    if len(trig) != runs:
        raise RuntimeError(f"expected {runs} trigger pulses, logged {len(trig)}")
    trig_ns = np.array([t.start_ns for t in trig], dtype=np.int64)
    offset_ns = trig_ns - start_us * 1000          # constant up to ISR latency
    residual_us = (offset_ns - np.median(offset_ns)) / 1000
    frames = int(1_000_000_000 // FRAME_NS) + 1
    widths = np.zeros((runs, frames))
    rises = np.array([p.start_ns for p in servo], dtype=np.int64)
    w_all = np.array([p.width_ns for p in servo], dtype=np.int64)
    for i, t0 in enumerate(trig_ns):
        j = np.searchsorted(rises, t0)
        widths[i] = w_all[j:j + frames] / 1000
    return {
        "ping_rtt_ms": stats(rtt_ms),
        "clock_fit": {"drift_ppm": round(clock.drift_ppm, 1),
                      "residual_us": round(clock.residual_ns / 1e3, 1), "pings": clock.samples},
        "run_command_to_start_ms": stats(cmd_to_start_ms),
        "trigger_minus_start_residual_us": stats(residual_us),
        "trigger_minus_start_offset_us": round(float(np.median(offset_ns)) / 1e3, 3),
        "done_minus_start_ms": stats((done_us - start_us) / 1000),
        "pulse_width_max_diff_between_runs_us": round(float(np.ptp(widths, axis=0).max()), 3),
        "series": {"rtt_ms": [round(x, 4) for x in rtt_ms],
                   "run_command_to_start_ms": [round(float(x), 4) for x in cmd_to_start_ms],
                   "trigger_residual_us": [round(float(x), 4) for x in residual_us]},
    }


def plot(results: dict, path: Path) -> None:
    s = results["series"]
    fig, (ax1, ax2) = pyplot().subplots(1, 2, figsize=(11, 4.2))
    ax1.hist(s["rtt_ms"], bins=40, color="tab:blue")
    r = results["ping_rtt_ms"]
    ax1.set_xlabel("PING round trip [ms]")
    ax1.set_ylabel("pings")
    ax1.set_title(f"command round trip: median {r['median']:.2f} ms, p90 {r['p90']:.2f} ms "
                  f"(n={r['n']})", fontsize=9)
    k = np.arange(len(s["run_command_to_start_ms"]))
    ax2.plot(k, s["run_command_to_start_ms"], "o", color="tab:orange",
             label="host: RUN written -> motion start [ms]")
    ax2.set_xlabel("RUN #")
    ax2.set_ylabel("host latency to motion start [ms]")
    ax3 = ax2.twinx()
    ax3.plot(k, s["trigger_residual_us"], "s", color="tab:green", markersize=3,
             label="trigger edge - START, minus median [µs]")
    ax3.set_ylabel("trigger - START residual [µs]")
    lim = max(1.0, float(np.max(np.abs(s["trigger_residual_us"]))) * 1.5)
    ax3.set_ylim(-lim, lim)
    h1, l1 = ax2.get_legend_handles_labels()
    h2, l2 = ax3.get_legend_handles_labels()
    ax2.legend(h1 + h2, l1 + l2, fontsize=7, loc="upper right")
    ax2.set_title("motion start over RUNs: host-timed vs trigger-timed", fontsize=9)
    fig.suptitle("rig_servo firmware in the virtual Arduino (simavr, paced to real time, no USB)",
                 fontsize=9)
    save_figure(fig, path, dpi=110)


def main(argv=None) -> None:
    ap = arg_parser(__doc__, quick="5 RUNs, 50 pings (a smoke run)")
    args = ap.parse_args(argv)
    missing = [p for p in va_mod.missing_tools() if p != "avrdude"]
    if missing:
        sys.exit("bench_servo needs the Debian packages " + " ".join(missing))
    runs, pings = (5, 50) if args.quick else (50, 200)
    with tempfile.TemporaryDirectory() as tmp:
        res = measure(runs, pings, Path(tmp))
    results = {"machine": machine(),
               "quick": bool(args.quick), "runs": runs, "pings": pings, **res}
    name = "servo_quick" if args.quick else "servo"
    write_results(args.out, name, results, plot)
    for key in ("ping_rtt_ms", "run_command_to_start_ms", "trigger_minus_start_residual_us",
                "done_minus_start_ms"):
        print(f"{key}: {results[key]}")
    print(f"pulse width max diff between runs: {results['pulse_width_max_diff_between_runs_us']} us")


if __name__ == "__main__":
    main()
