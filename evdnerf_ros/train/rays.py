"""Ray batches for training: windows, views and pixels.

A batch is drawn from one window [t0, t1) of the current window set (the sequence cut
into ``n`` equal windows; integer ns edges), or, with ``span_fraction``, from a *span* of
consecutive windows (a uniform pair of distinct window edges): its summed events give the
log change over that longer time, still within one threshold of the truth (the events of a
pixel count from one reference level), so a span compares the scene at two distant times
as two frames would, where a single window sees only a small step.  Each ray picks a training view uniformly;
``event_ray_fraction`` of the rays go through a pixel (uniform among them) that has at
least one event in that window (``TrainingSet.event_pixels``), the rest through a
uniform pixel.  A view without events in the window gives a uniform pixel instead.
The GT log change comes from ``TrainingSet.log_change_stack`` (cached per window set).

A moving training view (a camera on a robot arm, a sweep: ``TrainingSet.poses``) sees the
static world pass by, which no static view records; its pixel's ray differs at the two window
edges, so a batch holding such rays carries the end edge's rays too (``RayBatch.moving``,
``origins_end``, ``dirs_end``; the poses interpolated as ``PoseTrack`` does), and every pixel of
such a view may change (the dynamic region selects none of its rays).

All randomness comes from the sampler's own ``numpy.random.Generator`` (its state goes
into checkpoints).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from ..errors import InputError
from ..events.slicing import frame_at_or_before, window_edges
from ..field.render import area_rays, finer, pixel_rays, subpixels
from ..geometry.camera import PinholeCamera, common_look_at
from ..geometry.pose_track import PoseTrack


def camera_of(K: np.ndarray, width: int, height: int) -> PinholeCamera:
    return PinholeCamera(width=int(width), height=int(height), fx=float(K[0, 0]),
                         fy=float(K[1, 1]), cx=float(K[0, 2]), cy=float(K[1, 2]))


def default_box(train_set, fraction: float = 0.35) -> np.ndarray:
    """(2, 3) scene box: the set's ``scene_bounds`` if present, else a cube centred on the
    least-squares common look-at point of the views' optical axes, of half-size
    ``fraction`` x the mean camera distance to it."""
    sb = getattr(train_set, "scene_bounds", None)
    if sb is not None:
        return np.asarray(sb, np.float64).reshape(2, 3)
    centres = [train_set.pose(v)[:3, 3] for v in train_set.views]
    target = common_look_at([train_set.pose(v) for v in train_set.views])
    half = fraction * float(np.mean([np.linalg.norm(c - target) for c in centres]))
    if not half > 0:
        half = 1.0
    return np.stack([target - half, target + half])


def view_rays(train_set, views, pixel_samples: int = 1) -> tuple[torch.Tensor, torch.Tensor]:
    """Origins and unit directions of every pixel of each view, (V, H*W, 3) float32 each; with
    ``pixel_samples`` s > 1 each pixel's s x s sub-pixel rays, (V, H*W, s*s, 3)."""
    s = int(pixel_samples)
    o, d = zip(*(area_rays(camera_of(train_set.K(v), train_set.width, train_set.height), train_set.pose(v), s)
                 for v in views))
    shape = (len(views), train_set.width * train_set.height) + ((s * s,) if s > 1 else ()) + (3,)
    return torch.stack(o).reshape(shape), torch.stack(d).reshape(shape)


def _pick_per_view(pix: np.ndarray, vi: np.ndarray, u: np.ndarray, candidates) -> None:
    """In place: pix[j] = a uniform pick (by u[j] in [0, 1)) among candidates(vi[j]),
    left unchanged where that view has no candidates."""
    for v in np.unique(vi):
        cand = candidates(int(v))
        if cand.size:
            sel = np.flatnonzero(vi == v)
            pix[sel] = cand[np.minimum((u[sel] * cand.size).astype(np.int64), cand.size - 1)]


@dataclass
class RayBatch:
    origins: torch.Tensor      # (N, 3)
    dirs: torch.Tensor         # (N, 3)
    dl: torch.Tensor           # (N,) GT log change of the window
    on_event: torch.Tensor     # (N,) bool: the pixel had events in the window
    t0: float                  # normalised window start
    t1: float                  # normalised window end
    window: int                # (first) window index in the current set
    n_windows: int
    views: np.ndarray          # (N,) view index into the sampler's view list
    pixels: np.ndarray         # (N,) flat pixel index
    #: rays per pixel side (``TrainConfig.pixel_samples``); above 1, ``origins`` / ``dirs`` (and
    #: the ``_end`` pair) are (N, s*s, 3): each pixel's sub-pixel rays
    pixel_samples: int = 1
    counts: torch.Tensor | None = None  # (N, 2) (positive, negative) event counts, when kept
    span: int = 1              # consecutive windows the batch spans
    #: a frame-based camera (``camera_grid``): each ray's window start and end fall between two
    #: frame times; (4, N) normalised times (start's frame before / after, end's before / after) and
    #: (2, N) weights of the later frame, the camera's log image being the frames joined linearly
    grid_times: torch.Tensor | None = None
    grid_weights: torch.Tensor | None = None
    #: rays of moving views (a training set with one): (N,) bool, and every ray's origin and
    #: direction at the window's end (equal to ``origins`` / ``dirs`` for a static view's ray)
    moving: torch.Tensor | None = None
    origins_end: torch.Tensor | None = None
    dirs_end: torch.Tensor | None = None


class RaySampler:
    def __init__(self, train_set, *, views=None, event_ray_fraction: float = 0.5,
                 seed: int = 0, dynamic=None, box=None, keep_counts: bool = False,
                 camera_grid: bool = False, pixel_samples: int = 1):
        """``keep_counts``: also return each ray's per-polarity event counts (for learned
        thresholds; needs views stored as events).  ``camera_grid``: where the set records that a
        view's camera drew the scene only on a grid of frame times (``TrainingSet.frame_grid``:
        the virtual rig's twin), each batch also carries the frame times around its window edges."""
        self.ts = train_set
        self.keep_counts = bool(keep_counts)
        self.views = list(train_set.train_views if views is None else views)
        if not self.views:
            raise InputError(f"{train_set.path}: no training views")
        self.frac = float(event_ray_fraction)
        self.rng = np.random.default_rng(seed)
        self.width, self.height = int(train_set.width), int(train_set.height)
        self.P = self.width * self.height
        self.pixel_samples = int(pixel_samples)
        self.origins, self.dirs = view_rays(train_set, self.views, self.pixel_samples)  # (V, P[, s*s], 3)
        # a moving view's rays come from its trajectory at each batch's window edges
        self.tracks = []
        t0, t1 = train_set.time_range
        for v in self.views:
            track = train_set.poses(v)
            if track is not None:
                track = PoseTrack(*track, source=f"{train_set.path}: view {v} poses")
                if track.span_ns[0] > t0 or track.span_ns[1] < t1:
                    raise InputError(f"{train_set.path}: view {v}'s camera trajectory covers "
                                     f"[{track.span_ns[0]}, {track.span_ns[1]}] ns, not the set's time range "
                                     f"[{t0}, {t1}] ns; a window edge outside it has no pose: record the "
                                     "poses over the whole recording, or make the view a validation view")
            self.tracks.append(track)
        self.moving = np.array([t is not None for t in self.tracks], bool)
        self.cameras = [camera_of(train_set.K(v), self.width, self.height) for v in self.views]
        self.finer_cameras = [finer(c, self.pixel_samples) for c in self.cameras]
        # With a dynamic region, uniform rays come only from the pixels whose rays cross
        # it: every other pixel of a static view predicts exactly no change (a moving view's
        # may all change).
        self.active = None
        if dynamic is not None:
            # (a pixel whose any sub-pixel ray crosses it)
            self.active = [np.arange(self.P) if self.moving[i] else
                           torch.nonzero(dynamic.rays_crossing(self.origins[i].reshape(-1, 3),
                                                               self.dirs[i].reshape(-1, 3), box)
                                         .reshape(self.P, -1).any(1), as_tuple=False).squeeze(1).numpy()
                           for i in range(len(self.views))]
        self._n = None
        self._edges = None
        self._dl = None                        # (V, n, P) float32
        self._counts = None                    # (V, n, P, 2) int16/int32 with keep_counts
        self._pix: dict = {}
        self._active = None                    # (V, n + 1, P) windows with a change so far
        self._centroids: dict = {}
        self.device = torch.device("cpu")
        self.grids = None                      # (V, 2) int64 (period, a frame time), or None
        if camera_grid:
            grids = [train_set.frame_grid(v) for v in self.views]
            if all(g is not None for g in grids):
                self.grids = np.array(grids, np.int64)
            if self.grids is not None and self.moving.any():
                raise InputError(f"{train_set.path}: camera_grid with a moving training view "
                                 f"({self.views[int(np.argmax(self.moving))]}) is not supported; "
                                 "set camera_grid: false")

    def to(self, device) -> "RaySampler":
        """Batches on ``device`` from now on (the rays of every view are copied there once;
        the event tables stay in host memory and only a batch's values travel)."""
        self.device = torch.device(device)
        self.origins, self.dirs = self.origins.to(self.device), self.dirs.to(self.device)
        return self

    # ----- window sets
    def set_windows(self, n: int) -> None:
        if n == self._n:
            return
        t0, t1 = self.ts.time_range
        edges = window_edges(t0, t1, int(n))
        if self.keep_counts:
            counts = np.stack([self.ts.polarity_count_stack(v, edges).reshape(len(edges) - 1, -1, 2)
                               for v in self.views])
            small = counts.max(initial=0) <= np.iinfo(np.int16).max
            self._counts = counts.astype(np.int16 if small else np.int32)
            c_pos, c_neg = self.ts.thresholds
            self._dl = (c_pos * counts[..., 0] - c_neg * counts[..., 1]).astype(np.float32)
        else:
            self._dl = np.stack([self.ts.log_change_stack(v, edges).reshape(len(edges) - 1, -1)
                                 for v in self.views])
        self._edges, self._n, self._pix, self._active = edges, int(n), {}, None

    @property
    def edges(self) -> np.ndarray:
        return self._edges

    def event_pixels(self, vi: int, k: int) -> np.ndarray:
        key = (vi, k)
        if key not in self._pix:
            self._pix[key] = self.ts.event_pixels(self.views[vi], int(self._edges[k]),
                                                  int(self._edges[k + 1]))
        return self._pix[key]

    def span_pixels(self, vi: int, k0: int, k1: int) -> np.ndarray:
        """Pixels of view ``vi`` whose log change is non-zero in some window of k0..k1-1."""
        if self._active is None:
            changed = self._dl != 0
            if self._counts is not None:
                changed |= self._counts.any(axis=-1)
            dtype = np.int16 if self._n < np.iinfo(np.int16).max else np.int32
            self._active = np.zeros((changed.shape[0], self._n + 1, changed.shape[2]), dtype)
            np.cumsum(changed, axis=1, out=self._active[:, 1:])
        return np.flatnonzero(self._active[vi, k1] != self._active[vi, k0])

    # ----- batches
    def event_centroid(self, vi: int) -> tuple[float, float]:
        """(x, y) centroid of the view's pixels with events over the whole sequence (the
        image centre for a view without events)."""
        if vi not in self._centroids:
            t0, t1 = self.ts.time_range
            pix = self.ts.event_pixels(self.views[vi], t0, t1)
            if pix.size:
                self._centroids[vi] = (float(np.mean(pix % self.width)),
                                       float(np.mean(pix // self.width)))
            else:
                self._centroids[vi] = ((self.width - 1) / 2, (self.height - 1) / 2)
        return self._centroids[vi]

    def crop_box(self, vi: int, fraction: float) -> tuple[int, int, int, int]:
        """(x0, y0, w, h) of the centred crop (``fraction`` of each side) of a view."""
        w = max(1, int(round(self.width * fraction)))
        h = max(1, int(round(self.height * fraction)))
        cx, cy = self.event_centroid(vi)
        x0 = int(np.clip(round(cx - (w - 1) / 2), 0, self.width - w))
        y0 = int(np.clip(round(cy - (h - 1) / 2), 0, self.height - h))
        return x0, y0, w, h

    def sample(self, rays: int, *, usable_windows: int | None = None,
               crop: float | None = None, span_fraction: float = 0.0) -> RayBatch:
        """A batch of ``rays`` rays from one window among the first ``usable_windows``, or
        with probability ``span_fraction`` from a span of them (module docstring);
        ``crop`` (a fraction in (0, 1]) limits the uniform rays to the crop centred on each
        view's event centroid (the paper's crop warm-up); with a dynamic region the uniform
        rays come from the pixels that see it instead, a tighter focus, and ``crop`` is moot."""
        if self._n is None:
            raise RuntimeError("call set_windows(n) first")
        rng = self.rng
        m = self._n if usable_windows is None else max(1, min(self._n, int(usable_windows)))
        span = 1
        if span_fraction > 0 and m > 1 and rng.random() < span_fraction:
            k, k_end = sorted(int(e) for e in rng.choice(m + 1, size=2, replace=False))
            span = k_end - k
        else:
            k = int(rng.integers(m))
        vi = rng.integers(len(self.views), size=rays)
        if self.active is not None:
            pix = rng.integers(self.P, size=rays)
            _pick_per_view(pix, vi, rng.random(rays), lambda v: self.active[v])
        elif crop is None or crop >= 1.0:
            pix = rng.integers(self.P, size=rays)
        else:
            boxes = np.array([self.crop_box(v, crop) for v in range(len(self.views))])[vi]
            ux, uy = rng.random(rays), rng.random(rays)
            x = boxes[:, 0] + np.minimum((ux * boxes[:, 2]).astype(np.int64), boxes[:, 2] - 1)
            y = boxes[:, 1] + np.minimum((uy * boxes[:, 3]).astype(np.int64), boxes[:, 3] - 1)
            pix = y * self.width + x
        if span == 1:
            def events_in(v):
                return self.event_pixels(v, k)
        else:
            def events_in(v):
                return self.span_pixels(v, k, k + span)
        n_ev = int(round(self.frac * rays))
        # the first n_ev rays: event pixels (a view without any keeps its uniform pixel)
        _pick_per_view(pix[:n_ev], vi[:n_ev], rng.random(n_ev), events_in)
        dev = self.device
        vi_t = torch.as_tensor(vi, device=dev)
        pix_t = torch.as_tensor(pix, device=dev)
        if span == 1:
            dl = self._dl[vi, k, pix]
            counts = None if self._counts is None else self._counts[vi, k, pix].astype(np.int32)
        else:
            ks = np.arange(k, k + span)[None, :]
            dl = self._dl[vi[:, None], ks, pix[:, None]].sum(axis=1, dtype=np.float32)
            counts = None if self._counts is None else \
                self._counts[vi[:, None], ks, pix[:, None]].astype(np.int32).sum(axis=1)
        on_event = np.zeros(rays, bool)
        for v in np.unique(vi):                    # mark every ray whose pixel had events
            sel = vi == v
            on_event[sel] = np.isin(pix[sel], events_in(int(v)))
        tn = self.ts.normalized_time(self._edges[[k, k + span]])
        grid_times = grid_weights = None
        if self.grids is not None:
            grid_times, grid_weights = self._frame_times(self._edges[[k, k + span]], vi)
        origins, dirs = self.origins[vi_t, pix_t], self.dirs[vi_t, pix_t]
        moving = origins_end = dirs_end = None
        if self.moving.any():
            moving = self.moving[vi]
            origins_end, dirs_end = origins.clone(), dirs.clone()
            for (o, d), edge in (((origins, dirs), k), ((origins_end, dirs_end), k + span)):
                self._moving_rays(o, d, vi, pix, int(self._edges[edge]))
            moving = torch.as_tensor(moving, device=dev)
        return RayBatch(origins=origins, dirs=dirs, moving=moving, origins_end=origins_end, dirs_end=dirs_end,
                        dl=torch.as_tensor(dl, device=dev),
                        on_event=torch.as_tensor(on_event, device=dev), t0=float(tn[0]), t1=float(tn[1]),
                        window=k, n_windows=self._n, views=vi, pixels=pix, span=span,
                        pixel_samples=self.pixel_samples,
                        counts=None if counts is None else torch.as_tensor(counts, device=dev),
                        grid_times=grid_times, grid_weights=grid_weights)

    def _moving_rays(self, origins: torch.Tensor, dirs: torch.Tensor, vi: np.ndarray,
                     pix: np.ndarray, edge_ns: int) -> None:
        """Overwrite, in place, the rays of moving views' pixels with their rays at ``edge_ns``."""
        for v in np.unique(vi[self.moving[vi]]):
            sel = np.flatnonzero(vi == v)
            pose = self.tracks[v].poses([edge_ns])
            sub = subpixels(self.width, pix[sel], self.pixel_samples).reshape(-1)
            o, d = pixel_rays(self.finer_cameras[v], pose, np.zeros(sub.size, np.int64), sub, device=self.device)
            idx = torch.as_tensor(sel, device=self.device)
            origins[idx], dirs[idx] = o.reshape(origins[idx].shape), d.reshape(dirs[idx].shape)

    def _frame_times(self, edges: np.ndarray, vi: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
        """((4, N) normalised frame times around the two window edges, (2, N) weights of the later
        frame) of rays from views ``vi`` (int64 arithmetic: the frames lie on each view's grid)."""
        period, point = self.grids[vi, 0], self.grids[vi, 1]
        times, weights = [], []
        for edge in edges:
            before = frame_at_or_before(np.int64(edge), period, point)
            times += [before, before + period]
            weights.append((np.int64(edge) - before) / period)
        tn = self.ts.normalized_time(np.stack(times).reshape(-1)).reshape(4, -1)
        dev = self.device
        return (torch.as_tensor(tn, dtype=torch.float32, device=dev),
                torch.as_tensor(np.stack(weights), dtype=torch.float32, device=dev))


@dataclass
class FrameBatch:
    origins: torch.Tensor      # (N, 3)
    dirs: torch.Tensor         # (N, 3)
    grey: torch.Tensor         # (N,) the blurred frame's linear intensity
    t: float                   # normalised mid-exposure time of the frame


class FrameSampler:
    """Rays through the blurred grey frames (the paper's DNeRF-on-blurred-frames baseline):
    per batch one frame index, shared by all views (they are synchronised), views uniform
    per ray, pixels uniform; the frame is rendered at its mid-exposure time."""

    def __init__(self, train_set, *, views=None, seed: int = 0):
        self.ts = train_set
        self.views = list(train_set.train_views if views is None else views)
        stacks, times = [], []
        for v in self.views:
            if train_set.poses(v) is not None:
                raise InputError(f"{train_set.path}: view {v} is a moving camera; frame supervision "
                                 "renders static views only (train it on events, or drop the view)")
            fr = train_set.frames(v)
            if fr is None or not len(fr["frames"]):
                raise InputError(f"{train_set.path}: view {v} has no blurred frames; "
                                 "frame supervision needs them (simulate with --frame-rate > 0)")
            stacks.append(np.asarray(fr["frames"], np.float32).reshape(len(fr["frames"]), -1))
            mid = np.asarray(fr["t_start"], np.int64) + (np.asarray(fr["t_end"], np.int64)
                                                        - np.asarray(fr["t_start"], np.int64)) // 2
            times.append(mid)
        n = min(len(s) for s in stacks)
        self.frames = np.stack([s[:n] for s in stacks])               # (V, F, P)
        t0, t1 = train_set.time_range
        keep = (times[0][:n] >= t0) & (times[0][:n] <= t1)
        if not keep.any():
            raise InputError(f"{train_set.path}: no blurred frame lies in the training time range")
        self.frame_index = np.flatnonzero(keep)
        self.t_norm = train_set.normalized_time(times[0][:n])
        self.rng = np.random.default_rng(seed)
        self.origins, self.dirs = view_rays(train_set, self.views)
        self.P = train_set.width * train_set.height
        self.device = torch.device("cpu")

    def to(self, device) -> "FrameSampler":
        """Batches on ``device`` from now on (as ``RaySampler.to``)."""
        self.device = torch.device(device)
        self.origins, self.dirs = self.origins.to(self.device), self.dirs.to(self.device)
        return self

    def sample(self, rays: int) -> FrameBatch:
        f = int(self.frame_index[self.rng.integers(len(self.frame_index))])
        vi = self.rng.integers(len(self.views), size=rays)
        pix = self.rng.integers(self.P, size=rays)
        vt, pt = torch.as_tensor(vi, device=self.device), torch.as_tensor(pix, device=self.device)
        return FrameBatch(origins=self.origins[vt, pt], dirs=self.dirs[vt, pt],
                          grey=torch.as_tensor(self.frames[vi, f, pix], device=self.device),
                          t=float(self.t_norm[f]))
