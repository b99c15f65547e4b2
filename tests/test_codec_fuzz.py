"""Fuzzing: arbitrary bytes never crash a decoder (only FormatError), output stays bounded,
streaming equals one-shot, and malformed RAW headers give FormatError."""

import warnings

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from evdnerf_ros.errors import FormatError
from evdnerf_ros.events.codecs import Decoded, DroppedEventsWarning, decode, encode, make_decoder
from evdnerf_ros.events.types import EVENT_DTYPE, make_events
from evdnerf_ros.io.raw import RawHeader, read_raw, read_raw_header

WORD = {"evt3": 2, "evt2": 4, "mono": 8}
MAX_PER_WORD = {"evt3": 12, "evt2": 1, "mono": 1}
FUZZ = settings(max_examples=150, deadline=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])


def one_shot(data, enc, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DroppedEventsWarning)
        try:
            return decode(data, enc, **kw)
        except FormatError as e:
            return e


def streamed(data, enc, cuts, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DroppedEventsWarning)
        d = make_decoder(enc, **kw)
        parts, prev = [], 0
        try:
            for c in sorted(cuts) + [len(data)]:
                parts.append(d.feed(data[prev:c]))
                prev = c
            parts.append(d.close())
        except FormatError as e:
            return e
        return Decoded.concatenate(parts)


def check(data, enc, cuts, **kw):
    ref = one_shot(data, enc, **kw)
    got = streamed(data, enc, cuts, **kw)
    if isinstance(ref, FormatError):
        assert isinstance(got, FormatError)
        assert ref.offset is None or 0 <= ref.offset <= len(data)
        return
    assert not isinstance(got, FormatError), got
    n_words = len(data) // WORD[enc]
    assert ref.events.shape[0] <= MAX_PER_WORD[enc] * n_words
    assert ref.triggers.shape[0] <= n_words
    assert ref.events.dtype == EVENT_DTYPE
    assert np.all(np.diff(ref.events["t"]) >= 0)
    assert np.all(np.isin(ref.events["p"], [-1, 1]))
    if enc != "mono":
        assert ref.events["x"].max(initial=0) < 2048 and ref.events["y"].max(initial=0) < 2048
    assert np.array_equal(got.events, ref.events)
    assert np.array_equal(got.triggers, ref.triggers)


cut_lists = st.lists(st.integers(0, 600), max_size=6)


@FUZZ
@given(st.binary(max_size=600), st.sampled_from(["evt3", "evt2", "mono"]), cut_lists)
def test_random_bytes(data, enc, cuts):
    check(data, enc, [c for c in cuts if c <= len(data)])


# words biased towards meaningful types, so that the decoders get deep into their logic
evt3_word = st.one_of(
    st.integers(0, 0xFFFF),
    st.builds(lambda t, v: (t << 12) | v, st.sampled_from([0x0, 0x2, 0x3, 0x4, 0x5, 0x6, 0x8, 0xA]),
              st.integers(0, 0xFFF)),
    st.builds(lambda v: 0x8000 | v, st.integers(0, 8)),
    st.builds(lambda v: 0x6000 | v, st.integers(0, 40)),
)
evt2_word = st.one_of(
    st.integers(0, 0xFFFFFFFF),
    st.builds(lambda t, v: (t << 28) | v, st.sampled_from([0x0, 0x1, 0x8, 0xA, 0xE]),
              st.integers(0, (1 << 28) - 1)),
    st.builds(lambda v: (0x8 << 28) | v, st.integers(0, 6)),
    st.builds(lambda p, lsb, xy: (p << 28) | (lsb << 22) | xy, st.integers(0, 1),
              st.integers(0, 63), st.integers(0, (1 << 22) - 1)),
)


@FUZZ
@given(st.lists(evt3_word, max_size=200), cut_lists, st.booleans())
def test_structured_evt3(ws, cuts, carry):
    data = np.array(ws, "<u2").tobytes()
    check(data, "evt3", [c for c in cuts if c <= len(data)], time_low_carry=carry)


@FUZZ
@given(st.lists(evt2_word, max_size=120), cut_lists)
def test_structured_evt2(ws, cuts):
    data = np.array(ws, "<u4").tobytes()
    check(data, "evt2", [c for c in cuts if c <= len(data)])


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 10**7), st.integers(0, 65535), st.integers(0, 32767),
                          st.booleans()), max_size=50))
def test_mono_round_trip(rows):
    rows.sort(key=lambda r: r[0])
    ev = np.empty(0, EVENT_DTYPE)
    if rows:
        t, x, y, p = map(np.array, zip(*rows))
        ev = make_events(t, x, y, p)
    assert np.array_equal(decode(encode(ev, "mono"), "mono").events, ev)


header_line = st.one_of(
    st.sampled_from([b"% evt 3.0", b"% evt 2.0", b"% evt 2.1", b"% format EVT3;width=5;height=7",
                     b"% format EVT2", b"% format EVT21", b"% geometry 3x4", b"% geometry x",
                     b"% end", b"%", b"% format EVT3;width=-1", b"% evt", b"% format"]),
    st.binary(max_size=30).map(lambda b: b"% " + b),
    st.binary(max_size=30),
)


@FUZZ
@given(st.lists(header_line, max_size=6), st.binary(max_size=64), st.booleans())
def test_malformed_raw_headers(tmp_path, lines, body, newline_at_end):
    head = b"\n".join(lines) + (b"\n" if newline_at_end and lines else b"")
    p = tmp_path / "fuzz.raw"
    p.write_bytes(head + body)
    try:
        h = read_raw_header(p)
    except FormatError:
        return
    assert isinstance(h, RawHeader) and h.encoding in ("evt3", "evt2")
    assert 0 <= h.header_bytes <= len(head + body)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DroppedEventsWarning)
        try:
            d, _ = read_raw(p)
        except FormatError:
            return
    assert d.events.dtype == EVENT_DTYPE
