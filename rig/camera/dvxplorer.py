"""iniVation DVXplorer driver (libcaer's open USB protocol), pure Python on python-libusb1.

Facts from libcaer (``dvxplorer.c``, ``dvxplorer.h``, ``usb_utils.c``, public headers):

* USB 152a:8419, configuration 1, interface 0, events on bulk IN 0x82 (libcaer queues
  8 transfers x 8 KiB, as :class:`DVXplorer` does by default);
* configuration: vendor request 0xBF, wValue = module, wIndex = parameter, 4 bytes big-endian
  (OUT 0x40 writes, IN 0xC0 reads); 0xC2 writes several {u8 module, u8 parameter, u32 BE}
  records at once (wValue = their count);
* versions: firmware = bcdDevice's low byte, logic version = (SYSINFO 6, 0), logic patch =
  (6, 7); libcaer requires logic 18 with patch >= 2 and firmware 8 (neuromorphic-drivers wants
  firmware >= 9 and patch 4: :attr:`DVXplorer.MIN_FIRMWARE_VERSION` accepts both);
* the Samsung sensor's registers (biases, cropper, mode, ...) are module 5 (DEVICE_DVS) with
  the 16-bit register address as the parameter, one byte per register;
* start (``dvXplorerDataStart``): everything off, clear the endpoint halt, queue the transfers,
  then USB run (9,0) = 1, multiplexer timestamp run (0,1) = 1, multiplexer run (0,0) = 1, DVS
  run (1,3) = 1, external input detector (4,0) = 1 when triggers are enabled, and the sensor's
  timestamp reset + stream mode; stop is the reverse.

Events are decoded by :mod:`rig.camera.caer_words` (sensor microseconds unwrapped to int64 ns
from the sensor's zero); external input edges arrive as triggers. ``encoding = "libcaer"``:
:func:`libcaer_packet` turns an EventChunk into the payload of an ``EventPacket`` as
libcaer_driver publishes it (``evdnerf_ros.events.codecs`` "libcaer" records).
"""

from __future__ import annotations

import time

import numpy as np

from evdnerf_ros.events.codecs import encode as encode_events
from evdnerf_ros.events.types import EVENT_DTYPE

from .caer_words import CaerWordDecoder, CaerWordEncoder
from .device import SAMPLE_EVENT, EventChunk, UsbLink
from .errors import CameraError, CameraProtocolError
from .libcaer_device import LibcaerDevice

__all__ = ["DVXplorer", "BIASES", "BIAS_PRESETS", "libcaer_packet", "thresholds_from_biases", "BASE_THRESHOLD"]

#: contrast threshold (log intensity) at the middle bias current 4; the ON threshold doubles
#: every 4 steps of current_on up, the OFF threshold every 4 steps of current_off down (so
#: libcaer's default on=0 / off=8 gives 0.2 / 0.2, its presets symmetric pairs)
BASE_THRESHOLD = 0.4


def thresholds_from_biases(current_on: int, current_off: int, base: float = BASE_THRESHOLD):
    """(C_on, C_off) for the sensor's BIAS_CURRENT_ON / BIAS_CURRENT_OFF values: the bias ->
    threshold model of the driver and of its twin (rig.camera.virtual.dvxplorer)."""
    return (base * 2.0 ** ((int(current_on) - 4) / 4.0), base * 2.0 ** ((4 - int(current_off)) / 4.0))

VID, PID = 0x152A, 0x8419

# modules and parameters (libcaer include/libcaer/devices/dvxplorer.h)
MUX, DVS, IMU, EXTINPUT, DEVICE_DVS, SYSINFO, USB = 0, 1, 3, 4, 5, 6, 9
MUX_RUN, MUX_TIMESTAMP_RUN, MUX_TIMESTAMP_RESET, MUX_RUN_CHIP = 0, 1, 2, 3
MUX_DROP_EXTINPUT_ON_STALL, MUX_DROP_DVS_ON_STALL = 4, 5
DVS_SIZE_COLUMNS, DVS_SIZE_ROWS, DVS_ORIENTATION_INFO, DVS_RUN = 0, 1, 2, 3
IMU_RUN_ACCELEROMETER, IMU_RUN_GYROSCOPE, IMU_RUN_TEMPERATURE = 2, 3, 4
EXTINPUT_RUN_DETECTOR, EXTINPUT_DETECT_RISING, EXTINPUT_DETECT_FALLING = 0, 1, 2
EXTINPUT_DETECT_PULSES, EXTINPUT_DETECT_PULSE_POLARITY, EXTINPUT_DETECT_PULSE_LENGTH = 3, 4, 5
SYSINFO_LOGIC_VERSION, SYSINFO_CHIP_IDENTIFIER, SYSINFO_DEVICE_IS_MASTER = 0, 1, 2
SYSINFO_LOGIC_CLOCK, SYSINFO_USB_CLOCK, SYSINFO_CLOCK_DEVIATION, SYSINFO_LOGIC_PATCH = 3, 5, 6, 7
USB_RUN = 0

# Samsung sensor registers (libcaer src/dvxplorer.h), module DEVICE_DVS
REG_BIAS_CURRENT_RANGE_SELECT_LOGSFONREST = 0x000B
REG_BIAS_CURRENT_RANGE_SELECT_LOGALOGD_MONITOR = 0x000C
REG_BIAS_OTP_TRIM = 0x000D
REG_BIAS_PINS_DBGP = 0x000F
REG_BIAS_PINS_DBGN = 0x0010
REG_BIAS_CURRENT_LEVEL_SFOFF = 0x0012
REG_BIAS_PINS_BUFP = 0x0013
REG_BIAS_PINS_BUFN = 0x0014
REG_BIAS_PINS_DOB = 0x0015
REG_BIAS_CURRENT_AMP = 0x0018
REG_BIAS_CURRENT_ON = 0x001C
REG_BIAS_CURRENT_OFF = 0x001E
REG_CONTROL_MODE = 0x3000
REG_CONTROL_CLOCK_DIVIDER_SYS = 0x3011
REG_CONTROL_PARALLEL_OUT_CONTROL = 0x3019
REG_CONTROL_PARALLEL_OUT_ENABLE = 0x301E
REG_CONTROL_PACKET_FORMAT = 0x3067
REG_DIGITAL_RESTART = 0x3201
REG_DIGITAL_TIMESTAMP_SUBUNIT = 0x3234
REG_DIGITAL_TIMESTAMP_RESET = 0x3238
REG_TIMING_GH_COUNT_FINE = 0x3243
REG_TIMING_GRS_COUNT_FINE = 0x3247
REG_DIGITAL_MODE_CONTROL = 0x3255
REG_TIMING_GRS_END_FINE = 0x3259
REG_DIGITAL_EXTERNAL_TRIGGER = 0x3260
REG_DIGITAL_BOOT_SEQUENCE = 0x3266
REG_CROPPER_BYPASS = 0x3300
REG_CROPPER_Y_START_GROUP = 0x3301
REG_CROPPER_Y_START_MASK = 0x3302
REG_CROPPER_Y_END_GROUP = 0x3303
REG_CROPPER_Y_END_MASK = 0x3304
REG_CROPPER_X_START_ADDRESS = 0x3305     # 2 registers, high byte first
REG_CROPPER_X_END_ADDRESS = 0x3307       # 2 registers, high byte first
REG_ACTIVITY_DECISION_BYPASS = 0x3500
REG_SPATIAL_HISTOGRAM_OFF = 0x3600

CHIP_MODE_OFF, CHIP_MODE_STREAM = 0, 2

#: The sensor's bias parameters by libcaer's DVX_DVS_CHIP_BIAS names (lower case):
#: name -> (register, bit mask, shift, largest value). Values are what libcaer's
#: dvXplorerConfigSet takes; bits of shared registers are read-modify-written as libcaer does.
BIASES = {
    "current_range_log": (REG_BIAS_CURRENT_RANGE_SELECT_LOGSFONREST, 0x08, 3, 1),
    "current_range_sf": (REG_BIAS_CURRENT_RANGE_SELECT_LOGSFONREST, 0x04, 2, 1),
    "current_range_on": (REG_BIAS_CURRENT_RANGE_SELECT_LOGSFONREST, 0x02, 1, 1),
    "current_range_nrst": (REG_BIAS_CURRENT_RANGE_SELECT_LOGSFONREST, 0x01, 0, 1),
    "current_range_loga": (REG_BIAS_CURRENT_RANGE_SELECT_LOGALOGD_MONITOR, 0x10, 4, 1),
    "current_range_logd": (REG_BIAS_CURRENT_RANGE_SELECT_LOGALOGD_MONITOR, 0x0C, 2, 3),
    "current_level_sf": (REG_BIAS_CURRENT_LEVEL_SFOFF, 0x10, 4, 1),
    "current_level_noff": (REG_BIAS_CURRENT_LEVEL_SFOFF, 0x02, 1, 1),
    "current_amp": (REG_BIAS_CURRENT_AMP, 0xFF, 0, 8),
    "current_on": (REG_BIAS_CURRENT_ON, 0xFF, 0, 8),
    "current_off": (REG_BIAS_CURRENT_OFF, 0xFF, 0, 8),
}

#: libcaer's DVX_DVS_CHIP_BIAS_SIMPLE presets: the register values each one writes, in order.
BIAS_PRESETS = {
    "very_low": ((REG_BIAS_CURRENT_RANGE_SELECT_LOGSFONREST, 0x06), (REG_BIAS_CURRENT_LEVEL_SFOFF, 0x7D),
                 (REG_BIAS_CURRENT_ON, 0x06), (REG_BIAS_CURRENT_OFF, 0x02)),
    "low": ((REG_BIAS_CURRENT_RANGE_SELECT_LOGSFONREST, 0x06), (REG_BIAS_CURRENT_LEVEL_SFOFF, 0x7D),
            (REG_BIAS_CURRENT_ON, 0x03), (REG_BIAS_CURRENT_OFF, 0x05)),
    "default": ((REG_BIAS_CURRENT_RANGE_SELECT_LOGSFONREST, 0x06), (REG_BIAS_CURRENT_LEVEL_SFOFF, 0x7D),
                (REG_BIAS_CURRENT_ON, 0x00), (REG_BIAS_CURRENT_OFF, 0x08)),
    "high": ((REG_BIAS_CURRENT_RANGE_SELECT_LOGSFONREST, 0x04), (REG_BIAS_CURRENT_LEVEL_SFOFF, 0x7F),
             (REG_BIAS_CURRENT_ON, 0x05), (REG_BIAS_CURRENT_OFF, 0x03)),
    "very_high": ((REG_BIAS_CURRENT_RANGE_SELECT_LOGSFONREST, 0x04), (REG_BIAS_CURRENT_LEVEL_SFOFF, 0x7F),
                  (REG_BIAS_CURRENT_ON, 0x02), (REG_BIAS_CURRENT_OFF, 0x06)),
}

#: The sensor bring-up libcaer's dvXplorerOpen writes after taking the chip out of reset.
CHIP_INIT = (
    (REG_BIAS_OTP_TRIM, 0x24), (REG_BIAS_PINS_DBGP, 0x07), (REG_BIAS_PINS_DBGN, 0xFF),
    (REG_BIAS_PINS_BUFP, 0x03), (REG_BIAS_PINS_BUFN, 0x7F), (REG_BIAS_PINS_DOB, 0x00),
    (REG_BIAS_CURRENT_AMP, 0x04), (REG_BIAS_CURRENT_RANGE_SELECT_LOGALOGD_MONITOR, 0x14),
) + BIAS_PRESETS["default"] + (
    (REG_CONTROL_CLOCK_DIVIDER_SYS, 0xA0), (REG_CONTROL_PARALLEL_OUT_CONTROL, 0x00),
    (REG_CONTROL_PARALLEL_OUT_ENABLE, 0x01), (REG_CONTROL_PACKET_FORMAT, 0x80),
    (REG_DIGITAL_TIMESTAMP_SUBUNIT, 0x31), (REG_DIGITAL_MODE_CONTROL, 0x0C),
    (REG_DIGITAL_BOOT_SEQUENCE, 0x08), (REG_TIMING_GH_COUNT_FINE, 50), (REG_TIMING_GRS_COUNT_FINE, 50),
    (REG_TIMING_GRS_END_FINE, 50), (REG_SPATIAL_HISTOGRAM_OFF, 0x01),
    (REG_DIGITAL_EXTERNAL_TRIGGER, 0x00),                    # external trigger mode: timestamp reset
    (REG_CROPPER_BYPASS, 0x01), (REG_ACTIVITY_DECISION_BYPASS, 0x01),
    (REG_DIGITAL_RESTART, 0x02),                             # DTAG restart after config
)


class DVXplorer(LibcaerDevice):
    """An iniVation DVXplorer (module doc). ``DVXplorer(serial=None)``: the first one found,
    or the one with that USB serial string."""

    model = "DVXplorer"
    encoding = "libcaer"
    width = 640
    height = 480
    USB_IDS = ((VID, PID),)
    DATA_ENDPOINT = 0x82
    TRANSFERS = 8
    TRANSFER_SIZE = 8192

    #: firmware (bcdDevice low byte) at least this: libcaer's 8 (neuromorphic-drivers needs 9)
    MIN_FIRMWARE_VERSION = 8
    #: FPGA logic version exactly this (libcaer DVXPLORER_REQUIRED_LOGIC_VERSION)
    REQUIRED_LOGIC_VERSION = 18
    #: FPGA logic patch level at least this (libcaer DVXPLORER_REQUIRED_LOGIC_PATCH_LEVEL)
    MIN_LOGIC_PATCH = 2
    #: libcaer waits 10 ms after "everything off" and 50 ms after the multiplexer starts
    CLEAR_SLEEP_S = 0.010
    START_SETTLE_S = 0.050
    PARAM_FORMAT = "0x{:04x}"          # module 5's parameters are the sensor's 16-bit register addresses

    def __init__(self, serial: str | None = None, **kw):
        super().__init__(serial, **kw)
        self.logic_patch: int | None = None
        self.chip_id: int | None = None
        self.invert_xy = False
        self.logic_clock_mhz = 0.0
        self._trigger_input = False
        self._decoder: CaerWordDecoder | None = None

    # ------------------------------------------------------------------ sensor registers (module 5)
    def register_write(self, register: int, value: int) -> None:
        self.config_write(DEVICE_DVS, register, value & 0xFF)

    def register_read(self, register: int) -> int:
        return self.config_read(DEVICE_DVS, register) & 0xFF

    # ------------------------------------------------------------------ life cycle
    def _open(self) -> None:
        self.link = UsbLink.open(self.USB_IDS, self.requested_serial, what=self.model)
        try:
            self.serial = self.link.handle.getSerialNumber() or ""
        except Exception:     # noqa: BLE001 - a missing serial string is not fatal
            self.serial = ""
        bcd = self.link.bcd_device
        self.firmware_version = bcd & 0xFF
        if self.firmware_version < self.MIN_FIRMWARE_VERSION:
            raise CameraProtocolError(
                f"{self.name}: firmware version {self.firmware_version} (bcdDevice 0x{bcd:04x}) is older than "
                f"{self.MIN_FIRMWARE_VERSION}, the oldest this driver (and libcaer) supports; update the firmware "
                "with iniVation's DV flashy tool")
        self.logic_version = self.config_read(SYSINFO, SYSINFO_LOGIC_VERSION)
        if self.logic_version != self.REQUIRED_LOGIC_VERSION:
            raise CameraProtocolError(
                f"{self.name}: FPGA logic version {self.logic_version} (config module 6 parameter 0) is not "
                f"{self.REQUIRED_LOGIC_VERSION}, the one libcaer's protocol needs; flash the matching logic with "
                "iniVation's DV flashy tool")
        self.logic_patch = self.config_read(SYSINFO, SYSINFO_LOGIC_PATCH)
        if self.logic_patch < self.MIN_LOGIC_PATCH:
            raise CameraProtocolError(
                f"{self.name}: FPGA logic patch level {self.logic_patch} (config module 6 parameter 7) is below "
                f"{self.MIN_LOGIC_PATCH}; update the logic with iniVation's DV flashy tool")
        self.chip_id = self.config_read(SYSINFO, SYSINFO_CHIP_IDENTIFIER)
        cols = self.config_read(DVS, DVS_SIZE_COLUMNS)
        rows = self.config_read(DVS, DVS_SIZE_ROWS)
        orient = self.config_read(DVS, DVS_ORIENTATION_INFO)
        if not (0 < cols <= 1024 and 0 < rows <= 512):
            raise CameraProtocolError(f"{self.name}: the sensor reports {cols}x{rows} pixels (config module 1 "
                                      "parameters 0 / 1), which the DVXplorer words cannot address")
        self.invert_xy = bool(orient & 0x04)
        self.width, self.height = (rows, cols) if self.invert_xy else (cols, rows)
        logic_clock = self.config_read(SYSINFO, SYSINFO_LOGIC_CLOCK)
        deviation = self.config_read(SYSINFO, SYSINFO_CLOCK_DEVIATION)
        self.logic_clock_mhz = logic_clock * deviation / 1000.0
        # everything off, then the sensor out of reset and libcaer's bring-up
        self._all_off()
        self.config_write(MUX, MUX_RUN_CHIP, 1)
        time.sleep(0.010)
        for reg, val in CHIP_INIT:
            self.register_write(reg, val)
        self.config_write(MUX, MUX_DROP_EXTINPUT_ON_STALL, 1)
        self.config_write(MUX, MUX_DROP_DVS_ON_STALL, 0)
        self._configure_trigger_detector(False)

    def _close(self) -> None:
        if self.link is not None:
            try:
                self.config_write(MUX, MUX_RUN_CHIP, 0)          # sensor back in reset, as libcaer closes
            except CameraError:
                pass

    def _all_off(self) -> None:
        """libcaer's 'ensure it is shut down completely' sequence of dvXplorerDataStart."""
        self.config_write(DVS, DVS_RUN, 0)
        self.config_write(IMU, IMU_RUN_ACCELEROMETER, 0)
        self.config_write(IMU, IMU_RUN_GYROSCOPE, 0)
        self.config_write(IMU, IMU_RUN_TEMPERATURE, 0)
        self.config_write(EXTINPUT, EXTINPUT_RUN_DETECTOR, 0)
        self.config_write(MUX, MUX_RUN, 0)
        self.config_write(MUX, MUX_TIMESTAMP_RUN, 0)
        self.config_write(USB, USB_RUN, 0)

    def start(self) -> None:
        """Everything off, clear the data endpoint, queue the transfers, then the run bits in
        libcaer's order (module doc)."""
        self._need_open("start()")
        if self.is_streaming:
            return
        self._all_off()
        time.sleep(self.CLEAR_SLEEP_S)
        try:
            self.link.handle.clearHalt(self.DATA_ENDPOINT)
        except Exception as exc:      # noqa: BLE001
            raise self.link._error(exc, f"clear halt on 0x{self.DATA_ENDPOINT:02x}") from None
        super().start()              # queues the transfers, then _start_hardware()

    def _start_hardware(self) -> None:
        self.config_write(USB, USB_RUN, 1)
        self.config_write(MUX, MUX_TIMESTAMP_RUN, 1)
        self.config_write(MUX, MUX_RUN, 1)
        time.sleep(self.START_SETTLE_S)
        self.config_write(DVS, DVS_RUN, 1)
        if self._trigger_input:
            self.config_write(EXTINPUT, EXTINPUT_RUN_DETECTOR, 1)
        self.register_write(REG_DIGITAL_TIMESTAMP_RESET, 1)
        self.register_write(REG_DIGITAL_TIMESTAMP_RESET, 0)
        self.register_write(REG_CONTROL_MODE, CHIP_MODE_STREAM)

    def _stop_hardware(self) -> None:
        self.register_write(REG_CONTROL_MODE, CHIP_MODE_OFF)
        self.config_write(DVS, DVS_RUN, 0)
        self.config_write(EXTINPUT, EXTINPUT_RUN_DETECTOR, 0)
        self.config_write(MUX, MUX_RUN, 0)
        self.config_write(MUX, MUX_TIMESTAMP_RUN, 0)
        self.config_write(USB, USB_RUN, 0)

    def reset_timestamps(self) -> None:
        """Reset the sensor clock to zero (libcaer's DVX_MUX_TIMESTAMP_RESET: a 0xC2 batch of
        1 then 0). The stream then carries a timestamp-reset word; later times restart at 0."""
        self._need_open("reset_timestamps()")
        self.config_write_many([(MUX, MUX_TIMESTAMP_RESET, 1), (MUX, MUX_TIMESTAMP_RESET, 0)])

    def read_raw(self, timeout_s: float = 1.0):
        """As Device.read_raw; an idle timeout is confirmed with one config read first: a
        streaming DVXplorer sends a timestamp-wrap word at least every 32.8 ms, so silence
        may be an unplug that libusb did not report (it only notices one when polling the
        device node fails): then CameraDisconnected, after every chunk received before."""
        chunk = super().read_raw(timeout_s)
        if chunk is None and self.link is not None:
            self.config_read(SYSINFO, SYSINFO_LOGIC_VERSION)   # raises CameraDisconnected when gone
        return chunk

    # ------------------------------------------------------------------ decoding
    def _reset_decoder(self) -> None:
        self._decoder = CaerWordDecoder(self.width, self.height, "DVXplorer", invert_xy=self.invert_xy)

    def _decode(self, data: bytes):
        return self._decoder.feed(data)

    def _sample_words(self) -> bytes:
        return CaerWordEncoder(self.width, self.height, "DVXplorer").encode(SAMPLE_EVENT)

    def warm_up(self) -> None:
        super().warm_up()
        libcaer_packet(SAMPLE_EVENT, 0)      # the recorder's packet encoder loads its kernel too

    @property
    def decoder(self) -> CaerWordDecoder | None:
        """The stream's word decoder (its counters: resets, bad_addresses, imu_words, ...)."""
        return self._decoder

    # ------------------------------------------------------------------ biases
    THRESHOLD_MODEL = "rig.camera.dvxplorer.thresholds_from_biases"

    def contrast_thresholds(self, biases: dict) -> tuple[float, float]:
        """The model's (C_on, C_off) for ``biases`` (current_on, current_off)."""
        return thresholds_from_biases(int(biases["current_on"]), int(biases["current_off"]))

    @property
    def biases(self) -> dict[str, int]:
        """The sensor's bias parameters (libcaer names, module doc), read from its registers."""
        self._need_open("biases")
        regs = {}
        out = {}
        for name, (reg, mask, shift, _top) in BIASES.items():
            if reg not in regs:
                regs[reg] = self.register_read(reg)
            out[name] = (regs[reg] & mask) >> shift
        return out

    def set_biases(self, biases: dict[str, int]) -> None:
        """Write bias parameters by name (read-modify-write of shared registers, as libcaer)."""
        self._need_open("set_biases()")
        self.check_bias_names(biases, BIASES)
        for name, value in biases.items():
            reg, mask, shift, top = BIASES[name]
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or not 0 <= int(value) <= top:
                raise CameraError(f"{self.name}: bias {name} = {value!r} is out of range; use an integer "
                                  f"0..{top}")
        for name, value in biases.items():
            reg, mask, shift, _top = BIASES[name]
            if mask == 0xFF:
                self.register_write(reg, int(value))
            else:
                cur = self.register_read(reg)
                self.register_write(reg, (cur & ~mask & 0xFF) | ((int(value) << shift) & mask))

    def set_bias_preset(self, preset: str) -> None:
        """libcaer's DVX_DVS_CHIP_BIAS_SIMPLE: one of very_low, low, default, high, very_high."""
        self._need_open("set_bias_preset()")
        if preset not in BIAS_PRESETS:
            raise CameraError(f"{self.name}: unknown bias preset {preset!r}; valid presets: "
                              f"{', '.join(BIAS_PRESETS)}")
        self.register_write(REG_BIAS_CURRENT_AMP, 0x04)
        self.register_write(REG_BIAS_CURRENT_RANGE_SELECT_LOGALOGD_MONITOR, 0x14)
        for reg, val in BIAS_PRESETS[preset]:
            self.register_write(reg, val)

    # ------------------------------------------------------------------ ROI (the sensor's cropper)
    def set_roi(self, x: int, y: int, w: int, h: int) -> None:
        """Crop to x..x+w-1, y..y+h-1 (output coordinates) with the sensor's cropper registers,
        including libcaer's corner case (start and end rows in one 8-row group)."""
        self._need_open("set_roi()")
        x, y, w, h = self.check_roi(x, y, w, h)
        if self.invert_xy:
            x, y, w, h = y, x, h, w
        x0, x1, y0, y1 = x, x + w - 1, y, y + h - 1
        start_group, start_mask = y0 // 8, (0xFF << (y0 % 8)) & 0xFF
        end_group, end_mask = y1 // 8, 0xFF >> (7 - y1 % 8)
        if start_group == end_group:
            end_mask &= start_mask
            start_mask = 0xFF
        for reg, val in ((REG_CROPPER_X_START_ADDRESS, x0 >> 8), (REG_CROPPER_X_START_ADDRESS + 1, x0 & 0xFF),
                         (REG_CROPPER_X_END_ADDRESS, x1 >> 8), (REG_CROPPER_X_END_ADDRESS + 1, x1 & 0xFF),
                         (REG_CROPPER_Y_START_GROUP, start_group), (REG_CROPPER_Y_START_MASK, start_mask),
                         (REG_CROPPER_Y_END_GROUP, end_group), (REG_CROPPER_Y_END_MASK, end_mask),
                         (REG_CROPPER_BYPASS, 0)):
            self.register_write(reg, val)

    def clear_roi(self) -> None:
        self._need_open("clear_roi()")
        self.register_write(REG_CROPPER_BYPASS, 1)

    @property
    def roi(self) -> tuple[int, int, int, int] | None:
        """(x, y, w, h) read back from the cropper registers; None when the cropper is bypassed."""
        self._need_open("roi")
        if self.register_read(REG_CROPPER_BYPASS):
            return None
        r = self.register_read
        x0 = (r(REG_CROPPER_X_START_ADDRESS) << 8) | r(REG_CROPPER_X_START_ADDRESS + 1)
        x1 = (r(REG_CROPPER_X_END_ADDRESS) << 8) | r(REG_CROPPER_X_END_ADDRESS + 1)
        sg, sm = r(REG_CROPPER_Y_START_GROUP), r(REG_CROPPER_Y_START_MASK)
        eg, em = r(REG_CROPPER_Y_END_GROUP), r(REG_CROPPER_Y_END_MASK)
        if not em or not sm:
            raise CameraProtocolError(f"{self.name}: cropper row masks are empty (start 0x{sm:02x}, end "
                                      f"0x{em:02x}); set the ROI again")
        lowest = (em if sg == eg else sm) & -(em if sg == eg else sm)
        y0 = sg * 8 + lowest.bit_length() - 1
        y1 = eg * 8 + em.bit_length() - 1
        x, y, w, h = x0, y0, x1 - x0 + 1, y1 - y0 + 1
        if self.invert_xy:
            x, y, w, h = y, x, h, w
        return (x, y, w, h)

    # ------------------------------------------------------------------ triggers
    def _configure_trigger_detector(self, enabled: bool) -> None:
        self.config_write(EXTINPUT, EXTINPUT_DETECT_RISING, int(enabled))
        self.config_write(EXTINPUT, EXTINPUT_DETECT_FALLING, int(enabled))
        self.config_write(EXTINPUT, EXTINPUT_DETECT_PULSES, 0)

    def enable_trigger_input(self, enabled: bool = True) -> None:
        """Report rising and falling edges on the sync connector's input as triggers (id 0,
        value 1 rising / 0 falling); takes effect at once when streaming."""
        self._need_open("enable_trigger_input()")
        enabled = bool(enabled)
        self._configure_trigger_detector(enabled)
        self._trigger_input = enabled
        if self.is_streaming:
            self.config_write(EXTINPUT, EXTINPUT_RUN_DETECTOR, int(enabled))

    @property
    def trigger_input_enabled(self) -> bool:
        return self._trigger_input

    # ------------------------------------------------------------------ recording
    def libcaer_packet(self, chunk: EventChunk, sensor_zero_host_ns: int | None = None):
        """(stamp_ns, time_base_ns, payload) of the ``libcaer`` EventPacket for ``chunk``, as
        libcaer_driver publishes it; the host time of the sensor's zero comes from ``clock``
        unless given (time.monotonic_ns scale; pass a wall-clock one for bag stamps)."""
        if sensor_zero_host_ns is None:
            sensor_zero_host_ns = int(self.clock.sensor_ns_to_host_ns(0))
        return libcaer_packet(chunk.events, sensor_zero_host_ns)


_LOW31 = (1 << 31) - 1


def libcaer_packet(events, sensor_zero_host_ns: int):
    """(stamp_ns, time_base_ns, payload) of one ``libcaer`` EventPacket holding ``events``
    (EVENT_DTYPE, sensor ns from the sensor's zero, whole microseconds, sorted): libcaer_driver's
    convention, ``time_base`` = host time of the sensor's zero + the high bits (above 31) of the
    first event's microseconds, each record's 31-bit timestamp the low bits; the stamp is the
    host time of the first event. Empty events give (sensor_zero_host_ns, sensor_zero_host_ns, b"")."""
    ev = np.asarray(events)
    if ev.dtype != EVENT_DTYPE:
        raise CameraError(f"libcaer_packet: events must be EVENT_DTYPE, got {ev.dtype}")
    zero = int(sensor_zero_host_ns)
    if zero < 0:
        raise CameraError(f"libcaer_packet: the sensor's zero maps to host time {zero} < 0; EventPacket times "
                          "are unsigned: pass a clock whose zero is earlier")
    if ev.size == 0:
        return zero, zero, b""
    first_us = int(ev["t"][0]) // 1000
    time_base = zero + 1000 * (first_us & ~_LOW31)
    host = ev.copy()
    host["t"] += zero
    return int(host["t"][0]), time_base, encode_events(host, "libcaer", time_base_ns=time_base)
