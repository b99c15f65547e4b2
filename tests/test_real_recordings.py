"""Real recordings from real cameras (../shared/data/real/, see its README for the sources and
the reference values their projects test against). Skipped where that folder is absent."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from evdnerf_ros.cli import main
from evdnerf_ros.io.event_files import read_event_file
from evdnerf_ros.io.raw import read_raw_header

REAL = Path(os.environ.get("EVDNERF_REAL_DATA", Path(__file__).resolve().parents[1].parent / "shared" / "data" / "real"))
EXPELLIARMUS = REAL / "expelliarmus"
pytestmark = pytest.mark.skipif(not EXPELLIARMUS.is_dir(), reason=f"real recordings not found at {REAL}")


def test_gen41_evt3_file_decodes_as_openeb_does():
    """A Gen4.1 writes a TIME_LOW at once replaced by a lower one about once per ms: not
    corruption. Reference: 219,596 CD events at 11,718,656 .. 11,727,457 us."""
    path = EXPELLIARMUS / "evt3_sample.raw"
    data = read_event_file(path)
    ev = data.events
    assert ev.size == 219_596
    assert (int(ev["t"][0]) // 1000, int(ev["t"][-1]) // 1000) == (11_718_656, 11_727_457)
    assert np.all(np.diff(ev["t"]) >= 0)
    assert (data.width, data.height) == (1280, 720)          # from plugin_name hal_plugin_gen41_evk3
    assert data.anomalies["time_low_back"] > 0
    # expelliarmus' own decode has x, y, p right (its times drift at each TIME_LOW decrease)
    theirs = np.load(EXPELLIARMUS / "evt3_sample.npy")
    assert np.array_equal(ev["x"], theirs["x"]) and np.array_equal(ev["y"], theirs["y"])
    assert np.array_equal(ev["p"], np.where(theirs["p"] > 0, 1, -1))


def test_gen3_evt2_file_without_geometry_line():
    """Reference: 539,481 CD events at 1,317,888 .. 1,367,888 us; no geometry line (640x480)."""
    path = EXPELLIARMUS / "evt2_sample.raw"
    assert (read_raw_header(path).width, read_raw_header(path).height) == (640, 480)
    ev = read_event_file(path).events
    assert ev.size == 539_481
    assert (int(ev["t"][0]) // 1000, int(ev["t"][-1]) // 1000) == (1_317_888, 1_367_888)


def test_cli_reads_and_converts_the_real_evt3_file(tmp_path, capsys):
    path = EXPELLIARMUS / "evt3_sample.raw"
    assert main(["info", str(path)]) == 0
    out = capsys.readouterr().out
    assert "1280x720" in out and "tolerated" in out and "time low back" in out
    assert main(["convert-events", str(path), str(tmp_path / "e.npz")]) == 0
    assert main(["render-events", str(tmp_path / "e.npz"), "--start", "0", "--window", "1ms",
                 "-o", str(tmp_path / "e.png")]) == 0
    assert read_event_file(tmp_path / "e.npz").events.size == 219_596
