"""Real recordings from real cameras (../shared/data/real/, see its README for the sources and
the reference values their projects test against). Skipped where that folder is absent."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest

from evdnerf_ros.cli import main
from evdnerf_ros.io.event_files import read_event_file
from evdnerf_ros.io.raw import read_raw_header

REAL = Path(os.environ.get("EVDNERF_REAL_DATA", Path(__file__).resolve().parents[1].parent / "shared" / "data" / "real"))
EXPELLIARMUS = REAL / "expelliarmus"
pytestmark = pytest.mark.skipif(not EXPELLIARMUS.is_dir(), reason=f"real recordings not found at {REAL}")


def test_gen41_evt3_file_decodes_as_openeb_does():
    """A Gen4.1 writes a TIME_LOW at once replaced by a lower one about once per ms: not
    corruption. Reference: 219,596 CD events at 11,718,656 .. 11,727,457 us."""
    path = EXPELLIARMUS / "evt3_sample.raw"
    data = read_event_file(path)
    ev = data.events
    assert ev.size == 219_596
    assert (int(ev["t"][0]) // 1000, int(ev["t"][-1]) // 1000) == (11_718_656, 11_727_457)
    assert np.all(np.diff(ev["t"]) >= 0)
    assert (data.width, data.height) == (1280, 720)          # from plugin_name hal_plugin_gen41_evk3
    assert data.anomalies["time_low_back"] > 0
    # expelliarmus' own decode has x, y, p right (its times drift at each TIME_LOW decrease)
    theirs = np.load(EXPELLIARMUS / "evt3_sample.npy")
    assert np.array_equal(ev["x"], theirs["x"]) and np.array_equal(ev["y"], theirs["y"])
    assert np.array_equal(ev["p"], np.where(theirs["p"] > 0, 1, -1))


def test_gen3_evt2_file_without_geometry_line():
    """Reference: 539,481 CD events at 1,317,888 .. 1,367,888 us; no geometry line (640x480)."""
    path = EXPELLIARMUS / "evt2_sample.raw"
    assert (read_raw_header(path).width, read_raw_header(path).height) == (640, 480)
    ev = read_event_file(path).events
    assert ev.size == 539_481
    assert (int(ev["t"][0]) // 1000, int(ev["t"][-1]) // 1000) == (1_317_888, 1_367_888)


def test_cli_reads_and_converts_the_real_evt3_file(tmp_path, capsys):
    path = EXPELLIARMUS / "evt3_sample.raw"
    assert main(["info", str(path)]) == 0
    out = capsys.readouterr().out
    assert "1280x720" in out and "tolerated" in out and "time low back" in out
    assert main(["convert-events", str(path), str(tmp_path / "e.npz")]) == 0
    assert main(["render-events", str(tmp_path / "e.npz"), "--start", "0", "--window", "1ms",
                 "-o", str(tmp_path / "e.png")]) == 0
    assert read_event_file(tmp_path / "e.npz").events.size == 219_596


# --------------------------------------------------------------------------- bags from real cameras

BAG_TOPIC = "/event_camera/events"


def _need(path):
    if not path.exists():
        pytest.skip(f"real recording {path} not found")
    return path


@pytest.mark.parametrize("name", ["event_camera_py/test_events_1", "event_camera_py/test_events_1.bag"])
def test_metavision_driver_evt3_bag_matches_event_camera_py(name):
    """metavision_driver's convention (time_base 0, sensor time in the payload): events land on
    the host clock of the first packet; the payload's sensor times match event_camera_py's test."""
    from evdnerf_ros.io.bag_reader import iter_event_packets, read_events

    path = _need(REAL / name)
    s = read_events(path, BAG_TOPIC)
    ev, tr, off = s.events, s.triggers, s.time_offset_ns
    first = next(iter_event_packets(path, BAG_TOPIC))
    # on the host clock: the first packet's first item (here a trigger) is at its stamp
    assert first.time_base == 0 and min(int(ev["t"][0]), int(tr["t"][0])) == first.stamp_ns
    sensor_ns = np.concatenate([ev["t"], tr["t"]]) - off
    assert np.all(sensor_ns % 1000 == 0)
    assert ((ev["p"] < 0).sum(), (ev["p"] > 0).sum()) == (218_291, 125_183)
    assert int(sensor_ns.sum()) // 1000 == 2_885_601_049_874
    assert ((tr["value"] == 0).sum(), (tr["value"] != 0).sum()) == (2078, 2079)
    assert (int(ev["t"][0]) - off) // 1000 == 7_139_845
    assert (s.width, s.height) == (640, 480)


def test_evt3_trigger_bag_matches_event_camera_codecs():
    from evdnerf_ros.io.bag_reader import read_events

    s = read_events(_need(REAL / "event_camera_codecs" / "test_data_evt3_trigger"), BAG_TOPIC)
    ev, tr, off = s.events, s.triggers, s.time_offset_ns
    assert int((ev["t"] - off).sum()) == 1_222_326_831_810_000
    assert (int(ev["x"].sum()), int(ev["y"].sum()), int((ev["p"] > 0).sum())) == (42_078_718, 31_656_267, 41_439)
    assert (int((tr["t"] - off).sum()), int(tr["value"].sum()), int(tr["id"].sum())) == (29_096_982_000, 1, 0)


def test_the_pre_2023_event_array_msgs_bag_reads_as_event_camera_codecs_does(tmp_path, capsys):
    """`event_array_msgs/msg/EventArray`, EventPacket's name before the rename (mono encoding):
    read, listed by `info` with its events and converted; the codec's own test's sums."""
    from evdnerf_ros.cli import main
    from evdnerf_ros.io.bag_reader import read_events

    path = _need(REAL / "event_camera_codecs" / "test_data_mono_cd")
    s = read_events(path, BAG_TOPIC)
    ev = s.events
    assert (int(ev["t"].sum()), int(ev["x"].sum()), int(ev["y"].sum()), int((ev["p"] > 0).sum())) == \
        (4_950_000, 34_450, 26_450, 50)
    assert main(["info", str(path), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["topics"][0]["type"] == "event_array_msgs/msg/EventArray" and info["events"]["count"] == 100
    out = tmp_path / "events.npz"
    assert main(["convert-events", str(path), str(out)]) == 0
    assert np.array_equal(read_event_file(out).events, ev)


def _payloads(path):
    from evdnerf_ros.io import event_messages as em
    from evdnerf_ros.io.bag_reader import open_bag

    with open_bag(path) as bag:
        return [em.parse_event_packet(m.data) for m in bag.messages(BAG_TOPIC)]


def test_libcaer_cmp_bag_with_empty_storage_identifier():
    """libcaer_driver's compressed encoding, in a rosbag2 whose metadata names no storage and lists
    no files. Checked independently of our decoder, from the token counts of the raw payloads."""
    from evdnerf_ros.io.bag_reader import open_bag, read_events

    path = _need(REAL / "event_camera_py" / "test_events_2")
    with open_bag(path) as bag:
        assert (bag.storage, bag.storage_inferred, bag.message_count) == ("mcap", True, 100)
    s = read_events(path, BAG_TOPIC)
    ev = s.events
    fields = _payloads(path)
    words = np.concatenate([np.frombuffer(bytes(f.events), "<u2") for f in fields])
    code = words >> 12
    assert int(code.max()) <= 5                                   # no VECT_12 / unknown tokens
    # one event per ADDR_Y, one per set bit of each VECT_8 (event_camera_codecs' count: nothing
    # lies outside the 346x260 geometry here)
    v8 = words[code == 5] & 0xFF
    expect = int((code == 3).sum()) + int(np.unpackbits(v8.astype(np.uint8)).sum())
    assert ev.size == expect == 571_266 and s.dropped_out_of_geometry == 0
    # polarity: ADDR_Y's bit 11, or the VECT_BASE_Y before each VECT_8 (libcaer_driver writes them in pairs)
    prev = np.flatnonzero(code == 5) - 1
    assert np.all(code[prev] == 4)
    on = int(((code == 3) & ((words >> 11) & 1 == 1)).sum()) + \
        int(np.unpackbits(v8[((words[prev] >> 11) & 1) == 1].astype(np.uint8)).sum())
    assert int((ev["p"] > 0).sum()) == on
    assert (s.width, s.height, s.encoding) == (346, 260, "libcaer_cmp")
    assert int(ev["x"].max()) < 346 and int(ev["y"].max()) < 260
    assert np.all(np.diff(ev["t"]) >= 0)
    # each message's first event is at its time_base (offset 0): a host time in 2025
    assert int(ev["t"][0]) == fields[0].time_base and 2025 == 1970 + int(ev["t"][0]) // (365.25 * 86400e9)


def test_libcaer_bag_across_the_timestamp_rollover():
    """libcaer_driver's raw records across the 31-bit microsecond rollover: the driver moves the
    high bits into time_base (a 2**31 us step between packets); times stay monotonic."""
    from evdnerf_ros.io.bag_reader import read_events

    path = _need(REAL / "event_camera_codecs" / "test_data_libcaer_rollover")
    fields = _payloads(path)
    tbs = np.array([f.time_base for f in fields], np.int64)
    assert set(np.diff(tbs).tolist()) == {0, 2**31 * 1000}          # the rollover is in this file
    recs = [np.frombuffer(bytes(f.events), [("d", "<u4"), ("ts", "<i4")]) for f in fields]
    s = read_events(path, BAG_TOPIC)
    ev = s.events
    assert ev.size == sum(r.size for r in recs) == 334_331               # 8 bytes per event
    assert np.all(np.diff(ev["t"]) >= 0)
    gap = int(np.diff(ev["t"]).max())
    assert gap < 100_000_000                                             # no 35-minute jump at the rollover
    assert (s.width, s.height) == (640, 480)
    assert int(ev["x"].max()) < 640 and int(ev["y"].max()) < 480
    # the first event of every packet is time_base + 1000 * its timestamp
    starts = np.cumsum([0] + [r.size for r in recs[:-1]])
    assert np.array_equal(ev["t"][starts], tbs + 1000 * np.array([int(r["ts"][0]) for r in recs]))
    n_on = sum(int(((r["d"] >> 1) & 1).sum()) for r in recs)
    assert int((ev["p"] > 0).sum()) == n_on and 0 < n_on < ev.size


@pytest.mark.parametrize("encoding", ["evt3", "libcaer", "libcaer_cmp", "mono"])
def test_real_bags_reencode_to_the_same_times(tmp_path, encoding):
    from evdnerf_ros.io.bag_reader import iter_event_packets, read_events
    from evdnerf_ros.io.reencode import reencode_bag

    for name in ("event_camera_py/test_events_2", "event_camera_codecs/test_data_libcaer_rollover"):
        src = _need(REAL / name)
        out = tmp_path / f"{src.name}_{encoding}"
        reencode_bag(src, out, encoding=encoding)
        assert np.array_equal(read_events(out, BAG_TOPIC).events, read_events(src, BAG_TOPIC).events)
        a, b = list(iter_event_packets(src, BAG_TOPIC)), list(iter_event_packets(out, BAG_TOPIC))
        assert [(p.stamp_ns, p.seq, p.frame_id) for p in a] == [(p.stamp_ns, p.seq, p.frame_id) for p in b]
