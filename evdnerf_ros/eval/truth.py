"""The true scene as the reference of an evaluation (training sets converted from `simulate`,
or from a capture on the closed-loop virtual rig, whose camera twin renders a known scene).

A trained field is scored against the events; so is the all-zero prediction (the floor).  For
a simulated or virtual-rig session we also know the scene itself: its renderer, scored by the
same protocol on the same views and windows, is what a perfect field would reach (events are
quantised and noisy, so it is not a perfect score).  The **fraction of the floor-to-truth
margin** a field closes, ``(field - floor) / (truth - floor)``, says how far training got
independently of how hard the scene is.

What is needed is recorded by ``evdnerf convert`` in the training set's provenance under
``truth``: the scene (preset name or absolute file path), the renderer's supersampling, and per
view the scene time at the common time origin (``offset_ns - clock_offset_ns``: the view clock
reads scene time + its clock offset).  With ``--downsample 2`` the true dL is rendered at the
size before downsampling and summed over 2x2 blocks, as the events were.  A set converted with
``--crop`` is rendered through its own (shifted) intrinsics at the crop's size: the sensor
window the events came from, not the whole sensor.  A virtual-rig capture's camera twin rendered
only on a grid of its sensor clock (``render_grid``: period and, per view, the scene time of a
grid point) and joined its renders linearly in log; the reference does the same (on the
demo's 48x36 fork its squared error against the events, as a multiple of the floor's, fell
from 1.2x to 0.5x at 128 windows, from 3.1-3.4x to 0.55-0.64x at 256).  Its servo followed
the firmware's 50 Hz commands as they reached it, joined linearly; where the record has them
(``servo_tracks``: per view, scene times and degrees) the reference's servo follows them too,
not the stored profile (the firmware in simavr is paced by the wall clock: in one capture one
view's motion reached the twin about 72 ms late, and the profile-driven reference scored 4 dB
below the floor there).  A session that knows its scene but
not every view's time in it gets ``truth_note`` instead (why not), which :meth:`TrueScene.of`
reports.
"""

from __future__ import annotations

import numpy as np

from ..errors import EvdnerfError
from ..events.logmap import LOG_EPS
from ..events.slicing import frame_at_or_before
from ..geometry.camera import PinholeCamera
from ..geometry.pose_track import PoseTrack


class TrueScene:
    """Renders the true per-window log change dL of a training set's views."""

    def __init__(self, train_set, record: dict):
        from ..sim.render import SceneRenderer
        from ..sim.scene import load_scene

        self.ts = train_set
        self.record = record
        self.scene = load_scene(record["scene"], check_cameras=False)
        prov = train_set.provenance
        self.s = int(prov.get("downsample", 1))
        # the size the events had before downsampling: the crop's (whose K convert shifted), else the sensor's
        crop = prov.get("crop")
        w0, h0 = crop[2:] if crop else prov.get("source_size", [train_set.width, train_set.height])
        self.size = int(w0), int(h0)
        self.origin = {k: int(v) for k, v in record["scene_time_at_origin_ns"].items()}
        self.supersample = int(record.get("supersample", 2))
        grid = record.get("render_grid")
        self.grid_period = int(grid["period_ns"]) if grid else None
        self.grid_at = {k: int(v) for k, v in grid["scene_ns"].items()} if grid else {}
        if grid and not self.grid_period > 0:
            raise EvdnerfError(f"{train_set.path}: truth.render_grid.period_ns must be > 0, got {self.grid_period}")
        self._renderer = SceneRenderer

    @classmethod
    def of(cls, train_set) -> tuple["TrueScene | None", str]:
        """(the reference, "") or (None, why there is none)."""
        record = train_set.provenance.get("truth")
        if not record:
            return None, (train_set.provenance.get("truth_note")
                          or "no true scene: the training set was not converted from a simulated session "
                             "or a capture on the virtual rig")
        try:
            return cls(train_set, record), ""
        except EvdnerfError as exc:
            return None, f"true scene unavailable ({exc})"

    def _camera(self, view) -> PinholeCamera:
        K, s = self.ts.K(view), self.s
        # undo convert's pixel-centre scaling: fx' = fx/s, cx' = (cx + 0.5)/s - 0.5
        return PinholeCamera(width=self.size[0], height=self.size[1], fx=K[0, 0] * s, fy=K[1, 1] * s,
                             cx=(K[0, 2] + 0.5) * s - 0.5, cy=(K[1, 2] + 0.5) * s - 0.5)

    def log_change_stack(self, view, edges: np.ndarray, ks) -> np.ndarray:
        """(len(ks), H, W) float32: the true dL of windows ks (edges in the common clock)."""
        return self.log_changes(view, [(int(edges[k]), int(edges[k + 1])) for k in ks])

    def log_changes(self, view, windows) -> np.ndarray:
        """(len(windows), H, W) float32: the true dL of each (t_start, t_end) window (common
        clock), rendering each distinct time once (``eval.windows.window_changes``)."""
        from .windows import window_changes

        if view not in self.origin:
            raise EvdnerfError(f"{self.ts.path}: view {view}: no scene time recorded for it")
        servo = (self.record.get("servo_tracks") or {}).get(view)
        if servo is not None:
            from ..sim.joint import follow_servo_track

            follow_servo_track(self.scene, servo["scene_ns"], servo["deg"])
        renderer = self._renderer(self.scene, self._camera(view), supersample=self.supersample)
        track = self.ts.poses(view)
        pose_at = (PoseTrack(*track, source=f"view {view} poses") if track is not None
                   else (lambda _t, T=self.ts.pose(view): T))
        eps = float(self.ts.eps if self.ts.eps is not None else LOG_EPS)

        def log_render(t_scene: int) -> np.ndarray:
            img = renderer.render(pose_at(t_scene - self.origin[view]), t_scene)
            return np.log(np.asarray(img, np.float64) + eps)

        if self.grid_period is None:
            def log_image(t_common: int) -> np.ndarray:
                return log_render(t_common + self.origin[view])
        else:
            if view not in self.grid_at:
                raise EvdnerfError(f"{self.ts.path}: view {view}: no render grid recorded for it")
            log_image = self._on_grid(log_render, self.origin[view], self.grid_at[view])

        return np.stack([self._bin(d) for d in window_changes(log_image, windows)]).astype(np.float32)

    def _on_grid(self, log_render, origin: int, grid_point: int):
        """log_image(t_common) of a camera twin that rendered only at the scene times
        ``grid_point + k * period`` and joined them linearly in log (each grid time rendered once)."""
        on_grid = on_render_grid(log_render, self.grid_period, grid_point)
        return lambda t_common: on_grid(t_common + origin)

    def _bin(self, d: np.ndarray) -> np.ndarray:
        s = self.s
        if s == 1:
            return d
        h, w = self.ts.height, self.ts.width
        return d[:h * s, :w * s].reshape(h, s, w, s).sum(axis=(1, 3))


def on_render_grid(log_render, period: int, grid_point: int):
    """``log_image(t)`` of a frame-based camera: ``log_render`` (int64 ns -> log image) drawn only at
    the times ``grid_point + k * period`` and joined linearly in log between them, each grid time
    rendered once (the virtual rig's camera twin: ``rig.virtual.frame_ns``)."""
    renders: dict = {}

    def at(t: int) -> np.ndarray:
        if t not in renders:
            renders[t] = log_render(t)
        return renders[t]

    def log_image(t: int) -> np.ndarray:
        a = frame_at_or_before(t, period, grid_point)
        if a == t:
            return at(a)
        w = (t - a) / period
        return at(a) * (1.0 - w) + at(a + period) * w

    return log_image


def margin_closed(field: float, floor: float, truth: float) -> float | None:
    """(field - floor) / (truth - floor); None when the truth is no better than the floor (a
    static scene: no margin to close)."""
    margin = truth - floor
    if not np.isfinite(margin) or margin <= 1e-9:
        return None
    return float((field - floor) / margin)
