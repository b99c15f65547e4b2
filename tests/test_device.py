"""The ``device`` setting (auto, cpu, cuda) of train / eval / publish: CPU tensors stay on the
CPU, and a GPU that was asked for but is absent is a clear error, never a silent fallback."""

import numpy as np
import pytest
import torch

from evdnerf_ros.device import CUDA_INSTALL, DeviceError, check_device_name, resolve_device
from evdnerf_ros.errors import InputError


@pytest.fixture
def no_cuda(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)


def test_names_and_auto(no_cuda):
    assert resolve_device("cpu") == torch.device("cpu")
    assert resolve_device("auto") == torch.device("cpu")           # no GPU: auto is the CPU
    assert resolve_device(" CPU ") == torch.device("cpu")
    assert check_device_name("cuda:1") == "cuda:1"
    for bad in ("gpu", "cuda:x", "", 3):
        with pytest.raises(DeviceError, match="auto, cpu, cuda"):
            resolve_device(bad, "config key device")
    assert issubclass(DeviceError, InputError)


def test_auto_picks_cuda_when_available(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    assert resolve_device("auto").type == "cuda"


@pytest.mark.parametrize("name", ["cuda", "cuda:0"])
def test_cuda_requested_but_absent_names_the_fix(no_cuda, name):
    with pytest.raises(DeviceError) as exc:
        resolve_device(name, "RUN: device")
    msg = str(exc.value)
    assert msg.startswith("RUN: device") and "requested but" in msg
    assert "torch==2.13.0" in msg and "--index-url https://download.pytorch.org/whl/cu" in msg
    assert CUDA_INSTALL in msg


def _tiny_run(tmp_path):
    from evdnerf_ros.train.checkpoint import save_checkpoint
    from evdnerf_ros.train.config import TrainConfig, field_from_config

    cfg = TrainConfig(backbone="planes")
    torch.manual_seed(3)
    dyn = torch.zeros((8, 8, 8), dtype=torch.bool)
    dyn[3:5, 3:5, 2:6] = True
    run = tmp_path / "run"
    run.mkdir()
    save_checkpoint(run / "checkpoint.pt", field=field_from_config(cfg), optimizer=None,
                    iteration=0, config=cfg.to_dict(), backbone=cfg.backbone, rng={},
                    box=[[-1, -1, -1], [1, 1, 1]], extra={"dynamic": dyn})
    return run


def test_cpu_tensors_stay_on_the_cpu(tmp_path, no_cuda):
    from evdnerf_ros.geometry.camera import PinholeCamera, look_at
    from evdnerf_ros.train.run import TrainedRun

    run = TrainedRun.load(_tiny_run(tmp_path))
    cam = PinholeCamera.from_fov(12, 10, 50.0)
    for device in ("cpu", "auto"):
        r = run.renderer(cam, duration_ns=10**9, device=device)
        T = look_at([0.0, -3.0, 0.3], [0.0, 0.0, 0.0])
        img = r.render(T, 0)
        assert isinstance(img, np.ndarray) and img.dtype == np.float32 and img.shape == (10, 12)
        assert r.device == torch.device("cpu")
        assert all(p.device.type == "cpu" for p in r.field.parameters())
        assert r.dynamic.mask.device.type == "cpu"
        for plan in r._plan_cache[1]:
            for name in ("static_rays", "static_grey", "dyn_rays", "delta", "base_sigma", "dyn_idx"):
                assert getattr(plan, name).device.type == "cpu", name
            assert all(f.device.type == "cpu" for f in plan.feats[1])
    baked = run.renderer(cam, duration_ns=10**9, bake_resolution=8, device="cpu")
    assert all(b.device.type == "cpu" for b in baked.field.buffers())


def test_cuda_absent_is_an_error_in_eval_and_publish(tmp_path, no_cuda, capsys):
    from evdnerf_ros.cli import main
    from evdnerf_ros.nodes.event_publisher import EventPublisher
    from evdnerf_ros.train.run import TrainedRun

    run_dir = _tiny_run(tmp_path)
    from evdnerf_ros.geometry.camera import PinholeCamera

    with pytest.raises(DeviceError, match="torch==2.13.0"):
        TrainedRun.load(run_dir).renderer(PinholeCamera.from_fov(8, 8, 50.0), duration_ns=10**9, device="cuda")
    from evdnerf_ros.eval.published import _write_trajectory
    from evdnerf_ros.geometry.camera import look_at

    T = look_at([0.0, -3.0, 0.3], [0.0, 0.0, 0.0])
    traj = _write_trajectory(tmp_path / "t.yaml", [0, 10_000_000], [T, T])
    with pytest.raises(DeviceError, match="device 'cuda' requested"):
        EventPublisher(("--ros-args", "--log-level", "warn"), dds=False, overrides={
            "run_dir": str(run_dir), "device": "cuda", "trajectory": str(traj), "camera.width": 8, "camera.height": 8,
            "field_duration": 1.0, "duration": 0.01})
    assert main(["eval", str(run_dir), str(tmp_path / "none.h5"), "--device", "cuda"]) == 2
    err = capsys.readouterr().err
    assert "device 'cuda' requested" in err and "pip install" in err


# ---------------------------------------------------------------------- training
SMALL = {"backbone": "planes", "rays": 64, "n_samples": 8, "occupancy_resolution": 8, "occupancy_warmup": 2, "occupancy_every": 2,
         "eval_every": 0, "checkpoint_every": 0, "log_every": 0,
         "field": {"resolutions": [8, 16], "features": 4, "time_resolution": 8}}


def _trainer(ts, device, **cfg):
    from evdnerf_ros.train.trainer import Trainer

    return Trainer(ts, {**SMALL, **cfg}, iters=6, log=lambda *_: None, device=device)


def test_training_on_the_cpu_keeps_every_tensor_there(tiny_train_h5, no_cuda):
    from evdnerf_ros.io.trainingset import TrainingSet

    with TrainingSet(tiny_train_h5) as ts:
        for device in ("cpu", "auto"):
            tr = _trainer(ts, device, learn_thresholds=True)
            assert tr.device == torch.device("cpu")
            tr.train()
            assert all(p.device.type == "cpu" for p in tr.field.parameters())
            assert all(p.device.type == "cpu" for p in tr.thresholds.parameters())
            assert tr.occupancy.occupied.device.type == "cpu" and tr.dynamic.mask.device.type == "cpu"
            batch = tr.sampler.sample(8)
            assert {t.device.type for t in (batch.origins, batch.dirs, batch.dl, batch.on_event, batch.counts)} == {"cpu"}
            assert tr.gen.device.type == "cpu"


def test_train_cuda_absent_is_an_error_before_the_run_folder(tiny_train_h5, tmp_path, no_cuda, capsys):
    from evdnerf_ros.cli import main

    run = tmp_path / "run"
    assert main(["train", str(tiny_train_h5), "-o", str(run), "--iters", "2", "--device", "cuda"]) == 2
    err = capsys.readouterr().err
    assert "--device: device 'cuda' requested" in err and "pip install" in err
    assert not run.exists()


cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA GPU here (runs on a GPU machine)")


@cuda
def test_cuda_training_matches_the_cpu_and_resumes_across_devices(tiny_train_h5, tmp_path):
    """The same run on the GPU: every tensor there, losses as on the CPU (float32 sums in another
    order, and a different jitter stream: close, not equal), checkpoints readable on the CPU."""
    from evdnerf_ros.io.trainingset import TrainingSet
    from evdnerf_ros.train.trainer import Trainer

    with TrainingSet(tiny_train_h5) as ts:
        losses = {}
        for device in ("cpu", "cuda"):
            tr = _trainer(ts, device, perturb=False)
            losses[device] = [tr.step() for _ in range(6)]
            if device == "cuda":
                assert all(p.device.type == "cuda" for p in tr.field.parameters())
                assert tr.occupancy.occupied.device.type == "cuda" and tr.dynamic.mask.device.type == "cuda"
        assert np.allclose(losses["cpu"], losses["cuda"], rtol=2e-3, atol=1e-6), losses
        tr = Trainer(ts, SMALL, iters=4, run_dir=tmp_path, log=lambda *_: None, device="cuda")
        tr.train()
        tr2 = Trainer(ts, SMALL, iters=8, run_dir=tmp_path, log=lambda *_: None, device="cpu")
        tr2.resume(tmp_path / "checkpoint.pt")
        assert tr2.iteration == 4 and all(p.device.type == "cpu" for p in tr2.field.parameters())
        tr2.train()
        assert np.isfinite(tr2.last_loss)


@cuda
def test_cuda_eval_and_publish_match_the_cpu(tiny_train_h5, tmp_path):
    from evdnerf_ros.eval.evaluate import run_eval
    from evdnerf_ros.train.trainer import run_train

    run_train(tiny_train_h5, tmp_path / "run", config=SMALL, iters=20, log=lambda *_: None, device="cuda")
    res = {d: run_eval(tmp_path / "run", tiny_train_h5, n_windows=8, max_views=1, factors=(1,), log=lambda *_: None,
                       device=d) for d in ("cpu", "cuda")}
    a, b = (r["val_windows_x1"]["continuous"]["psnr"] for r in (res["cpu"], res["cuda"]))
    assert abs(a - b) < 0.05, (a, b)
