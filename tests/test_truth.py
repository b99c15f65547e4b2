"""The true scene as the reference of an evaluation (eval/truth.py)."""

import numpy as np
import pytest
import torch

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


def test_each_views_pooled_margin_as_if_scored_alone(tiny_train_h5):
    """Every split reports each view's pooled scores (which viewpoints a field gets wrong): with
    the split's data range, so the PSNRs shift against a view scored alone, but the margin
    closed, a ratio of log MSE ratios, is the same as that view's own evaluation."""
    from evdnerf_ros.eval.evaluate import evaluate_views
    from evdnerf_ros.field import PlanesField
    from evdnerf_ros.train.rays import default_box

    with TrainingSet(tiny_train_h5) as ts:
        truth, why = TrueScene.of(ts)
        assert truth is not None, why
        views = list(ts.train_views[:2])
        assert len(views) == 2
        field = PlanesField(resolutions=(4,), time_resolution=4, features=2, seed=0)
        kw = dict(box=default_box(ts), n_samples=4, log_eps=1e-3, truth=truth)
        _, _, both = evaluate_views(field, ts, views, 8, **kw)
        assert set(both["per_view"]) == {str(v) for v in views}
        for v in views:
            _, _, alone = evaluate_views(field, ts, [v], 8, **kw)
            pv = both["per_view"][str(v)]
            assert pv["margin_closed_pooled"] == pytest.approx(alone["margin_closed"]["pooled"], rel=1e-6)
            shift = 20 * np.log10(both["data_range"] / alone["data_range"])
            assert pv["psnr_pooled"] == pytest.approx(alone["continuous"]["psnr_pooled"] + shift, abs=1e-6)
            assert pv["zero_floor_pooled"] == pytest.approx(alone["zero_floor"]["psnr_pooled"] + shift, abs=1e-6)
        # a cached truth score renders no true images: each view then has no truth of its own
        _, _, cached = evaluate_views(field, ts, views, 8, truth_metrics=both["truth"], **kw)
        assert all("truth_pooled" not in pv for pv in cached["per_view"].values())
        assert cached["per_view"][str(views[0])]["psnr_pooled"] == both["per_view"][str(views[0])]["psnr_pooled"]


def _with_truth(src, dst, **changes):
    """A copy of training set ``src`` whose provenance truth record has ``changes``."""
    import json
    import shutil

    import h5py

    shutil.copy(src, dst)
    with h5py.File(dst, "r+") as f:
        prov = json.loads(f["provenance"][()])
        prov["truth"].update(changes)
        del f["provenance"]
        f["provenance"] = json.dumps(prov)
    return dst


def test_render_grid_joins_the_twins_renders_linearly(tiny_train_h5, tmp_path):
    """A camera twin that rendered every ``period`` only: on grid points the reference is the
    plain one; between them each pixel's log is linear, so half a grid step changes by half."""
    from evdnerf_ros.errors import EvdnerfError

    with TrainingSet(tiny_train_h5) as ts:
        views, origin = ts.views, ts.provenance["truth"]["scene_time_at_origin_ns"]
        t0 = ts.time_range[0]
    period = 40_000_000
    # grid points at common time t0 in every view (scene time t0 + origin)
    grid = {"period_ns": period, "scene_ns": {v: int(origin[v]) + int(t0) for v in views}}
    path = _with_truth(tiny_train_h5, tmp_path / "grid.h5", render_grid=grid)
    with TrainingSet(tiny_train_h5) as plain_set, TrainingSet(path) as grid_set:
        plain, _ = TrueScene.of(plain_set)
        twin, why = TrueScene.of(grid_set)
        assert twin is not None, why
        view = grid_set.val_views[0]
        a = int(t0) + 8 * period                    # mid-motion
        on_grid = [(a, a + period), (a + period, a + 3 * period)]
        np.testing.assert_allclose(twin.log_changes(view, on_grid), plain.log_changes(view, on_grid), atol=1e-6)
        [step] = plain.log_changes(view, [(a, a + period)])
        [half] = twin.log_changes(view, [(a, a + period // 2)])
        np.testing.assert_allclose(half, 0.5 * step, atol=1e-5)
        [exact_half] = plain.log_changes(view, [(a, a + period // 2)])
        assert np.abs(exact_half - 0.5 * step).max() > 0.05      # the motion is not linear in log
    del grid["scene_ns"][view]
    path = _with_truth(tiny_train_h5, tmp_path / "partial.h5", render_grid=grid)
    with TrainingSet(path) as grid_set:
        twin, _ = TrueScene.of(grid_set)
        with pytest.raises(EvdnerfError, match=f"view {view}: no render grid"):
            twin.log_changes(view, [(a, a + period)])


def test_convert_records_the_twins_render_grid():
    from evdnerf_ros.session.convert import _truth_record

    source = {"kind": "capture", "rig": "virtual", "scene_ref": "fork", "supersample": 1}
    views = {"a": {"offset_ns": 500, "ground_truth_clock_offset_ns": 200, "ground_truth_sensor_zero_scene_ns": -7},
             "b": {"offset_ns": 900, "ground_truth_clock_offset_ns": 100, "ground_truth_sensor_zero_scene_ns": 3}}
    record, why = _truth_record(source, views, None, frame_ns=8_000_000)
    assert why == "" and record["scene_time_at_origin_ns"] == {"a": 300, "b": 800}
    assert record["render_grid"] == {"period_ns": 8_000_000, "scene_ns": {"a": -7, "b": 3}}
    # a view without its sensor zero, or no render period: the reference renders at exact times
    views["b"]["ground_truth_sensor_zero_scene_ns"] = None
    assert "render_grid" not in _truth_record(source, views, None, frame_ns=8_000_000)[0]
    assert "render_grid" not in _truth_record(source, views, None)[0]
    # a simulated session renders every time it is asked
    assert "render_grid" not in _truth_record({"kind": "simulation", "scene_ref": "fork"}, views, None,
                                              frame_ns=8_000_000)[0]


def test_no_true_scene_where_the_twin_rendered_stale_joint_angles():
    """A view whose stream the virtual rig's camera twin rendered with stale joint angles (the
    harness fell behind real time) does not show the scene: no true scene for the set, saying which
    view and why; zero stale renders change nothing."""
    from evdnerf_ros.session.convert import _truth_record

    source = {"kind": "capture", "rig": "virtual", "scene_ref": "fork", "supersample": 1}
    views = {"a": {"offset_ns": 500, "ground_truth_clock_offset_ns": 200, "ground_truth_stale_renders": 0},
             "b": {"offset_ns": 900, "ground_truth_clock_offset_ns": 100, "ground_truth_stale_renders": 0}}
    assert _truth_record(source, views, None)[0] is not None
    views["b"]["ground_truth_stale_renders"] = 3
    record, why = _truth_record(source, views, None)
    assert record is None and "view(s) b (3)" in why and "stale joint angles" in why


class _Flicker(torch.nn.Module):
    """A fog whose grey swings with time (not linearly): the field interface, nothing learned."""

    def forward(self, x, t):
        return torch.full((x.shape[0],), 2.0), 0.4 + 0.3 * torch.sin(9.0 * t.reshape(-1)).expand(x.shape[0])

    def space_features(self, x):
        return x

    def decode(self, x, t):
        return self.forward(x, t)

    def decode_static(self, x):
        return self.forward(x, torch.zeros(1))


def test_a_frame_based_camera_in_training_and_evaluation(tiny_train_h5, tmp_path):
    """``camera_grid``: where the set records the twin's frame grid, a window edge is the two
    frames around it joined in log. Edges on the grid: exactly the exact-time renders (training
    loss and evaluation alike); edges between frames: the frames around them, weighted by where
    the edge falls; a set without a grid is unaffected, a damaged one is an error naming it."""
    from evdnerf_ros.errors import FormatError
    from evdnerf_ros.eval.evaluate import evaluate_views
    from evdnerf_ros.eval.truth import on_render_grid
    from evdnerf_ros.train.rays import RaySampler
    from evdnerf_ros.train.trainer import Trainer

    # on_render_grid: linear between grid times, each grid time rendered once
    calls = []

    def log_render(t):
        calls.append(t)
        return np.array([float(t) ** 2])

    image = on_render_grid(log_render, 10, 3)
    assert image(13)[0] == 169.0 and image(18)[0] == pytest.approx(0.5 * 169 + 0.5 * 529)
    assert image(-2)[0] == pytest.approx(0.5 * 49 + 0.5 * 9) and sorted(calls) == [-7, 3, 13, 23]

    with TrainingSet(tiny_train_h5) as ts:
        views, origin = ts.views, ts.provenance["truth"]["scene_time_at_origin_ns"]
        t0, t1 = ts.time_range
        assert all(ts.frame_grid(v) is None for v in views)
    n = 8
    assert (t1 - t0) % n == 0
    period = (t1 - t0) // n                        # one frame per window: every edge on the grid
    on_grid = _with_truth(tiny_train_h5, tmp_path / "on.h5", render_grid={
        "period_ns": period, "scene_ns": {v: int(origin[v]) + int(t0) + 3 * period for v in views}})
    off_grid = _with_truth(tiny_train_h5, tmp_path / "off.h5", render_grid={
        "period_ns": period, "scene_ns": {v: int(origin[v]) + int(t0) + period // 4 for v in views}})
    cfg = {"n_samples": 16, "rays": 64, "perturb": False, "windows": [n], "window_switch": [], "seed": 3}
    with TrainingSet(on_grid) as on_set, TrainingSet(off_grid) as off_set:
        assert on_set.frame_grid(views[0]) == (period, int(t0) + 3 * period)
    broken = _with_truth(tiny_train_h5, tmp_path / "broken.h5", render_grid={
        "period_ns": 0, "scene_ns": {v: int(origin[v]) for v in views}})
    with TrainingSet(broken) as ts, pytest.raises(FormatError, match=r"broken\.h5.*render_grid.*period > 0"):
        ts.frame_grid(views[0])
    with TrainingSet(on_grid) as on_set, TrainingSet(off_grid) as off_set:
        sampler = RaySampler(off_set, camera_grid=True, seed=1)
        sampler.set_windows(n)
        batch = sampler.sample(32)
        edges = off_set.normalized_time(window_edges(t0, t1, n)[[batch.window, batch.window + 1]])
        before, after = batch.grid_times[0::2].numpy(), batch.grid_times[1::2].numpy()
        assert np.all(before <= edges[:, None] + 1e-7) and np.all(after >= edges[:, None] - 1e-7)
        np.testing.assert_allclose(batch.grid_weights.numpy(), 0.75, atol=1e-6)   # a quarter frame past
        assert RaySampler(off_set, camera_grid=False).grids is None

        losses = []
        for grid in (True, False):
            tr = Trainer(on_set, dict(cfg, camera_grid=grid), iters=1, log=lambda m: None)
            tr.sampler.set_windows(n)
            torch.manual_seed(0)
            b = tr.sampler.sample(64)
            assert (b.grid_times is not None) == grid
            losses.append(float(tr.compute_loss(b).detach()))
        assert losses[0] == pytest.approx(losses[1], rel=1e-5)
        field = _Flicker()                           # a grey not linear in time: frames show it
        kw = dict(box=tr.box, n_samples=16, log_eps=tr.cfg.log_eps, background=tr.cfg.background)
        val = on_set.val_views[:1]
        pred_on, _, _ = evaluate_views(field, on_set, val, n, windows=range(n), **kw)
        pred_exact, _, _ = evaluate_views(field, on_set, val, n, windows=range(n), camera_grid=False, **kw)
        np.testing.assert_allclose(pred_on, pred_exact, atol=1e-6)
        pred_off, _, _ = evaluate_views(field, off_set, val, n, windows=range(n), **kw)
        assert np.abs(pred_off - pred_exact).max() > 1e-4
