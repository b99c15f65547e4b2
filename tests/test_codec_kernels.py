"""The numba kernels behind the EVT codecs: resumable trigger output, encoder output bounds,
error order, one compiled specialisation per kernel, and the no-cache fallback."""

import warnings

import numpy as np
import pytest

from evdnerf_ros.errors import FormatError
from evdnerf_ros.events.codecs import (
    Decoded, DroppedEventsWarning, _common, decode, encode, evt2, evt3, make_decoder, make_encoder,
)
from evdnerf_ros.events.types import make_events, make_triggers
from synthetic_events import synthetic_events, synthetic_triggers

MAX_ID = {"evt3": 16, "evt2": 32}


@pytest.mark.parametrize("enc", ["evt3", "evt2"])
def test_many_triggers_refill_the_kernel_trigger_buffer(enc):
    # far more triggers than the first trigger buffer holds, also across feed() boundaries
    ev = synthetic_events(5_000, duration_us=200_000, seed=21)
    tr = synthetic_triggers(3_000, duration_us=200_000, max_id=MAX_ID[enc])
    data = encode(ev, enc, triggers=tr)
    d = decode(data, enc)
    assert np.array_equal(d.events, ev) and np.array_equal(d.triggers, tr)
    dec = make_decoder(enc)
    parts = [dec.feed(data[a:a + 999]) for a in range(0, len(data), 999)] + [dec.close()]
    got = Decoded.concatenate(parts)
    assert np.array_equal(got.events, ev) and np.array_equal(got.triggers, tr)


@pytest.mark.parametrize("enc", ["evt3", "evt2"])
def test_encoder_output_bound_covers_fillers_across_calls(enc):
    # huge gaps (many filler TIME_HIGH words), a triggers-only call in between
    big = (1 << 36) if enc == "evt2" else (1 << 27)
    a = make_events(np.array([5, 6]) * 1000, [1, 2], [3, 3], [1, -1])
    trig = make_triggers(np.array([big, big + 1]) * 1000, [1, 2], [1, 0])
    b = make_events(np.array([2 * big, 2 * big]) * 1000, [7, 8], [1, 1], [1, 1])
    e = make_encoder(enc)
    blob = e.encode(a) + e.encode(a[:0], trig) + e.encode(b)
    d = decode(blob, enc)
    assert np.array_equal(d.events, np.concatenate([a, b]))
    assert np.array_equal(d.triggers, trig)


def test_evt3_reports_the_first_error_in_stream_order():
    # TIME_HIGH 5 repeated resets the low time bits, so the trigger at word 4 goes backwards;
    # the backwards TIME_HIGH 1 at word 6 comes later and is not the one reported
    w = np.array([0x8005, 0x6010, 0xA101, 0x8005, 0xA100, 0x0001, 0x8001], "<u2")
    with pytest.raises(FormatError, match="EXT_TRIGGER") as ei:
        decode(w.tobytes(), "evt3")
    assert ei.value.offset == 8


def test_evt2_reports_the_first_error_in_stream_order():
    # an event going backwards (word 2) before a backwards TIME_HIGH (word 3)
    w = np.array([(8 << 28) | 10, (1 << 28) | (5 << 22), (1 << 28) | (4 << 22), (8 << 28) | 9],
                 "<u4")
    with pytest.raises(FormatError, match="event time goes backwards") as ei:
        decode(w.tobytes(), "evt2")
    assert ei.value.offset == 8


def test_evt3_dropped_events_counted_per_vector_bit():
    w = np.array([0x8000, 0x0003, 0x4000 | 0b1011, 0x3000 | 4, 0x5000 | 0b11], "<u2")
    with pytest.warns(DroppedEventsWarning, match=r"3 event\(s\)"):
        d = decode(w.tobytes(), "evt3")
    assert d.events["x"].tolist() == [4, 5]


def test_each_kernel_compiles_once_for_all_input_kinds(tmp_path):
    ev = synthetic_events(3_000, seed=22)
    tr = synthetic_triggers(10, duration_us=3_000)
    for enc in ("evt3", "evt2"):
        data = encode(ev, enc, triggers=tr)
        encode(ev[::2], enc)                         # strided events
        arr = np.frombuffer(data, np.uint8)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", DroppedEventsWarning)
            for obj in (data, bytearray(data), memoryview(data), arr, arr.copy(), data[1:-1]):
                try:
                    decode(obj, enc)
                except FormatError:
                    pass
    for fn in (evt3._count_events, evt3._decode, evt3._encode, evt2._decode, evt2._encode,
               _common._scan_us):
        assert len(fn.signatures) == 1, (fn, fn.signatures)


def test_kernel_falls_back_to_no_cache_where_numba_cannot_cache(monkeypatch):
    calls = []
    real = _common.numba.njit

    def njit(**kw):
        calls.append(kw)
        if kw.get("cache"):
            raise RuntimeError("cannot cache function 'f': no locator available for file 'x.py'")
        return real(**kw)

    monkeypatch.setattr(_common.numba, "njit", njit)

    def add_one(x):
        return x + 1

    f = _common.kernel(add_one)
    assert f(41) == 42
    assert calls == [{"cache": True, "nogil": True}, {"nogil": True}]


@pytest.mark.parametrize("enc", ["evt3", "evt2"])
def test_too_small_output_array_is_an_error_not_a_memory_overrun(enc):
    ev = synthetic_events(2_000, duration_us=2_000, burst_fraction=0.9, seed=23)
    data = encode(ev, enc)
    dec = make_decoder(enc)
    out = np.empty(dec.count_events(data) - 1, ev.dtype)
    with pytest.raises(ValueError, match="shorter than count_events"):
        dec._feed_into(data, out)
