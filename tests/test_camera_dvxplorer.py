"""The DVXplorer driver (rig.camera.dvxplorer) in a child process against its virtual twin
(rig.camera.virtual.dvxplorer) served through umockdev, and neuromorphic-drivers as an
independent peer on the same twin. Skipped where umockdev / gi / the preload are missing."""

from __future__ import annotations

import json
import textwrap

import numpy as np
import pytest

from evdnerf_ros.events.types import EVENT_DTYPE
from rig.camera import dvxplorer as D
from rig.camera.caer_words import canonical_order
from rig.camera.virtual.usb import umockdev_available

ok, why = umockdev_available()
pytestmark = pytest.mark.skipif(not ok, reason=why)

if ok:
    from rig.camera.virtual.dvxplorer import VirtualDVXplorer, thresholds_from_biases
    from rig.camera.virtual.usb import VirtualUsbBus, run_child, spawn_child

PRELUDE = """
import json, sys, time
import numpy as np
from rig.camera.dvxplorer import DVXplorer
from rig.camera.errors import CameraDisconnected, CameraError, CameraProtocolError
OUT = sys.argv[1]
def read_until(cam, t_us, limit_s=30.0):
    parts, trig = [], []
    t0 = time.monotonic()
    while time.monotonic() - t0 < limit_s:
        c = cam.read(1.0)
        if c is None:
            break
        parts.append(c.events); trig.append(c.triggers)
        if cam.decoder.time_us >= t_us:
            break
    ev = np.concatenate(parts) if parts else np.empty(0, [("t", "<i8"), ("x", "<u2"), ("y", "<u2"), ("p", "i1")])
    return ev, np.concatenate(trig) if trig else None
"""


def run_driver(bus, tmp_path, body: str, timeout=90):
    """Run PRELUDE + body in a child under the bus; returns the JSON it dumped to OUT (a dict)."""
    script = tmp_path / "child.py"
    script.write_text(PRELUDE + textwrap.dedent(body))
    out = tmp_path / "out.json"
    res = run_child([__import__("sys").executable, str(script), str(out)], bus, timeout=timeout)
    assert res.returncode == 0, f"driver child failed:\n{res.stdout}\n{res.stderr[-4000:]}"
    return json.loads(out.read_text()), res


def make_events(n, span_us, seed=0, t0_us=1):
    rng = np.random.default_rng(seed)
    ev = np.empty(n, EVENT_DTYPE)
    ev["t"] = np.sort(rng.integers(t0_us, span_us, n)) * 1000
    ev["x"] = rng.integers(0, 640, n)
    ev["y"] = rng.integers(0, 480, n)
    ev["p"] = rng.choice(np.array([-1, 1], np.int8), n)
    return ev


@pytest.fixture
def bus():
    with VirtualUsbBus() as b:
        yield b


def test_open_start_order_and_events_bit_for_bit_across_wraps(bus, tmp_path):
    ev = make_events(40_000, 3_000_000, seed=1)                 # 3 s: 91 timestamp wraps
    twin = VirtualDVXplorer(ev, realtime=False, step_us=20_000)
    bus.add(twin)
    info, _ = run_driver(bus, tmp_path, """
        cam = DVXplorer().open()
        n_open = None
        ident = dict(serial=cam.serial, fw=cam.firmware_version, logic=cam.logic_version,
                     patch=cam.logic_patch, w=cam.width, h=cam.height, encoding=cam.encoding)
        print("OPENED", flush=True)
        cam.start()
        ev, _ = read_until(cam, 3_000_000)
        cam.stop()
        np.save(OUT + ".npy", ev)
        ident.update(stats=cam.stats.as_dict(), resets=cam.decoder.resets,
                     drift=cam.clock.drift_ppm)
        cam.close()
        json.dump(ident, open(OUT, "w"))
    """)
    assert info["serial"] == "DVX00001" and info["fw"] == 8 and info["logic"] == 18 and info["patch"] == 2
    assert (info["w"], info["h"], info["encoding"]) == (640, 480, "libcaer")
    got = np.load(str(tmp_path / "out.json") + ".npy")
    truth = twin.emitted_events()
    assert np.array_equal(truth, canonical_order(ev))        # the twin sent every input event
    assert np.array_equal(got, truth)                         # ... and the driver got them, bit for bit
    assert info["stats"]["dropped_chunks"] == 0
    # the start order of libcaer: all off, ..., then USB, MUX TS, MUX, DVS run, sensor stream mode
    w = twin.writes
    idx = {k: i for i, k in enumerate(w) if k[2] == 1 and k[:2] in
           {(9, 0), (0, 1), (0, 0), (1, 3)}}
    order = sorted(idx, key=idx.get)
    assert [k[:2] for k in order] == [(9, 0), (0, 1), (0, 0), (1, 3)]
    first_run = min(idx.values())
    off_before = [k[:2] for k in w[:first_run] if k[2] == 0]
    for key in [(1, 3), (4, 0), (0, 0), (0, 1), (9, 0)]:
        assert key in off_before                              # everything off before the start
    assert (0, 3, 1) in w[:first_run]                         # sensor out of reset at open
    stream_mode = w.index((5, D.REG_CONTROL_MODE, 2))
    assert stream_mode > idx[(1, 3, 1)]
    # stop in reverse: sensor mode off, DVS, ..., MUX, MUX TS, USB
    tail = [k for k in w[stream_mode + 1:] if k[2] == 0 and k[:2] in
            {(5, D.REG_CONTROL_MODE), (1, 3), (0, 0), (0, 1), (9, 0)}]
    assert [k[:2] for k in tail][:5] == [(5, D.REG_CONTROL_MODE), (1, 3), (0, 0), (0, 1), (9, 0)]
    assert twin.stalled == []
    assert not twin.streaming


def test_trigger_edges_biases_roi_and_timestamp_reset(bus, tmp_path):
    twin = VirtualDVXplorer(None, realtime=True)
    bus.add(twin)
    proc = spawn_child([__import__("sys").executable, "-c", PRELUDE + textwrap.dedent("""
        cam = DVXplorer().open()
        res = {"biases0": cam.biases, "roi0": cam.roi}
        cam.set_biases({"current_on": 6, "current_off": 2, "current_range_logd": 2, "current_level_sf": 1})
        cam.set_roi(10, 13, 100, 2)                  # rows 13..14: one 8-row group (libcaer corner case)
        res["roi1"] = cam.roi
        cam.set_roi(33, 5, 200, 300)
        res["roi2"] = cam.roi
        res["biases1"] = cam.biases
        try:
            cam.set_biases({"bias_diff_on": 3})
        except CameraError as exc:
            res["unknown_bias"] = str(exc)
        cam.enable_trigger_input(True)
        cam.start()
        print("STREAMING", flush=True)
        trig = []
        t0 = time.monotonic()
        while time.monotonic() - t0 < 10 and len(trig) < 4:
            c = cam.read(0.5)
            if c is not None and c.triggers.size:
                trig += c.triggers.tolist()
        cam.reset_timestamps()
        t0 = time.monotonic()
        while time.monotonic() - t0 < 5 and cam.decoder.resets == 0:
            cam.read(0.5)
        res["resets"] = cam.decoder.resets
        res["trig"] = trig
        cam.stop()
        cam.clear_roi()
        res["roi3"] = cam.roi
        cam.close()
        json.dump(res, open(OUT, "w"))
    """), str(tmp_path / "out.json")], bus)
    try:
        assert proc.stdout.readline().strip() == "STREAMING"
        import time
        edges = []
        while len(edges) < 2:
            e = twin.pulse_trigger(width_us=250)
            if e is not None:
                edges.append(e)
            time.sleep(0.2)
        out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, err[-4000:]
    res = json.loads((tmp_path / "out.json").read_text())
    assert res["biases0"]["current_on"] == 0 and res["biases0"]["current_off"] == 8   # libcaer default
    assert res["roi0"] is None
    assert res["roi1"] == [10, 13, 100, 2] and res["roi2"] == [33, 5, 200, 300] and res["roi3"] is None
    b = res["biases1"]
    assert (b["current_on"], b["current_off"], b["current_range_logd"], b["current_level_sf"]) == (6, 2, 2, 1)
    assert twin.biases() == b
    assert twin.thresholds() == thresholds_from_biases(6, 2)
    assert "bias_diff_on" in res["unknown_bias"] and "current_on" in res["unknown_bias"]
    want = []
    for rise, fall in edges:
        want += [[rise, 0, 1], [fall, 0, 0]]
    assert res["trig"] == want
    assert np.array_equal(twin.emitted_triggers()["t"], [w[0] for w in want])
    assert res["resets"] == 1
    assert any(w[:2] == (0, 2) for w in twin.writes)          # the 0xC2 batch reached the multiplexer


def test_roi_crops_the_stream(bus, tmp_path):
    ev = make_events(20_000, 1_000_000, seed=2)
    twin = VirtualDVXplorer(ev, realtime=False, step_us=20_000)
    bus.add(twin)
    run_driver(bus, tmp_path, """
        cam = DVXplorer().open()
        cam.set_roi(100, 13, 300, 200)
        cam.start()
        ev, _ = read_until(cam, 1_000_000)
        cam.stop(); cam.close()
        np.save(OUT + ".npy", ev)
        json.dump({}, open(OUT, "w"))
    """)
    got = np.load(str(tmp_path / "out.json") + ".npy")
    keep = (ev["x"] >= 100) & (ev["x"] < 400) & (ev["y"] >= 13) & (ev["y"] < 213)
    assert 0 < got.size < ev.size
    assert np.array_equal(got, canonical_order(ev[keep]))


def test_unknown_request_stalls_and_old_firmware_is_refused(bus, tmp_path):
    twin = VirtualDVXplorer(None)
    old = VirtualDVXplorer(None, serial="OLDFW001", firmware=7)
    patch = VirtualDVXplorer(None, serial="PATCH001", logic_patch=1)
    for d in (twin, old, patch):
        bus.add(d)
    res, _ = run_driver(bus, tmp_path, """
        res = {}
        cam = DVXplorer("DVX00001").open()
        try:
            cam.link.control_out(0x40, 0xB8, 0, 0, b"\\x00" * 4)
        except CameraProtocolError as exc:
            res["stall"] = str(exc)
        res["still_usable"] = cam.config_read(6, 0)
        cam.close()
        for serial in ("OLDFW001", "PATCH001"):
            try:
                DVXplorer(serial).open()
            except CameraProtocolError as exc:
                res[serial] = str(exc)
        try:
            DVXplorer("NOSUCH").open()
        except CameraError as exc:
            res["missing"] = type(exc).__name__ + ": " + str(exc)
        json.dump(res, open(OUT, "w"))
    """)
    assert "stalled" in res["stall"] and "0xb8" in res["stall"].lower()
    assert [(s.request, s.request_type) for s in twin.stalled] == [(0xB8, 0x40)]
    assert res["still_usable"] == 18
    assert "firmware version 7" in res["OLDFW001"] and "8" in res["OLDFW001"]
    assert "patch level 1" in res["PATCH001"]
    assert res["missing"].startswith("CameraNotFound") and "DVX00001" in res["missing"]


def test_idle_read_times_out_and_unplug_keeps_what_came_before(bus, tmp_path):
    idle = VirtualDVXplorer(None, serial="IDLE0001", idle_wraps=False)
    live = VirtualDVXplorer(make_events(200_000, 20_000_000, seed=3), serial="LIVE0001", realtime=True)
    bus.add(idle)
    bus.add(live)
    proc = spawn_child([__import__("sys").executable, "-c", PRELUDE + textwrap.dedent("""
        res = {}
        cam = DVXplorer("IDLE0001").open(); cam.start()
        t0 = time.monotonic(); r = cam.read(0.3); res["idle"] = [r is None, time.monotonic() - t0]
        cam.stop(); cam.close()
        cam = DVXplorer("LIVE0001").open(); cam.start()
        parts = []
        while sum(p.size for p in parts) < 2000:
            c = cam.read(2.0)
            if c is not None:
                parts.append(c.events)
        print("GOT", flush=True)
        try:
            while True:
                c = cam.read(2.0)
                if c is not None:
                    parts.append(c.events)
        except CameraDisconnected as exc:
            res["unplug"] = str(exc)
        res["stats"] = cam.stats.as_dict()
        np.save(OUT + ".npy", np.concatenate(parts))
        json.dump(res, open(OUT, "w"))
        # under umockdev libusb never reaps the transfers of an unplugged device (it learns of
        # an unplug from poll errors a regular file never gives), so closing would wait forever
        import os; os._exit(0)
    """), str(tmp_path / "out.json")], bus)
    try:
        assert proc.stdout.readline().strip() == "GOT"
        live.unplug()
        _out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, err[-4000:]
    res = json.loads((tmp_path / "out.json").read_text())
    assert res["idle"][0] and 0.25 <= res["idle"][1] < 2.0
    assert "unplug" in res["unplug"].lower()
    got = np.load(str(tmp_path / "out.json") + ".npy")
    truth = live.emitted_events()
    assert got.size >= 2000
    assert np.array_equal(got, truth[:got.size])              # everything before the unplug, in order


def test_slow_consumer_gets_counted_drops(bus, tmp_path):
    twin = VirtualDVXplorer(make_events(400_000, 4_000_000, seed=4), realtime=False, step_us=10_000)
    bus.add(twin)
    res, _ = run_driver(bus, tmp_path, """
        import warnings
        cam = DVXplorer(queue_chunks=4).open(); cam.start()
        time.sleep(2.0)                                # the consumer falls behind
        got = 0
        for _ in range(20):
            c = cam.read(0.5)
            if c is None:
                break
            got += c.events.size
        cam.stop()
        json.dump({"stats": cam.stats.as_dict(), "got": got}, open(OUT, "w"))
        cam.close()
    """)
    s = res["stats"]
    assert s["dropped_chunks"] > 0 and s["dropped_bytes"] > 0
    assert s["queue_high_water"] == 4
    assert s["bytes"] > s["dropped_bytes"]


def test_neuromorphic_drivers_decodes_exactly_the_twins_events(bus, tmp_path):
    pytest.importorskip("neuromorphic_drivers")
    ev = make_events(3000, 1_500_000, seed=5)                   # 45 timestamp wraps
    twin = VirtualDVXplorer(ev, realtime=False, step_us=50_000, firmware=9, logic_patch=4, idle_wraps=False)
    bus.add(twin)
    script = tmp_path / "peer.py"
    script.write_text(textwrap.dedent("""
        import sys, time
        import numpy as np
        import neuromorphic_drivers as nd
        parts, t0 = [], time.monotonic()
        with nd.open(iterator_timeout=1.0) as device:
            for status, packet in device:
                if packet is None or time.monotonic() - t0 > 30:
                    break
                if packet.polarity_events is not None and len(packet.polarity_events):
                    parts.append(packet.polarity_events.copy())
        np.save(sys.argv[1], np.concatenate(parts))
    """))
    res = run_child([__import__("sys").executable, str(script), str(tmp_path / "nd.npy")], bus, timeout=90)
    assert res.returncode == 0, res.stderr[-4000:]
    nd_ev = np.load(tmp_path / "nd.npy")
    truth = twin.emitted_events()
    assert np.array_equal(truth, canonical_order(ev))
    assert nd_ev.size == truth.size
    assert np.array_equal(nd_ev["t"].astype(np.int64) * 1000, truth["t"])
    assert np.array_equal(nd_ev["x"], truth["x"]) and np.array_equal(nd_ev["y"], truth["y"])
    assert np.array_equal(nd_ev["on"], truth["p"] > 0)
