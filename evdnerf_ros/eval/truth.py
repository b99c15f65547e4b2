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
window the events came from, not the whole sensor.  A session that knows its scene but not
every view's time in it gets ``truth_note`` instead (why not), which :meth:`TrueScene.of` reports.
"""

from __future__ import annotations

import numpy as np

from ..errors import EvdnerfError
from ..events.logmap import LOG_EPS
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
        renderer = self._renderer(self.scene, self._camera(view), supersample=self.supersample)
        track = self.ts.poses(view)
        pose_at = (PoseTrack(*track, source=f"view {view} poses") if track is not None
                   else (lambda _t, T=self.ts.pose(view): T))
        eps = float(self.ts.eps if self.ts.eps is not None else LOG_EPS)

        def log_image(t_common: int) -> np.ndarray:
            img = renderer.render(pose_at(t_common), t_common + self.origin[view])
            return np.log(np.asarray(img, np.float64) + eps)

        return np.stack([self._bin(d) for d in window_changes(log_image, windows)]).astype(np.float32)

    def _bin(self, d: np.ndarray) -> np.ndarray:
        s = self.s
        if s == 1:
            return d
        h, w = self.ts.height, self.ts.width
        return d[:h * s, :w * s].reshape(h, s, w, s).sum(axis=(1, 3))


def margin_closed(field: float, floor: float, truth: float) -> float | None:
    """(field - floor) / (truth - floor); None when the truth is no better than the floor (a
    static scene: no margin to close)."""
    margin = truth - floor
    if not np.isfinite(margin) or margin <= 1e-9:
        return None
    return float((field - floor) / margin)
