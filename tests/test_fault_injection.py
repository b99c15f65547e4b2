"""Fault injection: every command, run as the user runs it (`python -m evdnerf_ros ...` in a
subprocess), against bad input, absurd flags, existing outputs, a full disk and signals.

The promise each case checks (docs/reliability.md):
- exit status 2 and exactly one line `evdnerf: error: ...` on stderr, no traceback;
- the line names the culprit (the flag, the file, the key);
- nothing that existed before was changed or deleted, and nothing half-written was left
  (no new file, no `.partial` folder).
Signals: SIGINT / SIGTERM leave no output, no `.partial` and no worker process; a killed run's
stale `.partial` is removed by the next run that writes the same output.
"""

from __future__ import annotations

import os
import resource
import shlex
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import pytest

from conftest import child_pids, pid_alive, ros_domain

EVDNERF = [sys.executable, "-m", "evdnerf_ros"]
SENTINEL = "user data: must survive"


# --------------------------------------------------------------------------- workspace

@pytest.fixture(scope="module")
def ws(tmp_path_factory) -> dict[str, Path]:
    """A small real workspace made by the commands themselves: session, events, training set."""
    root = tmp_path_factory.mktemp("faults")
    quiet = dict(stdout=subprocess.DEVNULL, check=True, cwd=root)
    subprocess.run(EVDNERF + ["simulate", "fork", "-o", "S", "--views", "2", "--val-views", "1",
                              "--resolution", "24", "24", "--frame-rate", "0", "--gt-times", "0",
                              "--jobs", "1"], **quiet)
    subprocess.run(EVDNERF + ["convert-events", "S/view_00", "e.npz"], **quiet)
    subprocess.run(EVDNERF + ["convert", "S", "-o", "T.h5", "--offsets", "ground-truth"], **quiet)
    subprocess.run(EVDNERF + ["train", "T.h5", "-o", "R", "--iters", "2", "--no-eval"], **quiet)
    return {"root": root, "S": root / "S", "E": root / "e.npz", "T": root / "T.h5", "R": root / "R"}


def snapshot(*roots: Path) -> dict:
    """Every path under the roots with its kind, size and content hash (small files)."""
    out = {}
    for root in roots:
        for p in [root, *root.rglob("*")]:
            if p.is_dir():
                out[str(p)] = "dir"
            elif p.is_file():
                st = p.stat()
                out[str(p)] = (st.st_size, st.st_mtime_ns, hash(p.read_bytes()) if st.st_size < 1 << 20 else 0)
    return out


def run(argv, cwd, *, timeout=120, preexec_fn=None, env=None) -> subprocess.CompletedProcess:
    return subprocess.run(EVDNERF + [str(a) for a in argv], cwd=cwd, capture_output=True, text=True,
                          timeout=timeout, preexec_fn=preexec_fn, env=env)


def error_lines(stderr: str) -> list[str]:
    """stderr lines, less the notes about removed stale partial outputs and a node's log lines."""
    return [ln for ln in stderr.splitlines() if ln.strip() and not ln.startswith(("evdnerf: removed ", "evdnerf: warning: ", "[INFO]"))]


def assert_clean_failure(res, culprit: str) -> str:
    lines = error_lines(res.stderr)
    assert "Traceback" not in res.stderr, res.stderr
    assert res.returncode == 2, (res.returncode, res.stderr, res.stdout[-500:])
    assert len(lines) == 1 and lines[0].startswith("evdnerf: error: "), res.stderr
    assert culprit.lower() in lines[0].lower(), f"{culprit!r} not named in: {lines[0]}"
    return lines[0]


def no_partials(*roots: Path) -> list[str]:
    return [str(p) for root in roots for p in root.rglob("*.partial")]


# --------------------------------------------------------------------------- the case table

@dataclass
class Case:
    id: str
    argv: list                       # {S} {E} {T} {R} {tmp} are filled in
    culprit: str                     # must appear in the error line
    setup: Callable | None = None    # setup(tmp, ws) makes the bad input / existing output
    kind: str = "flag"               # flag | existing | corrupt | typed (the docs/reliability.md table groups by it)
    extra: dict = field(default_factory=dict)


def _dir_with_data(name):
    def setup(tmp, ws):
        (tmp / name).mkdir(parents=True, exist_ok=True)
        (tmp / name / "precious.txt").write_text(SENTINEL)
    return setup


def _file(name, data: bytes):
    def setup(tmp, ws):
        (tmp / name).write_bytes(data)
    return setup


def _session_copy(mutate):
    """A copy of the workspace session whose session.yaml text is mutated."""
    def setup(tmp, ws):
        shutil.copytree(ws["S"], tmp / "S2")
        p = tmp / "S2" / "session.yaml"
        p.write_bytes(mutate(p.read_bytes()))
    return setup


def _npz(name, **arrays):
    def setup(tmp, ws):
        with open(tmp / name, "wb") as f:
            np.savez(f, **arrays)
    return setup


def _flipped(src_key, name, offset_frac):
    def setup(tmp, ws):
        data = bytearray(ws[src_key].read_bytes())
        i = int(len(data) * offset_frac)
        data[i:i + 64] = bytes(b ^ 0xFF for b in data[i:i + 64])
        (tmp / name).write_bytes(bytes(data))
    return setup


def _flip_file(path, offset_frac):
    data = bytearray(path.read_bytes())
    i = int(len(data) * offset_frac)
    data[i] ^= 0x01
    path.write_bytes(bytes(data))


def _truncated(src_key, name, frac):
    def setup(tmp, ws):
        data = ws[src_key].read_bytes()
        (tmp / name).write_bytes(data[: int(len(data) * frac)])
    return setup


RENDER = ["render-events", "{E}", "--start", "0", "--window", "10ms", "-o", "{tmp}/img.png"]
EV = np.zeros(4, [("t", "<i8"), ("x", "<u2"), ("y", "<u2"), ("p", "i1")])

CASES = [
    # ---- absurd flags: refused before any allocation, naming the flag
    Case("sync-bin-1ns", ["sync", "{S}", "--bin", "1ns", "--plot", "{tmp}/p.png"], "--bin"),
    Case("sync-bin-0", ["sync", "{S}", "--bin", "0", "--plot", "{tmp}/p.png"], "bin"),
    Case("sync-bin-nan", ["sync", "{S}", "--bin", "nan", "--plot", "{tmp}/p.png"], "--bin"),
    Case("sync-bin-negative", ["sync", "{S}", "--bin=-1ms", "--plot", "{tmp}/p.png"], "bin"),
    Case("sync-bin-1e30", ["sync", "{S}", "--bin", "1e30", "--plot", "{tmp}/p.png"], "--bin"),
    Case("render-start-1e308", RENDER[:3] + ["1e308"] + RENDER[4:], "--start"),
    Case("convert-end-huge", ["convert", "{S}", "-o", "{tmp}/t.h5", "--start", "0", "--end",
                              "99999999999999999999999", "--offsets", "ground-truth"], "--end"),
    Case("render-window-0", RENDER[:4] + ["0"] + RENDER[5:], "--window"),
    Case("render-window-garbage", RENDER[:4] + ["ten"] + RENDER[5:], "--window"),
    Case("render-upscale-0", RENDER + ["--upscale", "0"], "--upscale"),
    Case("render-upscale-huge", RENDER + ["--upscale", "100000"], "--upscale"),
    Case("render-saturation-nan", RENDER + ["--saturation", "nan"], "--saturation"),
    Case("render-saturation-0", RENDER + ["--saturation", "0"], "--saturation"),
    Case("render-rate-bin-1ns", RENDER + ["--rate", "--rate-bin", "1ns"], "--rate-bin"),
    Case("convert-n-windows-0", ["convert", "{S}", "-o", "{tmp}/x", "--format", "evdnerf", "--n-windows", "0",
                                 "--offsets", "ground-truth"], "--n-windows"),
    Case("convert-n-windows-1e30", ["convert", "{S}", "-o", "{tmp}/x", "--format", "evdnerf",
                                    "--n-windows", "1e30"], "--n-windows"),
    Case("eval-windows-0", ["eval", "{tmp}", "{T}", "--windows", "0"], "--windows"),
    Case("eval-windows-huge", ["eval", "{R}", "{T}", "--windows", "100000"], "--windows",
         extra={"env": {"EVDNERF_MEMORY_LIMIT": "256M"}}),
    Case("eval-flipped-checkpoint", ["eval", "{tmp}/R2", "{T}"], "checkpoint.pt",
         lambda tmp, ws: (shutil.copytree(ws["R"], tmp / "R2"), _flip_file(tmp / "R2" / "checkpoint.pt", 0.5)),
         "corrupt"),
    Case("train-init-flipped", ["train", "{T}", "-o", "{tmp}/r", "--iters", "1", "--init", "{tmp}/R2/checkpoint.pt"],
         "checkpoint.pt",
         lambda tmp, ws: (shutil.copytree(ws["R"], tmp / "R2"), _flip_file(tmp / "R2" / "checkpoint.pt", 0.3)),
         "corrupt"),
    Case("eval-max-views-neg", ["eval", "{tmp}", "{T}", "--max-views=-3"], "--max-views"),
    Case("train-eval-views-neg", ["train", "{T}", "-o", "{tmp}/r", "--iters", "1", "--eval-views=-1"],
         "--eval-views"),
    Case("demo-minutes-nan", ["demo", "-o", "{tmp}/d", "--train-minutes", "nan"], "--train-minutes"),
    Case("demo-minutes-neg", ["demo", "-o", "{tmp}/d", "--train-minutes=-1"], "--train-minutes"),
    Case("publish-duration-neg", ["publish", "-o", "{tmp}/b", "--duration=-1"], "--duration"),
    Case("publish-duration-inf", ["publish", "-o", "{tmp}/b", "--duration", "inf"], "--duration"),
    Case("publish-rtf-nan", ["publish", "-o", "{tmp}/b", "--realtime-factor", "nan"], "--realtime-factor"),
    Case("publish-resolution-0", ["publish", "-o", "{tmp}/b", "--resolution", "0", "0"], "--resolution"),
    Case("publish-resolution-huge", ["publish", "-o", "{tmp}/b", "--resolution", "1000000", "10"],
         "--resolution"),
    Case("echo-depth-0", ["echo", "/x", "--depth", "0"], "--depth"),
    Case("echo-idle-nan", ["echo", "/x", "--idle", "nan"], "--idle"),
    Case("echo-count-neg", ["echo", "/x", "--count=-5"], "--count"),
    Case("echo-relative-topic", ["echo", "x", "--idle", "1"], "topic"),

    # ---- existing outputs: never replaced without --overwrite, never a folder we did not make
    Case("convert-events-onto-folder", ["convert-events", "{E}", "{tmp}/out.npz"], "out.npz",
         _dir_with_data("out.npz"), "existing"),
    Case("convert-events-onto-file", ["convert-events", "{E}", "{tmp}/out.h5"], "out.h5",
         _file("out.h5", SENTINEL.encode()), "existing"),
    Case("render-onto-folder", RENDER[:-1] + ["{tmp}/img"], "img", _dir_with_data("img"), "existing"),
    Case("render-onto-folder-overwrite", RENDER[:-1] + ["{tmp}/img", "--overwrite"], "img",
         _dir_with_data("img"), "existing"),
    Case("render-onto-file", RENDER, "img.png", _file("img.png", SENTINEL.encode()), "existing"),
    Case("render-rate-onto-folder", RENDER + ["--rate", "--overwrite"], "img_rate.png",
         _dir_with_data("img_rate.png"), "existing"),
    Case("sync-plot-onto-folder", ["sync", "{S}", "--plot", "{tmp}/plots"], "plots",
         _dir_with_data("plots"), "existing"),
    Case("sync-plot-onto-folder-overwrite", ["sync", "{S}", "--plot", "{tmp}/plots", "--overwrite"], "plots",
         _dir_with_data("plots"), "existing"),
    Case("sync-plot-onto-file", ["sync", "{S}", "--plot", "{tmp}/p.png"], "p.png",
         _file("p.png", SENTINEL.encode()), "existing"),
    Case("sync-default-plot-is-folder", ["sync", "{tmp}/S2"], "sync.png",
         lambda tmp, ws: (shutil.copytree(ws["S"], tmp / "S2"), _dir_with_data("S2/sync.png")(tmp, ws)),
         "existing"),
    Case("report-png-is-folder", ["report", "{tmp}/run", "-o", "{tmp}", "--overwrite"], "report.png",
         _dir_with_data("report.png"), "existing"),
    Case("report-onto-file", ["report", "{tmp}/run", "-o", "{tmp}/rep"], "rep",
         _file("rep", SENTINEL.encode()), "existing"),
    Case("echo-save-events-onto-folder", ["echo", "/x", "--idle", "0.2", "--save-events", "{tmp}/ev"], "ev",
         _dir_with_data("ev"), "existing"),
    Case("echo-png-missing-parent", ["echo", "/x", "--idle", "30", "--png", "{tmp}/no/such/dir/e.png"],
         "does not exist", None, "existing"),
    Case("simulate-onto-folder", ["simulate", "fork", "-o", "{tmp}/sess"], "sess",
         _dir_with_data("sess"), "existing"),
    Case("simulate-overwrite-foreign-folder", ["simulate", "fork", "-o", "{tmp}/sess", "--overwrite"],
         "not written by evdnerf", _dir_with_data("sess"), "existing"),
    Case("simulate-overwrite-file", ["simulate", "fork", "-o", "{tmp}/sess", "--overwrite"], "not a folder",
         _file("sess", SENTINEL.encode()), "existing"),
    Case("demo-overwrite-foreign-folder", ["demo", "-o", "{tmp}/d", "--overwrite"], "not written by evdnerf",
         _dir_with_data("d"), "existing"),
    Case("convert-onto-folder", ["convert", "{S}", "-o", "{tmp}/t.h5", "--offsets", "ground-truth"], "t.h5",
         _dir_with_data("t.h5"), "existing"),
    Case("convert-h5-overwrite-folder", ["convert", "{S}", "-o", "{tmp}/t.h5", "--offsets", "ground-truth",
                                         "--overwrite"], "t.h5", _dir_with_data("t.h5"), "existing"),
    Case("convert-evdnerf-overwrite-foreign", ["convert", "{S}", "-o", "{tmp}/evd", "--format", "evdnerf",
                                               "--offsets", "ground-truth", "--overwrite"],
         "not written by evdnerf", _dir_with_data("evd"), "existing"),
    Case("publish-onto-folder", ["publish", "-o", "{tmp}/bag", "--duration", "0.01"], "bag",
         _dir_with_data("bag"), "existing"),
    Case("publish-onto-file", ["publish", "-o", "{tmp}/bag", "--duration", "0.01"], "bag",
         _file("bag", SENTINEL.encode()), "existing"),
    Case("output-parent-missing", ["convert-events", "{E}", "{tmp}/nope/out.npz"], "does not exist",
         None, "existing"),

    # ---- corrupt and crafted input files: one line naming the file
    Case("info-empty-npz", ["info", "{tmp}/x.npz"], "x.npz", _file("x.npz", b""), "corrupt"),
    Case("info-garbage-npz", ["info", "{tmp}/x.npz"], "x.npz", _file("x.npz", os.urandom(4096)), "corrupt"),
    Case("info-truncated-npz", ["info", "{tmp}/x.npz"], "x.npz", _truncated("E", "x.npz", 0.5), "corrupt"),
    Case("info-flipped-npz", ["info", "{tmp}/x.npz"], "x.npz", _flipped("E", "x.npz", 0.6), "corrupt"),
    Case("info-npz-missing-key", ["info", "{tmp}/x.npz"], "x.npz",
         _npz("x.npz", t=np.arange(4), x=np.zeros(4), width=4, height=4), "corrupt"),
    Case("info-npz-nan-times", ["info", "{tmp}/x.npz"], "x.npz",
         _npz("x.npz", t=np.array([0.0, np.nan]), x=np.zeros(2, np.uint16), y=np.zeros(2, np.uint16),
              p=np.ones(2, np.int8), width=4, height=4), "corrupt"),
    Case("render-empty-h5", RENDER[:1] + ["{tmp}/x.h5"] + RENDER[2:], "x.h5", _file("x.h5", b""), "corrupt"),
    Case("render-garbage-raw", RENDER[:1] + ["{tmp}/x.raw"] + RENDER[2:], "x.raw",
         _file("x.raw", b"% evt 3.0\n% end\n" + os.urandom(100)), "corrupt"),
    Case("convert-events-truncated-h5", ["convert-events", "{tmp}/x.h5", "{tmp}/y.npz"], "x.h5",
         _truncated("T", "x.h5", 0.3), "corrupt"),
    Case("info-flipped-training-set", ["info", "{tmp}/x.h5"], "x.h5", _flipped("T", "x.h5", 0.02), "corrupt"),
    Case("train-garbage-training-set", ["train", "{tmp}/x.h5", "-o", "{tmp}/r", "--iters", "1"], "x.h5",
         _file("x.h5", os.urandom(8192)), "corrupt"),
    Case("train-truncated-training-set", ["train", "{tmp}/x.h5", "-o", "{tmp}/r", "--iters", "1"], "x.h5",
         _truncated("T", "x.h5", 0.5), "corrupt"),
    Case("report-non-utf8-metrics", ["report", "{tmp}/run", "-o", "{tmp}/rep"], "metrics.jsonl",
         lambda tmp, ws: ((tmp / "run").mkdir(), (tmp / "run" / "metrics.jsonl").write_bytes(b"\xff\xfe{]\n")),
         "corrupt"),
    Case("sync-not-a-session", ["sync", "{tmp}", "--plot", "{tmp}/p.png"], "session.yaml", None, "corrupt"),
    Case("sync-bag-garbage", ["sync", "{tmp}/S2", "--plot", "{tmp}/p.png"], "view_00",
         lambda tmp, ws: (shutil.copytree(ws["S"], tmp / "S2"),
                          (tmp / "S2" / "view_00" / "view_00.mcap").write_bytes(os.urandom(2000))), "corrupt"),

    # ---- ill-typed session.yaml and configs: one line naming the file and the key
    Case("session-not-utf8", ["sync", "{tmp}/S2", "--plot", "{tmp}/p.png"], "session.yaml",
         _session_copy(lambda b: b"\xff\xfe" + b), "typed"),
    Case("session-empty", ["sync", "{tmp}/S2", "--plot", "{tmp}/p.png"], "session.yaml",
         _session_copy(lambda b: b""), "typed"),
    Case("session-a-list", ["sync", "{tmp}/S2", "--plot", "{tmp}/p.png"], "session.yaml",
         _session_copy(lambda b: b"- 1\n- 2\n"), "typed"),
    Case("session-bad-yaml", ["sync", "{tmp}/S2", "--plot", "{tmp}/p.png"], "session.yaml",
         _session_copy(lambda b: b + b"\n  : : [\n"), "typed"),
    Case("config-not-a-mapping", ["train", "{T}", "-o", "{tmp}/r", "--iters", "1", "--config", "{tmp}/c.yaml"],
         "c.yaml", _file("c.yaml", b"[1, 2]\n"), "typed"),
    Case("config-unknown-key", ["train", "{T}", "-o", "{tmp}/r", "--iters", "1", "--config", "{tmp}/c.yaml"],
         "no_such_key", _file("c.yaml", b"no_such_key: 3\n"), "typed"),
    Case("config-non-utf8", ["train", "{T}", "-o", "{tmp}/r", "--iters", "1", "--config", "{tmp}/c.yaml"],
         "c.yaml", _file("c.yaml", b"lr: \xff\xfe\n"), "typed"),
    Case("scene-not-a-mapping", ["simulate", "{tmp}/scene.yaml", "-o", "{tmp}/s"], "scene.yaml",
         _file("scene.yaml", b"just text\n"), "typed"),
    Case("scene-non-utf8", ["simulate", "{tmp}/scene.yaml", "-o", "{tmp}/s"], "scene.yaml",
         _file("scene.yaml", b"name: \xff\n"), "typed"),
    Case("trajectory-non-utf8", ["publish", "-o", "{tmp}/b", "--trajectory", "{tmp}/t.csv"], "t.csv",
         _file("t.csv", b"t,x,y,z\n\xff\xfe\n"), "typed"),
    Case("params-file-garbage", ["publish", "-o", "{tmp}/b", "--params-file", "{tmp}/p.yaml"], "p.yaml",
         _file("p.yaml", b"{{{{\n"), "typed"),
]


def _fill(argv, tmp, ws):
    return [str(a).format(S=ws["S"], E=ws["E"], T=ws["T"], R=ws["R"], tmp=tmp) for a in argv]


@pytest.mark.parametrize("case", CASES, ids=[c.id for c in CASES])
def test_bad_input_fails_cleanly(case, ws, tmp_path):
    tmp = tmp_path / "w"
    tmp.mkdir()
    if case.setup:
        case.setup(tmp, ws)
    before = snapshot(tmp, ws["root"])
    res = run(_fill(case.argv, tmp, ws), tmp, env={**os.environ, **case.extra.get("env", {})})
    assert_clean_failure(res, case.culprit)
    after = snapshot(tmp, ws["root"])
    assert after == before, "changed: " + str(sorted(set(after.items()) ^ set(before.items()))[:6])
    assert not no_partials(tmp, ws["root"])


# --------------------------------------------------------------------------- a full disk

def _file_size_limit(nbytes):
    """A process whose writes beyond `nbytes` fail with EFBIG, as on a full disk."""
    def preexec():
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (nbytes, nbytes))
    return preexec


FULL_DISK = [
    ("convert-events-npz", ["convert-events", "{E}", "{tmp}/out.npz"], "out.npz"),
    ("convert-events-h5", ["convert-events", "{E}", "{tmp}/out.h5"], "out.h5"),
    ("convert-events-raw", ["convert-events", "{E}", "{tmp}/out.raw"], "out.raw"),
    ("convert-events-bag", ["convert-events", "{E}", "{tmp}/out_bag"], "out_bag"),
    ("convert-events-rosbag1", ["convert-events", "{E}", "{tmp}/out.bag"], "out.bag"),
    ("convert", ["convert", "{S}", "-o", "{tmp}/t.h5", "--offsets", "ground-truth"], "t.h5"),
    ("convert-evdnerf", ["convert", "{S}", "-o", "{tmp}/evd", "--format", "evdnerf", "--offsets",
                         "ground-truth"], "evd"),
    ("render-events", RENDER[:-1] + ["{tmp}/img.png", "--upscale", "8"], "img.png", 128),
    ("simulate", ["simulate", "fork", "-o", "{tmp}/sess", "--views", "1", "--val-views", "0",
                  "--resolution", "24", "24", "--frame-rate", "0", "--gt-times", "0", "--jobs", "1"], "sess"),
    ("publish", ["publish", "-o", "{tmp}/bag", "--duration", "0.2", "--resolution", "32", "32"], "bag"),
]


@pytest.mark.parametrize("case", FULL_DISK, ids=[c[0] for c in FULL_DISK])
def test_full_disk_is_one_line_and_leaves_nothing(case, ws, tmp_path):
    _, argv, culprit, *limit = case
    tmp = tmp_path / "w"
    tmp.mkdir()
    res = run(_fill(argv, tmp, ws), tmp, preexec_fn=_file_size_limit(limit[0] if limit else 2048))
    assert_clean_failure(res, culprit)
    assert list(tmp.iterdir()) == [], list(tmp.iterdir())


# --------------------------------------------------------------------------- signals

SIGNAL_JOBS = [
    ("simulate", ["simulate", "fork", "-o", "{tmp}/out", "--views", "4", "--val-views", "0",
                  "--resolution", "48", "48", "--jobs", "2"], "out"),
    ("convert", ["convert", "{S}", "-o", "{tmp}/out", "--format", "evdnerf", "--offsets", "ground-truth",
                 "--n-windows", "2000"], "out"),
    ("publish", ["publish", "-o", "{tmp}/out", "--resolution", "64", "64"], "out"),
]


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
@pytest.mark.parametrize("job", SIGNAL_JOBS, ids=[j[0] for j in SIGNAL_JOBS])
def test_signal_leaves_no_output_partial_or_worker(job, sig, ws, tmp_path):
    name, argv, out = job
    tmp = tmp_path / "w"
    tmp.mkdir()
    proc = subprocess.Popen(EVDNERF + _fill(argv, tmp, ws), cwd=tmp, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 60
    while not list(tmp.glob(".*.partial")) and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.05)
    assert proc.poll() is None, f"{name} ended before it could be interrupted: {proc.stderr.read()}"
    time.sleep(0.5)                              # well inside the work
    kids = child_pids(proc.pid)
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=60)
    assert "Traceback" not in err, err
    if name == "publish":                        # the node closes its bag: a valid, shorter recording
        assert proc.returncode in (0, 130, 143), err
        assert (tmp / out).is_dir() and not no_partials(tmp)
    else:
        assert proc.returncode == (130 if sig == signal.SIGINT else 143), err
        assert list(tmp.iterdir()) == [], list(tmp.iterdir())
    time.sleep(0.2)
    assert not [k for k in kids if pid_alive(k)], "worker processes outlived their parent"


def _dead_pid() -> int:
    pid = 4_000_000
    while Path(f"/proc/{pid}").exists():
        pid -= 1
    return pid


def test_stale_partial_of_a_killed_run_is_removed_and_reported(ws, tmp_path):
    stale = tmp_path / f".out.npz.{_dead_pid()}.abc123.partial"
    stale.mkdir()
    (stale / "out.npz").write_bytes(b"half")
    alive = tmp_path / f".out.npz.{os.getpid()}.def456.partial"   # a writer still running: kept
    alive.mkdir()
    res = run(["convert-events", ws["E"], "out.npz"], tmp_path)
    assert res.returncode == 0, res.stderr
    assert not stale.exists() and alive.is_dir()
    assert f"removed {stale.name}" in res.stderr
    assert (tmp_path / "out.npz").is_file()


def test_sigkilled_run_leaves_a_partial_the_next_run_cleans(ws, tmp_path):
    proc = subprocess.Popen(EVDNERF + ["convert", str(ws["S"]), "-o", "out", "--format", "evdnerf",
                                       "--offsets", "ground-truth", "--n-windows", "2000"],
                            cwd=tmp_path, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 60
    while not list(tmp_path.glob(".out.*.partial")) and time.monotonic() < deadline:
        time.sleep(0.05)
    proc.kill()
    proc.wait()
    assert list(tmp_path.glob(".out.*.partial"))
    res = run(["convert", ws["S"], "-o", "out", "--format", "evdnerf", "--offsets", "ground-truth",
               "--n-windows", "4"], tmp_path)
    assert res.returncode == 0, res.stderr
    assert "removed" in res.stderr and not list(tmp_path.glob(".out.*.partial"))


# --------------------------------------------------------------------------- hangs

def test_echo_idle_ends_a_wait_on_a_silent_topic(tmp_path):
    t0 = time.monotonic()
    res = run(["echo", "/nobody/publishes/here", "--idle", "1", "--json"], tmp_path, timeout=60,
              env={**os.environ, "ROS_DOMAIN_ID": str(ros_domain())})
    assert res.returncode == 0, res.stderr
    assert time.monotonic() - t0 < 30
    assert '"messages": 0' in res.stdout


# --------------------------------------------------------------------------- overwrite replaces only ours

def test_overwrite_replaces_our_own_outputs(ws, tmp_path):
    argv = ["convert", ws["S"], "-o", "evd", "--format", "evdnerf", "--offsets", "ground-truth", "--n-windows", "4"]
    assert run(argv, tmp_path).returncode == 0
    assert (tmp_path / "evd" / ".evdnerf-output").is_file()
    res = run(argv + ["--overwrite"], tmp_path)
    assert res.returncode == 0, res.stderr
    render = ["render-events", ws["E"], "--start", "0", "--window", "10ms", "-o", "img.png"]
    assert run(render, tmp_path).returncode == 0
    assert run(render, tmp_path).returncode == 2
    assert run(render + ["--overwrite"], tmp_path).returncode == 0


# --------------------------------------------------------------------------- a real full or read-only file system

def _can_mount_tmpfs() -> bool:
    if shutil.which("unshare") is None:
        return False
    probe = subprocess.run(["unshare", "-m", "sh", "-c", "mount -t tmpfs -o size=16k tmpfs /mnt"],
                           capture_output=True)
    return probe.returncode == 0


needs_mount = pytest.mark.skipif(not _can_mount_tmpfs(),
                                 reason="needs a private mount namespace (root, or unshare allowed)")


def run_on_small_fs(argv, mount: Path, *, size="32k", read_only=False):
    """Run evdnerf with its cwd on a fresh tmpfs of `size` (read-only after mounting if asked);
    returns the process result and what was left on that file system."""
    mount.mkdir(exist_ok=True)
    cmd = " ".join(shlex.quote(str(a)) for a in EVDNERF + list(argv))
    remount = f"mount -o remount,ro {mount} && " if read_only else ""
    script = (f"mount -t tmpfs -o size={size} tmpfs {mount} && {remount}cd {mount} && "
              f"{{ {cmd}; rc=$?; echo \"LEFT:$(ls -A)\"; exit $rc; }}")
    res = subprocess.run(["unshare", "-m", "sh", "-c", script], capture_output=True, text=True, timeout=180)
    left = [ln for ln in res.stdout.splitlines() if ln.startswith("LEFT:")][-1][5:].split()
    return res, left


SMALL_FS = [
    ("convert", ["convert", "{S}", "-o", "t.h5", "--offsets", "ground-truth"], "t.h5"),
    ("convert-evdnerf", ["convert", "{S}", "-o", "evd", "--format", "evdnerf", "--offsets", "ground-truth"],
     "evd"),
    ("convert-events-h5", ["convert-events", "{E}", "out.h5"], "out.h5"),
    ("convert-events-npz", ["convert-events", "{E}", "out.npz"], "out.npz"),
    ("convert-events-bag", ["convert-events", "{E}", "out_bag"], "out_bag"),
    ("simulate", ["simulate", "fork", "-o", "sess", "--views", "2", "--val-views", "0", "--resolution", "24",
                  "24", "--frame-rate", "0", "--gt-times", "0", "--jobs", "1"], "sess"),
    ("render-events", ["render-events", "{E}", "--start", "0", "--window", "10ms", "-o", "img.png",
                       "--upscale", "64"], "img.png"),
    ("train", ["train", "{T}", "-o", "run", "--iters", "3", "--no-eval"], "run"),
]


@needs_mount
@pytest.mark.parametrize("read_only", [False, True], ids=["full", "read-only"])
@pytest.mark.parametrize("case", SMALL_FS, ids=[c[0] for c in SMALL_FS])
def test_full_or_read_only_file_system(case, read_only, ws, tmp_path):
    _, argv, culprit = case
    size = "1m" if read_only else ("4k" if case[0] == "render-events" else "24k")
    res, left = run_on_small_fs(_fill(argv, tmp_path, ws), tmp_path / "mnt", size=size, read_only=read_only)
    assert_clean_failure(res, culprit)
    if case[0] == "train" and not read_only:
        # A run folder is written as training goes (config, metrics, lock): a first start that
        # could not write its checkpoint is restarted by the same command; nothing is half-written.
        assert left == ["run"], left
    else:
        assert left == [], left


def _event_messages(bag: Path) -> list[tuple[int, bytes]]:
    """(time, raw CDR) of the event topic, read by rosbags' own reader."""
    from rosbags.highlevel import AnyReader

    with AnyReader([bag]) as reader:
        conns = [c for c in reader.connections if c.topic.endswith("/events")]
        return [(t, bytes(raw)) for _, t, raw in reader.messages(connections=conns)]


def test_sigkilled_recording_is_kept_and_salvaged(tmp_path):
    """SIGKILL cannot be caught, but a recording flushes its chunks every second: the killed
    bag's partial folder is kept (not cleaned) and `salvage-bag` writes out exactly the
    messages an uninterrupted run starts with."""
    publish = ["publish", "--resolution", "16", "16", "--duration", "1.0"]
    proc = subprocess.Popen(EVDNERF + publish + ["-o", "b"], cwd=tmp_path, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    from evdnerf_ros.errors import EvdnerfError
    from evdnerf_ros.io.mcap_salvage import salvage_messages

    def flushed_events() -> bool:          # an event message on disk (a flush before the first holds none)
        for f in tmp_path.glob(".b.*.partial/b/*.mcap"):
            try:
                return any(m.topic.endswith("/events") for m in salvage_messages(f))
            except EvdnerfError:             # a file being written: look again
                return False
        return False

    deadline = time.monotonic() + 90
    while time.monotonic() < deadline and not flushed_events():
        time.sleep(0.05)
    proc.kill()
    proc.wait()
    partial = next(tmp_path.glob(".b.*.partial"))
    again = run(["publish", "-o", "b", "--resolution", "16", "16", "--duration", "0.01"], tmp_path)
    assert again.returncode == 0 and partial.is_dir() and f"kept {partial.name}" in again.stderr
    res = run(["salvage-bag", partial.name, "-o", "salvaged"], tmp_path)
    assert res.returncode == 0, res.stderr
    salvaged = _event_messages(tmp_path / "salvaged")
    assert salvaged
    full = run(publish + ["-o", "full"], tmp_path)
    assert full.returncode == 0, full.stderr
    reference = _event_messages(tmp_path / "full")
    assert len(salvaged) < len(reference)
    assert salvaged == reference[:len(salvaged)]


def test_salvage_refuses_what_is_not_a_recording(tmp_path):
    (tmp_path / "x.mcap").write_bytes(b"not an mcap at all")
    res = run(["salvage-bag", "x.mcap", "-o", "out"], tmp_path)
    assert_clean_failure(res, "x.mcap")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["x.mcap"]
