"""The ``hinge`` field: a static world and one rigid part on the rig's known joint."""

import numpy as np
import pytest
import torch

from evdnerf_ros.errors import InputError
from evdnerf_ros.field import HingeField, make_field
from evdnerf_ros.sim.scene import load_scene

BOX = np.array([[-1.5, -1.0, -1.3], [1.5, 1.2, 0.8]])


def _normalise(p):
    return (np.asarray(p) - BOX[0]) / (BOX[1] - BOX[0]) * 2.0 - 1.0


def _joint(angles, axis=(1.0, 0.0, 0.0), pivot=(0.0, 0.0, -0.95)):
    return {"pivot": _normalise(pivot).tolist(), "axis": list(axis), "half": ((BOX[1] - BOX[0]) / 2).tolist(),
            "angles_rad": list(angles)}


@pytest.mark.parametrize("t_scene_ms", [0, 250, 420, 700])
def test_part_frame_undoes_the_scenes_hinge(t_scene_ms):
    """A point of the fork, carried by the scene's own hinge to time t, maps back to where it
    was at angle 0 (an anisotropic box: the rotation is rigid in metres)."""
    scene = load_scene("fork", check_cameras=False)
    fork = scene.object("fork")
    t = t_scene_ms * 1_000_000
    angle = fork.motion.angle_rad(t)
    field = HingeField(_joint([angle, angle], axis=fork.motion.axis, pivot=fork.motion.pivot))
    rest = scene.transforms(-10 ** 9)["fork"]          # angle 0 before the servo starts
    assert fork.motion.angle_rad(-10 ** 9) == 0.0
    canonical = np.array([[0.0, 0.1, 0.3], [0.05, -0.12, -0.4], [0.0, 0.0, -0.95]])
    world = (scene.transforms(t)["fork"] @ np.linalg.inv(rest) @ np.c_[canonical, np.ones(3)].T).T[:, :3]
    back = field.part_frame(torch.tensor(_normalise(world), dtype=torch.float32), torch.tensor([0.3]))
    metres = (back.numpy() + 1.0) / 2.0 * (BOX[1] - BOX[0]) + BOX[0]
    np.testing.assert_allclose(metres, canonical, atol=1e-5)


def test_angle_is_linear_between_samples_and_held_outside():
    field = HingeField(_joint([0.0, 1.0, -1.0]))
    got = field.angle(torch.tensor([0.0, 0.25, 0.5, 0.75, 1.0, -0.5, 2.0]))
    np.testing.assert_allclose(got.numpy(), [0.0, 0.5, 1.0, 0.0, -1.0, 0.0, -1.0], atol=1e-6)


def test_the_static_world_never_changes_and_the_part_moves_with_the_joint():
    torch.manual_seed(0)
    field = make_field("hinge", joint=_joint([0.0, np.pi / 2]), seed=3)
    x = torch.rand(500, 3) * 2 - 1
    feats = field.space_features(x)
    d0, g0 = field.decode(feats, torch.tensor([0.0]))
    d1, g1 = field.decode(feats, torch.tensor([1.0]))
    assert not torch.allclose(d0, d1)                  # the part turned 90 degrees
    ds, gs = field.decode_static(feats)
    assert torch.all(d0 >= ds) and torch.all(d1 >= ds)  # static + moving density
    # per-point times give the same as one shared time (the reuse pair equals forward)
    dp, gp = field(x, torch.full((500, 1), 1.0))
    torch.testing.assert_close(dp, d1)
    torch.testing.assert_close(gp, g1)
    # without a joint angle change nothing changes
    still = make_field("hinge", joint=_joint([0.3, 0.3]), seed=3)
    f = still.space_features(x)
    torch.testing.assert_close(still.decode(f, torch.tensor([0.0]))[0], still.decode(f, torch.tensor([0.9]))[0])


def test_a_changing_world_starts_static_and_keeps_the_reuse_pair_exact():
    """``static_time_resolution``: the world is a planes field (for the part's shadow), static
    at the start (time planes at 1) and decoded the same through the reuse pair as directly."""
    field = make_field("hinge", joint=_joint([0.0, 1.0]), static_time_resolution=4, seed=5)
    x = torch.rand(300, 3) * 2 - 1
    feats = field.space_features(x)
    world = field.static.space_features(x)
    torch.testing.assert_close(field.static.decode(world, torch.tensor([0.1]))[0],
                               field.static.decode(world, torch.tensor([0.8]))[0])
    torch.testing.assert_close(field.decode_static(feats)[0], field.static.decode_static(world)[0])
    with torch.no_grad():
        for tp in field.static.time_planes:
            tp.uniform_(0.5, 2.0)
    feats = field.space_features(x)
    for t in (0.0, 0.37, 1.0):
        direct = field(x, torch.full((300, 1), t))
        torch.testing.assert_close(field.decode(feats, torch.tensor([t])), direct)


@pytest.mark.parametrize("bad, why", [({"angles_rad": [0.1]}, ">= 2 finite"), ({"axis": [0, 0, 0]}, "non-zero"),
                                      ({"half": [1, 0, 1]}, "> 0"), ({"angles_rad": [0.0, float("nan")]}, "finite")])
def test_a_bad_joint_is_a_clear_error(bad, why):
    with pytest.raises(ValueError, match=why):
        HingeField({**_joint([0.0, 1.0]), **bad})


def test_the_joint_travels_from_the_scene_through_the_session_into_the_training_set(tiny_train_h5):
    """The simulator writes the fork's servo joint into session.yaml, convert carries it onto the
    common clock, and the field's angle table matches the scene's hinge over the span."""
    from evdnerf_ros.io.trainingset import TrainingSet
    from evdnerf_ros.train.joint import joint_from_training_set

    scene = load_scene("fork", check_cameras=False)
    fork = scene.object("fork")
    with TrainingSet(tiny_train_h5) as ts:
        joint = joint_from_training_set(ts, BOX, samples=65)
        origin = int(np.median([int(v) for v in ts.provenance["truth"]["scene_time_at_origin_ns"].values()]))
        t0, t1 = ts.time_range
    np.testing.assert_allclose(joint["pivot"], _normalise(fork.motion.pivot))
    np.testing.assert_allclose(joint["axis"], fork.motion.axis)
    for k in (0, 13, 32, 50, 64):
        t = t0 + round(k / 64 * (t1 - t0))
        assert joint["angles_rad"][k] == pytest.approx(fork.motion.angle_rad(t + origin), abs=2e-4), k
    assert max(abs(a) for a in joint["angles_rad"]) > 0.5   # the swing is inside the span


def test_a_set_without_a_joint_says_to_train_planes(tiny_train_h5, tmp_path):
    import json
    import shutil

    import h5py

    from evdnerf_ros.io.trainingset import TrainingSet
    from evdnerf_ros.train.joint import joint_from_training_set

    copy = tmp_path / "real.h5"
    shutil.copy(tiny_train_h5, copy)
    with h5py.File(copy, "r+") as f:
        prov = json.loads(f["provenance"][()])
        prov.pop("joint")
        del f["provenance"]
        f.create_dataset("provenance", data=json.dumps(prov))
    with TrainingSet(copy) as ts, pytest.raises(InputError, match="real.h5: backbone hinge .* train with backbone planes"):
        joint_from_training_set(ts, BOX)


def test_a_hinge_run_trains_saves_and_loads(tiny_train_h5, tmp_path):
    """Trained a few iterations (the joint filled in from the set), saved, loaded back."""
    from evdnerf_ros.train.run import TrainedRun
    from evdnerf_ros.train.trainer import run_train

    run_train(tiny_train_h5, tmp_path / "run", config={
        "backbone": "hinge", "rays": 64, "n_samples": 16, "eval_every": 0, "log_every": 0,
        "field": {"resolutions": [8, 16], "features": 4}}, iters=3, log=lambda *_: None, device="cpu")
    run = TrainedRun.load(tmp_path / "run")
    assert isinstance(run.field, HingeField)
    # a config object given to the trainer is not changed (the joint belongs to this set)
    from evdnerf_ros.io.trainingset import TrainingSet
    from evdnerf_ros.train.config import TrainConfig
    from evdnerf_ros.train.trainer import Trainer

    given = TrainConfig.from_dict({"backbone": "hinge", "field": {"resolutions": [8], "features": 2}})
    with TrainingSet(tiny_train_h5) as ts:
        tr = Trainer(ts, given, iters=1, log=lambda *_: None)
    assert "joint" in tr.cfg.field and "joint" not in given.field
    assert run.field.angles.numel() == 257 and "joint" in (tmp_path / "run" / "config.yaml").read_text()
    # the joint is part of the config: a fresh field from it takes the trained weights
    from evdnerf_ros.train.config import field_from_config

    fresh = field_from_config(run.config)
    fresh.load_state_dict(run.field.state_dict())
    x = torch.rand(50, 3) * 2 - 1
    with torch.no_grad():
        torch.testing.assert_close(fresh(x, torch.full((50, 1), 0.4)), run.field(x, torch.full((50, 1), 0.4)))


def test_only_a_scene_whose_one_motion_is_a_servo_hinge_has_a_joint_record():
    from evdnerf_ros.sim.joint import ANGLE_STEP_NS, joint_record

    fork = load_scene("fork", check_cameras=False)
    record = joint_record(fork)
    drive = fork.object("fork").servo
    assert record["angle_rad"]["step_ns"] == ANGLE_STEP_NS
    values = record["angle_rad"]["values"]
    assert len(values) == drive.profile.duration_ns // ANGLE_STEP_NS + 1
    assert values[137] == pytest.approx(drive.angle_rad(drive.start_ns + 137 * ANGLE_STEP_NS))
    assert joint_record(load_scene("jet-down", check_cameras=False)) is None      # keyframed, no servo


@pytest.mark.parametrize("change, why", [
    ({"axis": [0, 0, 0]}, "non-zero"), ({"pivot": None}, "together"),
    ({"angle_rad": {"step_ns": 0, "values": [0.0, 1.0]}}, "step_ns"),
    ({"angle_rad": {"step_ns": 1000, "values": [0.0]}}, "at least 2")])
def test_session_yaml_checks_the_joint(tiny_train_h5, tmp_path, change, why):
    import shutil

    import yaml

    from evdnerf_ros.session.layout import load_session

    session = tmp_path / "s"
    shutil.copytree(tiny_train_h5.parent / "s", session)
    doc = yaml.safe_load((session / "session.yaml").read_text())
    assert doc["servo"]["angle_rad"]["values"]
    doc["servo"].update(change)
    (session / "session.yaml").write_text(yaml.safe_dump(doc))
    with pytest.raises(InputError, match=f"servo.*{why}"):
        load_session(session)


def test_the_part_prior_is_the_parts_mean_opacity_and_thins_only_the_part(tiny_train_h5):
    """``part_empty_weight``: the moving part's mean opacity over one sample's length (hand
    computed for a constant density), its gradient reaches the part alone, and training with it
    leaves the part's density at random points lower than without; a field without a part
    refuses it; hinge's default is on, a saved config from before it keeps it off."""
    from evdnerf_ros.io.trainingset import TrainingSet
    from evdnerf_ros.train.config import TrainConfig
    from evdnerf_ros.train.trainer import Trainer

    small = {"backbone": "hinge", "rays": 128, "n_samples": 16, "windows": [8], "window_switch": [],
             "eval_every": 0, "log_every": 0, "checkpoint_every": 0, "empty_points": 256,
             "field": {"resolutions": [8, 16], "features": 4}, "part_box": False}
    with TrainingSet(tiny_train_h5) as ts:
        tr = Trainer(ts, {**small, "part_empty_weight": 1.0}, iters=1, log=lambda *_: None)
        step = float(np.linalg.norm(tr.box[1] - tr.box[0])) / 16
        real = tr.field.part_density
        tr.field.part_density = lambda x, t: torch.full((x.shape[0],), 2.0)
        assert float(tr.part_empty_prior()) == pytest.approx(1 - np.exp(-2.0 * step), rel=1e-5)
        tr.field.part_density = real
        tr.field.zero_grad()
        tr.part_empty_prior().backward()
        grads = {n: p.grad for n, p in tr.field.named_parameters()}
        assert all(g is None or not g.any() for n, g in grads.items() if not n.startswith("moving."))
        assert any(g is not None and g.any() for n, g in grads.items() if n.startswith("moving."))
        x = torch.rand(2000, 3, generator=torch.Generator().manual_seed(0)) * 2 - 1
        t = torch.rand(2000, generator=torch.Generator().manual_seed(1))
        dens = {}
        for w in (0.0, 1.0):
            tr = Trainer(ts, {**small, "part_empty_weight": w}, iters=40, log=lambda *_: None)
            tr.train()
            with torch.no_grad():
                dens[w] = float(tr.field.part_density(x, t).mean())
    assert dens[1.0] < 0.5 * dens[0.0], dens
    assert TrainConfig(backbone="hinge").part_empty_weight == 1.0
    assert TrainConfig(backbone="planes").part_empty_weight == 0.0 and TrainConfig(backbone="rigid").part_empty_weight == 0.0
    assert TrainConfig.from_dict({"backbone": "hinge"}, saved=True).part_empty_weight == 0.0
    with pytest.raises(InputError, match="part_empty_weight.*planes field has no part"):
        TrainConfig(backbone="planes", part_empty_weight=0.5)


def _swept_region(joint, part_points_m, res=32):
    """The cells of a (res,)^3 grid over BOX that the part's points (metres, at angle 0) visit
    at the joint's angles: what a carved dynamic region holds of that part."""
    pivot = (np.asarray(joint["pivot"]) + 1) / 2 * (BOX[1] - BOX[0]) + BOX[0]
    k = np.asarray(joint["axis"], float) / np.linalg.norm(joint["axis"])
    mask = np.zeros((res,) * 3, bool)
    for theta in np.linspace(min(joint["angles_rad"]), max(joint["angles_rad"]), 200):
        w = part_points_m - pivot
        c, s = np.cos(theta), np.sin(theta)
        world = w * c + np.cross(k, w) * s + np.outer(w @ k, k) * (1 - c) + pivot
        idx = np.floor((_normalise(world) + 1) / 2 * res).astype(int)
        mask[tuple(np.clip(idx, 0, res - 1).T)] = True
    return mask


@pytest.mark.parametrize("axis", [(1.0, 0.0, 0.0), (0.6, 0.0, 0.8)])
def test_the_part_box_holds_the_part_and_is_thin_along_the_joints_axis(axis):
    """``train.joint.part_box``: from the region a thin blade swings through (+-45 deg), a box
    in the part's frame that holds every point of the blade (with its cells' margin), far
    thinner than the scene box along the joint's axis; a speck of region in a corner of the box
    leaves it unchanged; an empty region has none."""
    from evdnerf_ros.train.joint import part_box

    joint = _joint(np.radians([-45.0, 45.0]), axis=axis)
    k = np.asarray(axis) / np.linalg.norm(axis)
    u = np.cross(k, [0.0, 1.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(k, u)
    pivot = np.array([0.0, 0.0, -0.95])
    a, b, c = np.meshgrid(np.linspace(-0.01, 0.01, 3), np.linspace(-0.1, 0.1, 9), np.linspace(0.05, 0.9, 40))
    blade = pivot + a.reshape(-1, 1) * k + b.reshape(-1, 1) * u + c.reshape(-1, 1) * v
    mask = _swept_region(joint, blade)
    box = np.asarray(part_box(joint, mask))
    field = HingeField({**joint, "part_box": box.tolist()}, resolutions=(4,), features=2, seed=0)
    inside = field.part_frame(torch.tensor(_normalise(blade), dtype=torch.float32), torch.tensor([0.5]))
    assert bool((inside.abs() <= 1).all())          # angle 0 at t = 0.5: the blade in its own frame
    if axis == (1.0, 0.0, 0.0):                     # the box's x side against the scene's
        assert (box[1, 0] - box[0, 0]) / 2 < 0.35, box
    speck = mask.copy()
    speck[0, 0, 0] = speck[-1, -1, -1] = True
    np.testing.assert_allclose(part_box(joint, speck), box)
    assert part_box(joint, np.zeros_like(mask)) is None


def test_a_bounded_part_is_empty_outside_its_box_and_maps_its_box_to_the_planes():
    """With ``joint.part_box`` the part's frame is normalised to that box (its corners land on
    -1 and 1 of the planes) and the part's density is zero outside it, the world's unchanged."""
    joint = _joint([0.0, 0.0])
    box = [[-0.2, -0.3, -0.9], [0.1, 0.4, 0.2]]
    bounded = HingeField({**joint, "part_box": box}, resolutions=(4,), features=2, seed=0)
    free = HingeField(joint, resolutions=(4,), features=2, seed=0)
    corners = torch.tensor(box, dtype=torch.float32)
    torch.testing.assert_close(bounded.part_frame(corners, torch.tensor([0.5])), torch.tensor([[-1.0] * 3, [1.0] * 3]))
    x = torch.rand(400, 3, generator=torch.Generator().manual_seed(0)) * 2 - 1
    t = torch.full((400,), 0.5)
    out = ~((x >= corners[0]) & (x <= corners[1])).all(1)
    assert out.any() and (~out).any()
    with torch.no_grad():
        d_bounded, _ = bounded(x, t)
        d_free, _ = free(x, t)
        world, _ = free.decode_static(free.space_features(x))
        torch.testing.assert_close(d_bounded[out], world[out])          # the same seed: the same world
        assert bool((d_bounded[~out] > world[~out]).all())              # the part adds density inside
        assert bool((d_free[out] > world[out]).all())                   # unbounded: everywhere
    with pytest.raises(ValueError, match="part_box"):
        HingeField({**joint, "part_box": [[0, 0, 0], [0, 1, 1]]})


def test_a_part_box_run_trains_saves_and_loads_and_is_hinge_only(tiny_train_h5, tmp_path):
    """``part_box: true``: the trainer cuts the box from its dynamic region into the saved joint,
    a loaded run has it; other backbones and runs without a dynamic region refuse it by name; a
    saved config from before it reads as off."""
    from evdnerf_ros.train.config import TrainConfig
    from evdnerf_ros.train.run import TrainedRun
    from evdnerf_ros.train.trainer import run_train

    run_train(tiny_train_h5, tmp_path / "run", config={
        "backbone": "hinge", "part_box": True, "rays": 64, "n_samples": 16, "eval_every": 0, "log_every": 0,
        "field": {"resolutions": [8, 16], "features": 4}}, iters=3, log=lambda *_: None, device="cpu")
    run = TrainedRun.load(tmp_path / "run")
    assert run.field.part_bounded and run.config.part_box
    lo, hi = run.field.part_lo, run.field.part_hi
    assert bool((hi > lo).all()) and float((hi - lo).min()) < 2.0
    # the part prior stays the part's mean opacity over the scene box: zero outside its own box
    from evdnerf_ros.io.trainingset import TrainingSet
    from evdnerf_ros.train.trainer import Trainer

    with TrainingSet(tiny_train_h5) as ts:
        tr = Trainer(ts, {"backbone": "hinge", "part_box": True, "field": {"resolutions": [8], "features": 2}},
                     iters=1, log=lambda *_: None)
        fraction = float(torch.prod((tr.field.part_hi - tr.field.part_lo) / 2))
        assert 0 < fraction < 1 and tr.field.part_volume_fraction == pytest.approx(fraction)
        step = float(np.linalg.norm(tr.box[1] - tr.box[0])) / tr.cfg.n_samples
        tr.field.part_density = lambda x, t: torch.full((x.shape[0],), 2.0)
        assert float(tr.part_empty_prior()) == pytest.approx(fraction * (1 - np.exp(-2.0 * step)), rel=1e-5)
    assert TrainConfig.from_dict({"backbone": "hinge"}, saved=True).part_box is False
    assert TrainConfig(backbone="hinge").part_box == "auto" and TrainConfig(backbone="rigid").part_box is False
    assert TrainConfig(backbone="hinge", dynamic_region=False).part_box == "auto"     # resolves off: no region
    assert TrainConfig.from_dict({"backbone": "hinge", "part_box": None}).part_box == "auto"
    with pytest.raises(InputError, match="part_box: expected true, false or auto"):
        TrainConfig(backbone="hinge", part_box="yes")
    with pytest.raises(InputError, match="part_box.*planes field has none"):
        TrainConfig(backbone="planes", part_box=True)
    with pytest.raises(InputError, match="part_box.*dynamic region"):
        TrainConfig(backbone="hinge", part_box=True, dynamic_region=False)


def test_part_box_auto_bounds_the_part_where_the_pixels_are_finer_than_the_cells(tiny_train_h5):
    """``part_box: auto``: the tiny 32x32 set's pixels span ~9.6 cm at the joint, more than the
    4.4 cm finest cells of its scene box along the axis: off, and the trainer records it; with
    the views' focal lengths four times longer (2.4 cm pixels) it is on; without a dynamic
    region, off. The rule itself: footprint (distance / focal length) against cell, either side
    of it."""
    import json
    import shutil

    import h5py

    from evdnerf_ros.io.trainingset import TrainingSet
    from evdnerf_ros.train.joint import joint_from_training_set, part_box_pays
    from evdnerf_ros.train.rays import default_box
    from evdnerf_ros.train.trainer import Trainer

    small = {"backbone": "hinge", "field": {"resolutions": [8, 64], "features": 2}}
    with TrainingSet(tiny_train_h5) as ts:
        tr = Trainer(ts, small, iters=1, log=lambda *_: None)
        assert tr.cfg.part_box is False and not tr.field.part_bounded
        box = default_box(ts)
        joint = joint_from_training_set(ts, box)
        assert not part_box_pays(ts, box, joint, 64)
        # coarser planes: 8.75 cm cells still below the pixels, 17.5 cm cells above them
        assert part_box_pays(ts, box, joint, 32) is False and part_box_pays(ts, box, joint, 16) is True
        assert Trainer(ts, {**small, "dynamic_region": False}, iters=1, log=lambda *_: None).cfg.part_box is False
    sharp = tiny_train_h5.parent / "sharp.h5"
    if not sharp.exists():
        shutil.copyfile(tiny_train_h5, sharp)
        with h5py.File(sharp, "r+") as f:
            for name in json.loads(f.attrs["view_names"]):
                K = f["views"][name]["K"][...]
                K[0, 0] *= 4
                K[1, 1] *= 4
                f["views"][name]["K"][...] = K
    with TrainingSet(sharp) as ts:
        box = default_box(ts)
        assert part_box_pays(ts, box, joint_from_training_set(ts, box), 64)
        tr = Trainer(ts, small, iters=1, log=lambda *_: None)
        assert tr.cfg.part_box is True and tr.field.part_bounded
