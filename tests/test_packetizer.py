"""The packetizer and what composes it: raw sensor bytes passed through byte for byte, round
trips with absolute (epoch) times through rosbag2 MCAP / sqlite3 and ROS 1 bags for every
encoding, metavision_driver's evt3 time convention written and read, re-encoding a bag,
storage inference and picking the only event topic."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from evdnerf_ros.errors import InputError
from evdnerf_ros.events.codecs import encode, make_decoder
from evdnerf_ros.events.types import make_events, make_triggers
from evdnerf_ros.io import event_messages as em
from evdnerf_ros.io.bag_reader import iter_event_packets, open_bag, pick_event_topic, read_events
from evdnerf_ros.io.packetizer import Packetizer
from evdnerf_ros.io.reencode import reencode_bag
from evdnerf_ros.io.rosbag1 import Rosbag1Writer
from evdnerf_ros.io.rosbag2 import BagWriter
from evdnerf_ros.io.typestore import EVENT_PACKET, ros2_typestore

W, H = 640, 480
EPOCH = 1_744_227_144_744_040_812  # a 2025 host time, not on the microsecond grid
TOPIC = "/event_camera/events"


def epoch_events(rng, n=4000, span_us=3_000_000, t0=EPOCH - EPOCH % 1000):
    t = t0 + np.sort(rng.integers(0, span_us, n)) * 1000
    t[:50] = t[0]
    return make_events(t, rng.integers(0, W, n), rng.integers(0, H, n), rng.integers(0, 2, n).astype(bool))


def collect():
    got = []
    return got, lambda topic, msgtype, data, t: got.append((topic, msgtype, bytes(data), t))


# --------------------------------------------------------------------------- raw pass-through


@pytest.mark.parametrize("ros1", [False, True])
def test_raw_evt3_bytes_pass_through_byte_identical(rng, ros1):
    ev = epoch_events(rng, 3000)
    raw = encode(ev, "evt3", time_base_ns=int(ev["t"][0]) - 5000)  # a camera's stream: sensor time 5 ms on
    chunks = [raw[:1000], raw[1000:2470], raw[2470:]]                 # USB transfers: whole 16-bit words
    got, sink = collect()
    pk = Packetizer(sink, ros1=ros1)
    stamps = [EPOCH, EPOCH + 1_000_123, EPOCH + 2_000_456]
    for c, s in zip(chunks, stamps):
        assert pk.write_raw_packet(TOPIC, c, encoding="evt3", width=W, height=H, stamp_ns=s, frame_id="cam") == 1
    assert [g[3] for g in got] == stamps and {g[:2] for g in got} == {(TOPIC, EVENT_PACKET)}
    fields = [em.parse_event_packet(g[2], ros1=ros1) for g in got]
    assert [bytes(f.events) for f in fields] == chunks
    assert b"".join(bytes(f.events) for f in fields) == raw
    assert [(f.seq, f.time_base, f.stamp_ns, f.frame_id, f.encoding) for f in fields] == \
        [(k, 0, s, "cam", "evt3") for k, s in enumerate(stamps)]
    if not ros1:  # and rosbags' own deserialiser agrees on the whole message
        m = ros2_typestore().deserialize_cdr(got[1][2], EVENT_PACKET)
        assert bytes(m.events) == chunks[1] and (m.width, m.height, m.seq) == (W, H, 1)


def test_raw_pass_through_into_a_bag_and_decoded(tmp_path, rng):
    ev = epoch_events(rng, 2000)
    origin = int(ev["t"][0]) - 7000
    raw = encode(ev, "evt3", time_base_ns=origin)
    with BagWriter(tmp_path / "b") as w:
        w.write_raw_packet(TOPIC, raw, encoding="evt3", width=W, height=H, stamp_ns=int(ev["t"][0]))
        with pytest.raises(InputError, match="whole number of 2-byte words"):
            w.write_raw_packet(TOPIC, raw[:5], encoding="evt3", width=W, height=H, stamp_ns=int(ev["t"][-1]))
        with pytest.raises(InputError, match="either passed-through bytes or packetised events"):
            w.write_events(TOPIC, ev[-1:], width=W, height=H)
    with open_bag(tmp_path / "b") as bag:
        (m,) = list(bag.messages(TOPIC))
    assert bytes(em.parse_event_packet(m.data).events) == raw
    got = read_events(tmp_path / "b", TOPIC)
    assert np.array_equal(got.events, ev) and got.time_offset_ns == origin


# --------------------------------------------------------------------------- epoch round trips


@pytest.mark.parametrize("encoding", ["evt3", "evt2", "mono", "array", "libcaer", "libcaer_cmp"])
@pytest.mark.parametrize("container", ["mcap", "sqlite3", "ros1"])
def test_epoch_round_trip_every_container(tmp_path, rng, encoding, container):
    ev = epoch_events(rng, 3000, span_us=40_000_000)   # 40 s: crosses the EVT3 24-bit wrap
    if encoding in ("mono", "array"):
        ev["t"] += rng.integers(0, 1000, ev.size)       # ns resolution
        ev = ev[np.argsort(ev["t"], kind="stable")]
    tr = make_triggers(np.sort(rng.choice(ev["t"], 6, replace=False)), [0, 1] * 3, [0] * 6) \
        if encoding in ("evt3", "evt2") else None
    path = tmp_path / ("b.bag" if container == "ros1" else "b")
    writer = Rosbag1Writer(path) if container == "ros1" else BagWriter(path, storage=container)
    with writer as w:
        for part in np.array_split(ev, 3):
            t_tr = None if tr is None else tr[(tr["t"] >= part["t"][0]) & (tr["t"] <= part["t"][-1])]
            w.write_events(TOPIC, part, width=W, height=H, encoding=encoding, triggers=t_tr, packet_ns=250_000_000)
    got = read_events(path, TOPIC)
    assert np.array_equal(got.events, ev) and got.encoding == encoding
    if tr is not None:
        assert np.array_equal(got.triggers, tr[np.isin(tr["t"], got.triggers["t"])]) and got.triggers.size
    pks = list(iter_event_packets(path, TOPIC))
    assert all(p.stamp_ns == p.bag_time_ns for p in pks)
    assert all(p.stamp_ns == min([int(a["t"][0]) for a in (p.events, p.triggers) if a.size]) for p in pks)


def test_metavision_time_convention_written(tmp_path, rng):
    """evt3 as metavision_driver writes it: time_base 0, sensor time in the payload starting near
    0 (not at the date), header.stamp = the packet's first event time."""
    ev = epoch_events(rng, 5000, span_us=20_000_000)
    with BagWriter(tmp_path / "b") as w:
        w.write_events(TOPIC, ev, width=W, height=H, encoding="evt3")
    with open_bag(tmp_path / "b") as bag:
        fields = [em.parse_event_packet(m.data) for m in bag.messages(TOPIC)]
    assert {f.time_base for f in fields} == {0}
    sensor = make_decoder("evt3")  # what event_camera_codecs sees: time_base ignored, sensor time only
    parts = [sensor.feed(bytes(f.events)).events for f in fields]
    st = np.concatenate(parts)["t"]
    assert 0 <= st[0] < 4_096_000 and np.array_equal(st - st[0], ev["t"] - ev["t"][0])
    # every packet's stamp is its first event's time: stamp - sensor time is one constant offset
    offsets = {f.stamp_ns - int(p["t"][0]) for f, p in zip(fields, parts)}
    assert len(offsets) == 1 and offsets.pop() == int(ev["t"][0]) - int(st[0])
    # bag size follows the events, not the date (no TIME_HIGH filler from sensor time 0 to 2025)
    assert sum(len(f.events) for f in fields) < 8 * ev.size


def test_old_convention_bags_still_read(tmp_path, rng):
    """Bags written before: evt3 time_base = the topic's first time, sensor time from 0."""
    ev = epoch_events(rng, 1000)
    tb = int(ev["t"][0])
    payload = encode(ev, "evt3", time_base_ns=tb)
    prefix = em.CdrEventPacketPrefix("event_camera", H, W, "evt3")
    with BagWriter(tmp_path / "b") as w:
        w.write_raw(TOPIC, EVENT_PACKET, prefix(tb, 0, tb, len(payload)) + payload, tb)
    got = read_events(tmp_path / "b", TOPIC)
    assert np.array_equal(got.events, ev) and got.time_offset_ns == tb


def test_packetizer_sink_gets_what_the_bag_gets(tmp_path, rng):
    ev = epoch_events(rng, 3000)
    got, sink = collect()
    Packetizer(sink).write_events(TOPIC, ev, width=W, height=H, encoding="evt3")
    with BagWriter(tmp_path / "b") as w:
        w.write_events(TOPIC, ev, width=W, height=H, encoding="evt3")
    with open_bag(tmp_path / "b") as bag:
        assert [(m.t_ns, bytes(m.data)) for m in bag.messages(TOPIC)] == [(g[3], g[2]) for g in got]


def test_packetizer_errors():
    got, sink = collect()
    pk = Packetizer(sink)
    ev = make_events([10_000, 20_500], [0, 1], [0, 1], [1, 1])
    with pytest.raises(InputError, match="not a whole microsecond.*quantize_to_us"):
        pk.write_events(TOPIC, ev, width=W, height=H, encoding="evt3")
    with pytest.raises(InputError, match="x < 2048"):
        pk.write_events("/c", ev, width=4096, height=H, encoding="libcaer_cmp")
    with pytest.raises(InputError, match="must be callable"):
        Packetizer(object())
    assert got == [] and not pk.topics


# --------------------------------------------------------------------------- re-encoding


@pytest.mark.parametrize("encoding", ["evt3", "mono", "libcaer_cmp"])
def test_reencode_keeps_stamps_seq_frame_id_and_other_topics(tmp_path, rng, encoding):
    ev = epoch_events(rng, 3000)
    src = tmp_path / "src"
    hdr_shift = 123_457  # host stamps a little after the first events, as drivers stamp
    ts = ros2_typestore()
    with BagWriter(src, storage="sqlite3") as w:
        for k, part in enumerate(np.array_split(ev, 5)):
            w.write_packet(TOPIC, part, width=W, height=H, encoding="array", stamp_ns=int(part["t"][0]) + hdr_shift,
                           seq=40 + k, frame_id="dvs", t_ns=int(part["t"][0]) + 2 * hdr_shift)
        w.write("/rig/status", "std_msgs/msg/String", ts.types["std_msgs/msg/String"](data="hi"), EPOCH)
    out = tmp_path / "out.mcap"
    out = tmp_path / "out"
    rep = reencode_bag(src, out, encoding=encoding)
    assert (rep["topic"], rep["messages"], rep["events"], rep["copied"]) == (TOPIC, 5, ev.size, {"/rig/status": 1})
    a, b = list(iter_event_packets(src, TOPIC)), list(iter_event_packets(out, TOPIC))
    assert [(p.stamp_ns, p.bag_time_ns, p.frame_id) for p in a] == [(p.stamp_ns, p.bag_time_ns, p.frame_id) for p in b]
    assert [p.seq for p in b] == [0] * 5 or [p.seq for p in b] == list(range(5))  # ROS 2 EventArray has no seq
    assert np.array_equal(read_events(out, TOPIC).events, ev)
    with open_bag(out) as bag:
        assert [(t, m.data) for t, m in bag.read_messages("/rig/status")] == [(EPOCH, "hi")]
    # and again from the re-encoded bag (EventPacket seq now kept), repacketised, events only
    out2 = tmp_path / "out2"
    reencode_bag(out, out2, encoding="evt3")
    assert [p.seq for p in iter_event_packets(out2, TOPIC)] == [p.seq for p in b]
    out3 = tmp_path / "out3.bag"
    rep = reencode_bag(out, out3, encoding="array", repacketize=True, packet_ns=1_000_000_000, other_topics=False)
    assert np.array_equal(read_events(out3, TOPIC).events, ev) and rep["copied"] == {}
    with pytest.raises(InputError, match="other_topics=False"):
        reencode_bag(out, tmp_path / "x.bag")


def test_reencode_refuses_losing_triggers(tmp_path, rng):
    ev = epoch_events(rng, 500)
    with BagWriter(tmp_path / "s") as w:
        w.write_events(TOPIC, ev, width=W, height=H, triggers=make_triggers(ev["t"][:1], [1], [0]))
    with pytest.raises(InputError, match="trigger.*use encoding 'evt3'"):
        reencode_bag(tmp_path / "s", tmp_path / "o", encoding="mono")
    assert not (tmp_path / "o").exists()


# --------------------------------------------------------------------------- storage, topics


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_metadata_without_storage_identifier_is_inferred(tmp_path, rng, storage):
    ev = epoch_events(rng, 500)
    src = tmp_path / "b"
    with BagWriter(src, storage=storage) as w:
        w.write_events(TOPIC, ev, width=W, height=H)
    import yaml

    meta = src / "metadata.yaml"
    doc = yaml.safe_load(meta.read_text())
    info = doc["rosbag2_bagfile_information"]
    assert info["storage_identifier"] == storage
    info["storage_identifier"], info["files"] = "", []   # as test_events_2 (libcaer_driver) has it
    meta.write_text(yaml.safe_dump(doc))
    with open_bag(src) as bag:
        assert bag.storage == storage and bag.storage_inferred
    assert np.array_equal(read_events(src, TOPIC).events, ev)
    # an unusual suffix: told by the magic bytes, as ROS 2 asks each storage plugin
    odd = tmp_path / "odd"
    shutil.copytree(src, odd)
    for f in odd.iterdir():
        if f.suffix in (".mcap", ".db3"):
            f.rename(f.with_suffix(".bin"))
    (odd / "metadata.yaml").write_text(meta.read_text().replace(".mcap", ".bin").replace(".db3", ".bin"))
    with open_bag(odd) as bag:
        assert bag.storage == storage
    # files of no known kind: a clear error
    bad = tmp_path / "bad"
    shutil.copytree(odd, bad)
    next(bad.glob("*.bin")).write_bytes(b"not a bag at all")
    from evdnerf_ros.errors import FormatError

    with pytest.raises(FormatError, match="storage_identifier"):
        read_events(bad, TOPIC)


def test_pick_event_topic(tmp_path, rng):
    ev = epoch_events(rng, 100)
    with BagWriter(tmp_path / "one") as w:
        w.write_events("/cam/events", ev, width=W, height=H)
        w.write_camera_info("/cam/camera_info", W, H, np.eye(3), stamp_ns=EPOCH)
    assert pick_event_topic(tmp_path / "one") == "/cam/events"
    assert pick_event_topic(tmp_path / "one", "/x") == "/x"
    with BagWriter(tmp_path / "two") as w:
        w.write_events("/a", ev, width=W, height=H)
        w.write_events("/b", ev, width=W, height=H, encoding="array")
    with pytest.raises(InputError, match=r"2 event topics \(/a \[event_camera_msgs/msg/EventPacket\], /b .*--topic"):
        pick_event_topic(tmp_path / "two")
    with BagWriter(tmp_path / "none") as w:
        w.write_camera_info("/ci", W, H, np.eye(3), stamp_ns=EPOCH)
    with pytest.raises(InputError, match="no event topic"):
        pick_event_topic(tmp_path / "none")
