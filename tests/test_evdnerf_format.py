"""EvDNeRF paper format: export -> import round trip, axis conversion, their loader's conventions."""

import json
import pickle

import numpy as np
import pytest

from evdnerf_ros.errors import FormatError, InputError, OutputExistsError
from evdnerf_ros.events import make_events, window_edges
from evdnerf_ros.io.evdnerf_format import (AXES_FLIP, cv_to_gl, export_evdnerf, from_file_time, gl_to_cv,
                                          import_evdnerf, to_file_time)
from evdnerf_ros.io.trainingset import TrainingSet, ViewData, write_training_set

W, H = 24, 20
QUIET = {"log": lambda *_: None}
NS = 1_000_000_000


def rot(yaw, pitch):
    cy, sy, cp, sp = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch)
    Rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    Rx = np.array([[1, 0, 0], [0, cp, -sp], [0, sp, cp]])
    return Rz @ Rx


def cam(i):
    T = np.eye(4)
    T[:3, :3] = rot(0.7 * i, 1.9)
    T[:3, 3] = [np.cos(0.7 * i) * 4, np.sin(0.7 * i) * 4, 1.0]
    return T


def make_set(path, t_start, t_end, *, n=4000, seed=0, moving=False, frames=False):
    rng = np.random.default_rng(seed)
    K = np.array([[30.5, 0, 11.25], [0, 31.0, 9.75], [0, 0, 1]])
    views = []
    for i, (name, split) in enumerate((("view_00", "train"), ("view_01", "train"), ("val_00", "val"))):
        t = np.sort(rng.integers(t_start, t_end, n))
        ev = make_events(t, rng.integers(0, W, n), rng.integers(0, H, n), rng.random(n) < 0.5)
        vd = ViewData(name, split, K, cam(i), events=ev)
        if moving and i == 0:
            vd.poses_t = np.array([t_start, (t_start + t_end) // 2], np.int64)
            vd.poses_T = np.stack([cam(0), cam(5)])
        if frames:
            edges = window_edges(t_start, t_end, 4)
            vd.frames = {"frames": rng.random((4, H, W)).astype(np.float32), "t_start": edges[:-1],
                         "t_end": edges[1:]}
        views.append(vd)
    write_training_set(path, views, width=W, height=H, c_pos=0.3, c_neg=0.25, t_start=t_start, t_end=t_end)
    return path


def assert_same(a_path, b_path, *, poses=True):
    with TrainingSet(a_path) as a, TrainingSet(b_path) as b:
        assert a.views == b.views and a.time_range == b.time_range and a.thresholds == b.thresholds
        assert (a.width, a.height) == (b.width, b.height)
        for v in a.views:
            assert a.split(v) == b.split(v)
            assert np.array_equal(a.events(v), b.events(v))
            assert np.array_equal(a.K(v), b.K(v))
            if poses:
                assert np.array_equal(a.pose(v), b.pose(v))


@pytest.mark.parametrize("t_start, t_end, mode", [(0, NS, "normalized"), (-2_000_000, 597_000_123, "normalized"),
                                                  (5 * NS, 8 * NS + 7, "ns")])
def test_round_trip_is_exact(tmp_path, t_start, t_end, mode):
    src = make_set(tmp_path / "a.h5", t_start, t_end)
    out = tmp_path / "evd"
    export_evdnerf(src, out, n_windows=6, event_time=mode, **QUIET)
    import_evdnerf(out, tmp_path / "b.h5", **QUIET)
    assert_same(src, tmp_path / "b.h5")


def test_time_column_conversion():
    rng = np.random.default_rng(3)
    for D in (1, 7, 999_999_937, NS):
        dt = np.unique(rng.integers(0, D, 5000))
        c = to_file_time(dt + 11, 11, 11 + D, "normalized")
        assert c.min() >= 0 and c.max() < NS and np.all(np.diff(c) > 0)
        assert np.array_equal(from_file_time(c, 11, 11 + D, "normalized"), dt + 11)
    c = to_file_time(np.array([0, 3 * NS - 1]), 0, 3 * NS, "normalized")      # > 1 s: lossy, in range
    assert c.tolist() == [0, NS - 1]


def test_files_follow_their_loader(tmp_path):
    src = make_set(tmp_path / "a.h5", 0, NS, frames=True)
    out = tmp_path / "evd"
    n = 8
    export_evdnerf(src, out, n_windows=n, **QUIET)
    meta = json.loads((out / "transforms_train.json").read_text())
    frames = meta["frames"]
    # their loader: views = frames whose time is 1.0; timesteps = frames / views; view-major
    n_views = sum(abs(f["time"] - 1.0) < 1e-5 for f in frames)
    assert n_views == 2 and len(frames) // n_views == n + 1
    assert [f["time"] for f in frames[: n + 1]] == [k / n for k in range(n + 1)]
    evims = np.load(out / "data_frames_train.npy")
    assert evims.shape == (2, n, H, W) and evims.dtype == np.float32
    assert evims.shape[0] * evims.shape[1] < len(frames)   # their loader pads one zero frame per view
    evs = np.load(out / "data_train.npy", allow_pickle=True).tolist()
    with TrainingSet(src) as ts:
        K = ts.K()
        f = 0.5 * W / np.tan(0.5 * meta["camera_angle_x"])
        assert f == pytest.approx(K[0, 0])
        edges = window_edges(0, NS, n)
        for vi, view in enumerate(ts.train_views):
            assert np.array_equal(evims[vi], ts.log_change_stack(view, edges))
            T_gl = np.array(frames[vi * (n + 1)]["transform_matrix"])
            assert np.array_equal(T_gl, ts.pose(view) @ AXES_FLIP)
            # Blender camera looks down -z: its -z axis is our +z (forward), its +y our -y
            assert np.allclose(-T_gl[:3, 2], ts.pose(view)[:3, 2]) and np.allclose(-T_gl[:3, 1], ts.pose(view)[:3, 1])
            # their form_eventframe: t >= time0 * 1e9 and t < time1 * 1e9, histogram2d, C+ / C-
            ev = evs[vi]
            assert ev.shape[1] == 4
            for k in (0, 3, n - 1):
                sel = ev[(ev[:, 0] >= k / n * 1e9) & (ev[:, 0] < (k + 1) / n * 1e9)]
                pos, neg = sel[sel[:, 3] > 0], sel[sel[:, 3] < 0]
                frame = (0.3 * np.histogram2d(pos[:, 1], pos[:, 2], bins=(W, H), range=[[0, W], [0, H]])[0]
                         - 0.25 * np.histogram2d(neg[:, 1], neg[:, 2], bins=(W, H), range=[[0, W], [0, H]])[0]).T
                assert np.allclose(frame, evims[vi, k], atol=1e-5)
            png = out / (frames[vi * (n + 1) + 2]["file_path"] + ".png")
            from PIL import Image

            with Image.open(png) as im:
                assert im.size == (W, H) and im.mode == "L"
                expect = np.round(np.clip(ts.frames(view)["frames"][1], 0, 1) * 255).astype(np.uint8)
                assert np.array_equal(np.asarray(im), expect)


def test_poses_axis_conversion_is_its_own_inverse():
    T = cam(3)
    assert np.array_equal(gl_to_cv(cv_to_gl(T)), T)
    assert np.array_equal(cv_to_gl(T)[:, 0], T[:, 0]) and np.array_equal(cv_to_gl(T)[:3, 3], T[:3, 3])


def test_frames_only_dataset_becomes_dl_windows(tmp_path):
    src = make_set(tmp_path / "a.h5", 0, NS)
    out = tmp_path / "evd"
    export_evdnerf(src, out, n_windows=5, **QUIET)
    for s in ("train", "val"):
        (out / f"data_{s}.npy").unlink()
    import_evdnerf(out, tmp_path / "b.h5", **QUIET)
    edges = window_edges(0, NS, 5)
    with TrainingSet(src) as a, TrainingSet(tmp_path / "b.h5") as b:
        for v in a.views:
            assert not b.info(v).has_events and np.array_equal(b.dl_windows(v)[0], edges)
            assert np.array_equal(b.log_change_stack(v, edges), a.log_change_stack(v, edges))
            assert np.array_equal(b.pose(v), a.pose(v))
            with pytest.raises(InputError, match="pre-binned"):
                b.events(v)


def test_foreign_dataset_without_our_extension(tmp_path):
    """A folder as they publish it: 3x4 float32-ish Blender matrices, pickled float events with 0/1
    polarity, padded (V, T, H, W) frames, no thresholds."""
    d = tmp_path / "theirs"
    d.mkdir()
    T = 5
    frames = []
    for v in range(2):
        M = cv_to_gl(cam(v)).astype(np.float32).astype(np.float64)[:3]
        for k in range(T):
            frames.append({"file_path": f"./train/r_{v}_{k}", "time": k / (T - 1), "transform_matrix": M.tolist()})
    (d / "transforms_train.json").write_text(json.dumps({"camera_angle_x": 0.69, "frames": frames}))
    rng = np.random.default_rng(1)
    evs = []
    for v in range(2):
        n = 500
        evs.append(np.stack([np.sort(rng.integers(0, NS, n)).astype(np.float64), rng.integers(0, W, n),
                             rng.integers(0, H, n), rng.integers(0, 2, n)], 1))
    with open(d / "data_train.pkl", "wb") as f:
        pickle.dump(evs, f)
    np.save(d / "data_frames_train.npy", np.zeros((2, T, H, W), np.float32))
    summary = import_evdnerf(d, tmp_path / "b.h5", **QUIET)
    assert summary["views"]["view_01"]["events"] == 500
    with TrainingSet(tmp_path / "b.h5") as ts:
        assert ts.views == ["view_00", "view_01"] and ts.time_range == (0, NS) and ts.thresholds == (0.2, 0.2)
        f = 0.5 * W / np.tan(0.5 * 0.69)
        assert np.allclose(ts.K(), [[f, 0, W / 2], [0, f, H / 2], [0, 0, 1]])
        assert np.allclose(ts.pose(1), cam(1), atol=1e-6)          # re-orthonormalised float32 rotation
        R = ts.pose(1)[:3, :3]
        assert np.abs(R.T @ R - np.eye(3)).max() < 1e-12
        ev = ts.events("view_00")
        assert np.array_equal(ev["t"], evs[0][:, 0].astype(np.int64))
        assert np.array_equal(ev["p"], np.where(evs[0][:, 3] > 0, 1, -1))
    # the same without raw events: the padded (V, T, H, W) frames keep the first T-1
    (d / "data_train.pkl").unlink()
    import_evdnerf(d, tmp_path / "c.h5", c_pos=0.1, c_neg=0.1, **QUIET)
    with TrainingSet(tmp_path / "c.h5") as ts:
        assert ts.dl_windows(0)[1].shape == (T - 1, H, W) and ts.thresholds == (0.1, 0.1)


def test_moving_camera_export_samples_the_trajectory(tmp_path):
    src = make_set(tmp_path / "a.h5", 0, NS, moving=True)
    out = tmp_path / "evd"
    export_evdnerf(src, out, n_windows=4, **QUIET)
    import_evdnerf(out, tmp_path / "b.h5", **QUIET)
    with TrainingSet(tmp_path / "b.h5") as ts:
        t, T = ts.poses("view_00")
        assert t.tolist() == [0, 250_000_000, 500_000_000, 750_000_000, NS]
        assert np.allclose(T[1], cam(0)) and np.allclose(T[2], cam(5)) and np.allclose(T[4], cam(5))
        assert ts.poses("view_01") is None
    assert_same(src, tmp_path / "b.h5", poses=False)


def test_bad_inputs(tmp_path):
    with pytest.raises(InputError, match="not a folder"):
        import_evdnerf(tmp_path / "nope", tmp_path / "x.h5", **QUIET)
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="no transforms_train.json"):
        import_evdnerf(tmp_path / "empty", tmp_path / "x.h5", **QUIET)
    src = make_set(tmp_path / "a.h5", 0, NS, n=100)
    out = tmp_path / "evd"
    export_evdnerf(src, out, n_windows=3, **QUIET)
    with pytest.raises(OutputExistsError):
        export_evdnerf(src, out, n_windows=3, **QUIET)
    with pytest.raises(InputError, match="n_windows"):
        export_evdnerf(src, tmp_path / "e2", n_windows=0, **QUIET)
    evs = np.load(out / "data_val.npy", allow_pickle=True)
    evs[0][0, 1] = W + 3
    np.save(out / "data_val.npy", evs, allow_pickle=True)
    with pytest.raises(FormatError, match="outside the 24x20 image"):
        import_evdnerf(out, tmp_path / "x.h5", **QUIET)
    meta = json.loads((out / "transforms_train.json").read_text())
    meta["frames"][0]["transform_matrix"][0][0] = 3.0
    (out / "transforms_train.json").write_text(json.dumps(meta))
    with pytest.raises(FormatError, match="not a rigid"):
        import_evdnerf(out, tmp_path / "x.h5", **QUIET)
    (out / "data_train.npy").unlink()
    (out / "data_frames_train.npy").unlink()
    with pytest.raises(InputError, match="neither raw events"):
        import_evdnerf(out, tmp_path / "x.h5", **QUIET)
    assert not (tmp_path / "x.h5").exists()


def test_export_takes_training_sets_only_and_io_never_imports_session(tmp_path):
    """The io layer exports a training set; turning a session into one is session/convert's
    job (no import circle between io/evdnerf_format.py and session/convert.py)."""
    import ast
    from pathlib import Path

    import evdnerf_ros.io as io_pkg

    (tmp_path / "sess").mkdir()
    (tmp_path / "sess" / "session.yaml").write_text("format: evdnerf-rig-session\n")
    with pytest.raises(InputError, match="capture session, not a training set.*--format evdnerf"):
        export_evdnerf(tmp_path / "sess", tmp_path / "out", **QUIET)
    assert not (tmp_path / "out").exists()
    offenders = []
    for path in Path(io_pkg.__file__).parent.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom):
                mod = ("." * node.level) + (node.module or "")
                if mod.lstrip(".").split(".")[0] == "session" or "evdnerf_ros.session" in mod:
                    offenders.append(f"{path.name}: {mod}")
    assert offenders == []
