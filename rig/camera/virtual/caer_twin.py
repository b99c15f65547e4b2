"""What the libcaer-protocol twins (``VirtualDVXplorer``, ``VirtualDAVIS346``) share.

Both cameras speak libcaer's USB protocol: vendor request 0xBF writes (OUT) or reads (IN) one
4-byte big-endian register (module = wValue, parameter = wIndex), 0xC2 writes wValue records of
{u8 module, u8 parameter, u32 BE}; anything else stalls. Their words stream on one bulk IN
endpoint, paced by sensor time (``realtime``: the wall clock's pace; otherwise ``step_us`` of
sensor time per transfer that finds the FIFO short), and the external-input detector (module 4)
turns ``pulse_trigger()`` into edge words. The module numbers used here are the same in both
cameras' maps (libcaer's common modules).

``CaerTwin`` holds that; a camera's twin adds its register map and identity, ``_write`` (the
side effects of a register), ``_streaming`` and ``_produce_until`` (its words up to a sensor
time, appended to ``_backlog``) and sets ``DATA_ENDPOINT``.
"""

from __future__ import annotations

import struct

import numpy as np

from evdnerf_ros.events.types import EVENT_DTYPE, TRIGGER_DTYPE

from .. import dvxplorer as caer          # libcaer's common module numbers (the same on the DAVIS346)
from ..caer_words import TRIGGER_EDGE, TRIGGER_PULSE
from ..libcaer_device import REQUEST_CONFIG, REQUEST_CONFIG_MULTIPLE
from .scene_source import EmittedTruth, GivenEvents, live_sensor_us
from .usb import STALL, EmulatedUsbDevice

__all__ = ["CaerTwin", "as_source"]


def as_source(source, width: int, height: int):
    """The event source a twin streams: None (nothing), an EVENT_DTYPE array, a scene name /
    YAML path, or an object with ``events_until`` (rig.camera.virtual.scene_source)."""
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


class CaerTwin(EmulatedUsbDevice, EmittedTruth):
    """The libcaer USB protocol, the stream's pacing and the trigger input; see the module docstring."""

    #: the bulk IN endpoint the words stream on (0x81, the interrupt endpoint, stays silent)
    DATA_ENDPOINT: int
    #: at most this many step_us windows per bulk IN transfer when not realtime
    MAX_STEPS_PER_TRANSFER = 64

    def _init_stream(self, source, *, realtime: bool, latency_us: int, step_us: int, min_window_us: int,
                     idle_wraps: bool, max_transfer_bytes: int | None) -> None:
        """The protocol's and the stream's state (after ``self.width`` / ``self.height``)."""
        self.source = as_source(source, self.width, self.height)
        self.realtime = bool(realtime)
        # realtime: stream this far behind the wall clock (a camera's pipeline delay), so
        # that a signal learnt late (the virtual rig's trigger, its joint angles) still
        # lands at its true sensor time
        self.latency_us = int(latency_us)
        self.step_us = int(step_us)
        self.min_window_us = int(min_window_us)
        self.idle_wraps = bool(idle_wraps)
        self.max_transfer_bytes = None if max_transfer_bytes is None else max(2, int(max_transfer_bytes) & ~1)
        self.registers: dict[tuple[int, int], int] = {}
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
        self._thresholds = None

    # --- registers ------------------------------------------------------------------
    def register(self, module: int, param: int) -> int:
        with self.lock:
            return self.registers.get((module, param), 0)

    def _reg(self, module, param):
        return self.registers.get((module, param), 0)

    @property
    def streaming(self) -> bool:
        with self.lock:
            return self._streaming()

    @property
    def trigger_input_enabled(self) -> bool:
        return bool(self.register(caer.EXTINPUT, caer.EXTINPUT_RUN_DETECTOR))

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
        if setup.request == REQUEST_CONFIG:
            if setup.request_type == 0x40 and len(data) == 4:
                self._write(setup.value, setup.index, struct.unpack(">I", data)[0])
                return b""
            if setup.request_type == 0xC0 and setup.length == 4:
                self.reads.append((setup.value, setup.index))
                return struct.pack(">I", self._reg(setup.value, setup.index) & 0xFFFFFFFF)
            return STALL
        if setup.request == REQUEST_CONFIG_MULTIPLE and setup.request_type == 0x40:
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
            if endpoint != self.DATA_ENDPOINT:
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
            return live_sensor_us(self.source, self._t0_ns, self.latency_us)
        return self._produced_us + self.step_us

    def _produce(self, want: int) -> None:
        for _ in range(1 if self.realtime else self.MAX_STEPS_PER_TRANSFER):
            target = self._now_us()
            if target - self._produced_us < (self.min_window_us if self.realtime else 1):
                return
            self._produce_until(target)
            if len(self._backlog) >= want:
                return

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
        the camera is not streaming (a real camera reports nothing then either)."""
        with self.lock:
            if not self._streaming() or not self._reg(caer.EXTINPUT, caer.EXTINPUT_RUN_DETECTOR):
                return None
            if at_us is None:
                now = self._now_us() if self.realtime else self._produced_us + 1
            else:
                now = int(at_us)
            rise = max(int(now), self._produced_us + 1)
            fall = rise + max(1, int(width_us))
            if self._reg(caer.EXTINPUT, caer.EXTINPUT_DETECT_RISING):
                self._pending_tr.append((rise, TRIGGER_EDGE, 1))
            if self._reg(caer.EXTINPUT, caer.EXTINPUT_DETECT_FALLING):
                self._pending_tr.append((fall, TRIGGER_EDGE, 0))
            if self._reg(caer.EXTINPUT, caer.EXTINPUT_DETECT_PULSES):
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
