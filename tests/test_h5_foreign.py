"""HDF5 event files from other writers (DSEC's and v2e's events/{t,x,y,p}): the time unit is
never guessed (a time_unit attribute, else --time-unit), 0/1 polarity, and --geometry where the
file has no width / height (io/h5events.py)."""

import json

import h5py
import numpy as np
import pytest

from evdnerf_ros.cli import main
from evdnerf_ros.errors import FormatError, InputError
from evdnerf_ros.io.event_files import read_event_file

T_US = np.array([1_000, 1_250, 2_000, 4_000_017], np.uint32)


def _dsec(path, *, t=T_US, p=(1, 0, 1, 0), attrs=None, t_attrs=None):
    """A file as DSEC writes one: uint32 microseconds, uint8 0/1 polarity, no width / height."""
    with h5py.File(path, "w") as f:
        g = f.create_group("events")
        g.create_dataset("t", data=np.asarray(t))
        g.create_dataset("x", data=np.array([1, 2, 639, 0], np.uint16))
        g.create_dataset("y", data=np.array([5, 479, 7, 0], np.uint16))
        g.create_dataset("p", data=np.array(p, np.uint8 if min(p) >= 0 else np.int8))
        f.attrs.update(attrs or {})
        g["t"].attrs.update(t_attrs or {})
    return path


def test_a_file_without_a_time_unit_needs_one(tmp_path):
    p = _dsec(tmp_path / "events.h5")
    with pytest.raises(InputError, match=r"events\.h5: events/t has no time_unit attribute.*--time-unit"):
        read_event_file(p)
    with pytest.raises(InputError, match=r"no width / height attributes.*--geometry WxH"):
        read_event_file(p, time_unit="us")
    d = read_event_file(p, time_unit="us", geometry=(640, 480))
    assert d.events["t"].tolist() == [int(v) * 1000 for v in T_US]
    assert d.events["p"].tolist() == [1, -1, 1, -1] and (d.width, d.height) == (640, 480)
    # read in the wrong unit, the same file spans 1000x the time: the unit is what the user says
    assert read_event_file(p, time_unit="ns", geometry=(640, 480)).events["t"].tolist() == T_US.tolist()


@pytest.mark.parametrize("where", ["t", "file"])
@pytest.mark.parametrize("unit, ns", [("us", 1000), ("µs", 1000), ("ms", 1_000_000), ("ns", 1)])
def test_the_files_time_unit_is_honoured(tmp_path, where, unit, ns):
    attrs = {"width": 640, "height": 480}
    p = _dsec(tmp_path / "u.h5", attrs={**attrs, **({"time_unit": unit} if where == "file" else {})},
              t_attrs={"time_unit": unit} if where == "t" else None)
    d = read_event_file(p)
    assert d.events["t"].tolist() == [int(v) * ns for v in T_US]
    same = "us" if unit == "µs" else unit
    assert read_event_file(p, time_unit=same).events["t"].tolist() == d.events["t"].tolist()
    other = "s" if same != "s" else "ns"
    with pytest.raises(InputError, match=f"time_unit attribute says {same}, --time-unit says {other}"):
        read_event_file(p, time_unit=other)


def test_bad_units_polarities_and_overflow_are_clear_errors(tmp_path):
    p = _dsec(tmp_path / "minutes.h5", attrs={"width": 640, "height": 480, "time_unit": "min"})
    with pytest.raises(InputError, match=r"minutes\.h5: attribute time_unit: time unit 'min' is not one of"):
        read_event_file(p)
    p = _dsec(tmp_path / "mixed.h5", p=(1, 0, -1, 1), attrs={"width": 640, "height": 480, "time_unit": "us"})
    with pytest.raises(FormatError, match=r"events/p must hold \+1/-1 or 0/1"):
        read_event_file(p)
    p = _dsec(tmp_path / "huge.h5", t=np.array([0, 1, 2, 2**62], np.int64),
              attrs={"width": 640, "height": 480, "time_unit": "s"})
    with pytest.raises(FormatError, match="beyond int64 nanoseconds; check --time-unit"):
        read_event_file(p)
    raw = tmp_path / "x.raw"
    raw.write_bytes(b"% evt 3.0\n% geometry 8x8\n% end\n")
    with pytest.raises(InputError, match="--time-unit applies only to HDF5 and text files"):
        read_event_file(raw, time_unit="us")


def test_the_cli_takes_time_unit_and_geometry(tmp_path, capsys):
    p = _dsec(tmp_path / "events.h5")
    assert main(["info", str(p)]) == 2
    err = capsys.readouterr().err
    assert "events.h5" in err and "--time-unit" in err and "Traceback" not in err
    assert main(["info", str(p), "--time-unit", "us", "--geometry", "640x480", "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["events"]["count"] == 4 and info["events"]["width"] == 640
    assert info["events"]["t_last_ns"] == 4_000_017_000
    out = tmp_path / "ours.h5"
    assert main(["convert-events", str(p), str(out), "--time-unit", "us", "--geometry", "640x480"]) == 0
    capsys.readouterr()
    back = read_event_file(out)              # ours says time_unit: ns: no flag needed
    assert back.events["t"].tolist() == [int(v) * 1000 for v in T_US]
    assert main(["render-events", str(p), "--start", "0", "--window", "5ms", "-o", str(tmp_path / "e.png"),
                 "--time-unit", "us", "--geometry", "640x480"]) == 0
