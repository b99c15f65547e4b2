"""expelliarmus (an independent C implementation) as a peer for EVT 2.0 / EVT 3.0 RAW files.

Its array: t <i8 microseconds, x <i2, y <i2, p u1 (1 = ON). Its files have a `% evt x.0 `
header (trailing space) and no `% end` line.

Finding about its EVT 3.0 support (expelliarmus 1.1.12), established with our decoder:
* its WRITER is wrong: after the first word it never emits TIME_HIGH (it derives the TIME_HIGH
  field from bits 32+ of the time instead of bits 23-12), so its files only carry the low 12
  bits of time. A spec-conforming decoder must reject them (TIME_LOW goes backwards); when
  consecutive events are < 4096 us apart the lost carries can be inferred, which is what
  `time_low_carry=True` does; with larger gaps the information is simply not in the file.
* its READER compensates by treating every TIME_LOW decrease as a TIME_HIGH increment, which
  it counts on top of the TIME_HIGH words of a conforming stream: it reads conforming files
  (ours) 4096 us late for every 4096 us boundary crossed so far.
Its EVT 2.0 writer and reader are correct.
"""

import numpy as np
import pytest

from evdnerf_ros.errors import FormatError
from evdnerf_ros.io.raw import read_raw, read_raw_header, write_raw
from synthetic_events import synthetic_events

expelliarmus = pytest.importorskip("expelliarmus")
Wizard = expelliarmus.Wizard

PEER_DTYPE = np.dtype([("t", "<i8"), ("x", "<i2"), ("y", "<i2"), ("p", "u1")])


def to_peer(ev):
    a = np.empty(ev.size, PEER_DTYPE)
    a["t"] = ev["t"] // 1000
    a["x"], a["y"] = ev["x"], ev["y"]
    a["p"] = ev["p"] > 0
    return a


def peer_write(path, ev, enc):
    Wizard(encoding=enc).save(str(path), to_peer(ev))


def peer_read(path, enc):
    w = Wizard(encoding=enc)
    w.set_file(str(path))
    return w.read()


DENSE = dict(n=20_000, duration_us=20_000, seed=1)          # consecutive gaps << 4096 us
SPARSE = dict(n=2_000, duration_us=60_000_000, seed=2, burst_fraction=0.0)


def make(kind):
    k = dict(DENSE if kind == "dense" else SPARSE)
    return synthetic_events(k.pop("n"), **k)


@pytest.mark.parametrize("kind", ["dense", "sparse"])
def test_peer_evt2_writer_to_our_reader(tmp_path, kind):
    ev = make(kind)
    p = tmp_path / "peer.raw"
    peer_write(p, ev, "evt2")
    d, h = read_raw(p)
    # no geometry line: the size comes from plugin_name (hal_plugin_gen3_fx3), as OpenEB infers it
    assert h.encoding == "evt2" and (h.width, h.height) == (640, 480)
    assert np.array_equal(d.events, ev)


@pytest.mark.parametrize("kind", ["dense", "sparse"])
def test_our_evt2_writer_to_peer_reader(tmp_path, kind):
    ev = make(kind)
    p = tmp_path / "ours.raw"
    write_raw(p, ev, width=1280, height=720, encoding="evt2")
    assert np.array_equal(peer_read(p, "evt2"), to_peer(ev))


def test_peer_evt3_writer_dense_reads_exactly_with_time_low_carry(tmp_path):
    ev = make("dense")
    p = tmp_path / "peer.raw"
    peer_write(p, ev, "evt3")
    assert read_raw_header(p).encoding == "evt3"
    d, _ = read_raw(p, time_low_carry=True)
    assert np.array_equal(d.events, ev)
    # the peer agrees with itself on such files
    assert np.array_equal(peer_read(p, "evt3"), to_peer(ev))


def test_peer_evt3_writer_omits_time_high_words(tmp_path):
    ev = make("dense")
    p = tmp_path / "peer.raw"
    peer_write(p, ev, "evt3")
    h = read_raw_header(p)
    words = np.frombuffer(p.read_bytes()[h.header_bytes:], "<u2")
    assert ev["t"][-1] // 1000 > 4 * 4096                 # spans several TIME_HIGH periods
    assert np.count_nonzero(words >> 12 == 0x8) == 1      # ... yet only one TIME_HIGH word
    # a conforming decoder sees TIME_LOW going backwards and says how to read it anyway
    with pytest.raises(FormatError, match="time_low_carry") as ei:
        read_raw(p)
    assert ei.value.offset > h.header_bytes


def test_peer_evt3_writer_loses_time_across_gaps_over_4096us(tmp_path):
    ev = make("sparse")
    p = tmp_path / "peer.raw"
    peer_write(p, ev, "evt3")
    d, _ = read_raw(p, time_low_carry=True)
    theirs = peer_read(p, "evt3")
    # the file no longer holds the true times: both readers recover the same wrong ones
    assert np.array_equal(d.events["t"] // 1000, theirs["t"])
    err = ev["t"] // 1000 - theirs["t"]
    assert np.any(err != 0) and np.all(err % 4096 == 0)
    for k in "xy":
        assert np.array_equal(d.events[k], ev[k])


def test_our_evt3_writer_to_peer_reader_double_counts_time_high(tmp_path):
    ev = make("dense")
    p = tmp_path / "ours.raw"
    write_raw(p, ev, width=1280, height=720, encoding="evt3")
    theirs = peer_read(p, "evt3")
    assert theirs.size == ev.size
    for k in "xyp":
        assert np.array_equal(theirs[k], to_peer(ev)[k])
    # model of the peer reader: +4096 us for every TIME_LOW lower than the previous TIME_LOW
    h = read_raw_header(p)
    w = np.frombuffer(p.read_bytes()[h.header_bytes:], "<u2")
    ty = w >> 12
    tl = (w[ty == 6] & 0xFFF).astype(np.int64)
    drops = np.zeros(w.size, np.int64)
    drops[ty == 6] = np.concatenate([[0], tl[1:] < tl[:-1]])
    n_ev = (ty == 2) + (ty == 4) * np.bitwise_count(w & 0xFFF) + (ty == 5) * np.bitwise_count(w & 0xFF)
    predicted = ev["t"] // 1000 + 4096 * np.repeat(np.cumsum(drops), n_ev)
    assert np.array_equal(theirs["t"], predicted)
    assert not np.array_equal(theirs["t"], ev["t"] // 1000)
    # and we read our own file exactly
    assert np.array_equal(read_raw(p)[0].events, ev)
