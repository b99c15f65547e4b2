"""The training set: one HDF5 file (h5py) that `evdnerf convert` writes and the trainer reads.

Layout (``layout = "evdnerf_ros.trainingset"``, ``layout_version = 1``)
-----------------------------------------------------------------------
```
/                                   root attributes:
    layout, layout_version            "evdnerf_ros.trainingset", 1
    time_unit                         "ns"
    width, height                     image size of every view (after downsampling)
    c_pos, c_neg                      contrast thresholds C+ / C- (paper Eq. 5)
    eps                               the log-intensity epsilon, when known
    t_start, t_end                    the time range [t_start, t_end) of the set, int64 ns
                                      in the common (synced) clock: t = 0 is the common
                                      motion onset found by `evdnerf sync`
    index_step_ns                     step of the per-view time index (1 ms)
    downsample                        1, or 2 when events were summed over 2x2 blocks
    compression                       "scaleoffset" (default) or "gzip"
    view_names                        JSON list: the views, in session order
    scene_bounds                      (2, 3) float64 [min; max] in metres, only when known
/provenance                         JSON text: source bags, sync offsets and their source,
                                    software version, session.yaml sha256, window source, ...
/views/<name>/                      one group per view; attributes:
    split                             "train" | "val"
    num_events                        events stored (0 for views that only have dl windows)
    has_events                        False for imported frame-only views (see dl/ below)
    offset_ns                         the view clock's reading at common t = 0 (provenance;
                                      t_common = t_view - offset_ns)
    moving                            True when poses/ holds a camera trajectory
  K                                 (3, 3) float64 intrinsics (pixel centres at integer
                                    coordinates, OpenCV / ROS convention)
  T_world_cam                       (4, 4) float64 camera-to-world pose, OpenCV camera axes
                                    (x right, y down, z forward): the static pose of the view
  events/t, x, y, p                 int64 ns (common clock), uint16, uint16, int8 (+1 / -1);
                                    sorted by t, t_start <= t < t_end, x < width, y < height;
                                    chunked (65536 events) and compressed
  events/index                      int64 (n_bins + 1,), n_bins = ceil((t_end - t_start) /
                                    index_step_ns): index[k] = number of events with
                                    t < t_start + k * index_step_ns (so index[0] = 0 and
                                    index[-1] = num_events). A window [t0, t1) is found by
                                    reading only the events of the two 1-ms bins holding t0
                                    and t1 and binary-searching them (never a scan).
  poses/t, poses/T_world_cam        (M,) int64 ns (common clock), (M, 4, 4) float64: a moving
                                    camera's trajectory (from the bag's pose topic)
  frames/frames, t_start, t_end, t  optional motion-blurred grey frames (N, H, W) float32
                                    linear intensity, exposure start / end / centre times in
                                    the common clock (the session's frames .npz shifted by the
                                    view's offset; 2x2 means when downsampled)
  dl/edges, dl/windows              only for sets imported from EvDNeRF files that carry no
                                    raw events: (K + 1,) int64 window edges (common clock) and
                                    (K, H, W) float32 pre-binned dL = C+ N+ - C- N- per window
```

Compression: "scaleoffset" is HDF5's built-in lossless integer scale-offset filter (each
chunk stores its minimum and only the bits the range needs: about 5.5 bytes per event at
high rates, written at > 40 M events/s); "gzip" (level 1 + shuffle) is smaller (~4 bytes per
event) but about 4x slower to write. Both are part of every libhdf5, so any HDF5 reader
opens the file.

Reading: :class:`TrainingSet` (a context manager) gives the views, intrinsics, poses, split
and thresholds, and reads windows by binary search through the time index, in chunks, so a
1e8-event set never has to sit in RAM.

Damaged files: opening checks the whole layout above (attributes, ranks, dtypes, lengths,
the time index, K and poses) before reading any event, and checks declared sizes against the
memory budget (:func:`evdnerf_ros.limits.check_memory`); every block of events read later is
checked against the geometry, polarity and time order (scaleoffset has no checksum, so a
flipped bit can give an impossible pixel), and every HDF5 failure becomes a FormatError
naming the file and the view. Writing goes through :mod:`evdnerf_ros.io.guard`: a full disk
or a file-size limit ends in one error naming the output, never in a crash inside HDF5.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..atomic import atomic_output
from ..errors import FormatError, InputError
from ..events.types import EVENT_DTYPE, validate_events
from ..geometry.poses import check_rigid
from ..limits import check_memory
from .guard import h5_close, h5_create, h5_dataset, h5_memory, h5_number, h5_open, h5_reading, h5_text

LAYOUT = "evdnerf_ros.trainingset"
LAYOUT_VERSION = 1
INDEX_STEP_NS = 1_000_000
EVENT_CHUNK = 1 << 16
COMPRESSIONS = ("scaleoffset", "gzip")
SPLITS = ("train", "val")
#: Events per block when a reader streams through a long window.
READ_BLOCK = 1 << 22
#: Contrast thresholds (log-intensity units) outside (0, C_MAX] are refused.
C_MAX = 10.0
#: Times (ns) beyond this magnitude are refused (int64 arithmetic on them must not overflow).
T_LIMIT = 2**62
_FIX = "the training set is damaged; write it again with `evdnerf convert`"


def _filters(compression: str) -> dict:
    if compression == "scaleoffset":
        return {"scaleoffset": 0}
    if compression == "gzip":
        return {"compression": "gzip", "compression_opts": 1, "shuffle": True}
    raise InputError(f"compression {compression!r} is not one of {list(COMPRESSIONS)}")


def check_K(K, what: str) -> np.ndarray:
    try:
        K = np.asarray(K, np.float64)
    except (TypeError, ValueError):
        raise InputError(f"{what}: K is not a numeric 3x3 matrix") from None
    if K.shape != (3, 3) or not np.all(np.isfinite(K)):
        raise InputError(f"{what}: K must be a finite 3x3 matrix, got shape {K.shape}")
    if not (K[0, 0] > 0 and K[1, 1] > 0) or not np.array_equal(K[2], [0.0, 0.0, 1.0]):
        raise InputError(f"{what}: K is not a pinhole intrinsic matrix (need fx, fy > 0 and last "
                         f"row [0, 0, 1]); got {K.tolist()}")
    return K


# =========================================================================== writing


class _ViewWriter:
    """Appends one view's events (sorted batches) and builds its time index on the fly."""

    def __init__(self, owner: "TrainingSetWriter", name: str, group):
        self.owner, self.name, self.group = owner, name, group
        self.what = f"training set view {name}"
        self.n = 0
        self.last_t: int | None = None
        self._index_parts: list[np.ndarray] = []
        self._next_k = 0                    # next index edge still to fill
        self._ds = None
        self.has_events = True

    def _datasets(self):
        if self._ds is None:
            g = self.group.create_group("events")
            kw = _filters(self.owner.compression)
            self._ds = {name: g.create_dataset(name, shape=(0,), maxshape=(None,), dtype=EVENT_DTYPE[name],
                                               chunks=(self.owner.chunk,), **kw)
                        for name in ("t", "x", "y", "p")}
        return self._ds

    def append(self, events: np.ndarray) -> None:
        """Append a batch: sorted, continuing the previous batch in time, inside the geometry
        and the time range (InputError otherwise; nothing is published then)."""
        o = self.owner
        validate_events(events, width=o.width, height=o.height, source=self.what)
        ds = self._datasets()
        if events.size == 0:
            return
        t = events["t"]
        t0, t1 = int(t[0]), int(t[-1])
        if self.last_t is not None and t0 < self.last_t:
            raise InputError(f"{self.what}: batch starts at t={t0} ns, before the previous batch's last "
                             f"event (t={self.last_t} ns); batches must continue in time")
        if t0 < o.t_start:
            raise InputError(f"{self.what}: event at t={t0} ns lies before the set's t_start={o.t_start} ns")
        if o.t_end is not None and t1 >= o.t_end:
            raise InputError(f"{self.what}: event at t={t1} ns lies at or after the set's t_end={o.t_end} ns")
        # time index: edges t_start + k*step that are <= the batch's last event
        step = o.index_step_ns
        if o.t_end is None:
            o._check_index_size(t1 + 1)
        k_max = (t1 - o.t_start) // step
        if k_max >= self._next_k:
            edges = o.t_start + step * np.arange(self._next_k, k_max + 1, dtype=np.int64)
            self._index_parts.append(self.n + np.searchsorted(t, edges, "left").astype(np.int64))
            self._next_k = k_max + 1
        m = events.size
        for name, d in ds.items():
            d.resize((self.n + m,))
            d[self.n:self.n + m] = np.ascontiguousarray(events[name])
        self.n += m
        self.last_t = t1
        o.check_written()

    def add_frames(self, frames, t_start, t_end, t=None) -> None:
        """Blurred grey frames (N, H, W) float32 with exposure times (int64 ns, common clock)."""
        o = self.owner
        frames = np.asarray(frames, np.float32)
        if frames.ndim != 3 or frames.shape[1:] != (o.height, o.width):
            raise InputError(f"{self.what}: frames have shape {frames.shape}, expected (N, {o.height}, {o.width})")
        ts, te = np.asarray(t_start), np.asarray(t_end)
        for nm, a in (("t_start", ts), ("t_end", te)):
            if a.shape != (frames.shape[0],) or a.dtype.kind not in "iu":
                raise InputError(f"{self.what}: frames {nm} must be {frames.shape[0]} int64 ns times")
        ts, te = ts.astype(np.int64), te.astype(np.int64)
        t = (ts + (te - ts) // 2) if t is None else np.asarray(t).astype(np.int64)
        if frames.shape[0] == 0:
            return
        g = self.group.create_group("frames")
        g.create_dataset("frames", data=frames, chunks=(1,) + frames.shape[1:], compression="gzip",
                         compression_opts=1, shuffle=True)
        for nm, a in (("t_start", ts), ("t_end", te), ("t", t)):
            g.create_dataset(nm, data=a)
        o.check_written()

    def set_dl_windows(self, edges, windows) -> None:
        """Pre-binned dL windows (imported EvDNeRF sets without raw events)."""
        o = self.owner
        edges = np.asarray(edges)
        windows = np.asarray(windows, np.float32)
        if edges.dtype.kind not in "iu" or edges.ndim != 1 or edges.size < 2 or np.any(np.diff(edges) <= 0):
            raise InputError(f"{self.what}: dl edges must be a strictly increasing int64 array of >= 2 times")
        if windows.shape != (edges.size - 1, o.height, o.width):
            raise InputError(f"{self.what}: dl windows have shape {windows.shape}, expected "
                             f"({edges.size - 1}, {o.height}, {o.width})")
        if not np.all(np.isfinite(windows)):
            raise InputError(f"{self.what}: dl windows contain NaN or inf")
        g = self.group.create_group("dl")
        g.create_dataset("edges", data=edges.astype(np.int64))
        g.create_dataset("windows", data=windows, chunks=(1, o.height, o.width), compression="gzip",
                         compression_opts=1, shuffle=True)
        self.has_events = False
        o.check_written()

    def _count_before(self, t_end: int) -> int:
        """Number of stored events with t < t_end (reads one index bin)."""
        if self.n == 0 or t_end > self.last_t:
            return self.n
        o = self.owner
        index = np.concatenate(self._index_parts) if self._index_parts else np.zeros(1, np.int64)
        k = max(0, (t_end - o.t_start) // o.index_step_ns)
        lo = int(index[min(k, index.size - 1)])
        hi = int(index[k + 1]) if k + 1 < index.size else self.n
        t = self._ds["t"][lo:hi]
        return lo + int(np.searchsorted(t, t_end, "left"))

    def finish(self, t_end: int) -> None:
        o = self.owner
        ds = self._datasets() if self.has_events else None
        n_end = self._count_before(t_end)
        if ds is not None and n_end < self.n:          # drop what lies past the end of the window
            for d in ds.values():
                d.resize((n_end,))
            self.n = n_end
        n_bins = max(1, -(-(t_end - o.t_start) // o.index_step_ns))
        index = np.concatenate(self._index_parts) if self._index_parts else np.zeros(0, np.int64)
        index = np.minimum(index[:n_bins + 1], self.n)
        if index.size < n_bins + 1:
            index = np.concatenate([index, np.full(n_bins + 1 - index.size, self.n, np.int64)])
        index[-1] = self.n if ds is not None else 0
        if ds is not None:
            self.group["events"].create_dataset("index", data=index)
        self.group.attrs["num_events"] = int(self.n)
        self.group.attrs["has_events"] = bool(self.has_events)


class TrainingSetWriter:
    """Writes the layout above into `path` (give it a temporary path from
    :func:`evdnerf_ros.atomic.atomic_output`, or use :func:`write_training_set`).

    ``t_end`` may be left None while streaming and given to :meth:`finish`; events at or
    after it are then dropped from every view (the automatic motion end of `convert`).
    """

    def __init__(self, path, *, width: int, height: int, c_pos: float, c_neg: float, t_start: int,
                 t_end: int | None = None, eps: float | None = None, downsample: int = 1,
                 compression: str = "scaleoffset", index_step_ns: int = INDEX_STEP_NS,
                 chunk: int = EVENT_CHUNK, display=None):
        self.path = Path(path)
        # `display`: the output's real name (path is usually the atomic helper's temporary one)
        self.display = Path(display) if display is not None else self.path
        for nm, v in (("width", width), ("height", height)):
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or not 0 < int(v) <= 65535:
                raise InputError(f"training set: {nm} must be an integer in [1, 65535], got {v!r}")
        if not (math.isfinite(c_pos) and math.isfinite(c_neg) and 0 < c_pos <= C_MAX and 0 < c_neg <= C_MAX):
            raise InputError(f"training set: thresholds must be in (0, {C_MAX:g}], got C+={c_pos}, C-={c_neg}")
        _filters(compression)
        self.width, self.height = int(width), int(height)
        self.c_pos, self.c_neg, self.eps = float(c_pos), float(c_neg), eps
        self.t_start = int(t_start)
        self.t_end = None if t_end is None else int(t_end)
        if self.t_end is not None and self.t_end <= self.t_start:
            raise InputError(f"training set: t_end={self.t_end} must be after t_start={self.t_start}")
        self.downsample = int(downsample)
        self.compression = compression
        self.index_step_ns = int(index_step_ns)
        if self.index_step_ns < 1:
            raise InputError(f"training set: index_step_ns must be >= 1, got {index_step_ns}")
        if self.t_end is not None:
            self._check_index_size(self.t_end)
        self.chunk = int(chunk)
        self.file, self._guard = h5_create(self.path, self.display)
        self._views_group = self.file.create_group("views")
        self.views: dict[str, _ViewWriter] = {}

    def add_view(self, name: str, *, split: str, K, T_world_cam, poses_t=None, poses_T=None,
                 attrs: dict | None = None) -> _ViewWriter:
        what = f"training set view {name!r}"
        if not isinstance(name, str) or not name or "/" in name or name in (".", ".."):
            raise InputError(f"{what}: a view name must be a non-empty string without '/'")
        if name in self.views:
            raise InputError(f"{what}: duplicate view name; view names must be unique")
        if split not in SPLITS:
            raise InputError(f"{what}: split {split!r} is not one of {SPLITS}")
        K = check_K(K, what)
        T = check_rigid(T_world_cam, f"{what}: T_world_cam")
        g = self._views_group.create_group(name)
        g.attrs["split"] = split
        g.attrs["moving"] = poses_t is not None
        for k, v in (attrs or {}).items():
            g.attrs[k] = v
        g.create_dataset("K", data=K)
        g.create_dataset("T_world_cam", data=T)
        if poses_t is not None:
            pt = np.asarray(poses_t)
            pT = np.asarray(poses_T, np.float64)
            if pt.ndim != 1 or pt.dtype.kind not in "iu" or pT.shape != (pt.size, 4, 4) or pt.size == 0:
                raise InputError(f"{what}: poses need (M,) int64 times and (M, 4, 4) matrices")
            if np.any(np.diff(pt) < 0):
                raise InputError(f"{what}: pose times are not sorted")
            for i in range(pt.size):
                check_rigid(pT[i], f"{what}: pose {i} (t={int(pt[i])} ns)")
            pg = g.create_group("poses")
            pg.create_dataset("t", data=pt.astype(np.int64))
            pg.create_dataset("T_world_cam", data=pT)
        vw = _ViewWriter(self, name, g)
        self.views[name] = vw
        self.check_written()
        return vw

    def finish(self, *, t_end: int | None = None, provenance: dict | None = None,
               scene_bounds=None, attrs: dict | None = None) -> None:
        """Cut every view at t_end, write the indexes and the global attributes."""
        t_end = self.t_end if t_end is None else int(t_end)
        if t_end is None:
            raise InputError("training set: t_end is unknown; give it to finish()")
        if t_end <= self.t_start:
            raise InputError(f"training set: t_end={t_end} must be after t_start={self.t_start}")
        if self.t_end is not None and t_end > self.t_end:
            raise InputError(f"training set: t_end={t_end} is after the declared t_end={self.t_end}")
        self._check_index_size(t_end)
        if not self.views:
            raise InputError("training set: no views")
        for vw in self.views.values():
            vw.finish(t_end)
        a = self.file.attrs
        a.update(layout=LAYOUT, layout_version=LAYOUT_VERSION, time_unit="ns", width=self.width,
                 height=self.height, c_pos=self.c_pos, c_neg=self.c_neg, t_start=np.int64(self.t_start),
                 t_end=np.int64(t_end), index_step_ns=np.int64(self.index_step_ns),
                 downsample=self.downsample, compression=self.compression,
                 view_names=json.dumps(list(self.views)))
        if self.eps is not None:
            a["eps"] = float(self.eps)
        if scene_bounds is not None:
            b = np.asarray(scene_bounds, np.float64)
            if b.shape != (2, 3) or not np.all(np.isfinite(b)) or np.any(b[1] < b[0]):
                raise InputError(f"training set: scene_bounds must be [[xmin, ymin, zmin], [xmax, ymax, zmax]], "
                                 f"got {np.asarray(scene_bounds).tolist()}")
            a["scene_bounds"] = b
        for k, v in (attrs or {}).items():
            a[k] = v
        self.file.create_dataset("provenance", data=json.dumps(provenance or {}, indent=1, default=_json_default))
        self.t_end = t_end
        self.check_written()

    def _check_index_size(self, t_end: int) -> None:
        """The time index has one entry per step of [t_start, t_end): size it first."""
        n_bins = -(-(t_end - self.t_start) // self.index_step_ns)
        check_memory(16 * (n_bins + 1), f"{self.display}: a time index of {n_bins} bins of {self.index_step_ns} ns "
                     f"over [{self.t_start}, {t_end}) ns",
                     "the time window is implausibly long; give a shorter window (--start/--end) or fix the "
                     "times in session.yaml")

    def check_written(self) -> None:
        """Raise OutputWriteError naming the output once a write has failed (disk full)."""
        self._guard.check()

    def close(self, *, check: bool = True) -> None:
        if self.file is not None:
            f, self.file = self.file, None
            h5_close(f, self._guard, check=check)

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb):
        self.close(check=exc_type is None)
        if exc_type is not None and issubclass(exc_type, Exception):
            self.check_written()          # a failed write explains whatever went wrong after it
        return False


def _json_default(o):
    if isinstance(o, np.integer):
        return int(o)
    if isinstance(o, np.floating):
        return float(o)
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


@dataclass
class ViewData:
    """One view for :func:`write_training_set` (in-memory data)."""

    name: str
    split: str
    K: np.ndarray
    T_world_cam: np.ndarray
    events: np.ndarray | None = None
    poses_t: np.ndarray | None = None
    poses_T: np.ndarray | None = None
    frames: dict | None = None            # frames, t_start, t_end[, t]
    dl_edges: np.ndarray | None = None
    dl_windows: np.ndarray | None = None
    attrs: dict = field(default_factory=dict)


def write_training_set(path, views: list[ViewData], *, width: int, height: int, c_pos: float, c_neg: float,
                       t_start: int, t_end: int, eps: float | None = None, downsample: int = 1,
                       provenance: dict | None = None, scene_bounds=None, compression: str = "scaleoffset",
                       overwrite: bool = False) -> Path:
    """Write a whole training set from in-memory views, atomically."""
    with atomic_output(path, overwrite=overwrite) as tmp:
        with TrainingSetWriter(tmp, width=width, height=height, c_pos=c_pos, c_neg=c_neg, t_start=t_start,
                               t_end=t_end, eps=eps, downsample=downsample, compression=compression,
                               display=path) as w:
            for v in views:
                vw = w.add_view(v.name, split=v.split, K=v.K, T_world_cam=v.T_world_cam, poses_t=v.poses_t,
                                poses_T=v.poses_T, attrs=v.attrs)
                if v.events is not None:
                    for i in range(0, max(v.events.size, 1), READ_BLOCK):
                        vw.append(v.events[i:i + READ_BLOCK])
                if v.frames is not None:
                    vw.add_frames(v.frames["frames"], v.frames["t_start"], v.frames["t_end"], v.frames.get("t"))
                if v.dl_windows is not None:
                    if v.events is not None and v.events.size:
                        raise InputError(f"view {v.name}: give either raw events or dl windows, not both")
                    vw.set_dl_windows(v.dl_edges, v.dl_windows)
            w.finish(t_end=t_end, provenance=provenance, scene_bounds=scene_bounds)
    return Path(path)


# =========================================================================== reading


@dataclass
class ViewInfo:
    name: str
    index: int
    split: str
    K: np.ndarray
    T_world_cam: np.ndarray
    num_events: int
    has_events: bool
    offset_ns: int | None
    moving: bool


class TrainingSet:
    """Read-only access to a training-set .h5 (see the module doc for the layout).

    ``view`` arguments take a view name or its position in :attr:`views`. Times are int64
    ns in the set's common clock; windows are half-open [t0, t1).
    """

    def __init__(self, path, *, cache_mb: int = 16):
        self.path = Path(path)
        if not self.path.is_file():
            raise InputError(f"{self.path}: no such training set file")
        self._f = h5_open(self.path, hint="a training set is what `evdnerf convert` writes",
                          rdcc_nbytes=int(cache_mb) << 20, rdcc_nslots=10007)
        try:
            with h5_reading(self.path, hint=_FIX):
                self._load()
        except BaseException:
            self.close()
            raise

    def _load(self):
        f, where = self._f, str(self.path)
        a = f.attrs
        if h5_text(a, "layout", where, required=False) != LAYOUT:
            raise FormatError(f"not a training set (root attribute layout must be {LAYOUT!r}; files written "
                              "by `evdnerf convert` or `evdnerf import-evdnerf` are)", source=where)
        version = a.get("layout_version", -1)
        if not isinstance(version, (int, np.integer)) or int(version) != LAYOUT_VERSION:
            raise FormatError(f"layout_version {version!r} is not supported (this toolkit "
                              f"reads {LAYOUT_VERSION})", source=where)
        num = lambda key, **kw: h5_number(a, key, where, **kw)  # noqa: E731
        self.width = num("width", integer=True, low=1, high=65535)
        self.height = num("height", integer=True, low=1, high=65535)
        self.c_pos = float(num("c_pos", low=0, low_open=True, high=C_MAX))
        self.c_neg = float(num("c_neg", low=0, low_open=True, high=C_MAX))
        self.t_start = num("t_start", integer=True, low=-T_LIMIT, high=T_LIMIT)
        self.t_end = num("t_end", integer=True, low=-T_LIMIT, high=T_LIMIT)
        if self.t_end <= self.t_start:
            raise FormatError(f"t_end={self.t_end} is not after t_start={self.t_start}; {_FIX}", source=where)
        self.index_step_ns = num("index_step_ns", integer=True, low=1, high=T_LIMIT)
        eps = num("eps", required=False, low=0, low_open=True)
        self.eps = None if eps is None else float(eps)
        self.downsample = num("downsample", required=False, default=1, integer=True, low=1, high=64)
        self.scene_bounds = None
        if "scene_bounds" in a:
            b = np.asarray(a["scene_bounds"])
            if b.shape != (2, 3) or b.dtype.kind not in "iuf" or not np.all(np.isfinite(b)) or np.any(b[1] < b[0]):
                raise FormatError(f"attribute scene_bounds must be [[xmin, ymin, zmin], [xmax, ymax, zmax]]; {_FIX}",
                                  source=where)
            self.scene_bounds = b.astype(np.float64)
        try:
            names = json.loads(h5_text(a, "view_names", where))
        except ValueError:
            names = None
        if (not isinstance(names, list) or not names or not all(isinstance(n, str) and n and "/" not in n
                                                                for n in names) or len(set(names)) != len(names)):
            raise FormatError(f"attribute view_names must be a JSON list of unique view names; {_FIX}", source=where)
        h5_memory(self.width * self.height * 8, where, f"one {self.width}x{self.height} image")
        self.n_bins = -(-(self.t_end - self.t_start) // self.index_step_ns)
        h5_memory(len(names) * (self.n_bins + 1) * 8, where,
                  f"the time index ({len(names)} views x {self.n_bins + 1} bins of {self.index_step_ns} ns)")
        self._infos: dict[str, ViewInfo] = {}
        self._index: dict[str, np.ndarray] = {}
        for i, name in enumerate(names):
            self._infos[name] = self._load_view(i, name)
        self.views: list[str] = list(names)

    def _load_view(self, i: int, name: str) -> ViewInfo:
        """One view's metadata, checked; its time index is read (small), its events are not."""
        import h5py

        f, where = self._f, str(self.path)
        g = f["views"].get(name) if isinstance(f.get("views"), h5py.Group) else None
        if not isinstance(g, h5py.Group):
            raise FormatError(f"view {name!r} is listed in view_names but has no group views/{name}", source=where)
        what = f"{where}: view {name}"
        split = h5_text(g.attrs, "split", where)
        if split not in SPLITS:
            raise FormatError(f"view {name}: split {split!r} is not one of {SPLITS}; {_FIX}", source=where)
        K = check_K(h5_dataset(g, "K", where, shape=(3, 3), kinds="iuf", what=f"view {name}: K")[()], what)
        T = check_rigid(h5_dataset(g, "T_world_cam", where, shape=(4, 4), kinds="iuf",
                                  what=f"view {name}: T_world_cam")[()], f"{what}: T_world_cam")
        num_events = h5_number(g.attrs, "num_events", f"{where}: view {name}", integer=True, low=0, high=T_LIMIT)
        has_events = g.attrs.get("has_events", True)
        if not isinstance(has_events, (bool, np.bool_)):
            raise FormatError(f"view {name}: attribute has_events must be a boolean; {_FIX}", source=where)
        offset = h5_number(g.attrs, "offset_ns", f"{where}: view {name}", required=False, integer=True,
                           low=-2**63, high=2**63 - 1)
        info = ViewInfo(name=name, index=i, split=split, K=K, T_world_cam=T, num_events=num_events,
                        has_events=bool(has_events), offset_ns=offset, moving="poses" in g)
        H, W = self.height, self.width
        if info.moving:
            pt = h5_dataset(g, "poses/t", where, ndim=1, what=f"view {name}: poses/t")
            if pt.shape[0] < 1:
                raise FormatError(f"view {name}: poses/t is empty; {_FIX}", source=where)
            h5_dataset(g, "poses/T_world_cam", where, shape=(pt.shape[0], 4, 4), kinds="iuf",
                       what=f"view {name}: poses/T_world_cam")
        if "frames" in g:
            fr = h5_dataset(g, "frames/frames", where, ndim=3, kinds="f", what=f"view {name}: frames/frames")
            if fr.shape[1:] != (H, W):
                raise FormatError(f"view {name}: frames/frames has shape {fr.shape}, expected (N, {H}, {W}); {_FIX}",
                                  source=where)
            for k in ("t_start", "t_end", "t"):
                h5_dataset(g, f"frames/{k}", where, shape=(fr.shape[0],), what=f"view {name}: frames/{k}")
        if info.has_events:
            if not isinstance(g.get("events"), h5py.Group) or "index" not in g["events"]:
                raise FormatError(f"view {name}: no events/ group with an index", source=where)
            for k in ("t", "x", "y", "p"):
                h5_dataset(g, f"events/{k}", where, shape=(num_events,), what=f"view {name}: events/{k}")
            idx = h5_dataset(g, "events/index", where, shape=(self.n_bins + 1,),
                             what=f"view {name}: events/index")[()].astype(np.int64)
            if idx[0] != 0 or idx[-1] != num_events or np.any(idx[1:] < idx[:-1]):
                raise FormatError(f"view {name}: the time index does not match the {num_events} "
                                  "events; the file is damaged", source=where)
            self._index[name] = idx
        else:
            edges = h5_dataset(g, "dl/edges", where, ndim=1, what=f"view {name}: dl/edges")
            if edges.shape[0] < 2:
                raise FormatError(f"view {name}: dl/edges needs at least 2 times; {_FIX}", source=where)
            h5_dataset(g, "dl/windows", where, shape=(edges.shape[0] - 1, H, W), kinds="f",
                       what=f"view {name}: dl/windows")
        return info

    # ----- lifecycle
    def close(self) -> None:
        f, self._f = getattr(self, "_f", None), None
        if f is not None:
            f.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False

    def _file(self):
        if self._f is None:
            raise InputError(f"{self.path}: training set is closed")
        return self._f

    # ----- metadata
    def _name(self, view) -> str:
        if isinstance(view, (int, np.integer)) and not isinstance(view, bool):
            if not 0 <= int(view) < len(self.views):
                raise InputError(f"{self.path}: view index {view} out of range (0..{len(self.views) - 1})")
            return self.views[int(view)]
        if view not in self._infos:
            raise InputError(f"{self.path}: no view {view!r}; views: {', '.join(self.views)}")
        return view

    def info(self, view) -> ViewInfo:
        return self._infos[self._name(view)]

    @property
    def train_views(self) -> list[str]:
        return [v for v in self.views if self._infos[v].split == "train"]

    @property
    def val_views(self) -> list[str]:
        return [v for v in self.views if self._infos[v].split == "val"]

    def split(self, view) -> str:
        return self.info(view).split

    @property
    def thresholds(self) -> tuple[float, float]:
        return self.c_pos, self.c_neg

    @property
    def time_range(self) -> tuple[int, int]:
        return self.t_start, self.t_end

    @property
    def duration_ns(self) -> int:
        return self.t_end - self.t_start

    def normalized_time(self, t_ns) -> np.ndarray:
        """(t - t_start) / (t_end - t_start) as float64, from int64 differences (0 .. 1)."""
        return (np.asarray(t_ns, np.int64) - self.t_start) / float(self.t_end - self.t_start)

    def K(self, view=None) -> np.ndarray:
        """Intrinsics of a view, or (view=None) the one K shared by all views."""
        if view is not None:
            return self.info(view).K.copy()
        Ks = [self._infos[v].K for v in self.views]
        if any(not np.array_equal(Ks[0], k) for k in Ks[1:]):
            raise InputError(f"{self.path}: views have different intrinsics; ask per view with K(view)")
        return Ks[0].copy()

    def pose(self, view) -> np.ndarray:
        """The view's static T_world_cam (4x4, OpenCV axes)."""
        return self.info(view).T_world_cam.copy()

    def poses(self, view) -> tuple[np.ndarray, np.ndarray] | None:
        """A moving camera's trajectory (t (M,) int64, T_world_cam (M, 4, 4)), or None when static."""
        name = self._name(view)
        if not self._infos[name].moving:
            return None
        with h5_reading(self.path, f"view {name}: poses", _FIX):
            g = self._file()["views"][name]
            M = g["poses/t"].shape[0]
            h5_memory(M * 136, self.path, f"view {name}: {M} poses")
            t, T = g["poses/t"][()].astype(np.int64), g["poses/T_world_cam"][()].astype(np.float64)
        if np.any(t[1:] < t[:-1]):
            raise FormatError(f"view {name}: poses/t is not sorted; {_FIX}", source=str(self.path))
        check_rigid(T, f"{self.path}: view {name}: poses/T_world_cam")
        return t, T

    def num_events(self, view) -> int:
        return self.info(view).num_events

    @property
    def provenance(self) -> dict:
        f = self._file()
        with h5_reading(self.path, "provenance", _FIX):
            if "provenance" not in f:
                return {}
            ds = h5_dataset(f, "provenance", self.path, ndim=0, kinds="OSU", what="provenance")
            raw = ds[()]
            out = json.loads(raw.decode("utf-8") if isinstance(raw, bytes) else raw)
        if not isinstance(out, dict):
            raise FormatError(f"provenance is not a JSON object; {_FIX}", source=str(self.path))
        return out

    def frame_grid(self, view) -> tuple[int, int] | None:
        """(period_ns, one frame time in the common clock) of a view whose camera drew the scene
        only on a grid of frame times and joined them linearly in log (the virtual rig's camera
        twin: convert records it as ``provenance.truth.render_grid``), else None."""
        name = self._name(view)
        record = self.provenance.get("truth") or {}
        grid = record.get("render_grid") or {}
        frame = (grid.get("scene_ns") or {}).get(name)
        origin = (record.get("scene_time_at_origin_ns") or {}).get(name)
        if frame is None or origin is None:
            return None
        period = grid.get("period_ns")
        if isinstance(period, bool) or not isinstance(period, int) or period <= 0 \
                or not all(isinstance(v, int) and not isinstance(v, bool) for v in (frame, origin)):
            raise FormatError(f"view {name}: provenance.truth.render_grid holds period_ns {period!r} and frame "
                              f"time {frame!r} (need integer ns, period > 0); {_FIX}", source=str(self.path))
        return period, frame - origin

    def frames(self, view) -> dict | None:
        """Blurred frames {frames, t_start, t_end, t} in the common clock, or None."""
        name = self._name(view)
        with h5_reading(self.path, f"view {name}: frames", _FIX):
            g = self._file()["views"][name]
            if "frames" not in g:
                return None
            n = g["frames/frames"].shape[0]
            h5_memory(n * (self.width * self.height * 4 + 24), self.path, f"view {name}: {n} frames")
            out = {k: g["frames"][k][()] for k in ("frames", "t_start", "t_end", "t")}
        if not np.all(np.isfinite(out["frames"])):
            raise FormatError(f"view {name}: frames contain NaN or inf; {_FIX}", source=str(self.path))
        for k in ("t_start", "t_end", "t"):
            out[k] = out[k].astype(np.int64)
        return out

    def dl_windows(self, view) -> tuple[np.ndarray, np.ndarray] | None:
        """Pre-binned (edges, windows) of an imported frame-only view, or None."""
        name = self._name(view)
        if self._infos[name].has_events:
            return None
        with h5_reading(self.path, f"view {name}: dl windows", _FIX):
            g = self._file()["views"][name]
            n = g["dl/windows"].shape[0]
            h5_memory(n * (self.width * self.height * 4 + 8), self.path, f"view {name}: {n} dL windows")
            edges, windows = g["dl/edges"][()].astype(np.int64), g["dl/windows"][()]
        if np.any(edges[1:] <= edges[:-1]) or not np.all(np.isfinite(windows)):
            raise FormatError(f"view {name}: dl edges are not increasing or dl windows hold NaN/inf; {_FIX}",
                              source=str(self.path))
        return edges, windows

    # ----- events
    def _require_events(self, name: str) -> None:
        if not self._infos[name].has_events:
            raise InputError(f"{self.path}: view {name} holds pre-binned dL windows only (imported from "
                             "EvDNeRF data_frames without raw events); use log_change / log_change_stack on "
                             "its window edges, see dl_windows()")

    def _bound(self, name: str, t: int) -> int:
        """Number of events of the view with time < t: one index lookup and a binary search in
        the events of one index bin (never a scan)."""
        idx = self._index[name]
        n = int(idx[-1])
        if t <= self.t_start:
            return 0
        if t >= self.t_end:
            return n
        k = (t - self.t_start) // self.index_step_ns
        lo, hi = int(idx[k]), int(idx[k + 1])
        if lo == hi or (t - self.t_start) % self.index_step_ns == 0:
            return lo
        with h5_reading(self.path, f"view {name}: events {lo}..{hi}", _FIX):
            ts = self._file()["views"][name]["events/t"][lo:hi]
        return lo + int(np.searchsorted(ts, t, "left"))

    def index_range(self, view, t0: int | None = None, t1: int | None = None) -> tuple[int, int]:
        """[i0, i1): the positions of the events with t0 <= t < t1 (None: the set's range)."""
        name = self._name(view)
        self._require_events(name)
        t0 = self.t_start if t0 is None else int(t0)
        t1 = self.t_end if t1 is None else int(t1)
        i0 = self._bound(name, t0)
        return i0, max(i0, self._bound(name, t1))

    def _read(self, name: str, i0: int, i1: int) -> np.ndarray:
        h5_memory(2 * (i1 - i0) * EVENT_DTYPE.itemsize, self.path, f"view {name}: {i1 - i0} events")
        out = np.empty(i1 - i0, EVENT_DTYPE)
        if i1 > i0:
            with h5_reading(self.path, f"view {name}: events {i0}..{i1}", _FIX):
                g = self._file()["views"][name]["events"]
                for k in ("t", "x", "y", "p"):
                    out[k] = g[k][i0:i1]
            self._check_block(name, out, i0)
        return out

    def _check_block(self, name: str, ev: np.ndarray, i0: int) -> None:
        """Events as stored must be inside the geometry and the time range, sorted, +-1:
        scaleoffset has no checksum, so a damaged chunk shows up only here."""
        t, p = ev["t"], ev["p"]
        bad = []
        if int(ev["x"].max()) >= self.width or int(ev["y"].max()) >= self.height:
            bad.append(f"pixels outside {self.width}x{self.height}")
        if np.any((p != 1) & (p != -1)):
            bad.append("polarities other than +1/-1")
        if int(t[0]) < self.t_start or int(t[-1]) >= self.t_end:
            bad.append(f"times outside [{self.t_start}, {self.t_end}) ns")
        if np.any(t[1:] < t[:-1]):
            bad.append("times out of order")
        if bad:
            raise FormatError(f"view {name}: events {i0}..{i0 + ev.size} hold {' and '.join(bad)}; {_FIX}",
                              source=str(self.path))

    def events(self, view, t0: int | None = None, t1: int | None = None) -> np.ndarray:
        """Events of the view with t0 <= t < t1 (EVENT_DTYPE; None: the whole range)."""
        name = self._name(view)
        i0, i1 = self.index_range(name, t0, t1)
        return self._read(name, i0, i1)

    def iter_events(self, view, t0: int | None = None, t1: int | None = None, *, block: int | None = None):
        """The events of [t0, t1) in blocks of at most `block` events (default READ_BLOCK;
        bounded memory)."""
        block = READ_BLOCK if block is None else max(1, int(block))
        name = self._name(view)
        i0, i1 = self.index_range(name, t0, t1)
        for a in range(i0, i1, block):
            yield self._read(name, a, min(i1, a + block))

    def _check_window(self, t0, t1):
        t0, t1 = int(t0), int(t1)
        if t1 <= t0:
            raise InputError(f"window [{t0}, {t1}) ns is empty; t1 must be after t0")
        return t0, t1

    def log_change(self, view, t0: int, t1: int) -> np.ndarray:
        """(H, W) float32 dL = C+ N+ - C- N- of the events in [t0, t1) (paper Eq. 5)."""
        return self.log_change_stack(view, np.array(self._check_window(t0, t1), np.int64))[0]

    def log_change_stack(self, view, edges) -> np.ndarray:
        """(K, H, W) float32 dL images of the K windows [edges[k], edges[k+1]), streamed in blocks."""
        name = self._name(view)
        edges = _check_edges(edges)
        if not self._infos[name].has_events:
            return self._dl_from_windows(name, edges)
        counts = self.polarity_count_stack(name, edges)
        return (self.c_pos * counts[..., 0] - self.c_neg * counts[..., 1]).astype(np.float32)

    def polarity_count_stack(self, view, edges) -> np.ndarray:
        """(K, H, W, 2) event counts (positive, negative) of the K windows [edges[k], edges[k+1]);
        views stored as pre-binned dL windows have no counts (InputError)."""
        name = self._name(view)
        edges = _check_edges(edges)
        if not self._infos[name].has_events:
            raise InputError(f"{self.path}: view {name} holds pre-binned dL windows, not events, so "
                             "it has no per-polarity counts (learned thresholds need events)")
        W, H = self.width, self.height
        K, P = edges.size - 1, W * H
        h5_memory(K * P * 2 * (8 if K * P < (1 << 22) else 4), self.path,
                  f"view {name}: polarity counts of {K} windows of {W}x{H}")
        counts = np.zeros((K, H, W, 2), np.int64 if K * P < (1 << 22) else np.int32)
        flat_counts = counts.reshape(-1)
        for ev in self.iter_events(name, int(edges[0]), int(edges[-1])):
            k = np.searchsorted(edges, ev["t"], "right") - 1
            ka, kb = int(k[0]), int(k[-1])
            flat = ((k - ka) * P + ev["y"].astype(np.int64) * W + ev["x"]) * 2 + (ev["p"] < 0)
            part = np.bincount(flat, minlength=(kb - ka + 1) * P * 2)
            flat_counts[ka * P * 2:(kb + 1) * P * 2] += part.astype(counts.dtype, copy=False)
        return counts

    def _dl_from_windows(self, name: str, edges: np.ndarray) -> np.ndarray:
        dl_edges, windows = self.dl_windows(name)
        pos = np.searchsorted(dl_edges, edges)
        if np.any(pos >= dl_edges.size) or not np.array_equal(dl_edges[np.minimum(pos, dl_edges.size - 1)], edges):
            raise InputError(f"{self.path}: view {name} holds pre-binned dL windows only; windows must start "
                             f"and end on its edges ({dl_edges.size} edges, from {int(dl_edges[0])} to "
                             f"{int(dl_edges[-1])} ns)")
        out = np.empty((pos.size - 1,) + windows.shape[1:], np.float32)
        for j in range(pos.size - 1):
            a, b = int(pos[j]), int(pos[j + 1])
            out[j] = windows[a] if b - a == 1 else windows[a:b].sum(0, dtype=np.float64)
        return out

    def event_pixels(self, view, t0: int, t1: int) -> np.ndarray:
        """Sorted flat pixel indices (y * width + x, int64) that have at least one event in
        [t0, t1): the candidates for the trainer's positive rays."""
        t0, t1 = self._check_window(t0, t1)
        name = self._name(view)
        P = self.width * self.height
        if not self._infos[name].has_events:
            return np.flatnonzero(self.log_change(name, t0, t1).reshape(-1) != 0).astype(np.int64)
        hit = np.zeros(P, bool)
        for ev in self.iter_events(name, t0, t1):
            hit[ev["y"].astype(np.int64) * self.width + ev["x"]] = True
        return np.flatnonzero(hit).astype(np.int64)

    def __repr__(self) -> str:
        return (f"TrainingSet({str(self.path)!r}: {len(self.views)} views, {self.width}x{self.height}, "
                f"[{self.t_start}, {self.t_end}) ns)")


def _check_edges(edges) -> np.ndarray:
    edges = np.asarray(edges)
    if edges.ndim != 1 or edges.size < 2 or edges.dtype.kind not in "iu" or np.any(np.diff(edges) <= 0):
        raise InputError("window edges must be a strictly increasing 1-D int64 array of >= 2 times")
    return edges.astype(np.int64)
