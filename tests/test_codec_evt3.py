"""EVT 3.0 codec: word semantics, time unwrapping, errors, round trips, streaming."""

import warnings

import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from evdnerf_ros.errors import FormatError, InputError
from evdnerf_ros.events.codecs import (
    ENCODINGS, Decoded, DroppedEventsWarning, decode, encode, make_decoder, make_encoder,
    quantize_to_us,
)
from evdnerf_ros.events.types import EVENT_DTYPE, TRIGGER_DTYPE, make_events, make_triggers
from synthetic_events import synthetic_events, synthetic_triggers


def words(*ws) -> bytes:
    return np.array(ws, "<u2").tobytes()


def Y(y, sys_bit=0):
    return (sys_bit << 11) | y


def X(x, p):
    return 0x2000 | (p << 11) | x


def BASE(x, p):
    return 0x3000 | (p << 11) | x


def V12(mask):
    return 0x4000 | mask


def V8(mask):
    return 0x5000 | mask


def TL(v):
    return 0x6000 | v


def TH(v):
    return 0x8000 | v


def TRIG(value, tid):
    return 0xA000 | (tid << 8) | value


def ev_list(d):
    return [(int(e["t"]), int(e["x"]), int(e["y"]), int(e["p"])) for e in d.events]


def dec(*ws, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("error", DroppedEventsWarning)
        return decode(words(*ws), "evt3", **kw)


def stream_decode(data: bytes, cuts, **kw) -> Decoded:
    d = make_decoder("evt3", **kw)
    parts, prev = [], 0
    for c in list(cuts) + [len(data)]:
        parts.append(d.feed(data[prev:c]))
        prev = c
    parts.append(d.close())
    return Decoded.concatenate(parts)


# ---- word semantics --------------------------------------------------------------------------

def test_unknown_encoding_lists_valid_ones():
    with pytest.raises(InputError, match="evt3, evt2, mono"):
        decode(b"", "evt4")
    with pytest.raises(InputError, match="evt3"):
        encode(np.empty(0, EVENT_DTYPE), "EVT3")
    assert ENCODINGS == ("evt3", "evt2", "mono", "libcaer", "libcaer_cmp")


def test_addr_y_and_addr_x():
    d = dec(TH(0), TL(5), Y(7), X(3, 1), X(4, 0))
    assert ev_list(d) == [(5000, 3, 7, 1), (5000, 4, 7, -1)]
    assert d.events.dtype == EVENT_DTYPE and d.triggers.dtype == TRIGGER_DTYPE


def test_addr_y_system_type_bit_is_ignored():
    d = dec(TH(0), Y(9, sys_bit=1), X(1, 1))
    assert ev_list(d) == [(0, 1, 9, 1)]


def test_vect_base_x_and_vect_12():
    mask = (1 << 0) | (1 << 9) | (1 << 11)
    d = dec(TH(0), Y(2), BASE(100, 1), V12(mask), V8(0b11))
    assert ev_list(d) == [(0, 100, 2, 1), (0, 109, 2, 1), (0, 111, 2, 1),
                          (0, 112, 2, 1), (0, 113, 2, 1)]


def test_vect_8_advances_base_by_8_and_vect_12_by_12():
    d = dec(TH(0), Y(0), BASE(10, 0), V8(1), V8(1), V12(1), V12(0), V8(0x80))
    assert [e[1] for e in ev_list(d)] == [10, 18, 26, 57]
    assert {e[3] for e in ev_list(d)} == {-1}


def test_vect_8_ignores_bits_above_7_and_addr_x_keeps_vector_state():
    d = dec(TH(0), Y(1), BASE(20, 1), X(5, 0), V8(0xF01))
    assert ev_list(d) == [(0, 5, 1, -1), (0, 20, 1, 1)]


def test_time_low_and_time_high_compose():
    d = dec(TH(0x1), TL(0x234), Y(0), X(0, 1))
    assert d.events["t"][0] == 0x1234 * 1000


def test_time_high_resets_low_bits():
    d = dec(TH(1), TL(0x10), Y(0), X(0, 1), TH(2), X(1, 1))
    assert list(d.events["t"]) == [(0x1010) * 1000, 0x2000 * 1000]


def test_time_base_is_added():
    d = dec(TH(0), TL(3), Y(0), X(0, 1), time_base_ns=7)
    assert d.events["t"][0] == 7 + 3000


def test_time_high_wrap_is_unwrapped():
    d = dec(TH(4095), TL(4095), Y(0), X(0, 1), TH(0), TL(1), X(1, 1), TH(2049), X(2, 1),
            TH(0), X(3, 1))
    us = d.events["t"] // 1000
    assert list(us) == [(1 << 24) - 1, (1 << 24) + 1, (1 << 24) + 2049 * 4096, (2 << 24)]


def test_backwards_time_high_raises_with_offset():
    data = words(TH(100), Y(0), X(0, 1), TH(90), X(1, 1))
    with pytest.raises(FormatError) as ei:
        decode(data, "evt3", source="cam.raw")
    assert ei.value.offset == 6
    assert "cam.raw" in str(ei.value) and "byte offset 6" in str(ei.value)
    assert "TIME_HIGH" in str(ei.value)


def test_backwards_time_low_raises_unless_time_low_carry():
    data = words(TH(0), TL(4000), Y(0), X(0, 1), TL(5), X(1, 1))
    with pytest.raises(FormatError, match="time_low_carry") as ei:
        decode(data, "evt3")
    assert ei.value.offset == 8
    d = decode(data, "evt3", time_low_carry=True)
    assert list(d.events["t"] // 1000) == [4000, 4096 + 5]


def test_time_low_carry_matches_strict_on_conforming_streams():
    ev = synthetic_events(3000, duration_us=30_000_000, seed=3)
    data = encode(ev, "evt3")
    assert np.array_equal(decode(data, "evt3", time_low_carry=True).events, ev)


def test_repeated_time_high_followed_by_time_low_is_fine():
    d = dec(TH(3), TL(7), Y(0), X(0, 1), TH(3), TL(7), X(1, 1))
    assert list(d.events["t"] // 1000) == [3 * 4096 + 7] * 2


def test_repeated_time_high_that_moves_events_back_raises():
    data = words(TH(3), TL(7), Y(0), X(0, 1), TH(3), X(1, 1))
    with pytest.raises(FormatError, match="backwards") as ei:
        decode(data, "evt3")
    assert ei.value.offset == 8


def test_events_before_first_time_high_are_dropped_with_warning():
    data = words(Y(1), X(5, 1), TL(9), X(6, 1), TRIG(1, 2), TH(1), X(7, 0))
    with pytest.warns(DroppedEventsWarning, match=r"front\.raw.*2 event\(s\) and 1 trigger"):
        d = decode(data, "evt3", source="front.raw")
    assert ev_list(d) == [(4096 * 1000, 7, 1, -1)]
    assert d.triggers.size == 0


def test_events_before_first_addr_y_or_vect_base_are_dropped():
    with pytest.warns(DroppedEventsWarning):
        d = decode(words(TH(0), X(1, 1), Y(4), V12(0b11), BASE(8, 1), V8(1), X(2, 0)), "evt3")
    assert ev_list(d) == [(0, 8, 4, 1), (0, 2, 4, -1)]


def test_ext_trigger():
    d = dec(TH(2), TL(1), TRIG(1, 5), TL(2), TRIG(0, 15))
    assert d.events.size == 0
    assert d.triggers.tolist() == [(8193000, 5, 1), (8194000, 15, 0)]


@pytest.mark.parametrize("skipped", [0x1000, 0x7ABC, 0x9123, 0xB000, 0xC0FF, 0xD555, 0xEFFF, 0xF123])
def test_other_and_reserved_types_are_skipped(skipped):
    d = dec(TH(0), Y(1), X(1, 1), skipped, X(2, 1))
    assert ev_list(d) == [(0, 1, 1, 1), (0, 2, 1, 1)]


def test_others_followed_by_continued_words_are_skipped():
    d = dec(TH(0), Y(1), 0xE001, 0xF0F0, 0xF00F, 0x7003, X(3, 0), 0xD000, 0xF000, X(4, 1))
    assert ev_list(d) == [(0, 3, 1, -1), (0, 4, 1, 1)]


def test_odd_byte_count_raises_at_the_dangling_byte():
    data = words(TH(0), Y(0), X(1, 1)) + b"\x01"
    with pytest.raises(FormatError, match="truncated") as ei:
        decode(data, "evt3", source="x.raw")
    assert ei.value.offset == 6


def test_vector_beyond_11_bit_range_raises():
    with pytest.raises(FormatError, match="11-bit") as ei:
        decode(words(TH(0), Y(0), BASE(2040, 1), V12(1), V12(1)), "evt3")
    assert ei.value.offset == 8


def test_accepts_bytes_bytearray_memoryview_and_arrays():
    data = words(TH(0), TL(1), Y(2), X(3, 1))
    for obj in (data, bytearray(data), memoryview(data), np.frombuffer(data, np.uint8),
                np.frombuffer(data, "<u2")):
        assert ev_list(decode(obj, "evt3")) == [(1000, 3, 2, 1)]


# ---- encoder ---------------------------------------------------------------------------------

def word_types(data: bytes) -> np.ndarray:
    return np.frombuffer(data, "<u2") >> 12


def test_encoder_uses_vectors_for_row_bursts_and_addr_x_for_single_events():
    ev = make_events([5000] * 5 + [6000], [10, 11, 12, 20, 21, 7], [3] * 5 + [4], [1] * 6)
    data = encode(ev, "evt3")
    ty = list(word_types(data))
    assert ty[:3] == [0x8, 0x6, 0x0]                  # TIME_HIGH, TIME_LOW, ADDR_Y first
    assert 0x3 in ty and (0x4 in ty or 0x5 in ty)
    assert ty[-1] == 0x2 and ty.count(0x2) == 1
    assert np.array_equal(decode(data, "evt3").events, ev)


def test_encoder_time_words_only_when_time_changes():
    ev = make_events([0, 0, 1000, 4096_000, 4097_000], [1, 5, 2, 3, 4], [0, 1, 1, 1, 1], [1] * 5)
    ty = list(word_types(encode(ev, "evt3")))
    assert ty.count(0x8) == 2 and ty.count(0x6) == 4 and ty.count(0x0) == 2


def test_encoder_inserts_time_high_words_across_long_gaps():
    gap_us = 20_000_000          # longer than the 2**24 us wrap
    ev = make_events([1000_000, (1000 + gap_us) * 1000], [1, 2], [0, 0], [1, -1])
    data = encode(ev, "evt3")
    ty = word_types(data)
    assert np.count_nonzero(ty == 0x8) >= gap_us // (1 << 22)
    assert np.array_equal(decode(data, "evt3").events, ev)


def test_first_event_far_from_time_base_round_trips():
    ev = make_events(np.array([3600_000_000, 3600_000_001]) * 1000, [1, 2], [3, 4], [1, -1])
    assert np.array_equal(decode(encode(ev, "evt3"), "evt3").events, ev)


def test_encode_requires_whole_microseconds():
    ev = make_events([1500], [0], [0], [1])
    with pytest.raises(InputError, match="quantize_to_us"):
        encode(ev, "evt3")
    q = quantize_to_us(ev)
    assert q["t"][0] == 1000
    assert np.array_equal(decode(encode(q, "evt3"), "evt3").events, q)


def test_quantize_floors_relative_to_time_base_and_keeps_order():
    ev = make_events([10_999, 11_000, 11_500], [1, 2, 3], [0, 0, 0], [1, 1, -1])
    q = quantize_to_us(ev, time_base_ns=500)
    assert list(q["t"]) == [10_500, 10_500, 11_500]
    assert list(q["x"]) == [1, 2, 3]
    assert np.array_equal(decode(encode(q, "evt3", time_base_ns=500), "evt3",
                                 time_base_ns=500).events, q)


def test_encode_validates_input():
    with pytest.raises(InputError, match="before time_base_ns"):
        encode(make_events([1000], [0], [0], [1]), "evt3", time_base_ns=2000)
    with pytest.raises(InputError, match="sorted"):
        encode(make_events([2000, 1000], [0, 0], [0, 0], [1, 1]), "evt3")
    with pytest.raises(InputError, match="x=2048"):
        encode(make_events([0], [2048], [0], [1]), "evt3")
    with pytest.raises(InputError, match="ids 0..15"):
        encode(make_events([0], [0], [0], [1]), "evt3", triggers=make_triggers([0], [16], [1]))
    with pytest.raises(InputError, match="value"):
        encode(make_events([0], [0], [0], [1]), "evt3", triggers=make_triggers([0], [1], [2]))


def test_encode_empty():
    assert encode(np.empty(0, EVENT_DTYPE), "evt3") == b""
    assert decode(b"", "evt3").events.size == 0


# ---- round trips -----------------------------------------------------------------------------

@pytest.mark.parametrize("kind", ["dense", "sparse", "wraps", "gap", "triggers"])
def test_round_trip(kind):
    if kind == "dense":
        ev = synthetic_events(20_000, duration_us=2_000, burst_fraction=0.9, seed=1)
        tr = None
    elif kind == "sparse":
        ev = synthetic_events(2_000, duration_us=8_000_000, burst_fraction=0.0, seed=2)
        tr = None
    elif kind == "wraps":
        ev = synthetic_events(20_000, duration_us=60_000_000, seed=3)
        tr = None
    elif kind == "gap":
        a = synthetic_events(3_000, duration_us=100_000, seed=4)
        b = synthetic_events(3_000, duration_us=100_000, seed=5, t0_us=20_200_000)
        ev = np.concatenate([a, b])
        tr = None
    else:
        ev = synthetic_events(10_000, duration_us=40_000_000, seed=6)
        tr = synthetic_triggers(300, duration_us=40_000_000)
        tr["t"][:10] = ev["t"][100:110]          # ties with events
    ev["t"] += 123_000
    if tr is not None:
        tr["t"] += 123_000
    data = encode(ev, "evt3", triggers=tr, time_base_ns=123_000)
    d = decode(data, "evt3", time_base_ns=123_000)
    assert np.array_equal(d.events, ev)
    if tr is not None:
        assert np.array_equal(d.triggers, tr)


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.data())
def test_round_trip_random_streams(data):
    n = data.draw(st.integers(0, 400))
    span = data.draw(st.sampled_from([1, 50, 5_000, 3_000_000, 40_000_000]))
    seed = data.draw(st.integers(0, 2**31))
    rng = np.random.default_rng(seed)
    t = np.sort(rng.integers(0, span, n)) * 1000
    x = rng.integers(0, data.draw(st.sampled_from([3, 30, 2048])), n)
    y = rng.integers(0, data.draw(st.sampled_from([1, 4, 2048])), n)
    p = rng.choice([-1, 1], n)
    order = np.lexsort((x, y, t)) if data.draw(st.booleans()) else np.argsort(t, kind="stable")
    ev = make_events(t[order], x[order], y[order], p[order])
    ntr = data.draw(st.integers(0, 5))
    tr = make_triggers(np.sort(rng.integers(0, span, ntr)) * 1000, rng.integers(0, 16, ntr),
                       rng.integers(0, 2, ntr))
    blob = encode(ev, "evt3", triggers=tr)
    d = decode(blob, "evt3")
    assert np.array_equal(d.events, ev)
    assert np.array_equal(d.triggers, tr)


# ---- streaming -------------------------------------------------------------------------------

def test_streaming_random_splits_equal_one_shot():
    ev = synthetic_events(20_000, duration_us=40_000_000, seed=7)
    tr = synthetic_triggers(50, duration_us=40_000_000)
    data = encode(ev, "evt3", triggers=tr)
    ref = decode(data, "evt3")
    rng = np.random.default_rng(0)
    for n_cuts in (1, 7, 300):
        cuts = np.sort(rng.integers(0, len(data), n_cuts))
        got = stream_decode(data, cuts)
        assert np.array_equal(got.events, ref.events)
        assert np.array_equal(got.triggers, ref.triggers)


def test_streaming_split_inside_words_and_time_pairs():
    data = words(TH(5), TL(6), Y(1), X(1, 1), TH(6), TL(1), X(2, 0), BASE(4, 1), V12(0b101))
    ref = decode(data, "evt3")
    for cut in range(1, len(data)):
        got = stream_decode(data, [cut])
        assert np.array_equal(got.events, ref.events), cut
    got = stream_decode(data, range(1, len(data)))       # one byte at a time
    assert np.array_equal(got.events, ref.events)


def test_streaming_close_raises_on_dangling_byte():
    d = make_decoder("evt3", source="live", offset=100)
    d.feed(words(TH(0), Y(0)) + b"\x02")
    with pytest.raises(FormatError) as ei:
        d.close()
    assert ei.value.offset == 104 and "live" in str(ei.value)


def test_stream_encoder_chunks_concatenate():
    ev = synthetic_events(30_000, duration_us=50_000_000, seed=8)
    tr = synthetic_triggers(40, duration_us=50_000_000)
    enc = make_encoder("evt3", time_base_ns=0)
    bounds = [0, 1, 5000, 5001, 17000, 30_000]
    # include a chunk boundary inside a run of equal times
    ev["t"][4998:5003] = ev["t"][4998]
    ev["t"][5003:] = np.maximum(ev["t"][5003:], ev["t"][4998])
    blob = b""
    for a, b in zip(bounds[:-1], bounds[1:]):
        lo = 0 if a == 0 else np.searchsorted(tr["t"], ev["t"][a - 1], side="right")
        hi = len(tr) if b == len(ev) else np.searchsorted(tr["t"], ev["t"][b - 1], side="right")
        blob += enc.encode(ev[a:b], tr[lo:hi])
    d = decode(blob, "evt3")
    assert np.array_equal(d.events, ev)
    assert np.array_equal(d.triggers, tr)


def test_stream_encoder_chunk_decodes_on_its_own_up_to_wraps():
    ev = synthetic_events(2_000, duration_us=1_000_000, seed=9)
    enc = make_encoder("evt3")
    enc.encode(ev[:1000])
    second = decode(enc.encode(ev[1000:]), "evt3")
    assert np.array_equal(second.events, ev[1000:])


def test_stream_encoder_across_a_long_gap():
    a = synthetic_events(500, duration_us=1000, seed=10)
    b = synthetic_events(500, duration_us=1000, seed=11, t0_us=50_000_000)
    enc = make_encoder("evt3")
    blob = enc.encode(a) + enc.encode(b)
    assert np.array_equal(decode(blob, "evt3").events, np.concatenate([a, b]))


def test_stream_encoder_rejects_chunks_out_of_order():
    enc = make_encoder("evt3")
    enc.encode(make_events([5000], [0], [0], [1]))
    with pytest.raises(InputError, match="time order"):
        enc.encode(make_events([4000], [0], [0], [1]))


def test_large_inputs_are_encoded_in_chunks_seamlessly(monkeypatch):
    import evdnerf_ros.events.codecs._common as common
    monkeypatch.setattr(common, "ENCODE_CHUNK", 777)
    ev = synthetic_events(10_000, duration_us=30_000_000, burst_fraction=0.8, seed=12)
    ev["t"][770:800] = ev["t"][770]              # a vector run across a chunk boundary
    ev["y"][770:800] = ev["y"][770]
    ev["p"][770:800] = 1
    ev["x"][770:800] = np.arange(100, 130)
    tr = synthetic_triggers(100, duration_us=30_000_000)
    tr["t"][3] = ev["t"][776]                    # tie with a chunk's last event
    tr.sort(order="t", kind="stable")
    blob = encode(ev, "evt3", triggers=tr)
    d = decode(blob, "evt3")
    assert np.array_equal(d.events, ev) and np.array_equal(d.triggers, tr)
    # only the first chunk starts with the header words
    assert np.count_nonzero(word_types(blob) == 0x8) < 30_000_000 // 4096 + 20


def test_encoder_state_survives_a_rejected_chunk(monkeypatch):
    import evdnerf_ros.events.codecs._common as common
    monkeypatch.setattr(common, "ENCODE_CHUNK", 100)
    ev = synthetic_events(1000, duration_us=100_000, seed=13)
    enc = make_encoder("evt3")
    first = enc.encode(ev[:500])
    bad = ev[500:].copy()
    bad["p"][300] = 0
    with pytest.raises(InputError, match="event 300 has polarity 0"):
        enc.encode(bad)
    rest = enc.encode(ev[500:])
    assert np.array_equal(decode(first + rest, "evt3").events, ev)


# ---- time-word anomalies real cameras write (../shared/data/real/README.md)

def test_time_low_replaced_by_a_lower_one_before_any_event_is_tolerated_and_counted():
    # a Gen4.1 writes TIME_LOW 811 and at once TIME_LOW 800: the latest wins (OpenEB, event_camera_codecs)
    decoder = make_decoder("evt3")
    d = decoder.feed(words(TH(0), Y(0), TL(700), X(0, 1), TL(811), TL(800), X(1, 1), TL(900), X(2, 1)))
    assert list(d.events["t"] // 1000) == [700, 800, 900]
    assert decoder.time_anomalies == {"time_low_back": 1, "time_high_back": 0}


def test_time_high_stepping_back_a_few_units_is_tolerated_and_counted():
    decoder = make_decoder("evt3")
    d = decoder.feed(words(TH(100), TL(5), Y(0), X(0, 1), TH(97), TH(100), TL(9), X(1, 1)))
    assert list(d.events["t"] // 1000) == [100 * 4096 + 5, 100 * 4096 + 9]
    assert decoder.time_anomalies["time_high_back"] == 1


def test_time_high_step_back_that_moves_an_event_back_raises():
    with pytest.raises(FormatError, match="backwards"):
        dec(TH(100), TL(5), Y(0), X(0, 1), TH(97), X(1, 1))


def test_time_high_dropping_more_than_ten_units_without_a_wrap_raises():
    with pytest.raises(FormatError, match="TIME_HIGH word"):
        dec(TH(100), TL(5), Y(0), X(0, 1), TH(89), TL(0), X(1, 1))


# ---- the anomaly rules as properties: random conforming streams, anomalies injected -----------

def _random_stream(data):
    """Random sorted events (small x / y ranges, so rows and vector runs occur) and triggers,
    encoded by our encoder: a conforming word stream without anomalies."""
    n = data.draw(st.integers(1, 300))
    span = data.draw(st.sampled_from([50, 20_000, 300_000, 3_000_000, 40_000_000]))
    rng = np.random.default_rng(data.draw(st.integers(0, 2**31)))
    t = np.sort(rng.integers(0, span, n)) * 1000
    ev = make_events(t, rng.integers(0, 40, n), rng.integers(0, 6, n), rng.choice([-1, 1], n))
    ntr = data.draw(st.integers(0, 6))
    tr = make_triggers(np.sort(rng.integers(0, span, ntr)) * 1000, rng.integers(0, 16, ntr),
                       rng.integers(0, 2, ntr))
    w = np.frombuffer(encode(ev, "evt3", triggers=tr), "<u2").copy()
    return ev, tr, w, rng


def _feed_in_pieces(w, rng):
    """Decode words fed at random byte cuts; returns (Decoded, time_anomalies)."""
    data = w.astype("<u2").tobytes()
    cuts = np.sort(rng.integers(0, len(data) + 1, 3))
    decoder = make_decoder("evt3")
    parts = [decoder.feed(data[a:b]) for a, b in zip(np.r_[0, cuts], np.r_[cuts, len(data)])]
    parts.append(decoder.close())
    return Decoded.concatenate(parts), decoder.time_anomalies


def _event_prefix(w):
    """Prefix count of event words (ADDR_X / VECT_12 / VECT_8): any event in w[a:b] iff
    n[b] > n[a]."""
    ty = w >> 12
    return np.r_[0, np.cumsum((ty == 2) | (ty == 4) | (ty == 5))]


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.data())
def test_property_tolerated_anomalies_decode_unchanged_and_are_counted(data):
    """Injected into any conforming stream: TIME_LOW words at once replaced by a lower one
    (nothing in between) and TIME_HIGH words stepping back 1..10 units just before the next
    TIME_HIGH. The events and triggers decode exactly as without them, whatever the feed
    boundaries, and each injection is counted once."""
    ev, tr, w, rng = _random_stream(data)
    ty = w >> 12
    low = (w & 0xFFF).astype(np.int64)
    # a TIME_LOW v gets a higher one before it (v' in v+1..4095)
    tl = np.flatnonzero((ty == 6) & (low < 0xFFF))
    k_tl = data.draw(st.integers(0, min(len(tl), 20)))
    at_tl = np.sort(rng.choice(tl, k_tl, replace=False)) if k_tl else np.empty(0, np.int64)
    val_tl = 0x6000 | (low[at_tl] + 1 + rng.integers(0, 0xFFF - low[at_tl]))
    # a TIME_HIGH gets, just before it, the previous TIME_HIGH value less 1..10 units (not
    # across the 12-bit zero: OpenEB and event_camera_codecs read that as a jump forward)
    th = np.flatnonzero(ty == 8)
    step = rng.integers(1, 11, max(len(th) - 1, 0))
    prev = low[th[:-1]]
    ok = prev >= step
    cand, prev, step = th[1:][ok], prev[ok], step[ok]
    k_th = data.draw(st.integers(0, min(len(cand), 20)))
    pick = np.sort(rng.choice(len(cand), k_th, replace=False)) if k_th else np.empty(0, np.int64)
    at_th, val_th = cand[pick], 0x8000 | (prev[pick] - step[pick])
    w2 = np.insert(w, np.r_[at_tl, at_th], np.r_[val_tl, val_th]).astype(np.uint16)
    assert len(w2) == len(w) + k_tl + k_th
    d, anomalies = _feed_in_pieces(w2, rng)
    assert np.array_equal(d.events, ev) and np.array_equal(d.triggers, tr)
    assert anomalies == {"time_low_back": k_tl, "time_high_back": k_th}


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.data())
def test_property_an_event_time_going_back_is_refused(data):
    """In any conforming stream, turn a time word that separates events into one that gives the
    following events an earlier time than the events before it: a TIME_LOW below the previous
    TIME_LOW of the same TIME_HIGH period, or a TIME_HIGH 1..10 units below the previous one.
    The anomaly would be tolerated on its own; an event going back is a FormatError at that
    word's offset, however the bytes are fed."""
    ev, tr, w, rng = _random_stream(data)
    ty = w >> 12
    val = (w & 0xFFF).astype(np.int64)
    n_ev = _event_prefix(w)
    tw = np.flatnonzero((ty == 6) | (ty == 8))
    th = np.flatnonzero(ty == 8)
    cands = []
    for a, b, c in zip(tw[:-1], tw[1:], np.r_[tw[2:], len(w)]):
        # a TIME_LOW after another one of the same TIME_HIGH period, events before and after
        if ty[a] == 6 and ty[b] == 6 and val[a] >= 1 and n_ev[b] > n_ev[a] and n_ev[c] > n_ev[b]:
            cands.append((b, 0x6000 | int(rng.integers(0, val[a])), "low"))
    for a, b, c in zip(th[:-1], th[1:], np.r_[th[2:], len(w)]):
        # a TIME_HIGH with events since the previous TIME_HIGH and before the next one
        if val[a] >= 1 and n_ev[b] > n_ev[a] and n_ev[c] > n_ev[b]:
            cands.append((b, 0x8000 | (val[a] - int(rng.integers(1, min(val[a], 10) + 1))), "high"))
    assume(cands)
    at, word, kind = cands[data.draw(st.integers(0, len(cands) - 1))]
    w2 = w.copy()
    w2[at] = word
    with pytest.raises(FormatError, match="backwards") as ei:
        _feed_in_pieces(w2, rng)
    # reported at the time word that set the earlier time: `at` or a TIME_LOW after it, the
    # last time word before the first event word after `at`
    first_ev = at + int(np.argmax(n_ev[at + 1:] > n_ev[at]))
    # ... or, when an EXT_TRIGGER word comes first, that trigger going back past the previous one
    off = ei.value.offset
    assert off == 2 * tw[tw < first_ev][-1] or (at < off // 2 < first_ev and ty[off // 2] == 0xA), off
    assert ei.value.offset >= 2 * at


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.data())
def test_property_time_high_dropping_more_than_ten_units_without_a_wrap_is_refused(data):
    ev, tr, w, rng = _random_stream(data)
    ty = w >> 12
    th = np.flatnonzero(ty == 8)
    prev = (w[th[:-1]] & 0xFFF).astype(np.int64)
    ok = np.flatnonzero(prev >= 11)
    assume(ok.size)
    i = int(ok[data.draw(st.integers(0, ok.size - 1))])
    drop = data.draw(st.integers(11, min(int(prev[i]), 2048)))
    w2 = w.copy()
    w2[th[i + 1]] = 0x8000 | (int(prev[i]) - drop)
    with pytest.raises(FormatError, match="TIME_HIGH word") as ei:
        _feed_in_pieces(w2, rng)
    assert ei.value.offset == 2 * th[i + 1]
