"""TrainedRun.load: the one loader of a run folder; every missing or damaged piece is one
clear error naming the run folder (or its checkpoint) and the fix."""

from __future__ import annotations

import io

import numpy as np
import pytest
import torch

from evdnerf_ros.errors import InputError
from evdnerf_ros.field import DynamicRegion, OccupancyGrid, make_field
from evdnerf_ros.train.checkpoint import CheckpointError, FORMAT, FORMAT_VERSION, header, save_checkpoint
from evdnerf_ros.train.config import TrainConfig, field_from_config
from evdnerf_ros.train.run import TrainedRun
from evdnerf_ros import __version__

FIELD = dict(resolutions=[8], time_resolution=4, features=4, hidden=8)


def _save(run, *, cfg=None, field=None, extra=None, box=((-1, -1, -1), (1, 1, 1)), iteration=3):
    cfg = cfg or TrainConfig(backbone="planes", field=FIELD).to_dict()
    torch.manual_seed(0)
    field = field if field is not None else field_from_config(TrainConfig(backbone="planes", field=FIELD))
    run.mkdir(exist_ok=True)
    save_checkpoint(run / "checkpoint.pt", field=field, optimizer=None, iteration=iteration, config=cfg,
                    backbone="planes", rng={}, box=[list(b) for b in box], extra=extra)
    return field


def _save_raw(path, data: dict):
    """A correctly checksummed checkpoint file holding exactly ``data``."""
    buf = io.BytesIO()
    torch.save(data, buf)
    path.write_bytes(header(buf.getbuffer()) + buf.getvalue())


def test_a_good_run_gives_every_piece(tmp_path):
    occ = torch.zeros((4, 4, 4), dtype=torch.bool)
    occ[1:3, 1:3, 1:3] = True
    dyn = torch.zeros((6, 6, 6), dtype=torch.bool)
    dyn[2, 2, 2] = True
    field = _save(tmp_path / "R", extra={"occupied": occ, "dynamic": dyn,
                                         "train_set": {"time_range_ns": [10, 2_000_000_010],
                                                       "thresholds": [0.3, 0.2]}})
    run = TrainedRun.load(tmp_path / "R")
    assert run.iteration == 3 and run.config == TrainConfig(backbone="planes", field=FIELD)
    np.testing.assert_array_equal(run.box, [[-1, -1, -1], [1, 1, 1]])
    assert isinstance(run.occupancy, OccupancyGrid) and torch.equal(run.occupancy.occupied, occ)
    assert isinstance(run.dynamic, DynamicRegion) and torch.equal(run.dynamic.mask, dyn)
    assert run.time_range_ns == (10, 2_000_000_010) and run.thresholds == (0.3, 0.2)
    assert not run.field.training
    for k, v in field.state_dict().items():
        assert torch.equal(run.field.state_dict()[k], v)
    assert run.field is run.field                                  # built once
    assert "iteration=3" in repr(run)


def test_an_old_checkpoint_without_records_still_loads(tmp_path):
    _save(tmp_path / "R")
    run = TrainedRun.load(tmp_path / "R")
    assert run.occupancy is None and run.dynamic is None
    assert run.time_range_ns is None and run.thresholds is None
    with pytest.raises(InputError, match="does not record the training set's time span.*field_duration"):
        run.renderer(object())
    assert run.renderer(_cam(), duration_ns=10**9).duration_ns == 10**9


def _cam():
    from evdnerf_ros.geometry.camera import PinholeCamera

    return PinholeCamera.from_fov(8, 6, 40.0)


def test_missing_folder_file_and_checkpoint(tmp_path):
    with pytest.raises(CheckpointError, match=r"nope: no such run folder; give the folder `evdnerf train"):
        TrainedRun.load(tmp_path / "nope")
    (tmp_path / "f").write_text("x")
    with pytest.raises(CheckpointError, match=r"f: is a file, not a run folder"):
        TrainedRun.load(tmp_path / "f")
    (tmp_path / "E").mkdir()
    with pytest.raises(CheckpointError, match=r"E: holds no checkpoint.pt.*run `evdnerf train"):
        TrainedRun.load(tmp_path / "E")
    (tmp_path / "D" / "checkpoint.pt").mkdir(parents=True)
    with pytest.raises(CheckpointError, match=r"checkpoint.pt: is not a regular file; train again"):
        TrainedRun.load(tmp_path / "D")


def test_damaged_or_foreign_checkpoints(tmp_path):
    _save(tmp_path / "R")
    ck = tmp_path / "R" / "checkpoint.pt"
    raw = bytearray(ck.read_bytes())
    raw[-100] ^= 0xFF
    ck.write_bytes(bytes(raw))
    with pytest.raises(CheckpointError, match=r"R/checkpoint.pt: damaged checkpoint \(its SHA-256"):
        TrainedRun.load(tmp_path / "R")
    ck.write_text("rays: 5\n")
    with pytest.raises(CheckpointError, match="not an evdnerf_ros training checkpoint"):
        TrainedRun.load(tmp_path / "R")


def _base(**over):
    d = {"format": FORMAT, "format_version": FORMAT_VERSION, "software_version": __version__,
         "iteration": 1, "config": TrainConfig(backbone="planes", field=FIELD).to_dict(), "backbone": "planes",
         "field": field_from_config(TrainConfig(backbone="planes", field=FIELD)).state_dict(), "optimizer": None, "rng": {},
         "box": [[-1, -1, -1], [1, 1, 1]], "extra": {}}
    d.update(over)
    return {k: v for k, v in d.items() if v is not KeyError}


@pytest.mark.parametrize("over, message", [
    (dict(field=KeyError), "holds no field: damaged or not written by `evdnerf train`; train again"),
    (dict(config=KeyError, box=KeyError), "holds no config, box"),
    (dict(config=dict(TrainConfig(backbone="planes").to_dict(), rays=-4)), r"checkpoint.pt \(config\): rays: must be >= 1"),
    (dict(config={"learning_rate": 1}), r"checkpoint.pt \(config\): learning_rate: unknown key"),
    (dict(iteration=-1), "iteration -1 is not a count"),
    (dict(box=[[0, 0, 0], [0, 1, 1]]), "scene box .* max > min"),
    (dict(box="cube"), "scene box 'cube'"),
    (dict(extra=[1]), "'extra' record is a list"),
    (dict(extra={"occupied": [1, 2]}), "its occupancy grid is not a 3-D grid"),
    (dict(extra={"dynamic": torch.zeros(3)}), "its dynamic region is not a 3-D grid"),
    (dict(extra={"train_set": {"time_range_ns": [5, 5]}}), "time range .* two increasing int64 ns"),
    (dict(extra={"train_set": {"thresholds": [0.2, -1]}}), "thresholds .* are not positive"),
])
def test_inconsistent_pieces_are_one_error(tmp_path, over, message):
    (tmp_path / "R").mkdir()
    _save_raw(tmp_path / "R" / "checkpoint.pt", _base(**over))
    with pytest.raises(InputError, match=message) as exc:
        TrainedRun.load(tmp_path / "R")
    assert str(exc.value).startswith(str(tmp_path / "R")) and "\n" not in str(exc.value)


def test_weights_that_do_not_fit_the_config(tmp_path):
    other = make_field("planes", **dict(FIELD, features=6))
    (tmp_path / "R").mkdir()
    _save_raw(tmp_path / "R" / "checkpoint.pt", _base(field=other.state_dict()))
    run = TrainedRun.load(tmp_path / "R")                          # the state loads lazily ...
    with pytest.raises(CheckpointError, match=r"checkpoint.pt: the weights do not fit the planes field"):
        run.field                                                  # ... and its error names the file
    _save_raw(tmp_path / "R" / "checkpoint.pt", _base(field=[1, 2]))
    with pytest.raises(CheckpointError, match="field weights are a list, not a state dict"):
        TrainedRun.load(tmp_path / "R").field


def test_eval_and_publisher_report_a_bad_run_in_one_line(tmp_path, capsys):
    from evdnerf_ros.eval.evaluate import run_eval
    from evdnerf_ros.nodes.sources import FieldSource

    (tmp_path / "E").mkdir()
    with pytest.raises(CheckpointError, match="E: holds no checkpoint.pt"):
        run_eval(tmp_path / "E", tmp_path / "t.h5")
    with pytest.raises(CheckpointError, match="E: holds no checkpoint.pt"):
        FieldSource(tmp_path / "E", _cam(), duration_ns=10**9)
