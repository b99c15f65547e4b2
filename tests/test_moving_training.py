"""Training on a moving view: its rays at each window edge from its trajectory, its change rendered
from two rays with the world whole; what it cannot train with."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from evdnerf_ros.errors import InputError
from evdnerf_ros.field.render import pixel_rays, render_rays
from evdnerf_ros.geometry.pose_track import PoseTrack
from evdnerf_ros.io.trainingset import TrainingSet
from evdnerf_ros.train import RaySampler, TrainConfig, Trainer, run_train
from evdnerf_ros.train.rays import FrameSampler, camera_of
from evdnerf_ros.train.run import TrainedRun

SMALL_FIELD = dict(resolutions=[16, 32], time_resolution=8, features=8, hidden=32)


def small_config(**kw):
    base = dict(backbone="planes", n_samples=16, rays=256, windows=[8], window_switch=[], field=SMALL_FIELD, lr=2e-2,
                lr_warmup_iters=10, log_every=0, eval_every=0, time_curriculum=0, checkpoint_every=0)
    base.update(kw)
    return TrainConfig(**base)


@pytest.fixture(scope="module")
def sweep_set(sweep_h5):
    with TrainingSet(sweep_h5) as ts:
        yield ts


def test_a_moving_views_rays_follow_its_trajectory_at_each_window_edge(sweep_set):
    ts = sweep_set
    sampler = RaySampler(ts, seed=3)
    sampler.set_windows(8)
    assert sampler.views[-1] == "moving_00" and sampler.moving.tolist() == [False] * 4 + [True]
    track = PoseTrack(*ts.poses("moving_00"))
    cam = camera_of(ts.K("moving_00"), ts.width, ts.height)
    seen = 0
    for _ in range(6):
        b = sampler.sample(200, span_fraction=0.5)
        moving = b.moving.numpy()
        assert np.array_equal(moving, b.views == 4)
        # a static view's ray is the same at both edges, and the one its view_rays give
        assert torch.equal(b.origins_end[~b.moving], b.origins[~b.moving])
        assert torch.equal(b.dirs_end[~b.moving], b.dirs[~b.moving])
        sel = np.flatnonzero(moving)
        seen += sel.size
        if not sel.size:
            continue
        edges = sampler.edges[[b.window, b.window + b.span]]
        for (o, d), edge in (((b.origins, b.dirs), edges[0]), ((b.origins_end, b.dirs_end), edges[1])):
            ref_o, ref_d = pixel_rays(cam, track.poses([int(edge)]), np.zeros(sel.size, np.int64), b.pixels[sel])
            torch.testing.assert_close(o[sel], ref_o)
            torch.testing.assert_close(d[sel], ref_d)
        # the camera turns between the edges: the rays differ
        assert float((b.dirs_end[sel] - b.dirs[sel]).norm(dim=1).min()) > 0
    assert seen > 100


def test_a_moving_views_change_is_two_rays_rendered_whole(sweep_set):
    """The trainer's change of a moving view's ray is the field at the end ray and time minus at the
    start ray and time, the world whole (not only what a dynamic region holds), and a static
    view's ray in the same batch is rendered as before (shared samples, changes only)."""
    tr = Trainer(sweep_set, small_config(perturb=False), iters=1, log=lambda *_: None)
    assert tr.dynamic is not None
    tr.sampler.set_windows(8)
    batch = tr.sampler.sample(256)
    m = batch.moving
    assert 0 < int(m.sum()) < 256
    with torch.no_grad():
        got = tr.predicted_change(batch)
        kw = dict(box=tr.box, n_samples=tr.cfg.n_samples, background=tr.cfg.background,
                  dynamic=tr.dynamic)
        r0 = render_rays(tr.field, batch.origins[m], batch.dirs[m], batch.t0, **kw)
        r1 = render_rays(tr.field, batch.origins_end[m], batch.dirs_end[m], batch.t1, **kw)
        eps = tr.cfg.log_eps
        want = torch.log(r1["grey"] + eps) - torch.log(r0["grey"] + eps)
        torch.testing.assert_close(got[m], want)
        s0, s1 = render_rays(tr.field, batch.origins[~m], batch.dirs[~m], [batch.t0, batch.t1],
                             changes_only=True, **kw)
        torch.testing.assert_close(got[~m], torch.log(s1["grey"] + eps) - torch.log(s0["grey"] + eps))
        # the camera moves: its rays change even where the field is still
        assert float(got[m].abs().max()) > 0


def test_training_on_a_moving_view_runs(sweep_h5, tmp_path):
    run = tmp_path / "run"
    summary = run_train(sweep_h5, run, config=small_config(), iters=40, log=lambda *_: None)
    assert summary["iterations"] == 40 and summary["skipped"] == 0 and np.isfinite(summary["loss"])
    loaded = TrainedRun.load(run)
    # its ring holds only the static training views (the orbit a publisher plays by default)
    assert len(loaded.ring) == 4


def test_what_a_moving_view_cannot_train(sweep_set):
    ts = sweep_set

    class Altered:
        """The set with some of its methods replaced."""

        def __init__(self, **methods):
            self.__dict__.update(methods)

        def __getattr__(self, name):
            return getattr(ts, name)

    with pytest.raises(InputError, match="moving_00.*moving camera"):
        FrameSampler(ts)
    # the twin's frame grid is a static camera's: refused with a moving view
    with pytest.raises(InputError, match="camera_grid with a moving training view \\(moving_00\\)"):
        RaySampler(Altered(frame_grid=lambda view: (8_000_000, 0)), camera_grid=True)
    # a trajectory that stops before the set's time range ends: refused at once, by name
    t, T = ts.poses("moving_00")
    keep = t < t[0] + (t[-1] - t[0]) // 2
    short = Altered(poses=lambda view: (t[keep], T[keep]) if view == "moving_00" else ts.poses(view))
    with pytest.raises(InputError, match="view moving_00's camera trajectory covers .* not the set's time range"):
        RaySampler(short)
