"""The EvDNeRF paper's on-disk format (github anish-bhattacharya/EvDNeRF, `load_blender.py`):
export a training set to it, and import their released datasets into ours.

Their folder, per split (``train``, ``val``)::

    transforms_{split}.json   {"camera_angle_x": ..., "frames": [{"file_path", "time",
                              "transform_matrix"}, ...]}: frames view-major (all timesteps of
                              view 0, then view 1, ...), time in [0, 1] (each view runs from
                              0 to exactly 1.0, which is how their loader counts views),
                              transform_matrix = camera-to-world in Blender / OpenGL camera axes
                              (x right, y up, z backward)
    {file_path}.png           a grey image per frame (their loader always reads it)
    data_frames_{split}.npy   (V, T-1, H, W) float32 event frames: window k of view v is
                              dL = C+ N+ - C- N- of the events between timesteps k and k+1
    data_{split}.npy          optional raw events: an object array of V arrays (N, 4)
                              [t, x, y, p] (their loader: np.load(allow_pickle=True).tolist());
                              or data_{split}.pkl with the same list, pickled

Conventions decided here (their code is the reference):

- Poses: ``T_gl = T_cv @ diag(1, -1, -1, 1)`` (flip the camera's y and z axes) on export,
  and the same product back on import (it is its own inverse, exact in floating point).
- Intrinsics: ``camera_angle_x = 2 atan(W / (2 fx))``; their rays put the principal point
  at (W/2, H/2) with one focal length, so on import without our extension K =
  [[f, 0, W/2], [0, f, H/2], [0, 0, 1]], f = W / (2 tan(camera_angle_x / 2)) (or ``focal``).
- Event time column: their trainer slices a view's events with ``t >= time * 1e9``, i.e.
  it reads the column as normalised time in ns (1e9 = the end of the sequence). Export
  therefore writes ``event_time="normalized"`` (default): ``floor((t - t_start) * 1e9 / D)``
  with D = t_end - t_start. For D <= 1 s this is exactly invertible
  (``t = t_start + ceil(c * D / 1e9)``, used on import); for longer sets it loses
  resolution (D / 1e9 ns per step, the export logs it) and ``event_time="ns"`` (plain ns
  since t_start; exact, but their trainer then assumes a 1 s sequence) is the lossless
  choice. Polarity is written +1 / -1; on import any p > 0 is +1 and anything else -1
  (their files use both +1/-1 and 1/0).
- Our extension: each transforms json also carries ``"evdnerf_ros": {t_start_ns, t_end_ns,
  event_time, width, height, K, c_pos, c_neg, downsample, views: [{name, num_frames,
  moving}]}``, which makes export -> import exact (events, poses, intrinsics, split, names,
  time range). Their loader ignores unknown keys.
- Images: the PNGs are the view's blurred frame whose exposure holds the timestep (linear
  intensity clipped to [0, 1], x 255), or mid-grey when the set has no frames (EvDNeRF's
  event loss never reads them).
- Import prefers raw events; a split that has only ``data_frames`` is stored as pre-binned
  dL windows (``views/<name>/dl/{edges, windows}`` in the .h5, edges = the timesteps in
  ns); their ``(V, T, H, W)`` variant (one window per timestep) keeps the first T-1.
  Thresholds are not in their files: import takes ``c_pos`` / ``c_neg`` (default: our
  extension's, else the paper's 0.2).
- Moving cameras export one pose per timestep (the trajectory's latest pose at or before
  it); importing gives that sampled trajectory back.

Memory: data_frames are streamed per view; the raw event arrays are built in memory one view
at a time (their format is one pickled (N, 4) array per view, 32 bytes per event as int64):
``events=False`` leaves them out for very large sets.

Security: their raw events are pickles (``allow_pickle``); unpickling runs code from the
file, so import only datasets you trust.
"""

from __future__ import annotations

import json
import math
import pickle
import struct
from pathlib import Path

import numpy as np

from ..atomic import atomic_output
from ..errors import FormatError, InputError
from ..events.slicing import window_edges
from ..events.types import EVENT_DTYPE
from ..geometry.poses import check_rigid
from ..limits import check_number
from .guard import read_text, writing
from .npz import check_npy_file
from .trainingset import C_MAX, T_LIMIT, TrainingSet, ViewData, write_training_set

EXT_KEY = "evdnerf_ros"
EXT_VERSION = 1
EVENT_TIMES = ("normalized", "ns")
SPLITS = ("train", "val")
NS = 1_000_000_000
#: x diag(1, -1, -1, 1) on the right: OpenCV camera axes <-> Blender / OpenGL camera axes.
AXES_FLIP = np.diag([1.0, -1.0, -1.0, 1.0])
#: Imported rotations off orthonormal by more than this are refused; smaller errors (float32
#: files) are re-orthonormalised by SVD.
IMPORT_POSE_TOL = 1e-3
DEFAULT_THRESHOLD = 0.2


def cv_to_gl(T_world_cam: np.ndarray) -> np.ndarray:
    """OpenCV camera-to-world (x right, y down, z forward) -> Blender / OpenGL (y up, z back)."""
    return np.asarray(T_world_cam, np.float64) @ AXES_FLIP


def gl_to_cv(T_gl: np.ndarray) -> np.ndarray:
    return np.asarray(T_gl, np.float64) @ AXES_FLIP


# --------------------------------------------------------------------------- event time column


def to_file_time(t: np.ndarray, t_start: int, t_end: int, mode: str) -> np.ndarray:
    """int64 event times -> their time column (see the module doc)."""
    dt = np.asarray(t, np.int64) - np.int64(t_start)
    D = int(t_end) - int(t_start)
    if mode == "ns" or D == NS:
        return dt
    if D < NS:
        return (dt * NS) // D                       # exact: dt < D < 1e9, product < 1e18
    return np.minimum(np.floor(dt * (NS / D)).astype(np.int64), NS - 1)


def from_file_time(c: np.ndarray, t_start: int, t_end: int, mode: str) -> np.ndarray:
    c = np.asarray(c, np.int64)
    D = int(t_end) - int(t_start)
    if mode == "ns" or D == NS:
        return np.int64(t_start) + c
    if D < NS:
        return np.int64(t_start) + (c * D + (NS - 1)) // NS   # ceil: the exact inverse
    return np.int64(t_start) + np.floor(c * (D / NS)).astype(np.int64)


# --------------------------------------------------------------------------- export


def _open_source(source):
    """(TrainingSet, cleanup) for a TrainingSet or a training-set .h5 path. A session folder
    is refused: converting sessions is the session layer's job (io never imports it)."""
    if isinstance(source, TrainingSet):
        return source, None
    p = Path(source)
    if p.is_dir() and (p / "session.yaml").is_file():
        raise InputError(f"{p}: is a capture session, not a training set; export it with "
                         "`evdnerf convert SESSION -o OUT --format evdnerf` (or "
                         "evdnerf_ros.session.convert.run_convert(..., fmt='evdnerf'))")
    ts = TrainingSet(p)
    return ts, ts.close


def _pose_at(ts: TrainingSet, view: str, t: int) -> np.ndarray:
    tr = ts.poses(view)
    if tr is None:
        return ts.pose(view)
    pt, pT = tr
    i = int(np.clip(np.searchsorted(pt, t, "right") - 1, 0, pt.size - 1))
    return pT[i]


def _grey_images(ts: TrainingSet, view: str, edges: np.ndarray) -> list[np.ndarray]:
    fr = ts.frames(view)
    if fr is None:
        return [np.full((ts.height, ts.width), 128, np.uint8)] * edges.size
    out = []
    for t in edges:
        inside = np.flatnonzero((fr["t_start"] <= t) & (t < fr["t_end"]))
        i = int(inside[0]) if inside.size else int(np.argmin(np.abs(fr["t"] - t)))
        out.append(np.round(np.clip(fr["frames"][i], 0.0, 1.0) * 255).astype(np.uint8))
    return out


def _save_png_grey(path: Path, img: np.ndarray) -> None:
    from PIL import Image

    Image.fromarray(np.ascontiguousarray(img, np.uint8)).save(path)   # 2-D uint8: mode "L"


def export_evdnerf(source, out_dir, *, n_windows: int = 32, event_time: str = "normalized",
                   events: bool = True, images: bool = True, overwrite: bool = False,
                   log=print) -> dict:
    """Write the paper's format for a TrainingSet or a training-set .h5 (a session is
    converted to one first by :func:`evdnerf_ros.session.convert.run_convert`, which then
    calls this). `n_windows` windows of equal length span the set's time range:
    T = n_windows + 1 timesteps per view. Returns a summary; the folder appears atomically."""
    if isinstance(n_windows, bool) or not isinstance(n_windows, (int, np.integer)) or n_windows < 1:
        raise InputError(f"export: n_windows must be an integer >= 1, got {n_windows!r}")
    if event_time not in EVENT_TIMES:
        raise InputError(f"export: event_time {event_time!r} is not one of {list(EVENT_TIMES)}")
    ts, cleanup = _open_source(source)
    try:
        return _export(ts, Path(out_dir), int(n_windows), event_time, events, images, overwrite, log)
    finally:
        if cleanup is not None:
            cleanup()


def _export(ts: TrainingSet, out_dir: Path, n: int, event_time: str, events: bool, images: bool,
            overwrite: bool, log) -> dict:
    D = ts.t_end - ts.t_start
    if D < n:
        raise InputError(f"export: the set's {D} ns cannot be split into {n} windows")
    if event_time == "normalized" and D > NS and events:
        log(f"export: the set lasts {D} ns > 1 s: the normalised event time column has {D / NS:.3g} ns "
            "steps (use event_time='ns' for exact times)")
    edges = window_edges(ts.t_start, ts.t_end, n)
    W, H = ts.width, ts.height
    summary = {"out": str(out_dir), "n_windows": n, "splits": {}}
    with atomic_output(out_dir, overwrite=overwrite, directory=True) as tmp, writing(out_dir):
        tmp.mkdir()
        for split in SPLITS:
            views = ts.train_views if split == "train" else ts.val_views
            if not views:
                log(f"export: no {split} views; {split} files not written")
                continue
            K0 = ts.K(views[0])
            frames, ext_views = [], []
            stack = np.empty((len(views), n, H, W), np.float32)
            raw = np.empty(len(views), dtype=object)
            have_raw = events and all(ts.info(v).has_events for v in views)
            if images:
                (tmp / split).mkdir()
            for vi, view in enumerate(views):
                for k in range(n + 1):
                    T_gl = cv_to_gl(_pose_at(ts, view, int(edges[k])))
                    frames.append({"file_path": f"./{split}/r_{vi:03d}_{k:03d}", "time": k / n,
                                   "transform_matrix": T_gl.tolist()})
                stack[vi] = ts.log_change_stack(view, edges)
                if have_raw:
                    ev = ts.events(view)
                    arr = np.empty((ev.size, 4), np.int64)
                    arr[:, 0] = to_file_time(ev["t"], ts.t_start, ts.t_end, event_time)
                    arr[:, 1], arr[:, 2], arr[:, 3] = ev["x"], ev["y"], ev["p"]
                    raw[vi] = arr
                if images:
                    for k, img in enumerate(_grey_images(ts, view, edges)):
                        _save_png_grey(tmp / split / f"r_{vi:03d}_{k:03d}.png", img)
                info = ts.info(view)
                ext_views.append({"name": view, "num_frames": n + 1, "moving": info.moving,
                                  "K": info.K.tolist(), "num_events": info.num_events})
            meta = {
                "camera_angle_x": 2.0 * math.atan(W / (2.0 * float(K0[0, 0]))),
                "frames": frames,
                EXT_KEY: {"version": EXT_VERSION, "t_start_ns": ts.t_start, "t_end_ns": ts.t_end,
                          "event_time": event_time, "n_windows": n, "width": W, "height": H,
                          "K": K0.tolist(), "c_pos": ts.c_pos, "c_neg": ts.c_neg, "downsample": ts.downsample,
                          "views": ext_views, "source": str(ts.path)},
            }
            (tmp / f"transforms_{split}.json").write_text(json.dumps(meta, indent=1))
            np.save(tmp / f"data_frames_{split}.npy", stack)
            if have_raw:
                np.save(tmp / f"data_{split}.npy", raw, allow_pickle=True)
            elif events:
                log(f"export: {split}: some views carry no raw events; data_{split}.npy not written")
            summary["splits"][split] = {"views": list(views), "frames_shape": list(stack.shape),
                                        "raw_events": bool(have_raw)}
    parts = ", ".join(f"{k}: {len(v['views'])} views" for k, v in summary["splits"].items())
    log(f"export: {out_dir} ({parts}, {n} windows)")
    return summary


# --------------------------------------------------------------------------- import


def _read_json(path: Path) -> dict:
    text = read_text(path, what="transforms json")
    try:
        meta = json.loads(text)
    except (ValueError, RecursionError) as exc:
        raise FormatError(f"not readable JSON ({type(exc).__name__}: {exc})", source=str(path)) from None
    if not isinstance(meta, dict) or not isinstance(meta.get("frames"), list) or not meta["frames"]:
        raise FormatError("needs a non-empty `frames` list", source=str(path))
    for i, fr in enumerate(meta["frames"]):
        if not isinstance(fr, dict):
            raise FormatError(f"frames[{i}] must be an object with file_path, time, transform_matrix",
                              source=str(path))
        t = fr.get("time")
        if isinstance(t, bool) or not isinstance(t, (int, float)) or not 0.0 <= t <= 1.0:
            raise FormatError(f"frames[{i}].time must be a number in [0, 1], got {t!r}", source=str(path))
    ext = meta.get(EXT_KEY)
    if ext is not None:
        _check_extension(ext, str(path), len(meta["frames"]))
    return meta


def _check_extension(ext, where: str, n_frames: int) -> None:
    """Our extension's fields (see the module doc), checked before any is used."""
    if not isinstance(ext, dict):
        raise FormatError(f"`{EXT_KEY}` must be an object", source=where)
    name = f"{where}: {EXT_KEY}"
    for k in ("t_start_ns", "t_end_ns"):
        check_number(ext.get(k), f"{name}.{k}", integer=True, low=-T_LIMIT, high=T_LIMIT)
    if ext["t_end_ns"] <= ext["t_start_ns"]:
        raise FormatError(f"{EXT_KEY}.t_end_ns must be after t_start_ns", source=where)
    for k in ("width", "height"):
        check_number(ext.get(k), f"{name}.{k}", integer=True, low=1, high=65535)
    for k in ("c_pos", "c_neg"):
        if k in ext:
            check_number(ext[k], f"{name}.{k}", low=0, low_open=True, high=C_MAX)
    if "downsample" in ext:
        check_number(ext["downsample"], f"{name}.downsample", integer=True, low=1, high=64)
    _check_K_list(ext.get("K"), f"{name}.K")
    views = ext.get("views")
    if views is not None:
        if not isinstance(views, list):
            raise FormatError(f"{EXT_KEY}.views must be a list", source=where)
        for i, v in enumerate(views):
            if not isinstance(v, dict) or not isinstance(v.get("name"), str) or not v["name"]:
                raise FormatError(f"{EXT_KEY}.views[{i}] needs a `name`", source=where)
            check_number(v.get("num_frames"), f"{name}.views[{i}].num_frames", integer=True, low=2,
                         high=n_frames)
            if "K" in v:
                _check_K_list(v["K"], f"{name}.views[{i}].K")


def _check_K_list(K, name: str) -> None:
    try:
        ok = np.asarray(K, np.float64).shape == (3, 3)
    except (TypeError, ValueError, OverflowError):
        ok = False
    if not ok:
        raise InputError(f"{name}: must be a 3x3 list of numbers")


def _pose_cv(M, where: str) -> np.ndarray:
    try:
        T = np.asarray(M, np.float64)
    except (TypeError, ValueError, OverflowError):
        raise FormatError("transform_matrix is not numeric", source=where) from None
    if T.shape == (3, 4):
        T = np.vstack([T, [0.0, 0.0, 0.0, 1.0]])
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise FormatError(f"transform_matrix must be a finite 4x4 (or 3x4) matrix, got shape {T.shape}",
                          source=where)
    T = gl_to_cv(T)
    if np.abs(T[3] - [0, 0, 0, 1]).max() <= IMPORT_POSE_TOL:
        T[3] = [0.0, 0.0, 0.0, 1.0]                  # float32 files: snap the last row, then check
    try:
        check_rigid(T, "transform_matrix", tol=IMPORT_POSE_TOL)
    except InputError as exc:
        raise FormatError(str(exc), source=where) from None
    R = T[:3, :3]
    if np.abs(R.T @ R - np.eye(3)).max() > 1e-9:   # re-orthonormalise float32 rounding
        u, _, vt = np.linalg.svd(R)
        T[:3, :3] = u @ vt
    return T


def _group_views(frames: list, ext: dict | None, where: str) -> list[list[int]]:
    if ext and isinstance(ext.get("views"), list):
        counts = [int(v["num_frames"]) for v in ext["views"]]
        if sum(counts) != len(frames):
            raise FormatError(f"the extension lists {sum(counts)} frames but there are {len(frames)}", source=where)
        out, a = [], 0
        for c in counts:
            out.append(list(range(a, a + c)))
            a += c
        return out
    groups, cur, prev = [], [], None
    for i, fr in enumerate(frames):
        t = float(fr.get("time", np.nan))
        if not math.isfinite(t):
            raise FormatError(f"frame {i} has no finite `time`", source=where)
        if prev is not None and t < prev:
            groups.append(cur)
            cur = []
        cur.append(i)
        prev = t
    groups.append(cur)
    return groups


#: What np.load / pickle raise on a damaged file (a pickle can raise nearly anything: their
#: raw events are pickles, see the module doc).
_LOAD_ERRORS = (OSError, ValueError, TypeError, EOFError, pickle.UnpicklingError, AttributeError, ImportError,
                IndexError, KeyError, UnicodeError, OverflowError, RecursionError, MemoryError, struct.error)


def _load_raw_events(src: Path, split: str):
    npy, pkl = src / f"data_{split}.npy", src / f"data_{split}.pkl"
    if npy.is_file():
        check_npy_file(npy)
        try:
            obj = np.load(npy, allow_pickle=True)
        except _LOAD_ERRORS as exc:
            raise FormatError(f"unreadable ({type(exc).__name__}: {exc})", source=str(npy)) from None
        if obj.ndim == 0:
            raise FormatError("holds a single value, expected one (N, 4) event array per view", source=str(npy))
        return (list(obj) if obj.dtype == object else [obj[i] for i in range(obj.shape[0])]), npy
    if pkl.is_file():
        try:
            with open(pkl, "rb") as f:
                obj = pickle.load(f)  # noqa: S301 - their format; see the module doc
            obj = list(obj)
        except _LOAD_ERRORS as exc:
            raise FormatError(f"unreadable ({type(exc).__name__}: {exc})", source=str(pkl)) from None
        return obj, pkl
    return None, None


def import_evdnerf(src_dir, out_h5, *, c_pos: float | None = None, c_neg: float | None = None,
                   overwrite: bool = False, log=print) -> dict:
    """Read an EvDNeRF-format folder into a training-set .h5 (atomically); returns a summary."""
    src = Path(src_dir)
    if not src.is_dir():
        raise InputError(f"{src}: not a folder; expected an EvDNeRF dataset folder with transforms_train.json")
    metas = {s: _read_json(src / f"transforms_{s}.json") for s in SPLITS if (src / f"transforms_{s}.json").is_file()}
    if not metas:
        raise InputError(f"{src}: no transforms_train.json or transforms_val.json; not an EvDNeRF dataset")
    ext0 = next((m[EXT_KEY] for m in metas.values() if isinstance(m.get(EXT_KEY), dict)), None)
    if ext0 is not None:
        t_start, t_end = int(ext0["t_start_ns"]), int(ext0["t_end_ns"])
        mode = str(ext0.get("event_time", "normalized"))
        if mode not in EVENT_TIMES:
            raise FormatError(f"unknown event_time {mode!r} in the {EXT_KEY} extension", source=str(src))
    else:
        t_start, t_end, mode = 0, NS, "normalized"
    D = t_end - t_start
    thresholds_source = "given" if c_pos is not None else ("extension" if ext0 else "paper default 0.2")
    c_pos = float(c_pos if c_pos is not None else (ext0 or {}).get("c_pos", DEFAULT_THRESHOLD))
    c_neg = float(c_neg if c_neg is not None else (ext0 or {}).get("c_neg", DEFAULT_THRESHOLD))

    views: list[ViewData] = []
    size = None
    summary = {"out": str(out_h5), "views": {}, "source": str(src)}
    for split, meta in metas.items():
        where = str(src / f"transforms_{split}.json")
        ext = meta.get(EXT_KEY) if isinstance(meta.get(EXT_KEY), dict) else None
        frames = meta["frames"]
        groups = _group_views(frames, ext, where)
        raw, raw_path = _load_raw_events(src, split)
        dframes = None
        if raw is None:
            dpath = src / f"data_frames_{split}.npy"
            if not dpath.is_file():
                raise InputError(f"{src}: split {split} has neither raw events (data_{split}.npy / .pkl) nor event "
                                 f"frames (data_frames_{split}.npy); nothing to import")
            dframes = _load_frames_npy(dpath)
            if dframes.ndim != 4 or dframes.shape[0] != len(groups):
                raise FormatError(f"shape {dframes.shape} does not match {len(groups)} views (V, T-1, H, W)",
                                  source=str(dpath))
        elif len(raw) != len(groups):
            raise FormatError(f"holds {len(raw)} views but transforms_{split}.json has {len(groups)}",
                              source=str(raw_path))
        # image size
        if ext is not None:
            hw = (int(ext["height"]), int(ext["width"]))
        elif dframes is not None:
            hw = tuple(int(v) for v in dframes.shape[2:])
        else:
            dpath = src / f"data_frames_{split}.npy"
            if dpath.is_file():
                hw = tuple(int(v) for v in _load_frames_npy(dpath).shape[2:])
                if len(hw) != 2:
                    raise FormatError("expected (V, T-1, H, W) event frames", source=str(dpath))
            else:
                from PIL import Image

                png = src / (str(frames[0]["file_path"]) + ".png")
                try:
                    with Image.open(png) as im:
                        hw = (im.height, im.width)
                except OSError:
                    raise InputError(f"{src}: cannot tell the image size (no extension, no data_frames, no "
                                     f"readable {png})") from None
        if size is None:
            size = hw
        elif size != hw:
            raise InputError(f"{src}: split {split} is {hw[1]}x{hw[0]} but the other split is {size[1]}x{size[0]}; "
                             "all views must share one resolution")
        H, W = size
        # intrinsics
        if ext is not None:
            K_default = np.asarray(ext["K"], np.float64)
        else:
            focal, ang = meta.get("focal"), meta.get("camera_angle_x", np.nan)
            if isinstance(focal, (int, float)) and not isinstance(focal, bool) and 0 < focal < 1e12:
                f = float(focal)
            else:
                ang = float(ang) if isinstance(ang, (int, float)) and not isinstance(ang, bool) else np.nan
                if not (math.isfinite(ang) and 0 < ang < math.pi):
                    raise FormatError("camera_angle_x must be an angle in (0, pi) radians", source=where)
                f = 0.5 * W / math.tan(0.5 * ang)
            K_default = np.array([[f, 0.0, W / 2.0], [0.0, f, H / 2.0], [0.0, 0.0, 1.0]])
        for vi, idxs in enumerate(groups):
            ev_ext = (ext or {}).get("views", [None] * len(groups))[vi] if ext else None
            name = ev_ext["name"] if ev_ext else (f"view_{vi:02d}" if split == "train" else f"val_{vi:02d}")
            K = np.asarray(ev_ext["K"], np.float64) if ev_ext and "K" in ev_ext else K_default
            times = np.array([float(frames[i]["time"]) for i in idxs])
            t_ns = t_start + np.round(times * D).astype(np.int64)
            Ts = np.stack([_pose_cv(frames[i].get("transform_matrix"), f"{where}: frame {i}") for i in idxs])
            moving = bool(np.abs(Ts - Ts[0]).max() > 1e-9)
            vd = ViewData(name=name, split=split, K=K, T_world_cam=Ts[0],
                          poses_t=t_ns if moving else None, poses_T=Ts if moving else None,
                          attrs={"source": "evdnerf-import"})
            if raw is not None:
                vd.events, dropped = _events_from_array(raw[vi], t_start, t_end, mode, W, H, f"{raw_path}: view {vi}")
                if dropped:
                    log(f"import: {name}: {dropped} events outside [{t_start}, {t_end}) ns dropped")
            else:
                k_needed = len(idxs) - 1
                if dframes.shape[1] not in (k_needed, k_needed + 1):
                    raise FormatError(f"view {vi} has {dframes.shape[1]} event frames for {len(idxs)} timesteps "
                                      f"(expected {k_needed})", source=str(src / f'data_frames_{split}.npy'))
                if np.any(np.diff(t_ns) <= 0):
                    raise FormatError(f"view {vi}: frame times are not strictly increasing", source=where)
                vd.dl_edges = t_ns
                vd.dl_windows = np.asarray(dframes[vi, :k_needed], np.float32)
            views.append(vd)
            summary["views"][name] = {"split": split, "events": None if vd.events is None else int(vd.events.size),
                                      "dl_windows": None if vd.dl_windows is None else int(vd.dl_windows.shape[0])}
    names = [v.name for v in views]
    if len(set(names)) != len(names):
        raise InputError(f"{src}: duplicate view names {names}; view names must be unique")
    provenance = {"software": "evdnerf_ros", "command": "import-evdnerf", "source_dir": str(src.resolve()),
                  "event_time": mode, "extension": ext0 is not None,
                  "thresholds_source": thresholds_source}
    from .. import __version__

    provenance["software_version"] = __version__
    write_training_set(out_h5, views, width=W, height=H, c_pos=c_pos, c_neg=c_neg, t_start=t_start, t_end=t_end,
                       downsample=int((ext0 or {}).get("downsample", 1)), provenance=provenance, overwrite=overwrite)
    log(f"import: {len(views)} views from {src} -> {out_h5}")
    return summary


def _events_from_array(arr, t_start: int, t_end: int, mode: str, W: int, H: int, where: str):
    try:
        a = np.asarray(arr)
    except (TypeError, ValueError):
        raise FormatError("events are not a numeric array", source=where) from None
    if a.ndim != 2 or a.shape[1] != 4 or a.dtype.kind not in "iuf":
        raise FormatError(f"events must be an (N, 4) numeric array [t, x, y, p], got shape {a.shape} "
                          f"dtype {a.dtype}", source=where)
    if a.dtype.kind == "f" and not np.all(np.isfinite(a)):
        raise FormatError("events contain NaN or inf", source=where)
    # times outside the file's range [0, time of t_end - 1] lie outside the set: drop them before
    # converting, so that garbage values cannot overflow the int64 arithmetic
    hi = int(to_file_time(np.array([t_end - 1], np.int64), t_start, t_end, mode)[0])
    col = np.round(a[:, 0]) if a.dtype.kind == "f" else a[:, 0]
    inside = (col >= 0) & (col <= hi)
    outside = int(a.shape[0] - np.count_nonzero(inside))
    if outside:
        a, col = a[inside], col[inside]
    c = col.astype(np.int64)
    x, y = a[:, 1], a[:, 2]
    if a.size and (x.min() < 0 or y.min() < 0 or x.max() >= W or y.max() >= H
                   or (a.dtype.kind == "f" and (np.any(x != np.round(x)) or np.any(y != np.round(y))))):
        raise FormatError(f"event coordinates outside the {W}x{H} image (or not integers)", source=where)
    ev = np.empty(a.shape[0], EVENT_DTYPE)
    ev["t"] = from_file_time(c, t_start, t_end, mode)
    ev["x"], ev["y"] = x.astype(np.uint16), y.astype(np.uint16)
    ev["p"] = np.where(a[:, 3] > 0, 1, -1)
    if np.any(ev["t"][1:] < ev["t"][:-1]):
        ev = ev[np.argsort(ev["t"], kind="stable")]
    keep = (ev["t"] >= t_start) & (ev["t"] < t_end)
    dropped = int(ev.size - np.count_nonzero(keep))
    return (ev[keep] if dropped else ev), dropped + outside


def _load_frames_npy(path: Path) -> np.ndarray:
    """Their (V, T-1, H, W) event frames, memory-mapped (a header larger than the file is refused)."""
    check_npy_file(path, loads=False)
    try:
        arr = np.load(path, mmap_mode="r")
    except _LOAD_ERRORS as exc:
        raise FormatError(f"unreadable ({type(exc).__name__}: {exc})", source=str(path)) from None
    if arr.dtype.kind not in "iuf":
        raise FormatError(f"event frames have dtype {arr.dtype}, expected float32", source=str(path))
    return arr


def run_import_evdnerf(src_dir, out_h5, *, c_pos: float | None = None, c_neg: float | None = None,
                       overwrite: bool = False, log=print) -> dict:
    """`evdnerf import-evdnerf DIR -o TRAIN.h5 [--c-pos C --c-neg C]`."""
    return import_evdnerf(src_dir, out_h5, c_pos=c_pos, c_neg=c_neg, overwrite=overwrite, log=log)
