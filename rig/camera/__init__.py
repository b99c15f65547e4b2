"""Event cameras over USB (issue 14): pure-Python drivers on pyusb + python-libusb1.

    from rig.camera import list_cameras, open_camera
    for info in list_cameras():
        print(info)
    with open_camera(model="DVXplorer") as cam:      # or open_camera(serial="...")
        cam.start()
        chunk = cam.read(timeout_s=1.0)              # EventChunk | None

Model modules: ``rig.camera.dvxplorer.DVXplorer`` and ``rig.camera.davis346.DAVIS346`` (iniVation,
libcaer protocol: both subclass ``rig.camera.libcaer_device.LibcaerDevice``, its configuration
requests) and ``rig.camera.evk4.EVK4`` (Prophesee, EVT 3.0); all subclass ``rig.camera.device.Device``.
Virtual twins (``rig.camera.virtual``) serve the same protocol through umockdev, so everything
here also runs against them (in a process started with the virtual bus's environment).

Access to the USB device nodes needs the udev rules in ``config/99-evdnerf-cameras.rules``;
without them opening fails with ``CameraPermissionError`` naming that file.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass

from .device import Device, EventChunk, RawChunk, StreamStats, UsbLink
from .errors import (UDEV_RULES, CameraDisconnected, CameraError, CameraNotFound,
                     CameraPermissionError, CameraProtocolError, CameraTimeout)

#: (vid, pid) -> (model, "module:Class" or None when no driver exists yet)
KNOWN_CAMERAS: dict[tuple[int, int], tuple[str, str | None]] = {
    (0x152A, 0x8419): ("DVXplorer", "rig.camera.dvxplorer:DVXplorer"),
    (0x152A, 0x841A): ("DAVIS346", "rig.camera.davis346:DAVIS346"),
    (0x152A, 0x841B): ("DAVIS FX2", None),
    (0x04B4, 0x00F4): ("EVK4", "rig.camera.evk4:EVK4"),
    (0x04B4, 0x00F5): ("EVK4", "rig.camera.evk4:EVK4"),
}

__all__ = ["list_cameras", "open_camera", "CameraInfo", "KNOWN_CAMERAS", "Device", "EventChunk",
           "RawChunk", "StreamStats", "UsbLink", "CameraError", "CameraNotFound",
           "CameraPermissionError", "CameraDisconnected", "CameraProtocolError", "CameraTimeout",
           "UDEV_RULES"]


@dataclass(frozen=True)
class CameraInfo:
    model: str
    vid: int
    pid: int
    serial: str | None          # None when the device could not be opened (see error)
    bus: int
    address: int
    bcd_device: int
    error: str = ""             # why the serial could not be read ("" when accessible)

    @property
    def accessible(self) -> bool:
        return not self.error

    @property
    def where(self) -> str:
        return (f"{self.model} {self.vid:04x}:{self.pid:04x} at bus {self.bus:03d} device "
                f"{self.address:03d}")

    def __str__(self) -> str:
        sn = self.serial if self.serial is not None else "?"
        return f"{self.where} serial {sn}" + (f" ({self.error})" if self.error else "")


def _model_key(model: str) -> str:
    return "".join(c for c in str(model).lower() if c.isalnum())


def list_cameras() -> list[CameraInfo]:
    """Every connected camera of a known model (pyusb), serial read when accessible."""
    try:
        import usb.core
        import usb.util
    except ImportError as exc:  # pragma: no cover - dependency of the package
        raise CameraError(f"pyusb is not installed ({exc}); pip install 'pyusb>=1.2'") from None
    try:
        devices = list(usb.core.find(find_all=True,
                                     custom_match=lambda d: (d.idVendor, d.idProduct) in KNOWN_CAMERAS))
    except usb.core.NoBackendError:
        raise CameraError("pyusb found no libusb backend; install libusb-1.0 "
                          "(Debian: apt-get install libusb-1.0-0)") from None
    out = []
    for d in devices:
        model = KNOWN_CAMERAS[(d.idVendor, d.idProduct)][0]
        serial, error = None, ""
        try:
            serial = usb.util.get_string(d, d.iSerialNumber) if d.iSerialNumber else ""
        except usb.core.USBError as exc:
            error = ("permission denied: install " + UDEV_RULES if exc.errno == 13
                     else f"USB error: {exc}")
        except ValueError as exc:            # pyusb: no langid (usually a permission problem)
            error = f"cannot read strings ({exc}); install {UDEV_RULES}"
        finally:
            try:
                usb.util.dispose_resources(d)
            except Exception:
                pass
        out.append(CameraInfo(model, d.idVendor, d.idProduct, serial, d.bus, d.address,
                              d.bcdDevice, error))
    return out


def driver_class(model: str):
    """The Device subclass of ``model`` (imported lazily)."""
    key = _model_key(model)
    for name, target in KNOWN_CAMERAS.values():
        if _model_key(name) == key:
            if target is None:
                raise CameraError(f"{name}: no driver in this version (supported: "
                                  f"{', '.join(sorted({n for n, t in KNOWN_CAMERAS.values() if t}))})")
            mod, cls = target.split(":")
            return getattr(importlib.import_module(mod), cls)
    raise CameraError(f"unknown camera model {model!r}; known: "
                      f"{', '.join(sorted({n for n, _ in KNOWN_CAMERAS.values()}))}")


def open_camera(serial: str | None = None, model: str | None = None, **options) -> Device:
    """Open the camera with ``serial`` (or the first found, of ``model`` if given) and
    return its opened driver; ``options`` go to the model's constructor."""
    cams = list_cameras()
    found = cams
    if model is not None:
        driver_class(model)                  # unknown model -> error listing the known
        found = [c for c in found if _model_key(c.model) == _model_key(model)]
    if serial is not None:
        found = [c for c in found if c.serial == serial or (c.serial is None)]
    if not found:
        want = " ".join(x for x in (model and f"model {model}", serial and f"serial {serial!r}") if x)
        listed = "; ".join(str(c) for c in cams) or "none"
        raise CameraNotFound(f"no camera{(' with ' + want) if want else ''} connected "
                             f"(connected: {listed}); plug it in, check `lsusb`, or run a "
                             "virtual twin (evdnerf camera ... --virtual MODEL)")
    info = next((c for c in found if c.accessible), found[0])
    if not info.accessible:
        raise CameraPermissionError(info.where, info.error)
    cls = driver_class(info.model)
    dev = cls(serial=info.serial, **options)
    dev.open()
    return dev
