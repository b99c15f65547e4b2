"""The `evdnerf` command-line contracts: convert-events, info, render-events, demo."""

import json
import subprocess
import sys
import time

import numpy as np
import pytest

from conftest import random_events
from evdnerf_ros.cli import main
from evdnerf_ros.events import make_triggers
from evdnerf_ros.io.event_files import read_event_file
from evdnerf_ros.io.npz import write_npz
from evdnerf_ros.io.rosbag2 import BagWriter


def _us_grid_events(rng, n=20_000, width=64, height=48):
    ev = random_events(rng, n, width, height, t0=1_000_000, span=3_000_000_000)
    ev["t"] -= ev["t"] % 1000  # EVT formats carry whole microseconds
    return ev


@pytest.fixture
def npz_input(tmp_path, rng):
    ev = _us_grid_events(rng)
    tr = make_triggers([ev["t"][10], ev["t"][999]], [0, 0], [1, 0])
    path = tmp_path / "in.npz"
    write_npz(path, ev, 64, 48, tr)
    return path, ev, tr


@pytest.mark.parametrize("out_name,encoding,keeps_triggers", [
    ("a.raw", None, True), ("b.raw", "evt2", True), ("c.h5", None, True), ("d", None, True),
    ("e.mcap", "mono", False), ("f.db3", "array", False), ("g.bag", None, False),
])
def test_convert_events_round_trip(tmp_path, npz_input, out_name, encoding, keeps_triggers):
    src, ev, tr = npz_input
    args = ["convert-events", str(src), str(tmp_path / out_name)]
    if encoding:
        args += ["--encoding", encoding]
    if not keeps_triggers:
        # Trigger events cannot travel in these encodings: the CLI must refuse, not drop them.
        assert main(args) == 2
        assert not (tmp_path / out_name).exists()
        src2 = tmp_path / "no_triggers.npz"
        write_npz(src2, ev, 64, 48)
        args[1] = str(src2)
    assert main(args) == 0
    back = read_event_file(tmp_path / out_name)
    assert np.array_equal(back.events, ev) and (back.width, back.height) == (64, 48)
    if keeps_triggers:
        assert np.array_equal(back.triggers, tr)
    # ... and back again to npz through the CLI, from the converted file.
    assert main(["convert-events", str(tmp_path / out_name), str(tmp_path / "again.npz")]) == 0
    assert np.array_equal(read_event_file(tmp_path / "again.npz").events, ev)


def test_convert_events_custom_topic(tmp_path, rng, capsys):
    ev = _us_grid_events(rng, 1000)
    write_npz(tmp_path / "in.npz", ev, 64, 48)
    assert main(["convert-events", str(tmp_path / "in.npz"), str(tmp_path / "bag"),
                 "--out-topic", "/cam0/events"]) == 0
    # the only event topic is taken without --topic ...
    assert main(["convert-events", str(tmp_path / "bag"), str(tmp_path / "x.npz")]) == 0
    assert main(["convert-events", str(tmp_path / "bag"), str(tmp_path / "y.npz"),
                 "--topic", "/cam0/events"]) == 0
    assert np.array_equal(read_event_file(tmp_path / "x.npz").events, ev)
    # ... and among several, --topic is required and the error lists them
    with BagWriter(tmp_path / "two") as w:
        for topic in ("/a/events", "/b/events"):
            w.write_events(topic, ev, width=64, height=48)
    assert main(["convert-events", str(tmp_path / "two"), str(tmp_path / "z.npz")]) == 2
    err = capsys.readouterr().err
    assert "/a/events" in err and "/b/events" in err and "--topic" in err


def test_convert_errors_are_one_line_exit_2(tmp_path, npz_input, capsys):
    src, ev, _ = npz_input
    (tmp_path / "exists.h5").write_bytes(b"")
    cases = [
        ([str(src), str(tmp_path / "exists.h5")], "exists.h5: output already exists"),
        ([str(src), str(tmp_path / "x.raw"), "--encoding", "mono"], "not available for raw"),
        ([str(src), str(tmp_path / "x.npz"), "--encoding", "evt3"], "does not apply"),
        ([str(tmp_path / "missing.raw"), str(tmp_path / "y.npz")], "missing.raw: no such file"),
        ([str(src), str(tmp_path / "x.csv")], "unknown event file type"),
        ([str(src), str(tmp_path / "x.txt")], "text event files are read only"),
    ]
    for args, message in cases:
        capsys.readouterr()
        assert main(["convert-events", *args]) == 2
        err = capsys.readouterr().err
        assert message in err and err.count("\n") == 1, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["exists.h5", "in.npz"]


def test_convert_refuses_sub_microsecond_times_for_evt(tmp_path, rng, capsys):
    ev = random_events(rng, 100)
    ev["t"] = np.arange(100) * 1000 + 1  # not on the microsecond grid
    write_npz(tmp_path / "ns.npz", ev, 64, 48)
    assert main(["convert-events", str(tmp_path / "ns.npz"), str(tmp_path / "o.raw")]) == 2
    assert "microsecond" in capsys.readouterr().err
    assert not (tmp_path / "o.raw").exists()
    # ns-resolution encodings carry them exactly.
    assert main(["convert-events", str(tmp_path / "ns.npz"), str(tmp_path / "o"),
                 "--encoding", "array"]) == 0
    assert np.array_equal(read_event_file(tmp_path / "o").events, ev)


def test_info_json_and_text(tmp_path, npz_input, capsys):
    src, ev, tr = npz_input
    assert main(["convert-events", str(src), str(tmp_path / "bag")]) == 0
    capsys.readouterr()
    assert main(["info", str(tmp_path / "bag"), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    topics = {t["topic"]: t for t in info["topics"]}
    assert topics["/event_camera/events"]["type"] == "event_camera_msgs/msg/EventPacket"
    e = info["events"]
    assert (e["count"], e["width"], e["height"], e["triggers"]) == (len(ev), 64, 48, len(tr))
    assert e["duration_ns"] == int(ev["t"][-1] - ev["t"][0]) and e["encoding"] == "evt3"
    assert main(["info", str(src)]) == 0
    out = capsys.readouterr().out
    assert f"count       {len(ev)}" in out and "64x48" in out
    assert main(["info", str(tmp_path / "bag"), "--topic", "/nope"]) == 2
    assert "/event_camera/events" in capsys.readouterr().err  # lists the topics that exist


def test_render_events_image_and_rate(tmp_path, npz_input, capsys):
    src, ev, _ = npz_input
    out = tmp_path / "img.png"
    assert main(["render-events", str(src), "--start", "100ms", "--window", "0.05",
                 "-o", str(out), "--rate"]) == 0
    assert out.read_bytes()[:4] == b"\x89PNG"
    assert (tmp_path / "img_rate.png").stat().st_size > 1000
    t0 = int(ev["t"][0]) + 100_000_000
    n = int(((ev["t"] >= t0) & (ev["t"] < t0 + 50_000_000)).sum())
    assert f"{n} events" in capsys.readouterr().out
    assert main(["render-events", str(src), "--start", "x", "--window", "1", "-o", str(out)]) == 2


def test_every_subcommand_has_help():
    for cmd in ["demo", "convert-events", "info", "render-events"]:
        r = subprocess.run([sys.executable, "-m", "evdnerf_ros", cmd, "--help"],
                           capture_output=True, text=True, check=True)
        assert "usage: evdnerf " + cmd in r.stdout and len(r.stdout) > 200


def test_demo_runs_end_to_end(tmp_path, capsys):
    out = tmp_path / "demo"
    # an iteration budget, not the machine's speed (60 iterations, what 6 s gave on a slow day, published
    # no events: a field that young shows too little change), with two minutes as the bound
    assert main(["demo", "-o", str(out), "--train-minutes", "2", "--train-iterations", "120",
                 "--source", "simulate"]) == 0
    assert "session source: simulate (--source simulate)" in capsys.readouterr().out
    summary = json.loads((out / "summary.json").read_text())
    assert summary["source"] == "simulate"
    assert summary["views"] == 7 and min(summary["events_per_view"]) > 1000
    assert all(v["bit_exact"] for v in summary["round_trips"].values())
    assert (out / "event_images.png").exists() and (out / "event_rates.png").exists()
    assert (out / "session" / "session.yaml").exists() and (out / "session" / "sync.png").exists()
    assert all(abs(e) <= 1.0 for e in summary["sync_error_us"].values())
    assert summary["train_h5"]["views"] == 7 and summary["train_h5"]["dl_abs_sum_view0"] > 0
    assert summary["training"]["iterations"] == 120 and np.isfinite(summary["training"]["val_events_psnr"])
    assert np.isfinite(summary["training"]["moving_events_psnr"])
    for split in ("val", "moving"):           # the truth's scores, per window and pooled, and the margins
        scores = summary["training"][split]
        assert all(np.isfinite(scores[k][who]) for k in ("psnr", "psnr_pooled")
                   for who in ("field", "floor", "true_scene"))
        assert set(scores["margin_closed"]) == {"continuous", "quantized", "pooled"}
    assert (out / "run" / "eval_events.png").exists() and (out / "report" / "report.png").exists()
    pub = summary["published"]                 # the trained run published along its training ring
    from evdnerf_ros.io.rosbag2 import read_events

    events = read_events(out / pub["bag"], "/event_publisher/events").events
    assert pub["events"] == events.size > 0 and pub["sim_seconds"] > 0.5 and pub["rtf"] > 0
    # ... and scored against the events the camera would truly see along that ring
    assert pub["scored"] and pub["true_events"] > 0 and np.isfinite(pub["margin_closed"])
    assert pub["count_rel_diff"] == (pub["events"] - pub["true_events"]) / pub["true_events"]
    assert pub["zero_floor_psnr"] < pub["true_render_psnr"]
    # ... and apart, on the moving parts' cells and on the static world sweeping past the camera
    parts = pub["split"]
    assert parts["moving_parts"]["cells"] + parts["static_world"]["cells"] == pytest.approx(1.0)
    assert 0 < parts["moving_parts"]["true_events"] and parts["static_world"]["true_events"] > 0
    assert sum(p["true_events"] for p in parts.values()) <= pub["true_events"]
    import matplotlib.image

    picture = matplotlib.image.imread(out / pub["picture"])[..., :3]
    top, bottom = picture[: picture.shape[0] // 2], picture[picture.shape[0] // 2:]
    assert (top < 0.9).any(axis=-1).mean() > 0.01 and (bottom < 0.99).any()     # neither half blank
    assert summary["backbone"]["chosen"] == "hinge" and "joint" in summary["backbone"]["why"]
    assert summary["training"]["val"]["psnr_pooled"]["true_scene"] > summary["training"]["val"]["psnr_pooled"]["floor"]
    stages = summary["stage_seconds"]
    assert list(stages) == ["session", "round_trips", "sync", "pictures", "convert", "train", "eval", "publish"]
    assert all(v >= 0 for v in stages.values()) and sum(stages.values()) <= summary["wall_seconds"] + 0.5
    assert summary["training"]["stopped_by"] == "iterations"
    assert main(["demo", "-o", str(out)]) == 2          # refuses to overwrite
    assert "already exists" in capsys.readouterr().err


def test_video2events_cli(tmp_path, capsys):
    # A log-linear ramp at every pixel: exp(a t) crosses C = 0.2 exactly every 0.2 / a s.
    t = np.arange(11, dtype=np.int64) * 10_000_000
    a = 20.0  # per second -> one crossing every 10 ms
    frames = np.exp(a * t[:, None, None] * 1e-9) * np.ones((1, 3, 4)) - 1e-3
    np.savez(tmp_path / "frames.npz", frames=frames, t=t)
    assert main(["video2events", str(tmp_path / "frames.npz"), str(tmp_path / "ev.npz")]) == 0
    ev = read_event_file(tmp_path / "ev.npz").events
    assert len(ev) == 10 * 12 and np.all(ev["p"] == 1)
    assert np.array_equal(np.unique(ev["t"]), t[1:])
    assert main(["video2events", str(tmp_path / "frames.npz"), str(tmp_path / "ev.npz")]) == 2
    assert "already exists" in capsys.readouterr().err


def test_simulate_convert_import_cli(tmp_path, capsys):
    session = tmp_path / "s"
    assert main(["simulate", "fork", "-o", str(session), "--views", "2", "--val-views", "0",
                 "--resolution", "24", "18", "--frame-rate", "0", "--gt-times", "0",
                 "--supersample", "1", "--jobs", "1", "--min-step", "5ms"]) == 0
    assert main(["convert", str(session), "-o", str(tmp_path / "t.h5")]) == 2
    assert "run `evdnerf sync" in capsys.readouterr().err
    assert not (tmp_path / "t.h5").exists()
    assert main(["convert", str(session), "-o", str(tmp_path / "t.h5"), "--start", "0"]) == 2
    assert main(["convert", str(session), "-o", str(tmp_path / "t.h5"),
                 "--offsets", "ground-truth"]) == 0
    capsys.readouterr()
    assert main(["sync", str(session), "--json"]) == 0
    synced = json.loads(capsys.readouterr().out)
    assert {v["method"] for v in synced["views"].values()} == {"trigger"}
    assert (session / "sync.png").exists()
    assert main(["convert", str(session), "-o", str(tmp_path / "synced.h5")]) == 0
    assert main(["convert", str(session), "-o", str(tmp_path / "paper"), "--format", "evdnerf",
                 "--offsets", "ground-truth"]) == 0
    assert (tmp_path / "paper" / "transforms_train.json").exists()
    assert main(["import-evdnerf", str(tmp_path / "paper"), "-o", str(tmp_path / "back.h5")]) == 0
    from evdnerf_ros.io.trainingset import TrainingSet

    with TrainingSet(tmp_path / "t.h5") as a, TrainingSet(tmp_path / "back.h5") as b:
        assert a.views == b.views
        for v in a.views:
            assert np.array_equal(a.events(v, *a.time_range), b.events(v, *b.time_range))


def test_report_cli(tmp_path, capsys):
    for name, psnr in (("a", 24.0), ("b", 27.5)):
        (tmp_path / name).mkdir()
        (tmp_path / name / "metrics.jsonl").write_text(
            json.dumps({"iter": 0, "wall_s": 0.5, "val_psnr": 20.0, "val_psnr_zero_floor": 19.0})
            + "\n" + json.dumps({"iter": 50, "wall_s": 9.0, "val_psnr": psnr,
                                  "val_psnr_zero_floor": 19.0}) + "\n")
    assert main(["report", str(tmp_path / "a"), str(tmp_path / "b"), "-o", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "| b | 50 |" in out and "27.50" in out
    assert (tmp_path / "report.png").stat().st_size > 1000
    assert main(["report", str(tmp_path / "missing")]) == 2


def test_building_the_command_line_does_not_import_torch():
    """Every command builds the whole parser: it must not pay for torch (seconds) unless it trains,
    evaluates or renders a field."""
    import subprocess
    import sys

    code = "import sys; from evdnerf_ros.cli import build_parser; build_parser(); print('torch' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "False"


@pytest.mark.parametrize("command, key, value, expected", [
    (["eval", "RUN", "T.h5"], "max_views", 0, "must be >= 1"),
    (["eval", "RUN", "T.h5"], "published", "sideways", "'sideways' is not one of orbit, static"),
    (["eval", "RUN", "T.h5"], "windowz", 4, "windowz: unknown option"),
    (["demo", "-o", "OUT"], "train_minutes", 0, "must be > 0 and <= 10080"),
    (["demo", "-o", "OUT"], "source", "camera", "'camera' is not one of auto, virtual-rig, simulate"),
    (["demo", "-o", "OUT"], "train_iterations", -1, "must be >= 0"),
])
def test_eval_and_demo_config_files_are_checked_by_file_and_key(tmp_path, capsys, command, key, value, expected):
    """eval and demo read --config FILE through their options dataclass: a bad value names the file and
    key before anything runs (and nothing is written)."""
    cfg = tmp_path / "c.yaml"
    cfg.write_text(f"{key}: {json.dumps(value)}\n")
    args = [str(tmp_path / a) if a in ("RUN", "T.h5", "OUT") else a for a in command]
    assert main(args + ["--config", str(cfg)]) == 2
    err = capsys.readouterr().err
    assert f"{cfg}: {key}" in err and expected in err, err
    assert not (tmp_path / "OUT").exists()


def test_eval_config_values_reach_the_job(tmp_path, monkeypatch):
    """Config values land in run_eval; a flag typed wins over the file."""
    import evdnerf_ros.eval.evaluate as evaluate

    seen = {}
    monkeypatch.setattr(evaluate, "run_eval", lambda run, ts, **kw: seen.update(kw) or {})
    cfg = tmp_path / "c.yaml"
    cfg.write_text("max-views: 2\nwindows: 16\ndevice: cpu\n")
    assert main(["eval", "RUN", "T.h5", "--config", str(cfg), "--windows", "8"]) == 0
    assert (seen["max_views"], seen["n_windows"], seen["device"]) == (2, 8, "cpu")


# ------------------------------------------------- an interrupt that lands in a finalizer

class _RaisesInFinalizer:
    """Raises ``exc`` from ``__del__``, where Python can only report and drop it: what a
    signal's handler does when it runs while a finalizer (h5py's weakref callback) runs."""

    def __init__(self, exc):
        self.exc = exc

    def __del__(self):
        raise self.exc


@pytest.mark.parametrize("exc, sig", [("KeyboardInterrupt", "SIGINT"), ("Terminated", "SIGTERM")])
def test_an_interrupt_dropped_in_a_finalizer_is_delivered_again(exc, sig, monkeypatch):
    import signal

    from evdnerf_ros.cli.common import Terminated, _redeliver_swallowed_interrupt

    kind = {"KeyboardInterrupt": KeyboardInterrupt, "Terminated": Terminated}[exc]
    signum = getattr(signal, sig)
    saved = signal.getsignal(signum)
    # the handlers `evdnerf` runs with: Python's own for SIGINT; SIGTERM's has ignored the
    # signal since it raised (a second TERM must not cut the clean-up short)
    signal.signal(signum, signal.default_int_handler if sig == "SIGINT" else signal.SIG_IGN)
    monkeypatch.setattr(sys, "unraisablehook", _redeliver_swallowed_interrupt)
    try:
        with pytest.raises(kind):
            _RaisesInFinalizer(kind())          # dropped at once: __del__ runs here
            for _ in range(200):                # the job's own code, where it lands again
                time.sleep(0.01)
    finally:
        signal.signal(signum, saved)


def test_other_exceptions_in_finalizers_are_reported_as_usual(monkeypatch, capsys):
    from evdnerf_ros.cli.common import _redeliver_swallowed_interrupt

    monkeypatch.setattr(sys, "unraisablehook", _redeliver_swallowed_interrupt)
    _RaisesInFinalizer(ValueError("lost in a finalizer"))
    assert "lost in a finalizer" in capsys.readouterr().err


def test_demo_verdict_says_whether_the_field_beats_no_events():
    from evdnerf_ros.demo import _verdict

    def scores(field, floor, truth, margin):
        return {"psnr_pooled": {"field": field, "floor": floor, "true_scene": truth},
                "margin_closed": {"pooled": margin}}

    worse = _verdict("validation views", scores(27.48, 31.04, 35.29, -0.84))
    assert worse.startswith("validation views: the field's events are further") and "27.48 dB against 31.04" in worse
    better = _verdict("moving camera", scores(33.0, 31.0, 35.0, 0.5))
    assert "closer to the recording" in better and "50 % of the margin" in better
    assert "true scene" not in _verdict("validation views", scores(33.0, 31.0, None, None))
