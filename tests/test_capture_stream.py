"""The capture's camera stream kept across views (rig.camera.record.CameraStream), the EVT 3.0
resume words a view cut from it begins with, the bias -> threshold models the drivers and
their twins share, and what session.yaml records per view (biases, bias changes, thresholds).
No virtual rig: a scripted EVK4 stream in real time, fake cameras and change logs."""

from __future__ import annotations

import re
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import yaml

from evdnerf_ros.errors import InputError
from evdnerf_ros.events import make_events
from evdnerf_ros.events.codecs import make_decoder, make_encoder
from evdnerf_ros.io.bag_reader import read_events
from evdnerf_ros.session.recorder import ViewRecorder
from rig.camera.device import RawChunk
from rig.camera.evk4 import EVK4
from rig.camera.record import ArrivalClock, CameraStream, ChunkWriter

#: sensor time of the scripted stream's first event: past two 24-bit microsecond wraps, so a view
#: decodes at its true times only if its resume words count the wraps before it
SENSOR_START_NS = 40_000_000_000


def _events(rng, n: int, t0_ns: int, span_ns: int):
    t = np.sort(rng.integers(t0_ns, t0_ns + span_ns, n)) // 1000 * 1000      # EVT 3.0: whole us
    return make_events(t, rng.integers(0, 1280, n), rng.integers(0, 720, n),
                       rng.choice(np.array([-1, 1], np.int8), n))


# --------------------------------------------------------------------------- resume words


def test_resume_words_let_a_reader_start_at_any_transfer(rng):
    """A stream with wraps cut into small transfers: from any transfer on, the driver's resume
    words + the camera's bytes decode to exactly the events the driver decoded there, at the
    same unwrapped sensor times."""
    ev = _events(rng, 3000, SENSOR_START_NS, 3 * 2**24 * 1000)      # three more wraps inside
    data = make_encoder("evt3").encode(ev)
    cuts = np.sort(rng.choice(np.arange(1, len(data) // 2), 150, replace=False)) * 2
    driver = EVK4()
    chunks = [driver.decode_chunk(RawChunk(bytes(b), 0, 0, k))
              for k, b in enumerate(np.split(np.frombuffer(data, np.uint8), cuts))]
    assert np.array_equal(np.concatenate([c.events for c in chunks]), ev)
    for k in (0, 1, 7, 60, 149):
        words = driver.resume_words(chunks[k])
        assert (k == 0) == (words == b"")                   # the stream's first transfer needs none
        dec = make_decoder("evt3")
        assert dec.feed(words).events.size == 0             # state only
        got = np.concatenate([dec.feed(c.raw).events for c in chunks[k:]])
        assert np.array_equal(got, np.concatenate([c.events for c in chunks[k:]]))
    # without them the first transfers' events are lost or misplaced (the test can fail)
    bare = make_decoder("evt3")
    with pytest.warns(Warning):
        bare_ev = np.concatenate([bare.feed(c.raw).events for c in chunks[60:]])
    assert not np.array_equal(bare_ev, np.concatenate([c.events for c in chunks[60:]]))


def test_arrival_clock_keeps_the_on_time_latency_through_a_lagging_stretch():
    clock = ArrivalClock("cam", window_s=10.0)
    with pytest.raises(Exception, match="no clock yet"):
        clock.host_ns_to_sensor_ns(0)
    for k in range(100):                                     # on time: 5 ms latency, host = sensor + 1 s
        clock.add(k * 10_000_000, 1_000_000_000 + k * 10_000_000 + 5_000_000)
    for k in range(100, 300):                                # then lagging by up to 2 s
        clock.add(k * 10_000_000, 1_000_000_000 + k * 10_000_000 + 5_000_000 + (k - 100) * 10_000_000)
    assert clock.host_ns_to_sensor_ns(5_000_000_000) == 5_000_000_000 - 1_005_000_000
    for k in range(300, 1600):                               # 13 s later the lagging samples are all that is left
        clock.add(k * 10_000_000, 1_000_000_000 + k * 10_000_000 + 2_005_000_000)
    assert clock.latency_ns == 1_000_000_000 + 2_005_000_000


# --------------------------------------------------------------------------- the stream kept across views


class ScriptedEVK4(EVK4):
    """An EVK4 driver whose transfers come from a script in real time: events at 4 kev/s from
    sensor time SENSOR_START_NS on (sensor time = host time - t0), in transfers of at most 256
    bytes (cut anywhere in the word stream), 5 ms apart; everything it sent is kept."""

    def __init__(self, rng):
        super().__init__(serial="SCRIPT")
        self.rng = rng
        self.sent = []
        self._pending = b""
        self._encoder = make_encoder("evt3")

    def start(self):
        self._reset_decoder()
        self._t0 = time.monotonic_ns() - SENSOR_START_NS
        self._made = SENSOR_START_NS
        self._stream = object()
        self._seq = 0

    def stop(self):
        self._stream = None

    def read_raw(self, timeout_s: float = 1.0):
        time.sleep(0.005)
        now = time.monotonic_ns() - self._t0
        n = int((now - self._made) * 4000 // 10**9)
        if n > 0:                                 # (a lagging camera: its sensor time may stand still)
            ev = _events(self.rng, n, self._made, now - self._made)
            self.sent.append(ev)
            self._pending += self._encoder.encode(ev)
            self._made = now
        if not self._pending:
            return None
        out, self._pending = self._pending[:256], self._pending[256:]
        self._seq += 1
        return RawChunk(out, time.monotonic_ns(), time.time_ns(), self._seq)


class _Live:
    def __init__(self):
        self.packets = 0

    def raw_packet(self, payload, *, stamp_ns, time_base=0):
        self.packets += 1
        return 1

    def trigger_edges(self, triggers):
        return 1


def _record(stream, path, hold_s: float, *, end_after_s: float | None = None):
    """One span: open, wait, optionally end it at the stream's clock, wait, close."""
    with ViewRecorder(path, width=1280, height=720, encoding="evt3") as rec:
        writer = ChunkWriter(rec, stream.device, origin=stream.origin)
        span = stream.open_span(writer)
        time.sleep(hold_s)
        if end_after_s is not None:
            stream.end_span(span, stream.clock.host_ns_to_sensor_ns(time.monotonic_ns()))
            time.sleep(end_after_s)
        stream.close_span(span)
    return span, writer


def test_the_stream_is_cut_into_views_without_loss_or_overlap(rng, tmp_path):
    """Two views cut from one running stream (each after a stretch read and discarded): no event
    of the first lands in the second, every event sent is in exactly one view or counted as
    discarded, and each bag decodes, with its resume words, to exactly the camera's events at
    their true (wrapped twice) sensor times on the one clock of the stream."""
    cam = ScriptedEVK4(rng)
    live = _Live()
    stream = CameraStream(cam, live=live).start()
    try:
        time.sleep(0.3)                                      # the turntable turns: read, discarded
        a, wa = _record(stream, tmp_path / "A", 0.4, end_after_s=0.2)
        time.sleep(0.3)
        b, wb = _record(stream, tmp_path / "B", 0.4)
        time.sleep(0.1)
    finally:
        stream.stop()
    stream.check()
    sent = np.concatenate(cam.sent)
    got = {name: read_events(tmp_path / name) for name in "AB"}
    for name, w in (("A", wa), ("B", wb)):
        s = got[name]
        assert s.events.size > 100 and s.events.size == w.counts["events"]
        sensor = s.events["t"] - stream.origin.wall_ns           # the stream's one clock
        assert s.time_offset_ns == stream.origin.wall_ns
        lo = np.searchsorted(sent["t"], sensor[0])
        assert np.array_equal(sensor, sent["t"][lo:lo + sensor.size])            # exactly the camera's, in order
        assert np.array_equal(s.events[["x", "y", "p"]], sent[["x", "y", "p"]][lo:lo + sensor.size])
    sa, sb = (got[n].events["t"] - stream.origin.wall_ns for n in "AB")
    assert sa.max() < sb.min()                                   # no event of view A in view B
    assert sa.min() >= SENSOR_START_NS + 200_000_000             # the stretch before A is not in it
    # A ends at its end: the transfer that crossed it at most (256 bytes: ~10 ms of events)
    assert a.end_sensor_ns is not None and sa.max() < a.end_sensor_ns + 30_000_000
    # every event read went to A, to B or to the discarded count; the gaps were counted
    assert sa.size + sb.size + stream.discarded.events == cam.stats.events
    assert a.discarded_before["events"] > 0 and b.discarded_before["events"] > 0
    assert a.discarded_before["events"] + b.discarded_before["events"] + stream.discarded_since_span()["events"] \
        == stream.discarded.events
    assert live.packets == stream.discarded.transfers + sum(w.counts["messages"] - 1 for w in (wa, wb))
    assert a.dropped == b.dropped == 0


def test_a_camera_fault_in_the_reader_reaches_the_recording_side(rng):
    class Unplugged(ScriptedEVK4):
        def read_raw(self, timeout_s=1.0):
            if time.monotonic_ns() - self._t0 > SENSOR_START_NS + 100_000_000:
                from rig.camera.errors import CameraDisconnected
                raise CameraDisconnected("SCRIPT: the camera was unplugged")
            return super().read_raw(timeout_s)

    stream = CameraStream(Unplugged(rng)).start()
    try:
        deadline = time.monotonic() + 5
        while stream.error is None and time.monotonic() < deadline:
            stream.wait(0.05)
        from rig.camera.errors import CameraDisconnected

        with pytest.raises(CameraDisconnected, match="unplugged"):
            stream.check()
        with pytest.raises(CameraDisconnected):
            stream.open_span(None)
    finally:
        stream.stop()


def test_a_stream_that_cannot_catch_up_is_restarted_before_a_view(rng, monkeypatch):
    """A camera that falls behind real time (a twin rendering slower than real time) first gets
    the chance to catch up before a view opens; one still behind after CATCH_UP_S is restarted
    (a new sensor zero and clock), and one that keeps up is left alone."""
    import threading

    from rig import capture

    class Lagging(ScriptedEVK4):
        """After the first 0.2 s its sensor time runs at a tenth of real time."""

        def read_raw(self, timeout_s=1.0):
            real = time.monotonic_ns() - self._t0 - SENSOR_START_NS
            if real > 200_000_000 and self._stream is not None:
                self._t0 += int((time.monotonic_ns() - getattr(self, "_last", time.monotonic_ns())) * 0.9)
            self._last = time.monotonic_ns()
            return super().read_raw(timeout_s)

    monkeypatch.setattr(capture, "CATCH_UP_S", 0.5)
    logged = []
    for cam, restarted in ((ScriptedEVK4(rng), False), (Lagging(rng), True)):
        stream = CameraStream(cam).start()
        try:
            time.sleep(1.0)
            origin, clock = stream.origin, stream.clock
            waited = capture._catch_up(stream, threading.Event(), logged.append)
            assert (stream.restarts == 1) is restarted and (stream.origin is not origin) is restarted
            assert (stream.clock is not clock) is restarted
            assert waited < (capture.CATCH_UP_S + 2.0 if restarted else 0.5), waited
            stream.open_span(None)
            with pytest.raises(RuntimeError, match="span is open"):
                stream.restart()
        finally:
            stream.stop()
    assert len(logged) == 1 and "did not catch up" in logged[0] and "restarted it" in logged[0], logged


# --------------------------------------------------------------------------- bias -> threshold models


def test_the_bias_models_are_the_drivers_and_the_twins_follow_them(rng):
    """One copy of each model, on the driver side; each twin's thresholds are what its driver's
    model gives for the biases the driver reads, over random bias settings."""
    from rig.camera import davis346, driver_class, dvxplorer, evk4
    from rig.camera import evk4_registers as R
    from rig.camera.virtual import davis346 as vdavis
    from rig.camera.virtual import dvxplorer as vdvx
    from rig.camera.virtual import evk4 as vevk4

    assert vevk4.thresholds_from_biases is evk4.thresholds_from_biases
    assert vdvx.thresholds_from_biases is dvxplorer.thresholds_from_biases
    assert vdavis.D.thresholds_from_bias_words is davis346.thresholds_from_bias_words

    twin, driver = vevk4.VirtualEVK4(), driver_class("EVK4")()
    for _ in range(5):
        for name in ("bias_diff_on", "bias_diff_off"):
            lo, hi = R.BIAS_RANGES[name][:2]
            f = twin.factory[name]
            twin.registers[R.BIASES[name].address] = R.bias_register_value(
                f + int(rng.integers(max(lo, -f), min(hi, 255 - f) + 1)))
        assert driver.contrast_thresholds(twin.bias_offsets()) == pytest.approx(twin.thresholds(), rel=1e-12)
    assert driver.THRESHOLD_MODEL == "rig.camera.evk4.thresholds_from_biases"

    twin, driver = vdvx.VirtualDVXplorer(), driver_class("DVXplorer")()
    for _ in range(5):
        for reg in (dvxplorer.REG_BIAS_CURRENT_ON, dvxplorer.REG_BIAS_CURRENT_OFF):
            twin.registers[(dvxplorer.DEVICE_DVS, reg)] = int(rng.integers(0, 12))
        assert driver.contrast_thresholds(twin.biases()) == pytest.approx(twin.thresholds(), rel=1e-12)

    twin, driver = vdavis.VirtualDAVIS346(), driver_class("DAVIS346")()
    for _ in range(5):
        for name in ("diffbn", "onbn", "offbn"):
            kind = davis346.DEFAULT_BIASES[name][0]
            twin.registers[(davis346.BIAS, davis346.COARSE_FINE_BIASES[name])] = davis346.coarse_fine_word(
                kind, int(rng.integers(1, 8)), int(rng.integers(1, 256)))
        assert driver.contrast_thresholds(twin.biases()) == pytest.approx(twin.thresholds(), rel=1e-12)


# --------------------------------------------------------------------------- per-view biases and thresholds


@dataclass(frozen=True)
class Change:
    values: dict
    wall_ns: int
    sensor_ns: int | None
    source: str
    host_ns: int | None


class FakeCamera:
    model = "Prophesee EVK4"
    THRESHOLD_MODEL = "rig.camera.evk4.thresholds_from_biases"

    def __init__(self):
        self.clock = ArrivalClock("fake")

    def contrast_thresholds(self, biases):
        from rig.camera.evk4 import thresholds_from_biases

        return thresholds_from_biases(biases["bias_diff_on"], biases["bias_diff_off"])


def _take(begin, end):
    from rig.capture import ViewResult

    return ViewResult("v", True, {}, 1, 2, 1.0, host_span_ns=(begin, end))


def test_views_record_the_biases_in_force_their_changes_and_the_thresholds_they_give():
    from rig.camera.evk4 import thresholds_from_biases
    from rig.capture import BiasLog, CaptureOptions, ThresholdModel, _session_thresholds

    cam = FakeCamera()
    cam.clock.add(0, 1)                          # host = sensor + 1 ns
    start = {"bias_diff_on": 0, "bias_diff_off": 0, "bias_fo": 3}
    changes = [Change({"bias_fo": 3}, 0, None, "bias file", 50)]          # in `start` already
    log = BiasLog(start, changes, first=1)
    model = ThresholdModel.of(cam, CaptureOptions())
    v0 = log.view_record([_take(100, 200)], cam, model, cam.clock)
    assert v0 == {"biases": start, "bias_changes": [], "thresholds": {"c_pos": 0.2, "c_neg": 0.2},
                  "thresholds_source": "bias model"}
    changes += [Change({"bias_diff_on": 30}, 0, 777, "parameter service", 250),      # between views
                Change({"bias_diff_off": -20}, 0, None, "parameter service", 350),   # while recording
                Change({"bias_diff_on": 40}, 0, 999, "parameter service", 450)]      # in a repeat take
    v1 = log.view_record([_take(300, 400), _take(420, 500)], cam, model, cam.clock)
    assert v1["biases"] == dict(start, bias_diff_on=30)
    c = thresholds_from_biases(30, 0)
    assert v1["thresholds"] == {"c_pos": c[0], "c_neg": c[1]} and v1["thresholds_source"] == "bias model"
    # sensor times on the stream's clock (host - 1 ns here), the one the views are cut by
    assert [(m["when"], m["sensor_ns"], m["values"]) for m in v1["bias_changes"]] == [
        ("before", 249, {"bias_diff_on": 30}), ("recording", 349, {"bias_diff_off": -20}),
        ("repeat takes", 449, {"bias_diff_on": 40})]
    after = thresholds_from_biases(30, -20)
    assert v1["bias_changes"][1]["thresholds"] == {"c_pos": after[0], "c_neg": after[1]}
    assert log.view_record([_take(600, 700)], cam, model, cam.clock)["bias_changes"] == []      # each change once
    # a change whose thread appended it only after the previous view's record (a loaded machine):
    # not lost, it goes into the next view's record as before it
    changes.append(Change({"bias_fo": 5}, 0, None, "parameter service", 650))
    assert [(m["when"], m["values"]) for m in log.view_record([_take(800, 850)], cam, model, cam.clock)
            ["bias_changes"]] == [("before", {"bias_fo": 5})]
    late = BiasLog(start, [Change({"bias_fo": 4}, 0, 555, "parameter service", 10)])
    assert late.view_record([_take(100, 200)], cam, model, ArrivalClock("empty"))["bias_changes"][0]["sensor_ns"] == 555

    views = [dict(v0, name="view_00"), dict(v1, name="view_01")]
    th = _session_thresholds(views, model, cam.model)
    assert (th["c_pos"], th["c_neg"]) == (0.2, 0.2) and "bias model rig.camera.evk4" in th["source"]
    assert "differ between views" in th["per_view"]
    assert "the same" in _session_thresholds(views[:1], model, cam.model)["per_view"]

    # the options: asked for, a driver without a model, a model value the layout refuses
    opts = CaptureOptions(thresholds_from="options", c_pos=0.3, c_neg=0.4)
    fixed = ThresholdModel.of(cam, opts)
    assert log.view_record([_take(800, 900)], cam, fixed, cam.clock)["thresholds"] == {"c_pos": 0.3, "c_neg": 0.4}
    assert "--thresholds-from options" in _session_thresholds(
        [dict(log.view_record([_take(800, 900)], cam, fixed, cam.clock), name="v")], fixed, cam.model)["source"]

    class NoModel:
        model = "DVXplorer"

    said = []
    none = ThresholdModel.of(NoModel(), CaptureOptions(c_pos=0.25), log=said.append)
    assert none.of_biases(NoModel(), {}) == ({"c_pos": 0.25, "c_neg": 0.2}, "options")
    assert "no bias -> threshold model" in said[0]
    huge = BiasLog({"bias_diff_on": 400, "bias_diff_off": 0}, [])        # exp(4) * 0.2 = 10.9 > C_MAX
    rec = huge.view_record([_take(1, 2)], cam, model, cam.clock)
    assert rec["thresholds_source"] == "options" and rec["thresholds"] == {"c_pos": 0.2, "c_neg": 0.2}
    assert "outside (0, 10]" in model.describe("options", cam.model)


# --------------------------------------------------------------------------- the layout's schema


def _session(tmp_path, **view_keys):
    from evdnerf_ros.session.recorder import camera_record, session_document, view_record

    view = view_record("view_00", "train", np.eye(4), **view_keys)
    return session_document(source={"kind": "capture"}, rig={"kind": "turntable"},
                            camera=camera_record(32, 24, [[30, 0, 16], [0, 30, 12], [0, 0, 1]]),
                            thresholds={"c_pos": 0.2, "c_neg": 0.2, "source": "options"}, views=[view])


GOOD = {"thresholds": {"c_pos": 0.25, "c_neg": 0.3}, "thresholds_source": "bias model",
        "biases": {"bias_diff_on": -20, "bias_fo": 3},
        "bias_changes": [{"sensor_ns": 123, "when": "recording", "values": {"bias_diff_on": -20},
                          "source": "parameter service", "thresholds": {"c_pos": 0.25, "c_neg": 0.3}},
                         {"sensor_ns": None, "values": {"bias_fo": 3}}]}


def test_the_session_layout_reads_and_checks_per_view_thresholds_and_biases(tmp_path):
    from evdnerf_ros.session.layout import check_session
    from evdnerf_ros.session.recorder import write_session_yaml

    s = check_session(tmp_path, _session(tmp_path, **GOOD))
    assert s.views[0].thresholds == (0.25, 0.3) and (s.c_pos, s.c_neg) == (0.2, 0.2)
    assert check_session(tmp_path, _session(tmp_path)).views[0].thresholds is None
    bad = [({"thresholds": {"c_pos": 0.0, "c_neg": 0.3}}, "views[0].thresholds.c_pos"),
           ({"thresholds": {"c_pos": 0.2}}, "views[0].thresholds.c_neg"),
           ({"thresholds_source": "guess"}, "views[0].thresholds_source"),
           ({"biases": {"bias_fo": 1.5}}, "views[0].biases.bias_fo"),
           ({"biases": {"bias_fo": True}}, "views[0].biases.bias_fo"),
           ({"biases": [1, 2]}, "views[0].biases"),
           ({"bias_changes": {"values": {}}}, "views[0].bias_changes"),
           ({"bias_changes": [{"sensor_ns": "soon", "values": {}}]}, "views[0].bias_changes[0].sensor_ns"),
           ({"bias_changes": [{"sensor_ns": 5}]}, "views[0].bias_changes[0]"),
           ({"bias_changes": [{"values": {"x": 1}, "thresholds": {"c_pos": 11, "c_neg": 1}}]},
            "views[0].bias_changes[0].thresholds.c_pos")]
    (tmp_path / "S").mkdir()
    for keys, where in bad:
        with pytest.raises(InputError, match=re.escape(where)):
            check_session(tmp_path, _session(tmp_path, **keys))
        with pytest.raises(InputError, match=re.escape(where)):      # the writer refuses it too: nothing lands
            write_session_yaml(tmp_path / "S", _session(tmp_path, **keys))
        assert not (tmp_path / "S" / "session.yaml").exists()
    path = write_session_yaml(tmp_path / "S", _session(tmp_path, **GOOD))
    assert yaml.safe_load(Path(path).read_text())["views"][0]["bias_changes"][0]["sensor_ns"] == 123


def test_a_recording_holds_every_transfer_that_arrived_in_its_window(tmp_path, rng):
    """`camera record --duration D`: a consumer that falls behind (its first read stalls past the
    window's end: a cold decoder on a loaded machine) still writes every transfer that arrived
    within the D seconds and waited in the queue, and none that came later."""
    from rig.camera.record import record

    class Queued(ScriptedEVK4):
        """Transfers arrive every 5 ms from start() on, into a queue the reader takes them from;
        the first read stalls 0.7 s."""

        def start(self):
            super().start()
            self._arrivals = []
            self._stalled = False

        def read_raw(self, timeout_s: float = 1.0):
            if not self._stalled:
                self._stalled = True
                time.sleep(0.7)
            now = time.monotonic_ns()
            while self._made + self._t0 + 5_000_000 <= now:            # what arrived meanwhile
                t = self._made + 5_000_000
                ev = _events(self.rng, 20, self._made + 1000, 4_000_000)
                self.sent.append(ev)
                self._arrivals.append(RawChunk(self._encoder.encode(ev), t + self._t0, time.time_ns(),
                                               len(self._arrivals) + 1))
                self._made = t
            if not self._arrivals:
                time.sleep(min(timeout_s, 0.005))
                return None
            return self._arrivals.pop(0)

    cam = Queued(rng)
    bag = tmp_path / "bag"
    counts = record(cam, bag, duration_s=0.5, log=lambda m: None)
    # ~100 transfers of 20 events arrived in the 0.5 s (without the queue's drain: the first one
    # only), ~140 by the time the stalled read returned (the later ones are not the recording's)
    assert 20 * 80 <= counts["events"] <= 20 * 120, counts
    from evdnerf_ros.io.event_files import read_event_file

    assert read_event_file(bag).events.size == counts["events"]


def test_a_late_stream_that_advances_is_waited_for_one_that_stands_still_is_a_fault():
    """After DONE + settle (here at 100 s on the host clock, stall limit 15 s): a stream creeping
    forward (a twin rendering at a tenth of real time) is never a fault, however far behind;
    one whose sensor time stands still for more than 15 s is, counted from DONE + settle or from
    its last advance; nothing timed yet counts as standing still."""
    from rig.capture import StreamWatch

    creeping = StreamWatch(100.0, 15.0)
    assert not any(creeping.stalled(100.0 + k, 5_000_000_000 + k * 100_000_000) for k in range(60))
    still = StreamWatch(100.0, 15.0)
    assert not still.stalled(100.0, 7_000_000_000) and not still.stalled(114.9, 7_000_000_000)
    assert still.stalled(115.1, 7_000_000_000)
    resumed = StreamWatch(100.0, 15.0)
    assert not resumed.stalled(100.0, 1) and not resumed.stalled(110.0, 2)      # advanced at 110 s
    assert not resumed.stalled(124.9, 2) and resumed.stalled(125.1, 2)
    nothing = StreamWatch(100.0, 15.0)
    assert not nothing.stalled(110.0, None) and nothing.stalled(115.1, None)
