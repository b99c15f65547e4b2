import numpy as np
import pytest

from conftest import random_events
from evdnerf_ros.errors import InputError
from evdnerf_ros.events import (EVENT_DTYPE, as_events, counts_from_log_change, event_image,
                                event_rate, log_change_image, log_change_stack, make_events,
                                plot_event_rate, polarity_counts, save_png, signed_counts,
                                signed_to_rgb, sort_events, time_slice, validate_events,
                                window_edges)


def test_event_dtype_is_the_documented_one():
    assert EVENT_DTYPE.names == ("t", "x", "y", "p")
    assert [EVENT_DTYPE[n].str for n in EVENT_DTYPE.names] == ["<i8", "<u2", "<u2", "|i1"]


def test_make_events_accepts_01_polarity():
    ev = make_events([1, 2], [0, 1], [0, 0], np.array([1, 0], np.uint8))
    assert ev["p"].tolist() == [1, -1]


def test_validate_names_first_unsorted_event():
    ev = make_events([0, 5, 3], [0, 0, 0], [0, 0, 0], [1, 1, 1])
    with pytest.raises(InputError, match="my.npz: timestamps not sorted: event 2"):
        validate_events(ev, source="my.npz")


def test_validate_rejects_bad_polarity_and_out_of_bounds():
    ev = make_events([0, 1], [0, 0], [0, 0], [1, 1])
    ev["p"][1] = 0
    with pytest.raises(InputError, match="polarity"):
        validate_events(ev)
    ev = make_events([0, 1], [3, 64], [0, 0], [1, 1])
    with pytest.raises(InputError, match="x=64 outside.*64x48"):
        validate_events(ev, width=64, height=48)
    with pytest.raises(InputError, match="dtype"):
        validate_events(np.zeros(3, [("t", "<f8"), ("x", "<u2"), ("y", "<u2"), ("p", "i1")]))


def test_as_events_rejects_missing_fields():
    with pytest.raises(InputError, match="t, x, y, p"):
        as_events(np.zeros(2, [("t", "<i8"), ("x", "<u2")]))


def test_sort_is_stable():
    ev = make_events([5, 1, 5, 1], [0, 1, 2, 3], [0, 0, 0, 0], [1, 1, 1, 1])
    assert sort_events(ev)["x"].tolist() == [1, 3, 0, 2]


def test_time_slice_half_open_and_equal_to_mask(rng):
    ev = random_events(rng, 20_000, span=10_000)  # many equal timestamps
    for a, b in [(0, 10), (100, 100), (5000, 4000), (-50, 20_000), (1234, 5678)]:
        expect = ev[(ev["t"] >= a) & (ev["t"] < b)]
        assert np.array_equal(time_slice(ev, a, b), expect)


def test_time_slice_int64_extremes():
    big = np.iinfo(np.int64).max
    ev = make_events([-(2 ** 62), 0, 2 ** 62], [0, 0, 0], [0, 0, 0], [1, -1, 1])
    assert len(time_slice(ev, -big - 1, big)) == 3
    assert time_slice(ev, 2 ** 62, big)["t"].tolist() == [2 ** 62]


def test_window_edges_exact_integers():
    e = window_edges(0, 10, 3)
    assert e.tolist() == [0, 3, 6, 10]
    huge = window_edges(10 ** 18, 10 ** 18 + 7, 7)
    assert huge.dtype == np.int64 and np.all(np.diff(huge) == 1)
    with pytest.raises(ValueError):
        window_edges(0, 2, 3)


def test_counts_and_log_change_match_direct_loop(rng):
    ev = random_events(rng, 5000, width=8, height=6)
    n = polarity_counts(ev, 8, 6)
    ref = np.zeros((2, 6, 8), np.int64)
    np.add.at(ref, ((ev["p"] < 0).astype(int), ev["y"], ev["x"]), 1)
    assert np.array_equal(n, ref)
    assert np.array_equal(signed_counts(ev, 8, 6), ref[0] - ref[1])
    dl = log_change_image(ev, 8, 6, 0.25, 0.5)
    assert dl.dtype == np.float32
    np.testing.assert_allclose(dl, 0.25 * ref[0] - 0.5 * ref[1], rtol=1e-6)


def test_log_change_window_and_stack_agree(rng):
    ev = random_events(rng, 20_000, width=16, height=12, span=1_000_000)
    edges = window_edges(100_000, 900_000, 8)
    stack = log_change_stack(ev, edges, 16, 12, 0.2, 0.3)
    for k in range(8):
        one = log_change_image(ev, 16, 12, 0.2, 0.3, edges[k], edges[k + 1])
        np.testing.assert_array_equal(stack[k], one)
    assert stack.sum() == pytest.approx(
        log_change_image(ev, 16, 12, 0.2, 0.3, edges[0], edges[-1]).sum(), rel=1e-5)


@pytest.mark.parametrize("c_pos,c_neg", [(0.0, 0.2), (0.2, -1.0), (np.nan, 0.2), (np.inf, 0.2)])
def test_thresholds_must_be_positive_finite(rng, c_pos, c_neg):
    with pytest.raises(InputError, match="thresholds"):
        log_change_image(random_events(rng, 10), 64, 48, c_pos, c_neg)


def test_extreme_thresholds_and_counts_stay_exact():
    # One pixel with 10 million events (a hot pixel over a long recording) and a tiny C.
    n = 10_000_000
    ev = np.zeros(n, EVENT_DTYPE)
    ev["t"] = np.arange(n)
    ev["p"] = 1
    counts = polarity_counts(ev, 1, 1)
    assert counts[0, 0, 0] == n
    dl = log_change_image(ev, 1, 1, 1e-4, 1e-4)
    assert dl[0, 0] == pytest.approx(1000.0, rel=1e-6)


def test_empty_events_give_zero_images():
    ev = np.empty(0, EVENT_DTYPE)
    assert not log_change_image(ev, 5, 4, 0.2, 0.2).any()
    assert log_change_stack(ev, [0, 10, 20], 5, 4, 0.2, 0.2).shape == (2, 4, 5)
    assert np.all(event_image(ev, 5, 4) == 255)


def test_counts_from_log_change_floor_per_sign():
    d = np.array([0.0, 0.19, 0.2, 0.59, -0.2, -0.61, 1e6])
    assert counts_from_log_change(d, 0.2, 0.3).tolist() == [0, 0, 1, 2, 0, -2, 5_000_000]


def test_event_image_colours(tmp_path):
    ev = make_events([0, 1, 2, 3], [0, 1, 1, 2], [0, 0, 0, 0], [1, -1, -1, 1])
    ev = ev[np.argsort(ev["t"])]
    rgb = event_image(ev, 3, 1)
    assert rgb.shape == (1, 3, 3) and rgb.dtype == np.uint8
    assert rgb[0, 0, 0] > 200 and rgb[0, 0, 2] < 60    # red: positive
    assert rgb[0, 1, 2] > 200 and rgb[0, 1, 0] < 60    # blue: negative
    path = save_png(tmp_path / "img.png", rgb)
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert [p.name for p in tmp_path.iterdir()] == ["img.png"]   # no temp files left


def test_signed_to_rgb_rejects_bad_scale():
    with pytest.raises(InputError):
        signed_to_rgb(np.ones((2, 2)), vmax=np.nan)


def test_event_rate_bins_exact(rng):
    t = np.sort(rng.integers(0, 10_000_000, 50_000))
    edges, counts = event_rate(t, 1_000_000)
    assert edges.dtype == np.int64 and counts.sum() == t.size
    assert np.array_equal(counts, np.histogram(t, bins=edges)[0])
    with pytest.raises(InputError):
        event_rate(t, 0)


def test_event_rate_far_from_zero_keeps_ns():
    t0 = 1_700_000_000_000_000_000  # a Unix-epoch time in ns: float64 would lose ~256 ns
    t = t0 + np.array([0, 1, 999, 1000, 1001], np.int64)
    edges, counts = event_rate(t, 1000)
    assert counts.tolist() == [3, 2] and int(edges[0]) == t0


def test_rate_plot_written(tmp_path, rng):
    t = np.sort(rng.integers(0, 10 ** 9, 1000))
    p = plot_event_rate(tmp_path / "rate.png", {"a": event_rate(t, 10 ** 7), "b": event_rate(t, 10 ** 8)})
    assert p.stat().st_size > 1000
