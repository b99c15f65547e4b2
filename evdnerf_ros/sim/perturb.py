"""Sensor imperfections added to a recorded session: background noise, hot pixels, bursts of
pre-motion jitter, a shifted recording start, missing triggers or topics, views without motion.

It makes the hard cases for sync (and later stages) out of any session, real or simulated,
without touching the source.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..atomic import atomic_output
from ..session.layout import load_session, session_topics
from ..session.recorder import write_session_yaml


def perturb_session(src, dst, *, noise_hz: float = 0.0, hot: int = 0, hot_rate_hz: float = 1000.0,
                    bursts: int = 0, burst_events: int = 200, burst_ns: int = 3_000_000,
                    lead_ns: int = 0, drop_triggers: bool = False, drop_topics=(),
                    static_views=(), seed: int = 0) -> Path:
    """Copy a session with sensor imperfections added to every view's event stream (for
    testing and benchmarking sync; the source session is not touched).

    Per view: uniform background noise at ``noise_hz`` per pixel (Poisson, random polarity);
    ``hot`` hot pixels firing every 1/``hot_rate_hz`` s (with a little timing jitter) over the
    whole recording; ``bursts`` short bursts of ``burst_events`` events in ``burst_ns`` at
    random moments of the quiet lead-in (pre-motion jitter); a recording that starts a random
    0..``lead_ns`` earlier (so that bins do not line up with the scene clock). Views named in
    ``static_views`` keep only the noise (no motion, no trigger edges, no START). Trigger
    edges are dropped with ``drop_triggers``; topics in ``drop_topics`` are not copied. Times
    stay on the sensor's whole-microsecond grid. session.yaml records the perturbation
    under ``perturbation``.
    """
    import shutil

    from ..events.types import make_events, sort_events
    from ..io.rosbag2 import BagWriter, open_bag, read_events

    src, dst = Path(src), Path(dst)
    session = load_session(src)
    ev_topic, tr_topic = session_topics(session)
    rng = np.random.default_rng(seed)
    bags = {v.bag.resolve() for v in session.views}
    with atomic_output(dst, directory=True) as tmp:
        shutil.copytree(src, tmp, ignore=lambda d, names: [n for n in names if (Path(d) / n).resolve() in bags
                                                          or n == "session.yaml"])
        for view in session.views:
            stream = read_events(view.bag, ev_topic)
            w, h = stream.width, stream.height
            with open_bag(view.bag) as bag:
                b0, b1 = bag.start_ns, bag.end_ns
                others = [m for m in bag.messages() if m.topic != ev_topic]
            static = view.name in static_views
            ev = stream.events[:0] if static else stream.events
            tr = stream.triggers[:0] if (static or drop_triggers) else stream.triggers
            t0 = min(b0, int(stream.events["t"][0]) if stream.events.size else b0)
            t1 = max(b1, int(stream.events["t"][-1]) if stream.events.size else b1)
            lead = int(rng.integers(0, lead_ns // 1000 + 1)) * 1000 if lead_ns > 0 else 0
            t0 = max(0, (t0 - lead) // 1000 * 1000)
            span_us = max(1, (t1 - t0) // 1000)
            parts = [ev]
            n = int(rng.poisson(noise_hz * w * h * span_us * 1e-6)) if noise_hz > 0 else 0
            if n:
                parts.append(make_events(t0 + 1000 * rng.integers(0, span_us, n), rng.integers(0, w, n),
                                         rng.integers(0, h, n), rng.choice(np.array([-1, 1], np.int8), n)))
            for _ in range(hot):
                period_us = max(1, int(round(1e6 / hot_rate_hz)))
                k = np.arange(int(rng.integers(0, period_us)), span_us, period_us)
                tt = np.clip(k + rng.integers(-period_us // 10, period_us // 10 + 1, k.size), 0, span_us - 1)
                parts.append(make_events(t0 + 1000 * np.sort(tt), np.full(k.size, rng.integers(0, w)),
                                         np.full(k.size, rng.integers(0, h)), np.ones(k.size, np.int8)))
            quiet_end = int(stream.events["t"][0]) if (stream.events.size and not static) else t1
            for _ in range(bursts):
                a_us = int(rng.integers(0, max(1, (quiet_end - t0 - 2 * burst_ns) // 1000)))
                tt = t0 + 1000 * (a_us + rng.integers(0, max(1, burst_ns // 1000), burst_events))
                cx, cy = int(rng.integers(0, w)), int(rng.integers(0, h))
                parts.append(make_events(tt, np.clip(cx + rng.integers(-3, 4, burst_events), 0, w - 1),
                                         np.clip(cy + rng.integers(-3, 4, burst_events), 0, h - 1),
                                         rng.choice(np.array([-1, 1], np.int8), burst_events)))
            events = sort_events(np.concatenate(parts))
            with BagWriter(tmp / view.bag.relative_to(src)) as out:
                for m in others:
                    if m.topic in drop_topics or (static and m.topic == tr_topic):
                        continue
                    out.write_raw(m.topic, m.msgtype, m.data, m.t_ns)
                out.write_events(ev_topic, events, width=w, height=h, encoding="evt3",
                                 triggers=tr if len(tr) else None)
        data = dict(session.data)
        data["perturbation"] = {"source": str(src), "noise_hz": float(noise_hz), "hot_pixels": int(hot),
                                "hot_rate_hz": float(hot_rate_hz), "bursts": int(bursts),
                                "burst_events": int(burst_events), "lead_ns": int(lead_ns),
                                "drop_triggers": bool(drop_triggers), "drop_topics": list(drop_topics),
                                "static_views": list(static_views), "seed": int(seed)}
        write_session_yaml(tmp, data, overwrite=True)
    return dst
