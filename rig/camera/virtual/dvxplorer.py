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

import time

import numpy as np

from evdnerf_ros.events.types import EVENT_DTYPE

from .. import dvxplorer as D
from ..dvxplorer import BASE_THRESHOLD, thresholds_from_biases   # the driver's model: one copy
from ..caer_words import CaerWordEncoder, canonical_order
from ..device import SAMPLE_EVENT
from .caer_twin import CaerTwin
from .usb import EndpointSpec

__all__ = ["VirtualDVXplorer", "thresholds_from_biases", "BASE_THRESHOLD"]


class VirtualDVXplorer(CaerTwin):
    """Emulated DVXplorer; see the module docstring. ``firmware=9, logic_patch=4`` is what
    neuromorphic-drivers accepts (libcaer: firmware 8, patch >= 2)."""

    DATA_ENDPOINT = D.DVXplorer.DATA_ENDPOINT

    def __init__(self, source=None, *, serial: str = "DVX00001", firmware: int = 8, logic_version: int = 18,
                 logic_patch: int = 2, chip_id: int = 20, realtime: bool = True, latency_us: int = 0, step_us: int = 10_000,
                 min_window_us: int = 1_000, idle_wraps: bool = True, max_transfer_bytes: int | None = None,
                 speed: str = "super"):
        super().__init__(D.VID, D.PID, bcd_device=int(firmware) & 0xFF, serial=serial, manufacturer="iniVation",
                         product="DVXplorer", speed=speed,
                         endpoints=(EndpointSpec(0x81, "interrupt", 1), EndpointSpec(self.DATA_ENDPOINT)))
        self.width, self.height = D.DVXplorer.width, D.DVXplorer.height
        self._init_stream(source, realtime=realtime, latency_us=latency_us, step_us=step_us,
                          min_window_us=min_window_us, idle_wraps=idle_wraps, max_transfer_bytes=max_transfer_bytes)
        self.registers.update({
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
        })
        for reg, val in D.BIAS_PRESETS["default"]:
            self.registers[(D.DEVICE_DVS, reg)] = val
        self._encoder = CaerWordEncoder(self.width, self.height)
        # load the encoder's compiled kernel now, not inside the first event transfer's USB handler
        # (~0.5 s there, seconds on a loaded machine: every other request of the device waits)
        CaerWordEncoder(self.width, self.height).encode(SAMPLE_EVENT)

    # --- registers ------------------------------------------------------------------
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

    # --- event production ---------------------------------------------------------------
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
