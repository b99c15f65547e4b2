"""EVT 2.0 codec: word semantics, time unwrapping, errors, round trips, streaming."""

import warnings

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from evdnerf_ros.errors import FormatError, InputError
from evdnerf_ros.events.codecs import (
    Decoded, DroppedEventsWarning, decode, encode, make_decoder, make_encoder,
)
from evdnerf_ros.events.types import make_events, make_triggers
from synthetic_events import synthetic_events, synthetic_triggers


def words(*ws) -> bytes:
    return np.array(ws, "<u4").tobytes()


def CD(p, lsb, x, y):
    return (int(p) << 28) | (lsb << 22) | (x << 11) | y


def TH(v):
    return (0x8 << 28) | v


def TRIG(lsb, tid, value):
    return (0xA << 28) | (lsb << 22) | (tid << 8) | value


def ev_list(d):
    return [(int(e["t"]), int(e["x"]), int(e["y"]), int(e["p"])) for e in d.events]


def dec(*ws, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("error", DroppedEventsWarning)
        return decode(words(*ws), "evt2", **kw)


def stream_decode(data, cuts):
    d = make_decoder("evt2")
    parts, prev = [], 0
    for c in list(cuts) + [len(data)]:
        parts.append(d.feed(data[prev:c]))
        prev = c
    parts.append(d.close())
    return Decoded.concatenate(parts)


def test_cd_on_off_fields():
    d = dec(TH(3), CD(1, 5, 1234, 567), CD(0, 63, 2047, 0))
    assert ev_list(d) == [((3 * 64 + 5) * 1000, 1234, 567, 1), ((3 * 64 + 63) * 1000, 2047, 0, -1)]


def test_time_base():
    assert dec(TH(0), CD(1, 1, 0, 0), time_base_ns=5).events["t"][0] == 1005


def test_ext_trigger():
    d = dec(TH(1), TRIG(2, 31, 1), TRIG(3, 0, 0))
    assert d.triggers.tolist() == [(66_000, 31, 1), (67_000, 0, 0)]


def test_others_and_continued_are_skipped():
    d = dec(TH(0), CD(1, 0, 1, 1), 0xE0000001, 0xF1234567, 0xF0000000, 0x30000000, CD(1, 1, 2, 2))
    assert [e[1] for e in ev_list(d)] == [1, 2]


def test_time_high_wrap():
    top = (1 << 28) - 1
    d = dec(TH(top), CD(1, 63, 0, 0), TH(0), CD(1, 0, 1, 0), TH(5), CD(1, 0, 2, 0))
    us = list(d.events["t"] // 1000)
    assert us == [(top << 6) | 63, 1 << 34, (1 << 34) + (5 << 6)]


def test_backwards_time_high_raises_with_offset():
    with pytest.raises(FormatError, match="TIME_HIGH") as ei:
        decode(words(TH(10), CD(1, 0, 0, 0), TH(9)), "evt2", source="f.raw")
    assert ei.value.offset == 8 and "f.raw" in str(ei.value)


def test_event_time_going_backwards_raises():
    with pytest.raises(FormatError, match="backwards") as ei:
        decode(words(TH(10), CD(1, 5, 0, 0), CD(1, 4, 0, 0)), "evt2")
    assert ei.value.offset == 8


def test_events_before_first_time_high_dropped_with_warning():
    with pytest.warns(DroppedEventsWarning, match=r"cam.*2 event\(s\) and 1 trigger"):
        d = decode(words(CD(1, 0, 1, 1), TRIG(0, 1, 1), CD(0, 1, 2, 2), TH(1), CD(1, 0, 3, 3)),
                   "evt2", source="cam")
    assert ev_list(d) == [(64_000, 3, 3, 1)]


def test_byte_count_not_multiple_of_4_raises():
    with pytest.raises(FormatError, match="truncated") as ei:
        decode(words(TH(0), CD(1, 0, 0, 0)) + b"\x00\x01", "evt2")
    assert ei.value.offset == 8


def test_encoder_emits_time_high_when_time_over_64_changes():
    ev = make_events(np.array([0, 10, 63, 64, 64, 200]) * 1000, [0] * 6, [0] * 6, [1] * 6)
    w = np.frombuffer(encode(ev, "evt2"), "<u4")
    assert list(w >> 28) == [8, 1, 1, 1, 8, 1, 1, 8, 1]
    assert list(w[(w >> 28) == 8] & 0xFFFFFFF) == [0, 1, 3]


def test_encoder_validates():
    with pytest.raises(InputError, match="quantize_to_us"):
        encode(make_events([1], [0], [0], [1]), "evt2")
    with pytest.raises(InputError, match="ids 0..31"):
        encode(make_events([0], [0], [0], [1]), "evt2", triggers=make_triggers([0], [32], [0]))
    with pytest.raises(InputError, match="y=2048"):
        encode(make_events([0], [0], [2048], [1]), "evt2")


@pytest.mark.parametrize("kind", ["dense", "sparse", "long", "triggers"])
def test_round_trip(kind):
    tr = None
    if kind == "dense":
        ev = synthetic_events(20_000, duration_us=3_000, seed=1)
    elif kind == "sparse":
        ev = synthetic_events(3_000, duration_us=30_000_000, burst_fraction=0, seed=2)
    elif kind == "long":        # a 3-hour gap, and times beyond the 28-bit TIME_HIGH range
        a = synthetic_events(1_000, duration_us=1_000, seed=3)
        b = synthetic_events(1_000, duration_us=1_000, seed=4, t0_us=3 * 3600 * 10**6)
        c = synthetic_events(1_000, duration_us=1_000, seed=5, t0_us=(1 << 34) + 12345)
        ev = np.concatenate([a, b, c])
    else:
        ev = synthetic_events(10_000, duration_us=20_000_000, seed=6)
        tr = synthetic_triggers(200, duration_us=20_000_000, max_id=32)
    data = encode(ev, "evt2", triggers=tr)
    d = decode(data, "evt2")
    assert np.array_equal(d.events, ev)
    if tr is not None:
        assert np.array_equal(d.triggers, tr)


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 300), st.sampled_from([1, 100, 10_000, 50_000_000]), st.integers(0, 2**31))
def test_round_trip_random(n, span, seed):
    rng = np.random.default_rng(seed)
    t = np.sort(rng.integers(0, span, n)) * 1000
    ev = make_events(t, rng.integers(0, 2048, n), rng.integers(0, 2048, n), rng.choice([-1, 1], n))
    assert np.array_equal(decode(encode(ev, "evt2"), "evt2").events, ev)


def test_streaming_random_splits_equal_one_shot():
    ev = synthetic_events(10_000, duration_us=5_000_000, seed=7)
    tr = synthetic_triggers(30, duration_us=5_000_000, max_id=32)
    data = encode(ev, "evt2", triggers=tr)
    ref = decode(data, "evt2")
    rng = np.random.default_rng(1)
    for n_cuts in (1, 9, 500):
        got = stream_decode(data, np.sort(rng.integers(0, len(data), n_cuts)))
        assert np.array_equal(got.events, ref.events)
        assert np.array_equal(got.triggers, ref.triggers)
    small = words(TH(1), CD(1, 2, 3, 4), TH(2), CD(0, 1, 5, 6))
    for cut in range(1, len(small)):
        assert np.array_equal(stream_decode(small, [cut]).events, decode(small, "evt2").events)


def test_stream_encoder_chunks_concatenate():
    ev = synthetic_events(9_000, duration_us=9_000_000, seed=8)
    enc = make_encoder("evt2")
    blob = b"".join(enc.encode(ev[a:a + 1000]) for a in range(0, 9000, 1000))
    assert np.array_equal(decode(blob, "evt2").events, ev)


def test_large_inputs_are_encoded_in_chunks_seamlessly(monkeypatch):
    import evdnerf_ros.events.codecs._common as common
    monkeypatch.setattr(common, "ENCODE_CHUNK", 999)
    ev = synthetic_events(10_000, duration_us=10_000_000, seed=9)
    tr = synthetic_triggers(50, duration_us=10_000_000, max_id=32)
    d = decode(encode(ev, "evt2", triggers=tr), "evt2")
    assert np.array_equal(d.events, ev) and np.array_equal(d.triggers, tr)
