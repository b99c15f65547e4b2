"""Typed errors of the camera drivers; every one derives from the project's EvdnerfError.

Messages name the device (model and serial or bus address), the request / register at
fault and what would fix it, on one line.
"""

from __future__ import annotations

from evdnerf_ros.errors import EvdnerfError

#: The udev rules file shipped with the project (relative to the checkout / share dir).
UDEV_RULES = "config/99-evdnerf-cameras.rules"
UDEV_INSTALL_HINT = (f"install the udev rules: sudo cp {UDEV_RULES} /etc/udev/rules.d/ && "
                     "sudo udevadm control --reload-rules && sudo udevadm trigger, then "
                     "unplug and replug the camera (or add your user to the plugdev group)")


class CameraError(EvdnerfError):
    """Base of every camera driver error."""


class CameraNotFound(CameraError):
    """No camera (or none with the requested serial / model) is connected."""


class CameraPermissionError(CameraError):
    """The USB device node is not accessible to this user (LIBUSB_ERROR_ACCESS / errno 13)."""

    def __init__(self, device: str, detail: str = ""):
        why = f" ({detail})" if detail else ""
        super().__init__(f"{device}: permission denied opening the USB device{why}; "
                         + UDEV_INSTALL_HINT)
        self.device = device


class CameraDisconnected(CameraError):
    """The camera went away (unplug) mid-stream.

    ``received`` holds what was delivered before the unplug was seen (counts, and for
    a drained stream the chunks the caller had not read yet are delivered first)."""

    def __init__(self, message: str, *, chunks: int = 0, nbytes: int = 0):
        super().__init__(message)
        self.chunks = chunks
        self.nbytes = nbytes


class CameraProtocolError(CameraError):
    """A stall, a malformed reply or an unsupported firmware / logic version."""


class CameraTimeout(CameraError):
    """A control request or register reply did not arrive in time (never raised for an
    idle event stream: reads return None then)."""
