"""ROS 1 bag export: byte-exact dvs_msgs/EventArray, round trips, streaming, errors."""

from __future__ import annotations

import os

import numpy as np
import pytest

from evdnerf_ros.errors import FormatError, InputError, OutputExistsError
from evdnerf_ros.events.types import make_events
from evdnerf_ros.io import event_messages as em
from evdnerf_ros.io.rosbag1 import Rosbag1Writer, write_events_rosbag1
from evdnerf_ros.io.rosbag2 import bag_info, iter_event_packets, open_bag, read_events
from evdnerf_ros.io.typestore import DVS_EVENT_ARRAY, EVENT_PACKET, ros1_typestore

W, H = 346, 260
T0 = 1_600_000_000_000_000_000
TOPIC = "/dvs/events"


def make_stream(rng, n=5000, span_ns=20_000_000_000, us_grid=False):
    if us_grid:
        t = T0 + np.sort(rng.integers(0, span_ns // 1000, n)) * 1000
    else:
        t = T0 + np.sort(rng.integers(0, span_ns, n))
    return make_events(t, rng.integers(0, W, n), rng.integers(0, H, n), rng.integers(0, 2, n).astype(bool))


def test_ros1_md5_matches_rpg_dvs_ros():
    ts = ros1_typestore()
    assert ts.generate_msgdef(DVS_EVENT_ARRAY)[1] == "5e8beee5a6c107e504c2e78903c224b8"


@pytest.mark.parametrize("frame_id", ["", "a", "dvs", "event_camera"])
@pytest.mark.parametrize("n", [0, 1, 3])
def test_ros1_event_array_is_byte_identical_to_rosbags(rng, frame_id, n):
    ts = ros1_typestore()
    T = ts.types
    Time = T["builtin_interfaces/msg/Time"]
    ev = make_stream(rng, n)
    stamp = int(ev["t"][0]) if n else T0
    msg = T[DVS_EVENT_ARRAY](
        header=T["std_msgs/msg/Header"](seq=42, stamp=Time(sec=stamp // 10**9, nanosec=stamp % 10**9),
                                        frame_id=frame_id),
        height=H, width=W,
        events=[T["dvs_msgs/msg/Event"](x=int(e["x"]), y=int(e["y"]),
                                        ts=Time(sec=int(e["t"]) // 10**9, nanosec=int(e["t"]) % 10**9),
                                        polarity=bool(e["p"] > 0)) for e in ev])
    ref = bytes(ts.serialize_ros1(msg, DVS_EVENT_ARRAY))
    rec = em.ros1_event_records(ev, what="t")
    ours = em.Ros1EventArrayPrefix(frame_id, H, W)(42, stamp, n) + rec.tobytes()
    assert ours == ref
    got = em.parse_event_array(ref, ros1=True, what="t")
    assert np.array_equal(got.events, ev) and (got.seq, got.frame_id, got.stamp_ns) == (42, frame_id, stamp)


def test_ros1_event_packet_is_byte_identical_to_rosbags():
    ts = ros1_typestore()
    T = ts.types
    hdr = T["std_msgs/msg/Header"](seq=7, stamp=T["builtin_interfaces/msg/Time"](sec=5, nanosec=6), frame_id="cam")
    payload = np.arange(9, dtype=np.uint8)
    msg = T[EVENT_PACKET](header=hdr, height=H, width=W, seq=7, time_base=T0, encoding="evt3", is_bigendian=False,
                          events=payload)
    ref = bytes(ts.serialize_ros1(msg, EVENT_PACKET))
    ours = em.Ros1EventPacketPrefix("cam", H, W, "evt3")(7, 5_000_000_006, 7, T0, 9) + payload.tobytes()
    assert ours == ref


def test_round_trip_long_span_and_seq(tmp_path, rng):
    ev = make_stream(rng, 8000)
    path = tmp_path / "out.bag"
    n = write_events_rosbag1(path, ev, width=W, height=H, topic=TOPIC, packet_ns=30_000_000)
    assert os.listdir(tmp_path) == ["out.bag"]
    got = read_events(path, TOPIC)
    assert np.array_equal(got.events, ev)
    assert (got.width, got.height, got.encoding, got.message_count, got.msgtype) == (W, H, "array", n, DVS_EVENT_ARRAY)
    pk = list(iter_event_packets(path, TOPIC))
    assert [p.seq for p in pk] == list(range(n))  # ROS 1 header.seq counts messages
    assert all(p.bag_time_ns == p.stamp_ns == int(p.events["t"][0]) for p in pk)
    info = bag_info(path)
    assert info.storage == "rosbag1" and info.topics[TOPIC].events.event_count == ev.size
    assert (info.start_ns, info.end_ns) == (pk[0].stamp_ns, pk[-1].stamp_ns)
    # rosbags' own (per-object) ROS 1 deserialiser agrees on a message
    with open_bag(path) as bag:
        t, msg = next(bag.read_messages(TOPIC))
    assert msg.header.seq == 0 and msg.height == H and msg.width == W
    first = pk[0].events
    assert [(e.x, e.y, e.ts.sec * 10**9 + e.ts.nanosec, e.polarity) for e in msg.events] == \
        [(int(e["x"]), int(e["y"]), int(e["t"]), bool(e["p"] > 0)) for e in first]


def test_streaming_writer_with_other_topics(tmp_path, rng):
    ev = make_stream(rng, 3000, us_grid=True)
    path = tmp_path / "s.bag"
    with Rosbag1Writer(path) as w:
        for part in np.array_split(ev, 4):
            w.write_events(TOPIC, part, width=W, height=H)
        T = ros1_typestore().types
        w.write("/note", "std_msgs/msg/String", T["std_msgs/msg/String"](data="x"), T0)
        w.write_events("/mono", ev, width=W, height=H, encoding="mono")
    assert np.array_equal(read_events(path, TOPIC).events, ev)
    assert np.array_equal(read_events(path, "/mono").events, ev)
    assert set(bag_info(path).topics) == {TOPIC, "/mono", "/note"}


def test_ros1_errors(tmp_path, rng):
    ev = make_stream(rng, 100)
    path = tmp_path / "x.bag"
    path.write_bytes(b"")
    with pytest.raises(OutputExistsError):
        write_events_rosbag1(path, ev, width=W, height=H)
    with pytest.raises(InputError, match="ROS 1 time"):
        write_events_rosbag1(tmp_path / "neg.bag", make_events([1, 2 * 10**18 * 3], [0, 0], [0, 0], [1, 1]),
                             width=W, height=H)
    assert sorted(os.listdir(tmp_path)) == ["x.bag"]
    good = tmp_path / "g.bag"
    write_events_rosbag1(good, ev, width=W, height=H, topic=TOPIC)
    data = good.read_bytes()
    trunc = tmp_path / "t.bag"
    trunc.write_bytes(data[: len(data) - 200])
    with pytest.raises(FormatError, match="t.bag"):
        read_events(trunc, TOPIC)
    with pytest.raises(InputError, match=r"no topic '/nope'.*/dvs/events \[dvs_msgs/msg/EventArray\]"):
        read_events(good, "/nope")


def test_exception_mid_write_leaves_nothing(tmp_path, rng):
    with pytest.raises(KeyboardInterrupt):
        with Rosbag1Writer(tmp_path / "k.bag") as w:
            w.write_events(TOPIC, make_stream(rng, 500), width=W, height=H)
            raise KeyboardInterrupt
    assert os.listdir(tmp_path) == []


def test_small_blocks_and_batches(tmp_path, rng, monkeypatch):
    import evdnerf_ros.io.bag_reader as rb2

    monkeypatch.setattr(em, "BLOCK_EVENTS", 29)
    monkeypatch.setattr(rb2, "_BATCH_EVENTS", 77)
    ev = make_stream(rng, 2000)
    write_events_rosbag1(tmp_path / "s.bag", ev, width=W, height=H, topic=TOPIC, packet_ns=40_000_000)
    assert np.array_equal(read_events(tmp_path / "s.bag", TOPIC).events, ev)
