"""Prophesee EVK4 driver (rig.camera.evk4) against its virtual twin (rig.camera.virtual.evk4).

The twin runs in this process behind umockdev; every driver runs in a child process under
the preload (notes/usb-virtual.md, pitfall 2), and so does the independent peer
(neuromorphic-drivers).  Skipped with the reason where umockdev / gi are missing.
"""

from __future__ import annotations

import json
import subprocess
import textwrap
import time

import numpy as np
import pytest

from evdnerf_ros.events.codecs import decode
from evdnerf_ros.events.types import EVENT_DTYPE
from rig.camera import evk4_registers as R
from rig.camera.virtual.usb import umockdev_available

_OK, _WHY = umockdev_available()
pytestmark = pytest.mark.skipif(not _OK, reason=f"virtual USB unavailable: {_WHY}")

WRAP_US = 1 << 24


@pytest.fixture
def make_twin():
    from rig.camera.virtual.evk4 import VirtualEVK4
    from rig.camera.virtual.usb import VirtualUsbBus
    buses = []

    def make(source=None, **kw):
        bus = VirtualUsbBus()
        buses.append(bus)
        twin = VirtualEVK4(source, **kw)
        bus.add(twin)
        return bus, twin

    yield make
    for b in buses:
        b.close()


PRELUDE = """
import json, sys, time
import numpy as np
from rig.camera.evk4 import EVK4
from rig.camera import evk4_registers as R
from rig.camera.errors import (CameraDisconnected, CameraError, CameraNotFound,
                               CameraProtocolError)
def result(**kw):
    print("RESULT " + json.dumps(kw), flush=True)
def read_all(cam, idle_s=1.0, limit_s=60.0):
    evs, trs, raw = [], [], []
    t0 = time.monotonic()
    while time.monotonic() - t0 < limit_s:
        c = cam.read(idle_s)
        if c is None:
            break
        evs.append(c.events); trs.append(c.triggers); raw.append(c.raw)
    ev = np.concatenate(evs) if evs else np.empty(0, [("t", "<i8"), ("x", "<u2"), ("y", "<u2"), ("p", "i1")])
    tr = np.concatenate(trs) if trs else np.empty(0, [("t", "<i8"), ("id", "u1"), ("value", "u1")])
    return ev, tr, b"".join(raw)
"""


def child_result(returncode: int, stdout: str, stderr: str) -> dict:
    """The JSON a driver child printed on its last `RESULT ` line (it must have exited 0)."""
    lines = [ln for ln in stdout.splitlines() if ln.startswith("RESULT ")]
    assert returncode == 0 and lines, f"driver child failed (exit {returncode})\n{stdout}\n{stderr}"
    return json.loads(lines[-1][len("RESULT "):])


def run_driver(bus, body: str, timeout: float = 120.0) -> dict:
    from rig.camera.virtual.usb import run_child
    res = run_child(PRELUDE + textwrap.dedent(body), bus, timeout=timeout)
    return child_result(res.returncode, res.stdout, res.stderr)


def random_events(n, t_end_us, seed=0, t_start_us=0):
    """Sorted EVENT_DTYPE events on whole microseconds, with runs that share a time and a
    row (vector words) and events at the same microsecond."""
    rng = np.random.default_rng(seed)
    ev = np.empty(n, EVENT_DTYPE)
    ev["t"] = np.sort(rng.integers(t_start_us, t_end_us, n)) * 1000
    ev["x"] = rng.integers(0, R.WIDTH, n)
    ev["y"] = rng.integers(0, R.HEIGHT, n)
    ev["p"] = rng.choice(np.array([-1, 1], np.int8), n)
    # a few horizontal runs (same t, y, p; consecutive x): VECT_12 / VECT_8 words
    for k in range(0, n - 40, max(n // 20, 41)):
        ev["t"][k:k + 30] = ev["t"][k]
        ev["y"][k:k + 30] = ev["y"][k]
        ev["p"][k:k + 30] = 1
        ev["x"][k:k + 30] = np.arange(30) + 100
    order = np.lexsort((ev["x"], ev["y"], ev["t"]))
    return ev[order]


# ---------------------------------------------------------------------------------------
def test_open_identity_and_register_writes_in_documented_order(make_twin):
    bus, twin = make_twin(realtime=False)
    out = run_driver(bus, """
        t = time.monotonic()
        cam = EVK4()
        cam.open()
        opened = time.monotonic() - t
        cam.set_biases({"bias_diff_on": 20, "bias_fo": -10})
        cam.set_roi(10, 20, 300, 200)
        cam.enable_trigger_input(True)
        cam.start()
        cam.stop()
        cam.close()
        result(serial=cam.serial, sensor=cam.sensor, fw=cam.firmware_version,
               build=cam.build_date, opened=opened, model=cam.model, enc=cam.encoding,
               size=[cam.width, cam.height])
    """)
    assert out["serial"] == "000A1B2C" and out["sensor"] == "IMX636"
    assert out["fw"] == twin.release_version and out["build"] == twin.build_date
    assert (out["model"], out["enc"], out["size"]) == ("Prophesee EVK4", "evt3", [1280, 720])
    assert out["opened"] >= 2.5        # the bring-up's settling delays (1 s reset, 1.5 s MIPI)
    # identity: control 0xC0/0x72 first, then the 8-byte requests
    setup, _ = twin.control_log[0]
    assert (setup.request_type, setup.request, setup.length) == (0xC0, 0x72, 2)
    assert twin.requests[:3] == [R.REQ_SERIAL, R.REQ_RELEASE_VERSION, R.REQ_BUILD_DATE]
    factory = twin.factory
    expected = [(w.address, w.value) for w in R.open_sequence(trigger_in=False)]
    expected += [(0x1010, 0x11A10000 | (factory["bias_diff_on"] + 20)),
                 (0x1004, 0x11A10000 | (factory["bias_fo"] - 10))]
    expected += [(w.address, w.value) for w in R.roi_registers(10, 20, 300, 200)]
    expected += [(R.EDF_RESERVED_7004, R.edf_7004(True))]
    expected += [(w.address, w.value) for w in R.START + R.STOP]
    expected += [(s.address, 0x11A10000 | factory[n]) for n, s in R.BIASES.items()]
    expected += [(w.address, w.value) for w in R.DESTROY]
    assert twin.writes == expected
    # the factory biases were read back after the bring-up, before any bias write
    n_open = len(R.open_sequence())
    assert [a for a in twin.reads[:6]] == [s.address for s in R.BIASES.values()]
    assert len(twin.writes) > n_open > 590
    assert twin.stalled == []


def test_events_out_equal_events_in_across_the_24bit_wrap(make_twin, tmp_path):
    """A 20.5 s stream (sensor time wraps at 2**24 us = 16.78 s), bit for bit, and the raw
    bytes passed through untouched."""
    ev = random_events(120_000, 20_500_000, seed=1)
    # events right at the wrap and at both sides of it
    ev["t"][60_000:60_010] = np.arange(WRAP_US - 5, WRAP_US + 5) * 1000
    ev = ev[np.lexsort((ev["x"], ev["y"], ev["t"]))]
    bus, twin = make_twin(ev, realtime=False, step_us=50_000)
    out = run_driver(bus, f"""
        with EVK4(settle=False) as cam:
            cam.start()
            ev, tr, raw = read_all(cam)
            stats = cam.stats.as_dict()
            clock = cam.clock
            cam.stop()
        np.save({str(tmp_path / "wrap.npy")!r}, ev)
        open({str(tmp_path / "wrap.raw")!r}, "wb").write(raw)
        result(n=int(ev.size), ntr=int(tr.size), stats=stats, clock_samples=clock.samples)
    """)
    got = np.load(tmp_path / "wrap.npy")
    raw = (tmp_path / "wrap.raw").read_bytes()
    assert out["n"] == ev.size and out["ntr"] == 0
    assert got.dtype == EVENT_DTYPE
    assert np.array_equal(got, ev)                        # events out == events in
    assert np.array_equal(twin.emitted_events(), ev)
    assert int(got["t"][-1]) > WRAP_US * 1000             # past the 24-bit wrap
    assert raw == bytes(twin.streamed)                    # read_raw / chunk.raw untouched
    assert np.array_equal(decode(raw, "evt3").events, ev)
    assert out["stats"]["dropped_chunks"] == 0 and out["stats"]["events"] == ev.size
    assert out["clock_samples"] >= 2


def test_trigger_edges(make_twin):
    from rig.camera.virtual.usb import spawn_child
    ev = random_events(5_000, 30_000_000, seed=2)
    bus, twin = make_twin(ev, realtime=True)
    code = PRELUDE + textwrap.dedent("""
        with EVK4(settle=False) as cam:
            cam.start()
            print("ready-disabled", flush=True)
            sys.stdin.readline()
            cam.enable_trigger_input(True)
            print("ready-enabled", flush=True)
            trs, evs = [], []
            t0 = time.monotonic()
            # read on for 3 s at least: the clock fit's span (under load, a sub-second span put
            # the fitted scale 10-18 % off from arrival delays alone)
            while time.monotonic() - t0 < 20 and (sum(len(t) for t in trs) < 6 or time.monotonic() - t0 < 3.0):
                c = cam.read(0.5)
                if c is not None:
                    trs.append(c.triggers); evs.append(c.events)
            tr = np.concatenate(trs)
            clock = cam.clock
            cam.stop()
        result(t=tr["t"].tolist(), id=tr["id"].tolist(), value=tr["value"].tolist(),
               scale=clock.scale, n_events=int(sum(len(e) for e in evs)))
    """)
    proc = spawn_child(code, bus, stdin=subprocess.PIPE)
    try:
        assert proc.stdout.readline().strip() == "ready-disabled"
        time.sleep(0.2)
        assert twin.pulse_trigger() is None           # input off: the edge is dropped
        proc.stdin.write("go\n")
        proc.stdin.flush()
        assert proc.stdout.readline().strip() == "ready-enabled"
        assert twin.trigger_input_enabled
        pulses = []
        for _ in range(3):
            time.sleep(0.15)
            pulses.append(twin.pulse_trigger(width_us=250))
        out_s, err_s = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    out = child_result(proc.returncode, out_s, err_s)
    want_t = [t for p in pulses for t in p]
    assert out["t"] == want_t
    assert out["value"] == [1, 0, 1, 0, 1, 0] and out["id"] == [0] * 6
    assert all(b - a == 250_000 for a, b in zip(want_t[::2], want_t[1::2]))
    tr = twin.emitted_triggers()
    assert tr["t"].tolist() == want_t
    assert out["n_events"] > 0
    assert abs(out["scale"] / 1000.0 - 1.0) < 0.05   # sensor clock ~ host clock (live twin)


def test_biases_and_roi_round_trip_and_roi_crops(make_twin, tmp_path):
    from rig.camera.biases import read_bias_file
    ev = random_events(40_000, 2_000_000, seed=3)
    bus, twin = make_twin(ev, realtime=False, step_us=20_000)
    src = tmp_path / "in.bias"
    src.write_text("% EVK4 test biases\n25   % bias_diff_off\n-30  % bias_diff_on\n"
                   "7    % bias_hpf\n")
    saved = tmp_path / "saved.bias"
    out = run_driver(bus, f"""
        errors = {{}}
        with EVK4(settle=False) as cam:
            before = cam.biases
            cam.set_biases({{"bias_diff_on": 40, "bias_refr": -12, "bias_diff": 3}})
            after_set = cam.biases
            cam.save_bias_file({str(saved)!r})
            loaded = cam.load_bias_file({str(src)!r})
            after_load = cam.biases
            for name, call in (("unknown", lambda: cam.set_biases({{"bias_pr": 1}})),
                               ("range", lambda: cam.set_biases({{"bias_diff_on": 500}})),
                               # inside OpenEB's range but past the 8-bit register: refused, not clamped
                               ("register", lambda: cam.set_biases({{"bias_diff_on": 255 - cam.factory_biases["bias_diff_on"] + 1}})),
                               ("roi", lambda: cam.set_roi(1200, 0, 100, 10))):
                try:
                    call()
                except CameraError as exc:
                    errors[name] = str(exc)
            roi0 = cam.roi
            cam.set_roi(100, 50, 640, 360)
            roi1 = cam.roi
            cam.start()
            ev, tr, raw = read_all(cam)
            cam.stop()
            cam.clear_roi()
            roi2 = cam.roi
        np.save({str(tmp_path / "roi.npy")!r}, ev)
        result(before=before, after_set=after_set, loaded=loaded, after_load=after_load,
               errors=errors, roi0=roi0, roi1=roi1, roi2=roi2)
    """)
    zero = {n: 0 for n in R.BIASES}
    assert out["before"] == zero
    want_set = dict(zero, bias_diff_on=40, bias_refr=-12, bias_diff=3)
    assert out["after_set"] == want_set
    assert read_bias_file(saved, ranges=R.BIAS_RANGES) == want_set         # .bias written
    assert saved.read_text().startswith("% Prophesee EVK4 IMX636 serial 000A1B2C\n")
    assert out["loaded"] == {"bias_diff_off": 25, "bias_diff_on": -30, "bias_hpf": 7}
    want_load = dict(want_set, bias_diff_off=25, bias_diff_on=-30, bias_hpf=7)
    assert out["after_load"] == want_load
    # the sensor got them (close() then restores the factory values, as the peer does)
    restore = [(sp.address, 0x11A10000 | twin.factory[n]) for n, sp in R.BIASES.items()]
    body = twin.writes[:-len(R.DESTROY)]
    assert body[-len(restore):] == restore and twin.bias_offsets() == zero
    last = {a: v for a, v in body[:-len(restore)]}
    assert {n: (last.get(sp.address, twin.factory[n]) & 0xFF) - twin.factory[n]
            for n, sp in R.BIASES.items()} == want_load
    assert "unknown bias bias_pr; valid biases: bias_diff, bias_diff_off" in out["errors"]["unknown"]
    # OpenEB's [-150, 200] narrowed to what the 8-bit register holds from this sensor's factory value
    f = twin.factory["bias_diff_on"]
    held = f"outside its allowed range [{max(-150, -f)}, {min(200, 255 - f)}]"
    assert held in out["errors"]["range"] and held in out["errors"]["register"]
    assert "outside the 1280x720 sensor" in out["errors"]["roi"]
    # thresholds follow bias_diff_on / bias_diff_off (the twin's source got them)
    from rig.camera.virtual.evk4 import thresholds_from_biases
    c_on, c_off = thresholds_from_biases(-30, 25)
    assert (twin.source.c_pos, twin.source.c_neg) == pytest.approx((c_on, c_off))
    assert c_on < 0.2 < c_off
    # ROI: read back from the registers, applied to the stream, cleared
    assert out["roi0"] is None and out["roi1"] == [100, 50, 640, 360] and out["roi2"] is None
    got = np.load(tmp_path / "roi.npy")
    inside = ((ev["x"] >= 100) & (ev["x"] < 740) & (ev["y"] >= 50) & (ev["y"] < 410))
    assert 0 < got.size < ev.size
    assert np.array_equal(got, ev[inside])
    xo, yo, on, window = twin.roi_mask()
    assert on and window and xo.all() and yo.all()                          # cleared again


def test_unknown_command_and_register_are_reported(make_twin):
    bus, twin = make_twin()
    out = run_driver(bus, """
        msgs = {}
        with EVK4(settle=False) as cam:
            try:
                cam.request(bytes([0x55] * 8))
            except CameraProtocolError as exc:
                msgs["cmd"] = str(exc)
            try:
                cam.read_register(0x00F00000)
            except CameraProtocolError as exc:
                msgs["reg"] = str(exc)
            ok = cam.read_register(R.RO_CTRL)            # the camera still answers
        result(msgs=msgs, ok=ok)
    """)
    assert "request 55 55 55 55 55 55 55 55" in out["msgs"]["cmd"]
    assert "stalled" in out["msgs"]["cmd"]
    assert "register 0xF00000 read" in out["msgs"]["reg"] and "stalled" in out["msgs"]["reg"]
    assert out["ok"] == R.RO_OUTPUT_DISABLE
    assert twin.stalled == [bytes([0x55] * 8), R.read_command(0x00F00000)]


def test_wrong_sensor_type_and_unknown_serial(make_twin):
    bus, _twin = make_twin(sensor_type=0x99)
    out = run_driver(bus, """
        msgs = {}
        try:
            EVK4(settle=False).open()
        except CameraProtocolError as exc:
            msgs["type"] = str(exc)
        try:
            EVK4("DEADBEEF", settle=False).open()
        except CameraNotFound as exc:
            msgs["serial"] = str(exc)
        result(msgs=msgs)
    """)
    assert "sensor type 9900" in out["msgs"]["type"] and "IMX636" in out["msgs"]["type"]
    assert "no Prophesee EVK4 with serial 'DEADBEEF'" in out["msgs"]["serial"]
    assert "'000A1B2C'" in out["msgs"]["serial"]


def test_idle_read_times_out_cleanly(make_twin):
    bus, twin = make_twin(realtime=True)                 # streaming, but nothing happens
    out = run_driver(bus, """
        with EVK4(settle=False) as cam:
            cam.start()
            t = time.monotonic(); r1 = cam.read(0.3); d1 = time.monotonic() - t
            t = time.monotonic(); r2 = cam.read_raw(0.2); d2 = time.monotonic() - t
            streaming = cam.is_streaming
            cam.stop()
        result(r1=r1 is None, r2=r2 is None, d1=d1, d2=d2, streaming=streaming)
    """)
    assert out["r1"] and out["r2"] and out["streaming"]
    assert 0.25 <= out["d1"] < 2.0 and 0.15 <= out["d2"] < 2.0
    assert twin.bytes_streamed == 0


def test_unplug_mid_stream_keeps_what_arrived(make_twin, tmp_path):
    from rig.camera.virtual.usb import spawn_child
    ev = random_events(400_000, 20_000_000, seed=4)
    bus, twin = make_twin(ev, realtime=True)
    code = PRELUDE + textwrap.dedent(f"""
        got, msg = [], None
        cam = EVK4(settle=False)
        cam.open()
        cam.start()
        print("streaming", flush=True)
        t0 = time.monotonic()
        try:
            while time.monotonic() - t0 < 30:
                c = cam.read(0.5)
                if c is not None:
                    got.append(c.events)
        except CameraDisconnected as exc:
            msg = str(exc)
        ev = np.concatenate(got) if got else np.empty(0)
        np.save({str(tmp_path / "unplug.npy")!r}, ev)
        result(msg=msg, n=int(ev.size))
        # under umockdev libusb never reaps the transfers of an unplugged device (it learns of
        # an unplug from poll errors a regular file never gives), so close() would wait forever
        import os; os._exit(0)
    """)
    proc = spawn_child(code, bus)
    try:
        assert proc.stdout.readline().strip() == "streaming"
        t0 = time.monotonic()
        while twin.bytes_streamed < 60_000 and time.monotonic() - t0 < 20:
            time.sleep(0.05)
        assert twin.bytes_streamed >= 60_000
        twin.unplug()
        out_s, err_s = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    out = child_result(proc.returncode, out_s, err_s)
    assert out["msg"] and "unplugged" in out["msg"]
    got = np.load(tmp_path / "unplug.npy")
    emitted = twin.emitted_events()
    assert 0 < got.size <= emitted.size < ev.size
    assert np.array_equal(got, emitted[:got.size])       # everything before the unplug, in order
    assert np.array_equal(got, ev[:got.size])


def test_peer_neuromorphic_drivers_decodes_the_twin_exactly(make_twin, tmp_path):
    """Independent peer: neuromorphic-drivers (Rust, its own libusb) opens the twin in a
    child process, runs its 700-write bring-up and decodes exactly the events the twin
    emitted, across the 24-bit wrap.

    Its ring is given one transfer in flight (``parallel_submissions=1``): with several,
    neuromorphic-drivers moves every resubmitted transfer to a new ring buffer, and the
    umockdev emulation (rig.camera.virtual.usb) then delivers its bytes out of order (the
    peer's raw bytes differ from what the twin sent; our driver, which resubmits each
    transfer on its own buffer, is not affected).  See the EVK4 helper's report."""
    pytest.importorskip("neuromorphic_drivers", reason="neuromorphic-drivers (test extra) not installed")
    ev = random_events(60_000, 18_000_000, seed=5)
    bus, twin = make_twin(ev, realtime=False, step_us=40_000)
    code = textwrap.dedent(f"""
        import time, json, numpy as np
        import neuromorphic_drivers as nd
        ring = nd.prophesee_evk4.RingConfiguration(buffer_length=131072, ring_length=1024,
                                                   parallel_submissions=1)
        got, last, start = [], time.monotonic(), time.monotonic()
        with nd.open(iterator_timeout=0.5, ring_configuration=ring) as dev:
            serial = dev.serial()
            last = start = time.monotonic()
            for status, packet in dev:
                if time.monotonic() - last > 2.0 or time.monotonic() - start > 60:
                    break
                if packet is None or packet.polarity_events is None or not len(packet.polarity_events):
                    continue
                got.append(packet.polarity_events.copy())
                last = time.monotonic()
        ev = np.concatenate(got)
        np.save({str(tmp_path / "peer.npy")!r}, ev)
        print("RESULT " + json.dumps(dict(serial=serial, n=int(ev.size))), flush=True)
    """)
    from rig.camera.virtual.usb import run_child
    res = run_child(code, bus, timeout=150)
    out = child_result(res.returncode, res.stdout, res.stderr)
    assert out["serial"] == "000A1B2C"
    peer = np.load(tmp_path / "peer.npy")
    emitted = twin.emitted_events()
    assert np.array_equal(emitted, ev)
    assert peer.size == emitted.size
    assert np.array_equal(peer["t"].astype(np.int64) * 1000, emitted["t"])
    assert np.array_equal(peer["x"], emitted["x"]) and np.array_equal(peer["y"], emitted["y"])
    assert np.array_equal(peer["on"], emitted["p"] > 0)
    assert int(peer["t"][-1]) > WRAP_US
    assert len(twin.writes) > 600 and twin.stalled == []


def test_twin_streams_only_after_readout_enable(make_twin):
    """In process (no driver): the twin answers nothing on 0x81 until the time base runs
    and RO_CTRL opens the readout gate, and stops when the gate closes."""
    ev = random_events(1_000, 100_000, seed=6)
    _bus, twin = make_twin(ev, realtime=False, step_us=10_000)

    def write(addr, value):
        assert twin.bulk_out(R.EP_COMMAND_OUT, R.write_command(addr, value)) is None
        assert twin.bulk_in(R.EP_COMMAND_IN, 1024) == R.write_command(addr, value)

    assert twin.bulk_in(R.EP_EVENTS, 1 << 17) is None
    write(R.TIME_BASE_CTRL, R.TIME_BASE_IDLE | R.TIME_BASE_ENABLE)
    assert twin.bulk_in(R.EP_EVENTS, 1 << 17) is None    # gate still closed
    write(R.RO_CTRL, 0)
    chunk = twin.bulk_in(R.EP_EVENTS, 1 << 17)
    assert chunk and twin.streaming
    write(R.RO_CTRL, R.RO_OUTPUT_DISABLE)
    assert twin.bulk_in(R.EP_EVENTS, 1 << 17) is None and not twin.streaming
    assert np.array_equal(decode(chunk, "evt3").events, twin.emitted_events())


def test_thresholds_follow_bias_diff_on_off_in_a_simulated_scene(make_twin):
    """In process: the twin streams the simulated fork scene; raising bias_diff_on (and
    lowering bias_diff_off) raises the ON contrast threshold, so far fewer ON events come out
    of the same 160 ms, and the ON / OFF balance shifts."""
    from rig.camera.virtual.evk4 import thresholds_from_biases

    def stream(diff_on, diff_off):
        _bus, twin = make_twin("fork", realtime=False, step_us=20_000)

        def write(addr, value):
            assert twin.bulk_out(R.EP_COMMAND_OUT, R.write_command(addr, value)) is None
            assert twin.bulk_in(R.EP_COMMAND_IN, 1024) is not None

        write(0x1010, R.bias_register_value(twin.factory["bias_diff_on"] + diff_on))
        write(0x1018, R.bias_register_value(twin.factory["bias_diff_off"] + diff_off))
        write(R.TIME_BASE_CTRL, R.TIME_BASE_IDLE | R.TIME_BASE_ENABLE)
        write(R.RO_CTRL, 0)
        raw = b"".join(c for c in (twin.bulk_in(R.EP_EVENTS, 1 << 22) for _ in range(8)) if c)
        ev = decode(raw, "evt3").events
        assert twin.source.thresholds == pytest.approx(thresholds_from_biases(diff_on, diff_off))
        assert np.array_equal(ev, twin.emitted_events())
        return int((ev["p"] > 0).sum()), int((ev["p"] < 0).sum())

    on0, off0 = stream(0, 0)
    on1, off1 = stream(100, -40)
    assert on0 > 1000 and off0 > 1000
    assert on1 < 0.5 * on0
    assert on1 / off1 < 0.5 * on0 / off0
