"""The libcaer and libcaer_cmp EventPacket encodings: hand-built words decode as
event_camera_codecs' decoders read them, round trips, chunking, rollover, errors."""

from __future__ import annotations

import numpy as np
import pytest

from evdnerf_ros.errors import FormatError, InputError
from evdnerf_ros.events.codecs import decode, encode, make_decoder
from evdnerf_ros.events.codecs.libcaer import (ADDR_X, ADDR_Y, TIME_HIGH, TIME_LOW, VECT_8, VECT_BASE_Y,
                                               LibcaerCmpDecoder, LibcaerDecoder)
from evdnerf_ros.events.types import make_events

T0 = 1_702_306_974_272_224_018  # a libcaer_driver time_base (host ns, not on the us grid)


def rec(x, y, p, ts, valid=1):
    return np.array([(x << 17) | (y << 2) | (p << 1) | valid, ts], "<u4").tobytes()


def tok(code, value):
    return np.array([(code << 12) | value], "<u2").tobytes()


def ev_list(ev):
    return [(int(e["t"]), int(e["x"]), int(e["y"]), int(e["p"])) for e in ev]


def random_us_events(rng, n, *, t0=T0, span_us=5_000_000, w=640, h=480):
    t = t0 + np.sort(rng.integers(0, span_us, n)) * 1000
    t[: n // 5] = t[0]
    return make_events(t, rng.integers(0, w, n), rng.integers(0, h, n), rng.integers(0, 2, n).astype(bool))


# --------------------------------------------------------------------------- libcaer


def test_libcaer_fields_and_time_base():
    data = rec(639, 479, 1, 5) + rec(0, 1, 0, 7) + rec(12, 34, 1, 2**31 - 1)
    d = decode(data, "libcaer", time_base_ns=T0)
    assert ev_list(d.events) == [(T0 + 5000, 639, 479, 1), (T0 + 7000, 0, 1, -1), (T0 + (2**31 - 1) * 1000, 12, 34, 1)]


def test_libcaer_rollover_inside_a_packet_adds_2_pow_31_us():
    data = rec(1, 1, 1, 2**31 - 2) + rec(2, 2, 1, 3) + rec(3, 3, 0, 3) + rec(4, 4, 0, 1)
    t = decode(data, "libcaer", time_base_ns=0).events["t"]
    assert t.tolist() == [(2**31 - 2) * 1000, (2**31 + 3) * 1000, (2**31 + 3) * 1000, (2**32 + 1) * 1000]
    # a new packet restarts the count (its time_base carries the high bits, as libcaer_driver writes it)
    dec = LibcaerDecoder(time_base_ns=0)
    dec.feed(rec(1, 1, 1, 100))
    dec.next_packet(2**31 * 1000)
    assert dec.feed(rec(1, 1, 1, 5)).events["t"].tolist() == [(2**31 + 5) * 1000]


def test_libcaer_ignores_the_valid_bit_as_event_camera_codecs_does():
    assert decode(rec(1, 2, 1, 3, valid=0), "libcaer").events.size == 1


def test_libcaer_round_trip_and_any_chunking(rng):
    ev = random_us_events(rng, 5000)
    data = encode(ev, "libcaer", time_base_ns=T0)
    assert len(data) == 8 * ev.size
    assert np.array_equal(decode(data, "libcaer", time_base_ns=T0).events, ev)
    dec = make_decoder("libcaer", time_base_ns=T0)
    parts = [dec.feed(data[i:i + 13]).events for i in range(0, len(data), 13)]
    assert np.array_equal(np.concatenate(parts), ev)
    with pytest.raises(FormatError, match="dangling"):
        decode(data[:-3], "libcaer", time_base_ns=T0)


def test_libcaer_encoder_rolls_over_and_refuses_what_it_cannot_carry():
    ev = make_events(np.array([2**31 - 1, 2**31 + 4]) * 1000, [1, 2], [3, 4], [1, -1])
    data = encode(ev, "libcaer")
    assert np.frombuffer(data, "<i4")[1::2].tolist() == [2**31 - 1, 4]
    assert np.array_equal(decode(data, "libcaer").events, ev)
    with pytest.raises(InputError, match="whole microsecond"):
        encode(make_events([1500], [0], [0], [1]), "libcaer")
    with pytest.raises(InputError, match="rollover"):
        encode(make_events([0, 2**31 * 1000], [0, 0], [0, 0], [1, 1]), "libcaer")
    with pytest.raises(InputError, match="no triggers"):
        encode(ev, "libcaer", triggers=np.zeros(1, [("t", "<i8"), ("id", "u1"), ("value", "i1")]))


# --------------------------------------------------------------------------- libcaer_cmp


def test_cmp_tokens_decode_as_event_camera_codecs_reads_them():
    data = b"".join([
        tok(ADDR_X, 5), tok(ADDR_Y, (1 << 11) | 7),           # (5, 7) ON at offset 0
        tok(TIME_LOW, 3), tok(ADDR_Y, 9),                      # (5, 9) OFF at 3 us
        tok(TIME_HIGH, 2), tok(ADDR_X, 6),                     # offset (2 << 12) | 3 us
        tok(VECT_BASE_Y, (1 << 11) | 16), tok(VECT_8, 0b10000101), tok(VECT_8, 0b1),  # y 16, 18, 23 then 24
    ])
    d = decode(data, "libcaer_cmp", time_base_ns=T0)
    t2 = T0 + ((2 << 12) | 3) * 1000
    assert ev_list(d.events) == [(T0, 5, 7, 1), (T0 + 3000, 5, 9, -1), (t2, 6, 16, 1), (t2, 6, 18, 1),
                                 (t2, 6, 23, 1), (t2, 6, 24, 1)]
    for step in (2, 4, 6):  # the decoder state (time, x, vector base) carries across any word boundary
        dec = make_decoder("libcaer_cmp", time_base_ns=T0)
        parts = [dec.feed(data[i:i + step]).events for i in range(0, len(data), step)]
        assert ev_list(np.concatenate(parts)) == ev_list(d.events)


def test_cmp_state_carries_across_messages_and_time_restarts():
    dec = LibcaerCmpDecoder(time_base_ns=100_000, width=64, height=64)
    a = dec.feed(tok(ADDR_X, 3) + tok(TIME_LOW, 5) + tok(VECT_BASE_Y, 8) + tok(VECT_8, 1))
    dec.next_packet(200_000)
    b = dec.feed(tok(ADDR_Y, (1 << 11) | 2) + tok(VECT_8, 0b10))   # x = 3 and base y = 16 carried over
    assert ev_list(a.events) == [(105_000, 3, 8, -1)]
    assert ev_list(b.events) == [(200_000, 3, 2, 1), (200_000, 3, 17, -1)]


def test_cmp_drops_events_outside_the_geometry_and_counts_them():
    dec = LibcaerCmpDecoder(width=10, height=10)
    d = dec.feed(tok(ADDR_X, 9) + tok(ADDR_Y, 9) + tok(ADDR_Y, 10) + tok(ADDR_X, 10) + tok(ADDR_Y, 0))
    assert ev_list(d.events) == [(0, 9, 9, -1)] and dec.dropped_out_of_geometry == 2


def test_cmp_round_trip_any_chunking_and_order(rng):
    ev = random_us_events(rng, 20000, span_us=200_000)
    # same time, x, polarity and y block with y not increasing: order must survive
    extra = make_events([ev["t"][-1]] * 4, [7] * 4, [17, 16, 17, 23], [1] * 4)
    ev = np.concatenate([ev, extra])
    data = encode(ev, "libcaer_cmp", time_base_ns=int(ev["t"][0]))
    assert len(data) < 8 * ev.size
    assert np.array_equal(decode(data, "libcaer_cmp", time_base_ns=int(ev["t"][0])).events, ev)
    dec = make_decoder("libcaer_cmp", time_base_ns=int(ev["t"][0]))
    parts = [dec.feed(data[i:i + 101]).events for i in range(0, len(data), 101)]
    assert np.array_equal(np.concatenate(parts), ev)


def test_cmp_vectors_compress_dense_columns():
    t = np.full(8, 5000)
    ev = make_events(t, [3] * 8, np.arange(8, 16), [1] * 8)
    data = encode(ev, "libcaer_cmp")
    words = np.frombuffer(data, "<u2")
    assert [(int(w) >> 12) for w in words] == [TIME_LOW, ADDR_X, VECT_BASE_Y, VECT_8]
    assert int(words[-1]) & 0xFF == 0xFF


def test_cmp_errors():
    with pytest.raises(InputError, match="24-bit"):
        encode(make_events([0, 2**24 * 1000], [0, 0], [0, 0], [1, 1]), "libcaer_cmp")
    with pytest.raises(InputError, match="x, y < 2048"):
        encode(make_events([0], [2048], [0], [1]), "libcaer_cmp")
    with pytest.raises(FormatError, match="back in time"):
        decode(tok(ADDR_X, 1) + tok(TIME_LOW, 9) + tok(ADDR_Y, 1) + tok(TIME_LOW, 2) + tok(ADDR_Y, 1), "libcaer_cmp")


def test_cmp_empty_vector_still_moves_the_base():
    d = decode(tok(ADDR_X, 5) + tok(VECT_BASE_Y, 8) + tok(VECT_8, 0) + tok(VECT_8, 0b11), "libcaer_cmp")
    assert ev_list(d.events) == [(0, 5, 16, -1), (0, 5, 17, -1)]
