"""Pixels that gather light over their area (``pixel_samples``): each pixel's brightness is the mean
of its s x s sub-pixel rays, the same in training, evaluation and publishing."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from evdnerf_ros.errors import InputError
from evdnerf_ros.field import make_field
from evdnerf_ros.field.render import camera_rays, finer, pixel_rays, render_image, render_rays, subpixels
from evdnerf_ros.field.renderer import FieldRenderer
from evdnerf_ros.geometry.camera import PinholeCamera, look_at
from evdnerf_ros.geometry.pose_track import PoseTrack
from evdnerf_ros.io.trainingset import TrainingSet
from evdnerf_ros.train import RaySampler, TrainConfig, Trainer, run_train
from evdnerf_ros.train.rays import camera_of
from evdnerf_ros.train.run import TrainedRun

SMALL_FIELD = dict(resolutions=[16, 32], time_resolution=8, features=8, hidden=32)
BOX = np.array([[-0.5, -0.5, -0.5], [0.5, 0.5, 0.5]])


def small_config(**kw):
    base = dict(backbone="planes", n_samples=16, rays=128, windows=[8], window_switch=[], field=SMALL_FIELD, lr=2e-2,
                lr_warmup_iters=10, log_every=0, eval_every=0, time_curriculum=0, checkpoint_every=0)
    base.update(kw)
    return TrainConfig(**base)


def test_subpixels_are_the_finer_cameras_pixels_over_each_pixel():
    cam = PinholeCamera(5, 3, 4.0, 4.5, 2.1, 0.9)
    for s in (1, 2, 3):
        idx = subpixels(cam.width, np.arange(cam.width * cam.height), s)
        assert idx.shape == (15, s * s) and np.array_equal(np.sort(idx.ravel()), np.arange(15 * s * s))
        fine = finer(cam, s).ray_directions(1).reshape(-1, 3)
        # the sub-pixel grid ray_directions(s) documents, pixel by pixel
        grid = cam.ray_directions(s).reshape(cam.height, s, cam.width, s, 3).transpose(0, 2, 1, 3, 4)
        np.testing.assert_allclose(fine[idx], grid.reshape(15, s * s, 3), atol=1e-12)
    # pixel (u=4, v=2) of a 5-wide image at s = 2: rows 4..5, columns 8..9 of a 10-wide one
    assert subpixels(5, [2 * 5 + 4], 2).tolist() == [[48, 49, 58, 59]]


@pytest.fixture(scope="module")
def field():
    torch.manual_seed(0)
    f = make_field("planes", **SMALL_FIELD)
    with torch.no_grad():       # a field with something in it: density and grey vary in space and time
        for p in f.parameters():
            p.add_(0.3 * torch.randn_like(p))
    return f.eval()


def test_render_image_averages_the_finer_cameras_image(field):
    cam = PinholeCamera(6, 4, 5.0, 5.0, 2.5, 1.5)
    T = look_at([0.0, -2.0, 0.3], [0, 0, 0])
    one = render_image(field, cam, T, 0.3, BOX, 16)
    two = render_image(field, cam, T, 0.3, BOX, 16, pixel_samples=2)
    fine = render_image(field, finer(cam, 2), T, 0.3, BOX, 16)
    assert two.shape == one.shape == (4, 6)
    torch.testing.assert_close(two, fine.reshape(4, 2, 6, 2).mean((1, 3)))
    assert float((two - one).abs().max()) > 1e-4        # not the centre ray's value


@pytest.mark.parametrize("compiled", [True, False])
def test_the_renderer_and_its_pixels_agree_with_render_image(field, compiled):
    cam = PinholeCamera(6, 4, 5.0, 5.0, 2.5, 1.5)
    T = look_at([0.0, -2.0, 0.3], [0, 0, 0])
    r = FieldRenderer(field, cam, BOX, duration_ns=10**9, n_samples=16, pixel_samples=2)
    r.compiled_rays = compiled
    img = r.render(T, 300_000_000)
    want = render_image(field, cam, T, 0.3, BOX, 16, pixel_samples=2).numpy()
    np.testing.assert_allclose(img, want, atol=2e-5)
    pixels = np.array([0, 7, 23, 11])
    got = r.render_pixels(T[None], np.array([300_000_000]), np.zeros(4, np.int64), pixels)
    np.testing.assert_allclose(got, want.reshape(-1)[pixels], atol=2e-5)
    with pytest.raises(InputError, match="pixel_samples must be 1..8"):
        FieldRenderer(field, cam, BOX, duration_ns=10**9, pixel_samples=0)


def test_a_batch_carries_each_pixels_subpixel_rays(sweep_h5):
    with TrainingSet(sweep_h5) as ts:
        sampler = RaySampler(ts, seed=3, pixel_samples=2)
        sampler.set_windows(8)
        b = sampler.sample(300, span_fraction=0.5)
        assert b.pixel_samples == 2 and b.origins.shape == b.dirs.shape == b.dirs_end.shape == (300, 4, 3)
        track = PoseTrack(*ts.poses("moving_00"))
        edges = sampler.edges[[b.window, b.window + b.span]]
        for i in np.unique(b.views):
            view = sampler.views[i]
            cam = finer(camera_of(ts.K(view), ts.width, ts.height), 2)
            sel = np.flatnonzero(b.views == i)
            sub = subpixels(ts.width, b.pixels[sel], 2)
            for d, edge in ((b.dirs, edges[0]), (b.dirs_end, edges[1])):
                pose = track.poses([int(edge)])[0] if view == "moving_00" else ts.pose(view)
                _, ref = camera_rays(cam, pose)
                torch.testing.assert_close(d[sel], ref[torch.as_tensor(sub)])
        # a moving view's sub-pixel rays as pixel_rays gives them through the finer camera
        sel = np.flatnonzero(b.moving.numpy())
        assert sel.size
        sub = subpixels(ts.width, b.pixels[sel], 2).reshape(-1)
        cam = finer(camera_of(ts.K("moving_00"), ts.width, ts.height), 2)
        _, ref = pixel_rays(cam, track.poses([int(edges[1])]), np.zeros(sub.size, np.int64), sub)
        torch.testing.assert_close(b.dirs_end[sel].reshape(-1, 3), ref)


def test_the_trainers_change_is_the_log_of_each_pixels_mean(sweep_h5):
    with TrainingSet(sweep_h5) as ts:
        tr = Trainer(ts, small_config(perturb=False, pixel_samples=2), iters=1, log=lambda *_: None)
        tr.sampler.set_windows(8)
        batch = tr.sampler.sample(128)
        m = batch.moving
        assert 0 < int(m.sum()) < 128
        kw = dict(box=tr.box, n_samples=tr.cfg.n_samples, background=tr.cfg.background, dynamic=tr.dynamic)
        eps = tr.cfg.log_eps

        def mean_log(r):
            return torch.log(r["grey"].reshape(-1, 4).mean(1) + eps)

        with torch.no_grad():
            got = tr.predicted_change(batch)
            r0 = render_rays(tr.field, batch.origins[m].reshape(-1, 3), batch.dirs[m].reshape(-1, 3), batch.t0, **kw)
            r1 = render_rays(tr.field, batch.origins_end[m].reshape(-1, 3), batch.dirs_end[m].reshape(-1, 3),
                             batch.t1, **kw)
            torch.testing.assert_close(got[m], mean_log(r1) - mean_log(r0))
            s0, s1 = render_rays(tr.field, batch.origins[~m].reshape(-1, 3), batch.dirs[~m].reshape(-1, 3),
                                 [batch.t0, batch.t1], changes_only=True, **kw)
            torch.testing.assert_close(got[~m], mean_log(s1) - mean_log(s0))


def test_a_run_with_pixel_samples_trains_evaluates_and_publishes_with_them(tiny_train_h5, tmp_path):
    run = tmp_path / "run"
    summary = run_train(tiny_train_h5, run, config=small_config(pixel_samples=2), iters=20, log=lambda *_: None)
    assert summary["iterations"] == 20 and np.isfinite(summary["loss"])
    loaded = TrainedRun.load(run)
    assert loaded.config.pixel_samples == 2
    with TrainingSet(tiny_train_h5) as ts:
        view = ts.val_views[0]
        cam = camera_of(ts.K(view), ts.width, ts.height)
        t0 = int(ts.time_range[0])
        r = loaded.renderer(cam, t_origin_ns=t0)
        assert r.pixel_samples == 2
        t = t0 + 30_000_000
        tn = float(ts.normalized_time(np.array([t], np.int64))[0])
        img = r.render(ts.pose(view), t)
        want = render_image(loaded.field, cam, ts.pose(view), tn, loaded.box, loaded.config.n_samples,
                            background=loaded.config.background, dynamic=loaded.dynamic, pixel_samples=2)
        np.testing.assert_allclose(img, want.numpy(), atol=2e-5)


def test_pixel_samples_range_and_what_it_cannot_train():
    for bad in (0, 9, 1.5):
        with pytest.raises(InputError, match="pixel_samples"):
            TrainConfig.from_dict({"pixel_samples": bad})
    with pytest.raises(InputError, match="pixel_samples: needs supervision: events"):
        TrainConfig.from_dict({"pixel_samples": 2, "supervision": "frames"})
    # a run saved before the key existed reads as one ray per pixel
    assert TrainConfig.from_dict({}, saved=True).pixel_samples == 1
