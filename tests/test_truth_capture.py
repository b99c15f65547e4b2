"""The true scene of a session captured on the closed-loop virtual rig (eval/truth.py, convert's
``truth`` record): the same scene at the same times as for the simulated session it mirrors,
also through a ``--crop`` of the sensor window the scene sits in.

No rig is needed: a simulated session's session.yaml is rewritten into what
rig.demo_capture.add_truth writes (``source.kind: capture``, ``rig: virtual``, the scene preset,
the twin's supersampling, ``rig.virtual.scene_window``; the per-view ``clock_offset_ns`` means
the same in both: the view clock's reading at scene time 0)."""

import shutil

import numpy as np
import pytest
import yaml

from evdnerf_ros.eval.metrics import event_metrics, protocol_windows
from evdnerf_ros.eval.truth import TrueScene
from evdnerf_ros.events.slicing import window_edges
from evdnerf_ros.io.trainingset import TrainingSet
from evdnerf_ros.session.convert import run_convert

N_WINDOWS = 16
SUPERSAMPLE = 1      # the twin's; the simulation's options say the same, the capture's do not
#: (x, y, w, h) on the 32x24 sensor: even corner, so 2x2 blocks line up with the full sensor's
WINDOW = (6, 2, 22, 20)


def _quiet(*_):
    pass


@pytest.fixture(scope="module")
def sessions(tmp_path_factory):
    """(simulated session, its virtual-rig-capture twin, {view: offset_ns}): offsets are the
    true ones (clock offset + motion start), given to convert directly so that a view without
    a true clock offset still converts."""
    from evdnerf_ros.sim.simulate import SimulationOptions, simulate_session

    tmp = tmp_path_factory.mktemp("truth_capture")
    sim = tmp / "sim"
    simulate_session("fork", sim, SimulationOptions(
        views=2, val_views=0, resolution=(32, 24), frame_rate_hz=0, gt_times=0, supersample=SUPERSAMPLE,
        jobs=1, min_step_ns=2_000_000), log=_quiet)
    cap = tmp / "cap"
    shutil.copytree(sim, cap)
    data = yaml.safe_load((cap / "session.yaml").read_text())
    data["source"] = {"kind": "capture", "software_version": data["source"].get("software_version"),
                      "rig": "virtual", "scene": "fork", "scene_ref": "fork", "supersample": SUPERSAMPLE}
    data["rig"] = dict(data["rig"], virtual={"model": "evk4", "scene_size": list(WINDOW[2:]),
                                             "scene_window": list(WINDOW), "late_trigger_edges": 0})
    # a capture's options are the capture's: no renderer supersampling among them
    data["options"] = {k: v for k, v in (data.get("options") or {}).items() if k != "supersample"}
    (cap / "session.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
    start = int(data["time"]["motion_start_ns"])
    offsets = {v["name"]: int(v["ground_truth"]["clock_offset_ns"]) + start for v in data["views"]}
    return sim, cap, offsets


def _convert(session, out, offsets, **opts) -> TrainingSet:
    run_convert(session, out, offsets=offsets, frames=False, log=_quiet, **opts)
    return TrainingSet(out)


def _true_and_events(ts: TrainingSet) -> tuple[np.ndarray, np.ndarray]:
    """The true scene's and the events' dL of the training views at the protocol windows."""
    truth, why = TrueScene.of(ts)
    assert truth is not None, why
    edges = window_edges(*ts.time_range, N_WINDOWS)
    ks = list(protocol_windows(N_WINDOWS))
    true = np.concatenate([truth.log_change_stack(v, edges, ks) for v in ts.train_views])
    gt = np.concatenate([ts.log_change_stack(v, edges)[ks] for v in ts.train_views])
    return true, gt


def _score(true, gt, ts) -> dict:
    m = event_metrics(true, gt, c_pos=ts.c_pos, c_neg=ts.c_neg)
    return {k: m[k]["psnr"] for k in ("continuous", "quantized", "zero_floor")}


@pytest.mark.parametrize("downsample", [1, 2])
def test_a_virtual_rig_capture_has_the_simulated_sessions_true_scene(sessions, tmp_path, downsample):
    sim, cap, offsets = sessions
    with _convert(sim, tmp_path / "sim.h5", offsets, downsample=downsample) as ref, \
            _convert(cap, tmp_path / "cap.h5", offsets, downsample=downsample) as whole, \
            _convert(cap, tmp_path / "crop.h5", offsets, downsample=downsample, crop=WINDOW) as cropped:
        assert ref.provenance["session_source"]["kind"] == "simulation"
        assert whole.provenance["session_source"]["kind"] == "capture"
        rec = whole.provenance["truth"]
        assert rec == ref.provenance["truth"]
        assert rec["scene"] == "fork" and rec["supersample"] == SUPERSAMPLE
        assert cropped.provenance["truth"] == rec and cropped.provenance["crop"] == list(WINDOW)
        assert ref.time_range == whole.time_range == cropped.time_range

        true_ref, gt_ref = _true_and_events(ref)
        c = max(ref.thresholds)
        moving = np.abs(true_ref) > c
        assert moving.sum() > 50                       # the windows see the fork swing
        # the simulator's events are crossings of the true log image: with the time mapping right
        # the events' dL is within 2 C per source pixel of the truth almost everywhere it moves
        assert np.mean(np.abs(true_ref - gt_ref)[moving] <= 2 * c * downsample ** 2 + 0.05) > 0.95
        score_ref = _score(true_ref, gt_ref, ref)
        assert score_ref["continuous"] > score_ref["zero_floor"] + 1

        true_whole, gt_whole = _true_and_events(whole)
        np.testing.assert_array_equal(gt_whole, gt_ref)
        np.testing.assert_allclose(true_whole, true_ref, rtol=0, atol=1e-6)
        for k, v in _score(true_whole, gt_whole, whole).items():
            assert v == pytest.approx(score_ref[k], rel=1e-9, abs=1e-9), k

        # cropped: the set is the window's size and renders the same scene on the same pixels
        x, y, w, h = (int(a) // downsample for a in WINDOW)
        assert (cropped.width, cropped.height) == (w, h)
        region = (slice(None), slice(y, y + h), slice(x, x + w))
        assert moving[region].sum() > 0.9 * moving.sum()     # the window holds the scene's motion
        true_crop, gt_crop = _true_and_events(cropped)
        assert true_crop.shape == gt_crop.shape == true_ref[region].shape
        np.testing.assert_array_equal(gt_crop, gt_ref[region])
        np.testing.assert_allclose(true_crop, true_ref[region], rtol=0, atol=1e-5)
        score_region = _score(true_ref[region], gt_ref[region], ref)
        for k, v in _score(true_crop, gt_crop, cropped).items():
            assert v == pytest.approx(score_region[k], rel=1e-6, abs=1e-6), k


def test_a_view_without_its_true_clock_offset_gives_no_reference(sessions, tmp_path):
    _, cap, offsets = sessions
    late = tmp_path / "late"
    shutil.copytree(cap, late)
    data = yaml.safe_load((late / "session.yaml").read_text())
    name = data["views"][1]["name"]
    data["views"][1]["ground_truth"]["clock_offset_ns"] = None     # its trigger edge was placed late
    (late / "session.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
    lines = []
    run_convert(late, tmp_path / "late.h5", offsets=offsets, frames=False, crop=WINDOW, log=lines.append)
    with TrainingSet(tmp_path / "late.h5") as ts:
        assert "truth" not in ts.provenance
        truth, why = TrueScene.of(ts)
    assert truth is None
    assert f"no ground_truth.clock_offset_ns for view {name}," in why and "trigger edge late" in why
    assert data["views"][0]["name"] not in why
    assert any(why in line for line in lines)          # convert says so too


def _profile_track(lag_ns: int, step_ns: int = 1_000_000) -> dict:
    """The fork's servo angles every ``step_ns`` over the scene, ``lag_ns`` late (a servo_track)."""
    from evdnerf_ros.sim.scene import load_scene

    scene = load_scene("fork")
    drive = next(o.servo for o in scene.all_objects() if o.servo is not None)
    t = np.arange(scene.start_ns - step_ns, scene.end_ns + 2 * step_ns, step_ns, dtype=np.int64)
    deg = [np.degrees(drive.angle_rad(int(v) - lag_ns)) + drive.zero_deg for v in t]
    return {"scene_ns": [int(v) for v in t], "deg": [float(v) for v in deg]}


def test_the_reference_follows_the_servo_angles_the_twin_rendered(sessions, tmp_path):
    """A view whose servo commands reached the twin late (the firmware in simavr behind the wall
    clock): with each view's ``servo_track`` the reference renders those angles, not the profile."""
    _, cap, offsets = sessions
    lag = 60_000_000
    tracked = tmp_path / "tracked"
    shutil.copytree(cap, tracked)
    data = yaml.safe_load((tracked / "session.yaml").read_text())
    for v in data["views"]:
        v["ground_truth"]["servo_track"] = _profile_track(lag)
    (tracked / "session.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
    with _convert(cap, tmp_path / "cap.h5", offsets) as plain, \
            _convert(tracked, tmp_path / "tracked.h5", offsets) as ts:
        assert "servo_tracks" not in plain.provenance["truth"]
        assert set(ts.provenance["truth"]["servo_tracks"]) == set(ts.views)
        ref_plain, _ = TrueScene.of(plain)
        ref_tracked, _ = TrueScene.of(ts)
        edges = window_edges(*ts.time_range, N_WINDOWS)
        ks = list(protocol_windows(N_WINDOWS))
        view = ts.train_views[0]
        moved = ref_tracked.log_change_stack(view, edges, ks)
        later = ref_plain.log_change_stack(view, edges - lag, ks)
        assert np.abs(later).max() > 1                              # the windows see the fork swing
        np.testing.assert_allclose(moved, later, rtol=0, atol=0.02)
        # and the lag matters: the profile's own reference differs from the tracked one
        assert np.abs(ref_plain.log_change_stack(view, edges, ks) - moved).max() > 0.5


def test_a_malformed_servo_track_names_its_key(sessions, tmp_path):
    from evdnerf_ros.errors import InputError
    from evdnerf_ros.session.layout import load_session

    _, cap, _ = sessions
    bad = tmp_path / "bad"
    shutil.copytree(cap, bad)
    data = yaml.safe_load((bad / "session.yaml").read_text())
    data["views"][0]["ground_truth"]["servo_track"] = {"scene_ns": [0, 20, 10], "deg": [90, 91, 92]}
    (bad / "session.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
    with pytest.raises(InputError, match=r"views\[0\]\.ground_truth\.servo_track: scene_ns must increase"):
        load_session(bad)
    data["views"][0]["ground_truth"]["servo_track"] = {"scene_ns": [0, 20], "deg": [90]}
    (bad / "session.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
    with pytest.raises(InputError, match=r"servo_track\.deg: holds 1 angle for the 2 times of scene_ns"):
        load_session(bad)


def test_a_real_capture_gives_no_reference(sessions, tmp_path):
    """A capture not on the virtual rig knows no scene: no reference, the usual reason."""
    _, cap, offsets = sessions
    real = tmp_path / "real"
    shutil.copytree(cap, real)
    data = yaml.safe_load((real / "session.yaml").read_text())
    data["source"] = {k: v for k, v in data["source"].items() if k != "rig"}
    (real / "session.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
    with _convert(real, tmp_path / "real.h5", offsets) as ts:
        assert "truth" not in ts.provenance and "truth_note" not in ts.provenance
        truth, why = TrueScene.of(ts)
    assert truth is None and "not converted from a simulated session" in why


def test_the_rig_source_counts_stale_renders_per_stream():
    """When the virtual rig's pin harness falls behind (the feed knows the joints only up to an
    earlier time) the camera twin's source renders with the last known angles and counts the
    chunk late, per stream (one per recorded view), so that only that view's truth is withdrawn."""
    import time
    from types import SimpleNamespace

    from rig.camera.virtual.rig_source import RigDrivenSource

    class StalledTrack:                        # a joint the harness never reports beyond its start
        last_ns = None

        def deg(self, t):
            return np.full(np.shape(t), 90.0)

    src = RigDrivenSource("fork", 16, 12, SimpleNamespace(servo=StalledTrack(), turntable=StalledTrack()),
                          rate_hz=125.0, max_wait_s=0.02)
    try:
        src.zero_host_ns = lambda: time.monotonic_ns() - 10**9
        streams = []
        for _ in range(2):
            src.restart()
            streams.append(src.stream)
            deadline = time.monotonic() + 20
            while src.late_by_stream.get(streams[-1], 0) < 2 and time.monotonic() < deadline:
                src.ready_ns(50_000_000)
                time.sleep(0.01)
        assert streams[0] != streams[1]
        assert all(src.late_by_stream.get(s, 0) >= 2 for s in streams), src.late_by_stream
        assert sum(src.late_by_stream.values()) == src.late_renders
    finally:
        src.close()
