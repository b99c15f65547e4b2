"""The DAVIS346 driver (rig.camera.davis346) in a child process against its virtual twin
(rig.camera.virtual.davis346) served through umockdev, and neuromorphic-drivers as an independent
peer on the same twin. Skipped where umockdev / gi / the preload are missing."""

from __future__ import annotations

import json
import sys
import textwrap
import time

import numpy as np
import pytest

from evdnerf_ros.events.types import EVENT_DTYPE
from rig.camera import davis346 as D
from rig.camera.virtual.usb import umockdev_available

ok, why = umockdev_available()
pytestmark = pytest.mark.skipif(not ok, reason=why)

if ok:
    from rig.camera.virtual.davis346 import VirtualDAVIS346
    from rig.camera.virtual.usb import VirtualUsbBus, run_child, spawn_child

PRELUDE = """
import json, sys, time
import numpy as np
from rig.camera.davis346 import DAVIS346
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
    script = tmp_path / "child.py"
    script.write_text(PRELUDE + textwrap.dedent(body))
    out = tmp_path / "out.json"
    res = run_child([sys.executable, str(script), str(out)], bus, timeout=timeout)
    assert res.returncode == 0, f"driver child failed:\n{res.stdout}\n{res.stderr[-4000:]}"
    return json.loads(out.read_text()), res


def make_events(n, span_us, seed=0, t0_us=1):
    rng = np.random.default_rng(seed)
    ev = np.empty(n, EVENT_DTYPE)
    ev["t"] = np.sort(rng.integers(t0_us, span_us, n)) * 1000
    ev["x"] = rng.integers(0, 346, n)
    ev["y"] = rng.integers(0, 260, n)
    ev["p"] = rng.choice(np.array([-1, 1], np.int8), n)
    return ev


@pytest.fixture
def bus():
    with VirtualUsbBus() as b:
        yield b


def test_open_start_order_and_events_bit_for_bit_across_wraps(bus, tmp_path):
    ev = make_events(40_000, 3_000_000, seed=1)                 # 3 s: 91 timestamp wraps
    twin = VirtualDAVIS346(ev, realtime=False, step_us=20_000)
    bus.add(twin)
    info, _ = run_driver(bus, tmp_path, """
        cam = DAVIS346().open()
        ident = dict(serial=cam.serial, fw=cam.firmware_version, logic=cam.logic_version, patch=cam.logic_patch,
                     chip=cam.chip_id, w=cam.width, h=cam.height, encoding=cam.encoding, has=cam.has)
        cam.start()
        ev, _ = read_until(cam, 3_000_000)
        cam.stop()
        np.save(OUT + ".npy", ev)
        ident.update(stats=cam.stats.as_dict(), resets=cam.decoder.resets, frames=len(cam.read_frames()))
        cam.close()
        json.dump(ident, open(OUT, "w"))
    """)
    assert (info["serial"], info["fw"], info["logic"], info["patch"], info["chip"]) == ("DAV00001", 6, 18, 1, 5)
    assert (info["w"], info["h"], info["encoding"]) == (346, 260, "libcaer") and info["has"]["roi_filter"]
    got = np.load(str(tmp_path / "out.json") + ".npy")
    truth = twin.emitted_events()
    assert np.array_equal(truth, ev)                           # the twin sent every input event, in order
    assert np.array_equal(got, truth)                          # ... and the driver got them, bit for bit
    assert info["stats"]["dropped_chunks"] == 0 and info["frames"] == 0
    w = twin.writes
    # libcaer's default chip configuration was sent at open (biases as coarse-fine words)
    assert (5, 10, D.coarse_fine_word((1, 1, 1, 1), 4, 39)) in w and (5, 11, 0x5FFF) in w
    # start: everything off, chip run, USB, MUX timestamp, MUX, DVS (no APS: aps=False)
    runs = [k[:2] for k in w if k[2] == 1 and k[:2] in {(0, 3), (9, 0), (0, 1), (0, 0), (1, 3), (2, 4)}]
    assert runs == [(0, 3), (9, 0), (0, 1), (0, 0), (1, 3)]
    first = w.index((0, 3, 1))
    off_before = [k[:2] for k in w[:first] if k[2] == 0]
    for key in [(1, 3), (2, 4), (3, 2), (3, 3), (3, 4), (4, 0), (0, 0), (0, 1), (9, 0), (0, 3)]:
        assert key in off_before
    # stop in reverse: DVS, APS, IMU, external input, MUX, MUX timestamp, USB, chip
    dvs_on = w.index((1, 3, 1))
    tail = [k[:2] for k in w[dvs_on + 1:] if k[2] == 0][:10]
    assert tail == [(1, 3), (2, 4), (3, 2), (3, 3), (3, 4), (4, 0), (0, 0), (0, 1), (9, 0), (0, 3)]
    assert twin.stalled == [] and not twin.streaming


def test_trigger_edges_biases_roi_and_timestamp_reset(bus, tmp_path):
    twin = VirtualDAVIS346(None, realtime=True)
    bus.add(twin)
    proc = spawn_child([sys.executable, "-c", PRELUDE + textwrap.dedent("""
        cam = DAVIS346().open()
        res = {"biases0": cam.biases, "cf0": cam.coarse_fine_biases, "roi0": cam.roi}
        cam.set_biases({"onbn": (6, 100), "offbn_fine": 2, "diffbn_coarse": 4, "adcrefhigh_voltage": 30})
        res["biases1"] = cam.biases
        cam.set_roi(10, 13, 100, 2)
        res["roi1"] = cam.roi
        cam.set_roi(0, 0, 346, 260)
        res["roi_full"] = cam.roi
        for bad in ({"bias_diff_on": 3}, {"onbn_fine": 256}):
            try:
                cam.set_biases(bad)
            except CameraError as exc:
                res.setdefault("bad", []).append(str(exc))
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
        cam.set_roi(5, 6, 7, 8)
        cam.clear_roi()
        res["roi2"] = cam.roi
        cam.close()
        json.dump(res, open(OUT, "w"))
    """), str(tmp_path / "out.json")], bus)
    try:
        assert proc.stdout.readline().strip() == "STREAMING"
        edges = []
        while len(edges) < 2:
            e = twin.pulse_trigger(width_us=250)
            if e is not None:
                edges.append(e)
            time.sleep(0.2)
        _out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, err[-4000:]
    res = json.loads((tmp_path / "out.json").read_text())
    assert res["cf0"]["diffbn"] == [4, 39] and res["cf0"]["onbn"] == [5, 255] and res["cf0"]["offbn"] == [4, 1]
    assert res["roi0"] is None and res["roi_full"] is None and res["roi2"] is None
    assert res["roi1"] == [10, 13, 100, 2]
    b = res["biases1"]
    assert (b["onbn_coarse"], b["onbn_fine"], b["offbn_coarse"], b["offbn_fine"], b["adcrefhigh_voltage"],
            b["adcrefhigh_current"]) == (6, 100, 4, 2, 30, 7)
    assert twin.biases() == b
    onbn = twin.register(5, 11)
    assert onbn & 0xF == 0xF                                   # the type bits were kept (read-modify-write)
    c_on, c_off = twin.thresholds()
    assert c_on > 0.2 and c_off < 0.2                          # ON bias up -> C_on up; OFF bias up -> C_off down
    assert "bias_diff_on" in res["bad"][0] and "diffbn_coarse" in res["bad"][0] and "0..255" in res["bad"][1]
    want = []
    for rise, fall in edges:
        want += [[rise, 0, 1], [fall, 0, 0]]
    assert res["trig"] == want
    assert res["resets"] == 1
    assert any(w[:2] == (0, 2) for w in twin.writes)


def test_thresholds_follow_biases_monotonic_and_symmetric_at_default():
    w = {n: D.coarse_fine_word(*v) for n, v in D.DEFAULT_BIASES.items()}
    cf = lambda c, f: D.coarse_fine_word((1, 1, 1, 1), c, f)  # noqa: E731
    assert D.thresholds_from_bias_words(w["diffbn"], w["onbn"], w["offbn"]) == pytest.approx((0.2, 0.2))
    ons = [D.thresholds_from_bias_words(w["diffbn"], cf(5, f), w["offbn"])[0] for f in (50, 100, 200, 255)]
    offs = [D.thresholds_from_bias_words(w["diffbn"], w["onbn"], cf(3, f))[1] for f in (10, 50, 100, 200)]
    diffs = [D.thresholds_from_bias_words(cf(4, f), w["onbn"], w["offbn"]) for f in (20, 39, 80)]
    assert ons == sorted(ons) and offs == sorted(offs, reverse=True)
    assert [d[0] for d in diffs] == sorted([d[0] for d in diffs], reverse=True)
    assert [d[1] for d in diffs] == sorted(d[1] for d in diffs)


def test_roi_crops_the_stream_and_aps_frames_arrive(bus, tmp_path):
    ev = make_events(20_000, 1_000_000, seed=2)

    def scene(t_ns):                                           # a moving gradient, intensity in [0, 1]
        x = np.arange(346)[None, :] / 345.0
        y = np.arange(260)[:, None] / 259.0
        return (0.5 + 0.5 * np.sin(6.0 * x + 3.0 * y + t_ns * 1e-8)) * np.ones((260, 1))
    twin = VirtualDAVIS346(ev, realtime=True, frame_source=scene)     # live: the APS starts after the DVS
    bus.add(twin)
    info, _ = run_driver(bus, tmp_path, """
        cam = DAVIS346(aps=True).open()
        cam.set_roi(100, 13, 200, 150)
        cam.set_aps_timing(3000, 100_000)
        cam.start()
        ev, _ = read_until(cam, 1_200_000)
        frames = cam.read_frames()
        cam.stop(); cam.close()
        np.save(OUT + ".npy", ev)
        np.save(OUT + ".img.npy", np.stack([f.image for f in frames]))
        json.dump({"times": [[f.t_start_ns, f.t_exposure_start_ns, f.t_exposure_end_ns, f.t_end_ns]
                             for f in frames], "bad": cam.decoder.bad_frames}, open(OUT, "w"))
    """)
    got = np.load(str(tmp_path / "out.json") + ".npy")
    keep = (ev["x"] >= 100) & (ev["x"] < 300) & (ev["y"] >= 13) & (ev["y"] < 163)
    assert 0 < got.size < ev.size and np.array_equal(got, ev[keep])
    imgs = np.load(str(tmp_path / "out.json") + ".img.npy")
    truth = twin.emitted_frames
    assert len(info["times"]) >= 8 and info["bad"] == 0
    assert len(truth) >= len(info["times"])
    for k, (times, img) in enumerate(zip(info["times"], imgs)):
        f = truth[k]
        assert np.array_equal(img, f.image)
        assert times == [f.t_start_ns, f.t_exposure_start_ns, f.t_exposure_end_ns, f.t_end_ns]
        assert times[2] - times[1] == 3_000_000
    assert np.diff([t[0] for t in info["times"]]).tolist() == [100_000_000] * (len(info["times"]) - 1)
    assert (2, 4, 1) in twin.writes and (2, 12, 3000 * 64) in twin.writes


def test_unknown_request_stalls_and_unsupported_devices_are_refused(bus, tmp_path):
    twin = VirtualDAVIS346(None)
    for d in (twin, VirtualDAVIS346(None, serial="OLDFW001", firmware=5),
              VirtualDAVIS346(None, serial="PATCH001", logic_patch=0),
              VirtualDAVIS346(None, serial="CHIP0001", chip_id=7)):
        bus.add(d)
    res, _ = run_driver(bus, tmp_path, """
        res = {}
        cam = DAVIS346("DAV00001").open()
        try:
            cam.link.control_out(0x40, 0xB8, 0, 0, b"\\x00" * 4)
        except CameraProtocolError as exc:
            res["stall"] = str(exc)
        res["still_usable"] = cam.config_read(6, 0)
        cam.close()
        for serial in ("OLDFW001", "PATCH001", "CHIP0001"):
            try:
                DAVIS346(serial).open()
            except CameraProtocolError as exc:
                res[serial] = str(exc)
        json.dump(res, open(OUT, "w"))
    """)
    assert "stalled" in res["stall"] and "0xb8" in res["stall"].lower()
    assert [(s.request, s.request_type) for s in twin.stalled] == [(0xB8, 0x40)]
    assert res["still_usable"] == 18
    assert "firmware version 5" in res["OLDFW001"]
    assert "patch level 0" in res["PATCH001"]
    assert "chip identifier 7" in res["CHIP0001"]


def test_idle_read_times_out_and_unplug_keeps_what_came_before(bus, tmp_path):
    idle = VirtualDAVIS346(None, serial="IDLE0001", idle_wraps=False)
    live = VirtualDAVIS346(make_events(200_000, 20_000_000, seed=3), serial="LIVE0001", realtime=True)
    bus.add(idle)
    bus.add(live)
    proc = spawn_child([sys.executable, "-c", PRELUDE + textwrap.dedent("""
        res = {}
        cam = DAVIS346("IDLE0001").open(); cam.start()
        t0 = time.monotonic(); r = cam.read(0.3); res["idle"] = [r is None, time.monotonic() - t0]
        cam.stop(); cam.close()
        cam = DAVIS346("LIVE0001").open(); cam.start()
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
        np.save(OUT + ".npy", np.concatenate(parts))
        json.dump(res, open(OUT, "w"))
        import os; os._exit(0)        # libusb never reaps an unplugged device's transfers under umockdev
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
    assert got.size >= 2000 and np.array_equal(got, live.emitted_events()[:got.size])


def test_slow_consumer_gets_counted_drops(bus, tmp_path):
    twin = VirtualDAVIS346(make_events(400_000, 4_000_000, seed=4), realtime=False, step_us=10_000)
    bus.add(twin)
    res, _ = run_driver(bus, tmp_path, """
        cam = DAVIS346(queue_chunks=4).open(); cam.start()
        time.sleep(2.0)
        for _ in range(20):
            if cam.read(0.5) is None:
                break
        cam.stop()
        json.dump({"stats": cam.stats.as_dict()}, open(OUT, "w"))
        cam.close()
    """)
    s = res["stats"]
    assert s["dropped_chunks"] > 0 and s["dropped_bytes"] > 0
    assert s["queue_high_water"] == 4 and s["bytes"] > s["dropped_bytes"]


def test_neuromorphic_drivers_decodes_exactly_the_twins_events(bus, tmp_path):
    pytest.importorskip("neuromorphic_drivers")
    ev = make_events(3000, 1_500_000, seed=5)                   # 45 timestamp wraps
    # neuromorphic-drivers always runs the APS: this twin has no frame source, so it sends none
    twin = VirtualDAVIS346(ev, realtime=False, step_us=50_000, idle_wraps=False)
    bus.add(twin)
    script = tmp_path / "peer.py"
    script.write_text(textwrap.dedent("""
        import sys, time
        import numpy as np
        import neuromorphic_drivers as nd
        want, parts, t0, until = int(sys.argv[2]), [], time.monotonic(), None
        with nd.open(iterator_timeout=0.5) as device:
            for status, packet in device:     # until every event came (then 0.5 s more for extras)
                now = time.monotonic()
                if packet is None or now - t0 > 30 or (until is not None and now > until):
                    break
                if packet.polarity_events is not None and len(packet.polarity_events):
                    parts.append(packet.polarity_events.copy())
                if until is None and sum(len(p) for p in parts) >= want:
                    until = now + 0.5
        np.save(sys.argv[1], np.concatenate(parts))
    """))
    res = run_child([sys.executable, str(script), str(tmp_path / "nd.npy"), str(ev.size)], bus, timeout=90)
    assert res.returncode == 0, res.stderr[-4000:]
    nd_ev = np.load(tmp_path / "nd.npy")
    truth = twin.emitted_events()
    assert np.array_equal(truth, ev)
    assert nd_ev.size == truth.size
    assert np.array_equal(nd_ev["t"].astype(np.int64) * 1000, truth["t"])
    assert np.array_equal(nd_ev["x"], truth["x"]) and np.array_equal(nd_ev["y"], truth["y"])
    assert np.array_equal(nd_ev["on"], truth["p"] > 0)
