"""The DAVIS USB word codec (rig.camera.davis_words): hand-made words as libcaer reads them,
bit-for-bit round trips across many timestamp wraps and any chunking, APS frames, fuzzing."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from evdnerf_ros.errors import InputError
from evdnerf_ros.events.types import EVENT_DTYPE, TRIGGER_DTYPE
from rig.camera.davis_words import (TRIGGER_EDGE, TRIGGER_GENERATOR, TRIGGER_PULSE, DavisWordDecoder,
                                    DavisWordEncoder, decode_davis_words, encode_davis_words)


def words(*w) -> bytes:
    return np.array(w, "<u2").tobytes()


def random_events(n, span_us, seed=0, width=346, height=260):
    rng = np.random.default_rng(seed)
    ev = np.empty(n, EVENT_DTYPE)
    ev["t"] = np.sort(rng.integers(0, span_us, n)) * 1000
    ev["x"] = rng.integers(0, width, n)
    ev["y"] = rng.integers(0, height, n)
    ev["p"] = rng.choice(np.array([-1, 1], np.int8), n)
    return ev


def test_hand_made_words_decode_as_libcaer_reads_them():
    data = words(
        0x8000 | 100,            # timestamp 100 us
        0x1000 | 7,              # row 7
        0x3000 | 5,              # ON at column 5
        0x2000 | 6,              # OFF at column 6 (same row)
        0x1000 | 300,            # row 300 >= 260: skipped, row stays 7
        0x3000 | 400,            # column 400 >= 346: skipped
        0x7001,                  # wrap: 32768
        0x0003,                  # external input rising edge
        0x8000 | 9,
        0x3000 | 345,            # last column
        0x5012, 0x0005, 0x0007,  # IMU byte and start / end: skipped
        0x0002, 0x0004, 0x0011,  # falling edge, pulse, generator rising
        0x7003,                  # 3 wraps in one word (libcaer multiplies)
        0x2000 | 1,
        0x0001,                  # timestamp reset
        0x8000 | 3, 0x1000 | 0, 0x3000 | 0,
        0x0000, 0x0006, 0x5F00, 0x6C00)   # reserved / unknown: ignored and counted
    dec = DavisWordDecoder()
    ev, tr = dec.feed(data)
    assert ev.tolist() == [(100_000, 5, 7, 1), (100_000, 6, 7, -1), (32_777_000, 345, 7, 1),
                           (4 * 32_768_000, 1, 7, -1), (3_000, 0, 0, 1)]
    assert tr.tolist() == [(32_768_000, TRIGGER_EDGE, 1), (32_777_000, TRIGGER_EDGE, 0),
                           (32_777_000, TRIGGER_PULSE, 1), (32_777_000, TRIGGER_GENERATOR, 1)]
    assert dec.resets == 1 and dec.bad_addresses == 2 and dec.imu_words == 3 and dec.unknown_words == 4
    assert dec.time_us == 3


def test_invert_xy_swaps_and_checks_sensor_addresses():
    ev, _ = decode_davis_words(words(0x8000 | 1, 0x1000 | 200, 0x3000 | 300), 260, 346, invert_xy=True)
    assert ev.tolist() == [(1000, 200, 300, 1)]


def test_round_trip_bit_for_bit_across_many_wraps_in_the_given_order():
    ev = random_events(60_000, 20_000_000, seed=3)          # 20 s: 610 timestamp wraps
    ev[100:200] = ev[100]                                   # duplicates are carried as they are
    tr = np.zeros(6, TRIGGER_DTYPE)
    tr["t"] = np.sort(np.random.default_rng(4).integers(0, 20_000_000, 6)) * 1000
    tr["id"] = [0, 0, 1, 2, 2, 0]
    tr["value"] = [1, 0, 1, 1, 0, 1]
    data = encode_davis_words(ev, tr)
    out, otr = decode_davis_words(data)
    assert np.array_equal(out, ev) and np.array_equal(otr, tr)
    w = np.frombuffer(data, "<u2")
    assert np.count_nonzero(w == 0x7001) == int(ev["t"][-1] // 1000 >> 15)
    assert np.count_nonzero((w & 0xF000) == 0x7000) == np.count_nonzero(w == 0x7001)


def test_any_chunking_even_mid_word_gives_the_same_events_and_frames():
    rng = np.random.default_rng(6)
    ev = random_events(20_000, 3_000_000, seed=5)
    img = rng.integers(0, 1023, (260, 346))
    enc = DavisWordEncoder()
    data = (enc.encode(ev[:5000]) + enc.aps_begin(int(ev["t"][5000]) // 1000 + 1)
            + enc.encode(ev[5001:9000]) + enc.aps_end(int(ev["t"][9000]) // 1000, img) + enc.encode(ev[9000:]))
    ref = DavisWordDecoder(aps=True)
    ref_ev, _ = ref.feed(data)
    (frame,) = ref.take_frames()
    assert np.array_equal(ref_ev, np.concatenate([ev[:5000], ev[5001:]]))
    assert frame.image.dtype == np.uint16 and np.array_equal(frame.image, img << 6)
    assert frame.t_start_ns == 1000 * (int(ev["t"][5000]) // 1000 + 1) and frame.t_end_ns == int(ev["t"][9000])
    for _ in range(3):
        cuts = np.sort(rng.integers(0, len(data), 300))
        dec = DavisWordDecoder(aps=True)
        parts, prev = [], 0
        for c in [*cuts, len(data)]:
            parts.append(dec.feed(data[prev:c])[0])
            prev = c
        assert np.array_equal(np.concatenate(parts), ref_ev) and dec.pending_bytes == 0
        (f2,) = dec.take_frames()
        assert np.array_equal(f2.image, frame.image) and f2.t_exposure_end_ns == frame.t_exposure_end_ns
    off = DavisWordDecoder()                                # APS off: words skipped and counted
    assert np.array_equal(off.feed(data)[0], ref_ev) and off.frames == [] and off.aps_words > 2 * 346 * 260


def test_aps_cds_saturation_roi_flip_and_bad_frames_follow_libcaer():
    def frame(reset, signal, roi=None, cols=None):
        w = [0x8000 | 10, 0x0008]
        if roi is not None:
            for v in roi:
                w += [0x5100 | (v >> 8), 0x5200 | (v & 0xFF)]
        nx = len(reset[0]) if cols is None else cols
        for marker, read in ((11, reset), (12, signal)):
            for c in range(nx):
                w += [marker] + [0x4000 | int(read[r][c]) for r in range(len(read))] + [13]
        return w + [0x8000 | 20, 0x000A]
    reset = [[1000, 383, 1000], [900, 900, 500]]
    signal = [[400, 100, 0], [950, 100, 100]]
    roi = (10, 20, 12, 21)                                  # 3 columns x 2 rows at (10, 20)
    dec = DavisWordDecoder(aps=True)
    dec.feed(words(*frame(reset, signal, roi)))
    (f,) = dec.take_frames()
    assert (f.x, f.y, f.image.shape, f.global_shutter) == (10, 20, (2, 3), True)
    assert f.image.tolist() == [[600 << 6, 1023 << 6, 1023 << 6], [0, 800 << 6, 400 << 6]]
    flip = DavisWordDecoder(aps=True, aps_flip_x=True, aps_flip_y=True)
    flip.feed(words(*frame(reset, signal, roi)))
    assert np.array_equal(flip.take_frames()[0].image, f.image[::-1, ::-1])
    dec.feed(words(*frame(reset, signal, None, cols=2)))    # a column short: dropped, as libcaer
    assert dec.take_frames() == [] and dec.bad_frames == 1
    dec.feed(words(0x0001, *frame(reset, signal)[2:]))      # after a timestamp reset, until a frame start
    assert dec.take_frames() == []


def test_encoder_rejects_what_the_words_cannot_carry():
    ev = random_events(10, 1000)
    bad = ev.copy()
    bad["t"][3] += 1
    with pytest.raises(InputError, match="whole microsecond"):
        encode_davis_words(bad)
    bad = ev.copy()
    bad["x"][0] = 346
    with pytest.raises(InputError, match="outside"):
        encode_davis_words(bad)
    enc = DavisWordEncoder()
    enc.encode(ev)
    with pytest.raises(InputError, match="time order"):
        enc.encode(ev[:1])
    with pytest.raises(InputError, match="aps_end without"):
        enc.aps_end(10_000, np.zeros((260, 346), int))
    with pytest.raises(InputError, match="unknown model"):
        DavisWordDecoder(model="DAVIS9000")


def test_streaming_encoder_reset_and_idle_wraps():
    a = random_events(2000, 1_000_000, seed=7)
    b = random_events(2000, 1_000_000, seed=8)
    b["t"] += 5_000_000_000
    enc = DavisWordEncoder()
    data = enc.encode(a) + enc.advance(4_000_000) + enc.encode(b)
    c = random_events(100, 50_000, seed=9)
    data += enc.reset() + enc.encode(c)
    dec = DavisWordDecoder()
    out, _ = dec.feed(data)
    assert np.array_equal(out, np.concatenate([a, b, c])) and dec.resets == 1


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.binary(max_size=4000), st.integers(1, 64), st.booleans())
def test_random_bytes_never_crash_or_hang(data, step, aps):
    dec = DavisWordDecoder(aps=aps)
    n = 0
    for i in range(0, len(data), step):
        ev, tr = dec.feed(data[i:i + step])
        n += ev.size
        assert ev.dtype == EVENT_DTYPE and tr.dtype == TRIGGER_DTYPE
        if ev.size:
            assert int(ev["x"].max()) < 346 and int(ev["y"].max()) < 260
    for f in dec.take_frames():
        assert f.image.size <= 346 * 260
    assert dec.words == len(data) // 2
