"""Virtual iniVation DVXplorer: libcaer's USB protocol, served through umockdev.

``VirtualDVXplorer(source)`` is an ``EmulatedUsbDevice`` (152a:8419, manufacturer "iniVation",
product "DVXplorer", bcdDevice = firmware version in the low byte) that answers what the camera
answers (facts in rig.camera.dvxplorer):

* vendor request 0xBF: OUT (0x40) writes the 4-byte big-endian value of (module = wValue,
  parameter = wIndex) into a register map, IN (0xC0) reads it back (4 bytes; never-written
  parameters read 0); 0xC2 writes wValue records of {u8 module, u8 parameter, u32 BE}. Every
  write is recorded in order in ``writes`` (module, parameter, value), every read in ``reads``;
  any other vendor request (or a malformed one) stalls and is recorded in ``stalled``;
* the identity registers: logic version (6,0), chip id (6,1), logic patch (6,7), clocks, the
  sensor size (1,0) / (1,1) and orientation (1,2);
* libcaer words (rig.camera.caer_words) on bulk IN 0x82 ONLY while USB run (9,0), multiplexer
  run (0,0), multiplexer timestamp run (0,1) and DVS run (1,3) are all set. Sensor time starts
  at 0 when the timestamp generator starts (0,1); a multiplexer timestamp reset (0,2) = 1
  writes a timestamp-reset word and restarts time (and the source) at 0. While no event
  happens the stream still carries the timestamp-wrap word of every 2**15 us (``idle_wraps``);
* the contrast thresholds follow the ON / OFF bias currents (``thresholds()``, the driver's model
  rig.camera.dvxplorer.thresholds_from_biases); the sensor's
  cropper registers crop the events (libcaer's row-group masks, including its corner case);
  ``pulse_trigger()`` inserts external-input edge words when the detector (4,0) runs, for the
  edges it detects (4,1) rising, (4,2) falling, (4,3) pulses; ``unplug()`` pulls the cable.

Timing: ``realtime=True`` streams sensor time at the wall clock's pace (a live camera);
``realtime=False`` advances ``step_us`` of sensor time per bulk IN transfer that finds the
FIFO short (long streams in a fraction of their duration). What went out is kept as the
truth: ``emitted_events()`` / ``emitted_triggers()`` (EVENT_DTYPE / TRIGGER_DTYPE, sensor ns,
events in the order the words carry them, see caer_words.canonical_order).
"""

from __future__ import annotations

import struct
import time

import numpy as np

from evdnerf_ros.events.types import EVENT_DTYPE, TRIGGER_DTYPE

from .. import dvxplorer as D
from ..dvxplorer import BASE_THRESHOLD, thresholds_from_biases   # the driver's model: one copy
from ..caer_words import (TRIGGER_EDGE, TRIGGER_PULSE, CaerWordEncoder, canonical_order)
from ..device import SAMPLE_EVENT
from .scene_source import EmittedTruth, GivenEvents
from .usb import STALL, EmulatedUsbDevice, EndpointSpec

__all__ = ["VirtualDVXplorer", "thresholds_from_biases", "BASE_THRESHOLD"]

def _as_source(source, width, height):
    if source is None:
        return GivenEvents(np.empty(0, EVENT_DTYPE), width, height)
    if isinstance(source, np.ndarray):
        return GivenEvents(source, width, height)
    if isinstance(source, str):
        from .scene_source import SceneEventSource
        return SceneEventSource(source, width, height)
    if hasattr(source, "events_until"):
        return source
    raise TypeError("source must be None, an EVENT_DTYPE array, a scene name / YAML path or an "
                    "EventSource (rig.camera.virtual.scene_source)")


class VirtualDVXplorer(EmulatedUsbDevice, EmittedTruth):
    """Emulated DVXplorer; see the module docstring. ``firmware=9, logic_patch=4`` is what
    neuromorphic-drivers accepts (libcaer: firmware 8, patch >= 2)."""

    def __init__(self, source=None, *, serial: str = "DVX00001", firmware: int = 8, logic_version: int = 18,
                 logic_patch: int = 2, chip_id: int = 20, realtime: bool = True, latency_us: int = 0, step_us: int = 10_000,
                 min_window_us: int = 1_000, idle_wraps: bool = True, max_transfer_bytes: int | None = None,
                 speed: str = "super"):
        super().__init__(D.VID, D.PID, bcd_device=int(firmware) & 0xFF, serial=serial, manufacturer="iniVation",
                         product="DVXplorer", speed=speed,
                         endpoints=(EndpointSpec(0x81, "interrupt", 1), EndpointSpec(D.DVXplorer.DATA_ENDPOINT)))
        self.width, self.height = D.DVXplorer.width, D.DVXplorer.height
        self.source = _as_source(source, self.width, self.height)
        self.realtime = bool(realtime)
        # realtime: stream this far behind the wall clock (a camera's pipeline delay), so
        # that a signal learnt late (the virtual rig's trigger, its joint angles) still
        # lands at its true sensor time
        self.latency_us = int(latency_us)
        self.step_us = int(step_us)
        self.min_window_us = int(min_window_us)
        self.idle_wraps = bool(idle_wraps)
        self.max_transfer_bytes = None if max_transfer_bytes is None else max(2, int(max_transfer_bytes) & ~1)
        self.registers: dict[tuple[int, int], int] = {
            (D.SYSINFO, D.SYSINFO_LOGIC_VERSION): int(logic_version),
            (D.SYSINFO, D.SYSINFO_CHIP_IDENTIFIER): int(chip_id),
            (D.SYSINFO, D.SYSINFO_DEVICE_IS_MASTER): 1,
            (D.SYSINFO, D.SYSINFO_LOGIC_CLOCK): 104,
            (D.SYSINFO, D.SYSINFO_USB_CLOCK): 83,
            (D.SYSINFO, D.SYSINFO_CLOCK_DEVIATION): 1000,
            (D.SYSINFO, D.SYSINFO_LOGIC_PATCH): int(logic_patch),
            (D.DVS, D.DVS_SIZE_COLUMNS): self.width,
            (D.DVS, D.DVS_SIZE_ROWS): self.height,
            (D.DVS, D.DVS_ORIENTATION_INFO): 0,
            (D.IMU, 0): 0,                                  # no IMU samples are emulated
            (D.DEVICE_DVS, D.REG_CROPPER_BYPASS): 1,
        }
        for reg, val in D.BIAS_PRESETS["default"]:
            self.registers[(D.DEVICE_DVS, reg)] = val
        self.writes: list[tuple[int, int, int]] = []
        self.reads: list[tuple[int, int]] = []
        self.stalled: list = []                            # SetupPackets answered with a stall
        self._emitted: list[np.ndarray] = []
        self._emitted_tr: list[np.ndarray] = []
        self._pending_tr: list[tuple[int, int, int]] = []  # (sensor us, id, value)
        self._backlog = bytearray()
        self.bytes_streamed = 0
        self.transfers_streamed = 0
        self._clock_on = False
        self._t0_ns = 0
        self._produced_us = 0
        self._encoder = CaerWordEncoder(self.width, self.height)
        # load the encoder's compiled kernel now, not inside the first event transfer's USB handler
        # (~0.5 s there, seconds on a loaded machine: every other request of the device waits)
        CaerWordEncoder(self.width, self.height).encode(SAMPLE_EVENT)
        self._thresholds = None

    # --- registers ------------------------------------------------------------------
    def register(self, module: int, param: int) -> int:
        with self.lock:
            return self.registers.get((module, param), 0)

    def _reg(self, module, param):
        return self.registers.get((module, param), 0)

    def _write(self, module: int, param: int, value: int) -> None:
        self.writes.append((module, param, value))
        if module == D.SYSINFO:
            return                                          # read-only module (libcaer refuses too)
        key = (module, param)
        old = self.registers.get(key, 0)
        if module == D.DEVICE_DVS:
            value &= 0xFF
        self.registers[key] = value
        if key == (D.MUX, D.MUX_TIMESTAMP_RUN):
            if value and not old:
                self._start_clock()
            elif old and not value:
                self._clock_on = False
                self._backlog.clear()                       # the FIFO is flushed when time stops
                self._pending_tr.clear()
        elif key == (D.MUX, D.MUX_TIMESTAMP_RESET) and value and self._clock_on:
            self._start_clock()
            self._backlog += self._encoder.reset()

    def _start_clock(self) -> None:
        """Sensor time 0: the timestamp generator (re)starts and so does the source."""
        self._clock_on = True
        self._t0_ns = time.monotonic_ns()
        self._produced_us = 0
        self._encoder = CaerWordEncoder(self.width, self.height)
        self._pending_tr.clear()
        self.source.restart()

    def _streaming(self) -> bool:
        r = self._reg
        return bool(self._clock_on and r(D.USB, D.USB_RUN) and r(D.MUX, D.MUX_RUN) and r(D.DVS, D.DVS_RUN))

    @property
    def streaming(self) -> bool:
        with self.lock:
            return self._streaming()

    def biases(self) -> dict[str, int]:
        """The bias parameters as the driver reads them (libcaer names)."""
        with self.lock:
            return {n: (self._reg(D.DEVICE_DVS, reg) & mask) >> shift
                    for n, (reg, mask, shift, _top) in D.BIASES.items()}

    def thresholds(self) -> tuple[float, float]:
        with self.lock:
            return thresholds_from_biases(self._reg(D.DEVICE_DVS, D.REG_BIAS_CURRENT_ON),
                                          self._reg(D.DEVICE_DVS, D.REG_BIAS_CURRENT_OFF))

    def crop(self):
        """(x_ok[width], y_ok[height]) boolean masks the cropper applies, or None when bypassed."""
        with self.lock:
            return self._crop()

    def _crop(self):
        r = lambda reg: self._reg(D.DEVICE_DVS, reg)  # noqa: E731
        if r(D.REG_CROPPER_BYPASS):
            return None
        x0 = (r(D.REG_CROPPER_X_START_ADDRESS) << 8) | r(D.REG_CROPPER_X_START_ADDRESS + 1)
        x1 = (r(D.REG_CROPPER_X_END_ADDRESS) << 8) | r(D.REG_CROPPER_X_END_ADDRESS + 1)
        sg, sm = r(D.REG_CROPPER_Y_START_GROUP), r(D.REG_CROPPER_Y_START_MASK)
        eg, em = r(D.REG_CROPPER_Y_END_GROUP), r(D.REG_CROPPER_Y_END_MASK)
        x = np.arange(self.width)
        y = np.arange(self.height)
        g, b = y >> 3, y & 7
        y_ok = (g >= sg) & (g <= eg)
        if sg == eg:                                        # only the END mask applies
            y_ok &= ((em >> b) & 1).astype(bool) | (g != eg)
        else:
            y_ok &= ((sm >> b) & 1).astype(bool) | (g != sg)
            y_ok &= ((em >> b) & 1).astype(bool) | (g != eg)
        return (x >= x0) & (x <= x1), y_ok

    @property
    def trigger_input_enabled(self) -> bool:
        return bool(self.register(D.EXTINPUT, D.EXTINPUT_RUN_DETECTOR))

    # --- USB hooks -------------------------------------------------------------------
    def control(self, setup, data):
        with self.lock:
            reply = self._control(setup, bytes(data))
            if reply is STALL:
                self.stalled.append(setup)
            return reply

    def _control(self, setup, data):
        if setup.kind != "vendor":
            return STALL
        if setup.request == D.REQUEST_CONFIG:
            if setup.request_type == 0x40 and len(data) == 4:
                self._write(setup.value, setup.index, struct.unpack(">I", data)[0])
                return b""
            if setup.request_type == 0xC0 and setup.length == 4:
                self.reads.append((setup.value, setup.index))
                return struct.pack(">I", self._reg(setup.value, setup.index) & 0xFFFFFFFF)
            return STALL
        if setup.request == D.REQUEST_CONFIG_MULTIPLE and setup.request_type == 0x40:
            n = setup.value
            if n == 0 or len(data) != 6 * n:
                return STALL
            for k in range(n):
                m, p, v = struct.unpack_from(">BBI", data, 6 * k)
                self._write(m, p, v)
            return b""
        return STALL

    def bulk_in(self, endpoint: int, max_len: int):
        with self.lock:
            if endpoint != D.DVXplorer.DATA_ENDPOINT:
                return None if endpoint == 0x81 else STALL
            if self.max_transfer_bytes is not None:
                max_len = min(max_len, self.max_transfer_bytes)
            if not self._streaming():
                return None
            if len(self._backlog) < max_len:
                self._produce(max_len)
            if not self._backlog:
                return None
            n = min(max_len, len(self._backlog))
            out = bytes(self._backlog[:n])
            del self._backlog[:n]
            self.bytes_streamed += len(out)
            self.transfers_streamed += 1
            return out

    # --- event production ---------------------------------------------------------------
    def _now_us(self) -> int:
        if self.realtime:
            now = (time.monotonic_ns() - self._t0_ns) // 1000 - self.latency_us
            return min(now, self.source.ready_ns(1000 * now) // 1000)   # what is rendered
        return self._produced_us + self.step_us

    #: at most this many step_us windows per bulk IN transfer when not realtime
    MAX_STEPS_PER_TRANSFER = 64

    def _produce(self, want: int) -> None:
        for _ in range(1 if self.realtime else self.MAX_STEPS_PER_TRANSFER):
            target = self._now_us()
            if target - self._produced_us < (self.min_window_us if self.realtime else 1):
                return
            self._produce_until(target)
            if len(self._backlog) >= want:
                return

    def _produce_until(self, t1: int) -> None:
        th = thresholds_from_biases(self._reg(D.DEVICE_DVS, D.REG_BIAS_CURRENT_ON),
                                    self._reg(D.DEVICE_DVS, D.REG_BIAS_CURRENT_OFF))
        if th != self._thresholds and hasattr(self.source, "set_thresholds"):
            self.source.set_thresholds(*th)
            self._thresholds = th
        src = self.source.events_until(1000 * t1)
        ev = np.empty(src.shape[0], EVENT_DTYPE)
        ev["t"] = (src["t"] // 1000) * 1000                 # the sensor counts whole microseconds
        ev["x"], ev["y"], ev["p"] = src["x"], src["y"], src["p"]
        if ev.size:
            ok = (ev["x"] < self.width) & (ev["y"] < self.height) & (ev["p"] != 0)
            crop = self._crop()
            if crop is not None:
                xo, yo = crop
                ok &= xo[np.minimum(ev["x"], self.width - 1)] & yo[np.minimum(ev["y"], self.height - 1)]
            if not ok.all():
                ev = ev[ok]
        tr = self._take_triggers(t1)
        self._produced_us = t1
        words = b""
        if ev.size or tr.size:
            ev = canonical_order(ev)
            words = self._encoder.encode(ev, tr)
            if ev.size:
                self._emitted.append(ev)
            if tr.size:
                self._emitted_tr.append(tr)
        if self.idle_wraps:
            words += self._encoder.advance(t1)
        self._backlog += words

    def _take_triggers(self, t1_us: int) -> np.ndarray:
        due = [p for p in self._pending_tr if p[0] <= t1_us]
        if not due:
            return np.empty(0, TRIGGER_DTYPE)
        self._pending_tr = [p for p in self._pending_tr if p[0] > t1_us]
        tr = np.empty(len(due), TRIGGER_DTYPE)
        tr["t"] = [1000 * t for t, _i, _v in due]
        tr["id"] = [i for _t, i, _v in due]
        tr["value"] = [v for _t, _i, v in due]
        return tr

    def pulse_trigger(self, width_us: int = 100, at_us: int | None = None):
        """A pulse on the sync connector's input: a rising edge now (or at sensor time
        ``at_us``) and a falling edge ``width_us`` later. The detector reports what it is set
        to detect: rising edges (4,1), falling edges (4,2), pulses (4,3; at the pulse's end).
        Returns the (rising, falling) sensor times in ns, or None when the detector is off or
        the camera is not streaming (a real DVXplorer reports nothing then either)."""
        with self.lock:
            if not self._streaming() or not self._reg(D.EXTINPUT, D.EXTINPUT_RUN_DETECTOR):
                return None
            if at_us is None:
                now = self._now_us() if self.realtime else self._produced_us + 1
            else:
                now = int(at_us)
            rise = max(int(now), self._produced_us + 1)
            fall = rise + max(1, int(width_us))
            if self._reg(D.EXTINPUT, D.EXTINPUT_DETECT_RISING):
                self._pending_tr.append((rise, TRIGGER_EDGE, 1))
            if self._reg(D.EXTINPUT, D.EXTINPUT_DETECT_FALLING):
                self._pending_tr.append((fall, TRIGGER_EDGE, 0))
            if self._reg(D.EXTINPUT, D.EXTINPUT_DETECT_PULSES):
                self._pending_tr.append((fall, TRIGGER_PULSE, 1))
            self._pending_tr.sort()
            return 1000 * rise, 1000 * fall

    # --- truth --------------------------------------------------------------------------
    def writes_since(self, start: int = 0) -> list[tuple[int, int, int]]:
        with self.lock:
            return list(self.writes[start:])

    def sensor_time_ns(self) -> int:
        """The twin's current sensor time (what it has streamed up to), ns."""
        with self.lock:
            return 1000 * self._produced_us
