"""iniVation DAVIS346 driver (libcaer's open USB protocol, DAVIS FX3), pure Python on python-libusb1.

Facts from libcaer (``davis.c``, ``davis_common.h``, ``devices/davis.h``, ``biases``) and
neuromorphic-drivers (``devices/inivation_davis346.rs``):

* USB 152a:841a (DAVIS FX3), configuration 1, interface 0, events on bulk IN 0x82 (libcaer
  queues 8 transfers x 8 KiB, the default here; neuromorphic-drivers 32 x 128 KiB);
* configuration: vendor request 0xBF, wValue = module, wIndex = parameter, 4 bytes big-endian
  (OUT 0x40 writes, IN 0xC0 reads); 0xC2 writes several {u8 module, u8 parameter, u32 BE};
* modules: 0 multiplexer, 1 DVS, 2 APS, 3 IMU, 4 external input, 5 biases (parameters < 128)
  and chip configuration (>= 128), 6 system information, 9 USB;
* versions: firmware = bcdDevice's low byte (>= 6: neuromorphic-drivers' check; older libcaer
  releases accepted 3-5), FPGA logic version (6,0) = 18, logic patch (6,7) >= 1
  (neuromorphic-drivers wants exactly 1); the chip identifier (6,1) is 4 / 5 / 9 for the
  DAVIS346 A / B / C;
* open: everything off, libcaer's default chip configuration (biases: coarse-fine words
  ``enabled | sexN << 1 | typeNormal << 2 | currentLevelNormal << 3 | fine << 4 | coarse << 12``,
  VDACs ``voltage | current << 6``, shifted sources ``ref << 4 | reg << 10``; then the chip
  switches) and FPGA configuration (filters, APS window / exposure 4 ms / interval 40 ms in ADC
  clock cycles, external input, USB early packet delay 1 ms in USB clock cycles);
* start (``davisDataStart``): everything off, 10 ms, clear the endpoint halt, queue the
  transfers, chip run (0,3) = 1, 200 ms for the biases, USB run (9,0), multiplexer timestamp
  run (0,1), multiplexer run (0,0), 50 ms, DVS run (1,3), APS run (2,4) when frames are wanted,
  external input detector (4,0) when triggers are enabled; stop is the reverse, chip run last;
* DVS region of interest: the ROI filter (1,41..44: start column, start row, end column, end
  row, inclusive, in sensor coordinates) where the logic has one (1,40).

Events are decoded by :mod:`rig.camera.davis_words` (sensor microseconds unwrapped to int64 ns
from the sensor's zero; external input edges as triggers; APS frames with ``aps=True``).
``encoding = "libcaer"``: :meth:`DAVIS346.libcaer_packet` as for the DVXplorer.
"""

from __future__ import annotations

import math
import time

import numpy as np

from .davis_words import DavisWordDecoder, DavisWordEncoder
from .device import SAMPLE_EVENT, EventChunk, UsbLink
from .dvxplorer import libcaer_packet
from .errors import CameraError, CameraProtocolError
from .libcaer_device import LibcaerDevice

__all__ = ["DAVIS346", "BIASES", "DEFAULT_BIASES", "bias_current_pa", "coarse_fine_word", "thresholds_from_bias_words",
           "thresholds_from_biases"]

VID, PID = 0x152A, 0x841A

# modules and parameters (libcaer include/libcaer/devices/davis.h)
MUX, DVS, APS, IMU, EXTINPUT, BIAS, SYSINFO, USB = 0, 1, 2, 3, 4, 5, 6, 9
CHIP = BIAS                          # chip configuration: module 5, parameters >= 128
MUX_RUN, MUX_TIMESTAMP_RUN, MUX_TIMESTAMP_RESET, MUX_RUN_CHIP = 0, 1, 2, 3
MUX_DROP_EXTINPUT_ON_STALL, MUX_DROP_DVS_ON_STALL = 4, 5
DVS_SIZE_COLUMNS, DVS_SIZE_ROWS, DVS_ORIENTATION_INFO, DVS_RUN = 0, 1, 2, 3
DVS_WAIT_ON_STALL, DVS_EXTERNAL_AER_CONTROL, DVS_HAS_PIXEL_FILTER = 4, 5, 10
DVS_FILTER_PIXEL_0_ROW = 11          # rows at 11 + 2 i, columns at 12 + 2 i (i < 8)
DVS_HAS_BACKGROUND_ACTIVITY_FILTER, DVS_FILTER_BACKGROUND_ACTIVITY = 30, 31
DVS_FILTER_BACKGROUND_ACTIVITY_TIME, DVS_FILTER_REFRACTORY_PERIOD, DVS_FILTER_REFRACTORY_PERIOD_TIME = 32, 33, 34
DVS_HAS_ROI_FILTER, DVS_ROI_START_COLUMN, DVS_ROI_START_ROW, DVS_ROI_END_COLUMN, DVS_ROI_END_ROW = 40, 41, 42, 43, 44
DVS_HAS_SKIP_FILTER, DVS_FILTER_SKIP_EVENTS, DVS_FILTER_SKIP_EVENTS_EVERY = 50, 51, 52
DVS_HAS_POLARITY_FILTER, DVS_POLARITY_FLATTEN, DVS_POLARITY_SUPPRESS, DVS_POLARITY_SUPPRESS_TYPE = 60, 61, 62, 63
APS_SIZE_COLUMNS, APS_SIZE_ROWS, APS_ORIENTATION_INFO, APS_COLOR_FILTER, APS_RUN = 0, 1, 2, 3, 4
APS_WAIT_ON_STALL, APS_HAS_GLOBAL_SHUTTER, APS_GLOBAL_SHUTTER = 5, 6, 7
APS_START_COLUMN_0, APS_START_ROW_0, APS_END_COLUMN_0, APS_END_ROW_0 = 8, 9, 10, 11
APS_EXPOSURE, APS_FRAME_INTERVAL = 12, 13
IMU_TYPE, IMU_ORIENTATION_INFO, IMU_RUN_ACCELEROMETER, IMU_RUN_GYROSCOPE, IMU_RUN_TEMPERATURE = 0, 1, 2, 3, 4
IMU_SAMPLE_RATE_DIVIDER, IMU_ACCEL_DLPF, IMU_ACCEL_FULL_SCALE, IMU_GYRO_DLPF, IMU_GYRO_FULL_SCALE = 5, 6, 7, 9, 10
EXTINPUT_RUN_DETECTOR, EXTINPUT_DETECT_RISING, EXTINPUT_DETECT_FALLING = 0, 1, 2
EXTINPUT_DETECT_PULSES, EXTINPUT_DETECT_PULSE_POLARITY, EXTINPUT_DETECT_PULSE_LENGTH = 3, 4, 5
EXTINPUT_HAS_GENERATOR, EXTINPUT_RUN_GENERATOR = 10, 11
SYSINFO_LOGIC_VERSION, SYSINFO_CHIP_IDENTIFIER, SYSINFO_DEVICE_IS_MASTER = 0, 1, 2
SYSINFO_LOGIC_CLOCK, SYSINFO_ADC_CLOCK, SYSINFO_USB_CLOCK, SYSINFO_CLOCK_DEVIATION, SYSINFO_LOGIC_PATCH = 3, 4, 5, 6, 7
USB_RUN, USB_EARLY_PACKET_DELAY = 0, 1

#: libcaer DAVIS_CHIP_DAVIS346A / B / C
DAVIS346_CHIP_IDS = (4, 5, 9)

# bias generator addresses (libcaer DAVIS346_CONFIG_BIAS_*), module 5
VDAC_BIASES = {"apsoverflowlevel": 0, "apscas": 1, "adcrefhigh": 2, "adcreflow": 3, "adctestvoltage": 4}
COARSE_FINE_BIASES = {
    "localbufbn": 8, "padfollbn": 9, "diffbn": 10, "onbn": 11, "offbn": 12, "pixinvbn": 13, "prbp": 14,
    "prsfbp": 15, "refrbp": 16, "readoutbufbp": 17, "apsrosfbn": 18, "adccompbp": 19, "colsellowbn": 20,
    "dacbufbp": 21, "lcoltimeoutbn": 22, "aepdbn": 23, "aepuxbp": 24, "aepuybp": 25, "ifrefrbn": 26,
    "ifthrbn": 27, "biasbuffer": 34,
}
BIAS_SSP, BIAS_SSN = 35, 36
# chip configuration (module 5, >= 128)
CHIP_DIGITALMUX0, CHIP_ANALOGMUX0, CHIP_BIASMUX0 = 128, 132, 135
CHIP_RESETCALIBNEURON, CHIP_TYPENCALIBNEURON, CHIP_RESETTESTPIXEL = 136, 137, 138
CHIP_AERNAROW, CHIP_USEAOUT, CHIP_GLOBAL_SHUTTER, CHIP_SELECTGRAYCOUNTER, CHIP_TESTADC = 140, 141, 142, 143, 144

#: The bias parameters by name (flat integers, the Device API): name -> (parameter, shift, bits).
#: Coarse-fine biases have ``<name>_coarse`` (0..7) and ``<name>_fine`` (0..255); the VDACs
#: ``<name>_voltage`` (0..63) and ``<name>_current`` (0..7). Names are libcaer's DAVIS346 bias
#: names in lower case (DiffBn -> diffbn, OnBn -> onbn, ...).
BIASES: dict[str, tuple[int, int, int]] = {}
for _n, _p in COARSE_FINE_BIASES.items():
    BIASES[f"{_n}_coarse"] = (_p, 12, 3)
    BIASES[f"{_n}_fine"] = (_p, 4, 8)
for _n, _p in VDAC_BIASES.items():
    BIASES[f"{_n}_voltage"] = (_p, 0, 6)
    BIASES[f"{_n}_current"] = (_p, 6, 3)

# libcaer's CF_N_TYPE / CF_P_TYPE / CF_N_TYPE_OFF: (enabled, sexN, typeNormal, currentLevelNormal)
_N, _P, _N_OFF = (1, 1, 1, 1), (1, 0, 1, 1), (0, 1, 1, 1)

#: libcaer's davisCommonSendDefaultChipConfig for the DAVIS346: name -> (kind, coarse, fine)
DEFAULT_BIASES = {
    "localbufbn": (_N, 5, 164), "padfollbn": (_N_OFF, 7, 215), "diffbn": (_N, 4, 39), "onbn": (_N, 5, 255),
    "offbn": (_N, 4, 1), "pixinvbn": (_N, 5, 129), "prbp": (_P, 2, 58), "prsfbp": (_P, 1, 16),
    "refrbp": (_P, 4, 25), "readoutbufbp": (_P, 6, 20), "apsrosfbn": (_N, 6, 219), "adccompbp": (_P, 5, 20),
    "colsellowbn": (_N, 0, 1), "dacbufbp": (_P, 6, 60), "lcoltimeoutbn": (_N, 5, 49), "aepdbn": (_N, 6, 91),
    "aepuxbp": (_P, 4, 80), "aepuybp": (_P, 7, 152), "ifrefrbn": (_N, 5, 255), "ifthrbn": (_N, 5, 255),
    "biasbuffer": (_N, 5, 254),
}
#: libcaer's VDAC defaults: name -> (voltage, current)
DEFAULT_VDACS = {"apsoverflowlevel": (27, 6), "apscas": (21, 6), "adcrefhigh": (32, 7), "adcreflow": (1, 7),
                 "adctestvoltage": (21, 7)}

#: coarse index -> bias current (pA) at fine 255 (neuromorphic-drivers' table of the bias generator)
COARSE_CURRENT_PA = (11, 94, 756, 6054, 48437, 387500, 3100000, 24800000)


def coarse_fine_word(kind, coarse: int, fine: int) -> int:
    """libcaer's caerBiasCoarseFineGenerate."""
    en, sex_n, typ, level = kind
    return en | sex_n << 1 | typ << 2 | level << 3 | (int(fine) & 0xFF) << 4 | (int(coarse) & 7) << 12


def vdac_word(voltage: int, current: int) -> int:
    """libcaer's caerBiasVDACGenerate."""
    return (int(voltage) & 0x3F) | (int(current) & 7) << 6


def shifted_source_word(ref: int, reg: int) -> int:
    """libcaer's caerBiasShiftedSourceGenerate for operating mode SHIFTED_SOURCE, SPLIT_GATE."""
    return (int(ref) & 0x3F) << 4 | (int(reg) & 0x3F) << 10


def bias_current_pa(word: int) -> float:
    """The current (pA) a coarse-fine bias word asks for: C[coarse] * fine / 255."""
    return COARSE_CURRENT_PA[(int(word) >> 12) & 7] * ((int(word) >> 4) & 0xFF) / 255.0


def default_chip_config() -> list[tuple[int, int]]:
    """(parameter, value) of module 5 in libcaer's davisCommonSendDefaultChipConfig order (DAVIS346)."""
    out = [(VDAC_BIASES[n], vdac_word(*DEFAULT_VDACS[n])) for n in DEFAULT_VDACS]
    out += [(COARSE_FINE_BIASES[n], coarse_fine_word(*v)) for n, v in DEFAULT_BIASES.items()]
    out += [(BIAS_SSP, shifted_source_word(1, 33)), (BIAS_SSN, shifted_source_word(1, 33))]
    out += [(CHIP_DIGITALMUX0 + i, 0) for i in range(4)] + [(CHIP_ANALOGMUX0 + i, 0) for i in range(3)]
    out += [(CHIP_BIASMUX0, 0), (CHIP_RESETCALIBNEURON, 1), (CHIP_TYPENCALIBNEURON, 0), (CHIP_RESETTESTPIXEL, 1),
            (CHIP_AERNAROW, 0), (CHIP_USEAOUT, 0), (CHIP_SELECTGRAYCOUNTER, 1), (CHIP_TESTADC, 0)]
    return out


class DAVIS346(LibcaerDevice):
    """An iniVation DAVIS346 (module doc). ``DAVIS346(serial=None, aps=False)``: the first one found
    (or the one with that USB serial); with ``aps=True`` the APS runs while streaming and
    :meth:`read_frames` hands out the decoded frames."""

    model = "DAVIS346"
    encoding = "libcaer"
    width = 346
    height = 260
    USB_IDS = ((VID, PID),)
    DATA_ENDPOINT = 0x82
    TRANSFERS = 8
    TRANSFER_SIZE = 8192

    #: firmware (bcdDevice low byte) at least this (neuromorphic-drivers: 0.6)
    MIN_FIRMWARE_VERSION = 6
    #: FPGA logic version exactly this (libcaer DAVIS_FX3_REQUIRED_LOGIC_VERSION)
    REQUIRED_LOGIC_VERSION = 18
    #: FPGA logic patch level at least this
    MIN_LOGIC_PATCH = 1
    CLEAR_SLEEP_S = 0.010
    BIAS_SETTLE_S = 0.200
    START_SETTLE_S = 0.050
    #: libcaer's APS defaults (us)
    APS_EXPOSURE_US = 4000
    APS_FRAME_INTERVAL_US = 40000

    def __init__(self, serial: str | None = None, *, aps: bool = False, **kw):
        super().__init__(serial, **kw)
        self.aps = bool(aps)
        self.logic_patch: int | None = None
        self.chip_id: int | None = None
        self.invert_xy = False
        self.aps_size = (346, 260)
        self.aps_flip_x = self.aps_flip_y = False
        self.logic_clock_mhz = self.adc_clock_mhz = self.usb_clock_mhz = 0.0
        self.has = {}
        self.imu_type = 0
        self._trigger_input = False
        self._decoder: DavisWordDecoder | None = None

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
                f"{self.MIN_FIRMWARE_VERSION}, the oldest this driver supports; update the firmware with "
                "iniVation's DV flashy tool")
        r = self.config_read
        self.logic_version = r(SYSINFO, SYSINFO_LOGIC_VERSION)
        if self.logic_version != self.REQUIRED_LOGIC_VERSION:
            raise CameraProtocolError(
                f"{self.name}: FPGA logic version {self.logic_version} (config module 6 parameter 0) is not "
                f"{self.REQUIRED_LOGIC_VERSION}, the one libcaer's protocol needs; flash the matching logic with "
                "iniVation's DV flashy tool")
        self.logic_patch = r(SYSINFO, SYSINFO_LOGIC_PATCH)
        if self.logic_patch < self.MIN_LOGIC_PATCH:
            raise CameraProtocolError(
                f"{self.name}: FPGA logic patch level {self.logic_patch} (config module 6 parameter 7) is below "
                f"{self.MIN_LOGIC_PATCH}; update the logic with iniVation's DV flashy tool")
        self.chip_id = r(SYSINFO, SYSINFO_CHIP_IDENTIFIER)
        if self.chip_id not in DAVIS346_CHIP_IDS:
            raise CameraProtocolError(
                f"{self.name}: chip identifier {self.chip_id} (config module 6 parameter 1) is not a DAVIS346 "
                f"({'/'.join(map(str, DAVIS346_CHIP_IDS))}); this DAVIS FX3 carries another sensor, which this "
                "driver does not support (use libcaer / DV)")
        dev = r(SYSINFO, SYSINFO_CLOCK_DEVIATION) / 1000.0
        self.logic_clock_mhz = r(SYSINFO, SYSINFO_LOGIC_CLOCK) * dev
        self.adc_clock_mhz = r(SYSINFO, SYSINFO_ADC_CLOCK) * dev
        self.usb_clock_mhz = r(SYSINFO, SYSINFO_USB_CLOCK) * dev
        self.has = {"pixel_filter": r(DVS, DVS_HAS_PIXEL_FILTER), "activity_filter":
                    r(DVS, DVS_HAS_BACKGROUND_ACTIVITY_FILTER), "roi_filter": r(DVS, DVS_HAS_ROI_FILTER),
                    "skip_filter": r(DVS, DVS_HAS_SKIP_FILTER), "polarity_filter": r(DVS, DVS_HAS_POLARITY_FILTER),
                    "global_shutter": r(APS, APS_HAS_GLOBAL_SHUTTER), "generator": r(EXTINPUT, EXTINPUT_HAS_GENERATOR)}
        self.has = {k: bool(v) for k, v in self.has.items()}
        cols, rows = r(DVS, DVS_SIZE_COLUMNS), r(DVS, DVS_SIZE_ROWS)
        if not (0 < cols <= 4096 and 0 < rows <= 4096):
            raise CameraProtocolError(f"{self.name}: the sensor reports {cols}x{rows} DVS pixels (config module 1 "
                                      "parameters 0 / 1); not a working DAVIS346")
        self.invert_xy = bool(r(DVS, DVS_ORIENTATION_INFO) & 0x04)
        self.width, self.height = (rows, cols) if self.invert_xy else (cols, rows)
        self.aps_size = (r(APS, APS_SIZE_COLUMNS), r(APS, APS_SIZE_ROWS))
        orient = r(APS, APS_ORIENTATION_INFO)
        if orient & 0x04:
            raise CameraProtocolError(f"{self.name}: APS orientation 0x{orient:x} swaps x and y, which no DAVIS346 "
                                      "does; this driver decodes unswapped frames only")
        self.aps_flip_x, self.aps_flip_y = bool(orient & 0x02), bool(orient & 0x01)
        self.imu_type = r(IMU, IMU_TYPE)
        self._all_off()
        self._send_default_config()
        self._configure_trigger_detector(False)

    def _close(self) -> None:
        if self.link is not None:
            try:
                self.config_write(MUX, MUX_RUN_CHIP, 0)
            except CameraError:
                pass

    def _all_off(self) -> None:
        """libcaer's 'ensure it is shut down completely' sequence of davisDataStart."""
        for m, p in ((DVS, DVS_RUN), (APS, APS_RUN), (IMU, IMU_RUN_ACCELEROMETER), (IMU, IMU_RUN_GYROSCOPE),
                     (IMU, IMU_RUN_TEMPERATURE), (EXTINPUT, EXTINPUT_RUN_DETECTOR), (MUX, MUX_RUN),
                     (MUX, MUX_TIMESTAMP_RUN), (USB, USB_RUN), (MUX, MUX_RUN_CHIP)):
            self.config_write(m, p, 0)

    def _cycles(self, us: float, clock_mhz: float) -> int:
        return int(round(us * clock_mhz))

    def _send_default_config(self) -> None:
        """libcaer's davisSendDefaultConfig: chip / bias configuration, then the FPGA's."""
        for p, v in default_chip_config():
            self.config_write(CHIP, p, v)
        w = self.config_write
        w(MUX, MUX_DROP_EXTINPUT_ON_STALL, 1)
        w(MUX, MUX_DROP_DVS_ON_STALL, 1)
        w(DVS, DVS_WAIT_ON_STALL, 0)
        w(DVS, DVS_EXTERNAL_AER_CONTROL, 0)
        sx, sy = (self.height, self.width) if self.invert_xy else (self.width, self.height)
        if self.has["pixel_filter"]:
            for i in range(8):                               # every pixel-filter slot off (out of range)
                w(DVS, DVS_FILTER_PIXEL_0_ROW + 2 * i, self.height)
                w(DVS, DVS_FILTER_PIXEL_0_ROW + 1 + 2 * i, self.width)
        if self.has["activity_filter"]:
            w(DVS, DVS_FILTER_BACKGROUND_ACTIVITY, 1)
            w(DVS, DVS_FILTER_BACKGROUND_ACTIVITY_TIME, 8)
            w(DVS, DVS_FILTER_REFRACTORY_PERIOD, 0)
            w(DVS, DVS_FILTER_REFRACTORY_PERIOD_TIME, 1)
        if self.has["roi_filter"]:
            self._write_roi(0, 0, sx - 1, sy - 1)
        if self.has["skip_filter"]:
            w(DVS, DVS_FILTER_SKIP_EVENTS, 0)
            w(DVS, DVS_FILTER_SKIP_EVENTS_EVERY, 5)
        if self.has["polarity_filter"]:
            w(DVS, DVS_POLARITY_FLATTEN, 0)
            w(DVS, DVS_POLARITY_SUPPRESS, 0)
            w(DVS, DVS_POLARITY_SUPPRESS_TYPE, 0)
        w(APS, APS_WAIT_ON_STALL, 1)
        if self.has["global_shutter"]:
            w(CHIP, CHIP_GLOBAL_SHUTTER, 1)                  # kept in sync with the APS module, as libcaer
            w(APS, APS_GLOBAL_SHUTTER, 1)
        w(APS, APS_START_COLUMN_0, 0)
        w(APS, APS_START_ROW_0, 0)
        w(APS, APS_END_COLUMN_0, self.aps_size[0] - 1)
        w(APS, APS_END_ROW_0, self.aps_size[1] - 1)
        self.set_aps_timing(self.APS_EXPOSURE_US, self.APS_FRAME_INTERVAL_US)
        w(IMU, IMU_SAMPLE_RATE_DIVIDER, 0)
        w(IMU, IMU_ACCEL_DLPF, 1)
        w(IMU, IMU_ACCEL_FULL_SCALE, 1)
        if self.imu_type == 2:
            w(IMU, IMU_GYRO_DLPF, 1)
        w(IMU, IMU_GYRO_FULL_SCALE, 1)
        w(EXTINPUT, EXTINPUT_DETECT_PULSE_POLARITY, 1)
        w(EXTINPUT, EXTINPUT_DETECT_PULSE_LENGTH, self._cycles(10, self.logic_clock_mhz))
        if self.has["generator"]:
            w(EXTINPUT, EXTINPUT_RUN_GENERATOR, 0)
        w(USB, USB_EARLY_PACKET_DELAY, self._cycles(8 * 125, self.usb_clock_mhz))   # 1 ms

    def set_aps_timing(self, exposure_us: float, frame_interval_us: float) -> None:
        """APS exposure and frame interval (us; written in ADC clock cycles, as libcaer)."""
        self._need_open_or_opening("set_aps_timing()")
        if not (0 < exposure_us < frame_interval_us <= 10_000_000):
            raise CameraError(f"{self.name}: APS exposure {exposure_us} us / interval {frame_interval_us} us: use "
                              "0 < exposure < interval <= 10 s")
        self.config_write(APS, APS_EXPOSURE, self._cycles(exposure_us, self.adc_clock_mhz))
        self.config_write(APS, APS_FRAME_INTERVAL, self._cycles(frame_interval_us, self.adc_clock_mhz))

    def _need_open_or_opening(self, what: str) -> None:
        if self.link is None:
            self._need_open(what)

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
        self.config_write(MUX, MUX_RUN_CHIP, 1)
        time.sleep(self.BIAS_SETTLE_S)
        self.config_write(USB, USB_RUN, 1)
        self.config_write(MUX, MUX_TIMESTAMP_RUN, 1)
        self.config_write(MUX, MUX_RUN, 1)
        time.sleep(self.START_SETTLE_S)
        self.config_write(DVS, DVS_RUN, 1)
        if self.aps:
            self.config_write(APS, APS_RUN, 1)
        if self._trigger_input:
            self.config_write(EXTINPUT, EXTINPUT_RUN_DETECTOR, 1)

    def _stop_hardware(self) -> None:
        self.config_write(DVS, DVS_RUN, 0)
        self.config_write(APS, APS_RUN, 0)
        for p in (IMU_RUN_ACCELEROMETER, IMU_RUN_GYROSCOPE, IMU_RUN_TEMPERATURE):
            self.config_write(IMU, p, 0)
        self.config_write(EXTINPUT, EXTINPUT_RUN_DETECTOR, 0)
        self.config_write(MUX, MUX_RUN, 0)
        self.config_write(MUX, MUX_TIMESTAMP_RUN, 0)
        self.config_write(USB, USB_RUN, 0)
        self.config_write(MUX, MUX_RUN_CHIP, 0)

    def reset_timestamps(self) -> None:
        """Reset the sensor clock to zero (libcaer's DAVIS_CONFIG_MUX_TIMESTAMP_RESET: a 0xC2 batch
        of 1 then 0); the stream then carries a timestamp-reset word."""
        self._need_open("reset_timestamps()")
        self.config_write_many([(MUX, MUX_TIMESTAMP_RESET, 1), (MUX, MUX_TIMESTAMP_RESET, 0)])

    def read_raw(self, timeout_s: float = 1.0):
        """As Device.read_raw; an idle timeout is confirmed with one config read (a streaming DAVIS
        sends a timestamp-wrap word at least every 32.8 ms, so silence may be an unplug libusb did
        not report): then CameraDisconnected, after every chunk received before."""
        chunk = super().read_raw(timeout_s)
        if chunk is None and self.link is not None:
            self.config_read(SYSINFO, SYSINFO_LOGIC_VERSION)
        return chunk

    # ------------------------------------------------------------------ decoding
    def _reset_decoder(self) -> None:
        self._decoder = DavisWordDecoder(self.width, self.height, "DAVIS346", invert_xy=self.invert_xy,
                                         aps=self.aps, aps_size=self.aps_size, aps_flip_x=self.aps_flip_x,
                                         aps_flip_y=self.aps_flip_y)

    def _decode(self, data: bytes):
        return self._decoder.feed(data)

    def _sample_words(self) -> bytes:
        return DavisWordEncoder(self.width, self.height, "DAVIS346").encode(SAMPLE_EVENT)

    def warm_up(self) -> None:
        super().warm_up()
        libcaer_packet(SAMPLE_EVENT, 0)      # the recorder's packet encoder loads its kernel too

    @property
    def decoder(self) -> DavisWordDecoder | None:
        return self._decoder

    def read_frames(self) -> list:
        """The APS frames (rig.camera.davis_words.ApsFrame) decoded by read() since the last call."""
        return [] if self._decoder is None else self._decoder.take_frames()

    # ------------------------------------------------------------------ biases
    THRESHOLD_MODEL = "rig.camera.davis346.thresholds_from_biases"

    def contrast_thresholds(self, biases: dict) -> tuple[float, float]:
        """The model's (C_on, C_off) for ``biases`` (the DiffBn / OnBn / OffBn coarse and fine values)."""
        return thresholds_from_biases(biases)

    @property
    def biases(self) -> dict[str, int]:
        """The bias parameters (flat names, see BIASES), read back from the bias generator."""
        self._need_open("biases")
        words = {}
        out = {}
        for name, (p, shift, bits) in BIASES.items():
            if p not in words:
                words[p] = self.config_read(BIAS, p)
            out[name] = (words[p] >> shift) & ((1 << bits) - 1)
        return out

    @property
    def coarse_fine_biases(self) -> dict[str, tuple[int, int]]:
        """The coarse-fine biases as {name: (coarse, fine)} (libcaer's readable form)."""
        b = self.biases
        return {n: (b[f"{n}_coarse"], b[f"{n}_fine"]) for n in COARSE_FINE_BIASES}

    def set_biases(self, biases: dict) -> None:
        """Write bias parameters by flat name (``diffbn_coarse``: 3 ...) or as ``name: (coarse, fine)``
        for the coarse-fine biases; the other fields of each bias word are kept (read-modify-write)."""
        self._need_open("set_biases()")
        flat = {}
        for name, value in biases.items():
            if name in COARSE_FINE_BIASES and isinstance(value, (tuple, list)) and len(value) == 2:
                flat[f"{name}_coarse"], flat[f"{name}_fine"] = value
            else:
                flat[name] = value
        self.check_bias_names(flat, BIASES)
        for name, value in flat.items():
            _p, _s, bits = BIASES[name]
            top = (1 << bits) - 1
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or not 0 <= int(value) <= top:
                raise CameraError(f"{self.name}: bias {name} = {value!r} is out of range; use an integer 0..{top}")
        by_param: dict[int, list] = {}
        for name, value in flat.items():
            p, shift, bits = BIASES[name]
            by_param.setdefault(p, []).append((shift, bits, int(value)))
        for p, fields in by_param.items():
            word = self.config_read(BIAS, p)
            for shift, bits, value in fields:
                mask = ((1 << bits) - 1) << shift
                word = (word & ~mask) | (value << shift)
            self.config_write(BIAS, p, word)

    # ------------------------------------------------------------------ ROI (the DVS ROI filter)
    def _need_roi_filter(self) -> None:
        if not self.has.get("roi_filter"):
            raise CameraError(f"{self.name}: this logic has no DVS ROI filter (config module 1 parameter 40 is 0); "
                              "update the logic with iniVation's DV flashy tool, or crop in software")

    def _write_roi(self, c0: int, r0: int, c1: int, r1: int) -> None:
        for p, v in ((DVS_ROI_START_COLUMN, c0), (DVS_ROI_START_ROW, r0), (DVS_ROI_END_COLUMN, c1),
                     (DVS_ROI_END_ROW, r1)):
            self.config_write(DVS, p, v)

    def set_roi(self, x: int, y: int, w: int, h: int) -> None:
        """Pass only events in x..x+w-1, y..y+h-1 (output coordinates) through the ROI filter."""
        self._need_open("set_roi()")
        self._need_roi_filter()
        x, y, w, h = self.check_roi(x, y, w, h)
        if self.invert_xy:
            x, y, w, h = y, x, h, w
        self._write_roi(x, y, x + w - 1, y + h - 1)

    def clear_roi(self) -> None:
        self._need_open("clear_roi()")
        self._need_roi_filter()
        sx, sy = (self.height, self.width) if self.invert_xy else (self.width, self.height)
        self._write_roi(0, 0, sx - 1, sy - 1)

    @property
    def roi(self) -> tuple[int, int, int, int] | None:
        """(x, y, w, h) read back from the ROI filter; None when it passes the whole sensor."""
        self._need_open("roi")
        if not self.has.get("roi_filter"):
            return None
        r = self.config_read
        c0, r0 = r(DVS, DVS_ROI_START_COLUMN), r(DVS, DVS_ROI_START_ROW)
        c1, r1 = r(DVS, DVS_ROI_END_COLUMN), r(DVS, DVS_ROI_END_ROW)
        sx, sy = (self.height, self.width) if self.invert_xy else (self.width, self.height)
        if c0 == 0 and r0 == 0 and c1 >= sx - 1 and r1 >= sy - 1:
            return None
        if c1 < c0 or r1 < r0:
            raise CameraProtocolError(f"{self.name}: the ROI filter's end ({c1}, {r1}) is before its start "
                                      f"({c0}, {r0}); set the ROI again")
        x, y, w, h = c0, r0, min(c1, sx - 1) - c0 + 1, min(r1, sy - 1) - r0 + 1
        if self.invert_xy:
            x, y, w, h = y, x, h, w
        return (x, y, w, h)

    # ------------------------------------------------------------------ triggers
    def _configure_trigger_detector(self, enabled: bool) -> None:
        self.config_write(EXTINPUT, EXTINPUT_DETECT_RISING, int(enabled))
        self.config_write(EXTINPUT, EXTINPUT_DETECT_FALLING, int(enabled))
        self.config_write(EXTINPUT, EXTINPUT_DETECT_PULSES, 0)

    def enable_trigger_input(self, enabled: bool = True) -> None:
        """Report rising and falling edges on the sync connector's input as triggers (id 0, value 1
        rising / 0 falling); takes effect at once when streaming."""
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
        libcaer_driver publishes it (see rig.camera.dvxplorer.libcaer_packet)."""
        if sensor_zero_host_ns is None:
            sensor_zero_host_ns = int(self.clock.sensor_ns_to_host_ns(0))
        return libcaer_packet(chunk.events, sensor_zero_host_ns)


def thresholds_from_bias_words(diff_word: int, on_word: int, off_word: int, base: float = 0.2,
                               floor: float = 0.01) -> tuple[float, float]:
    """(C_on, C_off) contrast thresholds (log intensity) a DAVIS pixel's comparators set: the ON
    threshold grows with ln(I_on / I_diff), the OFF threshold with ln(I_diff / I_off) (the
    differencing amplifier's output has to move by the gap between the comparator biases), each
    scaled so that libcaer's default biases give ``base`` for both; monotonic (ON up -> C_on up,
    OFF down -> C_off up, DiffBn up -> C_on down and C_off up) and floored at ``floor``."""
    d = {n: coarse_fine_word(*v) for n, v in DEFAULT_BIASES.items()}
    i_d0, i_on0, i_off0 = (bias_current_pa(d[n]) for n in ("diffbn", "onbn", "offbn"))
    tiny = 1e-6
    i_d, i_on, i_off = (max(bias_current_pa(w), tiny) for w in (diff_word, on_word, off_word))
    c_on = base * math.log(i_on / i_d) / math.log(i_on0 / i_d0)
    c_off = base * math.log(i_d / i_off) / math.log(i_d0 / i_off0)
    return max(floor, c_on), max(floor, c_off)


def thresholds_from_biases(biases: dict) -> tuple[float, float]:
    """:func:`thresholds_from_bias_words` for the driver's flat biases (``diffbn_coarse``,
    ``diffbn_fine``, ``onbn_*``, ``offbn_*``): the current depends only on coarse and fine."""
    words = [coarse_fine_word(DEFAULT_BIASES[n][0], int(biases[f"{n}_coarse"]), int(biases[f"{n}_fine"]))
             for n in ("diffbn", "onbn", "offbn")]
    return thresholds_from_bias_words(*words)
