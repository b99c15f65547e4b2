"""Virtual iniVation DAVIS346: libcaer's DAVIS FX3 USB protocol, served through umockdev.

``VirtualDAVIS346(source)`` is an ``EmulatedUsbDevice`` (152a:841a, manufacturer "iniVation",
product "DAVIS FX3", bcdDevice = firmware version in the low byte) that answers what the camera
answers (facts in rig.camera.davis346):

* vendor request 0xBF: OUT (0x40) writes the 4-byte big-endian value of (module = wValue,
  parameter = wIndex) into a register map, IN (0xC0) reads it back (never-written parameters
  read 0); 0xC2 writes wValue records of {u8 module, u8 parameter, u32 BE}. Every write is
  recorded in order in ``writes``, every read in ``reads``; any other request (or a malformed
  one) stalls and is recorded in ``stalled``; the system information module (6) is read-only;
* the identity registers: logic version (6,0), chip id (6,1), logic patch (6,7), clocks (6,3..6),
  the DVS / APS sizes and orientations, the filter capabilities (DVS ROI filter present, ...);
* DAVIS words (rig.camera.davis_words) on bulk IN 0x82 only while USB run (9,0), chip run (0,3),
  multiplexer run (0,0), timestamp run (0,1) and DVS run (1,3) or APS run (2,4) are set (DVS
  events only while DVS run is). Sensor time starts at 0 when the timestamp generator starts; a
  timestamp reset (0,2) = 1 writes a reset word and restarts time and the source. While nothing
  happens the stream still
  carries a timestamp-wrap word every 2**15 us (``idle_wraps``);
* contrast thresholds follow the ON / OFF biases relative to DiffBn
  (rig.camera.davis346.thresholds_from_bias_words: C_on ~ ln(I_on / I_diff), C_off ~
  ln(I_diff / I_off), both 0.2 at libcaer's defaults); the DVS ROI filter (1,41..44) crops the
  events; ``pulse_trigger()`` inserts external-input edge words when the detector (4,0) runs;
  ``unplug()`` pulls the cable;
* while APS run (2,4) is set and the twin has a frame source (``frame_source(t_ns) -> (H, W)``
  intensity in [0, 1], or the renderer of a scene source), it sends a global-shutter frame every
  frame interval (2,13) with the exposure (2,12) (both in ADC clock cycles), the frame's image
  being the intensity at mid-exposure in ADC counts (round(I * 1022), decoded as counts << 6).

Timing: ``realtime=True`` streams at the wall clock's pace; ``realtime=False`` advances
``step_us`` of sensor time per bulk IN transfer that finds the FIFO short. What went out is kept
as the truth: ``emitted_events()`` / ``emitted_triggers()`` (in wire order) and ``emitted_frames``.
"""

from __future__ import annotations

import time

import numpy as np

from evdnerf_ros.events.types import EVENT_DTYPE

from .. import davis346 as D
from ..davis_words import ApsFrame, DavisWordEncoder
from ..device import SAMPLE_EVENT
from .caer_twin import CaerTwin
from .usb import EndpointSpec

__all__ = ["VirtualDAVIS346"]


class VirtualDAVIS346(CaerTwin):
    """Emulated DAVIS346; see the module docstring. The defaults (firmware 6, logic 18 patch 1,
    chip DAVIS346B) are what both libcaer-era drivers and neuromorphic-drivers accept."""

    DATA_ENDPOINT = D.DAVIS346.DATA_ENDPOINT
    ADC_CLOCK_MHZ = 64
    LOGIC_CLOCK_MHZ = 104
    USB_CLOCK_MHZ = 80

    def __init__(self, source=None, *, serial: str = "DAV00001", firmware: int = 6, logic_version: int = 18,
                 logic_patch: int = 1, chip_id: int = 5, realtime: bool = True, latency_us: int = 0, step_us: int = 10_000,
                 min_window_us: int = 1_000, idle_wraps: bool = True, max_transfer_bytes: int | None = None,
                 frame_source=None, roi_filter: bool = True, speed: str = "super"):
        super().__init__(D.VID, D.PID, bcd_device=int(firmware) & 0xFF, serial=serial, manufacturer="iniVation",
                         product="DAVIS FX3", speed=speed,
                         endpoints=(EndpointSpec(0x81, "interrupt", 1), EndpointSpec(self.DATA_ENDPOINT)))
        self.width, self.height = D.DAVIS346.width, D.DAVIS346.height
        self._init_stream(source, realtime=realtime, latency_us=latency_us, step_us=step_us,
                          min_window_us=min_window_us, idle_wraps=idle_wraps, max_transfer_bytes=max_transfer_bytes)
        self.frame_source = frame_source
        if frame_source is None and hasattr(self.source, "_render") and \
                (self.source.width, self.source.height) == (self.width, self.height):
            self.frame_source = self.source._render
        self.registers.update({
            (D.SYSINFO, D.SYSINFO_LOGIC_VERSION): int(logic_version),
            (D.SYSINFO, D.SYSINFO_CHIP_IDENTIFIER): int(chip_id),
            (D.SYSINFO, D.SYSINFO_DEVICE_IS_MASTER): 1,
            (D.SYSINFO, D.SYSINFO_LOGIC_CLOCK): self.LOGIC_CLOCK_MHZ,
            (D.SYSINFO, D.SYSINFO_ADC_CLOCK): self.ADC_CLOCK_MHZ,
            (D.SYSINFO, D.SYSINFO_USB_CLOCK): self.USB_CLOCK_MHZ,
            (D.SYSINFO, D.SYSINFO_CLOCK_DEVIATION): 1000,
            (D.SYSINFO, D.SYSINFO_LOGIC_PATCH): int(logic_patch),
            (D.DVS, D.DVS_SIZE_COLUMNS): self.width,
            (D.DVS, D.DVS_SIZE_ROWS): self.height,
            (D.DVS, D.DVS_ORIENTATION_INFO): 0,
            (D.DVS, D.DVS_HAS_PIXEL_FILTER): 1,
            (D.DVS, D.DVS_HAS_BACKGROUND_ACTIVITY_FILTER): 1,
            (D.DVS, D.DVS_HAS_ROI_FILTER): int(bool(roi_filter)),
            (D.DVS, D.DVS_HAS_SKIP_FILTER): 1,
            (D.DVS, D.DVS_HAS_POLARITY_FILTER): 1,
            (D.DVS, D.DVS_ROI_END_COLUMN): self.width - 1,
            (D.DVS, D.DVS_ROI_END_ROW): self.height - 1,
            (D.APS, D.APS_SIZE_COLUMNS): self.width,
            (D.APS, D.APS_SIZE_ROWS): self.height,
            (D.APS, D.APS_ORIENTATION_INFO): 0,
            (D.APS, D.APS_HAS_GLOBAL_SHUTTER): 1,
            (D.APS, D.APS_EXPOSURE): 4000 * self.ADC_CLOCK_MHZ,
            (D.APS, D.APS_FRAME_INTERVAL): 40000 * self.ADC_CLOCK_MHZ,
            (D.IMU, D.IMU_TYPE): 0,                          # no IMU samples are emulated
            (D.EXTINPUT, D.EXTINPUT_HAS_GENERATOR): 0,
        })
        for p, v in D.default_chip_config():                 # the chip powers up as libcaer configures it
            self.registers[(D.BIAS, p)] = v
        self.emitted_frames: list[ApsFrame] = []
        self._encoder = DavisWordEncoder(self.width, self.height)
        # load the encoder's compiled kernel now, not inside the first event transfer's USB handler
        # (~0.5 s there, seconds on a loaded machine: every other request of the device waits)
        DavisWordEncoder(self.width, self.height).encode(SAMPLE_EVENT)
        self._aps_next_us: int | None = None
        self._aps_open: tuple[int, int] | None = None      # (start us, end us) of the frame being exposed

    # --- registers ------------------------------------------------------------------
    def _write(self, module: int, param: int, value: int) -> None:
        self.writes.append((module, param, value))
        if module == D.SYSINFO:
            return
        key = (module, param)
        old = self.registers.get(key, 0)
        self.registers[key] = value
        if key == (D.MUX, D.MUX_TIMESTAMP_RUN):
            if value and not old:
                self._start_clock()
            elif old and not value:
                self._clock_on = False
                self._backlog.clear()
                self._pending_tr.clear()
                self._aps_open = None
        elif key == (D.MUX, D.MUX_TIMESTAMP_RESET) and value and self._clock_on:
            self._start_clock()
            self._backlog += self._encoder.reset()
        elif key == (D.APS, D.APS_RUN):
            if value and not old:
                self._aps_next_us = self._produced_us + 1
            elif old and not value:
                self._aps_next_us = None

    def _start_clock(self) -> None:
        self._clock_on = True
        self._t0_ns = time.monotonic_ns()
        self._produced_us = 0
        self._encoder = DavisWordEncoder(self.width, self.height)
        self._pending_tr.clear()
        self._aps_open = None
        if self._aps_next_us is not None:
            self._aps_next_us = 1
        self.source.restart()

    def _streaming(self) -> bool:
        r = self._reg
        return bool(self._clock_on and r(D.USB, D.USB_RUN) and r(D.MUX, D.MUX_RUN) and r(D.MUX, D.MUX_RUN_CHIP)
                    and (r(D.DVS, D.DVS_RUN) or r(D.APS, D.APS_RUN)))

    def biases(self) -> dict[str, int]:
        """The bias parameters as the driver reads them (flat names of rig.camera.davis346.BIASES)."""
        with self.lock:
            return {n: (self._reg(D.BIAS, p) >> s) & ((1 << b) - 1) for n, (p, s, b) in D.BIASES.items()}

    def thresholds(self) -> tuple[float, float]:
        with self.lock:
            return self._thresholds_now()

    def _thresholds_now(self):
        b = D.COARSE_FINE_BIASES
        return D.thresholds_from_bias_words(self._reg(D.BIAS, b["diffbn"]), self._reg(D.BIAS, b["onbn"]),
                                            self._reg(D.BIAS, b["offbn"]))

    def crop(self):
        """(x0, y0, x1, y1) inclusive the ROI filter passes."""
        with self.lock:
            return self._crop()

    def _crop(self):
        r = self._reg
        return (r(D.DVS, D.DVS_ROI_START_COLUMN), r(D.DVS, D.DVS_ROI_START_ROW), r(D.DVS, D.DVS_ROI_END_COLUMN),
                r(D.DVS, D.DVS_ROI_END_ROW))

    # --- production -------------------------------------------------------------------
    def _aps_marks(self, t1: int) -> list[tuple[int, int, int]]:
        """(time us, 0 begin / 1 end, end us) of the APS frame boundaries in (produced, t1]; a frame
        whose exposure ends after t1 is begun now and ended by a later call."""
        marks = []
        if self.frame_source is None:
            return marks
        if self._aps_open is not None:
            if self._aps_open[1] > t1:
                return marks
            marks.append((self._aps_open[1], 1, self._aps_open[1]))
        adc = max(1, self._reg(D.SYSINFO, D.SYSINFO_ADC_CLOCK))
        exposure = max(1, self._reg(D.APS, D.APS_EXPOSURE) // adc)
        interval = max(exposure + 1, self._reg(D.APS, D.APS_FRAME_INTERVAL) // adc)
        while self._reg(D.APS, D.APS_RUN) and self._aps_next_us is not None and self._aps_next_us <= t1:
            t0 = self._aps_next_us
            self._aps_next_us = t0 + interval
            marks.append((t0, 0, t0 + exposure))
            if t0 + exposure > t1:
                break
            marks.append((t0 + exposure, 1, t0 + exposure))
        return marks

    def _produce_until(self, t1: int) -> None:
        th = self._thresholds_now()
        if th != self._thresholds and hasattr(self.source, "set_thresholds"):
            self.source.set_thresholds(*th)
            self._thresholds = th
        src = self.source.events_until(1000 * t1)
        ev = np.empty(src.shape[0], EVENT_DTYPE)
        ev["t"] = (src["t"] // 1000) * 1000
        ev["x"], ev["y"], ev["p"] = src["x"], src["y"], src["p"]
        if ev.size:
            x0, y0, x1, y1 = self._crop()
            ok = ((ev["x"] >= x0) & (ev["x"] <= x1) & (ev["y"] >= y0) & (ev["y"] <= y1) & (ev["p"] != 0)
                  & (ev["x"] < self.width) & (ev["y"] < self.height))
            if not self._reg(D.DVS, D.DVS_RUN):
                ok[:] = False
            if not ok.all():
                ev = ev[ok]
        tr = self._take_triggers(t1)
        marks = self._aps_marks(t1)
        self._produced_us = t1
        words = bytearray()
        us = ev["t"] // 1000
        tus = tr["t"] // 1000
        i = j = 0
        for tm, kind, te in marks + [(t1, -1, t1)]:
            i2 = int(np.searchsorted(us, tm, side="right"))
            j2 = int(np.searchsorted(tus, tm, side="right"))
            if i2 > i or j2 > j:
                words += self._encoder.encode(ev[i:i2], tr[j:j2])
            i, j = i2, j2
            if kind == 0:
                words += self._encoder.aps_begin(tm)
                self._aps_open = (tm, te)
            elif kind == 1:
                words += self._aps_end(tm)
        if ev.size:
            self._emitted.append(ev)
        if tr.size:
            self._emitted_tr.append(tr)
        if self.idle_wraps:
            words += self._encoder.advance(t1)
        self._backlog += words

    def _aps_end(self, t_end: int) -> bytes:
        t_start = self._aps_open[0]
        self._aps_open = None
        mid = (t_start + t_end) * 500
        img = np.clip(np.asarray(self.frame_source(mid), np.float64), 0.0, 1.0)
        adc = np.rint(img * (DavisWordEncoder.APS_RESET_LEVEL - 1)).astype(np.int64)
        self.emitted_frames.append(ApsFrame((adc << 6).astype(np.uint16), 0, 0, 1000 * t_start, 1000 * t_start,
                                            1000 * t_end, 1000 * t_end, True))
        return self._encoder.aps_end(t_end, adc)
