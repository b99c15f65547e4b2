"""An analytic event stream for the demo: a bright bar rotating about the image centre.

Until the renderer-based simulator exists this is the embedded default scene. Its events
are exact: each pixel inside the bar's annulus sees the leading edge (brightening, +1
events) and the trailing edge (darkening, -1 events) at closed-form times; a log-contrast
of `contrast` between bar and background gives floor(contrast / C) events per edge,
spread over the time the soft edge takes to cross the pixel.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .events.types import make_events, make_triggers, sort_events


@dataclass(frozen=True)
class RotatingBar:
    width: int = 128
    height: int = 96
    duration_ns: int = 2_000_000_000
    start_ns: int = 200_000_000          # motion starts here (a trigger edge marks it)
    revolutions_per_s: float = 1.0
    bar_width_rad: float = 0.35
    edge_width_rad: float = 0.05
    inner_radius: float = 6.0
    contrast: float = 1.0                 # log(I_bar / I_background)
    threshold: float = 0.2

    def events(self) -> np.ndarray:
        yy, xx = np.mgrid[0:self.height, 0:self.width]
        cx, cy = (self.width - 1) / 2, (self.height - 1) / 2
        r = np.hypot(xx - cx, yy - cy)
        inside = (r >= self.inner_radius) & (r <= 0.45 * min(self.width, self.height))
        px, py = xx[inside], yy[inside]
        theta = np.mod(np.arctan2(py - cy, px - cx), 2 * np.pi)
        omega = 2 * np.pi * self.revolutions_per_s * 1e-9           # rad per ns
        motion_ns = self.duration_ns - self.start_ns
        n_turns = int(np.ceil(omega * motion_ns / (2 * np.pi))) + 1
        per_edge = int(np.floor(self.contrast / self.threshold + 1e-9))
        turn = np.arange(n_turns)[:, None]
        step = np.arange(per_edge)[:, None, None]
        spread = self.edge_width_rad * (step + 0.5) / per_edge
        lead = (theta + 2 * np.pi * turn + spread) / omega          # (per_edge, turns, pixels)
        trail = lead + self.bar_width_rad / omega
        t = np.concatenate([lead.ravel(), trail.ravel()])
        pol = np.repeat([1, -1], lead.size)
        x = np.tile(np.broadcast_to(px, lead.shape).ravel(), 2)
        y = np.tile(np.broadcast_to(py, lead.shape).ravel(), 2)
        # Sensor timestamps are whole microseconds.
        t_ns = self.start_ns + np.floor(t / 1000.0).astype(np.int64) * 1000
        keep = t_ns < self.duration_ns
        return sort_events(make_events(t_ns[keep], x[keep], y[keep], pol[keep]))

    def triggers(self) -> np.ndarray:
        """A rising then a falling trigger edge 1 ms apart at motion start (channel 0)."""
        return make_triggers([self.start_ns, self.start_ns + 1_000_000], [0, 0], [1, 0])
