"""Prophesee EVK4 (Sony IMX636, 1280x720, EVT 3.0) over USB, in Python.

Protocol (facts in rig.camera.evk4_registers, with their public sources):

* identity: control IN 0xC0 / 0x72 -> sensor type (0x31 IMX636, 0x35 IMX646); then the
  8-byte bulk request ``72 00*7`` on 0x02, whose reply on 0x82 carries the serial in bytes
  8-11 (u32 LE, printed ``%08X``); ``79 00*7`` gives the firmware release;
* registers: a 20-byte command on 0x02 (12-byte header, address u32 LE, value u32 LE),
  one reply on 0x82 (a read's reply echoes the first 16 bytes, then the value);
* open(): identity, the sensor bring-up (issd stop / destroy / init, filters bypassed, the
  event rate controller initialised and off, trigger input off), then the factory bias
  values are read back (biases are offsets from them, as in OpenEB);
* start(): 32 bulk IN transfers of 128 KiB queued on 0x81 (rig.camera.streaming), then the
  issd start sequence: the time base starts (sensor time 0) and the readout gate
  (RO_CTRL 0x9028) opens; stop() closes the gate and stops the time base;
* events: EVT 3.0 bytes, passed through untouched by ``read_raw()`` (the capture node
  records them as EventPacket ``evt3``), decoded by ``read()`` with the project's streaming
  EVT 3.0 decoder into int64 ns from the sensor's zero (24-bit microsecond wraps unwrapped);
  ``resume_words()`` gives the EVT 3.0 state words a recording cut from the running stream
  begins with (TIME_HIGH from 0 up to the current time, so the wraps before it count, then
  TIME_LOW, ADDR_Y, VECT_BASE_X);
* contrast thresholds: :func:`thresholds_from_biases` is the bias -> threshold model of the
  driver and of its twin (rig.camera.virtual.evk4), ``contrast_thresholds(biases)``.

``settle=False`` skips the bring-up's settling delays (1 s sensor reset, 1.5 s MIPI
start-up): only for emulated cameras, which need none.
"""

from __future__ import annotations

import math
import struct
import threading
import time

import numpy as np

from evdnerf_ros.events.codecs import evt3 as _evt3
from evdnerf_ros.events.codecs import make_decoder, make_encoder

from . import evk4_registers as R
from .biases import BiasRange, check_biases, read_bias_file, write_bias_file
from .device import SAMPLE_EVENT, Device, UsbLink
from .errors import CameraDisconnected, CameraError, CameraProtocolError

__all__ = ["EVK4", "thresholds_from_biases", "BASE_THRESHOLD", "THRESHOLD_E_FOLD"]

#: contrast threshold at the factory bias; each +THRESHOLD_E_FOLD DAC steps of bias_diff_on
#: (bias_diff_off) multiply the ON (OFF) threshold by e
BASE_THRESHOLD = 0.2
THRESHOLD_E_FOLD = 100.0
#: EVT 3.0 word types the resume words use, and the TIME_HIGH step between fillers (a quarter
#: of the 12-bit range: a decoder counts a wrap where TIME_HIGH drops by more than half of it)
_TIME_HIGH, _TIME_LOW, _ADDR_Y, _VECT_BASE_X = 0x8000, 0x6000, 0x0000, 0x3000
_HIGH_FILL = 1024


def thresholds_from_biases(diff_on_offset: int, diff_off_offset: int,
                           base: float = BASE_THRESHOLD) -> tuple[float, float]:
    """(C_on, C_off) contrast thresholds (log intensity) for bias offsets from the factory
    values: a larger bias_diff_on / bias_diff_off makes the pixel less sensitive."""
    return (base * math.exp(diff_on_offset / THRESHOLD_E_FOLD),
            base * math.exp(diff_off_offset / THRESHOLD_E_FOLD))


def evt3_resume_words(time_us: int, y: int, base_x: int, vector_polarity: int) -> bytes:
    """EVT 3.0 words (no event) that bring a decoder starting on them to time ``time_us``
    (unwrapped: TIME_HIGH words from 0 upwards, one each 2**22 us, so it counts every 24-bit
    wrap before), row ``y`` and vector base ``base_x``; a negative value is a state the stream
    had not set yet, and is left unset."""
    if time_us < 0:
        return b""
    high = int(time_us) >> 12
    highs = np.append(np.arange(0, high, _HIGH_FILL, dtype=np.int64), high)
    words = [_TIME_HIGH | (highs & 0xFFF), [_TIME_LOW | (int(time_us) & 0xFFF)]]
    if y >= 0:
        words.append([_ADDR_Y | (int(y) & 0x7FF)])
    if base_x >= 0:
        words.append([_VECT_BASE_X | (int(vector_polarity) & 1) << 11 | (int(base_x) & 0x7FF)])
    return np.concatenate([np.asarray(w, np.int64) for w in words]).astype("<u2").tobytes()


class EVK4(Device):
    """Prophesee EVK4 (IMX636): ``with EVK4() as cam: cam.start(); cam.read(1.0)``."""

    model = "Prophesee EVK4"
    encoding = "evt3"
    width = R.WIDTH
    height = R.HEIGHT
    USB_IDS = R.USB_IDS
    DATA_ENDPOINT = R.EP_EVENTS
    TRANSFERS = R.TRANSFERS
    TRANSFER_SIZE = R.TRANSFER_SIZE
    BIAS_NAMES = tuple(R.BIASES)

    def __init__(self, serial: str | None = None, *, settle: bool = True, **kwargs):
        super().__init__(serial, **kwargs)
        self.settle = bool(settle)
        self.sensor = ""
        self.build_date = 0
        self.factory_biases: dict[str, int] = {}
        self.trigger_input = False
        self._reg_lock = threading.RLock()
        self._decoder = None
        self._time_base_running = False

    # --- low level --------------------------------------------------------------------
    def request(self, command: bytes, *, what: str | None = None, reply_size: int = 1024) -> bytes:
        """Send one command on bulk OUT 0x02 and return the reply read on bulk IN 0x82."""
        link = self._link(what or "request")
        cmd = bytes(command)
        what = what or f"request {cmd.hex(' ')}"
        with self._reg_lock:
            n = link.bulk_write(R.EP_COMMAND_OUT, cmd, what=f"{what} (bulk OUT 0x02)")
            if n != len(cmd):
                raise CameraProtocolError(f"{self.name}: {what}: short write ({n} of {len(cmd)} "
                                          "bytes); check the cable / USB port")
            return link.bulk_read(R.EP_COMMAND_IN, reply_size, what=f"{what} (reply on bulk IN 0x82)")

    def write_register(self, address: int, value: int) -> None:
        what = f"register 0x{address:04X} write 0x{value & 0xFFFFFFFF:08X}"
        cmd = R.write_command(address, value)
        reply = self.request(cmd, what=what)
        if reply[:12] != cmd[:12]:
            raise CameraProtocolError(f"{self.name}: {what}: unexpected reply {reply[:20].hex(' ')}; "
                                      "the firmware does not speak the EVK4 register protocol "
                                      "(update the camera firmware with Prophesee's tools)")

    def read_register(self, address: int) -> int:
        what = f"register 0x{address:04X} read"
        cmd = R.read_command(address)
        reply = self.request(cmd, what=what)
        if len(reply) < R.REG_COMMAND_SIZE:
            raise CameraProtocolError(f"{self.name}: {what}: short reply ({len(reply)} bytes, "
                                      f"want {R.REG_COMMAND_SIZE}); check the firmware version")
        if reply[:16] != cmd[:16]:
            raise CameraProtocolError(f"{self.name}: {what}: the reply does not echo the "
                                      f"command ({reply[:16].hex(' ')}); check the firmware version")
        return struct.unpack_from("<I", reply, 16)[0]

    def write_sequence(self, writes) -> None:
        for w in writes:
            self.write_register(w.address, w.value)
            if self.settle and w.delay_s:
                time.sleep(w.delay_s)

    def _link(self, what: str) -> UsbLink:
        if self.link is None:
            raise CameraError(f"{self.name}: {what} needs an opened camera; call open() first")
        return self.link

    # --- life cycle ---------------------------------------------------------------------
    def _open(self) -> None:
        self.link = UsbLink.open(self.USB_IDS, self.requested_serial, what=self.model)
        t = self.link.control_in(*R.SENSOR_TYPE_REQUEST, what="sensor type (control 0xC0/0x72)")
        if len(t) < 1 or t[0] not in R.SENSOR_TYPES:
            raise CameraProtocolError(
                f"{self.link.name}: sensor type {t.hex() or 'empty'} (control 0xC0/0x72) is not an "
                f"IMX636 / IMX646 ({', '.join(f'0x{k:02x}' for k in R.SENSOR_TYPES)}); this driver "
                "supports the EVK4 only")
        self.sensor = R.SENSOR_TYPES[t[0]]
        self.serial = f"{self._payload(R.REQ_SERIAL, 'serial request 72'):08X}"
        self.firmware_version = self._payload(R.REQ_RELEASE_VERSION, "release version request 79")
        self.build_date = self._payload(R.REQ_BUILD_DATE, "build date request 7a")
        self.write_sequence(R.open_sequence(trigger_in=False))
        self.trigger_input = False
        self._time_base_running = False
        self.factory_biases = {name: self.read_register(spec.address) & 0xFF
                               for name, spec in R.BIASES.items()}

    def _payload(self, command: bytes, what: str) -> int:
        reply = self.request(command, what=what)
        if len(reply) < 12 or reply[:1] != command[:1]:
            raise CameraProtocolError(f"{self.name}: {what}: malformed reply {reply.hex(' ')} "
                                      "(want the request echoed and a 4-byte value); check the "
                                      "firmware version")
        return struct.unpack_from("<I", reply, 8)[0]

    def _close(self) -> None:
        if self.link is None:
            return
        try:
            if self._time_base_running:
                self.write_sequence(R.STOP)
                self._time_base_running = False
            for name, spec in R.BIASES.items():      # leave the sensor as we found it
                if name in self.factory_biases:
                    self.write_register(spec.address, R.bias_register_value(self.factory_biases[name]))
            self.write_sequence(R.DESTROY)
        except CameraDisconnected:
            pass

    def _start_hardware(self) -> None:
        self.write_sequence(R.START)
        self._time_base_running = True

    def _stop_hardware(self) -> None:
        try:
            self.write_sequence(R.STOP)
        finally:
            self._time_base_running = False

    def read_raw(self, timeout_s: float = 1.0):
        """As Device.read_raw; an idle timeout also checks that the camera is still there
        (one register read): libusb only notices an unplug when polling the device node
        fails, so a silent sensor could otherwise hide it.  Then CameraDisconnected, after
        every chunk received before."""
        chunk = super().read_raw(timeout_s)
        if chunk is None and self.link is not None:
            self.read_register(R.RO_CTRL)       # raises CameraDisconnected when gone
        return chunk

    # --- decoding ----------------------------------------------------------------------
    def _reset_decoder(self) -> None:
        self._decoder = make_decoder("evt3", source=f"{self.name} bulk IN 0x81")

    def _sample_words(self) -> bytes:
        return make_encoder("evt3").encode(SAMPLE_EVENT)

    def _decode(self, data: bytes) -> tuple[np.ndarray, np.ndarray]:
        if self._decoder is None:
            self._reset_decoder()
        d = self._decoder.feed(data)
        return d.events, d.triggers

    def _decoder_state(self) -> tuple:
        """(time us unwrapped, row, vector base x, vector polarity); -1: not set yet."""
        if self._decoder is None:
            return (-1, -1, -1, 0)
        st = self._decoder._state
        return (int(st[_evt3._S_TIME]), int(st[_evt3._S_Y]), int(st[_evt3._S_BX]), int(st[_evt3._S_VP]))

    def resume_words(self, chunk) -> bytes:
        return evt3_resume_words(*chunk.decoder_state) if chunk.decoder_state else b""

    # --- contrast thresholds ------------------------------------------------------------
    THRESHOLD_MODEL = "rig.camera.evk4.thresholds_from_biases"

    def contrast_thresholds(self, biases: dict) -> tuple[float, float]:
        """The model's (C_on, C_off) for bias offsets ``biases`` (bias_diff_on, bias_diff_off)."""
        return thresholds_from_biases(int(biases["bias_diff_on"]), int(biases["bias_diff_off"]))

    # --- biases -------------------------------------------------------------------------
    @property
    def biases(self) -> dict[str, int]:
        """Current bias offsets from the factory values, read back from the sensor."""
        self._need_open("biases")
        return {name: (self.read_register(spec.address) & 0xFF) - self.factory_biases[name]
                for name, spec in R.BIASES.items()}

    @property
    def bias_ranges(self):
        """OpenEB's allowed offsets, narrowed to what this sensor's 8-bit registers hold from
        its factory values (factory + offset in 0..255; nothing is clamped on the way)."""
        out = {}
        for name, r in R.BIAS_RANGES.items():
            f = self.factory_biases.get(name)
            lo, hi = (r.lo, r.hi) if f is None else (max(r.lo, -f), min(r.hi, 255 - f))
            out[name] = BiasRange(lo, hi, max(lo, min(r.rec_lo, hi)), min(hi, max(r.rec_hi, lo)))
        return out

    def check_bias_values(self, biases: dict[str, int], *, warn_recommended: bool = True) -> dict[str, int]:
        """Names, integers and ranges (:attr:`bias_ranges`) of a set_biases call, without
        writing; raises BiasFileError naming the bias and its range."""
        self._need_open("set_biases()")
        self.check_bias_names(biases, R.BIASES)
        return check_biases(biases, self.bias_ranges, source=f"{self.name} biases",
                            warn_recommended=warn_recommended)

    def set_biases(self, biases: dict[str, int]) -> None:
        """Set some biases (offsets from the factory values; OpenEB's names and ranges)."""
        values = self.check_bias_values(biases)
        for name, offset in values.items():
            spec = R.BIASES[name]
            self.write_register(spec.address, R.bias_register_value(self.factory_biases[name] + offset))

    def load_bias_file(self, path) -> dict[str, int]:
        """Apply a Prophesee .bias file (lines ``value % name``); returns what it set."""
        values = read_bias_file(path, ranges=R.BIAS_RANGES)
        self.set_biases(values)
        return values

    def save_bias_file(self, path, *, overwrite: bool = False):
        """Write the current biases to a .bias file."""
        return write_bias_file(path, self.biases, overwrite=overwrite,
                               header=f"{self.model} {self.sensor} serial {self.serial}")

    # --- ROI --------------------------------------------------------------------------
    @property
    def roi(self) -> tuple[int, int, int, int] | None:
        """The hardware window (x, y, w, h) read back from the TD_ROI registers; None when
        the whole frame is enabled."""
        self._need_open("roi")
        xs = [self.read_register(R.TD_ROI_X + 4 * k) for k in range(R.TD_ROI_X_COUNT)]
        ys = [self.read_register(R.TD_ROI_Y + 4 * k) for k in range(R.TD_ROI_Y_COUNT)]
        try:
            return R.roi_from_registers(xs, ys)
        except ValueError as exc:
            raise CameraError(f"{self.name}: the sensor's ROI registers hold a mask that is not "
                              f"one window ({exc}); call set_roi() or clear_roi()") from None

    def set_roi(self, x: int, y: int, w: int, h: int) -> None:
        self._need_open("set_roi()")
        x, y, w, h = self.check_roi(x, y, w, h)
        self.write_sequence(R.roi_registers(x, y, w, h))

    def clear_roi(self) -> None:
        self._need_open("clear_roi()")
        self.write_sequence(R.clear_roi_registers())

    # --- trigger input ----------------------------------------------------------------
    def enable_trigger_input(self, enabled: bool = True) -> None:
        """External trigger in: edges arrive as EXT_TRIGGER words (read() -> triggers)."""
        self._need_open("enable_trigger_input()")
        self.write_register(R.EDF_RESERVED_7004, R.edf_7004(bool(enabled)))
        self.trigger_input = bool(enabled)

    @property
    def trigger_input_enabled(self) -> bool:
        return self.trigger_input
