"""`evdnerf convert`: session -> training set; dL images equal those computed from the bags."""

import shutil

import numpy as np
import pytest
import yaml

from evdnerf_ros.errors import EvdnerfError, FormatError, InputError, OutputExistsError
from evdnerf_ros.events import log_change_image, log_change_stack, make_events, polarity_counts, window_edges
from evdnerf_ros.io.messages import camera_info, header, pose_stamped
from evdnerf_ros.io.rosbag2 import BagWriter, read_events
from evdnerf_ros.io.trainingset import TrainingSet
from evdnerf_ros.io.typestore import ros2_typestore
from evdnerf_ros.session.convert import (ConvertOptions, convert_session, detect_motion_end, downsample_K,
                                         run_convert)
from evdnerf_ros.session.layout import SESSION_FORMAT, SESSION_FORMAT_VERSION, load_session
from evdnerf_ros.sim.simulate import SimulationOptions, simulate_session

OPTS = SimulationOptions(views=2, val_views=1, resolution=(48, 36), frame_rate_hz=10, blur_samples=2, gt_times=0,
                         supersample=1, jobs=1, min_step_ns=2_000_000)
QUIET = {"log": lambda *_: None}


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    out = tmp_path_factory.mktemp("sim") / "fork"
    simulate_session("fork", out, OPTS, log=lambda *_: None)
    return out


@pytest.fixture(scope="module")
def train_h5(sim, tmp_path_factory):
    out = tmp_path_factory.mktemp("conv") / "train.h5"
    summary = run_convert(sim, out, offsets="ground-truth", **QUIET)
    return out, summary


def copy_session(src, dst, edit=None):
    shutil.copytree(src, dst)
    if edit is not None:
        p = dst / "session.yaml"
        data = yaml.safe_load(p.read_text())
        edit(data)
        p.write_text(yaml.safe_dump(data, sort_keys=False))
    return dst


def gt_offsets(session_dir):
    s = load_session(session_dir)
    return {v.name: v.ground_truth["clock_offset_ns"] + s.time["motion_start_ns"] for v in s.views}


def no_partial(folder):
    return [p.name for p in folder.iterdir() if "partial" in p.name or p.suffix == ".h5"]


# --------------------------------------------------------------------------- the simulated session


def test_dl_images_equal_those_from_the_bags(sim, train_h5):
    out, summary = train_h5
    session = load_session(sim)
    offsets = gt_offsets(sim)
    assert summary["window_source"] == "session-time" and summary["offsets_source"] == "ground-truth"
    t_end = session.time["motion_end_ns"] - session.time["motion_start_ns"]
    edges = window_edges(0, t_end, 16)
    with TrainingSet(out) as ts:
        assert ts.views == [v.name for v in session.views] and ts.time_range == (0, t_end)
        assert [ts.split(v) for v in ts.views] == ["train", "train", "val"]
        assert (ts.width, ts.height, ts.thresholds) == (48, 36, (session.c_pos, session.c_neg))
        for v in session.views:
            ev = read_events(v.bag).events.copy()
            ev["t"] -= offsets[v.name]
            ev = ev[(ev["t"] >= 0) & (ev["t"] < t_end)]
            assert ev.size > 1000
            assert np.array_equal(ts.events(v.name), ev)
            want = log_change_stack(ev, edges, 48, 36, session.c_pos, session.c_neg)
            assert np.array_equal(ts.log_change_stack(v.name, edges), want)
            a, b = int(edges[3]), int(edges[5])
            assert np.array_equal(ts.log_change(v.name, a, b),
                                  log_change_image(ev, 48, 36, session.c_pos, session.c_neg, a, b))
            assert np.allclose(ts.log_change(v.name, a, b), want[3] + want[4], atol=1e-5)
            assert np.array_equal(ts.K(v.name), session.K) and np.array_equal(ts.pose(v.name), v.T_world_cam)
            assert ts.info(v.name).offset_ns == offsets[v.name] and not ts.info(v.name).moving
            fr = ts.frames(v.name)
            with np.load(v.frames) as z:
                assert np.array_equal(fr["frames"], z["frames"])
                assert np.array_equal(fr["t_start"], z["t_start"] - offsets[v.name])
        prov = ts.provenance
        assert prov["offsets_source"] == "ground-truth" and len(prov["session_yaml_sha256"]) == 64
        assert prov["views"]["view_01"]["offset_ns"] == offsets["view_01"]
        assert prov["views"]["view_01"]["bag"].endswith("view_01") and prov["software_version"]


def test_downsampling_sums_2x2_blocks(sim, train_h5, tmp_path):
    out = tmp_path / "half.h5"
    run_convert(sim, out, offsets="ground-truth", downsample=2, **QUIET)
    with TrainingSet(train_h5[0]) as full, TrainingSet(out) as half:
        assert (half.width, half.height, half.downsample) == (24, 18, 2)
        edges = window_edges(full.t_start, full.t_end, 8)
        for v in full.views:
            f = full.log_change_stack(v, edges).astype(np.float64)
            # sum counts per polarity: compare as counts to avoid float re-association
            cp, cn = full.c_pos, full.c_neg
            ev = full.events(v)
            evh = half.events(v)
            assert np.array_equal(evh["t"], ev["t"]) and np.array_equal(evh["x"], ev["x"] // 2)
            blocks = f.reshape(8, 18, 2, 24, 2).sum(axis=(2, 4))
            got = half.log_change_stack(v, edges)
            assert np.allclose(got, blocks, atol=1e-5)
            for k in range(8):   # exactly: C+ and C- times the 2x2 block sums of the full-size counts
                n = polarity_counts(full.events(v, int(edges[k]), int(edges[k + 1])), 48, 36)
                n = n.reshape(2, 18, 2, 24, 2).sum(axis=(2, 4))
                assert np.array_equal(got[k], (cp * n[0] - cn * n[1]).astype(np.float32))
            K = full.K(v)
            assert np.allclose(half.K(v), [[K[0, 0] / 2, 0, (K[0, 2] + 0.5) / 2 - 0.5],
                                           [0, K[1, 1] / 2, (K[1, 2] + 0.5) / 2 - 0.5], [0, 0, 1]])
            assert half.frames(v)["frames"].shape[1:] == (18, 24)


def test_downsample_K_matches_pixel_centres():
    K = np.array([[100.0, 0, 63.5], [0, 90.0, 47.5], [0, 0, 1]])
    K2 = downsample_K(K, 2)
    # a point projecting to the centre of old pixel pair (2j, 2j+1) lands on new pixel j
    for u_old_pair, j in ((0, 0), (10, 5), (126, 63)):
        X = np.array([(u_old_pair + 0.5 - K[0, 2]) / K[0, 0], 0.0, 1.0])
        assert (K2 @ X)[0] == pytest.approx(j)
    assert K2[2].tolist() == [0, 0, 1]


def test_missing_sync_asks_for_evdnerf_sync(sim, tmp_path):
    out = tmp_path / "x.h5"
    with pytest.raises(InputError, match=r"no sync record.*evdnerf sync"):
        run_convert(sim, out, **QUIET)
    assert not out.exists() and no_partial(tmp_path) == []


def test_sync_offsets_and_automatic_end(sim, train_h5, tmp_path):
    offsets = gt_offsets(sim)

    def edit(d):
        for v in d["views"]:
            v["sync"] = {"offset_ns": offsets[v["name"]], "method": "test", "confidence": 1.0}
        d["time"]["motion_end_ns"] = None

    s2 = copy_session(sim, tmp_path / "synced", edit)
    out = tmp_path / "auto.h5"
    summary = run_convert(s2, out, **QUIET)
    assert summary["window_source"] == "rate-floor" and summary["offsets_source"] == "sync"
    with TrainingSet(out) as ts, TrainingSet(train_h5[0]) as ref:
        # the motion ends (minimum jerk, fading) at t = 1 s; the rate falls to 0 a little before
        assert 0.9e9 <= ts.t_end <= 1.0e9 and ts.t_start == 0
        for v in ts.views:
            assert np.array_equal(ts.events(v), ref.events(v, 0, ts.t_end))
        assert ts.provenance["window"]["source"] == "rate-floor"
        assert ts.provenance["views"]["view_00"]["sync"]["method"] == "test"
    # a given window
    out2 = tmp_path / "win.h5"
    run_convert(s2, out2, window=(-50_000_000, 300_000_000), **QUIET)
    with TrainingSet(out2) as ts, TrainingSet(train_h5[0]) as ref:
        assert ts.time_range == (-50_000_000, 300_000_000)
        assert np.array_equal(ts.events("val_00", 0, 300_000_000), ref.events("val_00", 0, 300_000_000))


def test_detect_motion_end_on_a_rate_curve():
    rng = np.random.default_rng(0)
    bin_ns = 10_000_000
    counts = rng.poisson(20, 300)                     # floor 20 per bin, bins -1 s .. 2 s
    counts[100:180] += 400                            # motion from 0 to 0.8 s
    end, info = detect_motion_end(counts, -100, bin_ns, 0, (-1_000_000_000, 1_999_999_999))
    assert end == 800_000_000 and info["rate_fell_back"]
    with pytest.raises(InputError, match="no motion"):
        detect_motion_end(rng.poisson(20, 300), -100, bin_ns, 0, (-1_000_000_000, 1_999_999_999))


def test_export_evdnerf_format_from_a_session(sim, train_h5, tmp_path):
    from evdnerf_ros.io.evdnerf_format import import_evdnerf

    out = tmp_path / "evd"
    run_convert(sim, out, fmt="evdnerf", offsets="ground-truth", n_windows=10, **QUIET)
    names = sorted(p.name for p in out.iterdir() if p.name != ".evdnerf-output")   # the folder's marker
    assert names == ["data_frames_train.npy", "data_frames_val.npy", "data_train.npy", "data_val.npy", "train",
                     "transforms_train.json", "transforms_val.json", "val"]
    assert np.load(out / "data_frames_train.npy").shape == (2, 10, 36, 48)
    back = tmp_path / "back.h5"
    import_evdnerf(out, back, **QUIET)
    with TrainingSet(back) as b, TrainingSet(train_h5[0]) as a:
        for v in a.views:
            assert np.array_equal(a.events(v), b.events(v)) and np.array_equal(a.pose(v), b.pose(v))
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []


def test_truncated_bag_gives_the_documented_error(sim, tmp_path):
    s2 = copy_session(sim, tmp_path / "trunc")
    mcap = next((s2 / "view_01").glob("*.mcap"))
    data = mcap.read_bytes()
    mcap.write_bytes(data[: len(data) // 2])
    out = tmp_path / "t.h5"
    with pytest.raises(FormatError, match=r"convert: view view_01 .*truncated"):
        run_convert(s2, out, offsets="ground-truth", **QUIET)
    assert not out.exists() and no_partial(tmp_path) == []


def test_offset_beyond_the_recording(sim, tmp_path):
    offsets = gt_offsets(sim)
    offsets["val_00"] += 60_000_000_000
    out = tmp_path / "o.h5"
    with pytest.raises(InputError, match=r"view val_00 .*beyond the recording"):
        convert_session(sim, out, ConvertOptions(offsets=offsets), **QUIET)
    assert not out.exists()


def test_intrinsics_mismatch_and_output_exists(sim, tmp_path):
    def edit(d):
        d["camera"]["K"][0][0] *= 1.01

    s2 = copy_session(sim, tmp_path / "k", edit)
    with pytest.raises(InputError, match="disagrees with session.yaml"):
        run_convert(s2, tmp_path / "k.h5", offsets="ground-truth", **QUIET)
    out = tmp_path / "ok.h5"
    run_convert(s2, out, offsets="ground-truth", intrinsics="session", frames=False, **QUIET)
    with TrainingSet(out) as ts:
        assert ts.K()[0, 0] == pytest.approx(load_session(s2).K[0, 0]) and ts.frames("view_00") is None
    with pytest.raises(OutputExistsError):
        run_convert(s2, out, offsets="ground-truth", intrinsics="session", **QUIET)
    with pytest.raises(InputError, match="ground_truth"):
        copy_session(sim, tmp_path / "nogt", lambda d: [v.pop("ground_truth") for v in d["views"]])
        run_convert(tmp_path / "nogt", tmp_path / "g.h5", offsets="ground-truth", **QUIET)


# --------------------------------------------------------------------------- hand-made sessions

W, H = 32, 24
K = [[40.0, 0.0, 15.5], [0.0, 40.0, 11.5], [0.0, 0.0, 1.0]]


def cam_pose(x):
    T = np.eye(4)
    T[:3, :3] = [[1, 0, 0], [0, -1, 0], [0, 0, -1]]
    T[:3, 3] = [x, 0.0, 2.0]
    return T


def write_view_bag(path, offset, *, size=(W, H), events=True, cinfo=True, poses=None, n=3000, seed=0):
    rng = np.random.default_rng(seed)
    t = offset + 1000 * np.sort(rng.integers(0, 400_000, n))         # 0 .. 0.4 s, whole µs
    ev = make_events(t, rng.integers(0, size[0], n), rng.integers(0, size[1], n), rng.random(n) < 0.5)
    with BagWriter(path) as bag:
        if cinfo:
            bag.write("/event_camera/camera_info", "sensor_msgs/msg/CameraInfo",
                      camera_info(size[0], size[1], K, stamp_ns=offset), offset)
        for stamp, msg in poses or []:
            bag.write("/rig/camera_pose", "geometry_msgs/msg/PoseStamped", msg, stamp)
        if events:
            bag.write_events("/event_camera/events", ev, width=size[0], height=size[1])
    return ev


def make_session(root, specs):
    """specs: list of dicts name, offset, and write_view_bag kwargs; sync offsets = offset."""
    root.mkdir()
    views = []
    for i, sp in enumerate(specs):
        sp = dict(sp)
        name, offset = sp.pop("name"), sp.pop("offset")
        T = sp.pop("T", cam_pose(i * 0.1))
        write_view_bag(root / name, offset, seed=i, **sp)
        views.append({"name": name, "bag": name, "split": "train" if i < 2 else "val",
                      "T_world_cam": T.tolist(), "sync": {"offset_ns": offset}})
    data = {"format": SESSION_FORMAT, "format_version": SESSION_FORMAT_VERSION,
            "camera": {"width": W, "height": H, "K": K, "D": [0.0] * 5},
            "thresholds": {"c_pos": 0.3, "c_neg": 0.2}, "time": {}, "views": views}
    (root / "session.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
    return root


def test_hand_made_session_converts(tmp_path):
    s = make_session(tmp_path / "s", [{"name": "a", "offset": 5_000_000_000}, {"name": "b", "offset": 7_000_000},
                                      {"name": "c", "offset": 123_000_000_000}])
    out = tmp_path / "o.h5"
    summary = run_convert(s, out, window=(100_000_000, 300_000_000), **QUIET)
    assert summary["events"] > 0
    with TrainingSet(out) as ts:
        assert ts.views == ["a", "b", "c"] and ts.val_views == ["c"] and ts.thresholds == (0.3, 0.2)
        for name, off in (("a", 5_000_000_000), ("c", 123_000_000_000)):
            ev = read_events(s / name).events.copy()
            ev["t"] -= off
            ev = ev[(ev["t"] >= 100_000_000) & (ev["t"] < 300_000_000)]
            assert np.array_equal(ts.events(name), ev)


def test_one_view_converts_without_sync(tmp_path, capsys):
    """A recording imported as one view: its time origin is its first event, or --origin; a
    session of more views still needs sync, and --origin is refused there."""
    from evdnerf_ros.cli import main

    s = make_session(tmp_path / "s", [{"name": "a", "offset": 5_000_000_000}])
    data = yaml.safe_load((s / "session.yaml").read_text())
    del data["views"][0]["sync"]
    (s / "session.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
    ev = read_events(s / "a").events
    first = int(ev["t"][0])
    out = tmp_path / "o.h5"
    lines = []
    run_convert(s, out, window=(0, 200_000_000), log=lines.append)
    assert any("one view, no sync needed" in line and f"{first} ns" in line and "first event" in line
               for line in lines), lines
    with TrainingSet(out) as ts:
        want = ev.copy()
        want["t"] -= first
        assert np.array_equal(ts.events("a"), want[want["t"] < 200_000_000])
    assert main(["convert", str(s), "-o", str(tmp_path / "p.h5"), "--origin", f"{first + 10_000_000}ns",
                 "--start", "0", "--end", "100ms"]) == 0
    capsys.readouterr()
    with TrainingSet(tmp_path / "p.h5") as ts:
        want = ev.copy()
        want["t"] -= first + 10_000_000
        assert np.array_equal(ts.events("a"), want[(want["t"] >= 0) & (want["t"] < 100_000_000)])
    two = make_session(tmp_path / "two", [{"name": "a", "offset": 1}, {"name": "b", "offset": 2}])
    with pytest.raises(InputError, match="--origin sets the time origin of a single-view session"):
        run_convert(two, tmp_path / "q.h5", origin=0, **QUIET)


def test_views_of_different_resolutions(tmp_path):
    s = make_session(tmp_path / "s", [{"name": "a", "offset": 10**9},
                                      {"name": "b", "offset": 10**9, "size": (64, 48)}])
    with pytest.raises(InputError, match=r"view b .*64x48 .*session.yaml's camera is 32x24"):
        run_convert(s, tmp_path / "o.h5", **QUIET)
    s2 = make_session(tmp_path / "s2", [{"name": "a", "offset": 10**9},
                                        {"name": "b", "offset": 10**9, "size": (64, 48), "cinfo": False}])
    with pytest.raises(InputError, match=r"view b .*event stream is 64x48"):
        run_convert(s2, tmp_path / "o.h5", intrinsics="session", **QUIET)
    assert not (tmp_path / "o.h5").exists()


def test_missing_topics_are_named(tmp_path):
    s = make_session(tmp_path / "s", [{"name": "a", "offset": 10**9}, {"name": "b", "offset": 10**9, "events": False}])
    with pytest.raises(InputError, match=r"view b .*no event topic '/event_camera/events'.*camera_info"):
        run_convert(s, tmp_path / "o.h5", **QUIET)
    s2 = make_session(tmp_path / "s2", [{"name": "a", "offset": 10**9, "cinfo": False}])
    with pytest.raises(InputError, match=r"no CameraInfo topic.*--intrinsics session"):
        run_convert(s2, tmp_path / "o.h5", **QUIET)


def test_moving_camera_and_bad_poses(tmp_path):
    off = 2 * 10**9
    traj = [(off + k * 50_000_000, pose_stamped(cam_pose(0.01 * k), off + k * 50_000_000)) for k in range(8)]
    s = make_session(tmp_path / "s", [{"name": "a", "offset": off, "poses": traj}])
    out = tmp_path / "m.h5"
    run_convert(s, out, window=(0, 350_000_000), **QUIET)
    with TrainingSet(out) as ts:
        t, T = ts.poses("a")
        assert t.tolist() == [k * 50_000_000 for k in range(8)] and ts.info("a").moving
        assert np.allclose(T[3], cam_pose(0.03)) and np.array_equal(ts.pose("a"), cam_pose(0.0))
    # a static pose topic that disagrees with session.yaml
    s2 = make_session(tmp_path / "s2", [{"name": "a", "offset": off, "poses": [(off, pose_stamped(cam_pose(1.0), off))]}])
    with pytest.raises(InputError, match="pose topic /rig/camera_pose says"):
        run_convert(s2, tmp_path / "x.h5", window=(0, 10**8), **QUIET)
    run_convert(s2, tmp_path / "y.h5", window=(0, 10**8), poses="session", **QUIET)
    # NaN in the pose topic (built by hand: the message helpers refuse it)
    types = ros2_typestore().types
    nan_msg = types["geometry_msgs/msg/PoseStamped"](
        header=header(off, "world"),
        pose=types["geometry_msgs/msg/Pose"](position=types["geometry_msgs/msg/Point"](x=np.nan, y=0.0, z=0.0),
                                             orientation=types["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0,
                                                                                               w=1.0)))
    s3 = make_session(tmp_path / "s3", [{"name": "a", "offset": off, "poses": [(off, nan_msg)]}])
    with pytest.raises(InputError, match=r"view a .*message 0.*not a valid rigid pose"):
        run_convert(s3, tmp_path / "z.h5", window=(0, 10**8), **QUIET)
    assert not (tmp_path / "z.h5").exists()


def test_session_yaml_errors_write_nothing(tmp_path):
    s = make_session(tmp_path / "s", [{"name": "a", "offset": 10**9}, {"name": "b", "offset": 10**9}])
    data = yaml.safe_load((s / "session.yaml").read_text())
    data["views"][1]["name"] = "a"
    (s / "session.yaml").write_text(yaml.safe_dump(data))
    with pytest.raises(InputError, match="duplicate view name"):
        run_convert(s, tmp_path / "o.h5", **QUIET)
    data["views"][1]["name"] = "b"
    data["views"][1]["T_world_cam"][0][0] = float("nan")
    (s / "session.yaml").write_text(yaml.safe_dump(data))
    with pytest.raises(InputError, match="NaN"):
        run_convert(s, tmp_path / "o.h5", **QUIET)
    data["views"][1]["T_world_cam"] = (cam_pose(0.0) @ np.diag([1.0, 1.0, 2.0, 1.0])).tolist()
    (s / "session.yaml").write_text(yaml.safe_dump(data))
    with pytest.raises(InputError, match="not a rigid transform"):
        run_convert(s, tmp_path / "o.h5", **QUIET)
    for bad in ({"downsample": 3}, {"window": (5, 5)}, {"offsets": "guess"}, {"fmt": "csv"}):
        with pytest.raises(EvdnerfError):
            run_convert(s, tmp_path / "o.h5", **bad, **QUIET)
    assert not (tmp_path / "o.h5").exists()


def test_background_writer_hands_errors_back():
    from evdnerf_ros.session.convert import _BackgroundAppender

    class Failing:
        def __init__(self):
            self.got = []

        def append(self, ev):
            if len(self.got) == 1:
                raise InputError("bad batch")
            self.got.append(ev)

    vw = Failing()
    sink = _BackgroundAppender(vw)
    sink.append(1)
    sink.append(2)
    with pytest.raises(InputError, match="bad batch"):
        for k in range(3, 100):       # raised at a later append (or at close)
            sink.append(k)
        sink.close()
    sink.close(raise_error=False)
    assert vw.got == [1]


def test_background_writer_stops_before_an_interrupt_leaves_close():
    """Ctrl-C / SIGTERM while close waits: the writer must be out of the file before the caller
    goes on to close it (an HDF5 file closed under a writing thread crashes the interpreter)."""
    import os
    import signal
    import threading
    import time

    from evdnerf_ros.session.convert import _BackgroundAppender

    class Slow:
        def __init__(self):
            self.writing = False
            self.done = 0

        def append(self, ev):
            self.writing = True
            time.sleep(0.3)
            self.done += 1
            self.writing = False

    vw = Slow()
    sink = _BackgroundAppender(vw)
    for k in range(2):
        sink.append(k)
    threading.Timer(0.1, os.kill, (os.getpid(), signal.SIGINT)).start()
    with pytest.raises(KeyboardInterrupt):
        sink.close()
    assert sink.stopped.is_set() and not vw.writing
    assert vw.done < 3                 # what was still queued was dropped, not written


def test_bad_twin_render_records_are_refused(sim, tmp_path):
    """rig.virtual.frame_ns and ground_truth.sensor_zero_scene_ns (a virtual-rig capture's render
    grid, for the true-scene reference) are checked; nothing is written."""
    def frame(value):
        return lambda d: d.setdefault("rig", {}).setdefault("virtual", {}).__setitem__("frame_ns", value)

    for value in (-5, 0, 2.5, True, "8ms"):
        s = copy_session(sim, tmp_path / f"f{value}", frame(value))
        with pytest.raises(InputError, match=r"rig.virtual.frame_ns must be a whole number"):
            run_convert(s, tmp_path / "o.h5", offsets="ground-truth", **QUIET)
    s = copy_session(sim, tmp_path / "z", lambda d: d["views"][0]["ground_truth"].__setitem__(
        "sensor_zero_scene_ns", "soon"))
    with pytest.raises(InputError, match="sensor_zero_scene_ns"):
        run_convert(s, tmp_path / "o.h5", offsets="ground-truth", **QUIET)
    assert not (tmp_path / "o.h5").exists() and not no_partial(tmp_path)
