"""`evdnerf calibrate`: intrinsics and view poses from event recordings of a ChArUco board.

Inputs are bags or event files (anything :func:`evdnerf_ros.io.event_files.read_event_file`
reads) or session folders (every view's bag). Steps: board images from events
(:mod:`.images`), ChArUco corners (:mod:`.detect`), blinks at one pose merged into one view,
``cv2.calibrateCamera`` (:mod:`.intrinsics`), and with ``view_poses`` a session whose every
view recorded the board at the rig's origin: each view's ``T_world_cam`` by solvePnP
(:mod:`.extrinsics`). The calibration YAML is written atomically::

    format: evdnerf-calibration
    format_version: 1
    software_version: ...
    board: {squares_x, squares_y, square_m, marker_m, dictionary}
    camera: {width, height, K, distortion_model: plumb_bob, D, fitted_distortion, rms_px,
             views, corners}
    sources: [{path, images, detected, too_few_corners, views, bursts?, mixed?}]
    frames: [{source, t_start_ns, t_end_ns, images, corners, rms_px}]     (views used)
    placement: centre-up | board          (where the board lay for the view poses)
    views: [{name, T_world_cam, corners, rms_px}]                        (with view_poses)

``write_session`` puts K, D and the view poses into that session's session.yaml through the
session layout's own writer (checked by its schema, replaced atomically).
"""

from __future__ import annotations

import copy
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from .. import __version__
from ..atomic import atomic_output, check_output
from ..errors import InputError
from ..options import option
from .board import DEFAULT_BOARD, DICTIONARIES, BoardSpec, load_board
from .detect import CornerDetector, Detection, check_detections, merge_same_pose
from .extrinsics import PLACEMENTS, view_pose
from .images import blink_images, window_images
from .intrinsics import DISTORTION_MODELS, Intrinsics, calibrate_intrinsics

CALIB_FORMAT = "evdnerf-calibration"
CALIB_FORMAT_VERSION = 1


@dataclass(frozen=True)
class CalibrationOptions:
    style: str = option("blink", "how the board was recorded: blink (a blinking board, held "
                                 "still at each pose) or window (a moving board: edge images)",
                        choices=("blink", "window"))
    polarity: str = option("both", "blink images from blink-on (on), blink-off (off) or both",
                           choices=("on", "off", "both"))
    bin_ns: int = option(1_000_000, "time bin for finding blink bursts", duration=True,
                         low=1_000, high=10**9, flag="--bin")
    gap_ns: int = option(2_000_000, "largest quiet gap inside one blink burst", duration=True,
                         low=0, high=10**9, flag="--gap")
    window_ns: int = option(10_000_000, "window of an edge image (style window)", duration=True,
                            low=1_000, high=10**10, flag="--window")
    min_corners: int = option(8, "fewest ChArUco corners for an image to be used", low=4,
                              high=10_000)
    min_views: int = option(5, "fewest board views (poses) to calibrate from", low=3,
                            high=100_000)
    same_pose_px: float = option(1.0, "consecutive images whose corners moved less than this "
                                      "(median, px) are one pose: merged", low=0, high=100)
    distortion: str = option("plumb_bob", "distortion fitted: plumb_bob (k1 k2 p1 p2 k3), "
                                          "radial (k1 k2) or none", choices=DISTORTION_MODELS)
    placement: str = option("centre-up", "where the board lay for view poses: centre-up (face "
                                         "up, centred on the rig origin, world z up) or board "
                                         "(world = board frame)", choices=PLACEMENTS)
    squares_x: int = option(DEFAULT_BOARD.squares_x, "board squares along x", low=3, high=100)
    squares_y: int = option(DEFAULT_BOARD.squares_y, "board squares along y", low=3, high=100)
    square_m: float = option(DEFAULT_BOARD.square_m, "board square side, metres (as printed)",
                             low=0, low_open=True, high=10)
    marker_m: float = option(DEFAULT_BOARD.marker_m, "board marker side, metres", low=0,
                             low_open=True, high=10)
    dictionary: str = option(DEFAULT_BOARD.dictionary, "ArUco dictionary of the board",
                             choices=DICTIONARIES)

    def board(self) -> BoardSpec:
        return BoardSpec(self.squares_x, self.squares_y, self.square_m, self.marker_m,
                         self.dictionary)


@dataclass
class Recording:
    name: str
    events: np.ndarray
    width: int
    height: int
    view: str | None = None     # the session view it is, if any


def read_recordings(inputs) -> list[Recording]:
    """Every input as event recordings: a session folder gives one per view."""
    from ..io.event_files import read_event_file
    from ..session.layout import load_session, session_yaml_path

    out = []
    for path in map(Path, inputs):
        if path.is_dir() and session_yaml_path(path).is_file():
            session = load_session(path)
            for v in session.views:
                f = read_event_file(v.bag)
                out.append(Recording(f"{path}:{v.name}", f.events, int(f.width), int(f.height),
                                     v.name))
            continue
        f = read_event_file(path)
        out.append(Recording(str(path), f.events, f.width, f.height))
    return out


def board_detections(rec: Recording, board: BoardSpec, options: CalibrationOptions,
                     detector: CornerDetector | None = None) -> tuple[list[Detection], dict]:
    """The board views of one recording and the counts of what was kept / dropped."""
    ev = rec.events
    if ev.size and np.any(np.diff(ev["t"]) < 0):
        ev = ev[np.argsort(ev["t"], kind="stable")]
    if options.style == "blink":
        images, counts = blink_images(ev, rec.width, rec.height, bin_ns=options.bin_ns,
                                      gap_ns=options.gap_ns, polarity=options.polarity,
                                      source=rec.name)
    else:
        images, counts = window_images(ev, rec.width, rec.height, window_ns=options.window_ns,
                                       source=rec.name)
    detector = detector or CornerDetector(board)
    dets, dcounts = detector.detect_images(images, min_corners=options.min_corners)
    views = merge_same_pose(dets, options.same_pose_px)
    return views, {**counts, **dcounts, "views": len(views)}


def _size(recs: list[Recording], where: str) -> tuple[int, int]:
    sizes = {(r.width, r.height) for r in recs}
    if len(sizes) != 1:
        raise InputError(f"{where}: the recordings come from sensors of different sizes "
                         f"({', '.join(f'{w}x{h}' for w, h in sorted(sizes))}); calibrate one "
                         "camera at a time")
    return sizes.pop()


def load_intrinsics(path) -> Intrinsics:
    """K and D of a calibration YAML this command wrote."""
    from ..yamlcheck import load_yaml

    data = load_yaml(path, what="calibration file")
    try:
        if data.get("format") != CALIB_FORMAT:
            raise KeyError("format")
        cam = data["camera"]
        K = np.asarray(cam["K"], np.float64).reshape(3, 3)
        D = np.asarray(cam["D"], np.float64).ravel()
        return Intrinsics(int(cam["width"]), int(cam["height"]), K, D,
                          float(cam.get("rms_px", float("nan"))), [], int(cam.get("views", 0)),
                          int(cam.get("corners", 0)), str(cam.get("fitted_distortion", "")))
    except (KeyError, TypeError, ValueError, AttributeError):
        raise InputError(f"{path}: not a calibration file written by `evdnerf calibrate` "
                         f"(format {CALIB_FORMAT!r} with camera.K, camera.D, width, height)"
                         ) from None


def run_calibration(inputs, output, options: CalibrationOptions | None = None, *,
                    board: BoardSpec | None = None, intrinsics=None, view_poses=None,
                    write_session: bool = False, overwrite: bool = False, log=print) -> dict:
    """Calibrate (see the module doc); returns the calibration document written to `output`.

    `inputs`: board recordings for the intrinsics (may be empty when `intrinsics`, a
    calibration YAML, is given, or when `view_poses` is: then its views are used).
    `view_poses`: a session folder whose every view saw the board at the rig's origin."""
    options = options or CalibrationOptions()
    board = board or options.board()
    output = check_output(Path(output), overwrite=overwrite)
    log = log or (lambda *a, **k: None)
    inputs = list(inputs)
    if not inputs and intrinsics is None and view_poses is None:
        raise InputError("calibrate: nothing to calibrate from; give board recordings (bags, "
                         "event files or a session folder)")
    if write_session and view_poses is None:
        raise InputError("calibrate: --write-session writes into the session of --view-poses; "
                         "give --view-poses SESSION")
    detector = CornerDetector(board)
    doc = {"format": CALIB_FORMAT, "format_version": CALIB_FORMAT_VERSION,
           "software_version": __version__, "board": board.record()}
    sources, frames = [], []

    pose_recs = read_recordings([view_poses]) if view_poses is not None else []
    pose_views = []
    for rec in pose_recs:
        views, counts = board_detections(rec, board, options, detector)
        pose_views.append(views)
        sources.append({"path": rec.name, **counts})

    if intrinsics is not None:
        intr = load_intrinsics(intrinsics)
        log(f"intrinsics from {intrinsics}")
    else:
        recs = read_recordings(inputs) if inputs else pose_recs
        where = ", ".join(str(p) for p in (inputs or [view_poses]))
        size = _size(recs, where)
        all_views: list[Detection] = []
        total = {"images": 0, "too_few_corners": 0}
        for k, rec in enumerate(recs):
            if inputs:
                views, counts = board_detections(rec, board, options, detector)
                sources.append({"path": rec.name, **counts})
            else:
                views, counts = pose_views[k], sources[k]
            total["images"] += counts["images"]
            total["too_few_corners"] += counts["too_few_corners"]
            log(f"{rec.name}: {counts['images']} board images, {counts['too_few_corners']} with "
                f"too few corners, {counts['views']} views")
            all_views += views
        check_detections(all_views, where, min_frames=options.min_views, counts=total)
        intr = calibrate_intrinsics(all_views, board, size, distortion=options.distortion,
                                    min_views=options.min_views, where=where)
        for v, rms in zip(all_views, intr.view_rms_px):
            frames.append({"source": v.source, "t_start_ns": int(v.t_start_ns),
                           "t_end_ns": int(v.t_end_ns), "images": int(v.images),
                           "corners": int(v.ids.size), "rms_px": float(rms)})
        log(f"K fx={intr.K[0, 0]:.3f} fy={intr.K[1, 1]:.3f} cx={intr.K[0, 2]:.3f} "
            f"cy={intr.K[1, 2]:.3f}, D={np.round(intr.D, 5).tolist()}, RMS {intr.rms_px:.3f} px "
            f"over {intr.views} views")
    doc["camera"] = intr.record()
    doc["sources"] = sources
    doc["frames"] = frames

    if view_poses is not None:
        doc["placement"] = options.placement
        doc["views"] = []
        for rec, views in zip(pose_recs, pose_views):
            if (rec.width, rec.height) != (intr.width, intr.height):
                raise InputError(f"{rec.name}: sensor {rec.width}x{rec.height} differs from the "
                                 f"calibrated {intr.width}x{intr.height}; use this camera's "
                                 "calibration")
            if not views:
                raise InputError(f"{rec.name}: no board view with {options.min_corners}+ corners; "
                                 "the board at the rig's origin must blink in this view's sight "
                                 "(record it again, closer or brighter)")
            best = max(views, key=lambda v: (v.ids.size, v.images))
            T, rms = view_pose(best, board, intr.K, intr.D, placement=options.placement,
                               where=rec.name)
            doc["views"].append({"name": rec.view, "T_world_cam": T.tolist(),
                                 "corners": int(best.ids.size), "rms_px": float(rms)})
            log(f"{rec.name}: pose from {best.ids.size} corners, RMS {rms:.3f} px, camera at "
                f"{np.round(T[:3, 3], 4).tolist()} m")

    text = yaml.safe_dump(doc, sort_keys=False)
    with atomic_output(output, overwrite=overwrite) as tmp:
        tmp.write_text(text)
    log(f"wrote {output}")
    if write_session:
        path = update_session(view_poses, intr, doc.get("views", []))
        log(f"updated {path}")
    return doc


def update_session(root, intr: Intrinsics, views: list[dict]) -> Path:
    """Write measured K, D and view poses into a session's session.yaml (through the session
    recorder's writer: checked by the layout's schema, replaced atomically)."""
    from ..session.layout import load_session
    from ..session.recorder import write_session_yaml

    session = load_session(root)
    if (session.width, session.height) != (intr.width, intr.height):
        raise InputError(f"{root}: the session's camera is {session.width}x{session.height}, the "
                         f"calibration {intr.width}x{intr.height}; calibrate this camera")
    data = copy.deepcopy(session.data)
    cam = data["camera"]
    cam["K"] = intr.K.tolist()
    cam["D"] = [float(d) for d in intr.D]
    cam["distortion_model"] = "plumb_bob"
    cam["calibration"] = {"rms_px": float(intr.rms_px), "views": int(intr.views),
                          "software_version": __version__}
    by_name = {v["name"]: v for v in views}
    for rec in data["views"]:
        if rec.get("name") in by_name:
            rec["T_world_cam"] = by_name[rec["name"]]["T_world_cam"]
            rec["pose_source"] = "calibrated"
    return write_session_yaml(root, data, overwrite=True)
