"""The true scene as the reference of an evaluation (eval/truth.py)."""

import numpy as np
import pytest

from evdnerf_ros.eval.metrics import event_metrics, protocol_windows
from evdnerf_ros.eval.truth import TrueScene, margin_closed
from evdnerf_ros.events.slicing import window_edges
from evdnerf_ros.io.trainingset import TrainingSet


def test_margin_closed_hand_computed_and_no_margin():
    assert margin_closed(35.0, 30.0, 40.0) == pytest.approx(0.5)
    assert margin_closed(28.0, 30.0, 40.0) == pytest.approx(-0.2)      # below the floor: negative
    assert margin_closed(30.0, 30.0, 30.0) is None                     # a static scene: no margin
    assert margin_closed(31.0, 30.0, 29.0) is None
    assert margin_closed(31.0, 30.0, float("nan")) is None


def test_convert_records_what_the_reference_needs(tiny_train_h5):
    with TrainingSet(tiny_train_h5) as ts:
        rec = ts.provenance["truth"]
        assert rec["scene"] == "fork" and rec["supersample"] == 2
        assert set(rec["scene_time_at_origin_ns"]) == set(ts.views)
        # ground-truth offsets: every view's common origin is the same scene instant
        assert len(set(rec["scene_time_at_origin_ns"].values())) == 1


def test_true_dl_agrees_with_the_noise_free_events(tiny_train_h5):
    """The simulator's events are exact crossings of the rendered log intensity, so per pixel and
    window the events' dL (C times net count) is within 2 C of the true dL: with the time mapping
    off by a window, most moving pixels would be far outside."""
    with TrainingSet(tiny_train_h5) as ts:
        truth, why = TrueScene.of(ts)
        assert truth is not None, why
        edges = window_edges(*ts.time_range, 16)
        ks = list(range(16))
        c = max(ts.thresholds)
        for view in (ts.val_views[0], "moving_00"):          # a static and a moving camera
            true = truth.log_change_stack(view, edges, ks)
            gt = ts.log_change_stack(view, edges)
            moving = np.abs(true) > c
            assert moving.sum() > 200
            assert np.mean(np.abs(true - gt)[moving] <= 2 * c + 0.05) > 0.97
            shifted = truth.log_change_stack(view, edges, ks[1:] + [0])
            assert np.mean(np.abs(shifted - gt)[moving] <= 2 * c + 0.05) < 0.8
        # scored by the protocol, the truth is far better than predicting no events
        m = event_metrics(true[protocol_windows(16)], gt[protocol_windows(16)], c_pos=ts.c_pos, c_neg=ts.c_neg)
        assert m["continuous"]["psnr"] > m["zero_floor"]["psnr"] + 2


def test_no_truth_for_a_recorded_session(tiny_train_h5, tmp_path):
    import shutil

    import h5py

    copy = tmp_path / "t.h5"
    shutil.copy(tiny_train_h5, copy)
    import json

    with h5py.File(copy, "r+") as f:
        prov = json.loads(f["provenance"][()])
        del prov["truth"]
        del f["provenance"]
        f["provenance"] = json.dumps(prov)
    with TrainingSet(copy) as ts:
        truth, why = TrueScene.of(ts)
    assert truth is None and "not converted from a simulated session" in why


def test_pooled_margin_where_empty_windows_leave_no_mean_margin(tiny_train_h5):
    """A sparse set: a window without events gives the floor the 100 dB cap, and a true scene
    whose sub-threshold dL is not exactly zero there falls below the floor in the protocol's
    mean over windows (no margin). One MSE over all windows still ranks them: the pooled margin."""
    from evdnerf_ros.eval.evaluate import evaluate_views
    from evdnerf_ros.field import PlanesField
    from evdnerf_ros.train.rays import default_box

    with TrainingSet(tiny_train_h5) as ts:
        truth, why = TrueScene.of(ts)
        assert truth is not None, why
        view, n = ts.val_views[0], 8
        edges = window_edges(*ts.time_range, n)
        gt = ts.log_change_stack(view, edges)[protocol_windows(n)]
        true = truth.log_change_stack(view, edges, protocol_windows(n))
        empty = np.zeros_like(gt[:1])
        faint = np.full_like(gt[:1], 0.01)                   # the truth's sub-threshold change
        m = event_metrics(np.concatenate([true, faint, faint]), np.concatenate([gt, empty, empty]),
                          c_pos=ts.c_pos, c_neg=ts.c_neg)
        assert m["continuous"]["psnr"] < m["zero_floor"]["psnr"]        # the 100 dB windows win
        assert m["continuous"]["psnr_pooled"] > m["zero_floor"]["psnr_pooled"]
        # evaluate_views reports the pooled margin of a field next to the protocol's
        field = PlanesField(resolutions=(4,), time_resolution=4, features=2, seed=0)
        _, _, scores = evaluate_views(field, ts, [view], n, box=default_box(ts), n_samples=4, log_eps=1e-3, truth=truth)
        pooled = scores["margin_closed"]["pooled"]
        assert pooled == pytest.approx(margin_closed(scores["continuous"]["psnr_pooled"],
                                                     scores["zero_floor"]["psnr_pooled"],
                                                     scores["truth"]["continuous"]["psnr_pooled"]))
