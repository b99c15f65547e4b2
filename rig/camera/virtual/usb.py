"""Emulated USB devices served to the real libusb through umockdev (no kernel USB needed).

The facts this module is built on are in ../shared/notes/usb-virtual.md (measured): a
``UMockdev.Testbed`` fakes /sys and /dev; any process started with
``LD_PRELOAD=libumockdev-preload.so.0`` and the testbed's ``UMOCKDEV_DIR`` sees the device, and
every usbdevfs ioctl its libusb makes on the device node arrives here, in the process owning
the testbed, on a GLib worker thread.  ``VirtualUsbBus`` owns the testbed and answers those
ioctls for each ``EmulatedUsbDevice`` added to it:

* GET_CAPABILITIES -> 0x1f (zero packet, bulk continuation, no packet size limit, bulk
  scatter-gather, reap after disconnect: libusb then submits a whole transfer as one URB);
* SUBMITURB: control URBs are answered at once (standard GET_DESCRIPTOR / GET_STATUS /
  GET_CONFIGURATION here, everything else through ``device.control()``), bulk OUT URBs are
  passed to ``device.bulk_out()``, bulk IN URBs wait in a per-endpoint queue;
* REAPURB(NDELAY): completed URBs first, then the oldest waiting IN URB of each endpoint is
  filled *lazily* from ``device.bulk_in(ep, max_len)``; when nothing is ready the EAGAIN answer
  is delayed (``eagain_delay_s``, pitfall 4: the device node is a regular file, so libusb's
  poll is always ready and it would spin);
* DISCARDURB: the URB is reaped later with status -ENOENT (libusb's cancel / timeouts);
* a stall is status -EPIPE; after ``device.unplug()`` the URBs still queued are reaped with
  -ESHUTDOWN (libusb: LIBUSB_TRANSFER_NO_DEVICE) and every other ioctl fails with ENODEV.

Every resolved URB and buffer stays referenced until it is reaped (pitfall 5), the driver
always runs in another process (pitfall 2: ``run_child`` / ``spawn_child``), and children get
``PR_SET_TIMERSLACK`` 1 ns (pitfall 1: the preload sleeps after each emulated ioctl).
"""

from __future__ import annotations

import collections
import ctypes
import ctypes.util
import errno
import os
import struct
import subprocess
import sys
import threading
import time
from dataclasses import dataclass

# --------------------------------------------------------------------------- availability
PRELOAD_NAME = "libumockdev-preload.so.0"
_PRELOAD_DIRS = ("/usr/lib/x86_64-linux-gnu", "/usr/lib/aarch64-linux-gnu", "/usr/lib64",
                 "/usr/lib", "/usr/local/lib", "/usr/local/lib/x86_64-linux-gnu")
MIN_UMOCKDEV = (0, 17, 14)
#: Transfer timeout (ms) of drivers talking to emulated devices (rig.camera.device.TRANSFER_TIMEOUT_MS).
EMULATED_TIMEOUT_MS = 10_000
INSTALL_HINT = ("install umockdev (Debian: apt-get install umockdev gir1.2-umockdev-1.0 "
                "python3-gi; `bash quickstart.sh test` as root does it and makes `gi` importable "
                "in the .venv)")


def preload_path() -> str | None:
    """Full path of umockdev's LD_PRELOAD library, or None."""
    for d in _PRELOAD_DIRS:
        p = os.path.join(d, PRELOAD_NAME)
        if os.path.exists(p):
            return p
    return None


def _load_umockdev():
    import gi
    gi.require_version("UMockdev", "1.0")
    from gi.repository import GLib, UMockdev
    return GLib, UMockdev


def umockdev_available() -> tuple[bool, str]:
    """(True, "") when emulated USB devices can be served here, else (False, why)."""
    if not sys.platform.startswith("linux"):
        return False, f"umockdev needs Linux (this is {sys.platform})"
    if preload_path() is None:
        return False, f"{PRELOAD_NAME} not found; {INSTALL_HINT}"
    try:
        _GLib, UMockdev = _load_umockdev()
    except ImportError as exc:
        return False, f"python `gi` is not importable ({exc}); {INSTALL_HINT}"
    except ValueError as exc:
        return False, f"UMockdev typelib missing ({exc}); {INSTALL_HINT}"
    if not hasattr(UMockdev.IoctlData, "update") or not hasattr(UMockdev.IoctlData, "retrieve"):
        return False, ("umockdev is older than 0.17.14 (IoctlData.update/retrieve missing); "
                       "upgrade it: " + INSTALL_HINT)
    if ctypes.util.find_library("usb-1.0") is None:
        return False, "libusb-1.0 not found; apt-get install libusb-1.0-0"
    return True, ""


# --------------------------------------------------------------------------- usbdevfs
def _ioc(direction: int, nr: int, size: int) -> int:
    return (direction << 30) | (size << 16) | (ord("U") << 8) | nr


_W, _R = 1, 2
USBDEVFS_SETINTERFACE = _ioc(_R, 4, 8)
USBDEVFS_SETCONFIGURATION = _ioc(_R, 5, 4)
USBDEVFS_GETDRIVER = _ioc(_W, 8, 260)
USBDEVFS_SUBMITURB = _ioc(_R, 10, 56)
USBDEVFS_DISCARDURB = _ioc(0, 11, 0)
USBDEVFS_REAPURB = _ioc(_W, 12, 8)
USBDEVFS_REAPURBNDELAY = _ioc(_W, 13, 8)
USBDEVFS_CLAIMINTERFACE = _ioc(_R, 15, 4)
USBDEVFS_RELEASEINTERFACE = _ioc(_R, 16, 4)
USBDEVFS_RESET = _ioc(0, 20, 0)
USBDEVFS_CLEAR_HALT = _ioc(_R, 21, 4)
USBDEVFS_GET_CAPABILITIES = _ioc(_R, 26, 4)
USBDEVFS_RESETEP = _ioc(_R, 3, 4)
CAPABILITIES = 0x1F
URB_SIZE = 56
URB_TYPE_INTERRUPT, URB_TYPE_CONTROL, URB_TYPE_BULK = 1, 2, 3
_SUCCEED = {USBDEVFS_SETINTERFACE, USBDEVFS_SETCONFIGURATION, USBDEVFS_CLAIMINTERFACE,
            USBDEVFS_RELEASEINTERFACE, USBDEVFS_RESET, USBDEVFS_CLEAR_HALT, USBDEVFS_RESETEP}


class _Stall:
    def __repr__(self) -> str:
        return "STALL"


#: Return this from a control / bulk hook to stall the request (the URB ends with -EPIPE).
STALL = _Stall()


@dataclass(frozen=True)
class SetupPacket:
    request_type: int
    request: int
    value: int
    index: int
    length: int

    @classmethod
    def parse(cls, raw: bytes) -> "SetupPacket":
        return cls(*struct.unpack("<BBHHH", bytes(raw[:8])))

    @property
    def is_in(self) -> bool:
        return bool(self.request_type & 0x80)

    @property
    def kind(self) -> str:
        return ("standard", "class", "vendor", "reserved")[(self.request_type >> 5) & 3]

    def __str__(self) -> str:
        return (f"bmRequestType 0x{self.request_type:02x} bRequest 0x{self.request:02x} "
                f"wValue 0x{self.value:04x} wIndex 0x{self.index:04x} wLength {self.length}")


@dataclass(frozen=True)
class EndpointSpec:
    address: int                  # 0x81 / 0x82 IN, 0x02 OUT
    kind: str = "bulk"            # "bulk" or "interrupt"
    interval: int = 0


SPEEDS = {"full": (12, 0x0200, 64), "high": (480, 0x0200, 512), "super": (5000, 0x0320, 1024)}


class EmulatedUsbDevice:
    """Base of an emulated device: descriptors from a small spec plus protocol hooks.

    Subclasses override ``control`` (vendor / class requests), ``bulk_out`` and ``bulk_in``;
    the base answers the standard requests (descriptors, strings, status, configuration).
    Hooks run on the bus's GLib worker thread: keep them short, guard shared state with
    ``self.lock``.
    """

    def __init__(self, vid: int, pid: int, *, bcd_device: int = 0x0100, serial: str = "00000001",
                 manufacturer: str = "evdnerf", product: str = "emulated device",
                 speed: str = "high", endpoints=(EndpointSpec(0x81), EndpointSpec(0x02)),
                 interface_class: int = 0xFF, max_power_ma: int = 500):
        if speed not in SPEEDS:
            raise ValueError(f"speed {speed!r}: use one of {', '.join(SPEEDS)}")
        self.vid, self.pid, self.bcd_device = int(vid), int(pid), int(bcd_device)
        self.serial, self.manufacturer, self.product = serial, manufacturer, product
        self.speed = speed
        self.endpoints = tuple(e if isinstance(e, EndpointSpec) else EndpointSpec(int(e))
                               for e in endpoints)
        self.interface_class = interface_class
        self.max_power_ma = max_power_ma
        self.lock = threading.RLock()
        self.unplugged = False
        self.bus: VirtualUsbBus | None = None
        self.devnode: str | None = None
        self.busnum = self.devnum = 0
        self.control_log: list[tuple[SetupPacket, bytes]] = []   # vendor/class requests seen

    # descriptors -------------------------------------------------------------------------
    def device_descriptor(self) -> bytes:
        _mbps, bcd_usb, mps = SPEEDS[self.speed]
        ep0 = 9 if self.speed == "super" else 64
        return struct.pack("<BBHBBBBHHHBBBB", 18, 1, bcd_usb, 0, 0, 0, ep0, self.vid, self.pid,
                           self.bcd_device, 1, 2, 3, 1)

    def config_descriptor(self) -> bytes:
        mps = SPEEDS[self.speed][2]
        eps = b""
        for e in self.endpoints:
            attr = 3 if e.kind == "interrupt" else 2
            eps += struct.pack("<BBBBHB", 7, 5, e.address, attr, mps, e.interval)
            if self.speed == "super":
                eps += struct.pack("<BBBBH", 6, 0x30, 15 if attr == 2 else 0, 0, 0)
        intf = struct.pack("<BBBBBBBBB", 9, 4, 0, 0, len(self.endpoints), self.interface_class,
                           0, 0, 0)
        total = 9 + len(intf) + len(eps)
        units = 8 if self.speed == "super" else 2
        conf = struct.pack("<BBHBBBBB", 9, 2, total, 1, 1, 0, 0x80,
                           min(255, self.max_power_ma // units))
        return conf + intf + eps

    def string_descriptor(self, index: int) -> bytes | None:
        if index == 0:
            return struct.pack("<BBH", 4, 3, 0x0409)
        text = {1: self.manufacturer, 2: self.product, 3: self.serial}.get(index)
        if text is None:
            return None
        raw = text.encode("utf-16-le")
        return bytes([2 + len(raw), 3]) + raw

    # request dispatch (called by the bus) -------------------------------------------------
    def handle_control(self, setup: SetupPacket, data: bytes):
        if setup.kind == "standard":
            return self._standard(setup, data)
        with self.lock:
            self.control_log.append((setup, bytes(data)))
        return self.control(setup, data)

    def _standard(self, setup: SetupPacket, data: bytes):
        req, dtype, idx = setup.request, setup.value >> 8, setup.value & 0xFF
        if req == 0x06 and setup.is_in:                       # GET_DESCRIPTOR
            if dtype == 1:
                return self.device_descriptor()
            if dtype == 2 and idx == 0:
                return self.config_descriptor()
            if dtype == 3:
                s = self.string_descriptor(idx)
                return STALL if s is None else s
            return STALL
        if req == 0x00 and setup.is_in:                       # GET_STATUS
            return b"\x00\x00"
        if req == 0x08 and setup.is_in:                       # GET_CONFIGURATION
            return b"\x01"
        if req == 0x0A and setup.is_in:                       # GET_INTERFACE
            return b"\x00"
        if req in (0x01, 0x03, 0x09, 0x0B) and not setup.is_in:  # features, config, interface
            return b""
        return STALL

    # hooks ------------------------------------------------------------------------------
    def control(self, setup: SetupPacket, data: bytes):
        """Vendor / class request: return the IN data (bytes), b"" / None for an OUT
        acknowledged, or STALL.  The base stalls everything."""
        return STALL

    def bulk_out(self, endpoint: int, data: bytes):
        """Bytes the host wrote to an OUT endpoint; return STALL to stall it."""
        return None

    def bulk_in(self, endpoint: int, max_len: int):
        """Bytes for a waiting IN transfer of up to ``max_len`` bytes, None when nothing is
        ready yet (the host will ask again), or STALL."""
        return None

    def unplug(self, *, reap_inflight: bool = True) -> None:
        """Simulate pulling the cable: every later ioctl of the host fails with ENODEV and
        its transfers end with LIBUSB_TRANSFER_NO_DEVICE.  ``reap_inflight=False``: the URBs
        in flight are never given back (a host that never reports them; libusb then never
        completes those transfers — what a driver's close() must survive)."""
        with self.lock:
            self.reap_inflight = bool(reap_inflight)
            self.unplugged = True


# --------------------------------------------------------------------------- the bus
class _Urb:
    __slots__ = ("data", "buf", "type", "endpoint", "length", "addr", "client")

    def __init__(self, data, buf, utype, endpoint, length, addr, client):
        self.data, self.buf, self.type = data, buf, utype
        self.endpoint, self.length, self.addr, self.client = endpoint, length, addr, client


class _ClientState:
    """Per-open-file state (one per process that opened the device node)."""

    def __init__(self, client):
        self.client = client
        self.done: collections.deque = collections.deque()       # (urb, status, actual)
        self.pending: dict[int, collections.deque] = {}          # endpoint -> IN URBs
        self.rr = 0


def set_timer_slack(ns: int = 1) -> bool:
    """prctl(PR_SET_TIMERSLACK, ns) for this process (inherited by children)."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        return libc.prctl(29, ctypes.c_ulong(ns), 0, 0, 0) == 0
    except (OSError, AttributeError):
        return False


class VirtualUsbBus:
    """A umockdev testbed serving emulated USB devices to child processes.

    ``bus.add(device)`` creates the sysfs entry and device node and attaches the ioctl
    handler; ``bus.env()`` is the environment a driver process needs; ``bus.close()`` (or
    the context manager) detaches everything.  Stop the driver processes first (pitfall 6).
    """

    def __init__(self, *, eagain_delay_s: float = 0.001):
        ok, why = umockdev_available()
        if not ok:
            raise RuntimeError(f"virtual USB unavailable: {why}")
        self._GLib, self._UM = _load_umockdev()
        self.testbed = self._UM.Testbed.new()
        self.root = self.testbed.get_root_dir()
        self.eagain_delay_s = float(eagain_delay_s)
        self.devices: list[EmulatedUsbDevice] = []
        self._handlers = []
        self._lock = threading.RLock()
        self._clients: dict[int, dict] = {}     # id(device) -> {client: _ClientState}
        self.ioctl_count = 0
        self.closed = False
        set_timer_slack(1)

    def __enter__(self) -> "VirtualUsbBus":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def env(self, base: dict | None = None) -> dict:
        """Environment for a driver process: LD_PRELOAD + UMOCKDEV_DIR (added to ``base``,
        default os.environ) and the longer transfer timeout of emulated devices."""
        env = dict(os.environ if base is None else base)
        pre = preload_path()
        old = env.get("LD_PRELOAD", "")
        env["LD_PRELOAD"] = pre + (":" + old if old and pre not in old else "")
        env["UMOCKDEV_DIR"] = self.root
        env.setdefault("EVDNERF_USB_TIMEOUT_MS", str(EMULATED_TIMEOUT_MS))   # rig.camera.device
        return env

    def add(self, device: EmulatedUsbDevice, busnum: int = 1) -> str:
        """Plug ``device`` in; returns its device node (/dev/bus/usb/BBB/DDD)."""
        with self._lock:
            devnum = 2 + len(self.devices)
            port = 1 + len(self.devices)
            name = f"{busnum}-{port}"
            devnode = f"/dev/bus/usb/{busnum:03d}/{devnum:03d}"
            mbps = SPEEDS[device.speed][0]
            attrs = {"busnum": str(busnum), "devnum": str(devnum),
                     "dev": f"189:{(busnum - 1) * 128 + devnum - 1}", "speed": str(mbps),
                     "idVendor": f"{device.vid:04x}", "idProduct": f"{device.pid:04x}",
                     "bcdDevice": f"{device.bcd_device:04x}", "bConfigurationValue": "1",
                     "bNumConfigurations": "1", "bNumInterfaces": " 1", "bDeviceClass": "00",
                     "serial": device.serial, "manufacturer": device.manufacturer,
                     "product": device.product, "maxchild": "0"}
            props = {"DEVNAME": devnode, "DEVTYPE": "usb_device", "SUBSYSTEM": "usb",
                     "DRIVER": "usb", "BUSNUM": f"{busnum:03d}", "DEVNUM": f"{devnum:03d}",
                     "ID_VENDOR_ID": f"{device.vid:04x}", "ID_MODEL_ID": f"{device.pid:04x}",
                     "ID_SERIAL_SHORT": device.serial,
                     "PRODUCT": f"{device.vid:x}/{device.pid:x}/{device.bcd_device:x}"}
            for k, v in (*attrs.items(), *props.items()):
                if any(c in v for c in "\n\\"):
                    raise ValueError(f"emulated USB device: {k}={v!r} must be one line")
            desc = (device.device_descriptor() + device.config_descriptor()).hex()
            syspath = f"/devices/pci0000:00/0000:00:14.0/usb{busnum}/{name}"
            text = (f"P: {syspath}\nN: {devnode[len('/dev/'):]}\n"
                    + "".join(f"E: {k}={v}\n" for k, v in props.items())
                    + "".join(f"A: {k}={v}\\n\n" for k, v in attrs.items())
                    + f"H: descriptors={desc}\n")
            self.testbed.add_from_string(text)
            handler = self._UM.IoctlBase()
            handler.connect("handle-ioctl", self._handle_ioctl, device)
            self.testbed.attach_ioctl(devnode, handler)
            device.bus, device.devnode, device.busnum, device.devnum = self, devnode, busnum, devnum
            device.syspath = "/sys" + syspath
            self.devices.append(device)
            self._handlers.append((devnode, handler))
            self._clients[id(device)] = {}
            return devnode

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        for devnode, _h in self._handlers:
            try:
                self.testbed.detach_ioctl(devnode)
            except Exception:
                pass
        self._handlers.clear()
        with self._lock:
            self._clients.clear()

    # ioctl handling (GLib worker thread) -----------------------------------------------
    def _state(self, device, client) -> _ClientState:
        clients = self._clients.setdefault(id(device), {})
        st = clients.get(client)
        if st is None:
            for c in [c for c in clients if not c.get_connected()]:
                del clients[c]                   # that process closed the node: forget its URBs
            st = clients[client] = _ClientState(client)
        return st

    def _handle_ioctl(self, _handler, client, device) -> bool:
        try:
            return self._dispatch(client, device)
        except Exception as exc:                 # never let an exception escape into GLib
            sys.stderr.write(f"virtual USB {device.devnode}: ioctl handler error: {exc!r}\n")
            client.complete(-1, errno.EIO)
            return True

    def _dispatch(self, client, device) -> bool:
        req = client.get_request()
        self.ioctl_count += 1
        with self._lock:
            st = self._state(device, client)
        if device.unplugged:
            return self._unplugged(client, req, st, device)
        if req in (USBDEVFS_REAPURBNDELAY, USBDEVFS_REAPURB):
            return self._reap(client, device, st)
        if req == USBDEVFS_SUBMITURB:
            return self._submit(client, device, st)
        if req == USBDEVFS_DISCARDURB:
            addr = struct.unpack("<Q", bytes(client.get_arg().retrieve())[:8])[0]
            with self._lock:
                for q in st.pending.values():
                    for u in q:
                        if u.addr == addr:
                            q.remove(u)
                            st.done.append((u, -errno.ENOENT, 0))
                            client.complete(0, 0)
                            return True
            client.complete(-1, errno.EINVAL)
            return True
        if req == USBDEVFS_GET_CAPABILITIES:
            data = client.get_arg().resolve(0, 4)
            data.update(0, struct.pack("<I", CAPABILITIES))
            client.complete(0, 0)
            return True
        if req == USBDEVFS_GETDRIVER:
            client.complete(-1, errno.ENODATA)
            return True
        if req in _SUCCEED:
            client.complete(0, 0)
            return True
        client.complete(-1, errno.ENOTTY)
        return True

    def _submit(self, client, device, st: _ClientState) -> bool:
        data = client.get_arg().resolve(0, URB_SIZE)
        raw = bytes(data.retrieve())
        utype, ep = raw[0], raw[1]
        length = struct.unpack_from("<i", raw, 24)[0]
        buf = data.resolve(16, length) if length > 0 else None
        urb = _Urb(data, buf, utype, ep, length, data.client_addr, client)
        if utype == URB_TYPE_CONTROL:
            payload = bytes(buf.retrieve()) if buf is not None else b""
            setup = SetupPacket.parse(payload[:8])
            reply = device.handle_control(setup, payload[8:8 + setup.length])
            if reply is STALL:
                result = (urb, -errno.EPIPE, 0)
            elif setup.is_in:
                out = bytes(reply or b"")[:max(0, min(setup.length, length - 8))]
                if out:
                    buf.update(8, out)
                result = (urb, 0, len(out))
            else:
                result = (urb, 0, setup.length)
            with self._lock:
                st.done.append(result)
        elif utype in (URB_TYPE_BULK, URB_TYPE_INTERRUPT) and not ep & 0x80:
            payload = bytes(buf.retrieve())[:length] if buf is not None else b""
            r = device.bulk_out(ep, payload)
            with self._lock:
                st.done.append((urb, -errno.EPIPE, 0) if r is STALL else (urb, 0, len(payload)))
        elif utype in (URB_TYPE_BULK, URB_TYPE_INTERRUPT):
            with self._lock:
                st.pending.setdefault(ep, collections.deque()).append(urb)
        else:
            client.complete(-1, errno.EINVAL)   # isochronous: not emulated
            return True
        client.complete(0, 0)
        return True

    def _unplugged(self, client, req, st: _ClientState, device=None) -> bool:
        """After an unplug: URBs already submitted are still reapable (capability "reap
        after disconnect"), waiting IN URBs ending with -ESHUTDOWN as the kernel does
        (libusb reports LIBUSB_TRANSFER_NO_DEVICE); every other ioctl, and a reap with
        nothing left, fails with ENODEV (that one after the EAGAIN delay: libusb's poll
        on a regular file never signals the disconnect, so it keeps reaping)."""
        if req not in (USBDEVFS_REAPURBNDELAY, USBDEVFS_REAPURB):
            client.complete(-1, errno.ENODEV)
            return True
        with self._lock:
            item = st.done.popleft() if st.done else None
            if item is None and getattr(device, "reap_inflight", True):
                for q in st.pending.values():
                    if q:
                        item = (q.popleft(), -errno.ESHUTDOWN, 0)
                        break
        if item is None:
            if self.eagain_delay_s > 0:
                time.sleep(self.eagain_delay_s)
            client.complete(-1, errno.ENODEV)
            return True
        return self._complete_reap(client, item)

    def _next_reapable(self, device, st: _ClientState):
        with self._lock:
            if st.done:
                return st.done.popleft()
            eps = [ep for ep, q in st.pending.items() if q]
        if not eps:
            return None
        n = len(eps)
        for i in range(n):                        # round robin over the IN endpoints
            ep = eps[(st.rr + i) % n]
            with self._lock:
                q = st.pending.get(ep)
                if not q:
                    continue
                urb = q[0]
            got = device.bulk_in(ep, urb.length)
            if got is None:
                continue
            with self._lock:
                if q and q[0] is urb:
                    q.popleft()
                else:                             # discarded meanwhile: keep the data? no URB
                    continue
            st.rr = (st.rr + i + 1) % n
            if got is STALL:
                return (urb, -errno.EPIPE, 0)
            got = bytes(got)[:urb.length]
            if got:
                urb.buf.update(0, got)
            return (urb, 0, len(got))
        return None

    def _reap(self, client, device, st: _ClientState) -> bool:
        item = self._next_reapable(device, st)
        if item is None and self.eagain_delay_s > 0:
            time.sleep(self.eagain_delay_s)       # pitfall 4: don't let libusb spin
            if device.unplugged:
                return self._unplugged(client, USBDEVFS_REAPURBNDELAY, st, device)
            item = self._next_reapable(device, st)
        if item is None:
            client.complete(-1, errno.EAGAIN)
            return True
        return self._complete_reap(client, item)

    def _complete_reap(self, client, item) -> bool:
        urb, status, actual = item
        urb.data.update(4, struct.pack("<i", status))
        urb.data.update(28, struct.pack("<i", actual))
        slot = client.get_arg().resolve(0, 8)
        slot.set_ptr(0, urb.data)
        client.complete(0, 0)
        return True


# --------------------------------------------------------------------------- children
def _child_preexec() -> None:
    set_timer_slack(1)


def _argv(code_or_argv) -> list[str]:
    if isinstance(code_or_argv, str):
        return [sys.executable, "-c", code_or_argv]
    return [str(a) for a in code_or_argv]


def spawn_child(code_or_argv, bus: VirtualUsbBus, *, env: dict | None = None, **popen_kw):
    """Start a driver process (python code or an argv) against ``bus``; returns the Popen.
    stdout / stderr are pipes (text) unless given."""
    popen_kw.setdefault("stdout", subprocess.PIPE)
    popen_kw.setdefault("stderr", subprocess.PIPE)
    popen_kw.setdefault("text", True)
    return subprocess.Popen(_argv(code_or_argv), env=bus.env(env), preexec_fn=_child_preexec,
                            **popen_kw)


def run_child(code_or_argv, bus: VirtualUsbBus, timeout: float = 60.0, *,
              env: dict | None = None, check: bool = False) -> subprocess.CompletedProcess:
    """Run a driver (python code or an argv) in a child process under the bus's preload and
    wait; the emulator keeps serving from this process meanwhile.  On timeout the child is
    killed and RuntimeError carries its output."""
    proc = spawn_child(code_or_argv, bus, env=env)
    try:
        out, err = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, err = proc.communicate()
        raise RuntimeError(f"virtual-USB child timed out after {timeout} s\n--- stdout\n{out}"
                           f"\n--- stderr\n{err}") from None
    res = subprocess.CompletedProcess(proc.args, proc.returncode, out, err)
    if check and res.returncode != 0:
        raise RuntimeError(f"virtual-USB child failed (exit {res.returncode})\n--- stdout\n{out}"
                           f"\n--- stderr\n{err}")
    return res
