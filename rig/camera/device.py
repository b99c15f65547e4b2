"""The camera driver base class and its shared pieces.

``Device`` is what every model module (``rig.camera.dvxplorer.DVXplorer``,
``rig.camera.evk4.EVK4``) subclasses.  It owns what is the same for every camera:

* the life cycle: ``open()`` / ``close()`` / context manager, ``start()`` / ``stop()``;
* the byte stream: a ``BulkStream`` (rig.camera.streaming: N queued async bulk IN
  transfers into a bounded queue) read with ``read_raw()``, and ``read()`` which passes the
  bytes to the model's decoder hook ``_decode(data) -> (events, triggers)``;
* the sensor-clock -> host-clock mapping ``clock`` (a ``rig.clock.ClockMap`` fitted from
  (sensor time, host arrival time) pairs, one per decoded chunk, by the lower envelope of
  the arrival latency);
* the stream statistics ``stats`` (transfers, bytes, drops, queue high water);
* ``UsbLink``: one python-libusb1 handle per camera (control transfers, synchronous bulk
  register traffic and the streaming transfers all go through it: usbfs claims an
  interface per open file, so a second library opening the same device would collide on
  real hardware), with libusb errors translated into the typed errors of
  ``rig.camera.errors``.

Host times: ``host_ns`` is ``time.monotonic_ns()`` (the clock the servo client stamps its
reports with, so camera and servo times share one host clock), ``wall_ns`` is
``time.time_ns()`` (what bag message stamps use).
"""

from __future__ import annotations

import abc
import collections
import errno as _errno
import os
import threading
import time
import weakref
from dataclasses import dataclass, field

import numpy as np

from evdnerf_ros.events.types import EVENT_DTYPE, TRIGGER_DTYPE
from rig.clock import ClockMap, fit_clock_map

from .errors import (CameraDisconnected, CameraError, CameraNotFound, CameraPermissionError,
                     CameraProtocolError, CameraTimeout)

#: (sensor_us, host_ns) samples kept for the clock fit (a sliding window).
CLOCK_SAMPLES = 4096
#: Timeout (ms) of one control or register transfer. A real camera answers in microseconds; an
#: emulated one is served by a Python process that may be busy rendering, so the virtual bus
#: gives its drivers a longer one through EVDNERF_USB_TIMEOUT_MS (rig.camera.virtual.usb).
TRANSFER_TIMEOUT_MS = int(os.environ.get("EVDNERF_USB_TIMEOUT_MS", "1000"))

#: python-libusb1 objects of links closed with abandoned transfers (a gone device never returned
#: them): kept referenced for the life of the process, so nothing frees memory libusb was given.
_ABANDONED: list = []


@dataclass(frozen=True)
class RawChunk:
    """One bulk IN transfer's bytes, exactly as the sensor sent them."""
    data: bytes
    host_ns: int          # time.monotonic_ns() when the transfer completed
    wall_ns: int          # time.time_ns() at the same moment
    seq: int              # transfer completion counter (gaps = dropped chunks)


#: the one event a model's ``_sample_words`` encodes (sensor time 1 us, pixel 0, 0, ON)
SAMPLE_EVENT = np.array([(1000, 0, 0, 1)], EVENT_DTYPE)


@dataclass(frozen=True)
class EventChunk:
    """The decoded content of one RawChunk: events (EVENT_DTYPE, sensor ns from the
    sensor's zero, unwrapped) and trigger edges (TRIGGER_DTYPE)."""
    events: np.ndarray
    triggers: np.ndarray
    host_ns: int
    wall_ns: int
    seq: int
    raw: bytes            # the bytes the events came from (for raw pass-through recording)
    #: the stream decoder's state before this chunk (model specific; () for encodings whose
    #: transfers stand alone): ``Device.resume_words(chunk)`` turns it into the words that let a
    #: reader start decoding at this chunk, as a recording cut from a running stream must
    decoder_state: tuple = ()


@dataclass
class StreamStats:
    transfers: int = 0          # completed bulk IN transfers with data
    bytes: int = 0              # bytes received (delivered + dropped)
    dropped_chunks: int = 0     # chunks dropped because the consumer's queue was full
    dropped_bytes: int = 0
    queue_high_water: int = 0   # most chunks ever waiting in the queue
    events: int = 0             # decoded by read()
    triggers: int = 0
    errors: int = 0             # transfers that completed with an error status
    started_ns: int = field(default_factory=time.monotonic_ns)

    def as_dict(self) -> dict:
        return {k: getattr(self, k) for k in self.__dataclass_fields__}


def _usb1():
    try:
        import usb1
    except ImportError as exc:  # pragma: no cover - dependency of the package
        raise CameraError("python-libusb1 is not installed: pip install 'libusb1>=3.1' "
                          f"(or pip install -e . in the checkout) [{exc}]") from None
    return usb1


def translate_usb_error(exc: BaseException, what: str) -> CameraError:
    """Map a python-libusb1 ``usb1.USBError`` or a pyusb ``usb.core.USBError`` to the
    camera error it means; ``what`` names the device and the request."""
    code = getattr(exc, "value", None)          # usb1: negative LIBUSB_ERROR_*
    err = getattr(exc, "errno", None)           # pyusb: errno
    backend = getattr(exc, "backend_error_code", None)
    if code is None and backend is not None:
        code = backend
    name = {-1: "IO", -2: "INVALID_PARAM", -3: "ACCESS", -4: "NO_DEVICE", -5: "NOT_FOUND",
            -6: "BUSY", -7: "TIMEOUT", -8: "OVERFLOW", -9: "PIPE", -10: "INTERRUPTED",
            -11: "NO_MEM", -12: "NOT_SUPPORTED"}.get(code)
    if name == "ACCESS" or err == _errno.EACCES:
        return CameraPermissionError(what, str(exc))
    if name == "NO_DEVICE" or err == _errno.ENODEV:
        return CameraDisconnected(f"{what}: the camera was unplugged (no device); plug it in "
                                  "again and reopen it")
    if name == "PIPE" or err == _errno.EPIPE:
        return CameraProtocolError(f"{what}: the camera stalled the request (unsupported "
                                   "request or register for this firmware); check the "
                                   "firmware version and the request code")
    if name == "TIMEOUT" or err == _errno.ETIMEDOUT or err == 110:
        return CameraTimeout(f"{what}: no reply in time; check the cable and that no other "
                             "program uses the camera")
    if name == "BUSY" or err == _errno.EBUSY:
        return CameraError(f"{what}: the device is busy (claimed by another program or "
                           "kernel driver); close the other program")
    return CameraError(f"{what}: USB error {exc}")


class UsbLink:
    """One opened USB camera through python-libusb1 (interface claimed).

    ``UsbLink.open(ids, serial=None)`` opens the first device whose (vid, pid) is in ``ids``
    (and whose serial string matches when given)."""

    def __init__(self, context, handle, device, name: str, interface: int = 0):
        self.context, self.handle, self.device = context, handle, device
        self.name = name
        self.interface = interface
        self.vid = device.getVendorID()
        self.pid = device.getProductID()
        self.bcd_device = device.getbcdDevice()
        self._closed = False
        self._abandoned: list = []      # streams that gave up on transfers (see abandon())

    @classmethod
    def open(cls, ids, serial: str | None = None, *, interface: int = 0,
             configuration: int | None = 1, what: str = "camera") -> "UsbLink":
        usb1 = _usb1()
        ids = {(int(v), int(p)) for v, p in ids}
        ctx = usb1.USBContext()
        ctx.open()
        seen, denied = [], None
        try:
            for dev in ctx.getDeviceIterator(skip_on_error=True):
                if (dev.getVendorID(), dev.getProductID()) not in ids:
                    dev.close()
                    continue
                where = f"{what} {dev.getVendorID():04x}:{dev.getProductID():04x} at bus " \
                        f"{dev.getBusNumber():03d} device {dev.getDeviceAddress():03d}"
                try:
                    handle = dev.open()
                except usb1.USBError as exc:
                    e = translate_usb_error(exc, where)
                    if isinstance(e, CameraPermissionError):
                        denied = e
                        continue
                    raise e from None
                try:
                    sn = handle.getSerialNumber() or ""
                except usb1.USBError:
                    sn = ""
                if serial is not None and sn != serial:
                    seen.append(sn)
                    handle.close()
                    continue
                try:
                    if configuration is not None:
                        try:
                            if handle.getConfiguration() != configuration:
                                handle.setConfiguration(configuration)
                        except usb1.USBError:
                            handle.setConfiguration(configuration)
                    handle.claimInterface(interface)
                except usb1.USBError as exc:
                    handle.close()
                    raise translate_usb_error(exc, f"{where}: claiming interface {interface}") from None
                return cls(ctx, handle, dev, f"{where} serial {sn or '?'}", interface)
        except BaseException:
            ctx.close()
            raise
        ctx.close()
        if denied is not None:
            raise denied
        if serial is not None and seen:
            raise CameraNotFound(f"no {what} with serial {serial!r}; connected: "
                                 f"{', '.join(repr(s) for s in seen)}; pass one of those")
        raise CameraNotFound(f"no {what} found (USB ids "
                             f"{', '.join(f'{v:04x}:{p:04x}' for v, p in sorted(ids))}); plug it "
                             "in, check `lsusb`, or use a virtual twin (--virtual MODEL)")

    # control transfers -------------------------------------------------------------
    def control_in(self, request_type: int, request: int, value: int, index: int, length: int,
                   timeout_ms: int | None = None, what: str = "") -> bytes:
        try:
            return bytes(self.handle.controlRead(request_type, request, value, index, length,
                                                 timeout_ms or TRANSFER_TIMEOUT_MS))
        except Exception as exc:
            raise self._error(exc, what or f"control IN 0x{request:02x} value 0x{value:04x} "
                                            f"index 0x{index:04x}") from None

    def control_out(self, request_type: int, request: int, value: int, index: int, data: bytes = b"",
                    timeout_ms: int | None = None, what: str = "") -> int:
        try:
            return self.handle.controlWrite(request_type, request, value, index, bytes(data),
                                            timeout_ms or TRANSFER_TIMEOUT_MS)
        except Exception as exc:
            raise self._error(exc, what or f"control OUT 0x{request:02x} value 0x{value:04x} "
                                            f"index 0x{index:04x}") from None

    # synchronous bulk (register traffic) ---------------------------------------------
    def bulk_write(self, endpoint: int, data: bytes, timeout_ms: int | None = None, what: str = "") -> int:
        try:
            return self.handle.bulkWrite(endpoint, bytes(data), timeout_ms or TRANSFER_TIMEOUT_MS)
        except Exception as exc:
            raise self._error(exc, what or f"bulk OUT 0x{endpoint:02x}") from None

    def bulk_read(self, endpoint: int, length: int, timeout_ms: int | None = None, what: str = "") -> bytes:
        try:
            return bytes(self.handle.bulkRead(endpoint, length, timeout_ms or TRANSFER_TIMEOUT_MS))
        except Exception as exc:
            raise self._error(exc, what or f"bulk IN 0x{endpoint:02x}") from None

    def _error(self, exc, what) -> Exception:
        usb1 = _usb1()
        if isinstance(exc, (usb1.USBError,)) or hasattr(exc, "errno"):
            return translate_usb_error(exc, f"{self.name}: {what}")
        return exc

    def abandon(self, stream) -> None:
        """``stream`` (a closed BulkStream) gave up on transfers that a gone device never
        returned: close() must then release the handle without waiting for them."""
        self._abandoned.append(stream)

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        if self._abandoned:
            self._close_abandoned()
            return
        try:
            try:
                self.handle.releaseInterface(self.interface)
            except Exception:
                pass
            self.handle.close()
        finally:
            self.context.close()

    def _close_abandoned(self) -> None:
        """Close a handle whose transfers libusb will never complete, without waiting.

        python-libusb1's ``USBDeviceHandle.close()`` (and each transfer's finalizer, also at
        interpreter exit) loops on ``handleEvents()`` until every transfer completes: forever
        here.  So its finalizers are detached and ``libusb_close()`` is called directly: libusb
        then drops the handle's transfers from its in-flight list (they never call back) and
        closes the device node.  The transfer objects (and their buffers) stay referenced in
        ``_ABANDONED``; then the context is closed as usual.  If the event thread of a stream
        is still running, or python-libusb1 is not shaped as expected, nothing is freed: the
        objects are parked and their finalizers detached (a bounded leak, never a hang)."""
        handle, ctx = self.handle, self.context
        _ABANDONED.append((ctx, handle, self.device, tuple(self._abandoned)))
        try:
            handle.releaseInterface(self.interface)
        except Exception:
            pass
        for f in list(getattr(handle, "_finalizer_dict", {}).values()):    # the transfers'
            if isinstance(f, weakref.finalize):
                f.detach()
        fin = getattr(handle, "close", None)
        peeked = fin.peek() if isinstance(fin, weakref.finalize) else None   # (obj, func, args, kw)
        kw = getattr(peeked[1], "keywords", None) if peeked else None
        kw = kw if isinstance(kw, dict) else {}
        inner = kw.get("kw") or {}
        threads_done = not any(getattr(s, "running", False) for s in self._abandoned)
        if (isinstance(fin, weakref.finalize) and callable(inner.get("libusb_close"))
                and inner.get("handle") is not None and threads_done):
            fin.detach()
            try:
                kw["pop"](kw["handle"])          # the context's finalizer must not close it again
            except (KeyError, TypeError):
                pass
            inner["libusb_close"](inner["handle"])
            dev = inner.get("device")
            if dev is not None:
                try:
                    dev.close()
                except Exception:
                    pass
            self.context.close()
            return
        for obj in (fin, getattr(ctx, "_USBContext__close", None)):   # park everything
            if isinstance(obj, weakref.finalize):
                obj.detach()


class Device(abc.ABC):
    """Abstract event camera; one subclass per model.

    Subclasses set the class attributes and implement the hooks:

    * ``_open()``: open the USB device (``self.link = UsbLink.open(...)`` usually), read the
      identity (``serial``, ``firmware_version``, ``logic_version``), check versions, bring
      the sensor to a known, stopped state;
    * ``_close()``: release everything ``_open`` took (the base closes ``self.link``);
    * ``_make_stream()`` -> BulkStream (default: ``self.link`` on ``DATA_ENDPOINT`` with
      ``TRANSFERS`` x ``TRANSFER_SIZE``);
    * ``_start_hardware()`` (after the transfers are queued) / ``_stop_hardware()``;
    * ``_reset_decoder()`` and ``_decode(data) -> (events, triggers)`` (streaming decoder
      carrying state across chunks, times in int64 sensor ns unwrapped from the sensor's
      zero); ``_sample_words()`` -> a one-event sample the decoder is warmed with
      (:meth:`warm_up`); optional ``_sensor_time_ns()`` -> the newest sensor time the decoder
      has seen (time words included), used for the clock samples; optional ``_decoder_state()`` and
      ``resume_words(chunk)`` where a recording cut from a running stream needs its decoder's
      state first (EVT 3.0);
    * optional ``THRESHOLD_MODEL`` / ``contrast_thresholds(biases)``: the model's bias ->
      contrast-threshold function, shared with the model's twin;
    * ``biases`` / ``set_biases`` / ``roi`` / ``set_roi`` / ``clear_roi`` /
      ``enable_trigger_input``.
    """

    model: str = ""
    encoding: str = ""           # EventPacket encoding of the raw bytes ("evt3", "libcaer")
    width: int = 0
    height: int = 0
    USB_IDS: tuple[tuple[int, int], ...] = ()
    DATA_ENDPOINT: int = 0x82
    TRANSFERS: int = 8
    TRANSFER_SIZE: int = 8192
    QUEUE_CHUNKS: int = 4096

    def __init__(self, serial: str | None = None, *, transfers: int | None = None,
                 transfer_size: int | None = None, queue_chunks: int | None = None):
        self.requested_serial = serial
        self.serial: str = serial or ""
        self.firmware_version: int = 0
        self.logic_version: int | None = None
        self.link: UsbLink | None = None
        self.transfers = int(transfers or self.TRANSFERS)
        self.transfer_size = int(transfer_size or self.TRANSFER_SIZE)
        self.queue_chunks = int(queue_chunks or self.QUEUE_CHUNKS)
        self.stats = StreamStats()
        self._stream = None
        self._is_open = False
        self._clock_lock = threading.Lock()
        self._clock_samples: collections.deque = collections.deque(maxlen=CLOCK_SAMPLES)
        self._clock: ClockMap | None = None
        self._clock_dirty = False
        self._last_sensor_ns: int | None = None

    # life cycle ------------------------------------------------------------------------
    @property
    def name(self) -> str:
        return f"{self.model} {self.serial or '(serial unknown)'}"

    @property
    def is_open(self) -> bool:
        return self._is_open

    @property
    def is_streaming(self) -> bool:
        return self._stream is not None

    def open(self) -> "Device":
        if self._is_open:
            return self
        try:
            self._open()
        except BaseException:
            self._release_link()
            raise
        self._is_open = True
        return self

    def close(self) -> None:
        if not self._is_open and self.link is None:
            return
        try:
            if self._stream is not None:
                try:
                    self.stop()
                except CameraDisconnected:
                    pass
            try:
                self._close()
            except CameraDisconnected:
                pass
        finally:
            self._release_link()
            self._is_open = False

    def _release_link(self) -> None:
        if self.link is not None:
            link, self.link = self.link, None
            link.close()

    def __enter__(self) -> "Device":
        return self.open()

    def __exit__(self, *exc) -> None:
        self.close()

    def _need_open(self, what: str) -> None:
        if not self._is_open:
            raise CameraError(f"{self.name}: {what} needs an opened camera; call open() first "
                              "(or use the camera as a context manager)")

    def start(self) -> None:
        """Queue the bulk transfers, then start the sensor (the libcaer order: the
        transfers are waiting before the first byte is produced)."""
        self._need_open("start()")
        if self._stream is not None:
            return
        self.stats = StreamStats()
        self.warm_up()                  # ends with a fresh decoder
        with self._clock_lock:
            self._clock_samples.clear()
            self._clock, self._clock_dirty = None, False
        self._last_sensor_ns = None
        self._stream = self._make_stream()
        try:
            self._start_hardware()
        except BaseException:
            stream, self._stream = self._stream, None
            self._close_stream(stream)
            raise

    def stop(self) -> None:
        """Stop the sensor, then cancel and reap the transfers.  Chunks still waiting in
        the queue are discarded: read them before stop()."""
        if self._stream is None:
            return
        stream, self._stream = self._stream, None
        try:
            self._stop_hardware()
        finally:
            self._close_stream(stream)

    def _close_stream(self, stream) -> None:
        try:
            stream.close()
        finally:
            if getattr(stream, "abandoned", 0) and self.link is not None:
                self.link.abandon(stream)        # a gone device kept transfers: don't wait on close

    # byte and event streams -----------------------------------------------------------
    def read_raw(self, timeout_s: float = 1.0) -> RawChunk | None:
        """The next chunk of bytes as the sensor sent them, or None after ``timeout_s`` of
        idle stream.  Raises CameraDisconnected after an unplug, once every chunk received
        before it has been returned."""
        if self._stream is None:
            raise CameraError(f"{self.name}: read before start(); call start() first")
        return self._stream.get(timeout_s)

    def read(self, timeout_s: float = 1.0) -> EventChunk | None:
        """The next decoded chunk (events + trigger edges), or None on an idle timeout."""
        raw = self.read_raw(timeout_s)
        if raw is None:
            return None
        return self.decode_chunk(raw)

    def decode_chunk(self, raw: RawChunk) -> EventChunk:
        state = self._decoder_state()
        events, triggers = self._decode(raw.data)
        if events.dtype != EVENT_DTYPE or triggers.dtype != TRIGGER_DTYPE:
            raise CameraProtocolError(f"{self.name}: the decoder returned {events.dtype} / "
                                      f"{triggers.dtype}, not EVENT_DTYPE / TRIGGER_DTYPE")
        self.stats.events += len(events)
        self.stats.triggers += len(triggers)
        t = self._sensor_time_ns()
        if t is None:
            cands = [int(a["t"][-1]) for a in (events, triggers) if len(a)]
            t = max(cands) if cands else None
        if t is not None:
            self.add_clock_sample(t, raw.host_ns)
        return EventChunk(events, triggers, raw.host_ns, raw.wall_ns, raw.seq, raw.data, state)

    def resume_words(self, chunk: EventChunk) -> bytes:
        """Bytes in this camera's encoding, holding no event, that put a decoder starting at
        ``chunk`` into the state the stream's own decoder had before it: what a recording
        cut from a running stream begins with. b"" where every transfer stands alone."""
        return b""

    # clock -------------------------------------------------------------------------------
    def add_clock_sample(self, sensor_ns: int, host_ns: int) -> None:
        """One (sensor time, host arrival time) pair; a sensor time that goes backwards (a
        timestamp reset) starts a new fit."""
        with self._clock_lock:
            if self._last_sensor_ns is not None and sensor_ns < self._last_sensor_ns:
                self._clock_samples.clear()
                self._clock = None
            self._last_sensor_ns = sensor_ns
            self._clock_samples.append((sensor_ns / 1000.0, host_ns))
            self._clock_dirty = True

    @property
    def sensor_time_ns(self) -> int | None:
        """The latest sensor time the stream has reached (None before the first timed chunk)."""
        with self._clock_lock:
            return self._last_sensor_ns

    @property
    def clock(self) -> ClockMap:
        """host_ns (time.monotonic_ns) of a sensor time: ``clock.sensor_ns_to_host_ns(t)``."""
        with self._clock_lock:
            if self._clock is None or self._clock_dirty:
                if len(self._clock_samples) < 2:
                    raise CameraError(f"{self.name}: no clock mapping yet ({len(self._clock_samples)} "
                                      "samples); read() events for a moment first")
                s = np.array(self._clock_samples, dtype=np.float64)
                self._clock = fit_clock_map(s[:, 0], s[:, 1], one_sided=True,
                                            source=f"{self.name} clock samples")
                self._clock_dirty = False
            return self._clock

    # stream construction -----------------------------------------------------------------
    def _make_stream(self):
        from .streaming import BulkStream
        if self.link is None:
            raise CameraError(f"{self.name}: no USB link; the model's _open() must set self.link")
        return BulkStream(self.link.handle, self.DATA_ENDPOINT, transfers=self.transfers,
                          size=self.transfer_size, queue_chunks=self.queue_chunks,
                          stats=self.stats, name=self.name)

    # helpers for subclasses -----------------------------------------------------------
    def check_bias_names(self, biases: dict, valid) -> None:
        unknown = sorted(set(biases) - set(valid))
        if unknown:
            raise CameraError(f"{self.name}: unknown bias {', '.join(unknown)}; valid biases: "
                              f"{', '.join(sorted(valid))}")

    def check_roi(self, x: int, y: int, w: int, h: int) -> tuple[int, int, int, int]:
        vals = tuple(int(v) for v in (x, y, w, h))
        x, y, w, h = vals
        if w <= 0 or h <= 0 or x < 0 or y < 0 or x + w > self.width or y + h > self.height:
            raise CameraError(f"{self.name}: ROI x={x} y={y} w={w} h={h} is outside the "
                              f"{self.width}x{self.height} sensor; use 0 <= x, x+w <= "
                              f"{self.width}, 0 <= y, y+h <= {self.height}, w, h > 0")
        return vals

    # hooks -----------------------------------------------------------------------------
    @abc.abstractmethod
    def _open(self) -> None: ...

    def _close(self) -> None:
        """Release model state; the base closes ``self.link`` afterwards."""

    @abc.abstractmethod
    def _start_hardware(self) -> None: ...

    @abc.abstractmethod
    def _stop_hardware(self) -> None: ...

    @abc.abstractmethod
    def _reset_decoder(self) -> None: ...

    @abc.abstractmethod
    def _decode(self, data: bytes) -> tuple[np.ndarray, np.ndarray]: ...

    def _sensor_time_ns(self) -> int | None:
        return None

    def _sample_words(self) -> bytes:
        """A few bytes of this model's stream holding one event (its own word encoder's output),
        for :meth:`warm_up`; b"" where there is nothing to warm."""
        return b""

    def warm_up(self) -> None:
        """Decode a one-event sample (:meth:`_sample_words`) with a throwaway decoder, then start a
        fresh one. The decoder's compiled kernels load on their first call in a process: ~0.5 s,
        seconds on a loaded machine, which must not fall inside a recording's first transfers
        (the window is wall time: it would lose that much of the stream). :meth:`start` calls it;
        cheap once loaded."""
        sample = self._sample_words()
        if sample:
            self._reset_decoder()
            self._decode(sample)
        self._reset_decoder()

    def _decoder_state(self) -> tuple:
        """The stream decoder's state that :meth:`resume_words` needs (() where none)."""
        return ()

    #: where :meth:`contrast_thresholds` comes from ("module.function"); None: no model
    THRESHOLD_MODEL: str | None = None

    def contrast_thresholds(self, biases: dict) -> tuple[float, float] | None:
        """(C_on, C_off) contrast thresholds (log intensity) this model's pixels have with
        ``biases`` (as :attr:`biases` reads them); None for a driver without a bias ->
        threshold model. Needs no device: a session computes it for any biases it recorded."""
        return None

    @property
    @abc.abstractmethod
    def biases(self) -> dict[str, int]: ...

    @abc.abstractmethod
    def set_biases(self, biases: dict[str, int]) -> None: ...

    @property
    @abc.abstractmethod
    def roi(self) -> tuple[int, int, int, int] | None: ...

    @abc.abstractmethod
    def set_roi(self, x: int, y: int, w: int, h: int) -> None: ...

    @abc.abstractmethod
    def clear_roi(self) -> None: ...

    @abc.abstractmethod
    def enable_trigger_input(self, enabled: bool = True) -> None: ...
