"""Calibration from events of a blinking ChArUco board: error against the number of board
views (poses) and against run time.

A simulated 320x240 event camera (K known, no distortion; tests/board_recordings.py: the
project's simulator renders OpenCV's board picture as an image texture, blinking, and its
event generator makes the events) sees the default board (7x5 squares of 30 mm) at N random
tilted poses, blinking once at each. For each N: the whole pipeline (board images from the
events, ChArUco corners, cv2.calibrateCamera) -> K's relative error (worst of fx, fy, cx, cy),
RMS reprojection error, and the pose error of four rig views (board at the origin, 0.3 m away)
computed with that K. Several seeds per N; the curve is the median with min-max.
Run: python bench/bench_calibration.py [--quick]
"""

from __future__ import annotations

import sys
import time

import numpy as np

from _common import ROOT, arg_parser, machine, pyplot, save_figure, write_results

sys.path.insert(0, str(ROOT / "tests"))

from board_recordings import blink_recording, board_scenes, camera_poses  # noqa: E402

from evdnerf_ros.calib.board import BoardSpec  # noqa: E402
from evdnerf_ros.calib.detect import CornerDetector, merge_same_pose  # noqa: E402
from evdnerf_ros.calib.extrinsics import view_pose  # noqa: E402
from evdnerf_ros.calib.images import blink_images  # noqa: E402
from evdnerf_ros.calib.intrinsics import calibrate_intrinsics  # noqa: E402
from evdnerf_ros.errors import InputError  # noqa: E402
from evdnerf_ros.geometry.camera import PinholeCamera, look_at  # noqa: E402

W, H = 320, 240
CAMERA = PinholeCamera(W, H, 288.0, 288.0, 162.7, 117.4)
BOARD = BoardSpec()


def rig_views(n=4):
    out = []
    for k in range(n):
        az, el = np.radians(90 * k + 20), np.radians(50 + 4 * k)
        out.append(look_at(0.30 * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az),
                                            np.sin(el)]), [0.0, 0.0, 0.0]))
    return out


def pose_err(T, T_true):
    dR = T[:3, :3].T @ T_true[:3, :3]
    ang = np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1)))
    return float(np.linalg.norm(T[:3, 3] - T_true[:3, 3])), float(ang)


def main(argv=None) -> None:
    ap = arg_parser(__doc__, quick="two seeds, fewer view counts (a smoke run)")
    args = ap.parse_args(argv)
    counts = [5, 8, 12, 20] if args.quick else [5, 6, 8, 10, 12, 16, 20, 30, 40]
    seeds = [1, 2] if args.quick else [1, 2, 3, 4, 5]
    scenes = board_scenes(BOARD)
    det = CornerDetector(BOARD)
    rig = rig_views()
    rig_dets = []
    for T in rig:
        ev = blink_recording(BOARD, CAMERA, [T], blinks=2, scenes=scenes)
        d, _ = det.detect_images(blink_images(ev, W, H)[0])
        rig_dets.append(max(merge_same_pose(d), key=lambda v: v.ids.size))
    rows = []
    idx = ([0, 1, 0, 1], [0, 1, 2, 2])
    for seed in seeds:
        t0 = time.perf_counter()
        ev = blink_recording(BOARD, CAMERA, camera_poses(BOARD, max(counts), seed=seed),
                             scenes=scenes)
        sim_s = time.perf_counter() - t0
        for n in counts:
            # the first n poses: pose k's blink ends at 46 (k + 1) ms (board_recordings: a 1 ms
            # jump, 5 ms quiet, a 40 ms blink period), the jump to pose n starts then
            t_pose = 46_000_000 * n + 500_000
            part = ev[ev["t"] < t_pose]
            t0 = time.perf_counter()
            try:
                images, c = blink_images(part, W, H)
                dets, _ = det.detect_images(images)
                views = merge_same_pose(dets)
                intr = calibrate_intrinsics(views, BOARD, (W, H))
            except InputError as exc:
                rows.append({"seed": seed, "poses": n, "error": str(exc)})
                continue
            secs = time.perf_counter() - t0
            kerr = float(np.max(np.abs(intr.K[idx] - CAMERA.K[idx]) / CAMERA.K[idx]))
            perr = [pose_err(view_pose(d, BOARD, intr.K, intr.D)[0], T) for d, T in zip(rig_dets, rig)]
            rows.append({"seed": seed, "poses": n, "views": intr.views, "seconds": secs,
                         "sim_seconds_all_poses": sim_s, "k_rel_err": kerr,
                         "K": intr.K.tolist(), "D": intr.D.tolist(), "rms_px": intr.rms_px,
                         "pose_err_mm_max": 1000 * max(p[0] for p in perr),
                         "pose_err_deg_max": max(p[1] for p in perr)})
            print(f"seed {seed} poses {n:3d}: views {intr.views:3d} K err {100 * kerr:.3f} % "
                  f"RMS {intr.rms_px:.3f} px pose {rows[-1]['pose_err_mm_max']:.2f} mm "
                  f"{rows[-1]['pose_err_deg_max']:.3f} deg, {secs:.2f} s")
    summary = []
    for n in counts:
        r = [x for x in rows if x["poses"] == n and "error" not in x]
        if not r:
            continue
        summary.append({"poses": n, **{f"{k}_{s}": float(f([x[k] for x in r]))
                                      for k in ("k_rel_err", "rms_px", "seconds",
                                                "pose_err_mm_max", "pose_err_deg_max")
                                      for s, f in (("median", np.median), ("max", np.max),
                                                   ("min", np.min))}})
    results = {"machine": machine("opencv-contrib-python-headless"), "quick": bool(args.quick),
               "camera": {"width": W, "height": H, "K": CAMERA.K.tolist()},
               "board": BOARD.record(), "targets": {"k_rel_err": 0.005, "rms_px": 0.3,
                                                    "pose_mm": 1.0, "pose_deg": 0.2},
               "runs": rows, "summary": summary}
    write_results(args.out, "calibration_quick" if args.quick else "calibration", results, plot)


def plot(results, path):
    plt = pyplot()
    s = results["summary"]
    n = [x["poses"] for x in s]
    fig, ax = plt.subplots(1, 3, figsize=(13, 3.8))
    for a, key, scale, label, target in (
            (ax[0], "k_rel_err", 100, "K relative error (worst of fx fy cx cy), %", 0.5),
            (ax[1], "pose_err_mm_max", 1, "worst rig-view position error, mm", 1.0)):
        med = np.array([x[f"{key}_median"] for x in s]) * scale
        lo = np.array([x[f"{key}_min"] for x in s]) * scale
        hi = np.array([x[f"{key}_max"] for x in s]) * scale
        a.fill_between(n, lo, hi, alpha=0.25)
        a.plot(n, med, "o-")
        a.axhline(target, color="r", ls="--", lw=1, label="target")
        a.set_xlabel("board poses")
        a.set_ylabel(label)
        a.set_yscale("log")
        a.legend()
    secs = [x["seconds_median"] for x in s]
    ax[2].plot(secs, [100 * x["k_rel_err_median"] for x in s], "o-")
    for x, y, k in zip(secs, [100 * x["k_rel_err_median"] for x in s], n):
        ax[2].annotate(str(k), (x, y), fontsize=8)
    ax[2].set_xlabel("calibration run time, s (images + corners + calibrateCamera)")
    ax[2].set_ylabel("K relative error, % (median)")
    ax[2].set_yscale("log")
    ax[2].axhline(0.5, color="r", ls="--", lw=1)
    fig.suptitle(f"ChArUco calibration from simulated blink events, {results['camera']['width']}x"
                 f"{results['camera']['height']}", fontsize=10)
    save_figure(fig, path)


if __name__ == "__main__":
    main()
