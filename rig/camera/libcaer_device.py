"""What the libcaer-protocol drivers (``DVXplorer``, ``DAVIS346``) share: the configuration requests.

libcaer talks to both cameras' FPGA through vendor request 0xBF — OUT (0x40) writes the 4-byte
big-endian value of (module = wValue, parameter = wIndex), IN (0xC0) reads it — and 0xC2, which
writes wValue records of {u8 module, u8 parameter, u32 BE} in one transfer (spiConfigSend,
spiConfigReceive, spiConfigSendMultiple in libcaer's usb_utils).
"""

from __future__ import annotations

import struct

from .device import Device
from .errors import CameraError, CameraProtocolError

REQUEST_CONFIG = 0xBF
REQUEST_CONFIG_MULTIPLE = 0xC2


class LibcaerDevice(Device):
    """A camera configured through libcaer's register requests (module docstring); a subclass keeps
    its word decoder (``time_us``, ``words``) in ``_decoder``, None until it streams."""

    CONTROL_TIMEOUT_MS = None          # the link's (rig.camera.device.TRANSFER_TIMEOUT_MS)
    #: how a parameter address reads in errors (the DVXplorer's sensor registers are 16-bit addresses)
    PARAM_FORMAT = "{}"

    def config_write(self, module: int, param: int, value: int) -> None:
        """One 0xBF configuration write (libcaer's spiConfigSend)."""
        self.link.control_out(0x40, REQUEST_CONFIG, module, param, struct.pack(">I", int(value) & 0xFFFFFFFF),
                              self.CONTROL_TIMEOUT_MS, what=f"config write module {module} parameter "
                              f"{self.PARAM_FORMAT.format(param)} = {int(value)}")

    def config_read(self, module: int, param: int) -> int:
        """One 0xBF configuration read (libcaer's spiConfigReceive): the 32-bit value."""
        what = f"config read module {module} parameter {self.PARAM_FORMAT.format(param)}"
        data = self.link.control_in(0xC0, REQUEST_CONFIG, module, param, 4, self.CONTROL_TIMEOUT_MS, what=what)
        if len(data) != 4:
            raise CameraProtocolError(f"{self.name}: {what}: {len(data)} bytes instead of 4; the device does not "
                                      "speak libcaer's config protocol (wrong firmware?)")
        return struct.unpack(">I", data)[0]

    def config_write_many(self, writes) -> None:
        """Several writes in one 0xC2 request (libcaer's spiConfigSendMultiple): (module, param, value)
        with module and param < 256."""
        writes = [(int(m), int(p), int(v)) for m, p, v in writes]
        if not writes:
            return
        if any(p > 0xFF or m > 0xFF for m, p, _ in writes):
            raise CameraError(f"{self.name}: a 0xC2 batch carries 8-bit module / parameter addresses; write "
                              "wider ones one by one with config_write")
        payload = b"".join(struct.pack(">BBI", m, p, v & 0xFFFFFFFF) for m, p, v in writes)
        self.link.control_out(0x40, REQUEST_CONFIG_MULTIPLE, len(writes), 0, payload, self.CONTROL_TIMEOUT_MS,
                              what=f"config batch of {len(writes)} writes")

    def _sensor_time_ns(self) -> int | None:
        decoder = self._decoder
        if decoder is None or decoder.words == 0:
            return None
        return decoder.time_us * 1000
