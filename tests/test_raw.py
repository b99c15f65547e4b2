"""OpenEB RAW files: header parsing, read / iterate / write, atomic writes, error offsets."""

import os

import numpy as np
import pytest

from evdnerf_ros.errors import FormatError, InputError, OutputExistsError
from evdnerf_ros.events.codecs import encode
from evdnerf_ros.events.types import make_events
from evdnerf_ros.io import raw as raw_mod
from evdnerf_ros.io.raw import iter_raw, read_raw, read_raw_header, write_raw
from synthetic_events import synthetic_events, synthetic_triggers


def put(tmp_path, name, data: bytes):
    p = tmp_path / name
    p.write_bytes(data)
    return p


EVT3_BODY = np.array([0x8001, 0x6002, 0x0003, 0x2804], "<u2").tobytes()   # 1 event (4098us, 4, 3, +1)


def test_write_then_read_evt3_and_evt2(tmp_path):
    ev = synthetic_events(20_000, duration_us=30_000_000, seed=1)
    for enc, max_id in (("evt3", 16), ("evt2", 32)):
        tr = synthetic_triggers(100, duration_us=30_000_000, max_id=max_id)
        p = tmp_path / f"a_{enc}.raw"
        write_raw(p, ev, width=1280, height=720, encoding=enc, triggers=tr)
        d, h = read_raw(p)
        assert h.encoding == enc and (h.width, h.height) == (1280, 720)
        assert h.fields["camera_integrator_name"] == "evdnerf_ros"
        assert h.fields["format"] == f"{enc.upper()};height=720;width=1280"
        text = p.read_bytes()[:h.header_bytes].decode()
        assert text.endswith("% end\n") and "% geometry 1280x720" in text
        assert np.array_equal(d.events, ev)
        assert np.array_equal(d.triggers, tr)


def test_write_raw_in_several_encoder_chunks(tmp_path, monkeypatch):
    monkeypatch.setattr(raw_mod, "_WRITE_CHUNK_EVENTS", 777)
    ev = synthetic_events(5_000, duration_us=40_000_000, seed=2)
    tr = synthetic_triggers(60, duration_us=41_000_000)
    tr["t"][5] = ev["t"][777 - 1]                   # tie with a chunk's last event
    tr.sort(order="t", kind="stable")
    p = tmp_path / "chunks.raw"
    write_raw(p, ev, width=1280, height=720, triggers=tr)
    d, _ = read_raw(p)
    assert np.array_equal(d.events, ev) and np.array_equal(d.triggers, tr)


def test_iter_raw_and_small_chunks_match_read_raw(tmp_path):
    ev = synthetic_events(30_000, duration_us=20_000_000, seed=3)
    p = tmp_path / "b.raw"
    write_raw(p, ev, width=1280, height=720)
    ref, _ = read_raw(p)
    for chunk in (8, 1000, 65536):
        parts = list(iter_raw(p, chunk_bytes=chunk))
        assert np.array_equal(np.concatenate([x.events for x in parts]), ref.events)
        d, _ = read_raw(p, chunk_bytes=chunk)
        assert np.array_equal(d.events, ref.events)


def test_header_variants(tmp_path):
    cases = [
        (b"% format EVT3;height=720;width=1280\n% end\n", ("evt3", 1280, 720)),
        (b"% evt 3.0 \n", ("evt3", None, None)),
        (b"% evt 2.0\r\n% geometry 640x480\r\n% end\r\n", ("evt2", 640, 480)),
        (b"% format EVT2\n% geometry 304x240\n", ("evt2", 304, 240)),
        (b"%\n% Date 2024-01-01 10:00:00\n% format evt3;width=10;height=20\n% end\n",
         ("evt3", 10, 20)),
    ]
    for i, (head, exp) in enumerate(cases):
        p = put(tmp_path, f"h{i}.raw", head + EVT3_BODY)
        h = read_raw_header(p)
        assert (h.encoding, h.width, h.height) == exp, head
        assert h.header_bytes == len(head)


def test_header_ends_at_first_non_percent_line(tmp_path):
    body = b"\x25\x00" + EVT3_BODY     # a binary word starting with '%' but not '% '
    p = put(tmp_path, "pct.raw", b"% evt 3.0 \n" + body)
    assert read_raw_header(p).header_bytes == len(b"% evt 3.0 \n")
    p2 = put(tmp_path, "pct2.raw", b"% evt 3.0\n% end\n% binary")
    assert read_raw_header(p2).header_bytes == len(b"% evt 3.0\n% end\n")


def test_expelliarmus_style_header_without_end(tmp_path):
    head = (b"% Date 1970-12-25 07:51:03 \n% evt 3.0 \n% firmware_version 0.0.0 \n"
            b"% integrator_name Prophesee \n")
    p = put(tmp_path, "peer.raw", head + EVT3_BODY)
    d, h = read_raw(p)
    assert h.encoding == "evt3" and h.fields["Date"] == "1970-12-25 07:51:03"
    assert d.events.tolist() == [(4098_000, 4, 3, 1)]


@pytest.mark.parametrize("head, match", [
    (b"% format EVT21;height=1;width=1\n% end\n", "not supported"),
    (b"% evt 2.1\n% end\n", "not supported"),
    (b"% format DAT\n% end\n", "unknown format"),
    (b"% evt 9.9\n", "unknown event format"),
    (b"% date today\n% end\n", "% format EVT3"),
    (b"% format EVT3\n% evt 2.0\n", "contradicts"),
    (b"% format EVT3\n% geometry 12by3\n", "WIDTHxHEIGHT"),
    (b"% format EVT3;width=abc\n", "not an integer"),
    (b"% evt 3.0", "truncated"),
    (b"% evt 3.0\n% bad \xff\xfe line\n", "UTF-8"),
])
def test_bad_headers(tmp_path, head, match):
    p = put(tmp_path, "bad.raw", head)
    with pytest.raises(FormatError, match=match) as ei:
        read_raw_header(p)
    assert str(p) in str(ei.value)


def test_missing_file(tmp_path):
    with pytest.raises(InputError, match="no such file"):
        read_raw(tmp_path / "nope.raw")


def test_header_only_file(tmp_path):
    p = put(tmp_path, "empty.raw", b"% format EVT3;width=4;height=4\n% end\n")
    d, h = read_raw(p)
    assert d.events.size == 0 and h.width == 4
    assert list(iter_raw(p)) == []


def test_a_file_cut_mid_word_keeps_every_complete_word(tmp_path, capsys):
    """As a killed recording ends: the complete words are read, with one warning naming the byte
    offset; strict (--strict) refuses the file instead, naming the offset too."""
    from evdnerf_ros.cli import main
    from evdnerf_ros.events.codecs._common import TruncatedStreamWarning

    head = b"% format EVT3;width=8;height=8\n% end\n"
    whole = put(tmp_path, "whole.raw", head + EVT3_BODY)
    p = put(tmp_path, "trunc.raw", head + EVT3_BODY + b"\x00")
    want, _ = read_raw(whole)
    with pytest.warns(TruncatedStreamWarning, match=f"trunc.raw: ends inside a 2-byte EVT 3.0 word at byte "
                                                   f"{len(head) + len(EVT3_BODY)} \\(1 byte"):
        got, _ = read_raw(p)
    assert np.array_equal(got.events, want.events) and got.events.size
    with pytest.warns(TruncatedStreamWarning):
        assert np.array_equal(np.concatenate([d.events for d in iter_raw(p)]), want.events)
    with pytest.raises(FormatError, match="truncated") as ei:
        read_raw(p, strict=True)
    assert ei.value.offset == len(head) + len(EVT3_BODY)
    with pytest.raises(FormatError):
        list(iter_raw(p, strict=True))
    out = tmp_path / "o.npz"
    assert main(["convert-events", str(p), str(out)]) == 0
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "trunc.raw: ends inside" in err and f"byte {len(head) + len(EVT3_BODY)}" in err
    assert main(["convert-events", str(p), str(tmp_path / "s.npz"), "--strict"]) == 2
    assert "truncated" in capsys.readouterr().err and not (tmp_path / "s.npz").exists()


def test_corrupt_word_offset_is_a_file_offset(tmp_path):
    head = b"% evt 3.0\n% end\n"
    body = np.array([0x8010, 0x0000, 0x2001, 0x8005, 0x2002], "<u2").tobytes()
    p = put(tmp_path, "corrupt.raw", head + body)
    with pytest.raises(FormatError, match="TIME_HIGH") as ei:
        read_raw(p)
    assert ei.value.offset == len(head) + 6


def test_write_raw_refuses_existing_path(tmp_path):
    ev = make_events([0], [1], [1], [1])
    p = tmp_path / "x.raw"
    write_raw(p, ev, width=4, height=4)
    with pytest.raises(OutputExistsError):
        write_raw(p, ev, width=4, height=4)
    assert sorted(os.listdir(tmp_path)) == ["x.raw"]


@pytest.mark.parametrize("kwargs, match", [
    (dict(events=make_events([1500], [1], [1], [1]), width=4, height=4), "whole microsecond"),
    (dict(events=make_events([0], [4], [1], [1]), width=4, height=4), "outside"),
    (dict(events=make_events([0], [1], [1], [1]), width=4, height=4, encoding="mono"), "evt3 or evt2"),
    (dict(events=make_events([0], [1], [1], [1]), width=0, height=4), "width"),
    (dict(events=make_events([0], [1], [1], [1]), width=4, height=4,
          triggers=np.array([(5000, 1, 1), (0, 1, 1)],
                            dtype=[("t", "<i8"), ("id", "u1"), ("value", "u1")])), "sort"),
])
def test_write_raw_validates_and_leaves_nothing_behind(tmp_path, kwargs, match):
    with pytest.raises(InputError, match=match):
        write_raw(tmp_path / "y.raw", **kwargs)
    assert os.listdir(tmp_path) == []


def test_write_raw_removes_temp_file_on_failure(tmp_path, monkeypatch):
    class FailingEncoder:
        def encode(self, *a, **k):
            raise OSError("disk full")
    monkeypatch.setattr(raw_mod, "make_encoder", lambda *a, **k: FailingEncoder())
    with pytest.raises(OSError, match="disk full"):
        write_raw(tmp_path / "z.raw", make_events([0], [1], [1], [1]), width=4, height=4)
    assert os.listdir(tmp_path) == []


def test_read_raw_time_low_carry_option(tmp_path):
    body = np.array([0x8000, 0x6F00, 0x0001, 0x2001, 0x6010, 0x2002], "<u2").tobytes()
    p = put(tmp_path, "carry.raw", b"% evt 3.0 \n" + body)
    with pytest.raises(FormatError, match="time_low_carry"):
        read_raw(p)
    d, _ = read_raw(p, time_low_carry=True)
    assert list(d.events["t"] // 1000) == [0xF00, 0x1010]


def test_evt2_file_roundtrip_through_encode(tmp_path):
    ev = synthetic_events(1000, duration_us=10_000, seed=4)
    p = put(tmp_path, "e2.raw", b"% evt 2.0\n% geometry 1280x720\n% end\n" + encode(ev, "evt2"))
    d, h = read_raw(p)
    assert h.encoding == "evt2" and np.array_equal(d.events, ev)


def test_raw_without_geometry_takes_the_geometry_flag(tmp_path, capsys):
    """A RAW header with neither a geometry line nor a known plugin_name: refused in one line
    naming --geometry, read with --geometry WxH; events outside it are an error."""
    import re

    from evdnerf_ros.cli import main
    from evdnerf_ros.events import make_events

    ev = make_events(np.arange(5) * 1000, np.arange(5), np.arange(5), np.ones(5, np.int8))
    write_raw(tmp_path / "g.raw", ev, width=8, height=8)
    text = (tmp_path / "g.raw").read_bytes()
    text = re.sub(rb"% geometry [^\n]*\n", b"", re.sub(rb"% format [^\n]*\n", b"% evt 3.0\n", text))
    (tmp_path / "bare.raw").write_bytes(text)
    assert main(["convert-events", str(tmp_path / "bare.raw"), str(tmp_path / "a.npz")]) == 2
    assert "--geometry" in capsys.readouterr().err
    assert main(["convert-events", str(tmp_path / "bare.raw"), str(tmp_path / "a.npz"), "--geometry", "8x8"]) == 0
    assert main(["convert-events", str(tmp_path / "bare.raw"), str(tmp_path / "b.npz"), "--geometry", "4x4"]) == 2
    assert "outside" in capsys.readouterr().err
    assert main(["convert-events", str(tmp_path / "bare.raw"), str(tmp_path / "c.npz"), "--geometry", "8"]) == 2
    assert "--geometry" in capsys.readouterr().err
