"""video2events: FRAMES.npz loading and validation, the library job, written outputs."""

from __future__ import annotations

import numpy as np
import pytest

from evdnerf_ros.errors import InputError, OutputExistsError
from evdnerf_ros.sim import (EventGenerator, linearize_8bit, load_frames_npz, run_video2events,
                             video_to_events)


def _video(rng, n=10, h=6, w=7):
    frames = rng.uniform(0.0, 2.0, (n, h, w)).astype(np.float32)
    t = (np.arange(n, dtype=np.int64) * 3_333_333) + 10**12
    return frames, t


def _save(path, **arrays):
    np.savez(path, **arrays)
    return path


def test_video_to_events_is_the_generator(rng):
    frames, t = _video(rng)
    ev = video_to_events(frames, t, c_pos=0.15, c_neg=0.25, threshold_sigma=0.02, seed=3)
    want = EventGenerator(7, 6, c_pos=0.15, c_neg=0.25, threshold_sigma=0.02,
                          seed=3).generate(frames, t)
    assert ev.size > 100 and ev.tobytes() == want.tobytes()


def test_load_frames_round_trip(tmp_path, rng):
    frames, t = _video(rng)
    path = _save(tmp_path / "f.npz", frames=frames, t=t)
    f2, t2 = load_frames_npz(path)
    assert np.array_equal(f2, frames) and np.array_equal(t2, t) and t2.dtype == np.int64


def test_8bit_frames_need_the_gamma_flag(tmp_path, rng):
    frames = rng.integers(0, 256, (4, 3, 5)).astype(np.uint8)
    t = np.arange(4, dtype=np.int64) * 1000
    path = _save(tmp_path / "f8.npz", frames=frames, t=t)
    with pytest.raises(InputError, match=r"f8.npz: frames are 8-bit .*--gamma-8bit"):
        load_frames_npz(path)
    lin, _ = load_frames_npz(path, gamma_8bit=True)
    np.testing.assert_allclose(lin, (frames / 255.0) ** 2.2, rtol=1e-6)
    assert linearize_8bit(np.array([0, 255], np.uint8)).tolist() == [0.0, 1.0]
    fpath = _save(tmp_path / "ff.npz", frames=frames.astype(np.float32), t=t)
    with pytest.raises(InputError, match="only to uint8"):
        load_frames_npz(fpath, gamma_8bit=True)
    with pytest.raises(InputError, match="uint16"):
        load_frames_npz(_save(tmp_path / "f16.npz", frames=frames.astype(np.uint16), t=t))


@pytest.mark.parametrize("value, what", [(np.nan, "not finite"), (np.inf, "not finite"),
                                         (-0.1, "negative")])
def test_bad_radiance_names_file_and_frame(tmp_path, rng, value, what):
    frames, t = _video(rng)
    frames[6, 2, 3] = value
    path = _save(tmp_path / "bad.npz", frames=frames, t=t)
    with pytest.raises(InputError, match=rf"bad.npz: frame 6 at t={t[6]} ns.*\(2, 3\).*{what}"):
        load_frames_npz(path)


def test_bad_times_and_shapes(tmp_path, rng):
    frames, t = _video(rng)
    t2 = t.copy()
    t2[4] = t2[3]
    with pytest.raises(InputError, match=r"t.npz: frame 4 time .* not after frame 3"):
        load_frames_npz(_save(tmp_path / "t.npz", frames=frames, t=t2))
    with pytest.raises(InputError, match="int64 nanoseconds, not floats"):
        load_frames_npz(_save(tmp_path / "tf.npz", frames=frames, t=t * 1e-9))
    with pytest.raises(InputError, match=r"shape \(9,\), expected \(10,\)"):
        load_frames_npz(_save(tmp_path / "tn.npz", frames=frames, t=t[:9]))
    with pytest.raises(InputError, match=r"expected \(N, H, W\)"):
        load_frames_npz(_save(tmp_path / "s.npz", frames=frames[:, :, :, None], t=t))
    with pytest.raises(InputError, match=r"missing arrays \['t'\]"):
        load_frames_npz(_save(tmp_path / "m.npz", frames=frames))
    with pytest.raises(InputError, match="no such file"):
        load_frames_npz(tmp_path / "nope.npz")
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(InputError, match="junk.npz: not a readable"):
        load_frames_npz(tmp_path / "junk.npz")


@pytest.mark.parametrize("suffix", [".npz", ".h5"])
def test_run_video2events_writes_readable_output(tmp_path, rng, suffix):
    from evdnerf_ros.io.event_files import read_event_file

    frames, t = _video(rng)
    src = _save(tmp_path / "frames.npz", frames=frames, t=t)
    out = tmp_path / f"events{suffix}"
    n = run_video2events(src, out, c_pos=0.2, c_neg=0.2, eps=1e-3, sigma=0.03,
                         refractory_ns=1000, seed=7, gamma_8bit=False)
    back = read_event_file(out)
    want = EventGenerator(7, 6, threshold_sigma=0.03, refractory_ns=1000, seed=7).generate(frames, t)
    assert n == back.events.size == want.size > 0
    assert (back.width, back.height) == (7, 6)
    assert np.array_equal(back.events, want)
    with pytest.raises(OutputExistsError):
        run_video2events(src, out, c_pos=0.2, c_neg=0.2, eps=1e-3, sigma=0.0, refractory_ns=0,
                         seed=0, gamma_8bit=False)


def test_run_video2events_leaves_nothing_on_bad_input(tmp_path, rng):
    frames, t = _video(rng)
    frames[1, 0, 0] = np.nan
    src = _save(tmp_path / "frames.npz", frames=frames, t=t)
    with pytest.raises(InputError, match="frame 1"):
        run_video2events(src, tmp_path / "out.npz")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["frames.npz"]
