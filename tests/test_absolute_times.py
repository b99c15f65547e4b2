"""Absolute (epoch) event times through every container, and the RAW `% t0` header line.

EVT 2.0 / 3.0 count sensor-clock microseconds: a RAW file written from epoch times keeps its
sensor times near zero and puts the origin in a `% t0 <us>` header line (io/raw.py; microseconds,
as faery writes and reads it, with a `% t0_unit us` line), so its
size follows the events, not the date. Every container gives the int64 ns times back exactly
(EVT: times are whole microseconds, the formats' resolution).
"""

import os

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from evdnerf_ros.cli import main
from evdnerf_ros.errors import FormatError, InputError
from evdnerf_ros.events.codecs import decode
from evdnerf_ros.events.codecs._common import ORIGIN_STEP_US, SENSOR_PERIOD_US, sensor_origin_ns
from evdnerf_ros.events.types import make_events, make_triggers
from evdnerf_ros.io.event_files import EventFile, read_event_file, write_event_file
from evdnerf_ros.io.raw import iter_raw, read_raw, read_raw_header, write_raw
from synthetic_events import synthetic_events, synthetic_triggers

EPOCH_US = 1_700_000_000_123_457            # 2023-11-14, not on a 4096 us boundary
EPOCH_NS = EPOCH_US * 1000
STEP_NS = ORIGIN_STEP_US * 1000


def epoch_stream(n=6_000, duration_us=600_000, seed=0, t0_us=EPOCH_US, max_id=16, n_trig=40):
    ev = synthetic_events(n, duration_us=duration_us, seed=seed, t0_us=t0_us)
    tr = synthetic_triggers(n_trig, duration_us=duration_us, seed=seed + 1, t0_us=t0_us, max_id=max_id)
    return ev, tr


def body(path):
    h = read_raw_header(path)
    return path.read_bytes()[h.header_bytes:], h


# ---- RAW: the sensor time starts near zero, the origin goes in the header -----------------------

@pytest.mark.parametrize("enc", ["evt3", "evt2"])
def test_raw_epoch_round_trip_is_exact_and_small(tmp_path, enc):
    ev, tr = epoch_stream(max_id=16 if enc == "evt3" else 32)
    p = tmp_path / f"epoch_{enc}.raw"
    write_raw(p, ev, width=1280, height=720, encoding=enc, triggers=tr)
    d, h = read_raw(p)
    assert np.array_equal(d.events, ev) and np.array_equal(d.triggers, tr)
    # the origin: the first time rounded down to a TIME_HIGH boundary, in the header
    first = min(int(ev["t"][0]), int(tr["t"][0]))
    assert h.t0_ns == first // STEP_NS * STEP_NS and h.t0_ns % STEP_NS == 0
    assert f"% t0 {h.t0_ns // 1000}\n% t0_unit us\n" in p.read_bytes()[:h.header_bytes].decode()
    assert h.t0_unit == "us"
    # the words hold sensor times below 4096 us at the start, without the origin
    data, _ = body(p)
    sensor = decode(data, enc)
    assert int(sensor.events["t"][0]) == int(ev["t"][0]) - h.t0_ns < STEP_NS
    # the size follows the events: the same events at sensor time 0 take as many bytes
    q = tmp_path / f"zero_{enc}.raw"
    write_raw(q, make_events(ev["t"] - h.t0_ns, ev["x"], ev["y"], ev["p"]), width=1280, height=720,
              encoding=enc, triggers=make_triggers(tr["t"] - h.t0_ns, tr["id"], tr["value"]))
    assert len(body(q)[0]) == len(data)
    assert os.path.getsize(p) < 8 * 1024 * (len(ev) + len(tr)) // 1000 + 1024   # < 8 KB per 1000


@pytest.mark.parametrize("enc", ["evt3", "evt2"])
def test_raw_epoch_streams_and_long_gaps(tmp_path, enc):
    """Events 40 s apart at an epoch time (wraps of the 24-bit clock inside the file), read
    whole and chunk by chunk."""
    ev = make_events(np.array([0, 1, 40_000_000, 40_000_000, 95_000_123]) * 1000 + EPOCH_NS,
                     [1, 2, 3, 4, 5], [0, 0, 1, 1, 2], [1, -1, 1, 1, -1])
    p = tmp_path / "gaps.raw"
    write_raw(p, ev, width=8, height=8, encoding=enc)
    assert np.array_equal(read_raw(p)[0].events, ev)
    for chunk in (8, 24, 1 << 16):
        got = np.concatenate([x.events for x in iter_raw(p, chunk_bytes=chunk)])
        assert np.array_equal(got, ev)
    assert os.path.getsize(p) < 1024


def test_raw_times_in_the_first_sensor_period_are_written_as_they_are(tmp_path):
    """Sensor times (what a camera writes: e.g. 11.7 s) keep origin 0 and no `% t0` line, so a
    RAW file converted again has the same words."""
    ev = synthetic_events(2_000, duration_us=1_000_000, seed=4, t0_us=11_718_656)
    p = tmp_path / "sensor.raw"
    write_raw(p, ev, width=1280, height=720)
    data, h = body(p)
    assert h.t0_ns == 0 and "% t0" not in p.read_bytes()[:h.header_bytes].decode()
    assert np.array_equal(decode(data, "evt3").events, ev)
    assert sensor_origin_ns(SENSOR_PERIOD_US * 1000 - 1000) == 0
    assert sensor_origin_ns(SENSOR_PERIOD_US * 1000) == SENSOR_PERIOD_US * 1000


def test_raw_negative_times_round_trip(tmp_path):
    ev = make_events(np.array([-5_000_123, -5_000_000, -1, 0, 7]) * 1000, [0, 1, 2, 3, 4], [0] * 5, [1] * 5)
    p = tmp_path / "neg.raw"
    write_raw(p, ev, width=8, height=8, encoding="evt2")
    d, h = read_raw(p)
    assert np.array_equal(d.events, ev)
    assert h.t0_ns == (-5_000_123_000) // STEP_NS * STEP_NS < 0


def test_raw_without_events_is_still_valid(tmp_path):
    p = tmp_path / "empty.raw"
    write_raw(p, make_events([], [], [], []), width=4, height=4)
    d, h = read_raw(p)
    assert d.events.size == 0 and h.t0_ns == 0 and len(body(p)[0]) == 0
    # triggers alone at an epoch time: their time sets the origin
    tr = make_triggers([EPOCH_NS, EPOCH_NS + 5_000], [1, 2], [1, 0])
    q = tmp_path / "triggers_only.raw"
    write_raw(q, make_events([], [], [], []), width=4, height=4, triggers=tr)
    d, h = read_raw(q)
    assert d.events.size == 0 and np.array_equal(d.triggers, tr)
    assert h.t0_ns == EPOCH_NS // STEP_NS * STEP_NS and len(body(q)[0]) < 16


def test_raw_explicit_origin(tmp_path):
    ev = make_events(np.array([0, 3]) * 1000 + EPOCH_NS, [1, 2], [1, 1], [1, 1])
    p = tmp_path / "t0.raw"
    write_raw(p, ev, width=4, height=4, t0_ns=EPOCH_NS - 7_000)
    d, h = read_raw(p)
    assert h.t0_ns == EPOCH_NS - 7_000 and np.array_equal(d.events, ev)
    assert list(decode(body(p)[0], "evt3").events["t"]) == [7_000, 10_000]
    with pytest.raises(InputError, match="after the first event"):
        write_raw(tmp_path / "late.raw", ev, width=4, height=4, t0_ns=EPOCH_NS + 1000)
    with pytest.raises(InputError, match="t0_ns must be an integer"):
        write_raw(tmp_path / "float.raw", ev, width=4, height=4, t0_ns=1.5)
    # an origin off the microsecond grid puts whole-microsecond times off it: refused
    with pytest.raises(InputError, match="whole microsecond"):
        write_raw(tmp_path / "grid.raw", ev, width=4, height=4, t0_ns=EPOCH_NS - 1)
    assert sorted(x.name for x in tmp_path.iterdir()) == ["t0.raw"]


def test_raw_refuses_times_off_the_microsecond_grid(tmp_path):
    ev = make_events([EPOCH_NS, EPOCH_NS + 1500], [1, 2], [1, 1], [1, 1])
    with pytest.raises(InputError, match="whole microsecond.*quantize_to_us"):
        write_raw(tmp_path / "x.raw", ev, width=4, height=4)
    assert list(tmp_path.iterdir()) == []


# ---- reading `% t0` ------------------------------------------------------------------------------

EVT3_BODY = np.array([0x8001, 0x6002, 0x0003, 0x2804, 0xA101], "<u2").tobytes()   # event + trigger at 4098 us
EVT2_BODY = np.array([0x80000040, 0x10802003, 0xA0800101], "<u4").tobytes()       # the same in EVT 2.0


#: `% t0` in microseconds (faery's, and any file that does not say otherwise), in the unit a
#: `% t0_unit` line names, and in nanoseconds in files this toolkit wrote before it wrote that line.
T0_HEADERS = [("", 1000, "us"), ("% t0_unit us\n", 1000, "us"), ("% t0_unit ns\n", 1, "ns"),
              ("% camera_integrator_name evdnerf_ros\n", 1, "ns"),
              ("% camera_integrator_name evdnerf_ros\n% t0_unit us\n", 1000, "us"),
              ("% camera_integrator_name Prophesee\n", 1000, "us")]


@pytest.mark.parametrize("head, data", [(b"% evt 3.0\n", EVT3_BODY), (b"% format EVT2;width=8;height=8\n", EVT2_BODY)])
@pytest.mark.parametrize("t0_value", [0, 1_700_000_000_000_000, -123_456_789, 7])
@pytest.mark.parametrize("lines, ns_per, unit", T0_HEADERS)
def test_t0_header_line_is_honoured(tmp_path, head, data, t0_value, lines, ns_per, unit):
    p = tmp_path / "t0.raw"
    p.write_bytes(head + f"% geometry 8x8\n{lines}% t0 {t0_value}\n% end\n".encode() + data)
    h = read_raw_header(p)
    t0 = t0_value * ns_per
    assert h.t0_ns == t0 and h.fields["t0"] == str(t0_value) and h.t0_unit == unit
    d, _ = read_raw(p)
    assert d.events.tolist() == [(t0 + 4098_000, 4, 3, 1)]
    assert d.triggers.tolist() == [(t0 + 4098_000, 1, 1)]
    assert [e.tolist() for x in iter_raw(p, chunk_bytes=8) for e in x.events] == [(t0 + 4098_000, 4, 3, 1)]
    f = read_event_file(p)
    assert f.events.tolist() == d.events.tolist()


@pytest.mark.parametrize("value, match", [("soon", "not an integer"), ("1.5e18", "not an integer"),
                                          (str(1 << 62), "out of range"), ("", "not an integer")])
def test_bad_t0_header_line_is_refused_naming_the_file(tmp_path, value, match):
    p = tmp_path / "bad_t0.raw"
    p.write_bytes(f"% evt 3.0\n% t0 {value}\n% end\n".encode() + EVT3_BODY)
    with pytest.raises(FormatError, match=match) as ei:
        read_raw_header(p)
    assert str(p) in str(ei.value) and "% t0" in str(ei.value)


def test_an_unknown_t0_unit_is_refused(tmp_path):
    p = tmp_path / "unit.raw"
    p.write_bytes(b"% evt 3.0\n% t0 5\n% t0_unit ms\n% end\n" + EVT3_BODY)
    with pytest.raises(FormatError, match=r"'% t0_unit ms' is not us or ns") as ei:
        read_raw_header(p)
    assert str(p) in str(ei.value)



def _faery():
    return pytest.importorskip("faery", reason="faery (aestream's I/O library, a test dependency) is not installed")


@pytest.mark.parametrize("version", ["evt3", "evt2"])
def test_faery_and_this_toolkit_agree_on_t0(tmp_path, version):
    """faery writes `% t0 <first event's us>` and reads it back; so do we, both ways."""
    faery = _faery()
    us = np.array([1605537493720000, 1605537493720100, 1605537493721000, 1605537493990017], np.uint64)
    ev = np.zeros(us.size, faery.EVENTS_DTYPE)
    ev["t"], ev["x"], ev["y"], ev["on"] = us, [1, 2, 3, 4], [5, 6, 7, 0], [True, False, True, False]
    theirs = tmp_path / f"faery_{version}.raw"
    faery.events_stream_from_array(ev, dimensions=(16, 16)).to_file(str(theirs), version=version)
    h = read_raw_header(theirs)
    assert (h.t0_ns, h.t0_unit) == (int(us[0]) * 1000, "us")
    d, _ = read_raw(theirs)
    assert d.events["t"].tolist() == [int(v) * 1000 for v in us]       # 1605537493.72 s, not 1605537.49
    assert d.events["x"].tolist() == [1, 2, 3, 4] and d.events["p"].tolist() == [1, -1, 1, -1]
    ours = tmp_path / f"ours_{version}.raw"
    write_raw(ours, d.events, width=16, height=16, encoding=version)
    assert read_raw_header(ours).t0_unit == "us"
    back = np.concatenate([np.asarray(p["t"]) for p in faery.events_stream_from_file(str(ours))])
    assert back.tolist() == us.tolist()


def test_a_file_written_before_the_t0_unit_line_reads_in_nanoseconds(tmp_path):
    """What this toolkit wrote before it wrote `% t0_unit`: its integrator name and `% t0 <ns>`."""
    p = tmp_path / "old.raw"
    p.write_bytes(b"% camera_integrator_name evdnerf_ros\n% evt 3.0\n% format EVT3;height=8;width=8\n"
                  b"% geometry 8x8\n% t0 913715200000\n% end\n" + EVT3_BODY)
    d, h = read_raw(p)
    assert (h.t0_ns, h.t0_unit) == (913715200000, "ns")
    assert d.events["t"].tolist() == [913715200000 + 4098_000]


@settings(max_examples=20, deadline=None, suppress_health_check=[HealthCheck.too_slow,
                                                                   HealthCheck.function_scoped_fixture])
@given(st.data())
def test_raw_round_trip_random_absolute_times(tmp_path_factory, data):
    """Any whole-microsecond start (negative, epoch, far future) and spread: exact times back,
    the sensor times start in the clock's first period, and the body is what the same events
    take at those sensor times: bounded by the events and their span, not by the date."""
    enc = data.draw(st.sampled_from(["evt3", "evt2"]))
    start_us = data.draw(st.integers(-(1 << 50), 1 << 51))
    n = data.draw(st.integers(1, 300))
    span = data.draw(st.sampled_from([1, 4096, 3_000_000, 70_000_000]))
    rng = np.random.default_rng(data.draw(st.integers(0, 2 ** 31)))
    t = (start_us + np.sort(rng.integers(0, span, n))) * 1000
    ev = make_events(t, rng.integers(0, 640, n), rng.integers(0, 480, n), rng.choice([-1, 1], n))
    d = tmp_path_factory.mktemp("abs")
    write_raw(d / "a.raw", ev, width=640, height=480, encoding=enc)
    got, h = read_raw(d / "a.raw")
    assert np.array_equal(got.events, ev)
    assert h.t0_ns <= int(t[0]) and (h.t0_ns == 0 or int(t[0]) - h.t0_ns < STEP_NS)
    assert int(t[0]) - h.t0_ns < SENSOR_PERIOD_US * 1000
    write_raw(d / "b.raw", make_events(t - h.t0_ns, ev["x"], ev["y"], ev["p"]),
              width=640, height=480, encoding=enc)
    assert read_raw_header(d / "b.raw").t0_ns == 0
    size = len(body(d / "a.raw")[0])
    assert size == len(body(d / "b.raw")[0])
    assert size <= 8 * n + 64 + span // (1 << 21)


# ---- every container ------------------------------------------------------------------------------

CONTAINERS = [("a.raw", "evt3"), ("b.raw", "evt2"), ("c.npz", None), ("d.h5", None),
              ("e.mcap", "evt3"), ("f.mcap", "mono"), ("g.mcap", "array"), ("h.db3", "evt3"),
              ("i.bag", "array")]


@pytest.mark.parametrize("name, enc", CONTAINERS)
def test_every_container_round_trips_epoch_times(tmp_path, name, enc):
    ev, tr = epoch_stream(n=3_000, duration_us=600_000, seed=7, max_id=16)
    keeps_triggers = name.endswith((".raw", ".npz", ".h5")) or enc == "evt3"
    data = EventFile(ev, tr if keeps_triggers else make_triggers([], [], []), 1280, 720, "npz")
    path = tmp_path / name
    write_event_file(path, data, encoding=enc)
    back = read_event_file(path)
    assert np.array_equal(back.events, ev)
    if keeps_triggers:
        assert np.array_equal(back.triggers, data.triggers)
    assert (back.width, back.height) == (1280, 720)
    size = sum(f.stat().st_size for f in path.rglob("*")) if path.is_dir() else path.stat().st_size
    assert size < 40 * len(ev) + 256 * 1024               # never hundreds of MB


def test_cli_converts_epoch_events_to_raw_and_back(tmp_path, capsys):
    ev, tr = epoch_stream(n=10_000, duration_us=600_000, seed=9)
    write_event_file(tmp_path / "in.npz", EventFile(ev, tr, 1280, 720, "npz"))
    for enc in ("evt3", "evt2"):
        out = tmp_path / f"out_{enc}.raw"
        assert main(["convert-events", str(tmp_path / "in.npz"), str(out), "--encoding", enc]) == 0
        assert out.stat().st_size < 80 * 1024                 # 10,000 events: 810 MB before
        assert main(["convert-events", str(out), str(tmp_path / f"back_{enc}.npz")]) == 0
        back = read_event_file(tmp_path / f"back_{enc}.npz")
        assert np.array_equal(back.events, ev) and np.array_equal(back.triggers, tr)
        png = tmp_path / f"r_{enc}.png"
        assert main(["render-events", str(out), "--start", "0", "--window", "10ms", "-o", str(png)]) == 0
        assert png.is_file()
    capsys.readouterr()
    bad = tmp_path / "bad.raw"
    bad.write_bytes(b"% evt 3.0\n% geometry 8x8\n% t0 yesterday\n% end\n" + EVT3_BODY)
    assert main(["convert-events", str(bad), str(tmp_path / "bad.npz")]) == 2
    err = capsys.readouterr().err
    assert "bad.raw" in err and "% t0" in err and "Traceback" not in err
