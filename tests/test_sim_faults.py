"""Bad input and signals for `simulate` and `video2events`: one error line naming the culprit,
exit 2, nothing written; worker processes end with their parent."""

from __future__ import annotations

import io
import os
import signal
import subprocess
import sys
import time
import zipfile
from pathlib import Path

import numpy as np
import pytest

from conftest import child_pids, pid_alive

from evdnerf_ros.cli import main

# A run small enough to start quickly; each case changes one flag.
SMALL = ["--views", "1", "--val-views", "0", "--resolution", "8", "6", "--supersample", "1",
         "--frame-rate", "0", "--gt-times", "0", "--jobs", "1"]


def _one_error_line(capsys, *needles):
    err = capsys.readouterr().err
    assert err.startswith("evdnerf: error: ") and err.count("\n") == 1, err
    assert "Traceback" not in err
    for needle in needles:
        assert needle in err, (needle, err)
    return err


# ------------------------------------------------------------------ simulate: flags

BAD_FLAGS = [
    ("--views", "0"), ("--views", "-2"), ("--views", "100000"), ("--val-views", "-1"),
    ("--seed", "-1"), ("--c-pos", "nan"), ("--c-pos", "inf"), ("--c-pos", "0"),
    ("--c-neg", "-0.2"), ("--c-neg", "1e30"), ("--eps", "0"), ("--eps", "nan"),
    ("--sigma", "-1"), ("--sigma", "inf"), ("--refractory-ns", "-5"), ("--tolerance-c", "0"),
    ("--tolerance-c", "-inf"), ("--min-step", "0"), ("--min-step", "-1ms"),
    ("--min-step", "1ns"), ("--max-step", "1e30s"), ("--max-step", "0"),
    ("--supersample", "0"), ("--supersample", "1000"), ("--frame-rate", "nan"),
    ("--frame-rate", "-30"), ("--frame-rate", "1e30"), ("--blur-samples", "0"),
    ("--gt-times", "-1"), ("--gt-times", "1000000"), ("--moving-views", "-1"),
    ("--moving-arc-deg", "nan"), ("--moving-arc-deg", "1e30"), ("--max-clock-offset", "-1"),
    ("--max-clock-offset", "inf"), ("--jobs", "-1"), ("--jobs", "100000"),
]


@pytest.mark.parametrize("flag, value", BAD_FLAGS)
def test_bad_flag_is_one_line_naming_it(tmp_path, capsys, flag, value):
    args = [a for a in SMALL]
    if flag in args:
        i = args.index(flag)
        del args[i:i + 2]
    out = tmp_path / "S"
    assert main(["simulate", "fork", "-o", str(out), *args, f"{flag}={value}"]) == 2
    _one_error_line(capsys, flag)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("extra, needle", [
    (["--resolution", "0", "6"], "--resolution W"),
    (["--resolution", "8", "100000"], "--resolution H"),
    (["--min-step", "20ms", "--max-step", "10ms"], "--min-step"),
    # a 1 s swing at 1 us on a 1 us grid is 1e6 renders: allowed; 1e3 s of motion is not
    (["--frame-rate", "100000", "--blur-samples", "1024"], "--blur-samples"),
])
def test_bad_flag_combinations(tmp_path, capsys, extra, needle):
    args = ["--views", "1", "--val-views", "0", "--supersample", "1", "--gt-times", "0"]
    assert main(["simulate", "fork", "-o", str(tmp_path / "S"), *args, *extra]) == 2
    _one_error_line(capsys, needle)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("extra, needle", [
    (["--resolution", "4000", "3000", "--supersample", "4"], "--resolution 4000 3000"),
    (["--resolution", "1000", "1000", "--frame-rate", "10000"], "--frame-rate"),
    (["--resolution", "1000", "1000", "--gt-times", "9000"], "--gt-times"),
])
def test_memory_is_estimated_before_anything_is_allocated(tmp_path, capsys, monkeypatch, extra,
                                                          needle):
    monkeypatch.setenv("EVDNERF_MEMORY_LIMIT", "2G")
    assert main(["simulate", "fork", "-o", str(tmp_path / "S"), "--views", "1", "--val-views",
                 "0", "--jobs", "1", *extra]) == 2
    _one_error_line(capsys, needle, "EVDNERF_MEMORY_LIMIT")
    assert list(tmp_path.iterdir()) == []


def test_min_step_over_long_motion_is_refused_up_front(tmp_path, capsys):
    scene = tmp_path / "long.yaml"
    scene.write_text("time: {start_s: 0, end_s: 5000}\n"
                     "objects:\n"
                     "  - type: sphere\n"
                     "    radius: 0.3\n"
                     "    motion: {keyframes: [{t_s: 0, position: [0, 0, 0]},"
                     " {t_s: 5000, position: [0, 0.5, 0]}]}\n")
    assert main(["simulate", str(scene), "-o", str(tmp_path / "S"), *SMALL, "--min-step",
                 "1ms"]) == 2
    _one_error_line(capsys, "--min-step", "renders per view")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["long.yaml"]


# ------------------------------------------------------------------ simulate: scene files

SPHERE = "objects:\n  - {type: sphere, radius: 0.3}\n"
_BOMB = ("objects:\n"
         "  - &a {type: group, children: [{type: sphere, radius: 0.1}, {type: sphere, radius: 0.1}]}\n"
         "  - &b {type: group, children: [*a, *a, *a, *a, *a, *a, *a, *a, *a, *a]}\n"
         "  - &c {type: group, children: [*b, *b, *b, *b, *b, *b, *b, *b, *b, *b]}\n"
         "  - &d {type: group, children: [*c, *c, *c, *c, *c, *c, *c, *c, *c, *c]}\n"
         "  - {type: group, children: [*d, *d, *d, *d, *d, *d, *d, *d, *d, *d]}\n")
BAD_SCENES = [
    (b"name: \xff\xfe\n" + SPHERE.encode(), "not UTF-8"),
    (b"", "empty"),
    (b"   \n# nothing\n", "empty"),
    (b"- 1\n- 2\n", "must be a mapping with keys name, description"),
    (b"42\n", "must be a mapping with keys name, description, time, background, lights, objects, cameras, got a number"),
    (b"name: x\n", "missing required key 'objects'"),
    (b"objects: 3\n", "objects: must be a list, got a number"),
    (b"objects: []\n", "objects: needs at least 1"),
    (b"objects:\n  - {type: sphere, radius: big}\n", "objects[0].radius: expected a number"),
    (b"objects:\n  - {type: sphere, radius: .nan}\n", "objects[0].radius: must be a finite number, got nan"),
    (b"objects:\n  - {type: sphere, radius: .inf}\n", "objects[0].radius: must be a finite number, got inf"),
    (b"objects:\n  - {type: sphere, radius: 1.0e+30}\n", "objects[0].radius: must be within"),
    (b"objects:\n  - {type: sphere, radius: 0.3, albedo: true}\n", "objects[0].albedo"),
    (b"objects:\n  - {type: box, size: [1, -1, 1]}\n", "objects[0].size[1]"),
    (b"objects:\n  - {type: box, size: [1, 1]}\n", "objects[0].size"),
    (b"objects:\n  - {type: sphere, radius: 0.3, colour: red}\n", "objects[0].colour"),
    (b"objects:\n  - {radius: 0.3}\n", "objects[0]: missing required key 'type'"),
    (b"objects:\n  - {type: teapot}\n", "objects[0].type"),
    (b"time: {start_s: 0, end_s: 1.0e+30}\n" + SPHERE.encode(), "time.end_s"),
    (b"time: {start_s: 0, end_s: .nan}\n" + SPHERE.encode(), "time.end_s"),
    (b"time: {start_s: 1, end_s: 1}\n" + SPHERE.encode(), "time.end_s"),
    (b"cameras: {intrinsics: {width: 1.5}}\n" + SPHERE.encode(), "cameras.intrinsics.width"),
    (b"cameras: {ring: {radius: -4}}\n" + SPHERE.encode(), "cameras.ring.radius"),
    (b"lights: {ambient: .nan}\n" + SPHERE.encode(), "lights.ambient"),
    (b"background: {intensity: 0}\n" + SPHERE.encode(), "background.intensity"),
    (b"background: {texture: {type: noise, scale: 1.0e-300}}\n" + SPHERE.encode(),
     "background.texture.scale"),
    (b"description: [1, 2]\n" + SPHERE.encode(), "description"),
    (b"objects: " + b"[" * 5000 + b"]" * 5000 + b"\n", "yaml"),
    (b"objects: [\n", "not valid YAML"),
    (b"objects: !!python/object:os.system [echo]\n", "not valid YAML"),
    (_BOMB.encode(), "more than 10000 objects"),
]


@pytest.mark.parametrize("content, needle", BAD_SCENES)
def test_bad_scene_file_is_one_line_naming_file_and_key(tmp_path, capsys, content, needle):
    scene = tmp_path / "scene.yaml"
    scene.write_bytes(content)
    assert main(["simulate", str(scene), "-o", str(tmp_path / "S"), *SMALL]) == 2
    err = _one_error_line(capsys, str(scene))
    assert needle.lower() in err.lower(), (needle, err)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene.yaml"]


def test_scene_that_is_a_folder_or_missing(tmp_path, capsys):
    (tmp_path / "dir.yaml").mkdir()
    for ref in (tmp_path / "dir.yaml", tmp_path / "missing.yaml"):
        assert main(["simulate", str(ref), "-o", str(tmp_path / "S"), *SMALL]) == 2
        _one_error_line(capsys, str(ref))


# ------------------------------------------------------------------ video2events

def _frames(n=5, h=4, w=6):
    rng = np.random.default_rng(1)
    return rng.uniform(0.1, 1.0, (n, h, w)).astype(np.float32), np.arange(n, dtype=np.int64) * 1000


def _npz(path, compressed=False, **arrays):
    (np.savez_compressed if compressed else np.savez)(path, **arrays)
    return path


def _npy_bytes(header: dict, payload: bytes) -> bytes:
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(buf, header)
    return b"\x93NUMPY\x01\x00"[:0] + buf.getvalue() + payload


def _crafted(path, shape):
    """An .npz whose frames header declares `shape` but holds 64 bytes (valid zip CRCs)."""
    f, t = _frames()
    buf = io.BytesIO()
    np.lib.format.write_array(buf, t)
    head = io.BytesIO()
    np.lib.format.write_array_header_1_0(
        head, {"descr": "<f4", "fortran_order": False, "shape": shape})
    with zipfile.ZipFile(path, "w") as z:
        z.writestr("frames.npy", b"\x93NUMPY\x01\x00" + head.getvalue()[8:] + bytes(64))
        z.writestr("t.npy", buf.getvalue())
    return path


def _bad_videos(d: Path):
    f, t = _frames()
    good = _npz(d / "good.npz", compressed=True, frames=f, t=t).read_bytes()
    cases = []

    def add(name, data_or_path, needle):
        p = d / name
        if isinstance(data_or_path, bytes):
            p.write_bytes(data_or_path)
        cases.append((p, needle))

    add("empty.npz", b"", "not a readable")
    add("text.npz", b"frames and times", "not a readable")
    add("trunc.npz", good[: len(good) // 2], "npz")
    with zipfile.ZipFile(io.BytesIO(good)) as z:
        info = z.getinfo("frames.npy")
    h = info.header_offset                       # local header: name and extra lengths
    data = h + 30 + int.from_bytes(good[h + 26:h + 28], "little") + int.from_bytes(
        good[h + 28:h + 30], "little")
    for k, pos in enumerate((data + 2, data + info.compress_size // 2)):
        bad = bytearray(good)
        bad[pos] ^= 0x5A
        add(f"flip{k}.npz", bytes(bad), "npz")
    np.save(d / "single.npy", f)
    (d / "single.npz").write_bytes((d / "single.npy").read_bytes())
    add("single.npz", d / "single.npz", "single .npy")
    add("no_t.npz", _npz(d / "no_t.npz", frames=f), "missing arrays ['t']")
    add("complex.npz", _npz(d / "complex.npz", frames=f.astype(np.complex64), t=t), "complex64")
    add("int16.npz", _npz(d / "int16.npz", frames=f.astype(np.int16), t=t), "int16")
    add("bool.npz", _npz(d / "bool.npz", frames=f > 0.5, t=t), "bool")
    add("object.npz", _npz(d / "object.npz", frames=np.array([None] * 5, dtype=object), t=t),
        "objects")
    add("2d.npz", _npz(d / "2d.npz", frames=f[0], t=t), "(N, H, W)")
    add("4d.npz", _npz(d / "4d.npz", frames=f[..., None], t=t), "(N, H, W)")
    add("zero.npz", _npz(d / "zero.npz", frames=f[:0], t=t[:0]), "at least one frame")
    g = f.copy()
    g[2, 1, 3] = np.nan
    add("nan.npz", _npz(d / "nan.npz", frames=g, t=t), "frame 2")
    g = f.copy()
    g[3, 0, 0] = -np.inf
    add("inf.npz", _npz(d / "inf.npz", frames=g, t=t), "frame 3")
    add("unsorted.npz", _npz(d / "unsorted.npz", frames=f, t=t[::-1].copy()), "increase")
    add("float_t.npz", _npz(d / "float_t.npz", frames=f, t=t * 1e-9), "not floats")
    add("short_t.npz", _npz(d / "short_t.npz", frames=f, t=t[:3]), "one time per frame")
    add("u64_t.npz", _npz(d / "u64_t.npz", frames=f,
                          t=np.uint64(2**63) + np.arange(5, dtype=np.uint64)), "2**62")
    add("huge.npz", _crafted(d / "huge.npz", (10**6, 10**6, 10**6)), "damaged or truncated")
    add("negshape.npz", _crafted(d / "negshape.npz", (-5, 4, 6)), "npz")
    return cases


def test_video2events_bad_frames_files(tmp_path, capsys):
    src = tmp_path / "in"
    src.mkdir()
    for path, needle in _bad_videos(src):
        out = tmp_path / "out.npz"
        assert main(["video2events", str(path), str(out)]) == 2, path
        _one_error_line(capsys, str(path), needle)
        assert not out.exists()
    assert main(["video2events", str(src), str(tmp_path / "out.npz")]) == 2
    _one_error_line(capsys, str(src))


def test_video2events_memory_is_checked_from_the_header(tmp_path, capsys, monkeypatch):
    f, t = _frames(n=50, h=40, w=60)
    path = _npz(tmp_path / "f.npz", frames=f, t=t)
    monkeypatch.setenv("EVDNERF_MEMORY_LIMIT", "100K")
    assert main(["video2events", str(path), str(tmp_path / "out.npz")]) == 2
    _one_error_line(capsys, str(path), "EVDNERF_MEMORY_LIMIT")


@pytest.mark.parametrize("flag, value", [
    ("--c-pos", "nan"), ("--c-pos", "0"), ("--c-neg", "inf"), ("--eps", "0"), ("--eps", "-1"),
    ("--sigma", "-0.1"), ("--sigma", "nan"), ("--interval-sigma", "1e30"),
    ("--refractory-ns", "-1"), ("--seed", "-3"),
])
def test_video2events_bad_flags(tmp_path, capsys, flag, value):
    f, t = _frames()
    path = _npz(tmp_path / "f.npz", frames=f, t=t)
    assert main(["video2events", str(path), str(tmp_path / "out.npz"), f"{flag}={value}"]) == 2
    _one_error_line(capsys, flag)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["f.npz"]


# ------------------------------------------------------------------ signals

@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="needs /proc (Linux)")
@pytest.mark.parametrize("how", ["SIGINT", "SIGTERM", "Ctrl-C", "SIGKILL"])
def test_workers_end_with_their_parent(tmp_path, how):
    """`simulate --jobs 2` stopped mid-run: no worker outlives it; SIGINT / SIGTERM (to the
    parent alone) and Ctrl-C (to the whole process group) leave no output folder."""
    out = tmp_path / "S"
    proc = subprocess.Popen(
        [sys.executable, "-c", "import sys; from evdnerf_ros.cli import main; sys.exit(main())",
         "simulate", "fork", "-o", str(out), "--jobs", "2", "--views", "6", "--val-views", "0",
         "--resolution", "48", "36", "--supersample", "1", "--frame-rate", "0", "--gt-times",
         "0"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        start_new_session=True)
    try:
        deadline = time.monotonic() + 60
        while len(child_pids(proc.pid)) < 2 and time.monotonic() < deadline:
            time.sleep(0.05)
        workers = child_pids(proc.pid)
        assert len(workers) >= 2, proc.communicate(timeout=30)
        time.sleep(0.5)                         # the workers are simulating now
        assert proc.poll() is None
        sent = time.monotonic()
        if how == "Ctrl-C":
            os.killpg(proc.pid, signal.SIGINT)
        else:
            proc.send_signal(getattr(signal, how))
        _, err = proc.communicate(timeout=60)
        # promptly: the whole run takes ~30 s; waiting for the views to finish is the bug
        assert time.monotonic() - sent < 10
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    deadline = time.monotonic() + 10
    while any(pid_alive(w) for w in workers) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not any(pid_alive(w) for w in workers), (how, workers)
    assert not out.exists()
    if how != "SIGKILL":                         # a killed parent cannot clean up
        assert proc.returncode in (130, 143), (proc.returncode, err)
        assert "Traceback" not in err, err
        assert list(tmp_path.iterdir()) == [], list(tmp_path.iterdir())
