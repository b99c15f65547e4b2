"""``backbone: auto`` chooses the field from what the training set records, logs why, and records it."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from conftest import NoEvents
from evdnerf_ros.errors import InputError


def _tiny_set(tmp_path_factory, scene: str):
    """``scene`` at 32x32, 6 training views + 1 validation view, 1 s."""
    from evdnerf_ros.session.convert import run_convert
    from evdnerf_ros.sim.simulate import SimulationOptions, simulate_session

    tmp = tmp_path_factory.mktemp(f"auto_{scene}")
    simulate_session(scene, tmp / "s", SimulationOptions(
        views=6, val_views=1, resolution=(32, 32), frame_rate_hz=20, blur_samples=2, gt_times=0,
        supersample=2, jobs=1, min_step_ns=2_000_000), log=lambda *_: None)
    run_convert(tmp / "s", tmp / "t.h5", offsets="ground-truth", log=lambda *_: None)
    return tmp / "t.h5"


@pytest.fixture(scope="module")
def jet_h5(tmp_path_factory):
    return _tiny_set(tmp_path_factory, "jet-down")


@pytest.fixture(scope="module")
def multi_h5(tmp_path_factory):
    return _tiny_set(tmp_path_factory, "multi")


def _choose(path, **cfg):
    from evdnerf_ros.io.trainingset import TrainingSet
    from evdnerf_ros.train.auto import choose_backbone
    from evdnerf_ros.train.config import TrainConfig
    from evdnerf_ros.train.rays import default_box

    config = TrainConfig.from_dict(cfg)
    with TrainingSet(path) as ts:
        return choose_backbone(ts, default_box(ts, config.box_fraction), config)


def test_auto_is_the_default_and_waits_for_a_training_set():
    from evdnerf_ros.train.config import TrainConfig, field_from_config

    cfg = TrainConfig()
    assert cfg.backbone == "auto" and cfg.n_samples is None and cfg.lr_final is None
    with pytest.raises(InputError, match="backbone auto is chosen from a training set.*name a backbone"):
        field_from_config(cfg)
    chosen = cfg.with_backbone("rigid")
    assert (chosen.backbone, chosen.n_samples, chosen.lr_final) == ("rigid", 64, 0.1)
    assert cfg.backbone == "auto"                      # a copy
    assert TrainConfig(n_samples=20).with_backbone("rigid").n_samples == 20   # given: kept


def test_a_recorded_joint_gets_hinge(tiny_train_h5):
    name, why, found = _choose(tiny_train_h5)
    assert (name, found) == ("hinge", {}) and "joint" in why


def test_one_compact_moving_part_gets_rigid_with_its_track(jet_h5):
    from evdnerf_ros.io.trainingset import TrainingSet
    from evdnerf_ros.train.rays import default_box
    from evdnerf_ros.train.track import track_from_events

    name, why, found = _choose(jet_h5)
    assert name == "rigid" and "radius" in why
    with TrainingSet(jet_h5) as ts:                    # the same track the rigid field would carve
        assert found["track"] == track_from_events(ts, default_box(ts, 0.35))


def test_motion_spread_over_the_box_gets_planes(multi_h5):
    name, why, found = _choose(multi_h5)
    assert (name, found) == ("planes", {}) and "half-diagonal" in why


def test_frames_supervision_gets_planes(jet_h5):
    assert _choose(jet_h5, supervision="frames")[:1] == ("planes",)


def test_a_set_where_nothing_moves_gets_planes(jet_h5):
    from evdnerf_ros.io.trainingset import TrainingSet
    from evdnerf_ros.train.auto import choose_backbone
    from evdnerf_ros.train.config import TrainConfig

    with TrainingSet(jet_h5) as ts:
        name, why, _ = choose_backbone(NoEvents(ts), np.array([[-1.4] * 3, [1.4] * 3]), TrainConfig())
    assert name == "planes" and "no time bin" in why


def test_train_logs_and_records_the_choice_and_resumes_it(jet_h5, tmp_path):
    from evdnerf_ros.train.run import TrainedRun
    from evdnerf_ros.train.trainer import run_train

    lines = []
    cfg = {"rays": 64, "n_samples": 8, "windows": [4], "window_switch": [], "eval_every": 0,
           "background_cells": 0, "dynamic_resolution": 16, "field": {"resolutions": [8]}}
    out = run_train(jet_h5, tmp_path / "run", config=cfg, iters=2, log=lines.append)
    assert out["backbone"] == "rigid" and "radius" in out["backbone_reason"]
    assert any(line.startswith("backbone auto: rigid, because one moving part") for line in lines)
    text = (tmp_path / "run" / "config.yaml").read_text()
    assert text.startswith("# backbone: auto chose rigid, because ")
    saved = yaml.safe_load(text)
    assert saved["backbone"] == "rigid" and "track" in saved["field"] and saved["n_samples"] == 8
    assert TrainedRun.load(tmp_path / "run").config.backbone == "rigid"
    again = run_train(jet_h5, tmp_path / "run", config=cfg, iters=3, log=lines.append)   # the same choice
    assert again["resumed"] and again["iterations"] == 3 and again["backbone"] == "rigid"


def test_options_of_another_backbone_are_refused_once_the_choice_is_made(jet_h5, tmp_path):
    from evdnerf_ros.train.trainer import run_train

    cfg = {"rays": 64, "n_samples": 8, "windows": [4], "window_switch": [], "eval_every": 0,
           "dynamic_resolution": 16, "field": {"time_resolution": 4}}
    with pytest.raises(InputError, match=r"field\.time_resolution.*backbone auto chose rigid, because .*"
                                         r"name the backbone"):
        run_train(jet_h5, tmp_path / "run", config=cfg, iters=2, log=lambda *_: None)
    assert not (tmp_path / "run").exists()             # nothing left behind
