"""The session recorder (the one writer of the session layout), read back by the reader."""

import math

import numpy as np
import pytest
import yaml

from evdnerf_ros import topics
from evdnerf_ros.errors import InputError
from evdnerf_ros.events.types import make_events, make_triggers
from evdnerf_ros.io.messages import K_from_camera_info, pose_from_pose_stamped, time_reference_ns
from evdnerf_ros.io.rosbag2 import BagWriter, open_bag, read_events
from evdnerf_ros.session.layout import load_session
from evdnerf_ros.session.recorder import (ViewRecorder, camera_record, servo_record, session_document,
                                          view_record, write_session_yaml)

W, H = 40, 30
K = np.array([[50.0, 0.0, 19.5], [0.0, 51.0, 14.5], [0.0, 0.0, 1.0]])
D = [0.01, -0.02, 0.0, 0.0, 0.001]


def _pose(az_deg: float, z: float = 1.0) -> np.ndarray:
    a = math.radians(az_deg)
    T = np.eye(4)
    T[:3, :3] = [[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0], [0.0, 0.0, 1.0]]
    T[:3, 3] = [0.3, -0.2, z]
    return T


def _events(rng, t0: int, n: int = 500) -> np.ndarray:
    t = t0 + 1000 * np.sort(rng.integers(0, 200_000, n))
    return make_events(t, rng.integers(0, W, n), rng.integers(0, H, n),
                       rng.choice(np.array([-1, 1], np.int8), n))


def _document(views) -> dict:
    return session_document(
        source={"kind": "capture", "operator": "test"},
        rig={"kind": "real", "ring_radius_m": 0.5, "firmware_version": "1.2.0", "device_serial": "00ca1"},
        camera=camera_record(W, H, K, D),
        servo=servo_record("fork_joint", start_ns_scene=None),
        thresholds={"c_pos": 0.25, "c_neg": 0.3, "eps": 0.001},
        time={"scene_start_ns": 0, "scene_end_ns": 300_000_000, "motion_start_ns": 50_000_000,
              "motion_end_ns": 250_000_000},
        views=views)


def test_recorded_session_reads_back_key_for_key(tmp_path, rng):
    root = tmp_path / "s"
    root.mkdir()
    written = {}
    views = []
    for i, (name, split, az) in enumerate([("view_00", "train", 0.0), ("view_01", "train", 120.0),
                                           ("val_00", "val", 60.0)]):
        t0 = 1_000_000_000 * (i + 1)
        ev = _events(rng, t0)
        tr = make_triggers(np.array([t0 + 50_000_000, t0 + 51_000_000]), np.zeros(2), [1, 0])
        T = _pose(az)
        with ViewRecorder(root / name, width=W, height=H) as rec:
            rec.camera_info(K, D, stamp_ns=t0)
            rec.pose(T, t0)
            rec.servo_trigger("START", t0 + 50_000_000, 7_000_000_000)
            rec.servo_trigger("DONE", t0 + 250_000_000, 7_200_000_000)
            for k in range(3):
                rec.servo_joint_state(["fork_joint"], [0.1 * k], t0 + k * 20_000_000)
            rec.events(ev, tr)
        written[name] = (t0, ev, tr, T)
        views.append(view_record(name, split, T, azimuth_deg=az, events=int(ev.size), frames=None,
                                 ground_truth={"clock_offset_ns": t0, "device_offset_ns": 7, "file": None}))
    doc = _document(views)
    path = write_session_yaml(root, doc)
    assert path == root / "session.yaml"

    s = load_session(root)
    assert s.data == doc                               # every key, as written
    assert yaml.safe_load(path.read_text()) == doc
    assert (s.width, s.height) == (W, H)
    np.testing.assert_array_equal(s.K, K)
    np.testing.assert_array_equal(s.D, D)
    assert (s.c_pos, s.c_neg, s.eps) == (0.25, 0.3, 0.001)
    assert s.servo == {"joint": "fork_joint", "joint_states": topics.SERVO_JOINT_STATES,
                       "trigger": topics.SERVO_TRIGGER, "start_ns_scene": None}
    assert s.time == doc["time"]
    assert s.data["camera"]["topics"] == {"events": topics.EVENTS, "camera_info": topics.CAMERA_INFO,
                                          "pose": topics.CAMERA_POSE}
    assert [v.name for v in s.views] == ["view_00", "view_01", "val_00"]
    for v, rec in zip(s.views, doc["views"]):
        t0, ev, tr, T = written[v.name]
        assert v.bag == root / v.name and v.split == rec["split"] and v.azimuth_deg == rec["azimuth_deg"]
        np.testing.assert_array_equal(v.T_world_cam, T)
        assert v.frames is None and v.sync is None and v.ground_truth == rec["ground_truth"]
        assert rec["moving_arc_deg"] is None

        stream = read_events(v.bag)                    # the default topic is the layout's
        assert stream.topic == topics.EVENTS and stream.encoding == "evt3"
        assert (stream.width, stream.height) == (W, H)
        assert np.array_equal(stream.events, ev) and np.array_equal(stream.triggers, tr)
        with open_bag(v.bag) as bag:
            assert set(bag.topics) == {topics.EVENTS, topics.CAMERA_INFO, topics.CAMERA_POSE,
                                       topics.SERVO_JOINT_STATES, topics.SERVO_TRIGGER}
            (_, info), = bag.read_messages(topics.CAMERA_INFO)
            np.testing.assert_allclose(K_from_camera_info(info), K)
            assert list(info.d) == D and info.header.frame_id == "event_camera"
            (_, pose), = bag.read_messages(topics.CAMERA_POSE)
            T_back, stamp, frame = pose_from_pose_stamped(pose)
            np.testing.assert_allclose(T_back, T, atol=1e-12)
            assert (stamp, frame) == (t0, "world")
            refs = [time_reference_ns(m) for _, m in bag.read_messages(topics.SERVO_TRIGGER)]
            assert refs == [(t0 + 50_000_000, 7_000_000_000, "rig_servo START"),
                            (t0 + 250_000_000, 7_200_000_000, "rig_servo DONE")]
            joints = [m for _, m in bag.read_messages(topics.SERVO_JOINT_STATES)]
            assert [list(m.name) for m in joints] == [["fork_joint"]] * 3
            assert [float(m.position[0]) for m in joints] == pytest.approx([0.0, 0.1, 0.2])


def test_moving_camera_trajectory(tmp_path):
    t = np.array([10, 20, 30], np.int64) * 1_000_000
    Ts = np.stack([_pose(a) for a in (0.0, 5.0, 10.0)])
    with ViewRecorder(tmp_path / "m", width=W, height=H) as rec:
        rec.poses(t, Ts)
    with open_bag(tmp_path / "m") as bag:
        back = [pose_from_pose_stamped(m) for _, m in bag.read_messages(topics.CAMERA_POSE)]
    assert [s for _, s, _ in back] == t.tolist()
    np.testing.assert_allclose(np.stack([T for T, _, _ in back]), Ts, atol=1e-12)
    with pytest.raises(InputError, match="must increase"):
        with ViewRecorder(tmp_path / "bad", width=W, height=H) as rec:
            rec.poses(t[::-1], Ts)
    assert not (tmp_path / "bad").exists()


def test_raw_event_packets_pass_through_byte_identical(tmp_path, rng):
    src = tmp_path / "src"
    ev = _events(rng, 5_000_000_000, 3000)
    tr = make_triggers(np.array([5_010_000_000]), np.zeros(1), [1])
    with BagWriter(src) as bag:
        bag.write_events(topics.EVENTS, ev, width=W, height=H, encoding="evt3", triggers=tr,
                         packet_ns=20_000_000)
    with open_bag(src) as bag:
        packets = [(m.data, m.t_ns) for m in bag.messages(topics.EVENTS)]
    assert len(packets) > 3
    with ViewRecorder(tmp_path / "dst", width=W, height=H) as rec:
        for data, t_ns in packets:
            rec.event_packet(data, t_ns)
    with open_bag(tmp_path / "dst") as bag:
        assert [(bytes(m.data), m.t_ns) for m in bag.messages(topics.EVENTS)] == \
               [(bytes(d), t) for d, t in packets]
    back = read_events(tmp_path / "dst")
    assert np.array_equal(back.events, ev) and np.array_equal(back.triggers, tr)
    # a packet of another sensor size is refused, and the view's bag is not left behind
    with pytest.raises(InputError, match=r"packet is 40x30 'evt3'.*records 20x30"):
        with ViewRecorder(tmp_path / "other", width=20, height=30) as rec:
            rec.event_packet(packets[0][0], packets[0][1])
    with pytest.raises(InputError, match="not a serialised"):
        with ViewRecorder(tmp_path / "junk", width=W, height=H) as rec:
            rec.event_packet(b"\x00\x01\x00\x00garbage", 1)
    assert not (tmp_path / "other").exists() and not (tmp_path / "junk").exists()
    with pytest.raises(InputError, match="START"):
        with ViewRecorder(tmp_path / "t", width=W, height=H) as rec:
            rec.servo_trigger("BEGIN", 1, 1)


@pytest.mark.parametrize("break_it,match", [
    (lambda d: d["views"][0].__setitem__("T_world_cam", (2 * np.eye(4)).tolist()), r"views\[0\]\.T_world_cam"),
    (lambda d: d.pop("thresholds"), "thresholds"),
    (lambda d: d["thresholds"].__setitem__("c_pos", -0.1), r"thresholds\.c_pos"),
    (lambda d: d["views"].append(dict(d["views"][0])), "duplicate view name"),
    (lambda d: d["camera"]["topics"].__setitem__("events", "no_slash"), r"camera\.topics\.events"),
    (lambda d: d["views"][0].__setitem__("events", np.int64(3)), "YAML cannot represent"),
    (lambda d: d.__setitem__("views", []), "views"),
])
def test_a_document_the_reader_refuses_is_never_written(tmp_path, break_it, match):
    root = tmp_path / "s"
    root.mkdir()
    doc = _document([view_record("view_00", "train", _pose(0.0), azimuth_deg=0.0)])
    break_it(doc)
    with pytest.raises(InputError, match=match) as exc:
        write_session_yaml(root, doc)
    assert "not written" in str(exc.value)
    assert list(root.iterdir()) == []                  # no session.yaml, no temporary
    # Replacing an existing, good session.yaml with a bad one keeps the good one.
    good = _document([view_record("view_00", "train", _pose(0.0), azimuth_deg=0.0)])
    write_session_yaml(root, good)
    before = (root / "session.yaml").read_bytes()
    with pytest.raises(InputError, match=match):
        write_session_yaml(root, doc, overwrite=True)
    assert (root / "session.yaml").read_bytes() == before
    assert [p.name for p in root.iterdir()] == ["session.yaml"]


def test_a_view_with_nothing_recorded_still_has_its_event_topic(tmp_path):
    """A capture interrupted before the camera's first packet: the bag is valid, its event topic
    is there and reads as no events (not 'no topic')."""
    from evdnerf_ros.io.rosbag2 import read_events
    from evdnerf_ros.session.recorder import ViewRecorder

    with ViewRecorder(tmp_path / "v", width=16, height=12):
        pass
    stream = read_events(tmp_path / "v")
    assert stream.events.size == 0 and stream.message_count == 0
