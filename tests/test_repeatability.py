"""Run-to-run agreement of repeated takes (evdnerf_ros.session.repeatability, `capture --repeats`)."""

import numpy as np
import pytest

from evdnerf_ros.errors import InputError
from evdnerf_ros.events.types import TRIGGER_DTYPE, make_events
from evdnerf_ros.session.recorder import ViewRecorder
from evdnerf_ros.session.repeatability import best_lag_ms, compare_takes, load_take, repeatability

W, H = 16, 12
SPAN = 200_000_000          # 0.2 s of motion after the trigger
MS = 1_000_000


def _motion(anchor_ns, *, late_ns=0, shift_px=0, seed=0):
    """A bar sweeping the sensor from the trigger on: one event per pixel it enters, plus noise
    before the trigger (which the takes must ignore)."""
    rng = np.random.default_rng(seed)
    t, x, y = [], [], []
    for k in range(W):
        tk = anchor_ns + late_ns + (k + 1) * 10 * MS
        for yy in range(H):
            t.append(tk + yy * 1000)
            x.append((k + shift_px) % W)
            y.append(yy)
    t += list(anchor_ns - 1000 * rng.integers(1, 50_000, 40))    # before the trigger (whole µs)
    x += list(rng.integers(0, W, 40))
    y += list(rng.integers(0, H, 40))
    order = np.argsort(t, kind="stable")
    return make_events(np.asarray(t, np.int64)[order], np.asarray(x)[order], np.asarray(y)[order],
                       np.ones(len(t), np.int8))


def _bag(path, anchor_ns, *, trigger=True, start_stamp=None, **motion):
    ev = _motion(anchor_ns, **motion)
    tr = np.zeros(2 if trigger else 0, TRIGGER_DTYPE)
    if trigger:
        tr["t"] = [anchor_ns, anchor_ns + MS]
        tr["value"] = [1, 0]
    with ViewRecorder(path, width=W, height=H, encoding="evt3") as rec:
        rec.events(ev, tr)
        if start_stamp is not None:
            rec.servo_trigger("START", start_stamp, 0)
    return path


def test_identical_takes_on_different_clocks_agree_exactly(tmp_path):
    a = _bag(tmp_path / "a", 5_000_000_000)
    b = _bag(tmp_path / "b", 9_123_456_000, seed=1)      # another clock, other pre-trigger noise
    rep = repeatability([a, b], span_ns=SPAN, bin_ns=MS, windows=8)
    [row] = rep["takes"]
    assert rep["anchor"] == "trigger" and rep["reference_events"] == W * H
    assert row["rate_corr"] == pytest.approx(1.0) and row["rate_rel_l1"] == 0.0 and row["lag_ms"] == 0.0
    assert row["image_corr"] == pytest.approx(1.0) and row["image_rel_l1"] == 0.0 and row["count_ratio"] == 1.0


def test_a_late_take_shows_its_lag_and_a_moved_scene_its_image_difference(tmp_path):
    a = _bag(tmp_path / "a", 5_000_000_000)
    late = _bag(tmp_path / "late", 7_000_000_000, late_ns=3 * MS)
    moved = _bag(tmp_path / "moved", 8_000_000_000, shift_px=3)
    rep = repeatability([a, late, moved], span_ns=SPAN, bin_ns=MS, windows=8)
    r_late, r_moved = rep["takes"]
    assert r_late["lag_ms"] == 3.0 and r_late["rate_corr"] < 0.5 and r_late["rate_corr_aligned"] == pytest.approx(1.0)
    assert r_moved["lag_ms"] == 0.0 and r_moved["rate_corr"] == pytest.approx(1.0)
    assert r_moved["image_corr"] < 0.5 and r_moved["image_rel_l1"] > 1.0
    assert rep["worst"]["abs_lag_ms"] == 3.0 and rep["worst"]["image_corr"] == r_moved["image_corr"]


def test_a_take_without_trigger_is_aligned_at_its_start_stamp_or_refused(tmp_path):
    a = _bag(tmp_path / "a", 5_000_000_000)
    b = _bag(tmp_path / "b", 6_000_000_000, trigger=False, start_stamp=6_000_000_000)
    take = load_take(b, span_ns=SPAN, bin_ns=MS)
    assert take.anchor == "START" and take.anchor_ns == 6_000_000_000
    assert compare_takes([load_take(a, span_ns=SPAN, bin_ns=MS), take], MS)["takes"][0]["rate_rel_l1"] == 0.0
    c = _bag(tmp_path / "c", 6_000_000_000, trigger=False)
    with pytest.raises(InputError, match=r"c: no trigger edge and no servo START.*trigger input"):
        load_take(c, span_ns=SPAN)


def test_empty_and_bad_inputs(tmp_path):
    a = _bag(tmp_path / "a", 5_000_000_000)
    take = load_take(a, span_ns=SPAN, bin_ns=MS)
    empty = load_take(a, span_ns=SPAN, bin_ns=MS)
    empty.rate[:] = 0
    empty.images[:] = 0
    empty.events = 0
    row = compare_takes([take, empty], MS)["takes"][0]
    assert row["rate_corr"] is None and row["lag_ms"] is None and row["image_corr"] is None   # no variance
    assert row["rate_rel_l1"] == 1.0 and row["count_ratio"] == 0.0
    assert compare_takes([empty, take], MS)["takes"][0]["count_ratio"] is None                 # nothing to divide by
    with pytest.raises(InputError, match="at least 2 takes"):
        compare_takes([take], MS)
    with pytest.raises(InputError, match="bin <= span"):
        load_take(a, span_ns=MS, bin_ns=2 * MS)
    assert best_lag_ms(np.zeros(5), np.ones(5), MS) is None
