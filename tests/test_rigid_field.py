"""The ``rigid`` field: a static world and one rigid part whose pose is learned from the events."""

import numpy as np
import pytest
import torch

from conftest import NoEvents
from evdnerf_ros.errors import InputError
from evdnerf_ros.field import RigidField, make_field
from evdnerf_ros.field.rigid import rotate
from evdnerf_ros.geometry.rotations import quat_from_axis_angle, quat_to_matrix

BOX = np.array([[-1.5, -1.0, -1.3], [1.5, 1.2, 0.8]])
HALF = (BOX[1] - BOX[0]) / 2


def _normalise(p):
    return (np.asarray(p) - BOX[0]) / (BOX[1] - BOX[0]) * 2.0 - 1.0


def _metres(x):
    return (np.asarray(x) + 1.0) / 2.0 * (BOX[1] - BOX[0]) + BOX[0]


def axis_angle_to_matrix(axis, angle):
    return quat_to_matrix(quat_from_axis_angle(axis, angle))


def _track(centres_m):
    return {"centre": _normalise(centres_m).tolist(), "half": HALF.tolist(), "radius": 0.9}


@pytest.fixture(scope="module")
def tiny_jet_h5(tmp_path_factory):
    """Jet-Down at 32x32, 6 training views + 1 validation view, 1 s (built once)."""
    from evdnerf_ros.session.convert import run_convert
    from evdnerf_ros.sim.simulate import SimulationOptions, simulate_session

    tmp = tmp_path_factory.mktemp("tiny_jet")
    simulate_session("jet-down", tmp / "s", SimulationOptions(
        views=6, val_views=1, resolution=(32, 32), frame_rate_hz=20, blur_samples=2, gt_times=0,
        supersample=2, jobs=1, min_step_ns=2_000_000), log=lambda *_: None)
    run_convert(tmp / "s", tmp / "t.h5", offsets="ground-truth", log=lambda *_: None)
    return tmp / "t.h5"


def test_rotate_is_rodrigues_and_smooth_at_zero():
    gen = torch.Generator().manual_seed(0)
    w = torch.randn(20, 3, generator=gen)
    r = torch.randn(20, 3, generator=gen)
    want = np.stack([axis_angle_to_matrix(ri / np.linalg.norm(ri), np.linalg.norm(ri)) @ wi
                     for wi, ri in zip(w.double().numpy(), r.double().numpy())])
    np.testing.assert_allclose(rotate(w, r).numpy(), want, atol=1e-5)
    zero = torch.zeros(20, 3, requires_grad=True)
    out = rotate(w, zero)
    torch.testing.assert_close(out, w)
    out.sum().backward()
    assert torch.isfinite(zero.grad).all() and zero.grad.abs().sum() > 0   # a first rotation has a gradient


@pytest.mark.parametrize("t", [0.0, 0.25, 0.6, 1.0])
def test_part_frame_undoes_the_pose(t):
    """A canonical point of the part, carried by the field's own pose (centre moving, turning about
    one axis) to time t, maps back to where it sits in the part's frame (rigid in metres in an
    anisotropic box)."""
    field = RigidField(_track([[0.1, 0.0, 0.6], [0.0, 0.2, -0.2], [-0.1, 0.1, -0.6]]), resolutions=[4], features=2)
    axis = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    angles = [0.0, 0.4, 1.1]
    with torch.no_grad():
        field.rotation.copy_(torch.tensor(np.outer(angles, axis), dtype=torch.float32))
    c = np.array([np.interp(t, [0, 0.5, 1], _metres(field.centre.detach().numpy())[:, i]) for i in range(3)])
    R = axis_angle_to_matrix(axis, np.interp(t, [0, 0.5, 1], angles))
    canonical = np.array([[0.0, 0.1, 0.3], [0.05, -0.12, -0.4], [0.3, 0.0, 0.0]])   # metres from the centre
    world = c + canonical @ R.T
    back = field.part_frame(torch.tensor(_normalise(world), dtype=torch.float32), torch.full((3,), t))
    np.testing.assert_allclose(back.detach().numpy() * 0.9, canonical, atol=1e-5)


def test_the_part_moves_with_its_track_and_the_world_stays():
    field = make_field("rigid", track=_track([[0.0, 0.0, 0.5], [0.0, 0.0, -0.5]]), seed=3)
    x = torch.rand(400, 3) * 2 - 1
    feats = field.space_features(x)
    d0, _ = field.decode(feats, torch.tensor([0.0]))
    d1, _ = field.decode(feats, torch.tensor([1.0]))
    assert not torch.allclose(d0, d1)
    ds, _ = field.decode_static(feats)
    assert torch.all(d0 >= ds) and torch.all(d1 >= ds)
    torch.testing.assert_close(field(x, torch.full((400, 1), 1.0)), field.decode(feats, torch.tensor([1.0])))
    still = make_field("rigid", track=_track([[0.0, 0.0, 0.2], [0.0, 0.0, 0.2]]), seed=3)
    f = still.space_features(x)
    torch.testing.assert_close(still.decode(f, torch.tensor([0.1]))[0], still.decode(f, torch.tensor([0.9]))[0])


@pytest.mark.parametrize("bad, why", [({"centre": [[0.0, 0.0, 0.0]]}, ">= 2 finite rows"),
                                      ({"centre": [[0.0, 0.0], [1.0, 1.0]]}, "rows of 3"),
                                      ({"centre": [[0, 0, 0], [0, float("nan"), 0]]}, "finite"),
                                      ({"half": [1, 0, 1]}, "> 0"), ({"radius": 0.0}, "radius")])
def test_a_bad_track_is_a_clear_error(bad, why):
    with pytest.raises(ValueError, match=why):
        RigidField({**_track([[0, 0, 0], [0, 0, 1]]), **bad})
    with pytest.raises(ValueError, match="pose_lr_scale"):
        RigidField(_track([[0, 0, 0], [0, 0, 1]]), pose_lr_scale=-1.0)


def test_the_track_from_the_events_follows_the_jet(tiny_jet_h5):
    """The centroid of each time bin's visual hull of the events lies near the jet's centre then
    (the scene's own keyframes: the jet falls 1.6 m in 1 s)."""
    from evdnerf_ros.io.trainingset import TrainingSet
    from evdnerf_ros.sim.scene import load_scene
    from evdnerf_ros.train.track import track_from_events

    scene = load_scene("jet-down", check_cameras=False)
    box = np.array([[-1.4] * 3, [1.4] * 3])
    with TrainingSet(tiny_jet_h5) as ts:
        track = track_from_events(ts, box, knots=9, resolution=32)
        origin = int(np.median([int(v) for v in ts.provenance["truth"]["scene_time_at_origin_ns"].values()]))
        t0, t1 = (int(v) for v in ts.time_range)
    centre = (np.asarray(track["centre"]) + 1.0) / 2.0 * 2.8 - 1.4
    for k in (2, 4, 6):
        t = t0 + round(k / 8 * (t1 - t0)) + origin
        true = scene.transforms(t)["jet"][:3, 3]
        assert np.linalg.norm(centre[k] - true) < 0.15, (k, centre[k], true)
    assert centre[0, 2] - centre[-1, 2] > 1.0           # it fell
    assert track["half"] == pytest.approx([1.4, 1.4, 1.4])
    assert 0.6 < track["radius"] < 1.2          # the jet reaches ~0.66 m from its centre


def test_a_set_without_a_moving_part_says_to_train_planes(tiny_jet_h5):
    from evdnerf_ros.io.trainingset import TrainingSet
    from evdnerf_ros.train.track import track_from_events

    box = np.array([[-1.4] * 3, [1.4] * 3])
    with TrainingSet(tiny_jet_h5) as ts:
        with pytest.raises(InputError, match=r"t\.h5: backbone rigid found no moving part.*backbone planes"):
            track_from_events(NoEvents(ts), box, resolution=16)


def test_a_rigid_run_learns_its_poses_slower_saves_and_loads(tiny_jet_h5, tmp_path):
    from evdnerf_ros.io.trainingset import TrainingSet
    from evdnerf_ros.train.config import TrainConfig, field_from_config
    from evdnerf_ros.train.ranges import field_parameters
    from evdnerf_ros.train.run import TrainedRun
    from evdnerf_ros.train.trainer import Trainer, run_train

    cfg = {"backbone": "rigid", "rays": 64, "n_samples": 16, "eval_every": 0, "log_every": 0,
           "lr_warmup_iters": 0, "lr_final": 1.0,
           "field": {"resolutions": [8, 16], "features": 4, "pose_lr_scale": 0.25}}
    given = TrainConfig.from_dict(cfg)
    with TrainingSet(tiny_jet_h5) as ts:
        tr = Trainer(ts, given, iters=4, log=lambda *_: None)
        start = tr.field.centre.detach().clone()
        tr.train()
    assert "track" in tr.cfg.field and "track" not in given.field
    assert field_parameters(tr.cfg) == sum(p.numel() for p in tr.field.parameters())
    pose_group = [g for g in tr.opt.param_groups if any(p is tr.field.centre for p in g["params"])]
    assert len(pose_group) == 1 and pose_group[0]["lr"] == pytest.approx(0.25 * tr.lr())
    assert not torch.equal(tr.field.centre.detach(), start)          # the track is learned
    run_train(tiny_jet_h5, tmp_path / "run", config=cfg, iters=3, log=lambda *_: None, device="cpu")
    run = TrainedRun.load(tmp_path / "run")
    assert isinstance(run.field, RigidField) and "track" in (tmp_path / "run" / "config.yaml").read_text()
    fresh = field_from_config(run.config)
    fresh.load_state_dict(run.field.state_dict())
    x = torch.rand(50, 3) * 2 - 1
    with torch.no_grad():
        torch.testing.assert_close(fresh(x, torch.full((50, 1), 0.4)), run.field(x, torch.full((50, 1), 0.4)))


def test_rigid_takes_its_own_defaults_for_samples_and_decay_unless_given():
    """``n_samples`` and ``lr_final`` default per backbone (rigid: 64, 0.1); a given value (or
    none at all, null) wins or falls back the same way however the config is built."""
    import yaml

    from evdnerf_ros.train.config import TrainConfig

    assert (TrainConfig(backbone="planes").n_samples, TrainConfig(backbone="planes").lr_final) == (48, 1.0)
    assert (TrainConfig(backbone="rigid").n_samples, TrainConfig(backbone="rigid").lr_final) == (64, 0.1)
    assert TrainConfig(backbone="rigid", n_samples=32).n_samples == 32
    assert (TrainConfig(backbone="hinge").n_samples, TrainConfig(backbone="hinge").lr_final) == (48, 0.1)
    cfg = TrainConfig.from_dict({"backbone": "rigid", "lr_final": 0.5, "n_samples": None})
    assert (cfg.n_samples, cfg.lr_final) == (64, 0.5)
    assert TrainConfig.from_dict({"n_samples": 24}).n_samples == 24
    saved = yaml.safe_load(TrainConfig.from_dict({"backbone": "rigid"}).dump())
    assert (saved["n_samples"], saved["lr_final"]) == (64, 0.1)     # a run's config says what it used
    with pytest.raises(InputError, match="lr_final"):
        TrainConfig.from_dict({"backbone": "rigid", "lr_final": 2.0})


def test_rigid_training_beats_the_zero_floor_on_the_validation_view(tiny_jet_h5, tmp_path):
    """Jet-Down at 32x32 from 6 views: the rigid field (its track from the events, learned on)
    lands clearly above the floor on the validation view in 300 iterations."""
    import json

    from evdnerf_ros.eval.evaluate import validation_eval
    from evdnerf_ros.train.trainer import run_train

    cfg = {"backbone": "rigid", "n_samples": 32, "rays": 512, "windows": [16], "window_switch": [],
           "eval_every": 300, "checkpoint_every": 0}
    run_train(tiny_jet_h5, tmp_path / "run", config=cfg, iters=300, log=lambda *_: None,
              eval_fn=validation_eval(n_windows=16), device="cpu")
    line = json.loads((tmp_path / "run" / "metrics.jsonl").read_text().splitlines()[-1])
    assert line["val_psnr"] > line["val_psnr_zero_floor"] + 1.0, line
    assert line["val_margin_closed"] > 0.2, line
