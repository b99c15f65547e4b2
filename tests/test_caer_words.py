"""The DVXplorer USB word codec (rig.camera.caer_words): hand-made words as libcaer reads them,
bit-for-bit round trips across many timestamp wraps and any chunking, and fuzzing."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from evdnerf_ros.errors import InputError
from evdnerf_ros.events.types import EVENT_DTYPE, TRIGGER_DTYPE
from rig.camera.caer_words import (TRIGGER_EDGE, TRIGGER_GENERATOR, TRIGGER_PULSE, CaerWordDecoder,
                                   CaerWordEncoder, canonical_order, decode_caer_words, encode_caer_words)


def words(*w) -> bytes:
    return np.array(w, "<u2").tobytes()


def random_events(n, span_us, seed=0, width=640, height=480, dense=False):
    rng = np.random.default_rng(seed)
    ev = np.empty(n, EVENT_DTYPE)
    t = np.sort(rng.integers(0, span_us, n))
    ev["t"] = t * 1000
    if dense:     # readout-like: same microsecond, same column, neighbouring rows
        ev["x"] = (t * 7 + rng.integers(0, 2, n)) % width
        ev["y"] = rng.integers(0, height // 8, n) * 8 + rng.integers(0, 8, n)
    else:
        ev["x"] = rng.integers(0, width, n)
        ev["y"] = rng.integers(0, height, n)
    ev["p"] = rng.choice(np.array([-1, 1], np.int8), n)
    return ev


# ---------------------------------------------------------------------------- the layout
def test_hand_made_words_decode_as_libcaer_reads_them():
    data = words(
        0x8000 | 100,                 # timestamp 100 us
        0x1000 | 5,                   # column 5
        0x4000 | (1 << 6) | 2,        # group 1 = rows 16.., group 2 = 2 + 1 -> rows 24..
        0x3000 | 0x81,                # group 1, ON, rows 16 and 23
        0x2000 | 0x100 | 0x02,        # group 2, OFF, row 25
        0x7001,                       # wrap: time = 32768
        0x0003,                       # external input rising edge at 32768
        0x8000 | 7,                   # 32768 + 7
        0x4000 | 0x800 | (2 << 6) | 3,  # group 1 = 3 (rows 24..), group 2 = 3 - 2 = 1 (rows 8..)
        0x2000 | 0x10,                # group 2 ON row 12 (column still 5)
        0x1000 | 0x800 | 9,           # column 9 with the start-of-frame marker
        0x3000 | 0x100 | 0x01,        # group 1 OFF row 24
        0x5000 | 0x0012,              # IMU data byte: skipped
        0x0002,                       # falling edge
        0x0004,                       # pulse
        0x0011,                       # generator rising edge
        0x0001,                       # timestamp reset
        0x8000 | 3,                   # 3 us after the reset
        0x3000 | 0x04,                # group 1 (still rows 24..), ON row 26, column 9
    )
    ev, tr = decode_caer_words(data)
    assert ev.tolist() == [(100_000, 5, 16, 1), (100_000, 5, 23, 1), (100_000, 5, 25, -1),
                           (32_775_000, 5, 12, 1), (32_775_000, 9, 24, -1), (3_000, 9, 26, 1)]
    assert tr.tolist() == [(32_768_000, TRIGGER_EDGE, 1), (32_775_000, TRIGGER_EDGE, 0),
                           (32_775_000, TRIGGER_PULSE, 1), (32_775_000, TRIGGER_GENERATOR, 1)]
    dec = CaerWordDecoder()
    dec.feed(data)
    assert dec.resets == 1 and dec.imu_words == 1 and dec.time_us == 3


def test_wrap_words_multiply_and_out_of_range_addresses_are_skipped():
    data = words(0x7003, 0x8000 | 1,           # 3 wraps in one word (libcaer multiplies)
                 0x1000 | 7, 0x4000, 0x3000 | 1,
                 0x1000 | 700,                  # column beyond 640: skipped, column stays 7
                 0x4000 | 61,                   # group 61 = row 488 >= 480: skipped
                 0x4000 | 0x800 | (5 << 6) | 2,  # group 2 = 2 - 5 < 0: skipped
                 0x3000 | 2, 0x6000, 0x0000, 0x0009)
    dec = CaerWordDecoder()
    ev, tr = dec.feed(data)
    assert ev.tolist() == [(3 * 32768_000 + 1000, 7, 0, 1), (3 * 32768_000 + 1000, 7, 1, 1)]
    assert tr.size == 0
    assert dec.bad_addresses == 3 and dec.unknown_words == 3


def test_invert_xy_swaps_and_checks_sensor_addresses():
    data = words(0x8000 | 1, 0x1000 | 300, 0x4000 | 2, 0x3000 | 1)
    ev, _ = decode_caer_words(data, 480, 640, invert_xy=True)      # sensor 640 columns x 480 rows
    assert ev.tolist() == [(1000, 16, 300, 1)]


# ---------------------------------------------------------------------------- round trips
@pytest.mark.parametrize("dense", [False, True])
def test_round_trip_bit_for_bit_across_many_wraps(dense):
    ev = random_events(60_000, 20_000_000, seed=3, dense=dense)     # 20 s: 610 timestamp wraps
    tr = np.zeros(6, TRIGGER_DTYPE)
    tr["t"] = np.sort(np.random.default_rng(4).integers(0, 20_000_000, 6)) * 1000
    tr["id"] = [0, 0, 1, 2, 2, 0]
    tr["value"] = [1, 0, 1, 1, 0, 1]
    data = encode_caer_words(ev, tr)
    out, otr = decode_caer_words(data)
    assert np.array_equal(out, canonical_order(ev))
    assert np.array_equal(otr, tr)
    # every period boundary crossed is one wrap word (data 1), as the camera sends them
    w = np.frombuffer(data, "<u2")
    assert np.count_nonzero(w == 0x7001) == int(ev["t"][-1] // 1000 >> 15)
    assert np.count_nonzero((w & 0xF000) == 0x7000) == np.count_nonzero(w == 0x7001)


def test_any_chunking_even_mid_word_gives_the_same_events():
    ev = random_events(20_000, 3_000_000, seed=5, dense=True)
    data = encode_caer_words(ev)
    ref, _ = decode_caer_words(data)
    rng = np.random.default_rng(6)
    for _ in range(5):
        cuts = np.sort(rng.integers(0, len(data), 200))
        dec = CaerWordDecoder()
        parts, prev = [], 0
        for c in [*cuts, len(data)]:
            e, _t = dec.feed(data[prev:c])
            parts.append(e)
            prev = c
        assert np.array_equal(np.concatenate(parts), ref)
        assert dec.pending_bytes == 0
    dec = CaerWordDecoder()                                     # one byte at a time
    small = data[:4001]
    got = np.concatenate([dec.feed(small[i:i + 1])[0] for i in range(len(small))])
    assert np.array_equal(got, decode_caer_words(small)[0])
    assert dec.pending_bytes == 1


def test_streaming_encoder_continues_one_stream_with_reset_and_idle_wraps():
    a = random_events(5000, 2_000_000, seed=7)
    b = random_events(5000, 2_000_000, seed=8)
    b["t"] += 10_000_000_000                                    # 10 s later
    enc = CaerWordEncoder()
    data = enc.encode(a) + enc.advance(9_000_000) + enc.encode(b)
    assert enc.time_us == int(b["t"][-1]) // 1000
    c = random_events(100, 50_000, seed=9)
    data += enc.reset() + enc.encode(c)
    dec = CaerWordDecoder()
    out, _ = dec.feed(data)
    assert np.array_equal(out, np.concatenate([canonical_order(a), canonical_order(b), canonical_order(c)]))
    assert dec.resets == 1
    with pytest.raises(InputError, match="time order"):
        enc.encode(c[:1])                          # before the stream's last event


def test_encoder_rejects_what_the_words_cannot_carry():
    ev = random_events(10, 1000)
    bad = ev.copy()
    bad["t"][3] += 1                                            # not a whole microsecond
    with pytest.raises(InputError, match="whole microsecond"):
        encode_caer_words(bad)
    bad = ev.copy()
    bad["x"][0] = 640
    with pytest.raises(InputError, match="outside"):
        encode_caer_words(bad)
    tr = np.zeros(1, TRIGGER_DTYPE)
    tr["id"] = 7
    with pytest.raises(InputError, match="trigger id 7"):
        encode_caer_words(ev, tr)
    with pytest.raises(InputError, match="unknown model"):
        CaerWordDecoder(model="DAVIS9000")


events_strategy = st.lists(
    st.tuples(st.integers(0, 3_000_000), st.integers(0, 639), st.integers(0, 479), st.sampled_from([-1, 1])),
    max_size=300)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(events_strategy, st.lists(st.integers(0, 4000), max_size=8))
def test_property_round_trip_and_chunking(items, cuts):
    ev = np.array(sorted(items, key=lambda r: r[0]), EVENT_DTYPE) if items else np.empty(0, EVENT_DTYPE)
    ev["t"] *= 1000
    data = encode_caer_words(ev)
    dec = CaerWordDecoder()
    parts, prev = [], 0
    for c in sorted(min(c, len(data)) for c in cuts) + [len(data)]:
        parts.append(dec.feed(data[prev:c])[0])
        prev = c
    got = np.concatenate(parts) if parts else np.empty(0, EVENT_DTYPE)
    assert np.array_equal(got, canonical_order(ev))


@settings(max_examples=200, deadline=None)
@given(st.binary(max_size=4096), st.integers(1, 4096))
def test_fuzz_random_bytes_never_crash_and_chunking_does_not_matter(blob, step):
    ev, tr = decode_caer_words(blob)
    assert ev.dtype == EVENT_DTYPE and tr.dtype == TRIGGER_DTYPE
    assert np.all(ev["x"] < 640) and np.all(ev["y"] < 480) and np.all(np.abs(ev["p"]) == 1)
    dec = CaerWordDecoder()
    parts = [dec.feed(blob[i:i + step]) for i in range(0, len(blob), step)]
    got = np.concatenate([p[0] for p in parts]) if parts else np.empty(0, EVENT_DTYPE)
    assert np.array_equal(got, ev)


# ---------------------------------------------------------------------------- against a reference
COUNTERS = ("resets", "bad_addresses", "imu_words", "unknown_words", "words", "time_us", "pending_bytes")


def reference_decode(data, cols=640, rows=480):
    """The module doc's word table, one word at a time in plain Python (no tables, no kernels)."""
    ev, tr = [], []
    c = dict.fromkeys(COUNTERS, 0)
    wrap = cur = x = y1 = y2 = 0
    for v in np.frombuffer(data[:len(data) & ~1], "<u2").tolist():
        c["words"] += 1
        code, d = v >> 12, v & 0xFFF
        if v & 0x8000:
            cur = wrap + (v & 0x7FFF)
        elif code in (2, 3):
            base = y1 if code == 3 else y2
            ev += [(cur * 1000, x, base + b, -1 if d & 0x100 else 1) for b in range(8) if d & (1 << b)]
        elif code == 1:
            if (d & 0x3FF) < cols:
                x = d & 0x3FF
            else:
                c["bad_addresses"] += 1
        elif code == 4:
            g1, off = d & 0x3F, (d >> 6) & 0x1F
            g2 = g1 - off if d & 0x800 else g1 + off
            if 8 * g1 < rows and 0 <= g2 and 8 * g2 < rows:
                y1, y2 = 8 * g1, 8 * g2
            else:
                c["bad_addresses"] += 1
        elif code == 7:
            wrap += d << 15
            cur = wrap
        elif code == 0 and d == 1:
            wrap = cur = 0
            c["resets"] += 1
        elif code == 0 and d in (2, 3):
            tr.append((cur * 1000, TRIGGER_EDGE, d - 2))
        elif code == 0 and d == 4:
            tr.append((cur * 1000, TRIGGER_PULSE, 1))
        elif code == 0 and d in (16, 17):
            tr.append((cur * 1000, TRIGGER_GENERATOR, d - 16))
        elif code == 5 or (code == 0 and d in (5, 7)):
            c["imu_words"] += 1
        else:
            c["unknown_words"] += 1
    c["time_us"] = cur
    c["pending_bytes"] = len(data) & 1
    return np.array(ev, EVENT_DTYPE), np.array(tr, TRIGGER_DTYPE), c


def mixed_words(n, seed):
    """Every kind of word: events (masks of any bit count), bad addresses, triggers, resets,
    IMU and unknown words, multi-period wraps."""
    rng = np.random.default_rng(seed)
    top = rng.choice([0x8, 0x1, 0x2, 0x3, 0x4, 0x0, 0x5, 0x6, 0x7], n, p=[.15, .2, .15, .2, .2, .04, .03, .02, .01])
    w = (top << 12) | rng.integers(0, 0x1000, n)
    w[top == 0x8] = 0x8000 | rng.integers(0, 0x8000, int(np.sum(top == 0x8)))
    w[top == 0x1] = 0x1000 | rng.integers(0, 700, int(np.sum(top == 0x1)))          # some columns >= 640
    w[top == 0x7] = 0x7000 | rng.integers(0, 4, int(np.sum(top == 0x7)))
    w[top == 0x0] = rng.choice([1, 2, 3, 4, 5, 7, 9, 16, 17, 0x800], int(np.sum(top == 0x0)))
    return w.astype("<u2").tobytes()


@pytest.mark.parametrize("seed", range(4))
def test_decoder_matches_a_word_by_word_reference(seed):
    data = mixed_words(3000, seed) + (b"\x35" if seed % 2 else b"")      # odd: a byte left pending
    ref_ev, ref_tr, ref_c = reference_decode(data)
    dec = CaerWordDecoder()
    ev, tr = dec.feed(data)
    assert ref_ev.size > 1000 and ref_tr.size > 10 and ref_c["bad_addresses"] > 10 and ref_c["resets"] > 5
    assert np.array_equal(ev, ref_ev) and np.array_equal(tr, ref_tr)
    assert {k: getattr(dec, k) for k in COUNTERS} == ref_c


def test_split_at_every_byte_offset_gives_the_whole_buffer_decode():
    data = mixed_words(400, 9)
    ref_ev, ref_tr, ref_c = reference_decode(data)
    for cut in range(len(data) + 1):
        # two pieces, and three with a one-byte middle (a word split twice in a row)
        for cuts in ([cut], [cut, cut + 1]):
            dec = CaerWordDecoder()
            parts, prev = [], 0
            for c in [*cuts, len(data)]:
                parts.append(dec.feed(data[prev:min(c, len(data))]))
                prev = min(c, len(data))
            assert np.array_equal(np.concatenate([p[0] for p in parts]), ref_ev), cuts
            assert np.array_equal(np.concatenate([p[1] for p in parts]), ref_tr), cuts
            assert {k: getattr(dec, k) for k in COUNTERS} == ref_c, cuts


def test_any_buffer_kind_decodes_alike():
    data = mixed_words(2000, 11)
    ref_ev, ref_tr, _ = reference_decode(data)
    shifted = bytearray(b"\x00" + data)
    for buf in (bytearray(data), memoryview(data), memoryview(shifted)[1:],        # odd address
                np.frombuffer(data, np.uint8).copy(), np.frombuffer(data, "<u2").copy()):
        ev, tr = CaerWordDecoder().feed(buf)
        assert np.array_equal(ev, ref_ev) and np.array_equal(tr, ref_tr), type(buf)
