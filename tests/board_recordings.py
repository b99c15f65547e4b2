"""Simulated event recordings of a blinking ChArUco board (test and benchmark data for calib).

The project's simulator renders the board's real picture (OpenCV's) as an image texture on a
thin box lying face up at the world origin (``centre-up``: its face on z = 0, centred), seen
by a pinhole camera of known K (no distortion). A blink is a screen switching the picture on
and off: ``on`` renders the textured board, ``off`` the same box with the black level all
over; frames ramp off -> on -> off and the project's event generator turns them into events.
Between poses the camera jumps (the board is off then; the background differs from the
board's off level, so a move makes a mixed-polarity edge burst that calibration must drop).
"""

from __future__ import annotations

import numpy as np

from evdnerf_ros.calib.board import BoardSpec
from evdnerf_ros.calib.extrinsics import T_world_board
from evdnerf_ros.events.types import empty_events
from evdnerf_ros.geometry.camera import CameraSetup, PinholeCamera
from evdnerf_ros.geometry.poses import rigid
from evdnerf_ros.geometry.rotations import quat_to_matrix
from evdnerf_ros.sim import geometry as geo
from evdnerf_ros.sim.generator import EventGenerator
from evdnerf_ros.sim.render import SceneRenderer
from evdnerf_ros.sim.scene import Background, Lights, Scene, SceneObject, Texture

THICKNESS = 0.002


def _rot(axis, deg):
    a = np.radians(deg) / 2
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    return quat_to_matrix(np.array([np.cos(a), *(np.sin(a) * axis)]))


def board_scenes(board: BoardSpec, *, albedo=0.5, contrast=0.9, background=0.02,
                 px_per_square=80):
    """(scene with the board on, scene with it off)."""
    img = board.image(px_per_square).astype(np.float64) / 255.0
    w, h = board.size_m
    pose = rigid(None, [0.0, 0.0, -THICKNESS / 2])
    tex = Texture("image", 1.0, contrast, image=img, size=(w, h))
    shape = geo.Box(np.array([w, h, THICKNESS]))
    lights = Lights(ambient=1.0, directional=(), shadows=False)
    scenes = []
    for on in (True, False):
        obj = SceneObject(name="board", type="box", key_path="objects[0]", shape=shape,
                          albedo=albedo if on else albedo * (1 - contrast),
                          texture=tex if on else None, pose=pose)
        scenes.append(Scene(name="charuco", source="charuco", start_ns=0, end_ns=10**9,
                            objects=[obj], background=Background(background), lights=lights,
                            cameras=CameraSetup()))
    return scenes


def camera_poses(board: BoardSpec, n: int, *, seed: int = 0, distance=(0.22, 0.34),
                 tilt_deg=35.0, shift=0.5):
    """n camera poses T_world_cam looking at the board from random tilted poses."""
    rng = np.random.default_rng(seed)
    w, h = board.size_m
    Twb = T_world_board(board, "centre-up")
    out = []
    for _ in range(n):
        target_b = np.array([w / 2 + rng.uniform(-shift, shift) * w / 2,
                             h / 2 + rng.uniform(-shift, shift) * h / 2, 0.0])
        R = (_rot([0, 1, 0], rng.uniform(-tilt_deg, tilt_deg))
             @ _rot([1, 0, 0], rng.uniform(-tilt_deg, tilt_deg))
             @ _rot([0, 0, 1], rng.uniform(-20, 20)))
        d = rng.uniform(*distance)
        pos_b = target_b - d * R[:, 2]
        out.append(Twb @ rigid(R, pos_b))
    return out


def blink_recording(board: BoardSpec, camera: PinholeCamera, poses, *, blinks=1,
                    supersample=3, c=0.1, threshold_sigma=0.0, seed=0, period_ns=40_000_000,
                    ramp_ns=1_000_000, scenes=None):
    """Events of the board blinking `blinks` times at each camera pose, sorted by t."""
    on_scene, off_scene = scenes or board_scenes(board)
    r_on = SceneRenderer(on_scene, camera, supersample)
    r_off = SceneRenderer(off_scene, camera, supersample)
    gen = EventGenerator(camera.width, camera.height, c_pos=c, c_neg=c,
                         threshold_sigma=threshold_sigma, seed=seed)
    half = period_ns // 2
    t = 1_000_000
    parts = []
    for k, T in enumerate(poses):
        on = r_on.render(T, 0)
        off = r_off.render(T, 0)
        if k == 0:
            gen.reset(off, t)
        else:
            t += ramp_ns                   # the jump to the next pose
            parts.append(gen.step(off, t))
        for _ in range(blinks):
            t0 = t + half // 4
            for frame, dt in ((off, 0), (on, ramp_ns), (on, half), (off, half + ramp_ns),
                              (off, period_ns)):
                parts.append(gen.step(frame, t0 + dt))
            t = t0 + period_ns
    parts = [p for p in parts if p.size]
    return np.concatenate(parts) if parts else empty_events()
