"""Training: losses, sampler, a tiny run, resume equality, NaN guard, metrics, checkpoints."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from evdnerf_ros.errors import InputError
from evdnerf_ros.train import (CheckpointError, RaySampler, TrainConfig, Trainer,
                               TrainingDivergedError, bin_loss, mse_loss, no_event_hinge,
                               run_train)
from evdnerf_ros.train.checkpoint import load_checkpoint

SMALL_FIELD = dict(resolutions=[16, 32], time_resolution=8, features=8, hidden=32)


def small_config(**kw):
    base = dict(backbone="planes", n_samples=24, rays=256, windows=[8], window_switch=[], field=SMALL_FIELD,
                lr=2e-2, lr_warmup_iters=10, log_every=0, eval_every=0, time_curriculum=0,
                checkpoint_every=0)
    base.update(kw)
    return TrainConfig(**base)


@pytest.fixture(scope="module")
def train_h5(tiny_train_h5):
    return tiny_train_h5


@pytest.fixture(scope="module")
def train_set(train_h5):
    from evdnerf_ros.io.trainingset import TrainingSet
    ts = TrainingSet(train_h5)
    yield ts
    ts.close()


# ------------------------------------------------------------------ losses
def test_bin_loss_hand_computed():
    c = 0.2
    dl = torch.tensor([0.4, 0.4, -0.2, 0.0, 0.0, 0.0])
    dl_hat = torch.tensor([0.5, 0.0, -0.3, 0.1, -0.1, 0.5])
    # bins: [0.4,0.6] in; [0.4,0.6] out -> (0-0.5)^2; [-0.4,-0.2] in; [-0.2,0.2] in, in;
    # 0.5 out of [-0.2, 0.2] -> (0.5 - 0)^2
    expect = (0.25 + 0.25) / 6
    assert float(bin_loss(dl_hat, dl, c, c)) == pytest.approx(expect, rel=1e-6)
    # paper variant: [dL, dL + C) for every sign; zero-event pixel only frees [0, C)
    # 0.5 in; 0 out -> 0.25; -0.3 out of [-0.2, 0) -> (-0.3 + 0.1)^2 = 0.04;
    # 0.1 in; -0.1 out -> (-0.1 - 0.1)^2 = 0.04; 0.5 out -> 0.16
    expect_p = (0.25 + 0.04 + 0.04 + 0.16) / 6
    assert float(bin_loss(dl_hat, dl, c, c, paper=True)) == pytest.approx(expect_p, rel=1e-5)
    # asymmetric thresholds: positive bin uses C+, negative C-
    assert float(bin_loss(torch.tensor([0.35]), torch.tensor([0.0]), 0.3, 0.1)) == \
        pytest.approx((0.35 - 0.1) ** 2, rel=1e-5)
    assert float(bin_loss(torch.zeros(0), torch.zeros(0), c, c)) == 0.0


def test_mse_and_hinge_hand_computed():
    dl = torch.tensor([0.4, 0.0, 0.0, -0.2])
    dl_hat = torch.tensor([0.2, 0.5, -0.1, -0.2])
    assert float(mse_loss(dl_hat, dl)) == pytest.approx((0.04 + 0.25 + 0.01) / 4, rel=1e-5)
    assert float(mse_loss(dl_hat, dl, 2.0, 0.4)) == pytest.approx(
        ((0.1 - 1) ** 2 + 0.25 ** 2 + 0.05 ** 2 + (0.1 - 0.5) ** 2) / 4, rel=1e-5)
    # no-event rays: 0.5 -> relu(0.5 - 0.2) = 0.3, -0.1 -> 0
    assert float(no_event_hinge(dl_hat, dl, 0.2, 0.2)) == pytest.approx(0.15, rel=1e-5)
    assert float(no_event_hinge(dl_hat[[0, 3]], dl[[0, 3]], 0.2, 0.2)) == 0.0


# ------------------------------------------------------------------ config
def test_config_yaml(tmp_path):
    p = tmp_path / "c.yaml"
    p.write_text("lr: 0.05\nwindows: [4, 8]\nwindow_switch: [0.5]\n")
    cfg = TrainConfig.load(p)
    assert cfg.lr == 0.05 and cfg.windows == [4, 8] and cfg.rays == TrainConfig().rays
    p.write_text("lr: 0.05\nlearning_rate: 1\n")
    with pytest.raises(InputError, match="learning_rate"):
        TrainConfig.load(p)
    with pytest.raises(InputError, match="window_switch"):
        TrainConfig(windows=[4, 8], window_switch=[])
    assert TrainConfig.from_dict(TrainConfig().to_dict()) == TrainConfig()


# ------------------------------------------------------------------ sampler
def test_sampler_proportions(train_set):
    s = RaySampler(train_set, event_ray_fraction=0.5, seed=3)
    s.set_windows(8)
    on, n, view_counts = 0, 0, np.zeros(len(s.views))
    dens = np.mean([s.event_pixels(v, k).size / s.P for v in range(len(s.views)) for k in range(8)])
    for _ in range(20):
        b = s.sample(200)
        half = b.on_event[:100].numpy()
        # every "event" ray whose view has events in the window is on an event pixel
        has = np.array([s.event_pixels(int(v), b.window).size > 0 for v in b.views[:100]])
        assert half[has].all()
        on += int(b.on_event.sum())
        n += 200
        view_counts += np.bincount(b.views, minlength=len(s.views))
        assert b.origins.shape == (200, 3) and b.dl.shape == (200,)
        assert b.on_event.numpy()[b.dl.numpy() != 0].all()   # a change needs events
    frac = on / n
    assert 0.4 <= frac <= 0.5 + 0.5 * dens + 0.08
    assert view_counts.min() > 0.7 * n / len(s.views)          # views uniform per ray


def test_sampler_spans(train_set):
    """A span batch's log change is the sum over its windows (what the events between its two
    edges give), its event rays lie on pixels that change in it, and the edges stay among
    the usable windows; span_fraction 0 draws exactly what it drew before spans existed."""
    from evdnerf_ros.events.slicing import window_edges

    s = RaySampler(train_set, event_ray_fraction=0.5, seed=4)
    s.set_windows(8)
    t0, t1 = train_set.time_range
    edges = window_edges(t0, t1, 8)
    spans = set()
    for _ in range(30):
        b = s.sample(300, usable_windows=6, span_fraction=1.0)
        assert 1 <= b.span and b.window + b.span <= 6
        spans.add(b.span)
        want = np.stack([train_set.log_change_stack(v, edges[[b.window, b.window + b.span]]).reshape(-1)
                         for v in s.views])[b.views, b.pixels]
        np.testing.assert_allclose(b.dl.numpy(), want, rtol=0, atol=1e-5)
        assert b.t0 == pytest.approx(b.window / 8) and b.t1 == pytest.approx((b.window + b.span) / 8)
        assert b.on_event.numpy()[b.dl.numpy() != 0].all()
        ev = b.on_event[:150].numpy()
        has = np.array([s.span_pixels(int(v), b.window, b.window + b.span).size > 0 for v in b.views[:150]])
        assert ev[has].all()
    assert len(spans) >= 3 and max(spans) > 1
    a, c = RaySampler(train_set, seed=9), RaySampler(train_set, seed=9)
    a.set_windows(8)
    c.set_windows(8)
    for _ in range(3):
        x, y = a.sample(64), c.sample(64, span_fraction=0.0)
        assert x.window == y.window and np.array_equal(x.pixels, y.pixels) and y.span == 1


def test_sampler_crop(train_set):
    s = RaySampler(train_set, event_ray_fraction=0.5, seed=1)
    s.set_windows(4)
    b = s.sample(400, crop=0.5)
    for v, p in zip(b.views[200:], b.pixels[200:]):
        x0, y0, w, h = s.crop_box(int(v), 0.5)
        assert w == h == 16
        assert x0 <= p % s.width < x0 + w and y0 <= p // s.width < y0 + h


def test_schedules(train_set):
    cfg = small_config(windows=[32, 64, 128], window_switch=[0.5, 0.75], time_curriculum=0.1,
                       lr=1.0, lr_warmup_iters=10, lr_warmup_start=0.1)
    tr = Trainer(train_set, cfg, iters=1000, log=lambda *_: None)
    assert [tr.n_windows(p) for p in (0.0, 0.49, 0.5, 0.74, 0.75, 1.0)] == [32, 32, 64, 64, 128, 128]
    assert tr.usable_windows(32, 0.0) == 3 and tr.usable_windows(32, 0.05) == 16
    assert tr.usable_windows(64, 0.1) == 64
    assert tr.lr() == pytest.approx(0.1)
    tr.iteration = 5
    assert tr.lr() == pytest.approx(0.55)
    tr.iteration = 10
    assert tr.lr() == 1.0


# ------------------------------------------------------------------ training
def test_tiny_run_loss_decreases(train_set):
    tr = Trainer(train_set, small_config(), iters=150, log=lambda *_: None)
    losses = []
    while not tr.done():
        losses.append(tr.step())
    first, last = np.mean(losses[:20]), np.mean(losses[-30:])
    assert last < 0.5 * first, (first, last)
    assert tr.skipped == 0


def test_empty_prior_hand_computed_and_it_clears_the_fog(train_set):
    """The sparsity prior is the mean opacity of one sample's length (constant density sigma:
    1 - exp(-sigma * diagonal / n_samples)); with it the trained field's density at random
    points of the box ends lower than without."""
    from evdnerf_ros.field import DynamicField

    class Constant(DynamicField):
        def forward(self, x, t):
            return torch.full((x.shape[0],), 2.0), torch.full((x.shape[0],), 0.5)

        def decode_static(self, x):
            return self.forward(x, None)

    tr = Trainer(train_set, small_config(empty_weight=1.0, empty_points=64), iters=1, log=lambda *_: None)
    tr.field = Constant()
    step = float(np.linalg.norm(tr.box[1] - tr.box[0])) / 24
    assert float(tr.empty_prior()) == pytest.approx(1 - np.exp(-2.0 * step), rel=1e-5)
    dens = {}
    x = torch.rand(2000, 3, generator=torch.Generator().manual_seed(0)) * 2 - 1
    for w in (0.0, 1.0):
        tr = Trainer(train_set, small_config(empty_weight=w), iters=40, log=lambda *_: None)
        tr.train()
        with torch.no_grad():
            dens[w] = float(tr.field.decode_static(tr.field.space_features(x))[0].mean())
    assert dens[1.0] < 0.5 * dens[0.0], dens


def test_resume_equals_uninterrupted_and_metrics(train_h5, train_set, tmp_path):
    cfg = small_config(rays=64, windows=[4, 8], window_switch=[0.5], eval_every=5,
                       time_curriculum=0.3, lr_warmup_iters=8, crop_warmup_iters=5,
                       no_event_weight=0.1, tv_weight=1e-3, time_smooth_weight=1e-3,
                       time_l1_weight=1e-3, occupancy_resolution=8, occupancy_warmup=3,
                       occupancy_every=4)
    calls = []

    def eval_fn(field, ctx):
        calls.append(ctx["iteration"])
        return {"val_psnr": 10.0 + ctx["iteration"]}

    a = run_train(train_h5, tmp_path / "A", config=cfg, iters=20, log=lambda *_: None,
                  eval_fn=eval_fn)
    assert a["iterations"] == 20 and not a["resumed"]
    def eval_b(field, ctx):
        return {"val_psnr": 10.0 + ctx["iteration"]}

    tr = Trainer(train_set, cfg, run_dir=tmp_path / "B", iters=20, log=lambda *_: None,
                 eval_fn=eval_b)
    (tmp_path / "B").mkdir()
    tr.train(until=10)
    assert load_checkpoint(tmp_path / "B" / "checkpoint.pt")["iteration"] == 10
    b = run_train(train_h5, tmp_path / "B", iters=20, log=lambda *_: None, eval_fn=eval_b)
    assert b["resumed"] and b["iterations"] == 20
    pa = load_checkpoint(tmp_path / "A" / "checkpoint.pt")["field"]
    pb = load_checkpoint(tmp_path / "B" / "checkpoint.pt")["field"]
    assert pa.keys() == pb.keys()
    for k in pa:
        assert torch.equal(pa[k], pb[k]), k
    # metrics.jsonl: valid JSON, increasing iter and wall_s, eval values present
    lines = [json.loads(s) for s in (tmp_path / "A" / "metrics.jsonl").read_text().splitlines()]
    assert [d["iter"] for d in lines] == [5, 10, 15, 20]
    walls = [d["wall_s"] for d in lines]
    assert all(b > a for a, b in zip(walls, walls[1:]))
    assert [d["val_psnr"] for d in lines] == [15.0, 20.0, 25.0, 30.0] and calls == [5, 10, 15, 20]
    assert lines[-1]["windows"] == 8 and lines[0]["windows"] == 4
    linesb = [json.loads(s) for s in (tmp_path / "B" / "metrics.jsonl").read_text().splitlines()]
    wb = [d["wall_s"] for d in linesb]
    assert all(y > x for x, y in zip(wb, wb[1:]))
    # the resumed run's lines equal the uninterrupted run's, wall-clock fields aside
    clock = ("wall_s", "elapsed_s")
    assert [{k: v for k, v in d.items() if k not in clock} for d in linesb] == \
        [{k: v for k, v in d.items() if k not in clock} for d in lines]


def test_checkpoint_errors(train_h5, train_set, tmp_path):
    cfg = small_config(rays=32)
    run_train(train_h5, tmp_path / "R", config=cfg, iters=2, log=lambda *_: None)
    ck = tmp_path / "R" / "checkpoint.pt"
    # config mismatch names the key
    with pytest.raises(CheckpointError, match="lr"):
        run_train(train_h5, tmp_path / "R", config=small_config(rays=32, lr=0.5), iters=4,
                  log=lambda *_: None)
    # other software major version
    data = load_checkpoint(ck)
    data["software_version"] = "99.0.0"
    bad = tmp_path / "bad.pt"
    torch.save(data, bad)
    with pytest.raises(CheckpointError, match="major"):
        load_checkpoint(bad)
    # init: weights only
    tr = Trainer(train_set, cfg, iters=5, log=lambda *_: None)
    tr.init_from(ck)
    for k, v in load_checkpoint(ck)["field"].items():
        assert torch.equal(tr.field.state_dict()[k], v)
    assert tr.iteration == 0
    with pytest.raises(CheckpointError, match="backbone and field"):
        Trainer(train_set, small_config(field=dict(SMALL_FIELD, features=4)), iters=5).init_from(ck)


def test_trained_run_reads_back_what_train_wrote(train_h5, train_set, tmp_path):
    """TrainedRun.load of a real run: config, iteration, weights, dynamic region and the
    training set's time span and thresholds, as eval and the publisher use them."""
    from evdnerf_ros.geometry.camera import look_at
    from evdnerf_ros.train.run import TrainedRun
    from evdnerf_ros.train.rays import camera_of

    cfg = small_config(rays=32, occupancy_resolution=8, occupancy_warmup=0, occupancy_every=1)
    r = run_train(train_h5, tmp_path / "R", config=cfg, iters=3, log=lambda *_: None)
    run = TrainedRun.load(tmp_path / "R")
    data = load_checkpoint(r["checkpoint"])
    assert run.iteration == 3 and run.config.diff(cfg) == [] and run.config.rays == 32
    np.testing.assert_array_equal(run.box, r["box"])
    for k, v in data["field"].items():
        assert torch.equal(run.field.state_dict()[k], v)
    assert run.time_range_ns == tuple(train_set.time_range)
    assert run.thresholds == pytest.approx(train_set.thresholds)
    assert run.dynamic is not None and torch.equal(run.dynamic.mask, data["extra"]["dynamic"])
    assert run.occupancy is not None and torch.equal(run.occupancy.occupied, data["extra"]["occupied"])
    cam = camera_of(train_set.K(), train_set.width, train_set.height)
    renderer = run.renderer(cam)
    assert renderer.duration_ns == train_set.duration_ns
    img = renderer.render(look_at([0.0, -4.0, 1.0], [0.0, 0.0, 0.0]), train_set.time_range[0])
    assert img.shape == (train_set.height, train_set.width) and np.all(np.isfinite(img))


def test_nan_guard(train_set):
    cfg = small_config(rays=32, max_nonfinite_steps=3)
    tr = Trainer(train_set, cfg, iters=100, log=lambda *_: None)
    poison = {"on": False}
    decode = tr.field.decode

    def bad_decode(feats, t):
        density, grey = decode(feats, t)
        if poison["on"]:
            grey = grey * float("nan")
        return density, grey

    tr.field.decode = bad_decode
    for _ in range(3):
        assert tr.step() is not None
    before = {k: v.clone() for k, v in tr.field.state_dict().items()}
    poison["on"] = True
    assert tr.step() is None and tr.step() is None
    assert tr.skipped == 2 and tr.iteration == 5
    for k, v in tr.field.state_dict().items():
        assert torch.equal(v, before[k])
    poison["on"] = False
    assert tr.step() is not None
    poison["on"] = True
    assert tr.step() is None           # 3 skips: still tolerated
    with pytest.raises(TrainingDivergedError, match="max_nonfinite_steps=3"):
        tr.step()


def test_minutes_budget_and_existing_run(train_h5, tmp_path):
    lines = []
    r = run_train(train_h5, tmp_path / "M", config=small_config(rays=32, log_every=1),
                  minutes=0.004, log=lines.append)
    assert r["iterations"] > 0 and r["wall_s"] >= 0.24 and any("ETA" in s for s in lines)
    with pytest.raises(InputError, match="--init"):
        run_train(train_h5, tmp_path / "M", iters=3, init=tmp_path / "M" / "checkpoint.pt",
                  log=lambda *_: None)
    r2 = run_train(train_h5, tmp_path / "M", config=small_config(rays=32), iters=2,
                   overwrite=True, log=lambda *_: None)
    assert r2["iterations"] == 2 and not r2["resumed"]


# ------------------------------------------------------------------ learned thresholds, reuse
def test_learned_thresholds_recover_the_balance(train_h5):
    """Declared thresholds 0.28/0.12 on data made with 0.2/0.2: the learned balance returns
    to the truth (the mean is kept: events fix log changes only up to one scale)."""
    from evdnerf_ros.io.trainingset import TrainingSet
    from evdnerf_ros.train.thresholds import LearnedThresholds

    lt = LearnedThresholds(0.3, 0.1)
    assert lt.values() == pytest.approx((0.3, 0.1))
    assert torch.allclose(lt.log_change(torch.tensor([[2, 1], [0, 3]])), torch.tensor([0.5, -0.3]))
    with TrainingSet(train_h5) as ts:
        true = ts.thresholds
        assert true == (0.2, 0.2)
        ts.c_pos, ts.c_neg = 0.28, 0.12
        tr = Trainer(ts, small_config(learn_thresholds=True, eval_every=100), iters=200,
                     log=lambda *_: None)
        tr.train()
        c_pos, c_neg = tr.thresholds.values()
    assert c_pos + c_neg == pytest.approx(0.4, abs=1e-6)
    assert abs(c_pos - 0.2) < 0.02, (c_pos, c_neg)


def test_learned_thresholds_resume_bit_exactly(train_h5, tmp_path):
    cfg = small_config(learn_thresholds=True, rays=64, checkpoint_every=5, eval_every=5)
    run_train(train_h5, tmp_path / "A", config=cfg, iters=10, log=lambda *_: None)
    run_train(train_h5, tmp_path / "B", config=cfg, iters=5, log=lambda *_: None)
    run_train(train_h5, tmp_path / "B", iters=10, log=lambda *_: None)
    a, b = (load_checkpoint(tmp_path / r / "checkpoint.pt") for r in "AB")
    assert torch.equal(a["extra"]["thresholds"]["balance"], b["extra"]["thresholds"]["balance"])
    assert a["extra"]["thresholds"]["balance"] != 0.0
    for k in a["field"]:
        assert torch.equal(a["field"][k], b["field"][k]), k
    line = json.loads((tmp_path / "A" / "metrics.jsonl").read_text().splitlines()[-1])
    assert line["c_pos"] + line["c_neg"] == pytest.approx(0.4, abs=1e-6)


def test_polarity_counts_match_log_changes(train_set):
    edges = np.linspace(*train_set.time_range, 9).astype(np.int64)
    v = train_set.train_views[0]
    counts = train_set.polarity_count_stack(v, edges)
    assert counts.shape == (8, train_set.height, train_set.width, 2) and counts.sum() > 0
    c_pos, c_neg = train_set.thresholds
    np.testing.assert_allclose(c_pos * counts[..., 0] - c_neg * counts[..., 1],
                               train_set.log_change_stack(v, edges), rtol=0, atol=1e-6)


def test_sample_reuse_switch_is_the_same_estimate(train_set):
    """Without jitter, rendering both window ends from shared samples and rendering them
    separately give the same loss; reuse only saves the repeated space work."""
    losses = []
    for reuse in (True, False):
        tr = Trainer(train_set, small_config(sample_reuse=reuse, perturb=False), iters=1,
                     log=lambda *_: None)
        tr.sampler.set_windows(8)
        batch = tr.sampler.sample(128)
        losses.append(float(tr.compute_loss(batch).detach()))
    assert losses[0] == pytest.approx(losses[1], rel=1e-5) and losses[0] > 0
