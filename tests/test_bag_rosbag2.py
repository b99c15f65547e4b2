"""rosbag2 event topics: byte-exact CDR, round trips per encoding x storage, an independent
MCAP reader as a peer, streaming, bag_info, and the error / atomic-output paths."""

from __future__ import annotations

import os
import sqlite3

import numpy as np
import pytest

from evdnerf_ros.errors import FormatError, InputError, OutputExistsError
from evdnerf_ros.events.types import EVENT_DTYPE, make_events, make_triggers
from evdnerf_ros.io import event_messages as em
from evdnerf_ros.io.rosbag2 import BagWriter, bag_info, iter_event_packets, open_bag, read_events
from evdnerf_ros.io.typestore import DVS_EVENT_ARRAY, EVENT_PACKET, ros2_typestore

W, H = 640, 480
T0 = 1_700_000_000_123_456_000  # an epoch time on the µs grid
TOPIC = "/event_camera/events"


def make_stream(rng, n=6000, span_ns=20_000_000_000, t0=T0, us_grid=True):
    """Events spanning > 16.78 s (the EVT3 24-bit µs wrap) with bursts and gaps."""
    if us_grid:
        t = t0 + np.sort(rng.integers(0, span_ns // 1000, n)) * 1000
    else:
        t = t0 + np.sort(rng.integers(0, span_ns, n))
    if n:
        t[: n // 10] = t[0]  # a burst of equal times
    return make_events(t, rng.integers(0, W, n), rng.integers(0, H, n), rng.integers(0, 2, n).astype(bool))


def make_trig(rng, events, n=20):
    t = np.sort(rng.choice(np.unique(events["t"]), n, replace=False))
    return make_triggers(t, rng.integers(0, 2, n), np.arange(n) % 2)


# --------------------------------------------------------------------------- byte layouts


def _rosbags_event_array(ts, events, frame_id, stamp_ns):
    T = ts.types
    Time = T["builtin_interfaces/msg/Time"]
    evs = [T["dvs_msgs/msg/Event"](x=int(e["x"]), y=int(e["y"]),
                                   ts=Time(sec=int(e["t"]) // 10**9, nanosec=int(e["t"]) % 10**9),
                                   polarity=bool(e["p"] > 0)) for e in events]
    hdr = T["std_msgs/msg/Header"](stamp=Time(sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9), frame_id=frame_id)
    return T[DVS_EVENT_ARRAY](header=hdr, height=H, width=W, events=evs)


@pytest.mark.parametrize("frame_id", ["", "a", "ab", "abc", "abcd", "event_camera", "ü"])
@pytest.mark.parametrize("n", [0, 1, 2, 5])
def test_cdr_event_array_is_byte_identical_to_rosbags(rng, frame_id, n):
    ts = ros2_typestore()
    ev = make_stream(rng, n, span_ns=3_000_000_000, t0=-1_500_000_000, us_grid=False)
    stamp = int(ev["t"][0]) if n else -7
    ref = bytes(ts.serialize_cdr(_rosbags_event_array(ts, ev, frame_id, stamp), DVS_EVENT_ARRAY))
    rec = em.cdr_event_records(ev, what="test")
    mv = memoryview(rec.view(np.uint8))
    ours = b"".join([em.CdrEventArrayPrefix(frame_id, H, W)(stamp, n), *em.cdr_events_bytes(mv, 0, n)])
    assert ours == ref
    got = em.parse_event_array(ref, what="test")
    assert np.array_equal(got.events, ev) and (got.width, got.height, got.frame_id, got.stamp_ns) == (W, H, frame_id, stamp)


@pytest.mark.parametrize("frame_id", ["", "ab", "abcde"])
@pytest.mark.parametrize("encoding", ["", "evt3", "mono", "libcaer_cmp"])
def test_cdr_event_packet_is_byte_identical_to_rosbags(frame_id, encoding):
    ts = ros2_typestore()
    T = ts.types
    payload = np.arange(7, dtype=np.uint8)
    hdr = T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=12, nanosec=34), frame_id=frame_id)
    msg = T[EVENT_PACKET](header=hdr, height=H, width=W, seq=2**40 + 3, time_base=T0, encoding=encoding,
                          is_bigendian=False, events=payload)
    ref = bytes(ts.serialize_cdr(msg, EVENT_PACKET))
    ours = em.CdrEventPacketPrefix(frame_id, H, W, encoding)(12 * 10**9 + 34, 2**40 + 3, T0, 7) + payload.tobytes()
    assert ours == ref
    f = em.parse_event_packet(ref, what="test")
    assert (f.stamp_ns, f.frame_id, f.height, f.width, f.seq, f.time_base, f.encoding) == \
        (12 * 10**9 + 34, frame_id, H, W, 2**40 + 3, T0, encoding)
    assert bytes(f.events) == payload.tobytes()


def test_truncated_message_is_a_format_error(rng):
    ev = make_stream(rng, 4)
    rec = em.cdr_event_records(ev, what="t")
    raw = b"".join([em.CdrEventArrayPrefix("cam", H, W)(int(ev["t"][0]), 4),
                    *em.cdr_events_bytes(memoryview(rec.view(np.uint8)), 0, 4)])
    with pytest.raises(FormatError, match="4 events need 61 bytes"):
        em.parse_event_array(raw[:-5], what="t")
    with pytest.raises(FormatError, match="truncated"):
        em.parse_event_array(raw[:10], what="t")


# --------------------------------------------------------------------------- round trips

ENCODINGS = ["evt3", "evt2", "mono", "array"]


def _write(path, ev, tr, encoding, storage, *, calls=3, **kw):
    cuts = np.linspace(0, ev.size, calls + 1).astype(int)
    n = 0
    with BagWriter(path, storage=storage) as w:
        for a, b in zip(cuts[:-1], cuts[1:]):
            part = ev[a:b]
            t_trig = None
            if tr is not None:
                lo = part["t"][0]
                hi = ev["t"][b] if b < ev.size else np.iinfo(np.int64).max
                t_trig = tr[(tr["t"] >= lo) & (tr["t"] < hi)]
            n += w.write_events(TOPIC, part, width=W, height=H, encoding=encoding, triggers=t_trig, **kw)
        w.write_camera_info("/event_camera/camera_info", W, H, [[500, 0, 320], [0, 500, 240], [0, 0, 1]],
                            stamp_ns=T0)
    return n


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
@pytest.mark.parametrize("encoding", ENCODINGS)
def test_round_trip_bit_exact(tmp_path, rng, encoding, storage):
    ev = make_stream(rng, us_grid=encoding in ("evt3", "evt2"))
    tr = make_trig(rng, ev) if encoding in ("evt3", "evt2") else None
    path = tmp_path / "bag"
    nmsg = _write(path, ev, tr, encoding, storage)
    assert sorted(os.listdir(tmp_path)) == ["bag"]  # no temporary left behind
    got = read_events(path, TOPIC)
    assert got.events.dtype == EVENT_DTYPE
    assert np.array_equal(got.events, ev)
    assert (got.width, got.height, got.encoding, got.message_count) == (W, H, encoding, nmsg)
    if tr is not None:
        assert np.array_equal(got.triggers, tr)
    else:
        assert got.triggers.size == 0
    # message by message: stamps are the packets' first times, bag time == header stamp
    pk = list(iter_event_packets(path, TOPIC))
    assert len(pk) == nmsg
    assert np.array_equal(np.concatenate([p.events for p in pk]), ev)
    assert all(p.bag_time_ns == p.stamp_ns for p in pk)
    assert [p.seq for p in pk] == (list(range(nmsg)) if encoding != "array" else [0] * nmsg)
    starts = [p.stamp_ns for p in pk]
    assert starts == sorted(starts)


def test_packets_close_at_packet_ns_and_max_events(tmp_path):
    t = T0 + np.array([0, 10, 999_999, 1_000_000, 1_000_001, 5_000_000, 5_000_001, 5_000_002])
    ev = make_events(t, [1] * 8, [2] * 8, [1] * 8)
    path = tmp_path / "b"
    with BagWriter(path) as w:
        assert w.write_events(TOPIC, ev, width=W, height=H, encoding="array") == 3
        assert w.write_events("/b", ev, width=W, height=H, encoding="mono", max_packet_events=2) == 5
    sizes = [p.events.size for p in iter_event_packets(path, TOPIC)]
    assert sizes == [3, 2, 3]
    assert [p.events.size for p in iter_event_packets(path, "/b")] == [2, 2, 1, 2, 1]
    assert [p.time_base for p in iter_event_packets(path, "/b")] == [T0, T0 + 999_999, T0 + 1_000_001,
                                                                      T0 + 5_000_000, T0 + 5_000_002]


def test_bare_mcap_and_db3_files_read_and_bag_info(tmp_path, rng):
    ev = make_stream(rng, 3000)
    tr = make_trig(rng, ev, 5)
    for storage, suffix in (("mcap", ".mcap"), ("sqlite3", ".db3")):
        path = tmp_path / storage
        with BagWriter(path, storage=storage) as w:
            w.write_events(TOPIC, ev, width=W, height=H, encoding="evt3", triggers=tr)
            w.write("/rig/status", "std_msgs/msg/String", ros2_typestore().types["std_msgs/msg/String"](data="hi"),
                    T0)
        bare = path / f"{storage}{suffix}"
        assert bare.exists()
        for p in (path, bare):
            got = read_events(p, TOPIC)
            assert np.array_equal(got.events, ev) and np.array_equal(got.triggers, tr)
            info = bag_info(p)
            assert info.storage == storage
            assert info.layout == ("rosbag2" if p == path else "file")
            assert set(info.topics) == {TOPIC, "/rig/status"}
            et = info.topics[TOPIC].events
            assert (et.event_count, et.trigger_count, et.width, et.height, et.encoding) == (ev.size, 5, W, H, "evt3")
            assert (et.first_ns, et.last_ns) == (int(ev["t"][0]), int(ev["t"][-1]))
            assert et.rate_ev_per_s == pytest.approx(ev.size / ((ev["t"][-1] - ev["t"][0]) / 1e9))
            assert info.start_ns == T0  # the String message; events start later
            assert info.end_ns == max(pk.bag_time_ns for pk in iter_event_packets(p, TOPIC))
            assert info.duration_ns == info.end_ns - info.start_ns
            assert info.message_count == info.topics[TOPIC].message_count + 1
            assert info.topics["/rig/status"].events is None and info.topics["/rig/status"].message_count == 1
    with open_bag(tmp_path / "mcap") as bag:
        (t, msg), = list(bag.read_messages("/rig/status"))
        assert (t, msg.data) == (T0, "hi")


def test_streaming_state_carries_across_calls(tmp_path, rng):
    ev = make_stream(rng, 5000)
    path = tmp_path / "s"
    with BagWriter(path) as w:
        for chunk in np.array_split(ev, 7):
            w.write_events(TOPIC, chunk, width=W, height=H, encoding="evt3", packet_ns=50_000_000)
    pk = list(iter_event_packets(path, TOPIC))
    assert [p.seq for p in pk] == list(range(len(pk)))
    assert {p.time_base for p in pk} == {0}  # metavision_driver's convention: sensor time in the payload
    assert all(p.stamp_ns == int(p.events["t"][0]) for p in pk)
    got = read_events(path, TOPIC)
    assert np.array_equal(got.events, ev)
    # the sensor clock starts at the first time rounded down to 4096 us (the date is in the stamps)
    assert got.time_offset_ns == int(ev["t"][0]) // 4_096_000 * 4_096_000


# --------------------------------------------------------------------------- independent reader


def _mcap_messages(path):
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    mcap_file = next(path.glob("*.mcap"))
    with open(mcap_file, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        return [(channel.topic, schema.name, message.log_time, ros_msg)
                for schema, channel, message, ros_msg in reader.iter_decoded_messages()]


def test_mcap_read_back_by_independent_reader_event_packet(tmp_path, rng):
    from evdnerf_ros.events.codecs import make_decoder

    ev = make_stream(rng, 4000)
    tr = make_trig(rng, ev, 8)
    path = tmp_path / "p"
    nmsg = _write(path, ev, tr, "evt3", "mcap", packet_ns=100_000_000)
    msgs = [m for m in _mcap_messages(path) if m[0] == TOPIC]
    assert len(msgs) == nmsg
    dec = None
    got_ev, got_tr = [], []
    for k, (topic, schema, log_time, m) in enumerate(msgs):
        assert schema == EVENT_PACKET
        stamp = m.header.stamp.sec * 10**9 + m.header.stamp.nanosec
        assert stamp == log_time
        assert (m.height, m.width, m.seq, m.encoding, m.is_bigendian) == (H, W, k, "evt3", False)
        assert m.header.frame_id == "event_camera"
        assert m.time_base == 0  # as metavision_driver writes evt3: sensor time in the payload
        if dec is None:  # the host time of sensor time 0, from the first stamp and the first sensor time
            probe = make_decoder("evt3").feed(bytes(m.events))
            first = min(int(a["t"][0]) for a in (probe.events, probe.triggers) if a.size)
            assert 0 <= first < 4_096_000  # the sensor clock starts near 0, whatever the date
            dec = make_decoder("evt3", time_base_ns=stamp - first)
        d = dec.feed(bytes(m.events))
        got_ev.append(d.events)
        got_tr.append(d.triggers)
        firsts = [int(a["t"][0]) for a in (d.events, d.triggers) if a.size]
        assert not firsts or min(firsts) == stamp
    d = dec.close()
    assert np.array_equal(np.concatenate(got_ev + [d.events]), ev)
    assert np.array_equal(np.concatenate(got_tr + [d.triggers]), tr)


def test_mcap_read_back_by_independent_reader_event_array(tmp_path, rng):
    ev = make_stream(rng, 3000, us_grid=False)
    path = tmp_path / "a"
    nmsg = _write(path, ev, None, "array", "mcap", packet_ns=250_000_000)
    msgs = [m for m in _mcap_messages(path) if m[0] == TOPIC]
    assert len(msgs) == nmsg
    parts = []
    for topic, schema, log_time, m in msgs:
        assert schema == DVS_EVENT_ARRAY
        assert (m.height, m.width, m.header.frame_id) == (H, W, "event_camera")
        e = m.events
        got = make_events(np.array([x.ts.sec * 10**9 + x.ts.nanosec for x in e], np.int64),
                          np.array([x.x for x in e]), np.array([x.y for x in e]), np.array([x.polarity for x in e]))
        assert log_time == m.header.stamp.sec * 10**9 + m.header.stamp.nanosec == int(got["t"][0])
        parts.append(got)
    assert np.array_equal(np.concatenate(parts), ev)
    ci = [m for m in _mcap_messages(path) if m[0] == "/event_camera/camera_info"]
    assert len(ci) == 1 and list(ci[0][3].k) == [500, 0, 320, 0, 500, 240, 0, 0, 1]


def test_sqlite3_rows_read_back_with_stdlib_sqlite(tmp_path, rng):
    ev = make_stream(rng, 2000, us_grid=False)
    path = tmp_path / "q"
    nmsg = _write(path, ev, None, "array", "sqlite3")
    con = sqlite3.connect(next(path.glob("*.db3")))
    rows = con.execute("SELECT m.timestamp, m.data FROM messages m JOIN topics t ON m.topic_id = t.id "
                       "WHERE t.name = ? AND t.type = ? ORDER BY m.timestamp", (TOPIC, DVS_EVENT_ARRAY)).fetchall()
    con.close()
    assert len(rows) == nmsg
    ts = ros2_typestore()
    first = ts.deserialize_cdr(rows[0][1], DVS_EVENT_ARRAY)  # rosbags' own (per-object) deserialiser
    assert rows[0][0] == first.header.stamp.sec * 10**9 + first.header.stamp.nanosec == int(ev["t"][0])
    assert [(e.x, e.y, e.polarity) for e in first.events[:5]] == \
        [(int(e["x"]), int(e["y"]), bool(e["p"] > 0)) for e in ev[:5]]


# --------------------------------------------------------------------------- errors


def test_missing_topic_lists_existing_topics(tmp_path, rng):
    path = tmp_path / "b"
    _write(path, make_stream(rng, 100), None, "array", "mcap", calls=1)
    with pytest.raises(InputError, match=r"no topic '/nope'.*/event_camera/camera_info \[sensor_msgs/msg/CameraInfo\]"):
        read_events(path, "/nope")
    with pytest.raises(InputError, match="has type sensor_msgs/msg/CameraInfo; event topics must be"):
        read_events(path, "/event_camera/camera_info")


def test_existing_output_is_refused(tmp_path):
    (tmp_path / "b").mkdir()
    with pytest.raises(OutputExistsError, match="already exists"):
        BagWriter(tmp_path / "b")
    with pytest.raises(OutputExistsError):
        with BagWriter(tmp_path / "b"):
            pass


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_truncated_bag_is_a_clear_error(tmp_path, rng, storage):
    path = tmp_path / "b"
    _write(path, make_stream(rng, 20000), None, "array", storage, calls=1)
    f = next(p for p in path.iterdir() if p.suffix in (".mcap", ".db3"))
    data = f.read_bytes()
    f.write_bytes(data[: len(data) // 2])
    with pytest.raises(FormatError, match=str(f.name) if storage == "mcap" else "b"):
        read_events(path, TOPIC)
    with pytest.raises(FormatError):
        read_events(f, TOPIC)


def test_not_a_bag(tmp_path):
    p = tmp_path / "x.mcap"
    p.write_bytes(b"hello world, not a bag")
    with pytest.raises(InputError, match="not a bag"):
        read_events(p)
    with pytest.raises(InputError, match="no such file"):
        read_events(tmp_path / "missing")
    (tmp_path / "d").mkdir()
    with pytest.raises(InputError, match="without metadata.yaml"):
        read_events(tmp_path / "d")


def test_bad_event_inputs(tmp_path, rng):
    ev = make_stream(rng, 50)
    with BagWriter(tmp_path / "b") as w:
        with pytest.raises(InputError, match="not a whole microsecond.*mono"):
            w.write_events("/e", make_events([T0, T0 + 1500], [0, 1], [0, 0], [1, 1]), width=W, height=H)
        with pytest.raises(InputError, match="triggers are only carried by encoding 'evt3'"):
            w.write_events("/m", ev, width=W, height=H, encoding="mono", triggers=make_trig(rng, ev, 2))
        with pytest.raises(InputError, match="negative"):
            w.write_events("/n", make_events([-5, 3], [0, 1], [0, 0], [1, 1]), width=W, height=H, encoding="array")
        with pytest.raises(InputError, match="outside the declared"):
            w.write_events("/o", ev, width=10, height=10, encoding="array")
        with pytest.raises(InputError, match="encoding 'raw'"):
            w.write_events("/r", ev, width=W, height=H, encoding="raw")
        w.write_events("/s", ev[25:], width=W, height=H, encoding="array")
        with pytest.raises(InputError, match="successive calls must continue in time"):
            w.write_events("/s", ev[:25], width=W, height=H, encoding="array")
        with pytest.raises(InputError, match="one topic carries one stream"):
            w.write_events("/s", ev[49:], width=W, height=H, encoding="mono")
        with pytest.raises(InputError, match="absolute ROS topic"):
            w.write_events("events", ev, width=W, height=H)
        with pytest.raises(InputError, match="unknown message type"):
            w.write("/x", "nope_msgs/msg/Nope", object(), 0)
        with pytest.raises(InputError, match="integer"):
            w.write_camera_info("/ci", W, H, np.eye(3), stamp_ns=1.5)
    # the early (pre-write) errors above leave a valid bag with the one good topic
    assert np.array_equal(read_events(tmp_path / "b", "/s").events, ev[25:])


def test_exception_mid_write_leaves_nothing(tmp_path, rng):
    ev = make_stream(rng, 2000)
    with pytest.raises(RuntimeError, match="boom"):
        with BagWriter(tmp_path / "b") as w:
            w.write_events(TOPIC, ev, width=W, height=H, encoding="array")
            raise RuntimeError("boom")
    assert os.listdir(tmp_path) == []


def test_failure_inside_write_events_discards_the_bag(tmp_path, rng, monkeypatch):
    ev = make_stream(rng, 2000)
    w = BagWriter(tmp_path / "b", storage="sqlite3").open()
    calls = {"n": 0}
    real = w._write_raw

    def flaky(conn, t, data):
        calls["n"] += 1
        if calls["n"] == 5:
            raise OSError("disk full")
        real(conn, t, data)

    monkeypatch.setattr(w, "_write_raw", flaky)
    with pytest.raises(OSError, match="disk full"):
        w.write_events(TOPIC, ev, width=W, height=H, encoding="array")
    with pytest.raises(InputError, match="failed part-way"):  # even a caller that swallowed the error
        w.close()
    assert os.listdir(tmp_path) == []


# --------------------------------------------------------------------------- generic reading


@pytest.mark.parametrize("ros1", [False, True])
def test_foreign_message_types_are_read_with_the_bags_definition(tmp_path, ros1):
    from rosbags.rosbag1 import Writer as Writer1
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    ts.register(get_types_from_msg("int32 a\nstring b\nstd_msgs/Header h\n", "my_msgs/msg/Foo"))
    T = ts.types
    stamp = T["builtin_interfaces/msg/Time"](sec=1, nanosec=2)
    hdr = T["std_msgs/msg/Header"](seq=3, stamp=stamp, frame_id="f") if ros1 else \
        T["std_msgs/msg/Header"](stamp=stamp, frame_id="f")
    msg = T["my_msgs/msg/Foo"](a=-5, b="x", h=hdr)
    if ros1:
        path = tmp_path / "foreign.bag"
        with Writer1(path) as w:
            w.write(w.add_connection("/foo", "my_msgs/msg/Foo", typestore=ts), 10, ts.serialize_ros1(msg, "my_msgs/msg/Foo"))
    else:
        path = tmp_path / "foreign"
        with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as w:
            w.write(w.add_connection("/foo", "my_msgs/msg/Foo", typestore=ts), 10, ts.serialize_cdr(msg, "my_msgs/msg/Foo"))
    with open_bag(path) as bag:
        assert bag.topics["/foo"].msgtype == "my_msgs/msg/Foo"
        ((t, got),) = list(bag.read_messages("/foo"))
    assert (t, got.a, got.b, got.h.frame_id, got.h.stamp.nanosec) == (10, -5, "x", "f", 2)
    with pytest.raises(InputError, match="has type my_msgs/msg/Foo"):
        read_events(path, "/foo")


def test_empty_bag_info(tmp_path):
    with BagWriter(tmp_path / "e", storage="sqlite3"):
        pass
    info = bag_info(tmp_path / "e")
    assert (info.message_count, info.start_ns, info.end_ns, info.duration_ns, info.topics) == (0, None, None, 0, {})


def test_write_raw_passes_serialised_messages_through(tmp_path):
    ts = ros2_typestore()
    raw = bytes(ts.serialize_cdr(ts.types["std_msgs/msg/String"](data="raw"), "std_msgs/msg/String"))
    with BagWriter(tmp_path / "r") as w:
        w.write_raw("/s", "std_msgs/msg/String", raw, 5)
        with pytest.raises(InputError, match="already carries std_msgs/msg/String"):
            w.write("/s", "std_msgs/msg/Int32", ts.types["std_msgs/msg/Int32"](data=1), 6)
    with open_bag(tmp_path / "r") as bag:
        assert [m.data for m in bag.messages("/s")] == [raw]


@pytest.mark.parametrize("encoding", ENCODINGS)
def test_small_blocks_and_batches_give_the_same_result(tmp_path, rng, monkeypatch, encoding):
    """Writing in record blocks and reading in batches (normally 1 Mi events / 2 MiB) is invisible."""
    import evdnerf_ros.io.bag_reader as rb2

    monkeypatch.setattr(em, "BLOCK_EVENTS", 37)
    monkeypatch.setattr(rb2, "_BATCH_EVENTS", 101)
    monkeypatch.setattr(rb2, "_BATCH_BYTES", 333)
    ev = make_stream(rng, 3000, us_grid=encoding in ("evt3", "evt2"))
    tr = make_trig(rng, ev) if encoding in ("evt3", "evt2") else None
    _write(tmp_path / "b", ev, tr, encoding, "mcap", packet_ns=20_000_000)
    got = read_events(tmp_path / "b", TOPIC)
    assert np.array_equal(got.events, ev)
    if tr is not None:
        assert np.array_equal(got.triggers, tr)
    assert bag_info(tmp_path / "b").topics[TOPIC].events.event_count == ev.size


def test_events_out_of_order_across_messages(tmp_path, rng):
    ev = make_stream(rng, 200, us_grid=False)
    prefix = em.CdrEventArrayPrefix("cam", H, W)

    def raw(part):
        rec = em.cdr_event_records(part, what="t")
        return b"".join([prefix(int(part["t"][0]), part.size),
                         *em.cdr_events_bytes(memoryview(rec.view(np.uint8)), 0, part.size)])

    with BagWriter(tmp_path / "u") as w:  # a foreign recorder: later events first
        w.write_raw(TOPIC, DVS_EVENT_ARRAY, raw(ev[100:]), T0)
        w.write_raw(TOPIC, DVS_EVENT_ARRAY, raw(ev[:100]), T0 + 1)
    with pytest.raises(FormatError, match="go back in time at index 100.*sort=True"):
        read_events(tmp_path / "u", TOPIC)
    assert np.array_equal(read_events(tmp_path / "u", TOPIC, sort=True).events, ev)
