"""Numerical stability of training and evaluation on extreme training sets.

Synthetic sets (16x16, 2 training views + 1 validation view on a ring around the origin):
a bright square slides across each image; its leading edge fires ``count`` positive events
per pixel and step, its trailing edge as many negative ones.  Every case must train
without NaN/inf (no skipped steps) and give finite metrics.
"""

import json

import numpy as np
import pytest

from evdnerf_ros.eval.evaluate import run_eval, validation_eval
from evdnerf_ros.events.types import EVENT_DTYPE
from evdnerf_ros.io.trainingset import TrainingSet, ViewData, write_training_set
from evdnerf_ros.geometry.camera import ring_poses
from evdnerf_ros.train.trainer import run_train

W = H = 16
K = np.array([[16.0, 0, 7.5], [0, 16.0, 7.5], [0, 0, 1]])


def sliding_square_events(t0: int, span: int, *, steps: int = 12, count: int = 1,
                          active=(0.0, 1.0)) -> np.ndarray:
    """Events of a 6x6 square moving one pixel per step, left to right, during the
    ``active`` fraction of [t0, t0 + span)."""
    a0, a1 = (int(span * f) for f in active)
    times = t0 + a0 + (np.arange(steps, dtype=np.int64) * (a1 - a0)) // steps
    ys = np.arange(5, 11)
    chunks = []
    for j, t in enumerate(times):
        for x, p in ((2 + j + 6, 1), (2 + j, -1)):          # leading edge +, trailing edge -
            if x >= W:
                continue
            n = len(ys) * count
            e = np.zeros(n, EVENT_DTYPE)
            e["t"] = t + np.arange(n, dtype=np.int64) % max(1, min(count, (a1 - a0) // steps))
            e["x"], e["y"], e["p"] = x, np.repeat(ys, count), p
            chunks.append(e)
    ev = np.concatenate(chunks)
    return ev[np.argsort(ev["t"], kind="stable")]


def make_set(path, *, c=0.2, t0=0, span=1_000_000_000, count=1, empty_view=False, active=(0.0, 1.0)):
    poses = ring_poses(3, 4.0, 10.0)
    views = []
    for i, (name, split) in enumerate((("a", "train"), ("b", "train"), ("v", "val"))):
        ev = (np.zeros(0, EVENT_DTYPE) if empty_view and name == "b"
              else sliding_square_events(t0, span, count=count, active=active))
        views.append(ViewData(name=name, split=split, K=K, T_world_cam=poses[i], events=ev))
    return write_training_set(path, views, width=W, height=H, c_pos=c, c_neg=c, t_start=t0,
                              t_end=t0 + span)


def train_and_eval(train_h5, run_dir, *, windows=(8,), loss="mse", iters=30):
    cfg = {"n_samples": 8, "rays": 64, "windows": list(windows), "window_switch": [],
           "eval_every": 15, "loss": loss, "dynamic_resolution": 16}
    summary = run_train(train_h5, run_dir, config=cfg, iters=iters, log=lambda *_: None,
                        eval_fn=validation_eval())
    assert summary["skipped"] == 0 and np.isfinite(summary["loss"])
    lines = [json.loads(x) for x in (run_dir / "metrics.jsonl").read_text().splitlines()]
    assert all(np.isfinite(x["val_psnr"]) and np.isfinite(x["val_psnr_zero_floor"]) for x in lines)
    result = run_eval(run_dir, train_h5, factors=(1,), log=lambda *_: None)
    for name in ("continuous", "quantized", "zero_floor"):
        assert np.isfinite(result["val_windows_x1"][name]["psnr"])
        assert np.isfinite(result["val_windows_x1"][name]["ssim"])
    return lines, result


@pytest.mark.parametrize("c", [0.01, 2.0])
@pytest.mark.parametrize("loss", ["mse", "bin"])
def test_extreme_thresholds(tmp_path, c, loss):
    train_and_eval(make_set(tmp_path / "t.h5", c=c), tmp_path / "run", loss=loss)


def test_hdr_changes_and_black_background(tmp_path):
    """35 events of C = 0.2 per pixel and step: dL = 7, a black (I -> 0, L = log eps)
    background against a bright square; gradients are clipped, nothing overflows."""
    train_and_eval(make_set(tmp_path / "t.h5", count=35), tmp_path / "run")


def test_windows_without_events_and_a_view_without_events(tmp_path):
    """Motion only in the first quarter: most windows are empty; view b recorded nothing
    (it carves nothing; its rays fall back to uniform pixels)."""
    ts_path = make_set(tmp_path / "t.h5", active=(0.0, 0.25), empty_view=True)
    with TrainingSet(ts_path) as ts:
        assert ts.num_events("b") == 0
    train_and_eval(ts_path, tmp_path / "run", windows=(16,))


def test_no_events_anywhere_keeps_the_field_static(tmp_path):
    poses = ring_poses(2, 4.0, 10.0)
    views = [ViewData(name=n, split=s, K=K, T_world_cam=poses[i], events=np.zeros(0, EVENT_DTYPE))
             for i, (n, s) in enumerate((("a", "train"), ("v", "val")))]
    path = write_training_set(tmp_path / "t.h5", views, width=W, height=H, c_pos=0.2, c_neg=0.2,
                              t_start=0, t_end=1_000_000)
    lines, result = train_and_eval(path, tmp_path / "run", iters=10)
    m = result["val_windows_x1"]
    assert m["continuous"]["psnr"] == m["zero_floor"]["psnr"]     # predicts exactly no change


def test_one_microsecond_and_whole_sequence_windows(tmp_path):
    span = 96_000                                                  # 96 us: 96 windows of 1 us
    path = make_set(tmp_path / "t.h5", span=span)
    train_and_eval(path, tmp_path / "fine", windows=(96,))
    train_and_eval(path, tmp_path / "whole", windows=(1,))


def test_absolute_timestamps_around_1e4_s(tmp_path):
    """t0 = 1e4 s: float32 seconds would lose the microseconds; the set's int64 times and
    the normalised times computed from int64 differences keep the windows exact."""
    t0 = 10_000 * 1_000_000_000 + 123_457
    path = make_set(tmp_path / "t.h5", t0=t0, span=4_000_000)
    lines, _ = train_and_eval(path, tmp_path / "run", windows=(4000,))   # 1 us windows
    near = make_set(tmp_path / "t0.h5", t0=0, span=4_000_000)
    with TrainingSet(path) as far_ts, TrainingSet(near) as near_ts:
        assert far_ts.time_range[0] == t0
        edges = np.arange(5, dtype=np.int64) * 1_000_000
        assert np.array_equal(far_ts.log_change_stack("a", edges + t0),
                              near_ts.log_change_stack("a", edges))
