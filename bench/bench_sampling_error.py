"""Error against run time of the time sampling: fixed rate vs adaptive bisection.

    python bench/bench_sampling_error.py [--quick] [--out bench/results]

Writes ``sampling_error.json`` and ``sampling_error.png`` into ``--out``.

Two analytic renderers with exactly known event times (so the error is measured, not
estimated); log intensity L = log(I + eps) of pixel (x, y):

* **sigmoid edge**: ``L = lo + A_y * sigmoid((t - tc_x) / tau)``, tau = 2 ms; the edge
  sweeps the 64 columns between 40 and 60 ms of a 100 ms span (activity localised in
  time: where adaptive sampling should pay); rows have contrasts
  A_y = C * (n + 1/2), n = 5..12 (no level sits at an asymptote, where the crossing
  time would be set by float rounding). Monotone per pixel, so every sampling gets the
  counts right and only timing errs. Exact time of level l:
  ``tc_x + tau * logit((l - lo) / A_y)``.
* **sigmoid bar**: sweeping the columns between 20 and 80 ms (activity spread over the
  span: a harder case for adaptive sampling), a bright bar of 3 ms passing each pixel (edges tau = 0.5 ms, peak
  height A_y above the start, leaving the pixel 0.5 C brighter than before): up then
  down, so a sampling that cuts the peak loses events (count error). Exact times by
  bisection (80 rounds, float64) on each monotone branch, the peak by ternary search.

Methods, each a curve over its knob:
* ``fixed``: rates 100 Hz .. 50 kHz.
* ``adaptive``: bisection with the midpoint-linearity check, tolerance 0.5 .. 0.002 C.
* ``adaptive_dlog_only``: bisection on log change alone (max |dL| per interval 2 .. 0.05 C,
  no linearity check) - the simpler rule, for comparison.

Max step (``swing``): an edge 0.3 px wide sweeps 48 px right and back twice, so the images
at 0, SPAN/2 and SPAN are identical (a servo's there-and-back swing). Adaptive sampling
(tolerance 0.1 C, min step SPAN/4096) with max steps SPAN .. SPAN/64, without and with the
motion guard (``travel_px``: the edge's speed bound times the piece length, 1 px allowed);
count error against the same sampler with max step = min step (the fine grid). Without
the guard a max step of SPAN sees no motion at all; with it every max step must give the
fine grid's counts.

Errors: per pixel the k-th ON event is matched with the k-th exact ON event and OFF events
from the end (a missed peak removes the first OFF events); timing error = |t - t_exact|
over matched events (max and median), count error = sum |n - n_exact| / sum n_exact.
Wall seconds are the whole `simulate_renderer` call (rendering included; the analytic
renders are cheap, so this is the sampler + generator cost).
"""

from __future__ import annotations

import json
import sys

import numpy as np

from _common import arg_parser, machine, pyplot, save_figure, timed, write_results

from evdnerf_ros.sim import LOG_EPS, EventGenerator, simulate_renderer  # noqa: E402

C = 0.2
SPAN = 100_000_000          # 100 ms


def _sig(z):
    return 1.0 / (1.0 + np.exp(-z))


class Edge:
    name = "sigmoid_edge"

    def __init__(self, w=64, h=8, tau=2_000_000, sweep=(0.4, 0.6)):
        self.w, self.h, self.tau = w, h, tau
        self.tc = np.linspace(*sweep, w)[None, :] * SPAN
        # Contrasts C * (n + 1/2), n = 5..: no threshold level sits near the asymptotes,
        # where a crossing time would be ill-defined (set by float rounding in the tails).
        self.amp = C * (5.5 + np.arange(h))[:, None]
        self.lo = -2.0

    def log(self, t):
        return self.lo + self.amp * _sig((t - self.tc) / self.tau)

    def __call__(self, t):
        return np.exp(self.log(float(t))) - LOG_EPS

    def exact(self):
        """{(x, y): (on_times, off_times)} in float ns, ESIM on the continuous signal."""
        out = {}
        L0, L1 = self.log(0.0), self.log(float(SPAN))
        for y in range(self.h):
            for x in range(self.w):
                a = self.amp[y, 0]
                n = int(np.floor((L1[y, x] - L0[y, x]) / C))
                lv = L0[y, x] + C * np.arange(1, n + 1)
                u = (lv - self.lo) / a
                out[(x, y)] = (self.tc[0, x] + self.tau * np.log(u / (1 - u)), np.zeros(0))
        return out


class Bar(Edge):
    name = "sigmoid_bar"

    def __init__(self, w=64, h=8, tau=500_000, width=3_000_000):
        super().__init__(w, h, tau, sweep=(0.2, 0.8))
        self.width = width
        half = width / (2.0 * tau)
        self.norm = _sig(half) - _sig(-half)     # peak of the raw bump
        self.end = 0.5 * C                       # the bar leaves the pixel 0.5 C brighter

    def log(self, t):
        up = _sig((t - self.tc) / self.tau)
        dn = _sig((t - self.tc - self.width) / self.tau)
        return self.lo + self.amp * (up - dn) / self.norm + self.end * dn

    def _log_px(self, t, x, y):
        up = _sig((t - self.tc[0, x]) / self.tau)
        dn = _sig((t - self.tc[0, x] - self.width) / self.tau)
        return self.lo + self.amp[y, 0] * (up - dn) / self.norm + self.end * dn

    def exact(self):
        out = {}
        L0 = self.log(0.0)
        L1 = self.log(float(SPAN))
        for y in range(self.h):
            for x in range(self.w):
                # peak by ternary search between the two edges
                a, b = self.tc[0, x], self.tc[0, x] + self.width
                for _ in range(200):
                    m1, m2 = a + (b - a) / 3, b - (b - a) / 3
                    if self._log_px(m1, x, y) < self._log_px(m2, x, y):
                        a = m1
                    else:
                        b = m2
                tpk = 0.5 * (a + b)
                n_up = int(np.floor((self._log_px(tpk, x, y) - L0[y, x]) / C))
                top = L0[y, x] + C * n_up
                n_dn = int(np.floor((top - L1[y, x]) / C))
                up_lv = L0[y, x] + C * np.arange(1, n_up + 1)
                dn_lv = top - C * np.arange(1, n_dn + 1)
                on = self._invert(up_lv, 0.0, tpk, x, y, rising=True)
                off = self._invert(dn_lv, tpk, float(SPAN), x, y, rising=False)
                out[(x, y)] = (on, off)
        return out

    def _invert(self, levels, a, b, x, y, rising):
        lo = np.full(levels.shape, a)
        hi = np.full(levels.shape, b)
        for _ in range(80):
            mid = 0.5 * (lo + hi)
            v = self._log_px(mid, x, y)
            below = v < levels if rising else v > levels
            lo = np.where(below, mid, lo)
            hi = np.where(below, hi, mid)
        return 0.5 * (lo + hi)


class Swing:
    name = "swing"

    def __init__(self, w=64, h=4, width=0.3):
        self.w, self.h, self.width = w, h, width
        self.x = np.arange(w)[None, :]
        self.amp = C * (3.5 + np.arange(h))[:, None]
        self.lo = -2.0
        self.speed_px_per_ns = 48.0 * 2.0 * np.pi / SPAN   # max |d/dt 48 sin^2(2 pi t / SPAN)|

    def edge(self, t):
        return 8.0 + 48.0 * np.sin(2.0 * np.pi * t / SPAN) ** 2

    def __call__(self, t):
        L = self.lo + self.amp * _sig((self.edge(float(t)) - self.x) / self.width)
        return np.exp(L) - LOG_EPS

    def travel(self, a, b):
        return self.speed_px_per_ns * (b - a)


def run_max_step(scene):
    """Count error against the fine grid for max steps SPAN .. SPAN/64, guard off and on."""
    min_step = SPAN // 4096

    def go(max_step, guard):
        gen = EventGenerator(scene.w, scene.h)
        wall, (ev, stats) = timed(lambda: simulate_renderer(
            scene, 0, SPAN, gen, tolerance_c=0.1, min_step_ns=min_step, max_step_ns=max_step,
            travel_px=scene.travel if guard else None))
        counts = np.bincount(ev["y"].astype(np.int64) * scene.w + ev["x"],
                             minlength=scene.w * scene.h)
        return counts, stats, wall

    fine, fine_stats, _ = go(min_step, False)
    runs = []
    for guard in (False, True):
        for k in range(7):
            max_step = SPAN >> k
            counts, stats, wall = go(max_step, guard)
            runs.append({"method": "adaptive_guard" if guard else "adaptive_no_guard",
                         "knob": max_step, "renders": stats.renders, "wall_s": wall,
                         "events": int(counts.sum()), "fine_events": int(fine.sum()),
                         "count_error": float(np.abs(counts - fine).sum() / fine.sum()),
                         "motion_splits": stats.motion_splits})
            r = runs[-1]
            print(f"{scene.name:13s} {r['method']:19s} {max_step / 1e6:8.3f} ms: renders "
                  f"{r['renders']:5d}  events {r['events']:5d} / {r['fine_events']}  count err "
                  f"{r['count_error']:.4f}")
    summary = {m: {"max_count_error": max(r["count_error"] for r in runs if r["method"] == m)}
               for m in ("adaptive_no_guard", "adaptive_guard")}
    return {"width": scene.w, "height": scene.h, "min_step_ns": min_step,
            "fine_renders": fine_stats.renders, "runs": runs, "summary": summary}


def errors(scene, exact, ev):
    terr, n_exact, n_diff = [], 0, 0
    pix = ev["y"].astype(np.int64) * scene.w + ev["x"]
    order = np.argsort(pix, kind="stable")
    pix_s = pix[order]
    bounds = np.searchsorted(pix_s, np.arange(scene.w * scene.h + 1))
    for (x, y), (on_x, off_x) in exact.items():
        p = y * scene.w + x
        sl = order[bounds[p]:bounds[p + 1]]
        t, pol = ev["t"][sl], ev["p"][sl]
        on, off = t[pol == 1], t[pol == -1]
        m = min(on.size, on_x.size)
        terr.append(np.abs(on[:m] - on_x[:m]))
        m = min(off.size, off_x.size)
        if m:
            terr.append(np.abs(off[off.size - m:] - off_x[off_x.size - m:]))
        n_exact += on_x.size + off_x.size
        n_diff += abs(on.size - on_x.size) + abs(off.size - off_x.size)
    terr = np.concatenate(terr)
    return {"max_timing_error_ns": float(terr.max()), "median_timing_error_ns":
            float(np.median(terr)), "count_error": n_diff / n_exact, "exact_events": n_exact}


def run(scene, exact, method, knob):
    gen = EventGenerator(scene.w, scene.h)
    kw = {}
    if method == "fixed":
        kw = dict(mode="fixed", rate_hz=knob)
    elif method == "adaptive":
        kw = dict(tolerance_c=knob, min_step_ns=1_000, max_step_ns=SPAN // 10)
    else:
        kw = dict(tolerance_c=1e9, max_dlog_c=knob, min_step_ns=1_000, max_step_ns=SPAN // 10)
    wall, (ev, stats) = timed(lambda: simulate_renderer(scene, 0, SPAN, gen, **kw))
    res = {"method": method, "knob": knob, "renders": stats.renders, "wall_s": wall,
           "events": int(ev.size), "smallest_step_ns": stats.smallest_step_ns,
           "at_min_step": stats.at_min_step}
    res.update(errors(scene, exact, ev))
    return res


KNOBS = {
    "fixed": [100, 200, 500, 1000, 2000, 5000, 10000, 20000, 50000],
    "adaptive": [0.5, 0.2, 0.1, 0.05, 0.02, 0.01, 0.005, 0.002],
    "adaptive_dlog_only": [2.0, 1.0, 0.5, 0.2, 0.1, 0.05],
}


def plot(result, path):
    scenes = list(result["scenes"])
    fig, axes = pyplot().subplots(len(scenes) + 1, 4, figsize=(19, 4.2 * (len(scenes) + 1)),
                                  squeeze=False)
    swing = result.get("max_step")
    for c in range(4):
        axes[-1, c].set_visible(c == 0)
    if swing:
        ax = axes[-1, 0]
        for method, style in (("adaptive_no_guard", "o--"), ("adaptive_guard", "s-")):
            pts = [p for p in swing["runs"] if p["method"] == method]
            ax.semilogx([p["knob"] / 1e6 for p in pts], [p["count_error"] for p in pts], style,
                        label=method)
        ax.set_xlabel("max step (ms)")
        ax.set_ylabel("count error vs the fine grid")
        ax.set_title("swing: there-and-back edge", fontsize=9)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    for r, sname in enumerate(scenes):
        rows = result["scenes"][sname]["runs"]
        for method, style in (("fixed", "o-"), ("adaptive", "s-"), ("adaptive_dlog_only", "^--")):
            pts = [p for p in rows if p["method"] == method]
            if not pts:
                continue
            rend = [p["renders"] for p in pts]
            wall = [p["wall_s"] for p in pts]
            mx = [max(p["max_timing_error_ns"], 0.5) / 1e3 for p in pts]
            cnt = [max(p["count_error"], 1e-5) for p in pts]
            med = [max(p["median_timing_error_ns"], 0.5) / 1e3 for p in pts]
            axes[r, 0].loglog(rend, mx, style, label=method)
            axes[r, 1].loglog(wall, mx, style, label=method)
            axes[r, 2].loglog(rend, med, style, label=method)
            axes[r, 3].loglog(rend, cnt, style, label=method)
        axes[r, 0].set_xlabel("renders")
        axes[r, 1].set_xlabel("wall seconds (render + sampler + generator)")
        axes[r, 2].set_xlabel("renders")
        axes[r, 3].set_xlabel("renders")
        axes[r, 0].set_ylabel("max event timing error (us)")
        axes[r, 1].set_ylabel("max event timing error (us)")
        axes[r, 2].set_ylabel("median event timing error (us, floored at 0.5 ns)")
        axes[r, 3].set_ylabel("count error (floored at 1e-5)")
        for c in range(4):
            axes[r, c].set_title(sname, fontsize=9)
            axes[r, c].grid(True, which="both", alpha=0.3)
            axes[r, c].legend(fontsize=8)
    save_figure(fig, path, dpi=100)


def main(argv=None):
    ap = arg_parser(__doc__, quick="fewer knob values, smaller images")
    args = ap.parse_args(argv)
    knobs = {k: (v[::3] if args.quick else v) for k, v in KNOBS.items()}
    size = dict(w=32, h=4) if args.quick else dict(w=64, h=8)
    result = {"benchmark": "sampling error against run time", "quick": args.quick,
              "machine": machine(),
              "threshold_c": C, "span_ns": SPAN, "scenes": {}}
    for scene in (Edge(**size), Bar(**size)):
        exact = scene.exact()
        runs = []
        for method, values in knobs.items():
            for v in values:
                r = run(scene, exact, method, v)
                runs.append(r)
                print(f"{scene.name:13s} {method:19s} {v:>8}: renders {r['renders']:6d}  "
                      f"max err {r['max_timing_error_ns'] / 1e3:10.2f} us  median "
                      f"{r['median_timing_error_ns'] / 1e3:8.3f} us  count err "
                      f"{r['count_error']:.4f}  {r['wall_s']:.3f} s")
        summary = {}
        for method in knobs:
            pts = [r for r in runs if r["method"] == method]
            summary[method] = {}
            for target_us in (100, 10, 1):
                ok = [r["renders"] for r in pts
                      if r["max_timing_error_ns"] <= target_us * 1e3 and r["count_error"] == 0]
                summary[method][f"renders_for_max_error_<={target_us}us"] = min(ok) if ok else None
        result["scenes"][scene.name] = {"width": scene.w, "height": scene.h,
                                        "tau_ns": scene.tau, "runs": runs,
                                        "summary": summary}
        print(scene.name, json.dumps(summary))
    result["max_step"] = run_max_step(Swing())
    print("swing", json.dumps(result["max_step"]["summary"]))
    write_results(args.out, "sampling_error", result, plot)
    return 0


if __name__ == "__main__":
    sys.exit(main())
