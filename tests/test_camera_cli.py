"""`evdnerf camera list / info / record --virtual MODEL`: the CLI hosts the twin and runs the
driver against it in a child process; the bag holds the camera's own encoding."""

import json
import subprocess
import sys

import numpy as np
import pytest

from evdnerf_ros.io.event_files import read_event_file
from evdnerf_ros.io.rosbag2 import open_bag
from rig.camera.virtual.usb import umockdev_available

ok, why = umockdev_available()
pytestmark = pytest.mark.skipif(not ok, reason=why)

EVDNERF = [sys.executable, "-m", "evdnerf_ros"]


def cli(*argv, timeout=180):
    return subprocess.run([*EVDNERF, *argv], capture_output=True, text=True, timeout=timeout)


def test_list_and_info_of_a_virtual_camera():
    r = cli("camera", "list", "--virtual", "evk4", "--scene-size", "32x24")
    assert r.returncode == 0, r.stderr
    assert "EVK4 04b4:00f4" in r.stdout and "serial 000A1B2C" in r.stdout
    r = cli("camera", "info", "--virtual", "dvxplorer", "--scene-size", "32x24")
    assert r.returncode == 0, r.stderr
    info = json.loads(r.stdout)
    assert (info["model"], info["width"], info["height"], info["encoding"]) == ("DVXplorer", 640, 480, "libcaer")
    assert "current_on" in info["biases"]


@pytest.mark.parametrize("model, encoding, size", [("dvxplorer", "libcaer", (640, 480)),
                                                   ("evk4", "evt3", (1280, 720))])
def test_record_a_virtual_camera(tmp_path, model, encoding, size):
    bag = tmp_path / "bag"
    r = cli("camera", "record", "--virtual", model, "--scene-size", "48x36", "-o", str(bag), "--duration", "1.5")
    assert r.returncode == 0, r.stderr
    with open_bag(bag) as b:
        msgs = list(b.read_messages("/event_camera/events"))
    assert msgs and all(m.encoding == encoding for _, m in msgs)
    data = read_event_file(bag)
    ev = data.events
    assert (data.width, data.height) == size and ev.size > 1000
    assert np.all(np.diff(ev["t"]) >= 0)
    # the scene is rendered at 48x36 in the sensor's centre; the rest of the array stays quiet
    x0, y0 = (size[0] - 48) // 2, (size[1] - 36) // 2
    assert ev["x"].min() >= x0 and ev["x"].max() < x0 + 48 and ev["y"].min() >= y0 and ev["y"].max() < y0 + 36


def test_bad_camera_arguments_are_one_line(tmp_path):
    r = cli("camera", "record", "--virtual", "evk4")
    assert r.returncode == 2 and "-o BAG" in r.stderr and r.stderr.count("\n") == 1
    r = cli("camera", "list", "--scene", "jet-down")
    assert r.returncode == 2 and "--virtual" in r.stderr
    r = cli("camera", "list", "--virtual", "evk4", "--scene-size", "2000x2000")
    assert r.returncode == 2 and "does not fit" in r.stderr
