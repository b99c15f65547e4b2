"""The ROS `mono` encoding: one 64-bit word per event, dt in ns from the packet time base."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from evdnerf_ros.errors import FormatError, InputError
from evdnerf_ros.events.codecs import Decoded, decode, encode, make_decoder, make_encoder
from evdnerf_ros.events.types import EVENT_DTYPE, make_events, make_triggers


def word(p, y, x, dt):
    return (p << 63) | (y << 48) | (x << 32) | dt


def test_decode_in_order_and_encode_bit_exact():
    data = np.array([word(0, 3, 2, 1), word(1, 0x7FFF, 0xFFFF, 0xFFFFFFFF)], "<u8").tobytes()
    d = decode(data, "mono", time_base_ns=10)
    assert d.events.tolist() == [(11, 2, 3, -1), (10 + 0xFFFFFFFF, 0xFFFF, 0x7FFF, 1)]
    assert encode(d.events, "mono", time_base_ns=10) == data


def test_nanosecond_times_round_trip():
    rng = np.random.default_rng(0)
    t = 1_700_000_000_123_456_789 + np.sort(rng.integers(0, 4_000_000_000, 5000))
    ev = make_events(t, rng.integers(0, 65536, 5000), rng.integers(0, 32768, 5000),
                     rng.choice([-1, 1], 5000))
    base = int(t[0]) - 17
    assert np.array_equal(decode(encode(ev, "mono", time_base_ns=base), "mono",
                                 time_base_ns=base).events, ev)


def test_dt_must_fit_32_bits():
    ev = make_events([0, 1 << 32], [0, 0], [0, 0], [1, 1])
    with pytest.raises(InputError, match="split"):
        encode(ev, "mono")
    with pytest.raises(InputError, match="split"):
        encode(make_events([5], [0], [0], [1]), "mono", time_base_ns=6)


def test_no_triggers_in_mono():
    with pytest.raises(InputError, match="no triggers"):
        encode(make_events([0], [0], [0], [1]), "mono", triggers=make_triggers([0], [0], [1]))


def test_y_limit():
    with pytest.raises(InputError, match="y=32768"):
        encode(make_events([0], [0], [32768], [1]), "mono")


def test_partial_word_raises():
    with pytest.raises(FormatError, match="truncated") as ei:
        decode(b"\x00" * 15, "mono")
    assert ei.value.offset == 8


def test_out_of_order_raises():
    data = np.array([word(1, 0, 0, 5), word(1, 0, 0, 4)], "<u8").tobytes()
    with pytest.raises(FormatError, match="backwards") as ei:
        decode(data, "mono")
    assert ei.value.offset == 8


def test_streaming_and_stream_encoder():
    rng = np.random.default_rng(1)
    ev = make_events(np.sort(rng.integers(0, 1 << 31, 3000)), rng.integers(0, 100, 3000),
                     rng.integers(0, 100, 3000), rng.choice([-1, 1], 3000))
    enc = make_encoder("mono")
    data = enc.encode(ev[:1000]) + enc.encode(ev[1000:])
    d = make_decoder("mono")
    cuts = np.sort(rng.integers(0, len(data), 50))
    parts, prev = [], 0
    for c in list(cuts) + [len(data)]:
        parts.append(d.feed(data[prev:c]))
        prev = c
    parts.append(d.close())
    assert np.array_equal(Decoded.concatenate(parts).events, ev)


@settings(max_examples=40, deadline=None)
@given(st.lists(st.tuples(st.integers(0, (1 << 32) - 1), st.integers(0, 65535),
                          st.integers(0, 32767), st.sampled_from([-1, 1])), max_size=60),
       st.integers(-(1 << 40), 1 << 40))
def test_round_trip_hypothesis(rows, base):
    rows.sort(key=lambda r: r[0])
    ev = np.empty(len(rows), EVENT_DTYPE)
    if rows:
        t, x, y, p = map(np.array, zip(*rows))
        ev = make_events(t + base, x, y, p)
    data = encode(ev, "mono", time_base_ns=base)
    assert len(data) == 8 * len(rows)
    assert np.array_equal(decode(data, "mono", time_base_ns=base).events, ev)
