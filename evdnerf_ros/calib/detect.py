"""ChArUco corners in board images (``cv2.aruco.CharucoDetector``), and views made of them.

An event image (counts) is scaled to 8 bits: the ``white_percentile`` of its non-zero pixels
becomes white (255), so a few hot pixels cannot darken the board. OpenCV finds the markers,
interpolates the chessboard corners between them and refines them to sub-pixel precision;
then (``refine``) each corner is refined again by ``cv2.cornerSubPix`` on the count image
itself with a window that stays inside the white margin around a square's corner (markers
inside the window bias the corner; measured on simulated blinks at 320x240: corner error
RMS 0.25 px -> 0.15 px).

Several blinks at one pose give the same corners up to noise: consecutive detections whose
shared corners moved by less than ``same_pose_px`` (median) are merged into one *view* (the
corners averaged over its blinks), so a pose counts once whatever the blink rate.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import InputError
from .board import BoardSpec, cv2_aruco
from .images import BoardImage


@dataclass
class Detection:
    """Corners found in one board image (or merged from several at one pose)."""

    ids: np.ndarray            # (N,) int, ascending
    corners: np.ndarray        # (N, 2) float64 pixels (OpenCV: pixel centres at integers)
    source: str = ""
    t_start_ns: int = 0
    t_end_ns: int = 0
    images: int = 1            # board images merged into it


def to_uint8(image: np.ndarray, white_percentile: float = 90.0) -> np.ndarray:
    """An event-count image as 8-bit grey (0 black .. 255 white); all zeros stays black."""
    img = np.asarray(image, dtype=np.float32)
    nz = img[img > 0]
    if nz.size == 0:
        return np.zeros(img.shape, np.uint8)
    white = float(np.percentile(nz, white_percentile))
    return np.clip(img * (255.0 / max(white, 1e-12)), 0, 255).round().astype(np.uint8)


class CornerDetector:
    """Detects the corners of one board in images; reuses OpenCV's detector between images."""

    def __init__(self, board: BoardSpec, *, white_percentile: float = 90.0, refine: bool = True):
        cv2 = cv2_aruco()
        self.board = board
        self.refine = bool(refine)
        self.white_percentile = float(white_percentile)
        params = cv2.aruco.DetectorParameters()
        params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
        cparams = cv2.aruco.CharucoParameters()
        cparams.minMarkers = 1
        self._cv2 = cv2
        self._det = cv2.aruco.CharucoDetector(board.cv_board(), cparams, params)

    def detect(self, image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(ids (N,), corners (N, 2)) in one image (float counts or uint8); N may be 0."""
        img = image if image.dtype == np.uint8 else to_uint8(image, self.white_percentile)
        corners, ids, _, _ = self._det.detectBoard(img)
        if ids is None or corners is None or len(ids) == 0:
            return np.empty(0, np.int64), np.empty((0, 2))
        ids = ids.reshape(-1).astype(np.int64)
        corners = corners.reshape(-1, 2).astype(np.float64)
        order = np.argsort(ids, kind="stable")
        ids, corners = ids[order], corners[order]
        if self.refine:
            corners = self._refine(np.asarray(image, np.float32), ids, corners)
        return ids, corners

    def _refine(self, image: np.ndarray, ids: np.ndarray, corners: np.ndarray) -> np.ndarray:
        """cornerSubPix on the image itself (counts, not the 8-bit copy) with a window that
        stays inside the white margin between a square's edge and its marker: about
        ``(square - marker) / 2`` of the local square size in pixels (>= 2 px)."""
        cv2 = self._cv2
        nx = self.board.squares_x - 1
        row, col = ids // nx, ids % nx
        pos = {int(i): k for k, i in enumerate(ids)}
        d = [np.linalg.norm(corners[k] - corners[pos[int(i) + 1]])
             for k, i in enumerate(ids) if col[k] + 1 < nx and int(i) + 1 in pos]
        d += [np.linalg.norm(corners[k] - corners[pos[int(i) + nx]])
              for k, i in enumerate(ids) if int(i) + nx in pos]
        if not d:
            return corners
        margin = 0.5 * (self.board.square_m - self.board.marker_m) / self.board.square_m
        half = int(max(2, round(0.9 * margin * float(np.median(d)))))
        crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 100, 1e-4)
        pts = corners.astype(np.float32).reshape(-1, 1, 2).copy()
        pts = cv2.cornerSubPix(image, pts, (half, half), (-1, -1), crit).reshape(-1, 2)
        moved = np.linalg.norm(pts - corners, axis=1)
        return np.where((moved < half)[:, None], pts.astype(np.float64), corners)

    def detect_images(self, images: list[BoardImage], *, min_corners: int = 8
                      ) -> tuple[list[Detection], dict]:
        """Detections of the images with at least `min_corners` non-collinear corners;
        counts: ``images``, ``detected``, ``too_few_corners``."""
        counts = {"images": len(images), "detected": 0, "too_few_corners": 0}
        out = []
        cvb = self._det.getBoard()
        for im in images:
            ids, corners = self.detect(im.image)
            if ids.size < max(4, int(min_corners)) or cvb.checkCharucoCornersCollinear(ids[:, None]):
                counts["too_few_corners"] += 1
                continue
            counts["detected"] += 1
            out.append(Detection(ids, corners, im.source, im.t_start_ns, im.t_end_ns))
        return out, counts


def merge_same_pose(detections: list[Detection], same_pose_px: float = 1.0) -> list[Detection]:
    """Consecutive detections of one source whose shared corners moved less than
    `same_pose_px` (median) merged into one view: each corner averaged over the detections
    that saw it (module doc)."""
    views: list[list[Detection]] = []
    for d in detections:
        if views and views[-1][-1].source == d.source:
            prev = views[-1][-1]
            common, ia, ib = np.intersect1d(prev.ids, d.ids, return_indices=True)
            if common.size >= 4 and np.median(np.linalg.norm(
                    prev.corners[ia] - d.corners[ib], axis=1)) < same_pose_px:
                views[-1].append(d)
                continue
        views.append([d])
    out = []
    for group in views:
        if len(group) == 1:
            out.append(group[0])
            continue
        ids = np.unique(np.concatenate([g.ids for g in group]))
        acc = np.zeros((ids.size, 2))
        n = np.zeros(ids.size)
        for g in group:
            k = np.searchsorted(ids, g.ids)
            acc[k] += g.corners
            n[k] += 1
        out.append(Detection(ids, acc / n[:, None], group[0].source, group[0].t_start_ns,
                             group[-1].t_end_ns, len(group)))
    return out


def check_detections(detections: list[Detection], where: str, *, min_frames: int,
                     counts: dict) -> None:
    """InputError unless at least `min_frames` views have corners: says how many images were
    made, how many had too few corners, and how to get more."""
    if len(detections) >= min_frames:
        return
    if counts.get("images", 0) == 0:
        raise InputError(f"{where}: no board image could be made from the events (no blink "
                         "bursts); is the board blinking and in view? record a blinking board "
                         "(or use --style window for a moving board)")
    raise InputError(
        f"{where}: {len(detections)} usable board view(s), need at least {min_frames} "
        f"({counts.get('images', 0)} board images, {counts.get('too_few_corners', 0)} with too "
        "few corners); record more board poses (tilted, covering the image), move more "
        "slowly, or use a bigger board / come closer")
