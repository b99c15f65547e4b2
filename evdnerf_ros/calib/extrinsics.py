"""A view's pose from the board placed at the rig's origin (``cv2.solvePnP``).

solvePnP gives the board in the camera, ``T_cam_board``; the view's pose is
``T_world_cam = T_world_board @ inv(T_cam_board)`` (4x4 float64, OpenCV camera axes, metres:
the project's convention, DESIGN.md "Poses"). Where the board sits in the world
(``placement``):

* ``centre-up`` (default): the board lies face up on the turntable, its centre at the world
  origin: world x = board x, world y = -board y, world z = -board z (up, out of the board's
  face) -- the rig's z-up world with the board's centre as origin;
* ``board``: the world is the board frame itself (origin at the picture's top-left corner,
  z into the board).
"""

from __future__ import annotations

import numpy as np

from ..errors import InputError
from ..geometry.poses import check_rigid, rigid
from .board import BoardSpec, cv2_aruco
from .detect import Detection
from .intrinsics import object_image_points

PLACEMENTS = ("centre-up", "board")
#: Residual (px) below which a corner is never dropped as an outlier by board_pose.
OUTLIER_PX = 0.5


def T_world_board(board: BoardSpec, placement: str = "centre-up") -> np.ndarray:
    """The board frame in the world (module doc)."""
    if placement == "board":
        return np.eye(4)
    if placement == "centre-up":
        w, h = board.size_m
        return rigid(np.diag([1.0, -1.0, -1.0]), [-w / 2.0, h / 2.0, 0.0])
    raise InputError(f"board placement must be one of {', '.join(PLACEMENTS)}, got {placement!r}")


def board_pose(detection: Detection, board: BoardSpec, K, D, *, where: str = "view"
               ) -> tuple[np.ndarray, float]:
    """(T_cam_board 4x4, reprojection RMS px) of one detection, by solvePnP (IPPE for the
    planar board, refined by Levenberg-Marquardt)."""
    cv2 = cv2_aruco()
    obj, img = object_image_points(board, detection)
    if obj.shape[0] < 4:
        raise InputError(f"{where}: {obj.shape[0]} board corners; a pose needs at least 4 "
                         "(bring the board fully into view)")
    K = np.asarray(K, np.float64)
    D = np.asarray(D, np.float64)
    ok, rvec, tvec = cv2.solvePnP(obj, img, K, D, flags=cv2.SOLVEPNP_IPPE)
    if not ok:
        raise InputError(f"{where}: solvePnP found no board pose; check the intrinsics and board")
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-14)
    rvec, tvec = cv2.solvePnPRefineLM(obj, img, K, D, rvec, tvec, crit)
    # one round of outlier rejection: a corner the refinement misplaced (a marker edge in its
    # window) is dropped when its residual exceeds 3x the median and OUTLIER_PX
    res = np.linalg.norm(cv2.projectPoints(obj, rvec, tvec, K, D)[0].reshape(-1, 2) - img, axis=1)
    keep = res <= max(OUTLIER_PX, 3.0 * float(np.median(res)))
    if 6 <= keep.sum() < keep.size:
        obj, img = obj[keep], img[keep]
        rvec, tvec = cv2.solvePnPRefineLM(obj, img, K, D, rvec, tvec, crit)
    proj, _ = cv2.projectPoints(obj, rvec, tvec, K, D)
    rms = float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - img) ** 2, axis=1))))
    R, _ = cv2.Rodrigues(rvec)
    T = rigid(R, np.asarray(tvec, np.float64).ravel())
    if T[2, 3] <= 0:
        raise InputError(f"{where}: the board came out behind the camera; check the board size "
                         "and intrinsics")
    return check_rigid(T, f"{where}: T_cam_board"), rms


def view_pose(detection: Detection, board: BoardSpec, K, D, *, placement: str = "centre-up",
              where: str = "view") -> tuple[np.ndarray, float]:
    """(T_world_cam, reprojection RMS px) of the camera that made `detection` (module doc)."""
    T_cam_board, rms = board_pose(detection, board, K, D, where=where)
    R, t = T_cam_board[:3, :3], T_cam_board[:3, 3]
    T_board_cam = rigid(R.T, -R.T @ t)
    return T_world_board(board, placement) @ T_board_cam, rms
