"""Intrinsics and distortion from ChArUco views (``cv2.calibrateCamera``).

Distortion models (``distortion``): ``plumb_bob`` (k1, k2, p1, p2, k3: ROS's and OpenCV's
default), ``radial`` (k1, k2; p1 = p2 = k3 = 0), ``none`` (a pinhole, D all zero). The result
holds K, D (always 5 numbers, ROS's plumb_bob order), the RMS reprojection error over all
corners and each view's own RMS, so a bad view shows.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import InputError
from .board import BoardSpec, cv2_aruco
from .detect import Detection

DISTORTION_MODELS = ("plumb_bob", "radial", "none")


@dataclass
class Intrinsics:
    width: int
    height: int
    K: np.ndarray                  # (3, 3)
    D: np.ndarray                  # (5,) k1 k2 p1 p2 k3
    rms_px: float                  # over every corner of every view used
    view_rms_px: list[float]
    views: int
    corners: int
    distortion: str = "plumb_bob"

    def record(self) -> dict:
        return {"width": int(self.width), "height": int(self.height), "K": self.K.tolist(),
                "distortion_model": "plumb_bob", "D": [float(d) for d in self.D],
                "fitted_distortion": self.distortion, "rms_px": float(self.rms_px),
                "views": int(self.views), "corners": int(self.corners)}


def _flags(cv2, distortion: str) -> int:
    if distortion not in DISTORTION_MODELS:
        raise InputError(f"distortion must be one of {', '.join(DISTORTION_MODELS)}, got {distortion!r}")
    if distortion == "plumb_bob":
        return 0
    flags = cv2.CALIB_ZERO_TANGENT_DIST | cv2.CALIB_FIX_K3
    if distortion == "none":
        flags |= cv2.CALIB_FIX_K1 | cv2.CALIB_FIX_K2
    return flags


def object_image_points(board: BoardSpec, d: Detection) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) float32 board points and (N, 2) float32 pixels of one detection."""
    return (board.corners_3d()[d.ids].astype(np.float32),
            d.corners.astype(np.float32))


def calibrate_intrinsics(detections: list[Detection], board: BoardSpec, size: tuple[int, int], *,
                         distortion: str = "plumb_bob", min_views: int = 5,
                         where: str = "calibration") -> Intrinsics:
    """K and distortion from ChArUco views of one camera of `size` (width, height) pixels."""
    cv2 = cv2_aruco()
    w, h = int(size[0]), int(size[1])
    if len(detections) < min_views:
        raise InputError(f"{where}: {len(detections)} usable board view(s), need at least "
                         f"{min_views} to calibrate; record more board poses (tilted, covering "
                         "the image), move more slowly, or use a bigger board")
    obj, img = zip(*(object_image_points(board, d) for d in detections))
    flags = _flags(cv2, distortion)
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    try:
        rms, K, D, rvecs, tvecs = cv2.calibrateCamera(list(obj), list(img), (w, h), None, None,
                                                      flags=flags, criteria=crit)
    except cv2.error as exc:
        raise InputError(f"{where}: OpenCV could not calibrate from {len(detections)} views "
                         f"({' '.join(str(exc).split())[:200]}); record more varied board poses"
                         ) from None
    D = np.zeros(5) if D is None else np.asarray(D, np.float64).ravel()[:5]
    D = np.concatenate([D, np.zeros(5 - D.size)])
    view_rms = []
    for o, i, r, t in zip(obj, img, rvecs, tvecs):
        proj, _ = cv2.projectPoints(o, r, t, K, D)
        view_rms.append(float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - i) ** 2, axis=1)))))
    K = np.asarray(K, np.float64)
    if not (np.all(np.isfinite(K)) and K[0, 0] > 0 and K[1, 1] > 0 and np.all(np.isfinite(D))):
        raise InputError(f"{where}: calibration diverged (K = {K.tolist()}); record more varied "
                         "board poses")
    return Intrinsics(w, h, K, D, float(rms), view_rms, len(detections),
                      int(sum(len(o) for o in obj)), distortion)
