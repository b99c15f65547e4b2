"""Training-set .h5: writer validation, time index, TrainingSet window reads against numpy masks."""

import json

import h5py
import numpy as np
import pytest

from evdnerf_ros.errors import FormatError, InputError, OutputExistsError
from evdnerf_ros.events import log_change_image, log_change_stack, make_events
from evdnerf_ros.io.trainingset import (INDEX_STEP_NS, LAYOUT, TrainingSet, TrainingSetWriter, ViewData,
                                        write_training_set)

W, H = 40, 30
K = np.array([[50.0, 0, 19.5], [0, 50.0, 14.5], [0, 0, 1]])
C_POS, C_NEG = 0.25, 0.15


def pose(angle=0.3, t=(0.1, -0.2, 3.0)):
    c, s = np.cos(angle), np.sin(angle)
    T = np.eye(4)
    T[:3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
    T[:3, 3] = t
    return T


def synth(rng, n, t0, t1, w=W, h=H, *, clumps=True):
    """Sorted events in [t0, t1), with many exact-ms times and ties (index edge cases)."""
    t = rng.integers(t0, t1, n)
    if clumps:
        k = n // 10
        t[:k] = t0 + INDEX_STEP_NS * rng.integers(0, max(1, (t1 - t0) // INDEX_STEP_NS), k)
        t[k:2 * k] = t[2 * k:3 * k]                      # duplicates
    t = np.sort(t)
    return make_events(t, rng.integers(0, w, n), rng.integers(0, h, n), rng.random(n) < 0.55)


T0, T1 = -3_000_000, 250_000_000  # a set may start before 0 and need not be whole ms long


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    rng = np.random.default_rng(7)
    path = tmp_path_factory.mktemp("ts") / "train.h5"
    evs = {"a": synth(rng, 60_000, T0, T1), "b": synth(rng, 1_000, T0 + 50_000_000, T0 + 60_000_000),
           "c": synth(rng, 0, T0, T1)}
    views = [ViewData("a", "train", K, pose(0.1), events=evs["a"], attrs={"offset_ns": np.int64(123)}),
             ViewData("b", "train", K, pose(0.5), events=evs["b"]),
             ViewData("c", "val", K, pose(0.9), events=evs["c"])]
    write_training_set(path, views, width=W, height=H, c_pos=C_POS, c_neg=C_NEG, t_start=T0, t_end=T1,
                       eps=1e-3, provenance={"note": "test", "bags": ["x"]})
    return path, evs


def mask(ev, t0, t1):
    return ev[(ev["t"] >= t0) & (ev["t"] < t1)]


def test_metadata(dataset):
    path, evs = dataset
    with TrainingSet(path) as ts:
        assert ts.views == ["a", "b", "c"] and ts.train_views == ["a", "b"] and ts.val_views == ["c"]
        assert (ts.width, ts.height, ts.thresholds, ts.eps) == (W, H, (C_POS, C_NEG), 1e-3)
        assert ts.time_range == (T0, T1) and ts.duration_ns == T1 - T0
        assert np.array_equal(ts.K(), K) and np.array_equal(ts.K("b"), K)
        assert np.array_equal(ts.pose("b"), pose(0.5)) and ts.poses("b") is None
        assert ts.num_events("a") == evs["a"].size and ts.info(2).name == "c"
        assert ts.info("a").offset_ns == 123 and ts.split(1) == "train"
        assert ts.provenance == {"note": "test", "bags": ["x"]}
        assert ts.normalized_time(np.array([T0, T1])).tolist() == [0.0, 1.0]
        with pytest.raises(InputError, match="no view 'z'"):
            ts.events("z")
        with pytest.raises(InputError, match="out of range"):
            ts.events(5)
    with h5py.File(path) as f:
        assert f.attrs["layout"] == LAYOUT and json.loads(f.attrs["view_names"]) == ["a", "b", "c"]
        d = f["views/a/events/t"]
        assert d.chunks and d.scaleoffset is not None
        idx = f["views/a/events/index"][()]
        assert idx[0] == 0 and idx[-1] == evs["a"].size
        assert idx.size == -(-(T1 - T0) // INDEX_STEP_NS) + 1


def test_window_reads_equal_numpy_masks(dataset):
    path, evs = dataset
    rng = np.random.default_rng(1)
    ev = evs["a"]
    edges_ms = T0 + INDEX_STEP_NS * np.arange(4)
    windows = [(T0, T1), (T0 - 10, T0 + 5), (T1 - 5, T1 + 100), (int(ev["t"][500]), int(ev["t"][500])),
               (int(edges_ms[1]), int(edges_ms[2])), (int(edges_ms[1]) - 1, int(edges_ms[3]) + 1),
               (-10**15, 10**15)]
    windows += [tuple(sorted(rng.integers(T0 - 1_000_000, T1 + 1_000_000, 2).tolist())) for _ in range(60)]
    windows += [(int(a), int(a) + int(d)) for a, d in zip(rng.choice(ev["t"], 30), rng.integers(1, 3_000_000, 30))]
    with TrainingSet(path) as ts:
        for t0, t1 in windows:
            got = ts.events("a", t0, t1)
            assert np.array_equal(got, mask(ev, t0, t1)), (t0, t1)
            i0, i1 = ts.index_range("a", t0, t1)
            assert (i0, i1) == (np.count_nonzero(ev["t"] < t0), max(i0, np.count_nonzero(ev["t"] < t1)))
        assert np.array_equal(ts.events("a"), ev)
        assert np.array_equal(ts.events("b", T0, T1), evs["b"])
        assert ts.events("c").size == 0 and ts.events("c", 0, 10).dtype == ev.dtype
        blocks = list(ts.iter_events("a", T0 + 1_000_000, T1 - 1_000_000, block=7_777))
        assert len(blocks) > 3 and np.array_equal(np.concatenate(blocks), mask(ev, T0 + 1_000_000, T1 - 1_000_000))


def test_log_change_and_event_pixels(dataset):
    path, evs = dataset
    ev = evs["a"]
    rng = np.random.default_rng(2)
    with TrainingSet(path) as ts:
        for _ in range(20):
            t0, t1 = sorted(rng.integers(T0, T1, 2).tolist())
            t1 += 1
            want = log_change_image(ev, W, H, C_POS, C_NEG, t0, t1)
            got = ts.log_change("a", t0, t1)
            assert got.dtype == np.float32 and np.array_equal(got, want)
            sel = mask(ev, t0, t1)
            assert np.array_equal(ts.event_pixels("a", t0, t1),
                                  np.unique(sel["y"].astype(np.int64) * W + sel["x"]))
        edges = np.unique(rng.integers(T0, T1, 9)).astype(np.int64)
        assert np.array_equal(ts.log_change_stack("a", edges), log_change_stack(ev, edges, W, H, C_POS, C_NEG))
        # streamed in small blocks: the same
        import evdnerf_ros.io.trainingset as mod

        old = mod.READ_BLOCK
        mod.READ_BLOCK = 1000
        try:
            edges = np.linspace(T0, T1, 33).astype(np.int64)
            assert np.array_equal(ts.log_change_stack("a", edges), log_change_stack(ev, edges, W, H, C_POS, C_NEG))
        finally:
            mod.READ_BLOCK = old
        assert not ts.log_change("c", T0, T1).any() and ts.event_pixels("c", T0, T1).size == 0
        with pytest.raises(InputError, match="empty"):
            ts.log_change("a", 5, 5)
        with pytest.raises(InputError, match="strictly increasing"):
            ts.log_change_stack("a", np.array([3, 2]))


def test_writer_streaming_truncates_at_t_end(tmp_path):
    rng = np.random.default_rng(3)
    ev = synth(rng, 20_000, 0, 80_000_000)
    path = tmp_path / "s.h5"
    with TrainingSetWriter(path, width=W, height=H, c_pos=0.2, c_neg=0.2, t_start=0, compression="gzip") as w:
        vw = w.add_view("v", split="train", K=K, T_world_cam=pose())
        for i in range(0, ev.size, 3001):
            vw.append(ev[i:i + 3001])
        w.finish(t_end=41_500_001, provenance={})
    with TrainingSet(path) as ts:
        assert ts.time_range == (0, 41_500_001)
        assert np.array_equal(ts.events("v"), mask(ev, 0, 41_500_001))
        assert np.array_equal(ts.events("v", 41_000_000, 10**12), mask(ev, 41_000_000, 41_500_001))
    with h5py.File(path) as f:
        assert f["views/v/events/t"].compression == "gzip"


def test_writer_rejects_bad_input(tmp_path):
    rng = np.random.default_rng(4)
    ev = synth(rng, 100, 0, 1_000_000)
    w = TrainingSetWriter(tmp_path / "x.h5", width=W, height=H, c_pos=0.2, c_neg=0.2, t_start=0, t_end=1_000_000)
    try:
        vw = w.add_view("v", split="train", K=K, T_world_cam=pose())
        with pytest.raises(InputError, match="duplicate view name"):
            w.add_view("v", split="train", K=K, T_world_cam=pose())
        with pytest.raises(InputError, match="split"):
            w.add_view("q", split="test", K=K, T_world_cam=pose())
        bad = pose()
        bad[0, 0] = np.nan
        with pytest.raises(InputError, match="NaN"):
            w.add_view("n", split="train", K=K, T_world_cam=bad)
        shear = pose()
        shear[0, 1] += 0.1
        with pytest.raises(InputError, match="not a rigid"):
            w.add_view("s", split="train", K=K, T_world_cam=shear)
        with pytest.raises(InputError, match="pinhole"):
            w.add_view("k", split="train", K=np.diag([1.0, -1.0, 1.0]), T_world_cam=pose())
        with pytest.raises(InputError, match="not sorted"):
            vw.append(ev[::-1])
        big = ev.copy()
        big["x"][5] = W
        with pytest.raises(InputError, match="outside"):
            vw.append(big)
        vw.append(ev[50:])
        with pytest.raises(InputError, match="before the previous batch"):
            vw.append(ev[:50])
        late = ev[-1:].copy()
        late["t"] = 1_000_000
        with pytest.raises(InputError, match="t_end"):
            vw.append(late)
    finally:
        w.close()


def test_write_training_set_is_atomic(tmp_path):
    path = tmp_path / "t.h5"
    rng = np.random.default_rng(5)
    good = ViewData("v", "train", K, pose(), events=synth(rng, 50, 0, 10_000_000))
    bad = ViewData("w", "train", K, pose(), events=synth(rng, 50, 0, 10_000_000, w=W + 5))
    with pytest.raises(InputError, match="outside"):
        write_training_set(path, [good, bad], width=W, height=H, c_pos=0.2, c_neg=0.2, t_start=0, t_end=10**7)
    assert not path.exists() and list(tmp_path.iterdir()) == []
    write_training_set(path, [good], width=W, height=H, c_pos=0.2, c_neg=0.2, t_start=0, t_end=10**7)
    with pytest.raises(OutputExistsError):
        write_training_set(path, [good], width=W, height=H, c_pos=0.2, c_neg=0.2, t_start=0, t_end=10**7)


def test_moving_camera_frames_and_dl_windows(tmp_path):
    path = tmp_path / "m.h5"
    pt = np.array([0, 5_000_000, 9_000_000], np.int64)
    pT = np.stack([pose(0.1 * i) for i in range(3)])
    frames = {"frames": np.random.default_rng(0).random((2, H, W)).astype(np.float32),
              "t_start": np.array([-5, 5_000_000]), "t_end": np.array([5_000_000, 10_000_000])}
    edges = np.array([0, 4_000_000, 10_000_000], np.int64)
    dl = np.random.default_rng(1).normal(size=(2, H, W)).astype(np.float32)
    views = [ViewData("m", "train", K, pT[0], events=synth(np.random.default_rng(2), 10, 0, 10**7),
                      poses_t=pt, poses_T=pT, frames=frames),
             ViewData("d", "val", K, pose(), dl_edges=edges, dl_windows=dl)]
    write_training_set(path, views, width=W, height=H, c_pos=0.2, c_neg=0.2, t_start=0, t_end=10**7)
    with TrainingSet(path) as ts:
        t, T = ts.poses("m")
        assert np.array_equal(t, pt) and np.array_equal(T, pT) and ts.info("m").moving
        fr = ts.frames("m")
        assert np.array_equal(fr["frames"], frames["frames"]) and fr["t"].tolist() == [2_499_997, 7_500_000]
        assert ts.frames("d") is None and not ts.info("d").has_events
        assert np.array_equal(ts.log_change("d", 0, 4_000_000), dl[0])
        assert np.allclose(ts.log_change("d", 0, 10_000_000), dl.sum(0), atol=1e-6)
        assert np.array_equal(ts.log_change_stack("d", edges), dl)
        assert np.array_equal(ts.event_pixels("d", 0, 4_000_000), np.flatnonzero(dl[0].reshape(-1) != 0))
        with pytest.raises(InputError, match="pre-binned"):
            ts.events("d")
        with pytest.raises(InputError, match="edges"):
            ts.log_change("d", 1, 4_000_000)


def test_reader_rejects_other_files(tmp_path):
    p = tmp_path / "other.h5"
    with h5py.File(p, "w") as f:
        f.attrs["layout"] = "something"
    with pytest.raises(FormatError, match="not a training set"):
        TrainingSet(p)
    (tmp_path / "junk.h5").write_bytes(b"not hdf5")
    with pytest.raises(FormatError, match="HDF5"):
        TrainingSet(tmp_path / "junk.h5")
    with pytest.raises(InputError, match="no such"):
        TrainingSet(tmp_path / "missing.h5")
