"""Camera calibration from events of a ChArUco board (evdnerf_ros.calib, `evdnerf calibrate`).

Data: the project's simulator renders OpenCV's picture of the board as an image texture,
blinking, seen by a 320x240 pinhole camera of known K (tests/board_recordings.py); events come
from the project's event generator. Targets (issue 15): K within 0.5 % of the truth and
reprojection RMS < 0.3 px; view poses within 1 mm and 0.2 degrees.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

pytest.importorskip("cv2")
sys.path.insert(0, str(Path(__file__).resolve().parent))

from board_recordings import blink_recording, board_scenes, camera_poses  # noqa: E402

from evdnerf_ros.calib.board import BoardSpec, board_from_mapping  # noqa: E402
from evdnerf_ros.calib.extrinsics import T_world_board, view_pose  # noqa: E402
from evdnerf_ros.calib.images import blink_images  # noqa: E402
from evdnerf_ros.calib.run import CalibrationOptions, run_calibration  # noqa: E402
from evdnerf_ros.cli import main  # noqa: E402
from evdnerf_ros.errors import InputError  # noqa: E402
from evdnerf_ros.events.codecs import quantize_to_us  # noqa: E402
from evdnerf_ros.events.types import empty_events  # noqa: E402
from evdnerf_ros.geometry.camera import PinholeCamera  # noqa: E402
from evdnerf_ros.geometry.poses import rigid  # noqa: E402
from evdnerf_ros.io.npz import write_npz  # noqa: E402
from evdnerf_ros.session.layout import load_session  # noqa: E402
from evdnerf_ros.session.recorder import (ViewRecorder, camera_record, session_document,  # noqa: E402
                                          view_record, write_session_yaml)

BOARD = BoardSpec()
W, H = 320, 240
CAMERA = PinholeCamera(W, H, 288.0, 288.0, 162.7, 117.4)    # principal point off-centre


def k_rel_errors(K) -> np.ndarray:
    """|fx, fy, cx, cy - truth| / truth."""
    idx = ([0, 1, 0, 1], [0, 1, 2, 2])
    return np.abs(np.asarray(K)[idx] - CAMERA.K[idx]) / CAMERA.K[idx]


def pose_errors(T, T_true) -> tuple[float, float]:
    """(position error m, rotation error deg)."""
    dR = T[:3, :3].T @ T_true[:3, :3]
    ang = np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1)))
    return float(np.linalg.norm(T[:3, 3] - T_true[:3, 3])), float(ang)


@pytest.fixture(scope="module")
def scenes():
    return board_scenes(BOARD)


@pytest.fixture(scope="module")
def intrinsics_recording(tmp_path_factory, scenes):
    ev = blink_recording(BOARD, CAMERA, camera_poses(BOARD, 20, seed=1), scenes=scenes)
    path = tmp_path_factory.mktemp("calib") / "board.npz"
    write_npz(path, ev, W, H)
    return path


@pytest.fixture(scope="module")
def calibration(intrinsics_recording):
    out = intrinsics_recording.parent / "calib.yaml"
    assert main(["calibrate", str(intrinsics_recording), "-o", str(out)]) == 0
    return out


def view_poses_truth(n=4):
    """Rig-like views: the board lies face up at the origin; cameras 0.3 m away, looking down
    at it from 45-60 deg elevation, one of them seeing the board only partly."""
    from evdnerf_ros.geometry.camera import look_at

    out = []
    for k in range(n):
        az = np.radians(90 * k + 20)
        el = np.radians(50 + 4 * k)
        pos = 0.30 * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
        target = [0.11, 0.0, 0.0] if k == n - 1 else [0.0, 0.0, 0.0]   # last: partly out of view
        out.append(look_at(pos, target))
    return out


def write_board_session(root: Path, poses, scenes, *, blinks=2):
    root.mkdir()
    views = []
    for k, T in enumerate(poses):
        ev = quantize_to_us(blink_recording(BOARD, CAMERA, [T], blinks=blinks, scenes=scenes))
        if ev.size == 0:                 # the board out of sight: sensor noise only
            rng = np.random.default_rng(k)
            ev = np.zeros(300, ev.dtype)
            ev["t"] = np.sort(rng.integers(0, 100_000, 300)) * 1000
            ev["x"], ev["y"] = rng.integers(0, W, 300), rng.integers(0, H, 300)
            ev["p"] = rng.choice([-1, 1], 300)
        name = f"view_{k:02d}"
        with ViewRecorder(root / name, width=W, height=H) as rec:
            rec.camera_info(CAMERA.K, stamp_ns=int(ev["t"][0]) if ev.size else 0)
            if ev.size:
                rec.events(ev)
            rec.pose(np.eye(4), 0)
        views.append(view_record(name, "train", np.eye(4), azimuth_deg=90.0 * k))
    doc = session_document(source={"kind": "test"}, rig={"kind": "virtual"},
                           camera=camera_record(W, H, [[250.0, 0, 160], [0, 250.0, 120], [0, 0, 1]]),
                           thresholds={"c_pos": 0.1, "c_neg": 0.1}, views=views)
    write_session_yaml(root, doc)
    return root


# ----------------------------------------------------------------------------- the board

def test_board_corners_match_opencv_and_yaml_is_checked():
    assert np.allclose(BOARD.cv_board().getChessboardCorners(), BOARD.corners_3d(), atol=1e-7)
    img = BOARD.image(40)
    assert img.shape == (5 * 40, 7 * 40) and img.dtype == np.uint8
    assert board_from_mapping({"squares_x": 5, "square_m": 0.04, "marker_m": 0.03}).squares_x == 5
    with pytest.raises(InputError, match="marker_m"):
        board_from_mapping({"square_m": 0.02, "marker_m": 0.03})
    with pytest.raises(InputError, match="unknown key"):
        board_from_mapping({"squares": 5})


def test_image_texture_renders_the_picture_upright(scenes):
    """The simulator's image texture: a camera straight above the board sees its picture
    (top row at +y, not mirrored)."""
    from evdnerf_ros.sim.render import SceneRenderer

    cam = PinholeCamera(560, 400, 1200.0, 1200.0, 279.5, 199.5)
    T = rigid(np.diag([1.0, -1.0, -1.0]), [0, 0, 0.6])      # looking down -z, image x = +x, rows = -y
    img = SceneRenderer(scenes[0], cam, 1).render(T, 0)
    w, h = BOARD.size_m
    u = 1200.0 * (w / 2) / 0.6
    v = 1200.0 * (h / 2) / 0.6
    import cv2

    # the board covers pixels [cx - u, cx + u] x [cy - v, cy + v]: 420 x 300 pixels
    rend = img[int(199.5 - v + 0.5):int(199.5 + v + 0.5), int(279.5 - u + 0.5):int(279.5 + u + 0.5)]
    pic = cv2.resize(BOARD.image(60), rend.shape[::-1], interpolation=cv2.INTER_AREA) > 127
    bright = rend > 0.5 * (rend.min() + rend.max())
    agree = [np.mean(bright == r) for r in (pic, pic[:, ::-1], pic[::-1], pic[::-1, ::-1])]
    assert agree[0] > 0.97 and max(agree[1:]) < agree[0] - 0.04, agree


def test_image_texture_from_yaml(tmp_path):
    from evdnerf_ros.sim.scene import load_scene

    np.save(tmp_path / "pic.npy", np.eye(4))
    (tmp_path / "s.yaml").write_text(
        "objects: [{type: box, size: [0.2, 0.2, 0.01], texture: {type: image, path: pic.npy, "
        "size: [0.2, 0.2], contrast: 0.8}}]\n")
    scene = load_scene(tmp_path / "s.yaml", check_cameras=False)
    assert scene.objects[0].texture.image.shape == (4, 4)
    (tmp_path / "bad.yaml").write_text(
        "objects: [{type: box, size: [1, 1, 1], texture: {type: image, path: nope.png, "
        "size: [1, 1]}}]\n")
    with pytest.raises(InputError, match="nope.png"):
        load_scene(tmp_path / "bad.yaml", check_cameras=False)


# ----------------------------------------------------------------------------- intrinsics

def test_intrinsics_from_a_blinking_board(calibration):
    doc = yaml.safe_load(calibration.read_text())
    cam = doc["camera"]
    err = k_rel_errors(cam["K"])
    assert np.all(err < 0.005), (err, cam["K"])
    assert cam["rms_px"] < 0.3, cam["rms_px"]
    assert cam["views"] >= 15 and (cam["width"], cam["height"]) == (W, H)
    # the jumps between poses are mixed-polarity bursts: dropped, and said so
    assert doc["sources"][0]["mixed"] > 0
    assert len(doc["frames"]) == cam["views"]


def test_blink_images_show_white_squares(intrinsics_recording):
    from evdnerf_ros.io.npz import read_npz

    ev = read_npz(intrinsics_recording)[0]
    images, counts = blink_images(ev[ev["t"] < 60_000_000], W, H)
    assert counts["bursts"] >= 2 and {im.polarity for im in images} == {1, -1}
    assert all(im.image.max() > 10 for im in images)


# ----------------------------------------------------------------------------- view poses

def test_view_poses_and_session_update(tmp_path, scenes, calibration):
    truth = view_poses_truth()
    session = write_board_session(tmp_path / "session", truth, scenes)
    out = tmp_path / "poses.yaml"
    assert main(["calibrate", "--intrinsics", str(calibration),
                 "--view-poses", str(session), "--write-session", "-o", str(out)]) == 0
    doc = yaml.safe_load(out.read_text())
    corners = [v["corners"] for v in doc["views"]]
    assert corners[-1] < BOARD.n_corners <= max(corners)       # the last view sees a part only
    for v, T_true in zip(doc["views"], truth):
        dp, da = pose_errors(np.array(v["T_world_cam"]), T_true)
        assert dp < 1e-3 and da < 0.2, (v["name"], dp, da)
    s = load_session(session)
    assert np.allclose(s.K, yaml.safe_load(calibration.read_text())["camera"]["K"])
    for v, T_true in zip(s.views, truth):
        assert pose_errors(v.T_world_cam, T_true)[0] < 1e-3


def test_view_pose_placement_board_frame(scenes):
    """placement 'board': the pose is in the board's own frame (z into the board)."""
    T = view_poses_truth(1)[0]
    ev = blink_recording(BOARD, CAMERA, [T], scenes=scenes)
    from evdnerf_ros.calib.detect import CornerDetector

    im = blink_images(ev, W, H)[0][0]
    ids, corners = CornerDetector(BOARD).detect(im.image)
    from evdnerf_ros.calib.detect import Detection

    T_b, _ = view_pose(Detection(ids, corners), BOARD, CAMERA.K, np.zeros(5), placement="board")
    T_expect = np.linalg.inv(T_world_board(BOARD, "centre-up")) @ T
    dp, da = pose_errors(T_b, T_expect)
    assert dp < 1e-3 and da < 0.2


# ----------------------------------------------------------------------------- refusals

def test_too_few_views_is_a_clear_error(tmp_path, scenes, capsys):
    ev = blink_recording(BOARD, CAMERA, camera_poses(BOARD, 2, seed=3), scenes=scenes)
    write_npz(tmp_path / "few.npz", ev, W, H)
    assert main(["calibrate", str(tmp_path / "few.npz"), "-o", str(tmp_path / "c.yaml")]) == 2
    err = capsys.readouterr().err
    assert "2 usable board view(s), need at least 5" in err and "more board poses" in err
    assert not (tmp_path / "c.yaml").exists()


def test_black_and_empty_recordings_are_clear_errors(tmp_path, scenes):
    write_npz(tmp_path / "empty.npz", empty_events(), W, H)
    with pytest.raises(InputError, match="no board image could be made"):
        run_calibration([tmp_path / "empty.npz"], tmp_path / "c.yaml", log=None)
    # a view looking away from the board: the board never appears
    away = rigid(np.eye(3), [0.0, 0.0, 0.3])                 # looks up, away from the board
    session = write_board_session(tmp_path / "s", [view_poses_truth(1)[0], away], scenes)
    with pytest.raises(InputError, match="view_01: no board view"):
        run_calibration([], tmp_path / "c.yaml", intrinsics=None, view_poses=session, log=None,
                        options=CalibrationOptions(min_views=1))
    assert not (tmp_path / "c.yaml").exists()
