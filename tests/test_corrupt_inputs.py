"""Corrupt, crafted and ill-typed input files (issue 12): every reader ends in one line
`evdnerf: error: ...` naming the file (and the key / dataset / view) with exit status 2 --
never a traceback, a huge allocation or a crash -- and a full disk during `convert` leaves
nothing behind."""

import io
import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import h5py
import numpy as np
import pytest
import yaml

from evdnerf_ros.cli import main
from evdnerf_ros.errors import EvdnerfError, InputError
from evdnerf_ros.events import make_events
from evdnerf_ros.events.types import empty_triggers
from evdnerf_ros.io.event_files import EventFile, write_event_file
from evdnerf_ros.io.guard import OutputWriteError
from evdnerf_ros.io.messages import camera_info
from evdnerf_ros.io.rosbag2 import BagWriter
from evdnerf_ros.io.trainingset import TrainingSet, ViewData, write_training_set
from evdnerf_ros.session.layout import SESSION_FORMAT, SESSION_FORMAT_VERSION

# decoders report events they drop from damaged streams as warnings; the error line is what
# these tests check
pytestmark = pytest.mark.filterwarnings("ignore::evdnerf_ros.events.codecs._common.DroppedEventsWarning")

W, H = 32, 24
K = [[40.0, 0.0, 15.5], [0.0, 40.0, 11.5], [0.0, 0.0, 1.0]]
QUIET = {"log": lambda *_: None}


def cli(capsys, *argv):
    """Run the CLI in-process: (exit status, stderr)."""
    capsys.readouterr()
    rc = main([str(a) for a in argv])
    return rc, capsys.readouterr().err


def assert_one_line(rc, err, *names):
    assert "Traceback" not in err, err
    assert rc == 2, (rc, err)
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("evdnerf: error: "), err
    for name in names:
        assert str(name) in lines[0], (name, lines[0])


def assert_clean(rc, err, name):
    """A mutation that may leave a file valid: success, or the one-line error naming it."""
    assert "Traceback" not in err, err
    if rc != 0:
        assert_one_line(rc, err, name)


def events(n=2000, seed=0, t0=10**9):
    rng = np.random.default_rng(seed)
    t = t0 + 1000 * np.sort(rng.integers(0, 400_000, n))        # whole µs: every container carries it
    return make_events(t, rng.integers(0, W, n), rng.integers(0, H, n), rng.random(n) < 0.5)


# =========================================================================== event files


@pytest.fixture(scope="module")
def sources(tmp_path_factory):
    root = tmp_path_factory.mktemp("sources")
    data = EventFile(events(), empty_triggers(), W, H, "npz")
    out = {}
    for name in ("a.npz", "a.h5", "a.raw", "a.bag", "bag2"):
        write_event_file(root / name, data)
        out[name] = root / name
    return out


def mutated(src: Path, dst_dir: Path, data: bytes) -> Path:
    """A copy of `src` (file or rosbag2 folder) whose file (the .mcap of a folder) holds `data`."""
    if src.is_dir():
        dst = dst_dir / src.name
        shutil.copytree(src, dst)
        next(dst.glob("*.mcap")).write_bytes(data)
        return dst
    dst = dst_dir / src.name
    dst.write_bytes(data)
    return dst


def _blob(src: Path) -> bytes:
    return next(src.glob("*.mcap")).read_bytes() if src.is_dir() else src.read_bytes()


def _flips(blob: bytes, seed: int, n: int) -> bytes:
    rng = np.random.default_rng(seed)
    b = bytearray(blob)
    for off in rng.integers(0, len(b), n):
        b[off] ^= 1 << int(rng.integers(0, 8))
    return bytes(b)


MUTATIONS = [("empty", True, lambda b: b"")] + [
    (f"truncated at {f:.0%}", None, lambda b, f=f: b[:int(len(b) * f)]) for f in (0.02, 0.5, 0.97)] + [
    (f"{n} bit(s) flipped, seed {s}", False, lambda b, n=n, s=s: _flips(b, s, n)) for n, s in
    ((1, 1), (1, 2), (4, 3), (4, 4), (32, 5), (32, 6))]


@pytest.mark.parametrize("container", ["a.npz", "a.h5", "a.raw", "a.bag", "bag2"])
def test_damaged_event_files(sources, container, tmp_path, capsys):
    src = sources[container]
    blob = _blob(src)
    for i, (label, must_fail, mutate) in enumerate(MUTATIONS):
        d = tmp_path / f"m{i}"
        d.mkdir()
        path = mutated(src, d, mutate(blob))
        # a truncated RAW ending on a word boundary is a valid, shorter recording
        strict = must_fail or (must_fail is None and container != "a.raw")
        for out, argv in ((None, ("info", path)), (d / "o.npz", ("convert-events", path, d / "o.npz")),
                          (d / "o.png", ("render-events", path, "--start", "0", "--window", "50ms",
                                         "-o", d / "o.png"))):
            rc, err = cli(capsys, *argv)
            (assert_one_line if strict else assert_clean)(rc, err, path)
            if rc and out is not None:
                assert not out.exists(), label
            assert not [p for p in d.iterdir() if "partial" in p.name], label


def _npy(shape, descr="<i8", payload=b"\0" * 16) -> bytes:
    f = io.BytesIO()
    np.lib.format.write_array_header_1_0(f, {"descr": descr, "fortran_order": False, "shape": shape})
    return f.getvalue() + payload


def _npz(path, arrays: dict, raw: dict | None = None) -> Path:
    """An .npz of `arrays` (saved normally) plus `raw` members given as .npy bytes."""
    with zipfile.ZipFile(path, "w") as z:
        for k, v in arrays.items():
            f = io.BytesIO()
            np.save(f, np.asarray(v), allow_pickle=True)
            z.writestr(f"{k}.npy", f.getvalue())
        for k, b in (raw or {}).items():
            z.writestr(f"{k}.npy", b)
    return path


def _good_npz_arrays():
    ev = events(50)
    return dict(t=ev["t"], x=ev["x"], y=ev["y"], p=ev["p"], width=np.int64(W), height=np.int64(H))


NPZ_CASES = [
    # (label, arrays edit, raw members, text expected in the message)
    ("terabyte header", lambda a: a.pop("t"), {"t": _npy((10**12,))}, "declares shape (1000000000000,)"),
    ("header larger than data", lambda a: a.pop("x"), {"x": _npy((50,), "<u2", b"\0" * 10)}, "array x declares"),
    ("bad header", lambda a: a.pop("y"), {"y": b"\x93NUMPY\x01\x00\x10\x00{'descr': <<<}   \n"}, "array y"),
    ("pickled objects", lambda a: a.update(p=np.array([1, -1, None], dtype=object)), None, "pickle"),
    ("float times", lambda a: a.update(t=a["t"].astype(float)), None, "int64 nanoseconds"),
    ("2-D x", lambda a: a.update(x=np.zeros((50, 2), np.uint16)), None, "array x has shape (50, 2)"),
    ("text width", lambda a: a.update(width=np.array("wide")), None, "width"),
    ("zero height", lambda a: a.update(height=np.int64(0)), None, "height: must be >= 1"),
    ("huge width", lambda a: a.update(width=np.int64(10**12)), None, "width: must be"),
    ("width array", lambda a: a.update(width=np.arange(3)), None, "width: expected one integer"),
    ("half the triggers", lambda a: a.update(trigger_t=np.arange(2)), None, "trigger_id"),
    ("x outside", lambda a: a.update(x=np.full(50, W, np.uint16)), None, "x outside"),
]


@pytest.mark.parametrize("label, edit, raw, text", NPZ_CASES, ids=[c[0] for c in NPZ_CASES])
def test_crafted_npz(label, edit, raw, text, tmp_path, capsys):
    arrays = _good_npz_arrays()
    edit(arrays)
    path = _npz(tmp_path / "c.npz", arrays, raw)
    for argv in (("info", path), ("convert-events", path, tmp_path / "o.h5")):
        rc, err = cli(capsys, *argv)
        assert_one_line(rc, err, path, text)
    assert not (tmp_path / "o.h5").exists()


def test_event_times_spanning_ages_are_sized_first(tmp_path, capsys):
    """An h5 output indexes every millisecond between its first and last event: a crafted span
    of 30 years is refused before allocating, naming the output."""
    a = _good_npz_arrays()
    a["t"] = np.linspace(0, 10**18, 50).astype(np.int64)
    path = _npz(tmp_path / "span.npz", a)
    rc, err = cli(capsys, "convert-events", path, tmp_path / "o.h5")
    assert_one_line(rc, err, tmp_path / "o.h5", "needs about")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["span.npz"]


def _h5_events(path, n=50, edit=None):
    ev = events(n)
    with h5py.File(path, "w") as f:
        f.attrs.update(width=W, height=H, layout="evdnerf_ros.events", time_unit="ns")   # as ours are
        g = f.create_group("events")
        for k in ("t", "x", "y", "p"):
            g.create_dataset(k, data=ev[k], maxshape=(None,), chunks=(64,))
        if edit is not None:
            edit(f)
    return path


def _resize_all(f, n):
    for k in ("t", "x", "y", "p"):
        f["events"][k].resize((n,))


def _replace(f, name, data):
    del f[name]
    f[name] = data


H5_CASES = [
    ("terabyte shape", lambda f: _resize_all(f, 10**12), "needs about"),
    ("t is a group", lambda f: (f["events"].__delitem__("t"), f["events"].create_group("t")), "events/t"),
    ("float x", lambda f: _replace(f, "events/x", np.zeros(50)), "events/x has dtype float64"),
    ("2-D p", lambda f: _replace(f, "events/p", np.ones((50, 2), np.int8)), "events/p has shape"),
    ("short y", lambda f: _replace(f, "events/y", np.zeros(10, np.uint16)), "events/y has 10 elements"),
    ("text width", lambda f: f.attrs.__setitem__("width", "wide"), "attribute width"),
    ("NaN height", lambda f: f.attrs.__setitem__("height", np.nan), "attribute height"),
    ("no width", lambda f: f.attrs.__delitem__("width"), "'width' is missing"),
    ("x outside", lambda f: _replace(f, "events/x", np.full(50, 99, np.uint16)), "outside the declared"),
    ("polarity 0", lambda f: _replace(f, "events/p", np.zeros(50, np.int8)), "+1/-1"),
]


@pytest.mark.parametrize("label, edit, text", H5_CASES, ids=[c[0] for c in H5_CASES])
def test_crafted_h5(label, edit, text, tmp_path, capsys):
    path = _h5_events(tmp_path / "c.h5", edit=edit)
    for argv in (("info", path), ("render-events", path, "--start", "0", "--window", "1ms", "-o", tmp_path / "o.png")):
        rc, err = cli(capsys, *argv)
        assert_one_line(rc, err, path, text)


@pytest.mark.parametrize("header, text", [
    (b"% format EVT3;width=0;height=24\n% end\n", "out of range"),
    (b"% format EVT3;width=32;height=99999999\n% end\n", "out of range"),
    (b"% evt 3.0\n% end\n", "no sensor geometry"),
    (b"% format EVT3;width=32;height=24\n% \xff\xfe\n% end\n", "not UTF-8"),
])
def test_crafted_raw_headers(header, text, tmp_path, capsys):
    path = tmp_path / "c.raw"
    path.write_bytes(header + np.array([0x8000, 0x0000], "<u2").tobytes())
    rc, err = cli(capsys, "convert-events", path, tmp_path / "o.npz")
    assert_one_line(rc, err, path, text)


def test_raw_events_outside_the_header_geometry(sources, tmp_path, capsys):
    blob = sources["a.raw"].read_bytes().replace(b"width=32", b"width=16").replace(b"geometry 32x", b"geometry 16x")
    path = tmp_path / "small.raw"
    path.write_bytes(blob)
    rc, err = cli(capsys, "render-events", path, "--start", "0", "--window", "1ms", "-o", tmp_path / "o.png")
    assert_one_line(rc, err, path, "outside the header's 16x24 geometry")


def test_bag_metadata_not_utf8_or_ill_typed(sources, tmp_path, capsys):
    for i, text in enumerate((b"\xff\xfe\x00garbage", b"rosbag2_bagfile_information: [1, 2]\n",
                              b"rosbag2_bagfile_information: {storage_identifier: [mcap]}\n")):
        bag = tmp_path / f"b{i}"
        shutil.copytree(sources["bag2"], bag)
        (bag / "metadata.yaml").write_bytes(text)
        rc, err = cli(capsys, "info", bag)
        assert_one_line(rc, err, bag)


# =========================================================================== training sets


@pytest.fixture(scope="module")
def train_h5(tmp_path_factory):
    """A small training set: two views with events and frames, one moving validation view."""
    path = tmp_path_factory.mktemp("ts") / "t.h5"
    views = []
    for i, (name, split) in enumerate((("view_00", "train"), ("view_01", "train"), ("val_00", "val"))):
        ev = events(3000, seed=i, t0=0)
        T = np.eye(4)
        T[:3, 3] = [i, 0, 2]
        vd = ViewData(name=name, split=split, K=np.array(K), T_world_cam=T, events=ev,
                      frames={"frames": np.full((3, H, W), 0.5, np.float32),
                              "t_start": np.array([0, 10**8, 2 * 10**8]),
                              "t_end": np.array([10**7, 10**8 + 10**7, 2 * 10**8 + 10**7])})
        if split == "val":
            Ts = np.stack([T, T, T])
            Ts[:, 0, 3] = [0, 0.1, 0.2]
            vd.poses_t, vd.poses_T = np.array([0, 10**8, 2 * 10**8]), Ts
        views.append(vd)
    write_training_set(path, views, width=W, height=H, c_pos=0.2, c_neg=0.2, t_start=0, t_end=400_000_000,
                       provenance={"test": True})
    return path


def read_everything(path):
    with TrainingSet(path) as ts:
        ts.provenance
        for v in ts.views:
            ts.frames(v)
            ts.poses(v)
            ts.events(v)
            ts.polarity_count_stack(v, np.linspace(ts.t_start, ts.t_end, 5).astype(np.int64))
            ts.event_pixels(v, ts.t_start, ts.t_end)


def _ts_edit(fn):
    def apply(path):
        with h5py.File(path, "r+") as f:
            fn(f)
    return apply


def _huge_view(f):
    g = f["views/view_00"]
    for k in ("t", "x", "y", "p"):
        d = g["events"][k]
        data = d[()]
        del g["events"][k]
        g["events"].create_dataset(k, data=data, maxshape=(None,), chunks=(1024,)).resize((10**12,))
    g.attrs["num_events"] = 10**12
    idx = g["events/index"][()]
    idx[-1] = 10**12
    _replace(f, "views/view_00/events/index", idx)


def _damage_events(f):
    x = f["views/view_01/events/x"][()]
    x[100] = 999
    _replace(f, "views/view_01/events/x", x)


TS_CASES = [
    ("missing events/x", _ts_edit(lambda f: f["views/view_00/events"].__delitem__("x")), "view_00: events/x"),
    ("K 2x2", _ts_edit(lambda f: _replace(f, "views/view_01/K", np.eye(2))), "view view_01: K"),
    ("K not pinhole", _ts_edit(lambda f: _replace(f, "views/view_01/K", -np.eye(3))), "not a pinhole"),
    ("float times", _ts_edit(lambda f: _replace(f, "views/val_00/events/t",
                                                f["views/val_00/events/t"][()].astype(float))), "events/t has dtype"),
    ("text width", _ts_edit(lambda f: f.attrs.__setitem__("width", "wide")), "attribute width"),
    ("NaN threshold", _ts_edit(lambda f: f.attrs.__setitem__("c_pos", np.nan)), "attribute c_pos"),
    ("huge threshold", _ts_edit(lambda f: f.attrs.__setitem__("c_neg", 1e30)), "attribute c_neg"),
    ("t_end before t_start", _ts_edit(lambda f: f.attrs.__setitem__("t_end", np.int64(-5))), "t_end=-5"),
    ("zero index step", _ts_edit(lambda f: f.attrs.__setitem__("index_step_ns", 0)), "index_step_ns"),
    ("huge time range", _ts_edit(lambda f: f.attrs.__setitem__("t_end", np.int64(2**61))), "needs about"),
    ("view_names not JSON", _ts_edit(lambda f: f.attrs.__setitem__("view_names", "[view_00")), "view_names"),
    ("unknown view", _ts_edit(lambda f: f.attrs.__setitem__("view_names", '["view_00", "nope"]')), "'nope'"),
    ("bad split", _ts_edit(lambda f: f["views/view_00"].attrs.__setitem__("split", "test")), "split 'test'"),
    ("index not monotone", _ts_edit(lambda f: f["views/view_00/events/index"].__setitem__(3, 10**6)),
     "time index"),
    ("terabyte view", _ts_edit(_huge_view), "needs about"),
    ("pixel outside", _ts_edit(_damage_events), "pixels outside 32x24"),
    ("frames of another size", _ts_edit(lambda f: _replace(f, "views/view_00/frames/frames", np.zeros((3, 2, 2)))),
     "frames/frames has shape"),
    ("NaN pose", _ts_edit(lambda f: f["views/val_00/poses/T_world_cam"].__setitem__((1, 0, 0), np.nan)),
     "poses/T_world_cam[1]"),
    ("provenance not JSON", _ts_edit(lambda f: _replace(f, "provenance", "{oops")), "provenance"),
    ("not a training set", _ts_edit(lambda f: f.attrs.__setitem__("layout", "other")), "not a training set"),
    ("empty", lambda p: p.write_bytes(b""), "empty"),
    ("truncated", lambda p: p.write_bytes(p.read_bytes()[:5000]), "not a readable HDF5"),
]


@pytest.mark.parametrize("label, damage, text", TS_CASES, ids=[c[0] for c in TS_CASES])
def test_damaged_training_sets(train_h5, label, damage, text, tmp_path):
    path = tmp_path / "t.h5"
    shutil.copy(train_h5, path)
    read_everything(path)                  # the copy is fine before the damage
    damage(path)
    with pytest.raises(EvdnerfError) as info:
        read_everything(path)
    msg = str(info.value)
    assert str(path) in msg and text in msg and "\n" not in msg, msg


def test_bit_flipped_training_sets(train_h5, tmp_path):
    blob = train_h5.read_bytes()
    for seed in range(24):
        path = tmp_path / f"f{seed}.h5"
        path.write_bytes(_flips(blob, 100 + seed, 1 + seed % 8))
        try:
            read_everything(path)
        except EvdnerfError as exc:
            assert str(path) in str(exc) and "\n" not in str(exc)


def test_train_cli_on_a_damaged_set(train_h5, tmp_path, capsys):
    path = tmp_path / "t.h5"
    shutil.copy(train_h5, path)
    _ts_edit(lambda f: f["views/view_00/events"].__delitem__("x"))(path)
    rc, err = cli(capsys, "train", path, "-o", tmp_path / "run", "--iters", "1", "--no-eval")
    assert_one_line(rc, err, path, "events/x")


# =========================================================================== sessions


def write_view_bag(path, offset, n=800, seed=0):
    ev = events(n, seed, t0=offset)
    with BagWriter(path) as bag:
        bag.write("/event_camera/camera_info", "sensor_msgs/msg/CameraInfo",
                  camera_info(W, H, K, stamp_ns=offset), offset)
        bag.write_events("/event_camera/events", ev, width=W, height=H)


def cam_pose(x):
    T = np.eye(4)
    T[:3, :3] = [[1, 0, 0], [0, -1, 0], [0, 0, -1]]
    T[:3, 3] = [x, 0.0, 2.0]
    return T


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    """A hand-made synced session: two views (bags + frames files)."""
    root = tmp_path_factory.mktemp("session") / "s"
    root.mkdir()
    (root / "frames").mkdir()
    views = []
    for i, name in enumerate(("a", "b")):
        offset = (i + 1) * 10**9
        write_view_bag(root / name, offset, seed=i)
        np.savez(root / "frames" / f"{name}.npz", frames=np.full((2, H, W), 0.5, np.float32),
                 t_start=np.array([offset, offset + 10**8]), t_end=np.array([offset + 10**7, offset + 11 * 10**7]))
        views.append({"name": name, "bag": name, "split": "train" if i == 0 else "val", "azimuth_deg": 90.0 * i,
                      "T_world_cam": cam_pose(0.1 * i).tolist(), "frames": f"frames/{name}.npz",
                      "sync": {"offset_ns": offset}})
    data = {"format": SESSION_FORMAT, "format_version": SESSION_FORMAT_VERSION,
            "camera": {"width": W, "height": H, "K": K, "D": [0.0] * 5,
                       "topics": {"events": "/event_camera/events"}},
            "thresholds": {"c_pos": 0.3, "c_neg": 0.2, "eps": 0.001},
            "time": {"motion_start_ns": 0, "motion_end_ns": 300_000_000}, "views": views}
    (root / "session.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
    return root


def _set(key_path, value):
    def edit(d):
        node = d
        for k in key_path[:-1]:
            node = node[k]
        if value is KeyError:
            del node[key_path[-1]]
        else:
            node[key_path[-1]] = value
    return edit


YAML_CASES = [
    ("camera.width", _set(("camera", "width"), "wide"), "camera.width: expected a number"),
    ("camera.height", _set(("camera", "height"), 2.5), "camera.height: expected a whole number"),
    ("camera.width 1e30", _set(("camera", "width"), 10**30), "camera.width: must be"),
    ("camera missing", _set(("camera",), KeyError), "camera: must be a mapping"),
    ("camera list", _set(("camera",), [1, 2]), "camera: must be a mapping"),
    ("camera.K", _set(("camera", "K"), [[1, 2], [3, 4]]), "camera.K: must be a 3x3 matrix"),
    ("camera.K text", _set(("camera", "K"), [["a", 0, 0], [0, 1, 0], [0, 0, 1]]), "camera.K: entry [0][0]"),
    ("camera.D", _set(("camera", "D"), "none"), "camera.D"),
    ("camera.topics", _set(("camera", "topics"), ["/a"]), "camera.topics: must be a mapping"),
    ("topic not absolute", _set(("camera", "topics", "events"), 5), "camera.topics.events"),
    ("c_pos NaN", _set(("thresholds", "c_pos"), float("nan")), "thresholds.c_pos: must be a finite number"),
    ("c_neg inf", _set(("thresholds", "c_neg"), float("inf")), "thresholds.c_neg"),
    ("c_pos 1e30", _set(("thresholds", "c_pos"), 1e30), "thresholds.c_pos: must be"),
    ("c_pos negative", _set(("thresholds", "c_pos"), -0.2), "thresholds.c_pos: must be > 0"),
    ("c_pos 401 digits", _set(("thresholds", "c_pos"), 10**400), "thresholds.c_pos: a 401-digit number"),
    ("K 401 digits", _set(("camera", "K"), [[10**400, 0, 0], [0, 1, 0], [0, 0, 1]]), "camera.K: entry [0][0]"),
    ("D 401 digits", _set(("camera", "D"), [10**400]), "camera.D"),
    ("c_pos text", _set(("thresholds", "c_pos"), "1e-1"), "thresholds.c_pos: expected a number, got the text"),
    ("eps bool", _set(("thresholds", "eps"), True), "thresholds.eps: expected a number"),
    ("time list", _set(("time",), [0, 1]), "time: must be a mapping"),
    ("motion_start text", _set(("time", "motion_start_ns"), "soon"), "time.motion_start_ns"),
    ("motion_end before start", _set(("time", "motion_end_ns"), -5), "time.motion_end_ns"),
    ("servo list", _set(("servo",), ["x"]), "servo: must be a mapping"),
    ("scene_bounds", _set(("scene_bounds",), [[0, 0, 0]]), "scene_bounds"),
    ("views mapping", _set(("views",), {"a": 1}), "views: must be a non-empty list"),
    ("views empty", _set(("views",), []), "views: must be a non-empty list"),
    ("view a list", _set(("views", 1), [1, 2]), "views[1]: must be a mapping"),
    ("view name number", _set(("views", 0, "name"), 7), "views[0].name"),
    ("view name slash", _set(("views", 0, "name"), "a/b"), "views[0].name"),
    ("view split", _set(("views", 1, "split"), "test"), "views[1].split"),
    ("view bag list", _set(("views", 1, "bag"), ["b"]), "views[1].bag"),
    ("view pose text", _set(("views", 1, "T_world_cam"), "identity"), "views[1].T_world_cam: must be a 4x4"),
    ("view pose NaN", _set(("views", 0, "T_world_cam"), [[float("nan")] * 4] * 4),
     "views[0].T_world_cam: contains NaN"),
    ("view pose 1e30", _set(("views", 0, "T_world_cam"), [[1e30] * 4] * 4), "views[0].T_world_cam"),
    ("view pose not rigid", _set(("views", 0, "T_world_cam"), (2 * np.eye(4)).tolist()), "not a rigid transform"),
    ("azimuth text", _set(("views", 1, "azimuth_deg"), "east"), "views[1].azimuth_deg"),
    ("frames number", _set(("views", 1, "frames"), 3), "views[1].frames"),
    ("sync list", _set(("views", 0, "sync"), [1]), "views[0].sync: must be a mapping"),
    ("sync offset float", _set(("views", 1, "sync", "offset_ns"), 1.5), "views[1].sync.offset_ns"),
    ("sync offset 1e30", _set(("views", 1, "sync", "offset_ns"), 10**30), "views[1].sync.offset_ns"),
    ("ground_truth text", _set(("views", 0, "ground_truth"), "none"), "views[0].ground_truth"),
    ("format_version text", _set(("format_version",), "1"), "format_version"),
]


@pytest.mark.parametrize("label, edit, text", YAML_CASES, ids=[c[0] for c in YAML_CASES])
def test_ill_typed_session_yaml(session, label, edit, text, tmp_path, capsys):
    s = tmp_path / "s"
    shutil.copytree(session, s)
    data = yaml.safe_load((s / "session.yaml").read_text())
    edit(data)
    (s / "session.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
    for argv in (("convert", s, "-o", tmp_path / "o.h5"), ("sync", s, "--plot", tmp_path / "p.png")):
        rc, err = cli(capsys, *argv)
        assert_one_line(rc, err, s / "session.yaml", text)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s"]


@pytest.mark.parametrize("label, content, text", [
    ("not UTF-8", b"format: evdnerf-rig-session\ncamera: {width: 3\xff2}\n", "not UTF-8"),
    ("empty", b"", "not a session file"),
    ("YAML syntax", b"format: [unclosed\n", "not valid YAML"),
    ("deep nesting", b"[" * 1000, "nested too deeply"),
    ("a list", b"- 1\n- 2\n", "not a session file"),
])
def test_unreadable_session_yaml(session, label, content, text, tmp_path, capsys):
    s = tmp_path / "s"
    shutil.copytree(session, s)
    (s / "session.yaml").write_bytes(content)
    for argv in (("convert", s, "-o", tmp_path / "o.h5"), ("sync", s)):
        rc, err = cli(capsys, *argv)
        assert_one_line(rc, err, s / "session.yaml", text)


def test_an_absurd_motion_window_is_sized_first(session, tmp_path, capsys):
    s = tmp_path / "s"
    shutil.copytree(session, s)
    data = yaml.safe_load((s / "session.yaml").read_text())
    data["time"]["motion_end_ns"] = 2**61
    (s / "session.yaml").write_text(yaml.safe_dump(data))
    rc, err = cli(capsys, "convert", s, "-o", tmp_path / "o.h5")
    assert_one_line(rc, err, tmp_path / "o.h5", "needs about")


def test_the_session_converts(session, tmp_path, capsys):
    rc, err = cli(capsys, "convert", session, "-o", tmp_path / "o.h5")
    assert rc == 0, err
    read_everything(tmp_path / "o.h5")


@pytest.mark.parametrize("label, damage, text", [
    ("terabyte frames", lambda p: _npz(p, {"t_start": [0], "t_end": [1]}, {"frames": _npy((10**6, H, W), "<f4")}),
     "declares shape"),
    ("bit flipped", lambda p: p.write_bytes(_flips(p.read_bytes(), 7, 8)), "frames"),
    ("truncated", lambda p: p.write_bytes(p.read_bytes()[:300]), "not a readable .npz"),
    ("NaN frames", lambda p: np.savez(p, frames=np.full((2, H, W), np.nan, np.float32), t_start=[0, 1],
                                      t_end=[1, 2]), "NaN"),
    ("float times", lambda p: np.savez(p, frames=np.zeros((2, H, W), np.float32), t_start=[0.5, 1.0],
                                       t_end=[1, 2]), "t_start must be"),
])
def test_damaged_frames_file(session, label, damage, text, tmp_path, capsys):
    s = tmp_path / "s"
    shutil.copytree(session, s)
    damage(s / "frames" / "b.npz")
    rc, err = cli(capsys, "convert", s, "-o", tmp_path / "o.h5")
    assert_one_line(rc, err, s / "frames" / "b.npz", text)
    assert not (tmp_path / "o.h5").exists()


# =========================================================================== other text files


def test_non_utf8_and_ill_typed_text_files(tmp_path, capsys):
    from evdnerf_ros.io.poses import load_poses

    (tmp_path / "p.yaml").write_bytes(b"poses:\n  - {t: 0.0, position: [0, 0, 1], orientation: [0, 0, 0, 1]} \xe9\n")
    (tmp_path / "p.csv").write_bytes(b"t_ns,x,y,z,qx,qy,qz,qw\n0,0,0,1,0,0,0,1\n\x00\xff\n")
    (tmp_path / "big.csv").write_text("t_ns,x,y,z,qx,qy,qz,qw\n0,0,0,1,0,0,0,1\n" + "9" * 40 + ",0,0,1,0,0,0,1\n")
    (tmp_path / "deep.yaml").write_text("[" * 1000)
    (tmp_path / "huge.yaml").write_text("poses:\n  - {t: 0, position: [1" + "0" * 400 + ", 0, 1], "
                                        "orientation: [0, 0, 0, 1]}\n")
    (tmp_path / "t.yaml").write_text("poses:\n  - {t_ns: 100000000000000000000000, position: [0, 0, 1], "
                                     "orientation: [0, 0, 0, 1]}\n")
    for name, text in (("p.yaml", "not UTF-8"), ("p.csv", "not UTF-8"), ("big.csv", r"2\*\*62"),
                       ("deep.yaml", "YAML"), ("t.yaml", "t_ns"), ("huge.yaml", "position")):
        with pytest.raises(InputError, match=text) as info:
            load_poses(tmp_path / name)
        assert str(tmp_path / name) in str(info.value)
    src = tmp_path / "paper"
    src.mkdir()
    for content, text in ((b'{"frames": [\xff]}', "not UTF-8"), (b"[" * 100_000, "JSON"),
                          (b'{"frames": [{"time": "x"}]}', "frames[0].time"),
                          (b'{"frames": [{"time": 0}], "evdnerf_ros": {"t_start_ns": "a"}}', "t_start_ns"),
                          (b'{"frames": [{"time": 0}], "evdnerf_ros": {"t_start_ns": 0, "t_end_ns": 9, "width": 2, '
                           b'"height": 2, "c_pos": 1' + b"0" * 400 + b"}}", "c_pos: a 401-digit number")):
        (src / "transforms_train.json").write_bytes(content)
        rc, err = cli(capsys, "import-evdnerf", src, "-o", tmp_path / "o.h5")
        assert_one_line(rc, err, src / "transforms_train.json", text)


# =========================================================================== full disk


def _fsize_limit(limit):
    def pre():
        import resource
        import signal

        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)     # writes past the limit fail with EFBIG
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))
    return pre


def test_full_disk_during_convert(session, tmp_path):
    """A file-size limit (what a full disk looks like to a writer) ends `convert` in one line
    naming the output, exit 2, nothing left behind; before the guard libhdf5 segfaulted."""
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    main(["convert", str(session), "-o", str(tmp_path / "full.h5")])
    size = (tmp_path / "full.h5").stat().st_size
    env = dict(os.environ, PYTHONDONTWRITEBYTECODE="1")
    for limit in (size // 2, 1000):       # fails while writing / refused up front
        out = out_dir / "o.h5"
        p = subprocess.run([sys.executable, "-m", "evdnerf_ros", "convert", str(session), "-o", str(out)],
                           preexec_fn=_fsize_limit(limit), capture_output=True, text=True, env=env, timeout=120,
                           cwd=Path(__file__).resolve().parents[1])
        lines = p.stderr.strip().splitlines()
        assert p.returncode == 2, p.stderr[-2000:]
        assert len(lines) == 1 and lines[0].startswith(f"evdnerf: error: {out}:"), p.stderr
        assert "File too large" in lines[0] or "can be written" in lines[0], lines[0]
        assert list(out_dir.iterdir()) == []


def test_failed_hdf5_writes_never_reach_hdf5(tmp_path, monkeypatch):
    """Writes that fail after some bytes (ENOSPC): write_h5 raises OutputWriteError naming the
    output, HDF5 closes cleanly and the atomic helper leaves nothing."""
    import errno

    from evdnerf_ros.io import guard
    from evdnerf_ros.io.h5events import write_h5

    real = os.pwrite
    budget = {"left": 20_000}

    def pwrite(fd, data, offset):
        if budget["left"] < len(data):
            raise OSError(errno.ENOSPC, "No space left on device")
        budget["left"] -= len(data)
        return real(fd, data, offset)

    monkeypatch.setattr(guard.os, "pwrite", pwrite)
    ev = events(200_000, seed=3)
    with pytest.raises(OutputWriteError, match=r"o.h5: writing failed: No space left on device"):
        write_h5(tmp_path / "o.h5", ev, W, H)
    assert list(tmp_path.iterdir()) == []


def test_guarded_file_keeps_failed_writes_readable(tmp_path, monkeypatch):
    """After a failed write HDF5 may read back what it wrote: it must see its latest bytes."""
    import errno

    from evdnerf_ros.io import guard

    g = guard.GuardedFile(tmp_path / "f.bin", display=tmp_path / "out.h5")
    g.write(b"a" * 100)
    monkeypatch.setattr(guard.os, "pwrite", lambda *a: (_ for _ in ()).throw(OSError(errno.ENOSPC, "full")))
    g.seek(50)
    g.write(b"b" * 100)          # fails: kept in memory
    g.seek(120)
    g.write(b"c" * 10)
    g.seek(50)
    g.write(b"d" * 20)           # rewrites the start of the first failed write
    g.seek(0)
    assert g.read(150) == b"a" * 50 + b"d" * 20 + b"b" * 50 + b"c" * 10 + b"b" * 20
    with pytest.raises(OutputWriteError, match=r"out.h5: writing failed: full"):
        g.check()
    g.close()
