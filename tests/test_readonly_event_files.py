"""Event files read but never written: text `t x y p` (the RPG Event Camera Dataset's events.txt;
io/text.py: times parsed exactly, the unit never guessed) and N-MNIST-style ATIS .bin
(io/atis_bin.py); the real events_viz chunk and N-MNIST sample read to their reference values."""

import os
from pathlib import Path

import numpy as np
import pytest

from evdnerf_ros.cli import main
from evdnerf_ros.errors import FormatError, InputError
from evdnerf_ros.io.event_files import read_event_file, write_event_file

REAL = Path(os.environ.get("EVDNERF_REAL_DATA", Path(__file__).resolve().parents[1].parent / "shared" / "data" / "real"))
CHUNK = REAL / "events_viz" / "events_chunk.txt"


def _text(tmp_path, body: str, name="e.txt"):
    p = tmp_path / name
    p.write_text(body)
    return p


@pytest.mark.skipif(not CHUNK.is_file(), reason=f"real recordings not found at {REAL}")
def test_the_rpg_chunk_reads_to_its_reference_values():
    d = read_event_file(CHUNK, geometry=(240, 180))
    ev = d.events
    assert ev.size == 50_000 and int((ev["p"] > 0).sum()) == 21_147
    assert (int(ev["t"][0]), int(ev["t"][-1])) == (3_811_000, 174_156_000)
    assert int((ev["t"] % 1000 != 0).sum()) == 25_376          # nanosecond digits kept exactly
    assert int(ev["x"].max()) < 240 and int(ev["y"].max()) < 180


def test_seconds_with_nanosecond_digits_are_exact(tmp_path):
    p = _text(tmp_path, "# t x y p\n0.003820001 1 2 0\n1.5 3 4 1\n1605537493.123456789 0 0 1\n")
    d = read_event_file(p, geometry=(8, 8))
    assert d.events["t"].tolist() == [3_820_001, 1_500_000_000, 1_605_537_493_123_456_789]
    assert d.events["p"].tolist() == [-1, 1, 1] and d.width == 8


def test_whole_number_times_need_a_unit(tmp_path):
    p = _text(tmp_path, "1000 1 2 1\n1250 3 4 -1\n")
    with pytest.raises(InputError, match=r"e\.txt: the times are whole numbers.*--time-unit"):
        read_event_file(p, geometry=(8, 8))
    assert read_event_file(p, geometry=(8, 8), time_unit="us").events["t"].tolist() == [1_000_000, 1_250_000]
    assert read_event_file(p, geometry=(8, 8), time_unit="ns").events["t"].tolist() == [1000, 1250]


@pytest.mark.parametrize("body, error, match", [
    ("0.0000000001 1 2 1\n", FormatError, "finer than a nanosecond"),
    ("0.1 1 2 0\n0.2 1 2 -1\n", FormatError, "mixes 0 and -1"),
    ("0.1 1 2 7\n", FormatError, "polarity must be 0/1 or -1/\\+1"),
    ("0.1 1 2\n", FormatError, "not a text event file"),
    ("-0.1 1 2 1\n", FormatError, "negative times"),
    ("0.2 1 2 1\n0.1 1 2 1\n", InputError, "timestamps not sorted"),
    ("0.1 9 2 1\n", InputError, "x=9 outside the declared 8x8 geometry"),
])
def test_bad_text_is_one_clear_error(tmp_path, body, error, match):
    with pytest.raises((FormatError, InputError), match=match) as ei:
        read_event_file(_text(tmp_path, body), geometry=(8, 8))
    assert "e.txt" in str(ei.value)


def test_the_cli_reads_text_and_never_writes_it(tmp_path, capsys):
    p = _text(tmp_path, "0.001 1 2 1\n0.002 3 4 0\n")
    assert main(["convert-events", str(p), str(tmp_path / "o.npz")]) == 2
    assert "--geometry" in capsys.readouterr().err
    assert main(["convert-events", str(p), str(tmp_path / "o.npz"), "--geometry", "8x8"]) == 0
    capsys.readouterr()
    assert read_event_file(tmp_path / "o.npz").events["t"].tolist() == [1_000_000, 2_000_000]
    assert main(["info", str(p)]) == 0
    out = capsys.readouterr().out
    assert "count       2" in out and "resolution  unknown" in out
    with pytest.raises(InputError, match="text event files are read only"):
        write_event_file(tmp_path / "back.txt", read_event_file(tmp_path / "o.npz"))


NMNIST = REAL / "tonic" / "sample_nmnist.bin"


@pytest.mark.skipif(not NMNIST.is_file(), reason=f"real recordings not found at {REAL}")
def test_the_nmnist_sample_reads_to_its_reference_values(tmp_path):
    d = read_event_file(NMNIST, geometry=(34, 34))
    ev = d.events
    assert ev.size == 4325 and int((ev["p"] > 0).sum()) == 2145
    assert (int(ev["t"][0]), int(ev["t"][-1])) == (654_000, 311_175_000)
    assert int(ev["x"].max()) < 34 and int(ev["y"].max()) < 34


def test_atis_bin_overflow_records_and_damage(tmp_path):
    """A y = 240 record adds 2**13 us to every later time; a size that is not whole records is refused."""
    def rec(x, y, p, t):
        w = (p << 23) | t
        return bytes([x, y, w >> 16 & 0xFF, w >> 8 & 0xFF, w & 0xFF])

    p = tmp_path / "s.bin"
    p.write_bytes(rec(1, 2, 1, 100) + rec(0, 240, 0, 0) + rec(3, 4, 0, 50))
    d = read_event_file(p, geometry=(34, 34))
    assert d.events["t"].tolist() == [100_000, (8192 + 50) * 1000] and d.events["p"].tolist() == [1, -1]
    p.write_bytes(rec(1, 2, 1, 100) + b"\x00\x01")
    with pytest.raises(FormatError, match=r"s\.bin: 7 bytes is not a whole number of 5-byte events"):
        read_event_file(p, geometry=(34, 34))
    with pytest.raises(InputError, match="N-MNIST-style .bin files are read only"):
        write_event_file(tmp_path / "o.bin", read_event_file(_text(tmp_path, "0.1 1 1 1\n"), geometry=(8, 8)))


AEDAT4 = REAL / "tonic" / "sample.aedat4"


@pytest.mark.skipif(not AEDAT4.is_file(), reason=f"real recordings not found at {REAL}")
def test_the_dvxplorer_aedat4_reads_to_its_reference_values(tmp_path):
    """Three independent readers agree on this file (the `aedat` package, faery, dv-processing)."""
    from evdnerf_ros.io.aedat4 import read_aedat4

    d = read_event_file(AEDAT4)
    ev = d.events
    assert (d.width, d.height, ev.size, int((ev["p"] > 0).sum())) == (320, 240, 111_954, 55_023)
    assert (int(ev["t"][0]), int(ev["t"][-1])) == (1_605_537_493_718_345_000, 1_605_537_494_308_262_000)
    *_, contents = read_aedat4(AEDAT4)
    assert contents.imu_samples == 475 and set(contents.streams.values()) >= {"events", "imus"}
    faery = pytest.importorskip("faery", reason="faery (a test dependency) is not installed")
    theirs = np.concatenate([np.asarray(p) for p in faery.events_stream_from_file(str(AEDAT4))])
    assert np.array_equal(theirs["t"].astype(np.int64) * 1000, ev["t"])
    assert np.array_equal(theirs["x"], ev["x"]) and np.array_equal(np.where(theirs["on"], 1, -1), ev["p"])
    cut = tmp_path / "cut.aedat4"
    cut.write_bytes(AEDAT4.read_bytes()[: AEDAT4.stat().st_size // 2])
    with pytest.raises((FormatError, InputError)) as ei:
        read_event_file(cut)
    assert "cut.aedat4" in str(ei.value)
    junk = tmp_path / "junk.aedat4"
    junk.write_bytes(b"not an aedat file at all")
    with pytest.raises(FormatError, match="not a readable AEDAT 4.0 file"):
        read_event_file(junk)


DAT = REAL / "expelliarmus" / "dat_sample.dat"


@pytest.mark.skipif(not DAT.is_file(), reason=f"real recordings not found at {REAL}")
def test_the_ncars_dat_reads_as_expelliarmus_reads_it(tmp_path):
    from evdnerf_ros.events.codecs._common import TruncatedStreamWarning

    d = read_event_file(DAT, geometry=(120, 100))
    ev = d.events
    assert (ev.size, int((ev["p"] > 0).sum()), int(ev["t"][0]), int(ev["t"][-1])) == (4407, 1671, 0, 99_937_000)
    theirs = np.load(DAT.with_suffix(".npy"))
    assert np.array_equal(theirs["t"] * 1000, ev["t"]) and np.array_equal(theirs["x"], ev["x"])
    assert np.array_equal(theirs["y"], ev["y"]) and np.array_equal(np.where(theirs["p"] > 0, 1, -1), ev["p"])
    cut = tmp_path / "cut.dat"
    cut.write_bytes(DAT.read_bytes()[:-3])
    with pytest.warns(TruncatedStreamWarning, match=r"cut\.dat: ends inside an 8-byte DAT event at byte"):
        assert read_event_file(cut, geometry=(120, 100)).events.size == 4406
    with pytest.raises(FormatError, match="dangling"):
        read_event_file(cut, geometry=(120, 100), strict=True)


def test_dat_header_geometry_wraps_and_bad_types(tmp_path):
    def dat(records, head=b"% Version 2\n% Width 640\n% Height 480\n", kind=0x0C, size=8):
        body = b"".join(np.array([t, x | y << 14 | p << 28], "<u4").tobytes() for t, x, y, p in records)
        p = tmp_path / "e.dat"
        p.write_bytes(head + bytes([kind, size]) + body)
        return p

    p = dat([(4_294_967_000, 1, 2, 1), (100, 639, 479, 0)])       # the 32-bit us clock wraps
    d = read_event_file(p)
    assert (d.width, d.height) == (640, 480)
    assert d.events["t"].tolist() == [4_294_967_000_000, (2**32 + 100) * 1000] and d.events["p"].tolist() == [1, -1]
    with pytest.raises(FormatError, match="event type 0x01 of 8 bytes is not a DAT CD event"):
        read_event_file(dat([(0, 1, 2, 1)], kind=0x01))
    with pytest.raises(InputError, match="Prophesee DAT file gives no sensor size"):
        read_event_file(dat([(0, 1, 2, 1)], head=b"% Version 2\n"))
