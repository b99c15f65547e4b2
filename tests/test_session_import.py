"""`evdnerf import-bags`: sessions from bags recorded without this toolkit (issue 15, item 6).

Synthetic "foreign" bags are made with our writers (several encodings and storages, ROS 1 and
ROS 2, a trigger-cut and a servo-START-cut recording); the imported sessions must decode to
the input's events per view, pass `evdnerf sync` and `evdnerf convert`, and be readable by the
independent mcap reader. The real bags of ../shared/data/real/ import as single-view sessions
with the reference counts of their source projects (skipped where that folder is absent)."""

from __future__ import annotations

import os
import warnings
from pathlib import Path

import numpy as np
import pytest
import yaml

from evdnerf_ros import topics
from evdnerf_ros.cli import main
from evdnerf_ros.errors import InputError
from evdnerf_ros.events.types import make_events, make_triggers
from evdnerf_ros.io.bag_reader import iter_event_packets, open_bag, read_events
from evdnerf_ros.io.messages import camera_info, intrinsics_from_camera_info, joint_state, time_reference
from evdnerf_ros.io.rosbag1 import Rosbag1Writer
from evdnerf_ros.io.rosbag2 import BagWriter
from evdnerf_ros.session.importer import ImportOptions, SessionImportWarning, import_bags
from evdnerf_ros.session.layout import load_session

W, H = 64, 48
T0 = 1_744_227_144_000_000_000          # a host time (2025), whole microseconds
K = np.array([[70.0, 0.0, 31.5], [0.0, 71.0, 23.5], [0.0, 0.0, 1.0]])
EV = topics.EVENTS


def _scene(rng, cuts_ns, *, end_ns, noise_hz=2_000, burst=4_000, burst_ns=80_000_000):
    """Events on the µs grid: sparse noise over [T0, end) plus a dense burst after each cut
    (the motion a trigger / START announces)."""
    n = int(noise_hz * (end_ns - T0) / 1e9)
    t = [T0 + 1000 * rng.integers(0, (end_ns - T0) // 1000, n)]
    for c in cuts_ns:
        t.append(c + 1000 * rng.integers(100, burst_ns // 1000, burst))
    t = np.sort(np.concatenate(t))
    return make_events(t, rng.integers(0, W, t.size), rng.integers(0, H, t.size),
                       rng.choice(np.array([-1, 1], np.int8), t.size))


def _pulses(cuts_ns, width_ns=1_000_000):
    t = np.sort(np.concatenate([np.asarray(cuts_ns), np.asarray(cuts_ns) + width_ns]))
    return make_triggers(t, np.zeros(t.size), np.tile([1, 0], len(cuts_ns)))


def _write_bag(path, ev, *, encoding="evt3", triggers=None, storage="mcap", topic="/event_camera/events",
               info=True, extra=None, packet_ns=1_000_000):
    ros1 = str(path).endswith(".bag")
    writer = Rosbag1Writer(path) if ros1 else BagWriter(path, storage=storage)
    with writer as w:
        if info and not ros1:
            w.write("/event_camera/camera_info", "sensor_msgs/msg/CameraInfo",
                    camera_info(W, H, K, stamp_ns=int(ev["t"][0])), int(ev["t"][0]))
        w.write_events(topic, ev, width=W, height=H, encoding=encoding, triggers=triggers, packet_ns=packet_ns)
        if extra is not None:
            extra(w)
    return path


def _view_events(root, name="view_00"):
    return read_events(Path(root) / name, EV)


# --------------------------------------------------------------------------- one bag per view


@pytest.mark.parametrize("encoding,storage", [("evt3", "mcap"), ("libcaer", "sqlite3"), ("libcaer_cmp", "mcap"),
                                              ("mono", "mcap"), ("array", "mcap"), ("evt3", "ros1"),
                                              ("array", "ros1")])
def test_whole_bag_import_keeps_every_event(tmp_path, rng, encoding, storage):
    end = T0 + 300_000_000
    ev = _scene(rng, [T0 + 100_000_000], end_ns=end)
    tr = _pulses([T0 + 100_000_000]) if encoding == "evt3" else None
    src = tmp_path / ("in.bag" if storage == "ros1" else "in")
    _write_bag(src, ev, encoding=encoding, triggers=tr, storage="mcap" if storage == "ros1" else storage)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        result = import_bags([src], tmp_path / "s")
    said = [str(w.message) for w in caught if issubclass(w.category, SessionImportWarning)]
    assert bool(said) == (storage == "ros1")          # our ROS 1 bags here carry no CameraInfo
    s = load_session(tmp_path / "s")
    assert [v.name for v in s.views] == ["view_00"] and np.array_equal(s.views[0].T_world_cam, np.eye(4))
    want = read_events(src, "/event_camera/events")
    got = _view_events(tmp_path / "s")
    assert np.array_equal(got.events, want.events) and np.array_equal(got.triggers, want.triggers)
    assert np.array_equal(got.events, ev)
    rec = s.data["views"][0]
    assert rec["events"] == ev.size == result.events
    assert (rec["imported"]["first_ns"], rec["imported"]["last_ns"]) == (int(ev["t"][0]), int(ev["t"][-1]))
    assert rec["imported"]["passed_through"] == (encoding != "array")
    # dvs_msgs arrays (whole µs here) become evt3; EventPacket keeps its encoding
    assert got.encoding == (encoding if encoding != "array" else "evt3") == rec["imported"]["encoding"]
    src_rec = s.data["source"]["inputs"][0]
    assert s.data["source"]["kind"] == "import"
    assert (src_rec["path"], src_rec["topic"], src_rec["encoding"]) == (str(src.resolve()), EV, encoding)
    assert (src_rec["first_ns"], src_rec["last_ns"], src_rec["events"]) == (int(ev["t"][0]), int(ev["t"][-1]),
                                                                              ev.size)
    if storage != "ros1":                    # the bag's CameraInfo gives the intrinsics
        assert np.allclose(s.K, K) and s.data["camera"]["intrinsics_source"] == "camera_info"
    if encoding != "array":                  # passed through: the same payload bytes, stamps, seq
        a = [(p.stamp_ns, p.seq, p.time_base) for p in iter_event_packets(src, EV)]
        b = [(p.stamp_ns, p.seq, p.time_base) for p in iter_event_packets(tmp_path / "s" / "view_00", EV)]
        assert a == b
        assert _payloads(src, storage == "ros1") == _payloads(tmp_path / "s" / "view_00", False)


def _payloads(path, ros1):
    from evdnerf_ros.io import event_messages as em

    with open_bag(path) as bag:
        return [bytes(em.parse_event_packet(m.data, ros1=ros1).events) for m in bag.messages(EV)]


def test_dvs_arrays_off_the_microsecond_grid_become_mono(tmp_path, rng):
    ev = _scene(rng, [T0 + 50_000_000], end_ns=T0 + 100_000_000)
    ev["t"] += rng.integers(0, 1000, ev.size)          # ns times: no common µs grid
    ev.sort(order="t", kind="stable")
    src = _write_bag(tmp_path / "dvs", ev, encoding="array", topic="/dvs/events", info=False)
    with pytest.warns(SessionImportWarning, match="nominal"):
        import_bags([src], tmp_path / "s", ImportOptions(fov_deg=60.0))
    got = _view_events(tmp_path / "s")
    assert got.encoding == "mono" and np.array_equal(got.events, ev)
    s = load_session(tmp_path / "s")
    assert s.data["camera"]["intrinsics_source"] == "nominal"
    assert s.K[0, 0] == pytest.approx((W / 2) / np.tan(np.radians(30.0)))


def test_views_sync_and_convert_and_the_independent_reader_reads_them(tmp_path, rng):
    """Three bags (one per view, each with its trigger pulse) -> ring poses -> sync by trigger
    gives each view's cut exactly -> convert writes a training set of the window."""
    bags, cuts = [], []
    for k in range(3):
        start = T0 + k * 10_000_000_000 + 1_234_000
        cut = start + 200_000_000
        ev = _scene(rng, [cut], end_ns=start + 500_000_000)
        ev = ev[ev["t"] >= start]
        bags.append(_write_bag(tmp_path / f"b{k}", ev, triggers=_pulses([cut]), storage=("mcap", "sqlite3")[k % 2]))
        cuts.append(cut)
    assert main(["import-bags", *map(str, bags), "-o", str(tmp_path / "s"), "--ring", "0.5",
                 "--ring-elevation-deg", "10"]) == 0
    s = load_session(tmp_path / "s")
    assert [v.azimuth_deg for v in s.views] == [0.0, 120.0, 240.0]
    assert np.allclose(s.views[1].T_world_cam[:3, 3], 0.5 * np.array([np.cos(np.radians(10)) * np.cos(np.radians(120)),
                                                                       np.cos(np.radians(10)) * np.sin(np.radians(120)),
                                                                       np.sin(np.radians(10))]))
    assert [v["events"] for v in s.data["views"]] == [read_events(b, EV).events.size for b in bags]
    assert main(["sync", str(tmp_path / "s")]) == 0
    synced = yaml.safe_load((tmp_path / "s" / "session.yaml").read_text())
    assert [v["sync"]["offset_ns"] for v in synced["views"]] == cuts
    assert [v["sync"]["method"] for v in synced["views"]] == ["trigger"] * 3
    out = tmp_path / "train.h5"
    assert main(["convert", str(tmp_path / "s"), "-o", str(out), "--start", "0", "--end", "100ms"]) == 0
    import h5py

    with h5py.File(out) as f:
        assert f.attrs  # a training set was written
    # every written bag is a real MCAP: the independent reader decodes it message for message
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    for k, bag in enumerate(bags):
        with open(next((tmp_path / "s" / f"view_{k:02d}").glob("*.mcap")), "rb") as fh:
            msgs = [(c.topic, m) for _, c, _, m in make_reader(fh, decoder_factories=[DecoderFactory()])
                    .iter_decoded_messages()]
        packets = [m for t, m in msgs if t == EV]
        assert [bytes(m.events) for m in packets] == _payloads(bag, False)
        info = [m for t, m in msgs if t == topics.CAMERA_INFO]
        assert len(info) == 1 and np.allclose(np.asarray(info[0].k).reshape(3, 3), K)


# --------------------------------------------------------------------------- one bag cut into views


def _one_bag_three_motions(tmp_path, rng, *, encoding="evt3", servo=True, triggers=True):
    cuts = [T0 + 400_000_000, T0 + 1_400_000_000, T0 + 2_400_000_000]
    end = T0 + 3_000_000_000
    ev = _scene(rng, cuts, end_ns=end)
    starts = [c - 3_000_000 for c in cuts]                 # START arrives 3 ms before the trigger edge
    # events right at and 1 us before every view boundary the tests use (pre-roll 50 / 100 ms)
    edge_t = np.array([c - d - pre - e for c in cuts for d in (0, 3_000_000) for pre in (50_000_000, 100_000_000)
                       for e in (0, 1000)], np.int64)
    ev = np.sort(np.concatenate([ev, make_events(edge_t, np.full(edge_t.size, 5), np.full(edge_t.size, 7),
                                                 np.ones(edge_t.size))]), order="t", kind="stable")

    def servo_msgs(w):
        for k, s in enumerate(starts):
            for what, t in (("START", s), ("DONE", s + 300_000_000)):
                w.write(topics.SERVO_TRIGGER, "sensor_msgs/msg/TimeReference",
                        time_reference(t, 5_000_000_000 + 1000 * k + t - T0, f"rig_servo {what}"), t)
        for t in range(T0, end, 100_000_000):
            w.write(topics.SERVO_JOINT_STATES, "sensor_msgs/msg/JointState",
                    joint_state(["fork_joint"], [0.001 * ((t - T0) // 100_000_000)], stamp_ns=t), t)

    src = _write_bag(tmp_path / "one", ev, encoding=encoding, triggers=_pulses(cuts) if triggers else None,
                     extra=servo_msgs if servo else None)
    return src, ev, cuts, starts


def test_one_bag_cut_at_trigger_edges_into_three_views(tmp_path, rng):
    src, ev, cuts, starts = _one_bag_three_motions(tmp_path, rng)
    import_bags([src], tmp_path / "s", ImportOptions(split_at="triggers", views=3, ring=1.0))
    s = load_session(tmp_path / "s")
    assert [v.name for v in s.views] == ["view_00", "view_01", "view_02"]
    pre = 100_000_000
    edges = [None, cuts[1] - pre, cuts[2] - pre, None]
    total = 0
    tr_in = read_events(src, EV).triggers
    for k, v in enumerate(s.views):
        got = _view_events(tmp_path / "s", v.name)
        lo = -np.inf if edges[k] is None else edges[k]
        hi = np.inf if edges[k + 1] is None else edges[k + 1]
        want = ev[(ev["t"] >= lo) & (ev["t"] < hi)]
        assert np.array_equal(got.events, want)                       # every event, in its own clock
        assert np.array_equal(got.triggers, tr_in[(tr_in["t"] >= lo) & (tr_in["t"] < hi)])
        rec = s.data["views"][k]
        assert rec["events"] == want.size and rec["imported"]["cut_ns"] == cuts[k]
        assert (rec["imported"]["first_ns"], rec["imported"]["last_ns"]) == (int(want["t"][0]), int(want["t"][-1]))
        # the servo messages of each view's range are copied
        with open_bag(tmp_path / "s" / v.name) as bag:
            copied = [m.t_ns for m in bag.messages(topics.SERVO_TRIGGER)]
        assert copied == [starts[k], starts[k] + 300_000_000]
        total += got.events.size
    assert total == ev.size
    assert s.data["source"]["split"]["cuts_ns"] == cuts and s.data["servo"]["joint"] == "fork_joint"
    assert main(["sync", str(tmp_path / "s")]) == 0
    synced = load_session(tmp_path / "s")
    assert [v.sync["offset_ns"] for v in synced.views] == cuts
    assert main(["convert", str(tmp_path / "s"), "-o", str(tmp_path / "t.h5"), "--start=-10ms",
                 "--end", "90ms"]) == 0


def test_servo_start_cuts_and_sync_by_start(tmp_path, rng):
    src, ev, cuts, starts = _one_bag_three_motions(tmp_path, rng, encoding="libcaer", triggers=False)
    import_bags([src], tmp_path / "s", ImportOptions(split_at="servo-start", views=3, ring=1.0, pre_roll_ns=50_000_000))
    s = load_session(tmp_path / "s")
    assert s.data["source"]["split"]["cuts_ns"] == starts
    counts = [v["events"] for v in s.data["views"]]
    bounds = [starts[1] - 50_000_000, starts[2] - 50_000_000]
    assert counts == [int((ev["t"] < bounds[0]).sum()), int(((ev["t"] >= bounds[0]) & (ev["t"] < bounds[1])).sum()),
                      int((ev["t"] >= bounds[1]).sum())]
    assert [v["imported"]["encoding"] for v in s.data["views"]] == ["libcaer"] * 3
    assert main(["sync", str(tmp_path / "s"), "--method", "start"]) == 0
    assert [v.sync["offset_ns"] for v in load_session(tmp_path / "s").views] == starts


def test_cuts_from_a_separate_trigger_topic(tmp_path, rng):
    cuts = [T0 + 300_000_000, T0 + 900_000_000]
    ev = _scene(rng, cuts, end_ns=T0 + 1_500_000_000)

    def trigger_topic(w):
        w.write_events("/event_camera/trigger", ev[:0], width=W, height=H, encoding="evt3", triggers=_pulses(cuts))
    src = _write_bag(tmp_path / "b", ev, extra=trigger_topic)
    with pytest.raises(InputError, match="2 event topics"):
        import_bags([src], tmp_path / "s", ImportOptions(split_at="triggers", ring=1.0))
    import_bags([src], tmp_path / "s", ImportOptions(split_at="triggers", topic=EV, ring=1.0,
                                                     trigger_topic="/event_camera/trigger", views=2))
    s = load_session(tmp_path / "s")
    assert s.data["source"]["split"]["cuts_ns"] == cuts
    assert [v["events"] for v in s.data["views"]] == [int((ev["t"] < cuts[1] - 100_000_000).sum()),
                                                      int((ev["t"] >= cuts[1] - 100_000_000).sum())]


def test_split_count_and_cut_errors(tmp_path, rng, capsys):
    src, *_ = _one_bag_three_motions(tmp_path, rng, servo=False)
    with pytest.raises(InputError, match=r"found 3 rising trigger edges but --views 4"):
        import_bags([src], tmp_path / "s", ImportOptions(split_at="triggers", views=4, ring=1.0))
    with pytest.raises(InputError, match=r"topic /rig/servo/trigger: no servo START messages found"):
        import_bags([src], tmp_path / "s", ImportOptions(split_at="servo-start"))
    with pytest.raises(InputError, match="no rising trigger edges of channel 3"):
        import_bags([src], tmp_path / "s", ImportOptions(split_at="triggers", trigger_id=3))
    with pytest.raises(InputError, match=r"3 views need poses"):
        import_bags([src], tmp_path / "s", ImportOptions(split_at="triggers"))
    with pytest.raises(InputError, match="cuts ONE bag"):
        import_bags([src, tmp_path / "other"], tmp_path / "s", ImportOptions(split_at="triggers"))
    assert main(["import-bags", str(src), "-o", str(tmp_path / "s"), "--split-at", "triggers", "--views", "2",
                 "--ring", "1"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--views 2" in err
    assert not (tmp_path / "s").exists() and not list(tmp_path.glob(".s.*"))


# --------------------------------------------------------------------------- calibration and poses


def test_calibration_file_and_poses_file(tmp_path, rng):
    ev = _scene(rng, [T0 + 50_000_000], end_ns=T0 + 100_000_000)
    bags = [_write_bag(tmp_path / f"b{k}", ev, info=False) for k in range(2)]
    calib = tmp_path / "cam.yaml"                  # what ROS camera_calibration writes
    calib.write_text(yaml.safe_dump({
        "image_width": W, "image_height": H, "camera_name": "evk4",
        "camera_matrix": {"rows": 3, "cols": 3, "data": [80.0, 0, 32.0, 0, 81.0, 24.0, 0, 0, 1]},
        "distortion_model": "plumb_bob",
        "distortion_coefficients": {"rows": 1, "cols": 5, "data": [0.1, -0.05, 0.001, 0.002, 0.0]},
        "rectification_matrix": {"rows": 3, "cols": 3, "data": [1, 0, 0, 0, 1, 0, 0, 0, 1]},
        "projection_matrix": {"rows": 3, "cols": 4, "data": [80.0, 0, 32.0, 0, 0, 81.0, 24.0, 0, 0, 0, 1, 0]}}))
    T1 = np.eye(4)
    T1[:3, 3] = [0.1, 0.2, 0.3]
    poses = tmp_path / "poses.yaml"
    s2 = float(np.sqrt(0.5))
    poses.write_text(yaml.safe_dump({"poses": [T1.tolist(), {"position": [1.0, 0.0, 0.5],
                                                              "orientation": [0.0, 0.0, s2, s2],
                                                              "azimuth_deg": 90.0}]}))
    import_bags(bags, tmp_path / "s", ImportOptions(calibration=str(calib), poses=str(poses)))
    s = load_session(tmp_path / "s")
    assert np.allclose(s.K, [[80, 0, 32], [0, 81, 24], [0, 0, 1]]) and np.allclose(s.D, [0.1, -0.05, 0.001, 0.002, 0])
    assert np.allclose(s.views[0].T_world_cam, T1)
    assert np.allclose(s.views[1].T_world_cam[:3, :3], [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12)
    assert s.views[1].azimuth_deg == 90.0
    with open_bag(tmp_path / "s" / "view_01") as bag:
        info = intrinsics_from_camera_info(next(m for _, m in bag.read_messages(topics.CAMERA_INFO)))
    assert np.allclose(info["K"], s.K) and np.allclose(info["D"], s.D)
    # the calibration must be of this sensor's resolution; poses one per view
    calib.write_text(calib.read_text().replace(f"image_width: {W}", "image_width: 640"))
    with pytest.raises(InputError, match=r"cam.yaml: 640x48 but the event stream .* is 64x48"):
        import_bags(bags, tmp_path / "s2", ImportOptions(calibration=str(calib), poses=str(poses)))
    with pytest.raises(InputError, match=r"poses.yaml: poses: 2 poses for 1 views"):
        import_bags(bags[:1], tmp_path / "s2", ImportOptions(poses=str(poses)))
    poses.write_text(yaml.safe_dump([(2 * np.eye(4)).tolist()]))
    with pytest.raises(InputError, match=r"poses.yaml: \[0\]"):
        import_bags(bags[:1], tmp_path / "s2", ImportOptions(poses=str(poses), fov_deg=70.0))
    assert not (tmp_path / "s2").exists()


def test_the_calibrate_commands_file_gives_intrinsics_and_poses(tmp_path, rng):
    """`evdnerf calibrate` writes camera: {width, height, K, D, ...} and views: [{name, T_world_cam}]."""
    ev = _scene(rng, [T0 + 50_000_000], end_ns=T0 + 100_000_000)
    bags = [_write_bag(tmp_path / f"b{k}", ev, info=False) for k in range(2)]
    Ts = [np.eye(4), np.eye(4)]
    Ts[1][:3, 3] = [0.0, 0.4, 0.1]
    doc = {"camera": {"width": W, "height": H, "K": [[90.0, 0, 31.0], [0, 90.5, 23.0], [0, 0, 1]],
                      "distortion_model": "plumb_bob", "D": [0.01, 0.0, 0.0, 0.0, 0.0], "rms_px": 0.1},
           "views": [{"name": f"view_{k:02d}", "T_world_cam": T.tolist(), "rms_px": 0.2} for k, T in enumerate(Ts)]}
    (tmp_path / "calib.yaml").write_text(yaml.safe_dump(doc, sort_keys=False))
    import_bags(bags, tmp_path / "s", ImportOptions(calibration=str(tmp_path / "calib.yaml"),
                                                    poses=str(tmp_path / "calib.yaml")))
    s = load_session(tmp_path / "s")
    assert np.allclose(s.K, doc["camera"]["K"]) and s.data["camera"]["intrinsics_source"] == "calibration"
    assert np.allclose(s.views[1].T_world_cam, Ts[1])


def test_unknown_calibration_is_said_in_session_yaml(tmp_path, rng):
    ev = _scene(rng, [T0 + 50_000_000], end_ns=T0 + 100_000_000)
    src = _write_bag(tmp_path / "b", ev, info=False)
    with pytest.warns(SessionImportWarning, match="good for `evdnerf sync` only"):
        import_bags([src], tmp_path / "s")
    s = load_session(tmp_path / "s")
    assert s.data["camera"]["intrinsics_source"] == "unknown"
    assert s.data["source"]["calibration"].startswith("unknown") and "sync only" in s.data["source"]["calibration"]


# --------------------------------------------------------------------------- bad input


def test_bad_inputs_name_the_file_and_the_fix(tmp_path, rng):
    ev = _scene(rng, [T0 + 50_000_000], end_ns=T0 + 100_000_000)
    good = _write_bag(tmp_path / "good", ev)
    with BagWriter(tmp_path / "none") as w:                    # no event topic
        w.write(topics.CAMERA_INFO, "sensor_msgs/msg/CameraInfo", camera_info(W, H, K, stamp_ns=T0), T0)
    with pytest.raises(InputError, match=r"none: the bag has no event topic"):
        import_bags([tmp_path / "none"], tmp_path / "s")

    def second(w):
        w.write_events("/dvs/events", ev, width=W, height=H, encoding="array")
    two = _write_bag(tmp_path / "two", ev, extra=second)
    with pytest.raises(InputError, match=r"two: the bag has 2 event topics .*choose one with --topic"):
        import_bags([two], tmp_path / "s")
    import_bags([two], tmp_path / "s", ImportOptions(topic="/dvs/events"))   # --topic picks one
    assert load_session(tmp_path / "s").data["source"]["inputs"][0]["topic"] == "/dvs/events"
    with pytest.raises(InputError, match=r"no topic '/nope'"):
        import_bags([two], tmp_path / "s3", ImportOptions(topic="/nope"))

    with BagWriter(tmp_path / "empty") as w:                   # an event topic without messages
        w.add_topic(EV, "event_camera_msgs/msg/EventPacket")
    with pytest.raises(InputError, match=r"empty: topic /event_camera/events has no messages"):
        import_bags([tmp_path / "empty"], tmp_path / "s3")

    with BagWriter(tmp_path / "small") as w:                   # another sensor size
        w.write_events(EV, make_events(ev["t"][:10], np.zeros(10), np.zeros(10), np.ones(10)),
                       width=32, height=32, encoding="evt3")
    with pytest.raises(InputError, match=r"small: topic /event_camera/events is 32x32 but .*good is 64x48"):
        import_bags([good, tmp_path / "small"], tmp_path / "s3", ImportOptions(ring=1.0))
    assert main(["import-bags", str(good), str(tmp_path / "small"), "-o", str(tmp_path / "s3"), "--ring", "1"]) == 2
    assert not (tmp_path / "s3").exists()
    with pytest.raises(Exception, match="already exists"):
        import_bags([good], tmp_path / "s")
    import_bags([good], tmp_path / "s", overwrite=True)        # a session this toolkit wrote
    assert load_session(tmp_path / "s").data["source"]["inputs"][0]["topic"] == EV


def test_a_failing_view_leaves_nothing(tmp_path, rng):
    """A bag whose event topic holds only empty packets fails after view_00 was written: the
    whole session is discarded."""
    ev = _scene(rng, [T0 + 50_000_000], end_ns=T0 + 100_000_000)
    good = _write_bag(tmp_path / "good", ev)
    with BagWriter(tmp_path / "hollow") as w:
        w.write_raw_packet(EV, b"", encoding="evt3", width=W, height=H, stamp_ns=T0)
    with pytest.raises(InputError, match=r"hollow: topic /event_camera/events: view view_01 has no events"):
        import_bags([good, tmp_path / "hollow"], tmp_path / "s", ImportOptions(ring=1.0))
    assert not (tmp_path / "s").exists() and not [p for p in tmp_path.iterdir() if p.name.startswith(".s")]


# --------------------------------------------------------------------------- real recordings

REAL = Path(os.environ.get("EVDNERF_REAL_DATA", Path(__file__).resolve().parents[1].parent / "shared" / "data" / "real"))


def _real(name):
    path = REAL / name
    if not path.exists():
        pytest.skip(f"real recording {path} not found")
    return path


@pytest.mark.parametrize("name", ["event_camera_py/test_events_1", "event_camera_py/test_events_1.bag"])
def test_real_metavision_bag_imports_with_its_reference_counts(tmp_path, name):
    """metavision_driver evt3 (README reference values from event_camera_py's tests)."""
    src = _real(name)
    with pytest.warns(SessionImportWarning):
        import_bags([src], tmp_path / "s")
    s = read_events(tmp_path / "s" / "view_00", EV)
    ev, tr, off = s.events, s.triggers, s.time_offset_ns
    assert ((ev["p"] < 0).sum(), (ev["p"] > 0).sum()) == (218_291, 125_183)
    assert ((tr["value"] == 0).sum(), (tr["value"] != 0).sum()) == (2078, 2079)
    sensor_ns = np.concatenate([ev["t"], tr["t"]]) - off
    assert int(sensor_ns.sum()) // 1000 == 2_885_601_049_874
    assert (int(ev["t"][0]) - off) // 1000 == 7_139_845
    rec = load_session(tmp_path / "s").data["views"][0]
    assert rec["events"] == 343_474 and rec["trigger_events"] == 4157 and rec["imported"]["passed_through"]
    assert main(["sync", str(tmp_path / "s")]) == 0          # by its first rising trigger edge
    assert load_session(tmp_path / "s").views[0].sync["method"] == "trigger"


def test_real_evt3_trigger_and_libcaer_bags_import_with_their_reference_counts(tmp_path):
    src = _real("event_camera_codecs/test_data_evt3_trigger")
    with pytest.warns(SessionImportWarning):
        import_bags([src], tmp_path / "a")
    s = read_events(tmp_path / "a" / "view_00", EV)
    ev, tr, off = s.events, s.triggers, s.time_offset_ns
    assert int((ev["t"] - off).sum()) == 1_222_326_831_810_000
    assert (int(ev["x"].sum()), int(ev["y"].sum()), int((ev["p"] > 0).sum())) == (42_078_718, 31_656_267, 41_439)
    assert (int((tr["t"] - off).sum()), int(tr["value"].sum()), int(tr["id"].sum())) == (29_096_982_000, 1, 0)
    assert (s.width, s.height) == (1280, 720)
    for name, count, enc in (("event_camera_py/test_events_2", 571_266, "libcaer_cmp"),
                             ("event_camera_codecs/test_data_libcaer_rollover", 334_331, "libcaer")):
        src = _real(name)
        out = tmp_path / Path(name).name
        with pytest.warns(SessionImportWarning):
            import_bags([src], out)
        got = read_events(out / "view_00", EV)
        assert got.events.size == count and got.encoding == enc
        assert np.array_equal(got.events, read_events(src, EV).events)
