"""Prophesee EVK4 (Sony IMX636 behind a Cypress FX3): USB protocol and register facts, as data.

Shared by the driver (rig.camera.evk4) and its virtual twin (rig.camera.virtual.evk4).
Facts only; sources (public, read for the values, no code taken):

* neuromorphic-drivers (neuromorphicsystems/neuromorphic-drivers,
  drivers/src/devices/prophesee_evk4.rs): USB ids, the serial request (control 0xC0/0x72,
  then bulk ``72 00*7`` on 0x02 with the serial in bytes 8-11 of the reply on 0x82), the
  20-byte register write / read commands, the register addresses and field layouts, the
  bring-up order (which follows OpenEB's issd_evk3_imx636_{stop,destroy,init,start}) and
  the ERC / filter set-up; EVT 3.0 on bulk IN 0x81 in 32 transfers of 128 KiB.
* OpenEB (prophesee-ai/openeb): hal_psee_plugins/include/devices/imx636/imx636_evk3_issd.h
  (the issd sequences), imx636_bias_settings.h + imx636_bias_settings_iterator.h (bias
  names, allowed and recommended offset ranges), src/devices/imx636/imx636_ll_biases.cpp
  (a bias register is ``0x11A10000 | clamp(factory + offset, 0, 255)``; the factory value
  is the low byte read at open), src/devices/imx636/imx636_tz_trigger_event.cpp (external
  trigger in = bit 10 of edf/Reserved_7004), src/devices/gen41/gen41_roi_command.cpp (ROI:
  40 td_roi_x and 23 td_roi_y registers holding the complement of the window masks, the
  top 16 bits of td_roi_y22 forced to 1, then roi_ctrl with roi_td_en, td_roi_roni_n_en,
  px_td_rstn and roi_td_shadow_trigger).
"""

from __future__ import annotations

import struct
from typing import NamedTuple

from .biases import BiasRange

# --- USB ------------------------------------------------------------------------------
VENDOR_ID = 0x04B4
PRODUCT_IDS = (0x00F4, 0x00F5)
USB_IDS = tuple((VENDOR_ID, pid) for pid in PRODUCT_IDS)
EP_COMMAND_OUT = 0x02
EP_COMMAND_IN = 0x82
EP_EVENTS = 0x81
TRANSFERS = 32
TRANSFER_SIZE = 128 * 1024
WIDTH, HEIGHT = 1280, 720

# control IN 0xC0 / 0x72 / wValue 0 / wIndex 0, 2 bytes: byte 0 = sensor type
SENSOR_TYPE_REQUEST = (0xC0, 0x72, 0x0000, 0x0000, 2)
SENSOR_TYPES = {0x31: "IMX636", 0x35: "IMX646"}

# 8-byte bulk requests on 0x02 (reply on 0x82: the request echoed, then a u32 LE payload)
REQ_SERIAL = bytes([0x72, 0, 0, 0, 0, 0, 0, 0])          # payload (bytes 8-11) = serial
REQ_RELEASE_VERSION = bytes([0x79, 0, 0, 0, 0, 0, 0, 0])  # payload = firmware release
REQ_BUILD_DATE = bytes([0x7A, 0, 0, 0, 0, 0, 0, 0])       # payload = build date
SERIAL_REPLY_SLICE = slice(8, 12)                         # u32 LE, printed as %08X

# 20-byte register commands on 0x02: 12-byte header, address u32 LE, value (or 1) u32 LE;
# a write is answered by the command echoed, a read by the 16 header+address bytes echoed
# followed by the register value (u32 LE).
REG_WRITE_HEADER = bytes([0x02, 0x01, 0x01, 0x40, 0x0C, 0, 0, 0, 0, 0, 0, 0])
REG_READ_HEADER = bytes([0x02, 0x01, 0x01, 0x00, 0x0C, 0, 0, 0, 0, 0, 0, 0])
REG_COMMAND_SIZE = 20


def write_command(address: int, value: int) -> bytes:
    return REG_WRITE_HEADER + struct.pack("<II", address, value & 0xFFFFFFFF)


def read_command(address: int) -> bytes:
    return REG_READ_HEADER + struct.pack("<II", address, 1)


# --- registers (byte addresses) ----------------------------------------------------------
ROI_CTRL = 0x0004            # bit 1 td_enable, 5 shadow_trigger, 6 td_roni_n_en, 10 td_rstn
UNKNOWN_002C = 0x002C
BIAS_BASE_CONF = 0x11A10000  # single | idac_en | buf_en | mux_en | buf_stg=1
TD_ROI_X = 0x2000            # 40 registers, bit b of register k = column 32k+b; 1 = masked
TD_ROI_X_COUNT = 40
TD_ROI_Y = 0x4000            # 23 registers, bit b of register k = row 32k+b; 1 = masked
TD_ROI_Y_COUNT = 23
EDF_RESERVED_7004 = 0x7004   # bit 10: external trigger input enable
READOUT_CTRL = 0x9000
TIME_BASE_CTRL = 0x9008      # bit 0 enable, 1 external, 2 primary, 3 external_enable
RO_CTRL = 0x9028             # bit 1 output_disable: the readout (event output) gate
MIPI_CONTROL = 0xB000
RESET = 0x400004

ROI_CTRL_RESERVED = 0x1E000A << 11
ROI_TD_ENABLE = 1 << 1
ROI_SHADOW_TRIGGER = 1 << 5
ROI_RONI_N_EN = 1 << 6
ROI_TD_RSTN = 1 << 10
RO_OUTPUT_DISABLE = 1 << 1
TIME_BASE_ENABLE = 1 << 0
TIME_BASE_IDLE = (0x64 << 4) | (1 << 2)          # primary, internal clock, not running
EXT_TRIGGER_BIT = 1 << 10
EDF_7004_BASE = 0b0111111111 | (0b11000 << 11)


def roi_ctrl(*, rstn: bool, shadow: bool = False, roni_n: bool = True, td_enable: bool = True) -> int:
    return (ROI_CTRL_RESERVED | (ROI_TD_ENABLE if td_enable else 0)
            | (ROI_SHADOW_TRIGGER if shadow else 0) | (ROI_RONI_N_EN if roni_n else 0)
            | (ROI_TD_RSTN if rstn else 0))


def edf_7004(trigger_in: bool) -> int:
    return EDF_7004_BASE | (EXT_TRIGGER_BIT if trigger_in else 0)


def bias_register_value(absolute: int) -> int:
    if not 0 <= int(absolute) <= 255:
        raise ValueError(f"bias register value {absolute} outside 0..255")   # callers check first
    return BIAS_BASE_CONF | int(absolute)


# --- biases ------------------------------------------------------------------------------
class BiasSpec(NamedTuple):
    address: int
    range: BiasRange      # offsets from the factory value: allowed, then recommended


#: The biases OpenEB exposes for the IMX636 (values are offsets from the factory default).
BIASES: dict[str, BiasSpec] = {
    "bias_fo": BiasSpec(0x1004, BiasRange(-150, 200, -35, 55)),
    "bias_hpf": BiasSpec(0x100C, BiasRange(0, 255, 0, 120)),
    "bias_diff_on": BiasSpec(0x1010, BiasRange(-150, 200, -85, 140)),
    "bias_diff": BiasSpec(0x1014, BiasRange(-150, 200, -25, 23)),
    "bias_diff_off": BiasSpec(0x1018, BiasRange(-150, 200, -35, 190)),
    "bias_refr": BiasSpec(0x1020, BiasRange(-50, 255, -20, 235)),
}
BIAS_RANGES = {name: spec.range for name, spec in BIASES.items()}
#: every bias register of the chip (neuromorphic-drivers' list), for the twin's register map
ALL_BIAS_REGISTERS = {"bias_pr": 0x1000, "bias_fo": 0x1004, "bias_hpf": 0x100C,
                      "bias_diff_on": 0x1010, "bias_diff": 0x1014, "bias_diff_off": 0x1018,
                      "bias_inv": 0x101C, "bias_refr": 0x1020, "bias_reqpuy": 0x1040,
                      "bias_reqpux": 0x1044, "bias_sendreqpdy": 0x1048, "bias_unknown_1": 0x104C,
                      "bias_unknown_2": 0x1050}


# --- sequences -----------------------------------------------------------------------------
class Write(NamedTuple):
    """One register write, then wait ``delay_s`` (the settling time the sources use)."""
    address: int
    value: int
    delay_s: float = 0.0


# issd_evk3_imx636_stop
STOP = (
    Write(ROI_CTRL, roi_ctrl(rstn=False)),
    Write(UNKNOWN_002C, 0x0022C324),
    Write(RO_CTRL, RO_OUTPUT_DISABLE, 0.001),
    Write(TIME_BASE_CTRL, TIME_BASE_IDLE),
    Write(MIPI_CONTROL, 0x000002F8, 0.0003),
)

# issd_evk3_imx636_destroy
DESTROY = (
    Write(0x0070, 0x00400008), Write(0x006C, 0x0EE47114, 0.0005),
    Write(0xA00C, 0x00020400, 0.0005), Write(0xA010, 0x00008068, 0.0002),
    Write(0x1104, 0x00000000, 0.0002), Write(0xA020, 0x00000050, 0.0002),
    Write(0xA004, 0x000B0500, 0.0002), Write(0xA008, 0x00002404, 0.0002),
    Write(0xA000, 0x000B0500), Write(0xB044, 0x00000000), Write(0xB004, 0x0000000A),
    Write(0xB040, 0x0000000E), Write(0xB0C8, 0x00000000), Write(0xB040, 0x00000006),
    Write(0xB040, 0x00000004), Write(0x0000, 0x4F006442), Write(0x0000, 0x0F006442),
    Write(0x00B8, 0x00000401), Write(0x00B8, 0x00000400), Write(0xB07C, 0x00000000),
)

# issd_evk3_imx636_init (the sensor reset takes 1 s, the MIPI bring-up another 1.5 s)
INIT = (
    Write(0x001C, 0x00000001), Write(RESET, 0x00000001, 1.0), Write(RESET, 0x00000000, 0.5),
    Write(MIPI_CONTROL, 0x00000158, 1.0), Write(0xB044, 0x00000000, 0.0003),
    Write(0xB004, 0x0000000A), Write(0xB040, 0x00000000), Write(0xB0C8, 0x00000000),
    Write(0xB040, 0x00000000), Write(0xB040, 0x00000000), Write(0x0000, 0x4F006442),
    Write(0x0000, 0x0F006442), Write(0x00B8, 0x00000400), Write(0x00B8, 0x00000400),
    Write(0xB07C, 0x00000000), Write(0xB074, 0x00000002), Write(0xB078, 0x000000A0),
    Write(0x00C0, 0x00000110), Write(0x00C0, 0x00000210), Write(0xB120, 0x00000001),
    Write(0xE120, 0x00000000), Write(0xB068, 0x00000004), Write(0xB07C, 0x00000001, 0.00001),
    Write(0xB07C, 0x00000003, 0.001), Write(0x00B8, 0x00000401), Write(0x00B8, 0x00000409),
    Write(0x0000, 0x4F006442), Write(0x0000, 0x4F00644A), Write(0xB080, 0x00000077),
    Write(0xB084, 0x0000000F), Write(0xB088, 0x00000037), Write(0xB08C, 0x00000037),
    Write(0xB090, 0x000000DF), Write(0xB094, 0x00000057), Write(0xB098, 0x00000037),
    Write(0xB09C, 0x00000067), Write(0xB0A0, 0x00000037), Write(0xB0A4, 0x0000002F),
    Write(0xB0AC, 0x00000028), Write(0xB0CC, 0x00000001), Write(MIPI_CONTROL, 0x000002F8),
    Write(0xB004, 0x0000008A), Write(0xB01C, 0x00000030), Write(0xB020, 0x00002000),
    Write(0xB02C, 0x000000FF), Write(0xB030, 0x00003E80), Write(0xB028, 0x00000FA0),
    Write(0xA000, 0x000B0501, 0.0002), Write(0xA008, 0x00002405, 0.0002),
    Write(0xA004, 0x000B0501, 0.0002), Write(0xA020, 0x00000150, 0.0002),
    Write(0xB040, 0x00000007), Write(0xB064, 0x00000006), Write(0xB040, 0x0000000F, 0.0001),
    Write(0xB004, 0x0000008A, 0.0002), Write(0xB0C8, 0x00000003, 0.0002),
    Write(0xB044, 0x00000001), Write(MIPI_CONTROL, 0x000002F9), Write(0x7008, 0x00000001),
    Write(0x7000, 0x00070001), Write(0x8000, 0x0001E085), Write(TIME_BASE_CTRL, TIME_BASE_IDLE),
    Write(ROI_CTRL, roi_ctrl(rstn=False)), Write(0x0018, 0x00000200),
    Write(0x1014, 0x11A1504D),                      # bias_diff: idac 0x4d, vdac 0x50
    Write(0x9004, 0x00000000, 0.001), Write(READOUT_CTRL, 0x00000200),
)

# anti-flicker bypassed, STC / trail filters off, burst pipeline bypassed
FILTERS = (
    Write(0xC008, 15 | (156 << 8) | (8 << 16)),    # AFK period
    Write(0xC000, 0b101),                           # AFK pipeline: bypass
    Write(0xD00C, 13 | (1 << 5) | (1 << 9)),        # STC timestamping
    Write(0xD004, (1480 << 1) | (1 << 24)),         # STC param: disabled
    Write(0xD008, 100000 << 1),                     # trail param: disabled
    Write(0xD0C0, 4 | (280 << 12) | (10 << 24)),    # burst pipeline invalidation
    Write(0xD0C4, 0),                               # burst pipeline initialisation
    Write(0xD000, 0b101),                           # burst pipeline: bypass
)

# event rate controller present but disabled (its LUTs initialised)
ERC = ((Write(0x6000, 0x00155400), Write(0x6004, 0), Write(0x6028, 0b10), Write(0x602C, 1))
       + tuple(Write(0x6800 + 4 * i, 0x08080808) for i in range(230))
       + (Write(0x602C, 2),)
       + tuple(Write(0x6400 + 4 * i, ((2 * i + 1) << 16) | (2 * i)) for i in range(256))
       + (Write(0x6050, 0), Write(0x6060, 0), Write(0x6070, 0), Write(0x6000, 0x00155401)))

# issd_evk3_imx636_start: the time base starts counting (sensor time 0) and the readout
# gate opens; the sensor streams EVT 3.0 on 0x81 from here on.
START = (
    Write(MIPI_CONTROL, 0x000002F9),
    Write(RO_CTRL, 0),
    Write(TIME_BASE_CTRL, TIME_BASE_IDLE | TIME_BASE_ENABLE),
    Write(UNKNOWN_002C, 0x0022C724),
    Write(ROI_CTRL, roi_ctrl(rstn=True)),
)


def open_sequence(trigger_in: bool = False) -> tuple[Write, ...]:
    """Every register write the driver's open() makes, in order (after the identity and
    factory-bias reads): stop, destroy, init, filters, ERC, trigger-in configuration."""
    return STOP + DESTROY + INIT + FILTERS + ERC + (Write(EDF_RESERVED_7004, edf_7004(trigger_in)),)


def roi_registers(x: int, y: int, w: int, h: int) -> tuple[Write, ...]:
    """The writes that restrict the sensor to the window [x, x+w) x [y, y+h) (OpenEB's
    gen41 ROI: register bit = 1 masks the column / row out)."""
    xs = _mask_words(x, w, TD_ROI_X_COUNT)
    ys = _mask_words(y, h, TD_ROI_Y_COUNT)
    ys[-1] |= 0xFFFF0000
    return (tuple(Write(TD_ROI_X + 4 * k, v) for k, v in enumerate(xs))
            + tuple(Write(TD_ROI_Y + 4 * k, v) for k, v in enumerate(ys))
            + (Write(ROI_CTRL, roi_ctrl(rstn=True, shadow=True)),))


def _mask_words(start: int, length: int, count: int) -> list[int]:
    full = (1 << (32 * count)) - 1
    window = ((1 << length) - 1) << start
    inv = full & ~window
    return [(inv >> (32 * k)) & 0xFFFFFFFF for k in range(count)]


def clear_roi_registers() -> tuple[Write, ...]:
    """All columns and rows enabled (the full frame)."""
    return roi_registers(0, 0, WIDTH, HEIGHT)


def roi_from_registers(xs, ys) -> tuple[int, int, int, int] | None:
    """(x, y, w, h) of the window the TD_ROI registers select, None for the full frame.

    Raises ValueError when the enabled columns or rows are not one contiguous run."""
    def runs(words, n):
        bits = 0
        for k, v in enumerate(words):
            bits |= (int(v) & 0xFFFFFFFF) << (32 * k)
        enabled = [i for i in range(n) if not (bits >> i) & 1]
        if not enabled:
            raise ValueError("every pixel is masked out")
        lo, hi = enabled[0], enabled[-1]
        if hi - lo + 1 != len(enabled):
            raise ValueError("the enabled columns / rows are not one contiguous window")
        return lo, hi - lo + 1
    x, w = runs(xs, WIDTH)
    y, h = runs(ys, HEIGHT)
    if (x, y, w, h) == (0, 0, WIDTH, HEIGHT):
        return None
    return x, y, w, h
