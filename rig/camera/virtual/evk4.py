"""Virtual Prophesee EVK4: the IMX636 camera's USB protocol, served through umockdev.

``VirtualEVK4(source)`` is an ``EmulatedUsbDevice`` (04b4:00f4, manufacturer "Prophesee",
product "EVK4") that answers what the real camera answers (facts in
rig.camera.evk4_registers):

* control IN 0xC0 / 0x72 -> the sensor type (0x31, IMX636);
* 8- and 12-byte requests on bulk OUT 0x02 (serial 0x72, release 0x79, build date 0x7a and
  the identification requests neuromorphic-drivers sends), each answered on bulk IN 0x82;
* 20-byte register writes / reads on 0x02 into a register map (reply on 0x82); every write
  is recorded in order in ``writes``; a write of 1 to the reset register restores the
  power-on values; an unknown command or an address outside the register space stalls
  the OUT endpoint (the driver reports a protocol error);
* EVT 3.0 on bulk IN 0x81, ONLY while the time base runs (TIME_BASE_CTRL 0x9008 bit 0) and
  the readout gate is open (RO_CTRL 0x9028 bit 1 clear): neuromorphic-drivers' open drains
  0x81 until a 1 s timeout before it starts the sensor, so a twin that streamed earlier
  would hang it.  Sensor time starts at 0 when the time base is enabled and wraps every
  2**24 us in the words (the project's streaming encoder writes the TIME_HIGH words);
* the source's events pass the ROI (TD_ROI_X / TD_ROI_Y masks, roi_ctrl) and the contrast
  thresholds follow bias_diff_on / bias_diff_off (``thresholds()``, through the driver's
  model rig.camera.evk4.thresholds_from_biases); ``pulse_trigger()``
  inserts EXT_TRIGGER rising / falling words when the trigger input (0x7004 bit 10) is on;
  ``unplug()`` pulls the cable.

Timing: ``realtime=True`` streams sensor time at the wall clock's pace (a live camera);
``realtime=False`` advances ``step_us`` of sensor time per bulk IN transfer (tests of long
streams: a 20 s stream takes a fraction of that).  What went out is kept as the truth
(``keep_truth=True``, the default; a long-running twin passes False): ``emitted_events()`` /
``emitted_triggers()`` (EVENT_DTYPE / TRIGGER_DTYPE, sensor ns) and ``streamed`` (the bytes).
"""

from __future__ import annotations

import collections
import os
import struct
import time

import numpy as np

from evdnerf_ros.events.codecs import make_encoder
from evdnerf_ros.events.types import EVENT_DTYPE, TRIGGER_DTYPE

from .. import evk4_registers as R
from ..device import SAMPLE_EVENT
from ..evk4 import thresholds_from_biases       # the driver's model: one copy, the twin follows it
from .scene_source import EmittedTruth, live_sensor_us
from .usb import STALL, EmulatedUsbDevice, EndpointSpec

__all__ = ["VirtualEVK4", "DEFAULT_FACTORY_BIASES", "thresholds_from_biases"]

#: the twin's factory (power-on) bias DAC values; a real chip has its own per-unit values
DEFAULT_FACTORY_BIASES = {"bias_pr": 0x7C, "bias_fo": 0x53, "bias_hpf": 0x00, "bias_diff_on": 0x66,
                          "bias_diff": 0x4D, "bias_diff_off": 0x49, "bias_inv": 0x5B,
                          "bias_refr": 0x14, "bias_reqpuy": 0x8C, "bias_reqpux": 0x7C,
                          "bias_sendreqpdy": 0x94, "bias_unknown_1": 0x74, "bias_unknown_2": 0x51}
_REGISTER_SPACE = 0x10000          # sensor / FPGA registers live below this
_IDENT_REPLIES = {0x01: b"CCam5 Imx636 Event-Based Camera",
                  0x03: b"psee,ccam5_imx636 psee,ccam5_gen42"}


def _as_source(source):
    """The twin's event supply (rig.camera.virtual.scene_source interface): an EVENT_DTYPE
    array (sensor ns from the start) -> GivenEvents, a scene preset name / YAML path ->
    SceneEventSource at the sensor's 1280x720, or an EventSource as it is."""
    from .scene_source import GivenEvents, SceneEventSource
    if source is None:
        return GivenEvents(np.empty(0, EVENT_DTYPE), R.WIDTH, R.HEIGHT)
    if isinstance(source, np.ndarray):
        return GivenEvents(source, R.WIDTH, R.HEIGHT, source="VirtualEVK4 events")
    if isinstance(source, (str, os.PathLike)):
        c_on, c_off = thresholds_from_biases(0, 0)
        return SceneEventSource(source, R.WIDTH, R.HEIGHT, c_pos=c_on, c_neg=c_off)
    if hasattr(source, "events_until") and hasattr(source, "restart"):
        return source
    raise TypeError("source must be an EVENT_DTYPE array, a scene name / YAML path or an "
                    "EventSource (rig.camera.virtual.scene_source)")


class VirtualEVK4(EmulatedUsbDevice, EmittedTruth):
    """Emulated EVK4; see the module docstring."""

    def __init__(self, source=None, *, serial: int = 0x000A1B2C, sensor_type: int = 0x31,
                 release_version: int = 0x00040200, build_date: int = 0x20240115,
                 factory_biases: dict | None = None, realtime: bool = True, latency_us: int = 0,
                 step_us: int = 10_000, min_window_us: int = 1_000, product_id: int = 0x00F4,
                 speed: str = "super", keep_truth: bool = True):
        super().__init__(R.VENDOR_ID, product_id, bcd_device=0x0100, serial=f"{int(serial):08X}",
                         manufacturer="Prophesee", product="EVK4", speed=speed,
                         endpoints=(EndpointSpec(R.EP_EVENTS), EndpointSpec(R.EP_COMMAND_OUT),
                                    EndpointSpec(R.EP_COMMAND_IN)))
        self.serial_number = int(serial) & 0xFFFFFFFF
        self.sensor_type = int(sensor_type)
        self.release_version = int(release_version)
        self.build_date = int(build_date)
        self.factory = dict(DEFAULT_FACTORY_BIASES, **(factory_biases or {}))
        self.source = _as_source(source)
        self.realtime = bool(realtime)
        # realtime: stream this far behind the wall clock (a camera's pipeline delay), so
        # that a signal learnt late (the virtual rig's trigger, its joint angles) still
        # lands at its true sensor time
        self.latency_us = int(latency_us)
        self.step_us = int(step_us)
        self.min_window_us = int(min_window_us)
        self.writes: list[tuple[int, int]] = []     # every register write, in order
        self.reads: list[int] = []                  # every register read (addresses)
        self.requests: list[bytes] = []             # every command received on 0x02
        self.stalled: list[bytes] = []              # commands answered with a stall
        self._replies: collections.deque = collections.deque()
        self._emitted: list[np.ndarray] = []
        self._emitted_tr: list[np.ndarray] = []
        self._pending_tr: list[tuple[int, int]] = []    # (sensor us, value) not yet encoded
        self._backlog = bytearray()
        self.bytes_streamed = 0
        self.transfers_streamed = 0
        self.keep_truth = bool(keep_truth)
        self.streamed = bytearray()                 # every byte sent on 0x81 (keep_truth)
        self._reset_registers()
        self._time_base_on = False
        self._starts = 0              # time-base starts so far
        self._produced_us = -1        # sensor time streamed so far (events <= it are out)
        self._t0_ns = 0               # monotonic ns of sensor time 0
        self._encoder = None
        # load the encoder's compiled kernel now, not inside the first event transfer's USB handler
        # (~0.5 s there, seconds on a loaded machine: every other request of the device waits)
        make_encoder("evt3").encode(SAMPLE_EVENT)

    # --- register map -------------------------------------------------------------------
    def _reset_registers(self) -> None:
        regs: dict[int, int] = {}
        for name, addr in R.ALL_BIAS_REGISTERS.items():
            regs[addr] = R.bias_register_value(self.factory[name])
        regs[R.TIME_BASE_CTRL] = R.TIME_BASE_IDLE
        regs[R.RO_CTRL] = R.RO_OUTPUT_DISABLE
        regs[R.ROI_CTRL] = R.roi_ctrl(rstn=False)
        regs[R.EDF_RESERVED_7004] = R.edf_7004(False)
        self.registers = regs
        self._update_roi()

    def register(self, address: int) -> int:
        with self.lock:
            return self.registers.get(address, 0)

    def _update_roi(self) -> None:
        regs = self.registers
        xs = [regs.get(R.TD_ROI_X + 4 * k, 0) for k in range(R.TD_ROI_X_COUNT)]
        ys = [regs.get(R.TD_ROI_Y + 4 * k, 0) for k in range(R.TD_ROI_Y_COUNT)]
        xbits = np.unpackbits(np.array(xs, "<u4").view(np.uint8), bitorder="little")
        ybits = np.unpackbits(np.array(ys, "<u4").view(np.uint8), bitorder="little")
        self._x_ok = xbits[:R.WIDTH] == 0
        self._y_ok = ybits[:R.HEIGHT] == 0
        ctrl = regs.get(R.ROI_CTRL, 0)
        self._roi_on = bool(ctrl & R.ROI_TD_ENABLE)
        self._roi_window = bool(ctrl & R.ROI_RONI_N_EN)   # ROI mode (else RONI)

    def _write(self, address: int, value: int) -> None:
        self.writes.append((address, value))
        old = self.registers.get(address, 0)
        self.registers[address] = value
        if address == R.RESET and value & 1:
            self._reset_registers()
            self._time_base_on = False
            self._backlog.clear()
            self._pending_tr.clear()
            return
        if address == R.ROI_CTRL or R.TD_ROI_X <= address < R.TD_ROI_X + 4 * R.TD_ROI_X_COUNT \
                or R.TD_ROI_Y <= address < R.TD_ROI_Y + 4 * R.TD_ROI_Y_COUNT:
            self._update_roi()
        if address == R.TIME_BASE_CTRL:
            on = bool(value & R.TIME_BASE_ENABLE)
            if on and not old & R.TIME_BASE_ENABLE:
                self._start_time_base()
            elif not on and old & R.TIME_BASE_ENABLE:
                self._stop_time_base()

    def _start_time_base(self) -> None:
        """Sensor time 0: the source starts again from its beginning."""
        self._time_base_on = True
        if self._starts:
            self.source.restart()
        self._starts += 1
        self._t0_ns = time.monotonic_ns()
        self._produced_us = -1
        self._encoder = make_encoder("evt3")
        self._pending_tr.clear()

    def _stop_time_base(self) -> None:
        self._time_base_on = False
        self._backlog.clear()          # the FIFO is flushed when the sensor stops
        self._pending_tr.clear()

    @property
    def streaming(self) -> bool:
        """True while events flow: time base running and readout gate open."""
        with self.lock:
            return self._streaming()

    def _streaming(self) -> bool:
        return self._time_base_on and not self.registers.get(R.RO_CTRL, 0) & R.RO_OUTPUT_DISABLE

    @property
    def trigger_input_enabled(self) -> bool:
        return bool(self.register(R.EDF_RESERVED_7004) & R.EXT_TRIGGER_BIT)

    def bias_offsets(self) -> dict[str, int]:
        """The current biases as the driver sees them (offsets from the factory values)."""
        with self.lock:
            return {n: (self.registers[s.address] & 0xFF) - self.factory[n] for n, s in R.BIASES.items()}

    def thresholds(self) -> tuple[float, float]:
        b = self.bias_offsets()
        return thresholds_from_biases(b["bias_diff_on"], b["bias_diff_off"])

    def roi_mask(self) -> tuple[np.ndarray, np.ndarray, bool, bool]:
        """(columns enabled, rows enabled, roi on, window mode) as the sensor applies them."""
        with self.lock:
            return self._x_ok.copy(), self._y_ok.copy(), self._roi_on, self._roi_window

    # --- USB hooks -------------------------------------------------------------------
    def control(self, setup, data):
        if (setup.request_type, setup.request) == R.SENSOR_TYPE_REQUEST[:2]:
            return bytes([self.sensor_type, 0x00])
        return STALL

    def bulk_out(self, endpoint: int, data: bytes):
        if endpoint != R.EP_COMMAND_OUT:
            return STALL
        cmd = bytes(data)
        with self.lock:
            self.requests.append(cmd)
            reply = self._command(cmd)
            if reply is STALL:
                self.stalled.append(cmd)
                return STALL
            self._replies.append(reply)
        return None

    def _command(self, cmd: bytes):
        if len(cmd) == R.REG_COMMAND_SIZE and cmd[:12] in (R.REG_WRITE_HEADER, R.REG_READ_HEADER):
            address, value = struct.unpack_from("<II", cmd, 12)
            if not (address < _REGISTER_SPACE or address == R.RESET):
                return STALL
            if cmd[:12] == R.REG_WRITE_HEADER:
                self._write(address, value)
                return cmd
            self.reads.append(address)
            return cmd[:16] + struct.pack("<I", self.registers.get(address, 0))
        if len(cmd) == 8 and cmd[1:] == bytes(7):
            payload = {0x72: self.serial_number, 0x79: self.release_version,
                       0x7A: self.build_date}.get(cmd[0])
            if payload is None:
                return STALL
            return cmd + struct.pack("<II", payload, 0)
        if len(cmd) == 8 and cmd == bytes([0x00, 0x00, 0x01, 0x00, 0, 0, 0, 0]):
            return cmd + bytes(4)
        if len(cmd) == 12 and cmd[0] in _IDENT_REPLIES and cmd[1:] == bytes([0, 1, 0, 4]) + bytes(7):
            return cmd[:8] + _IDENT_REPLIES[cmd[0]]
        return STALL

    def bulk_in(self, endpoint: int, max_len: int):
        with self.lock:
            if endpoint == R.EP_COMMAND_IN:
                return self._replies.popleft() if self._replies else None
            if endpoint != R.EP_EVENTS:
                return STALL
            if not self._streaming():
                return None
            if len(self._backlog) < max_len:
                self._produce()
            if not self._backlog:
                return None
            out = bytes(self._backlog[:max_len])
            del self._backlog[:max_len]
            self.bytes_streamed += len(out)
            if self.keep_truth:
                self.streamed += out
            self.transfers_streamed += 1
            return out

    # --- event production ---------------------------------------------------------------
    def _now_us(self) -> int:
        if self.realtime:
            return live_sensor_us(self.source, self._t0_ns, self.latency_us)
        return max(self._produced_us, 0) + self.step_us

    def _produce(self) -> None:
        target = self._now_us()
        if target - self._produced_us < (self.min_window_us if self.realtime else 1):
            return
        t1 = target
        self.source.set_thresholds(*self.thresholds())
        ev = np.array(self.source.events_until(1000 * t1), dtype=EVENT_DTYPE)   # (prev, t1]
        ok = (ev["x"] < R.WIDTH) & (ev["y"] < R.HEIGHT)
        if self._roi_on and ev.size:
            xo = self._x_ok[np.minimum(ev["x"], R.WIDTH - 1)]
            yo = self._y_ok[np.minimum(ev["y"], R.HEIGHT - 1)]
            ok &= (xo & yo) if self._roi_window else (xo | yo)
        if not ok.all():
            ev = ev[ok]
        # EVT 3.0 carries whole microseconds
        ev["t"] = (ev["t"] // 1000) * 1000
        tr = self._take_triggers(t1)
        self._produced_us = t1
        if ev.size or tr.size:
            self._backlog += self._encoder.encode(ev, tr)
            if ev.size and self.keep_truth:
                self._emitted.append(ev)
            if tr.size and self.keep_truth:
                self._emitted_tr.append(tr)

    def _take_triggers(self, t1_us: int) -> np.ndarray:
        due = [p for p in self._pending_tr if p[0] <= t1_us]
        if not due:
            return np.empty(0, TRIGGER_DTYPE)
        self._pending_tr = [p for p in self._pending_tr if p[0] > t1_us]
        tr = np.empty(len(due), TRIGGER_DTYPE)
        tr["t"] = [1000 * t for t, _v in due]
        tr["id"] = 0
        tr["value"] = [v for _t, v in due]
        return tr

    def pulse_trigger(self, width_us: int = 100, at_us: int | None = None):
        """A pulse on the trigger input: a rising edge now (or at sensor time ``at_us``)
        and a falling edge ``width_us`` later.  Returns the (rising, falling) sensor times
        in ns, or None when the input is disabled or the sensor is not streaming (a real
        EVK4 drops those edges too)."""
        with self.lock:
            if not self._streaming() or not self.trigger_input_enabled:
                return None
            now = self._produced_us if at_us is None and not self.realtime else (
                (time.monotonic_ns() - self._t0_ns) // 1000 if at_us is None else int(at_us))
            rise = max(int(now), self._produced_us, 0)
            fall = rise + max(1, int(width_us))
            self._pending_tr += [(rise, 1), (fall, 0)]
            self._pending_tr.sort()
            return 1000 * rise, 1000 * fall

    # --- truth --------------------------------------------------------------------------
    def register_writes(self, start: int = 0) -> list[tuple[int, int]]:
        with self.lock:
            return list(self.writes[start:])
