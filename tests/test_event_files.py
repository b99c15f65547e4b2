"""npz and h5 event files, atomic outputs and exact time parsing."""

import numpy as np
import pytest

from conftest import random_events
from evdnerf_ros.atomic import atomic_output
from evdnerf_ros.errors import InputError, OutputExistsError
from evdnerf_ros.events import make_triggers, time_slice
from evdnerf_ros.io.h5events import read_h5, read_h5_window, write_h5
from evdnerf_ros.io.npz import read_npz, write_npz
from evdnerf_ros.units import format_ns, parse_duration_ns


def test_npz_round_trip_with_triggers(tmp_path, rng):
    ev = random_events(rng, 10_000, t0=1_700_000_000_000_000_000)
    tr = make_triggers([ev["t"][5], ev["t"][50]], [0, 1], [1, 0])
    write_npz(tmp_path / "a.npz", ev, 64, 48, tr)
    got, got_tr, w, h = read_npz(tmp_path / "a.npz")
    assert np.array_equal(got, ev) and np.array_equal(got_tr, tr) and (w, h) == (64, 48)


def test_npz_bad_inputs_name_the_file(tmp_path):
    p = tmp_path / "float_t.npz"
    np.savez(p, t=np.array([0.5, 1.0]), x=[0, 1], y=[0, 0], p=[1, -1], width=4, height=4)
    with pytest.raises(InputError, match="float_t.npz.*int64 nanoseconds"):
        read_npz(p)
    p = tmp_path / "missing.npz"
    np.savez(p, t=np.array([1, 2]), x=[0, 1])
    with pytest.raises(InputError, match=r"missing.npz: missing arrays \['y', 'p', 'width', 'height'\]"):
        read_npz(p)
    p = tmp_path / "oob.npz"
    np.savez(p, t=np.array([1, 2]), x=[0, 70000], y=[0, 0], p=[1, -1], width=4, height=4)
    with pytest.raises(InputError, match="oob.npz: x outside"):
        read_npz(p)
    p = tmp_path / "pol.npz"
    np.savez(p, t=np.array([1, 2]), x=[0, 1], y=[0, 0], p=[1, 0], width=4, height=4)
    with pytest.raises(InputError, match=r"pol.npz: p must hold \+1/-1"):
        read_npz(p)
    p = tmp_path / "unsorted.npz"
    np.savez(p, t=np.array([2, 1]), x=[0, 1], y=[0, 0], p=[1, -1], width=4, height=4)
    with pytest.raises(InputError, match="unsorted.npz: timestamps not sorted"):
        read_npz(p)
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(InputError, match="junk.npz: not a readable"):
        read_npz(tmp_path / "junk.npz")


def test_h5_round_trip_and_window_reads(tmp_path, rng):
    ev = random_events(rng, 50_000, t0=-3_000_000, span=2_500_000_000)
    write_h5(tmp_path / "a.h5", ev, 64, 48)
    got, tr, w, h = read_h5(tmp_path / "a.h5")
    assert np.array_equal(got, ev) and len(tr) == 0 and (w, h) == (64, 48)
    for a, b in [(0, 10 ** 6), (-10 ** 9, 10 ** 8), (123_456_789, 987_654_321), (5, 5),
                 (2_400_000_000, 9_000_000_000), (-10 ** 12, -10 ** 11)]:
        assert np.array_equal(read_h5_window(tmp_path / "a.h5", a, b), time_slice(ev, a, b))


def test_h5_refuses_existing_and_bad_files(tmp_path, rng):
    ev = random_events(rng, 10)
    write_h5(tmp_path / "a.h5", ev, 64, 48)
    with pytest.raises(OutputExistsError, match="a.h5: output already exists"):
        write_h5(tmp_path / "a.h5", ev, 64, 48)
    (tmp_path / "b.h5").write_bytes(b"garbage")
    with pytest.raises(InputError, match="b.h5: not a readable HDF5"):
        read_h5(tmp_path / "b.h5")


def test_out_of_bounds_events_are_not_written(tmp_path, rng):
    ev = random_events(rng, 100, width=64)
    with pytest.raises(InputError, match="outside the declared 32x48"):
        write_h5(tmp_path / "a.h5", ev, 32, 48)
    assert list(tmp_path.iterdir()) == []


def test_atomic_output_leaves_nothing_on_failure(tmp_path):
    with pytest.raises(RuntimeError):
        with atomic_output(tmp_path / "out.bin") as tmp:
            tmp.write_bytes(b"half")
            raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []
    with atomic_output(tmp_path / "bagdir", directory=True) as tmp:
        assert not tmp.exists()
        tmp.mkdir()
        (tmp / "x").write_text("1")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bagdir"]
    with pytest.raises(InputError, match="parent folder"):
        with atomic_output(tmp_path / "no" / "such" / "file"):
            pass


@pytest.mark.parametrize("text,ns", [("1.5", 1_500_000_000), ("20ms", 20_000_000),
                                      ("150us", 150_000), ("7ns", 7), ("0.000000001s", 1),
                                      ("-2s", -2_000_000_000), ("4611686018.427387904", 2 ** 62),
                                      ("-4611686018427387904ns", -2 ** 62)])
def test_parse_duration_exact(text, ns):
    assert parse_duration_ns(text) == ns


@pytest.mark.parametrize("text", ["abc", "1.5ns", "0.0000000001", "", "inf", "nan", "4611686018.427387905",
                                  "9223372036.854775807", "1e30"])
def test_parse_duration_rejects(text):
    with pytest.raises(InputError):
        parse_duration_ns(text, name="--start")


def test_format_ns():
    assert format_ns(-1_500_000_001) == "-1.500000001 s"
