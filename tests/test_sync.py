"""`evdnerf sync`: per-view origins from trigger edges, START messages and event-rate curves,
checked against the clock offsets the simulator injected."""

import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml

from evdnerf_ros.errors import InputError
from evdnerf_ros.events.types import make_events
from evdnerf_ros.io.messages import time_reference
from evdnerf_ros.io.rosbag2 import BagWriter, open_bag, read_events
from evdnerf_ros.session.layout import load_session
from evdnerf_ros.sim.perturb import perturb_session
from evdnerf_ros.session.onset import correlate_onsets, detect_onset, hot_pixels
from evdnerf_ros.session.sync import run_sync
from evdnerf_ros.sim.scene import preset_path
from evdnerf_ros.sim.simulate import SimulationOptions, simulate_session

SIM = SimulationOptions(views=3, val_views=1, resolution=(48, 36), frame_rate_hz=0, gt_times=0,
                        supersample=1, jobs=1, min_step_ns=2_000_000)
QUIET = dict(log=None)
US = 1_000


def _relative_errors(result, session_dir) -> dict[str, int]:
    """(offset_v - offset_ref) - (clock_offset_v - clock_offset_ref), ns, per view."""
    data = yaml.safe_load((Path(session_dir) / "session.yaml").read_text())
    gt = {v["name"]: v["ground_truth"]["clock_offset_ns"] for v in data["views"]}
    ref = result["sync"]["reference_view"]
    off = {n: r["offset_ns"] for n, r in result["views"].items()}
    return {n: (off[n] - off[ref]) - (gt[n] - gt[ref]) for n in gt}


def _copy(src, dst) -> Path:
    shutil.copytree(src, dst)
    return Path(dst)


@pytest.fixture(scope="module")
def fork(tmp_path_factory):
    """The rig's servo scene: EXT_TRIGGER edges and START/DONE messages in every view."""
    out = tmp_path_factory.mktemp("sync") / "fork"
    simulate_session("fork", out, SIM, log=lambda *_: None)
    return out


@pytest.fixture(scope="module")
def jet(tmp_path_factory):
    """Jet-Down with a quiet lead-in (the preset starts moving at t = 0, i.e. when the
    recording starts, and a recording must begin before the motion), recorded by a rig
    without a trigger cable (the simulator's trigger edges dropped) and without a servo, so
    sync can only use the event rate."""
    base = tmp_path_factory.mktemp("sync")
    scene = yaml.safe_load(Path(preset_path("jet-down")).read_text())
    scene["time"] = {"start_s": 0.0, "end_s": 1.25}
    for o in scene["objects"]:
        for kf in (o.get("motion") or {}).get("keyframes", []):
            kf["t_s"] = round(kf["t_s"] + 0.15, 6)
    path = base / "jet-down-lead.yaml"
    path.write_text(yaml.safe_dump(scene))
    simulate_session(str(path), base / "jet_trigger", SIM, log=lambda *_: None)
    return perturb_session(base / "jet_trigger", base / "jet", drop_triggers=True)


@pytest.fixture(scope="module")
def noisy_jet(jet, tmp_path_factory):
    """The jet session with background noise (2 Hz per pixel), 3 hot pixels at 1 kHz, two
    bursts of pre-motion jitter, and recordings that start at random sub-ms moments."""
    out = tmp_path_factory.mktemp("sync") / "noisy_jet"
    return perturb_session(jet, out, noise_hz=2.0, hot=3, hot_rate_hz=1000.0, bursts=2,
                           lead_ns=20_000_000, seed=7)


# --------------------------------------------------------------------------- trigger / START


def test_trigger_sync_is_exact(fork, tmp_path):
    s = _copy(fork, tmp_path / "s")
    res = run_sync(s, **QUIET)
    assert res["sync"]["methods_used"] == ["trigger"]
    assert res["sync"]["reference_view"] == "view_00"
    errs = _relative_errors(res, s)
    # Trigger edges are stamped by the sensor on its whole-microsecond tick.
    assert all(abs(e) < US for e in errs.values()), errs
    for name, rec in res["views"].items():
        assert rec["method"] == "trigger" and rec["confidence"] == 1.0
        est = rec["estimates"]
        assert est["trigger"] == rec["offset_ns"] and est["start"] is not None
        # The firmware's START message agrees with the trigger edge to the microsecond.
        assert abs(est["start"] - est["trigger"]) < US
        assert rec["excluded_hot_pixels"] == 0
    # The rate estimates exist too, and how far they disagree is reported in µs.
    assert res["sync"]["max_disagreement_us"] == max(r["disagreement_us"] for r in res["views"].values())
    assert res["sync"]["max_disagreement_us"] > 0
    assert (s / "sync.png").stat().st_size > 0


def test_start_message_sync_is_exact(fork, tmp_path):
    s = _copy(fork, tmp_path / "s")
    res = run_sync(s, method="start", **QUIET)
    assert res["sync"]["methods_used"] == ["start"]
    errs = _relative_errors(res, s)
    assert all(e == 0 for e in errs.values()), errs     # host stamps are exact ns in the sim


def test_auto_prefers_start_when_the_trigger_line_is_missing(fork, tmp_path):
    s = perturb_session(fork, tmp_path / "s", drop_triggers=True, seed=1)
    res = run_sync(s, **QUIET)
    assert res["sync"]["methods_used"] == ["start"]
    assert all(r["estimates"]["trigger"] is None for r in res["views"].values())
    assert all(abs(e) < US for e in _relative_errors(res, s).values())


def test_mixed_methods_refer_to_one_instant(fork, tmp_path):
    # view_01 lost its trigger and START: it is synced by rate, corrected by the median
    # (rate - trigger) difference of the views that have both.
    s = perturb_session(fork, tmp_path / "s", static_views=(), seed=2)
    _strip_servo_sources(s, "view_01")
    res = run_sync(s, **QUIET)
    methods = {n: r["method"] for n, r in res["views"].items()}
    assert methods == {"view_00": "trigger", "view_01": "rate", "view_02": "trigger", "val_00": "trigger"}
    assert "rate" in res["sync"]["method_bias_ns"]
    # The fork starts with a minimum-jerk profile (no sudden onset): rate-based sync of it
    # is good to a few ms only, which is what the disagreement shows.
    err = abs(_relative_errors(res, s)["view_01"])
    assert err < 50_000_000


# --------------------------------------------------------------------------- event rate


def test_rate_sync_recovers_injected_offsets(jet, tmp_path):
    s = _copy(jet, tmp_path / "s")
    onset = _relative_errors(run_sync(s, method="onset", **QUIET), s)
    assert all(abs(e) <= 1_000_000 for e in onset.values()), onset           # one bin
    res = run_sync(s, method="rate", **QUIET)
    refined = _relative_errors(res, s)
    assert all(abs(e) <= 100 * US for e in refined.values()), refined
    assert all(r["quality"]["refined"] for r in res["views"].values())


def test_rate_sync_with_noise_hot_pixels_and_jitter(noisy_jet, tmp_path):
    s = _copy(noisy_jet, tmp_path / "s")
    res = run_sync(s, **QUIET)                                    # auto: nothing better here
    assert res["sync"]["methods_used"] == ["rate"]
    refined = _relative_errors(res, s)
    assert all(abs(e) <= 100 * US for e in refined.values()), refined
    for rec in res["views"].values():
        assert rec["excluded_hot_pixels"] == 3                    # exactly the injected ones
        assert rec["excluded_hot_events"] > 1000
        assert 0 < rec["confidence"] <= 1
        assert rec["quality"]["onset_snr"] > 8
        assert rec["estimates"]["trigger"] is None and rec["estimates"]["start"] is None
    onset = _relative_errors(run_sync(s, method="onset", **QUIET), s)
    assert all(abs(e) <= 1_000_000 for e in onset.values()), onset


@pytest.mark.parametrize("bin_ns", [200_000, 5_000_000])
def test_rate_sync_other_bins(noisy_jet, tmp_path, bin_ns):
    s = _copy(noisy_jet, tmp_path / "s")
    onset = _relative_errors(run_sync(s, method="onset", bin_ns=bin_ns, **QUIET), s)
    assert all(abs(e) <= max(bin_ns, 1_000_000) for e in onset.values()), onset
    refined = _relative_errors(run_sync(s, bin_ns=bin_ns, **QUIET), s)
    assert all(abs(e) <= 100 * US for e in refined.values()), refined


def test_no_refine_uses_the_onset(noisy_jet, tmp_path):
    s = _copy(noisy_jet, tmp_path / "s")
    res = run_sync(s, refine=False, **QUIET)
    assert res["sync"]["methods_used"] == ["onset"]
    assert all(r["estimates"]["rate_refined"] is None for r in res["views"].values())
    with pytest.raises(InputError, match="refinement"):
        run_sync(s, method="rate", refine=False, **QUIET)


def test_reference_view_option(noisy_jet, tmp_path):
    s = _copy(noisy_jet, tmp_path / "s")
    res = run_sync(s, reference_view="view_02", **QUIET)
    assert res["sync"]["reference_view"] == "view_02"
    assert res["views"]["view_02"]["quality"]["correlation_peak"] == 1.0
    assert all(abs(e) <= 100 * US for e in _relative_errors(res, s).values())
    with pytest.raises(InputError, match="no view 'nope'"):
        run_sync(s, reference_view="nope", **QUIET)


# --------------------------------------------------------------------------- session.yaml


def test_session_yaml_round_trip_keeps_everything_else(fork, tmp_path):
    s = _copy(fork, tmp_path / "s")
    before = yaml.safe_load((s / "session.yaml").read_text())
    bags_before = {p: p.read_bytes() for p in s.glob("*/*.mcap")}
    plot = tmp_path / "aligned.png"
    res = run_sync(s, plot_path=plot, **QUIET)
    assert plot.stat().st_size > 0 and not (s / "sync.png").exists()
    after = yaml.safe_load((s / "session.yaml").read_text())
    top = after.pop("sync")
    assert top == res["sync"]
    assert set(top) >= {"reference_view", "bin_ns", "method", "max_disagreement_us", "software_version"}
    for v in after["views"]:
        rec = v.pop("sync")
        assert rec == res["views"][v["name"]]
        assert set(rec) >= {"offset_ns", "method", "confidence", "estimates", "excluded_hot_pixels"}
        assert set(rec["estimates"]) == {"trigger", "start", "rate_onset", "rate_refined"}
        assert isinstance(rec["offset_ns"], int)
    assert after == before                                       # nothing else changed
    assert {p: p.read_bytes() for p in s.glob("*/*.mcap")} == bags_before   # bags untouched
    session = load_session(s)
    assert session.view("view_01").sync["offset_ns"] == res["views"]["view_01"]["offset_ns"]
    # Syncing again replaces the records (and still keeps the rest).
    res2 = run_sync(s, method="start", **QUIET)
    again = yaml.safe_load((s / "session.yaml").read_text())
    assert again["sync"]["method"] == "start" and res2["sync"]["methods_used"] == ["start"]
    again.pop("sync")
    for v in again["views"]:
        v.pop("sync")
    assert again == before


# --------------------------------------------------------------------------- bad input


def test_no_onset_names_the_view_and_saves_its_rate_plot(jet, tmp_path):
    s = perturb_session(jet, tmp_path / "s", noise_hz=2.0, static_views=("view_01",), seed=3)
    yaml_before = (s / "session.yaml").read_bytes()
    with pytest.raises(InputError, match="view_01") as exc:
        run_sync(s, **QUIET)
    plot = s / "sync_rate_view_01.png"
    assert str(plot) in str(exc.value) and "no motion onset" in str(exc.value)
    assert plot.stat().st_size > 0
    assert (s / "session.yaml").read_bytes() == yaml_before      # nothing else written
    assert not (s / "sync.png").exists()
    assert "sync this view by trigger/START" in str(exc.value)
    # the same view alone: a session of one view needs no sync, and the message says so
    data = yaml.safe_load(yaml_before)
    data["views"] = [v for v in data["views"] if v["name"] == "view_01"]
    (s / "session.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
    with pytest.raises(InputError, match=r"needs no sync: `evdnerf convert .*` takes its first event as t = 0"):
        run_sync(s, **QUIET)


def test_static_view_is_fine_when_a_better_source_exists(fork, tmp_path):
    # No onset is needed where a trigger edge says when the motion started.
    s = _copy(fork, tmp_path / "s")
    _replace_events(s, "val_00", keep_servo=True)
    res = run_sync(s, **QUIET)
    assert res["views"]["val_00"]["method"] == "trigger"
    assert res["views"]["val_00"]["estimates"]["rate_onset"] is None


def test_forced_method_that_a_view_lacks(jet, tmp_path):
    s = _copy(jet, tmp_path / "s")
    with pytest.raises(InputError, match="view view_00 has no trigger estimate"):
        run_sync(s, method="trigger", **QUIET)
    assert not (s / "sync.png").exists()


def test_origin_outside_the_recording(fork, tmp_path):
    s = _copy(fork, tmp_path / "s")
    _strip_servo_sources(s, "view_02", start_stamp_shift_ns=30_000_000_000)
    before = (s / "session.yaml").read_bytes()
    with pytest.raises(InputError, match=r"view view_02: the start origin .* outside the view's recording"):
        run_sync(s, method="start", **QUIET)
    assert (s / "session.yaml").read_bytes() == before


def test_missing_events_topic_is_named(fork, tmp_path):
    s = _copy(fork, tmp_path / "s")
    with pytest.raises(InputError, match="/no/such/events"):
        run_sync(s, events_topic="/no/such/events", **QUIET)


@pytest.mark.parametrize("kw,match", [
    (dict(method="best"), "sync: --method"), (dict(bin_ns=0), "sync: --bin"), (dict(k=float("nan")), "sync: k:"),
    (dict(min_correlation=2.0), "sync: min_correlation"),
])
def test_bad_options(fork, kw, match):
    with pytest.raises(InputError, match=match):
        run_sync(fork, **kw, **QUIET)


# --------------------------------------------------------------------------- building blocks


def test_hot_pixels_are_steady_outliers(rng):
    w, h, span = 32, 24, 1_000_000_000
    n = 20_000
    noise = make_events(np.sort(rng.integers(0, span, n)), rng.integers(0, w, n), rng.integers(0, h, n),
                        np.ones(n, np.int8))
    hot_t = np.arange(0, span, 1_000_000)                          # 1 kHz, all the time
    hot = make_events(hot_t, np.full(hot_t.size, 5), np.full(hot_t.size, 7), np.ones(hot_t.size, np.int8))
    # A busy motion pixel: as many events, but only while something moves past it.
    mt = np.sort(rng.integers(400_000_000, 600_000_000, 1000))
    motion = make_events(mt, np.full(mt.size, 20), np.full(mt.size, 10), np.ones(mt.size, np.int8))
    ev = np.concatenate([noise, hot, motion])
    ev = ev[np.argsort(ev["t"], kind="stable")]
    assert hot_pixels(ev, w, h, 0, span).tolist() == [7 * w + 5]
    assert hot_pixels(ev[:0], w, h, 0, span).size == 0


def _poisson_curve(rng, rate_per_bin):
    return rng.poisson(rate_per_bin)


def test_detect_onset_floor_jitter_and_several_peaks(rng):
    bin_ns = 1_000_000
    rate = np.full(600, 3.0)                   # noise floor
    rate[100:103] = 80.0                       # pre-motion jitter: a short burst
    rate[250:400] = 20.0                       # the motion ...
    rate[450:500] = 60.0                       # ... and a later, higher peak
    counts = _poisson_curve(rng, rate)
    edges = bin_ns * np.arange(601, dtype=np.int64)
    on, why = detect_onset(counts, edges, sustain_bins=4, windows=5, quiet_bins=50)
    assert why == "" and abs(on.t_ns - 250 * bin_ns) <= bin_ns
    assert on.snr > 8 and on.floor.per_bin == pytest.approx(3.0, abs=1.0)


def test_detect_onset_failures(rng):
    edges = 1_000_000 * np.arange(501, dtype=np.int64)
    on, why = detect_onset(_poisson_curve(rng, np.full(500, 3.0)), edges)
    assert on is None and "no sustained rise" in why
    moving = np.full(500, 3.0)
    moving[:300] = 40.0                         # already moving when the recording starts
    on, why = detect_onset(_poisson_curve(rng, moving), edges)
    assert on is None and "lead-in" in why
    on, why = detect_onset(np.zeros(500, np.int64), edges)
    assert on is None and "no events" in why


def test_correlate_onsets_recovers_a_sub_bin_shift(rng):
    """Two views of one motion: different gains and noise, a shift of 237 µs."""
    shift = 237_000
    t_on = 100_000_000
    def view(gain, t0):
        parts = [rng.integers(0, 200_000_000, 2000)]                     # floor
        n = int(gain * 300)
        # the rate jumps at the onset, then decays (the same shape in both views)
        parts.append(t0 + rng.exponential(15_000_000, n).astype(np.int64))
        return np.sort(np.concatenate(parts))
    t_ref = view(30.0, t_on)
    t_v = view(12.0, t_on + shift)
    lag, peak, inside = correlate_onsets(t_ref, t_on, t_v, t_on, fine_ns=100_000, pre_ns=3_000_000,
                                         post_ns=20_000_000, search_ns=1_500_000, smooth_bins=1.0)
    assert inside and peak > 0.5
    assert abs(lag - shift) < 100_000     # Poisson noise on the shape limits it (~35 µs typical)


# --------------------------------------------------------------------------- helpers


def _strip_servo_sources(session_dir, view, *, start_stamp_shift_ns=None):
    """Rewrite one view's bag without its trigger edges and START message, or (with a
    shift) with a START message whose header stamp lies that far from the original."""
    data = yaml.safe_load((Path(session_dir) / "session.yaml").read_text())
    topic = data["servo"]["trigger"]
    bag_dir = Path(session_dir) / view
    stream = read_events(bag_dir)
    with open_bag(bag_dir) as bag:
        msgs = list(bag.messages())
        starts = [(m.t_ns, bag.deserialize(m.data, m.msgtype)) for m in msgs if m.topic == topic]
    tmp = bag_dir.with_name(view + ".new")
    with BagWriter(tmp) as out:
        for m in msgs:
            if m.topic not in (topic, stream.topic):
                out.write_raw(m.topic, m.msgtype, m.data, m.t_ns)
        if start_stamp_shift_ns is not None:
            for t_ns, msg in starts:
                stamp = t_ns + start_stamp_shift_ns
                ref = msg.time_ref.sec * 1_000_000_000 + msg.time_ref.nanosec
                out.write(topic, "sensor_msgs/msg/TimeReference", time_reference(stamp, ref, msg.source), t_ns)
        out.write_events(stream.topic, stream.events, width=stream.width, height=stream.height,
                         triggers=stream.triggers if start_stamp_shift_ns is not None else None)
    shutil.rmtree(bag_dir)
    tmp.rename(bag_dir)


def _replace_events(session_dir, view, *, keep_servo):
    """A view whose camera saw nothing move: only a few scattered noise events."""
    bag_dir = Path(session_dir) / view
    stream = read_events(bag_dir)
    with open_bag(bag_dir) as bag:
        msgs = list(bag.messages())
        b0, b1 = bag.start_ns, bag.end_ns
    rng = np.random.default_rng(0)
    t = np.sort(rng.integers(b0 // 1000, b1 // 1000, 300)) * 1000
    ev = make_events(t, rng.integers(0, stream.width, t.size), rng.integers(0, stream.height, t.size),
                     np.ones(t.size, np.int8))
    tmp = bag_dir.with_name(view + ".new")
    with BagWriter(tmp) as out:
        for m in msgs:
            if m.topic != stream.topic:
                out.write_raw(m.topic, m.msgtype, m.data, m.t_ns)
        out.write_events(stream.topic, ev, width=stream.width, height=stream.height,
                         triggers=stream.triggers if keep_servo else None)
    shutil.rmtree(bag_dir)
    tmp.rename(bag_dir)


def test_every_simulated_session_syncs_by_its_trigger(tmp_path, capsys):
    """`evdnerf simulate jet-down` (no servo, moving from t = 0) used to make a session that
    `evdnerf sync` could not align (no onset, no trigger): the virtual camera now records an
    EXT_TRIGGER pulse at the start of the motion in every view, as a rig's trigger cable does."""
    from evdnerf_ros.cli import main
    from evdnerf_ros.sim.scene import load_scene

    out = tmp_path / "jet"
    assert main(["simulate", "jet-down", "-o", str(out), "--views", "2", "--resolution", "16", "16",
                 "--supersample", "1", "--frame-rate", "0", "--gt-times", "0", "--jobs", "1",
                 "--min-step", "5ms", "--max-step", "20ms"]) == 0
    data = yaml.safe_load((out / "session.yaml").read_text())
    assert data["servo"] is None and len(data["views"]) == 4           # 2 training + 2 validation
    m0 = load_scene("jet-down").motion_span_ns()[0]
    for v in data["views"]:
        off = v["ground_truth"]["clock_offset_ns"]
        tr = read_events(out / v["bag"]).triggers
        assert tr["t"].tolist() == [(m0 + off) // US * US, (m0 + 1_000_000 + off) // US * US]
        assert tr["value"].tolist() == [1, 0] and v["trigger_events"] == 2
    capsys.readouterr()
    assert main(["sync", str(out)]) == 0
    synced = yaml.safe_load((out / "session.yaml").read_text())
    assert synced["sync"]["methods_used"] == ["trigger"]
    gt = {v["name"]: v["ground_truth"]["clock_offset_ns"] for v in synced["views"]}
    off = {v["name"]: v["sync"]["offset_ns"] for v in synced["views"]}
    ref = synced["sync"]["reference_view"]
    assert all(abs((off[n] - off[ref]) - (gt[n] - gt[ref])) < US for n in gt), (off, gt)
