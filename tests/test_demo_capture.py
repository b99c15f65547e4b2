"""`evdnerf demo --source`: the demo's session captured on the closed-loop virtual rig (the
`evdnerf.session_sources` entry point, rig.demo_capture), or simulated; auto falls back with a
reason, and a virtual rig that cannot run is a clear error naming what is missing."""

import json
import subprocess
import sys

import numpy as np
import pytest
import yaml

from evdnerf_ros.cli import main
from evdnerf_ros.demo import choose_source
from evdnerf_ros.errors import InputError


EVDNERF = [sys.executable, "-m", "evdnerf_ros"]


def _need_rig():
    from rig.demo_capture import availability

    ok, why = availability()
    if not ok:
        pytest.skip(why)


def test_demo_captures_its_session_on_the_virtual_rig(tmp_path, rig_lock):
    """Capture -> round trip -> sync (checked against the twin's truth) -> convert (cropped to the
    scene's window) -> short training -> eval and report, on the rig's session."""
    _need_rig()
    out = tmp_path / "demo"
    # a CI-sized budget in iterations (the same field on a busy machine, later)
    r = subprocess.run(EVDNERF + ["demo", "-o", str(out), "--source", "virtual-rig", "--train-iterations", "300"],
                       capture_output=True, text=True, timeout=420)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    assert "session source: virtual-rig" in r.stdout
    assert "moving-camera view: skipped" in r.stdout

    doc = yaml.safe_load((out / "session" / "session.yaml").read_text())
    assert doc["source"]["kind"] == "capture" and doc["source"]["rig"] == "virtual"
    assert doc["source"]["scene"] == "fork" and doc["rig"]["kind"] == "turntable"
    views = doc["views"]
    from rig.demo_capture import VAL_EVERY, VIEWS

    assert len(views) == VIEWS == 25
    assert [v["split"] for v in views] == ["val" if i % VAL_EVERY == VAL_EVERY - 1 else "train" for i in range(VIEWS)]
    assert views[-1]["split"] == "train"       # no validation view beyond the last training view
    assert all(v["complete"] and v["events"] > 100 for v in views)
    # the true clock offsets come from the twin (every trigger edge placed on time on an idle
    # machine); sync by trigger finds each view's START within the sensor's microsecond
    motion_start = doc["time"]["motion_start_ns"]
    assert motion_start == doc["servo"]["start_ns_scene"] == 100_000_000
    # (a busy machine can make the twin place an edge late: that view then has no true offset,
    # and the rig says so)
    truth = {v["name"]: (v["ground_truth"] or {}).get("clock_offset_ns") for v in views}
    placed = {k: t for k, t in truth.items() if t is not None}
    late = doc["rig"]["virtual"]["late_trigger_edges"]
    assert len(placed) >= 3 and len(placed) + late >= len(views), [v["ground_truth"] for v in views]
    for v in views:
        assert v["sync"]["method"] == "trigger"
        if truth[v["name"]] is not None:
            assert abs(v["sync"]["offset_ns"] - truth[v["name"]] - motion_start) <= 1000
    # the views' clocks differ (separate recordings seconds apart): the check is not of a constant
    assert len({t // 10**9 for t in placed.values()}) == len(placed)

    summary = json.loads((out / "summary.json").read_text())
    assert summary["source"] == "virtual-rig" and summary["views"] == VIEWS
    assert all(v["bit_exact"] for v in summary["round_trips"].values())
    assert set(summary["sync_error_us"]) == set(placed) and all(abs(e) <= 1.0 for e in summary["sync_error_us"].values())

    x, y, w, h = doc["rig"]["virtual"]["scene_window"]
    from evdnerf_ros.io.trainingset import TrainingSet

    with TrainingSet(out / "train.h5") as ts:
        assert (ts.width, ts.height) == (w, h) and len(ts.views) == VIEWS and len(ts.val_views) == VIEWS // VAL_EVERY
        assert ts.provenance["crop"] == [x, y, w, h]
        assert ts.provenance["session_source"]["kind"] == "capture"
        # the demo's sensitive biases: the twin's thresholds follow the driver's bias model
        from rig.camera.evk4 import BASE_THRESHOLD, thresholds_from_biases
        from rig.demo_capture import BIASES

        sensitive = thresholds_from_biases(BIASES["bias_diff_on"], BIASES["bias_diff_off"])
        assert max(sensitive) < 0.75 * BASE_THRESHOLD
        assert ts.thresholds == pytest.approx(sensitive, rel=1e-6)
        truth = ts.provenance.get("truth")
        if truth is not None:          # every trigger edge placed on time
            grid = truth["render_grid"]
            assert grid["period_ns"] == doc["rig"]["virtual"]["frame_ns"] == 8_000_000
            assert set(grid["scene_ns"]) == set(ts.views)
            from evdnerf_ros.eval.truth import TrueScene
            from evdnerf_ros.events.slicing import window_edges

            # a recording that can show a model is right: the true scene leads the all-zero floor
            # by >= 3 dB on every validation view, at the trained windows and at 4x finer ones
            reference, why = TrueScene.of(ts)
            assert reference is not None, why
            for n in (32, 128):
                edges = window_edges(*ts.time_range, n)
                for view in ts.val_views:
                    gt = ts.log_change_stack(view, edges).astype(np.float64)
                    true = reference.log_change_stack(view, edges, range(n))
                    lead_db = 10 * np.log10(np.sum(gt ** 2) / np.sum((true - gt) ** 2))
                    assert lead_db >= 3.0, (view, n, lead_db)
    t = summary["training"]
    assert t["iterations"] == 300 and t["stopped_by"] == "iterations"
    assert np.isfinite(t["val_events_psnr"]) and np.isfinite(t["val_x4_events_psnr"])
    # the product: the learned simulator's events along a path no view saw, in a bag, scored
    pub = summary["published"]
    assert pub["scored"] and pub["events"] > 0 and pub["true_events"] > 0
    assert pub["true_render_psnr"] > pub["zero_floor_psnr"] + 3
    assert pub["split"]["moving_parts"]["true_events"] > 0
    assert "moving_events_psnr" not in t
    for picture in ("event_images.png", "event_rates.png", "session/sync.png", "run/eval_events.png",
                    "report/report.png"):
        assert (out / picture).is_file(), picture


def test_auto_falls_back_to_simulate_and_says_why(monkeypatch):
    import rig.virtual_arduino as va

    monkeypatch.setattr(va, "missing_tools", lambda: ["simavr", "libsimavr-dev"])
    chosen = choose_source("auto")
    assert chosen.name == "simulate"
    assert chosen.why.startswith("auto: the virtual rig cannot run here") and "simavr" in chosen.why
    assert choose_source("simulate").why == "--source simulate"
    with pytest.raises(InputError, match=r"--source virtual-rig: .*simavr libsimavr-dev.*apt-get install"):
        choose_source("virtual-rig")


def test_auto_without_the_rig_package_falls_back(monkeypatch):
    import importlib.metadata

    monkeypatch.setattr(importlib.metadata, "entry_points", lambda **_: [])
    chosen = choose_source("auto")
    assert chosen.name == "simulate" and "evdnerf.session_sources" in chosen.why
    with pytest.raises(InputError, match="no session source 'virtual-rig' is installed.*pip install"):
        choose_source("virtual-rig")


def test_auto_takes_the_rig_where_it_runs():
    _need_rig()
    chosen = choose_source("auto")
    assert chosen.name == "virtual-rig" and "umockdev" in chosen.why


def test_virtual_rig_source_unavailable_is_a_clear_cli_error(tmp_path, monkeypatch, capsys):
    from rig.camera.virtual import usb

    monkeypatch.setattr(usb, "umockdev_available", lambda: (False, "libumockdev-preload.so.0 not found; "
                                                                   + usb.INSTALL_HINT))
    assert main(["demo", "-o", str(tmp_path / "d"), "--source", "virtual-rig"]) == 2
    err = capsys.readouterr().err
    assert "evdnerf: error: demo --source virtual-rig" in err and "apt-get install umockdev" in err
    assert not (tmp_path / "d").exists()                 # nothing written before the source is known
