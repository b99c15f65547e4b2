"""Published-vs-true event metrics on a tiny scene, and the publisher's speed-up switches:
the leave-out switches change cost, not events; baking is an approximation within a stated
tolerance."""

import numpy as np
import pytest

from evdnerf_ros.events import make_events
from evdnerf_ros.eval.published import (event_image_stack, first_event_timing, published_vs_true, publisher_cost,
                                        side_by_side)


@pytest.fixture(scope="module")
def tiny_run(tiny_train_h5, tmp_path_factory):
    from evdnerf_ros.train.trainer import run_train

    run = tmp_path_factory.mktemp("pub_truth") / "run"
    run_train(tiny_train_h5, run, config={"backbone": "planes"}, iters=30, overwrite=True, log=lambda *_: None)
    return run


def test_event_images_and_first_event_timing_by_hand():
    edges = np.array([0, 100, 200], np.int64)
    true = make_events([10, 20, 150, 160], [1, 1, 0, 2], [0, 0, 1, 1], np.array([1, 1, -1, 1], np.int8))
    pub = make_events([15, 40, 170], [1, 1, 0], [0, 0, 1], np.array([1, -1, -1], np.int8))
    img = event_image_stack(true, edges, 3, 2, 0.2, 0.3)
    want = np.zeros((2, 2, 3), np.float32)
    want[0, 0, 1] = 0.4
    want[1, 1, 0] = -0.3
    want[1, 1, 2] = 0.2
    np.testing.assert_allclose(img, want, atol=1e-7)
    ft = first_event_timing(pub, true, edges, 3, 2)
    # true cells: (w0, x1, ON), (w1, x0 y1, OFF), (w1, x2 y1, ON); published: (w0, x1, ON), (w0, x1, OFF),
    # (w1, x0 y1, OFF): both = 2 (ON at 15 vs 10, OFF at 170 vs 150), either = 4
    assert (ft["cells_true"], ft["cells_published"], ft["cells_both"]) == (3, 3, 2)
    assert ft["matched"] == 0.5
    assert ft["median_abs_dt_us"] == pytest.approx(np.median([5, 20]) / 1e3)


def test_split_scores_by_the_moving_parts_cells():
    """Pooled scores on the moving parts' cells and on the rest, each against its own floor."""
    from evdnerf_ros.eval.published import split_scores
    from evdnerf_ros.events.types import EVENT_DTYPE

    rng = np.random.default_rng(0)
    true_img = rng.normal(0, 0.2, (4, 6, 5)).astype(np.float32)
    moving = np.zeros(true_img.shape, bool)
    moving[:, :3] = True
    pub = np.where(moving, true_img, 0).astype(np.float32)      # right on the moving parts, nothing elsewhere
    ev = np.zeros(3, EVENT_DTYPE)
    ev["t"], ev["x"], ev["y"], ev["p"] = [5, 15, 25], [0, 1, 2], [0, 4, 5], [1, -1, 1]
    edges = np.array([0, 10, 20, 30, 40], np.int64)
    s = split_scores(moving, pub, true_img, true_img, 1.0, ev[:1], ev, edges)
    assert s["moving_parts"]["cells"] == 0.5 and s["static_world"]["cells"] == 0.5
    assert s["moving_parts"]["margin_closed"] == pytest.approx(1.0)
    assert s["static_world"]["margin_closed"] == pytest.approx(0.0)
    assert (s["moving_parts"]["true_events"], s["static_world"]["true_events"]) == (1, 2)
    assert (s["moving_parts"]["published_events"], s["static_world"]["published_events"]) == (1, 0)


def test_published_vs_true_on_a_tiny_scene(tiny_run, tiny_train_h5, tmp_path):
    r = published_vs_true(tiny_run, tiny_train_h5, n_windows=8, static=True, duration_ns=300_000_000,
                          log=lambda *_: None)
    assert (r["width"], r["height"], r["windows"], r["path"]) == (32, 32, 8, "static")
    c = r["counts"]
    ref = r["reference"]["events"]
    assert c["true_on"] + c["true_off"] == ref.size > 0          # the fork moves: true events
    assert c["published_on"] + c["published_off"] == r["publisher"]["events"]
    for key in ("published", "zero_floor", "true_render"):
        assert np.isfinite(r[key]["psnr"]) and r[key]["mae"] >= 0
    # the true scene's own render explains its events far better than predicting nothing
    assert r["true_render"]["psnr"] > r["zero_floor"]["psnr"] + 3
    assert r["margin_closed"] is None or np.isfinite(r["margin_closed"])
    assert 0.0 <= r["first_events"]["matched"] <= 1.0
    # a still camera sees events of the moving parts only: (nearly) none fall in the static world's cells
    moving, world = r["split"]["moving_parts"], r["split"]["static_world"]
    assert moving["cells"] + world["cells"] == pytest.approx(1.0)
    assert 0 < moving["cells"] < 0.5 and moving["true_events"] + world["true_events"] <= ref.size
    assert world["true_events"] <= 0.08 * ref.size, r["split"]
    assert moving["published_events"] + world["published_events"] <= c["published_on"] + c["published_off"]
    assert r["publisher"]["rtf"] > 0 and r["publisher"]["samples_evaluated"] < r["publisher"]["samples_total"]
    # both image stacks, and the picture of the busiest true windows: true on top, published below
    assert r["images"]["true"].shape == r["images"]["published"].shape == (8, 32, 32)
    c_pos, c_neg = r["thresholds"]
    np.testing.assert_allclose(r["images"]["true"].sum(), c_pos * c["true_on"] - c_neg * c["true_off"], rtol=1e-4,
                               atol=2 * max(c_pos, c_neg))   # an event at the span's end is in no window
    picture = side_by_side(r, tmp_path / "pv.png", windows=3, upscale=2)
    import matplotlib.image

    rgb = matplotlib.image.imread(picture)[..., :3]
    assert rgb.shape == (2 * (2 * 32 + 2), 2 * (3 * 32 + 2 * 2), 3)
    assert (rgb[: 2 * 32] < 0.9).any(axis=-1).any()                 # the true windows are not blank
    # the truth can be reused (the benchmark's sweep): same reference, same scores for the same publisher
    again = published_vs_true(tiny_run, tiny_train_h5, n_windows=8, static=True, duration_ns=300_000_000,
                              true_reference=r["reference"], log=lambda *_: None)
    assert again["published"] == r["published"] and again["counts"] == r["counts"]
    # the publisher alone on the same path (no truth): the same renders and events, its own cost
    alone = publisher_cost(tiny_run, tiny_train_h5, static=True, duration_ns=300_000_000)
    assert (alone["events"], alone["renders"]) == (r["publisher"]["events"], r["publisher"]["renders"])
    assert alone["rtf"] > 0 and alone["wall_s"] > 0


def _publish(run, **params):
    from evdnerf_ros.eval.published import _collect

    return _collect({"run_dir": str(run), "camera.width": 24, "camera.height": 20, "realtime_factor": 0.0,
                     "field_duration": 1.0, "adaptive": False, "render_rate_hz": 400.0, "c_pos": 0.002,
                     "c_neg": 0.002, **params})


def _changing_run(tmp_path):
    """A planes field whose time planes vary (random), with a dynamic region and an occupancy grid."""
    import torch

    from evdnerf_ros.train.checkpoint import save_checkpoint
    from evdnerf_ros.train.config import TrainConfig, field_from_config

    cfg = TrainConfig(backbone="planes")
    torch.manual_seed(5)
    field = field_from_config(cfg)
    with torch.no_grad():
        for tp in field.time_planes:
            tp.uniform_(0.0, 3.0)
    dyn = torch.zeros((16, 16, 16), dtype=torch.bool)
    dyn[6:10, 6:10, 4:12] = True
    occ = torch.zeros((16, 16, 16), dtype=torch.bool)
    occ[3:13, 3:13, 2:14] = True
    run = tmp_path / "run"
    run.mkdir()
    ring = [np.array(look_at([3 * np.cos(a), 3 * np.sin(a), 0.5], [0, 0, 0])).tolist() for a in (0.0, 1.0, 2.0)]
    save_checkpoint(run / "checkpoint.pt", field=field, optimizer=None, iteration=0, config=cfg.to_dict(),
                    backbone=cfg.backbone, rng={}, box=[[-1, -1, -1], [1, 1, 1]],
                    extra={"dynamic": dyn, "occupied": occ, "train_set": {
                        "time_range_ns": [0, 10**9], "thresholds": [0.05, 0.05],
                        "camera": [24, 20, 30.0, 30.0, 11.5, 9.5], "ring": ring}})
    return run


def look_at(eye, target):
    from evdnerf_ros.geometry.camera import look_at as la

    return la(eye, target)


def test_leave_out_switches_change_cost_not_events(tmp_path):
    from evdnerf_ros.eval.published import _write_trajectory
    from evdnerf_ros.geometry.pose_track import PoseTrack
    from evdnerf_ros.train.run import TrainedRun

    tiny_run = _changing_run(tmp_path)
    t, T = TrainedRun.load(tiny_run).orbit(10**9)
    Tm = PoseTrack(t, T)(int((t[0] + t[1]) // 2))                 # a novel static view
    static = _write_trajectory(tmp_path / "static.yaml", [0, 250_000_000, 500_000_000], [Tm, Tm, Tm])
    runs = {}
    for name, sw in {"all": {}, "no_reuse": {"reuse_static": False}, "no_leave_out": {"leave_out": False},
                     "none": {"reuse_static": False, "leave_out": False}}.items():
        runs[name] = _publish(tiny_run, trajectory=str(static), **sw)
    ref = runs["none"][1]
    assert ref.size > 0
    for name, (rep, ev) in runs.items():
        np.testing.assert_array_equal(ev, ref, err_msg=name)        # the same events, exactly
    cost = {k: rep.samples_evaluated for k, (rep, _) in runs.items()}
    assert cost["all"] < 0.5 * cost["no_reuse"] and cost["no_reuse"] <= cost["none"]
    assert runs["none"][0].samples_total == runs["no_leave_out"][0].samples_total > runs["all"][0].samples_total
    assert runs["all"][0].rays_rendered < runs["no_leave_out"][0].rays_rendered
    # a moving camera cannot reuse, and still gets the same events with the switch on or off
    moving = _write_trajectory(tmp_path / "moving.yaml", t[:2], T[:2])
    a, b = (_publish(tiny_run, trajectory=str(moving), duration=0.05, trajectory_max_gap=2.0, reuse_static=s)
            for s in (True, False))
    np.testing.assert_array_equal(a[1], b[1])


def test_batched_renders_change_cost_not_events(tmp_path):
    """A static camera's midpoints rendered ahead in batches (``prefetch_levels``) feed the same
    frames: the same events, for the field and for it baked; ``render_times`` is K ``render``s."""
    from evdnerf_ros.eval.published import _write_trajectory
    from evdnerf_ros.geometry.pose_track import PoseTrack
    from evdnerf_ros.train.run import TrainedRun

    run = _changing_run(tmp_path)
    trained = TrainedRun.load(run)
    t, T = trained.orbit(10**9)
    Tm = PoseTrack(t, T)(int((t[0] + t[1]) // 2))
    static = _write_trajectory(tmp_path / "static.yaml", [0, 250_000_000], [Tm, Tm])
    for bake in (0, 16):
        renderer = trained.renderer(trained.train_camera, duration_ns=10**9, bake_resolution=bake)
        times = np.array([0, 130_000_000, 131_000_000, 700_000_000], np.int64)
        many = renderer.render_times(Tm, times)
        one = np.stack([renderer.render(Tm, int(ti)) for ti in times])
        assert many.shape == one.shape and not np.allclose(one[0], one[-1])     # the field changes
        np.testing.assert_allclose(many, one, rtol=1e-5, atol=1e-6, err_msg=f"bake {bake}")
        base = dict(trajectory=str(static), adaptive=True, min_step_ns=1_000_000, max_step_ns=16_000_000,
                    bake_resolution=bake)
        (r0, e0), (r3, e3) = (_publish(run, **base, prefetch_levels=k) for k in (0, 3))
        assert e0.size > 0
        np.testing.assert_array_equal(e3, e0, err_msg=f"bake {bake}")
        assert r3.renders > r0.renders          # frames rendered ahead that the refinement did not need
        # auto (-1, the default) on the CPU: batches for a baked field only; none without static reuse
        assert _publish(run, **base)[0].renders == (r3.renders if bake else r0.renders)
        assert _publish(run, **base, prefetch_levels=3, reuse_static=False)[0].renders == r0.renders


def test_baked_playback_is_close_to_the_field(tiny_run):
    """Baking is an approximation: at 48 vertices per axis the baked images stay within a mean
    0.02 / max 0.25 of the field's linear intensity (measured ~0.005 / ~0.1 on this run), and it
    evaluates no field sample at play time."""
    from evdnerf_ros.geometry.pose_track import PoseTrack
    from evdnerf_ros.train.run import TrainedRun

    run = TrainedRun.load(tiny_run)
    t, T = run.orbit(10**9)
    track = PoseTrack(t, T)
    cam = run.train_camera
    field = run.renderer(cam, duration_ns=10**9)
    baked = run.renderer(cam, duration_ns=10**9, bake_resolution=48)
    diffs = []
    for tt in np.linspace(0, 10**9, 7).astype(np.int64):
        a, b = field.render(track(int(tt)), int(tt)), baked.render(track(int(tt)), int(tt))
        diffs.append(np.abs(a - b))
    d = np.stack(diffs)
    assert d.mean() < 0.02 and d.max() < 0.25, (d.mean(), d.max())
    assert baked.field.n_times == 4 * (run.field.time_resolution - 1) + 1


def test_static_world_auto_is_flat_for_a_moving_camera_only(tmp_path):
    from evdnerf_ros.eval.published import _write_trajectory
    from evdnerf_ros.nodes.event_publisher import EventPublisher
    from evdnerf_ros.train.run import TrainedRun

    run = _changing_run(tmp_path)
    t, T = TrainedRun.load(run).orbit(10**9)
    static = _write_trajectory(tmp_path / "static.yaml", [0, 10**8], [T[0], T[0]])
    moving = _write_trajectory(tmp_path / "moving.yaml", t[:2], T[:2])

    def world(traj, **params):
        node = EventPublisher(("--ros-args", "--log-level", "warn"), dds=False, overrides={
            "run_dir": str(run), "trajectory": str(traj), "trajectory_max_gap": 2.0, "field_duration": 1.0,
            **params})
        with node:
            return node.source.static_world

    assert world(static) == "field"
    assert world(moving) == "flat"
    assert world(moving, duration=1e-9) == "flat"        # moving within the span, however short
    assert world(moving, static_world="field") == "field"
    assert world(static, static_world="flat") == "flat"


def test_resolve_static_world():
    from evdnerf_ros.field.renderer import resolve_static_world

    assert resolve_static_world("auto", moving=True, has_region=True) == "flat"
    assert resolve_static_world("auto", moving=False, has_region=True) == "field"
    assert resolve_static_world("auto", moving=True, has_region=False) == "field"    # nothing to keep
    assert resolve_static_world("flat", moving=False, has_region=True) == "flat"
    assert resolve_static_world("field", moving=True, has_region=True) == "field"


def test_per_pixel_sampling_follows_a_moving_camera_only(tmp_path):
    """``per_pixel`` auto: a moving camera refines its time steps pixel by pixel, rendering far
    fewer pixel values than whole images for events close to theirs; a static camera keeps whole
    images (their static part is reused)."""
    from evdnerf_ros.eval.published import _write_trajectory
    from evdnerf_ros.train.run import TrainedRun

    run = _changing_run(tmp_path)
    t, T = TrainedRun.load(run).orbit(10**9)
    moving = _write_trajectory(tmp_path / "moving.yaml", t[:2], T[:2])
    kw = dict(trajectory=str(moving), duration=0.04, trajectory_max_gap=2.0, adaptive=True)
    pix, pix_ev = _publish(run, **kw)
    img, img_ev = _publish(run, per_pixel="false", **kw)
    assert pix.pixels_rendered > 0 and img.pixels_rendered == 0
    assert pix.pixels_rendered < 0.5 * img.renders * 24 * 20
    assert img_ev.size > 50 and abs(pix_ev.size - img_ev.size) <= 0.2 * img_ev.size, (pix_ev.size, img_ev.size)
    static = _write_trajectory(tmp_path / "static.yaml", [0, 10**8], [T[0], T[0]])
    still, _ = _publish(run, trajectory=str(static), duration=0.04, adaptive=True)
    assert still.pixels_rendered == 0 and still.renders > 0


def test_motion_guard_keeps_a_fast_camera_s_events(tmp_path):
    """A camera swinging between two ring views (120 degrees) in 5 ms: per-pixel sampling without
    the motion guard (``max_travel_px`` 0) trusts three renders over pieces the view sweeps far
    across and loses events (64 of 4 309, measured); with the guard (default) it gets within a few
    of whole images at the finest step."""
    from evdnerf_ros.eval.published import _write_trajectory
    from evdnerf_ros.train.run import TrainedRun

    run = _changing_run(tmp_path)
    t, T = TrainedRun.load(run).orbit(10**9)
    fast = _write_trajectory(tmp_path / "fast.yaml", [0, 5_000_000], T[:2])
    kw = dict(trajectory=str(fast), duration=0.005, adaptive=True, field_duration=1.0)
    dense, dense_ev = _publish(run, per_pixel="false", max_step_ns=100_000, **kw)
    guarded, guarded_ev = _publish(run, **kw)
    blind, blind_ev = _publish(run, max_travel_px=0.0, **kw)
    assert guarded.pixels_rendered > blind.pixels_rendered > 0
    assert abs(guarded_ev.size - dense_ev.size) < 0.25 * abs(blind_ev.size - dense_ev.size), \
        (guarded_ev.size, blind_ev.size, dense_ev.size)


def test_the_chunks_pose_grid_and_rendering_ahead_change_cost_not_events(tmp_path, monkeypatch):
    """Per-pixel sampling of a moving camera looks its poses up on the chunk's sampling grid (made at
    once, ``_plan_poses``) instead of interpolating the trajectory at every render: the same events as
    without the grid; and chunks that are whole multiples of ``max_step_ns`` give the same events
    whatever their length and however many of them are sampled in one go (``render_ahead``: fewer,
    larger renders), published chunk by chunk as before."""
    from evdnerf_ros.eval.published import _write_trajectory
    from evdnerf_ros.geometry.pose_track import PoseTrack
    from evdnerf_ros.nodes import event_publisher
    from evdnerf_ros.train.run import TrainedRun

    run = _changing_run(tmp_path)
    t, T = TrainedRun.load(run).orbit(10**9)
    moving = _write_trajectory(tmp_path / "moving.yaml", t[:2], T[:2])
    kw = dict(trajectory=str(moving), duration=0.04, trajectory_max_gap=2.0, adaptive=True, max_step_ns=5_000_000,
              render_ahead=0.0)
    calls = []
    real = PoseTrack.poses
    monkeypatch.setattr(PoseTrack, "poses", lambda self, times: calls.append(len(times)) or real(self, times))
    grid, grid_ev = _publish(run, chunk=0.01, **kw)
    with_grid = len(calls)
    monkeypatch.setattr(event_publisher, "POSE_GRID_MAX", 0)
    calls.clear()
    plain, plain_ev = _publish(run, chunk=0.01, **kw)
    assert grid_ev.size > 50 and plain.renders == grid.renders > 8
    np.testing.assert_array_equal(grid_ev, plain_ev)
    # four chunks, each rendered in a few calls that no longer interpolate: one grid per chunk instead
    assert len(calls) - with_grid >= 4, (with_grid, len(calls))
    # a chunk that is no whole number of steps: the grid's last point is the chunk's end
    _, odd_plain = _publish(run, chunk=0.01, **{**kw, "min_step_ns": 300_000})
    monkeypatch.setattr(event_publisher, "POSE_GRID_MAX", 1 << 14)
    _, odd_grid = _publish(run, chunk=0.01, **{**kw, "min_step_ns": 300_000})
    np.testing.assert_array_equal(odd_grid, odd_plain)
    batches = []
    real_render = event_publisher.EventPublisher.render_pixels
    monkeypatch.setattr(event_publisher.EventPublisher, "render_pixels",
                        lambda self, t_ns, pixels: batches.append(pixels.size) or real_render(self, t_ns, pixels))
    render_calls, messages = {}, {}
    for chunk, ahead in ((0.01, 0.0), (0.02, 0.0), (0.01, 0.02), (0.01, 0.04), (0.01, -1.0)):
        batches.clear()
        rep, ev = _publish(run, chunk=chunk, **{**kw, "render_ahead": ahead})
        np.testing.assert_array_equal(ev, grid_ev)
        assert rep.render_calls == len(batches)        # the report counts the calls (a batch is one)
        render_calls[chunk, ahead], messages[chunk, ahead] = len(batches), rep.messages
    # sampled ahead, still published chunk by chunk: the same messages as one chunk at a time
    assert messages[0.01, 0.0] == messages[0.01, 0.02] == messages[0.01, 0.04] == messages[0.01, -1.0] > 4
    # longer chunks, or chunks sampled ahead: fewer, larger render calls (auto: the whole 40 ms at once)
    # rays per batch: cost, not events
    # (a batch of another size may round a matrix product differently: an event whose crossing lies
    # within float precision of a sampling step may move by one adaptive step, nothing more)
    _, small_batches = _publish(run, chunk=0.01, **{**kw, "ray_chunk": 37})
    assert small_batches.size == grid_ev.size
    moved = small_batches != grid_ev
    assert moved.sum() <= max(1, grid_ev.size // 100), moved.sum()
    for name in ("x", "y", "p"):
        np.testing.assert_array_equal(small_batches[name], grid_ev[name])
    assert np.abs(small_batches["t"].astype(np.int64) - grid_ev["t"].astype(np.int64)).max() <= kw["max_step_ns"]
    c = render_calls
    assert c[0.01, 0.0] > c[0.02, 0.0] == c[0.01, 0.02] > c[0.01, 0.04] == c[0.01, -1.0], c
