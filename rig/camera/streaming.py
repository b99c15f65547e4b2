"""Lossless-or-counted bulk IN streaming on python-libusb1 async transfers.

``BulkStream(handle, endpoint, transfers=N, size=S, queue_chunks=Q)`` submits N bulk IN
transfers of S bytes on ``endpoint`` and runs a libusb event thread.  Each completed
transfer's bytes become a ``RawChunk`` (with its host arrival time) put into a bounded
``queue.Queue``; the transfer is resubmitted from the callback at once, so the device always
has N transfers waiting.  The event thread never blocks: when the consumer falls behind and
the queue is full, the chunk is dropped and counted (``stats.dropped_chunks`` /
``dropped_bytes``, and a warning at most once a second) — never silently.

An unplug (LIBUSB_TRANSFER_NO_DEVICE, or a transfer error) stops the resubmission; the
consumer's ``get()`` still returns every chunk received before it, then raises
``CameraDisconnected``.  A stalled endpoint ends the stream with ``CameraProtocolError``.

``close()`` never waits long for a device that is gone: libusb completes a transfer only when
it reaps it (or learns of the unplug from a poll error), and a gone device's transfers may
never be reaped (an emulated device node is a regular file, which never reports POLLERR; a
wedged host controller neither).  python-libusb1 would then wait for them forever (its handle
and transfer finalizers loop on ``handleEvents()`` while a transfer is in flight).  So once the
device is known gone (the stream failed with ``CameraDisconnected``, or cancelling a transfer
said "no device") the transfers get ``GONE_GRACE_S`` to be reaped; those still in flight are
*abandoned*: the event thread stops, ``abandoned`` counts them, and ``UsbLink.close()``
releases the handle without waiting for them (``rig.camera.device.UsbLink.abandon``).  The
event thread signals its exit with an Event (not ``Thread.join``: before CPython 3.13 a join
interrupted by Ctrl-C can report a still-running thread as stopped).
"""

from __future__ import annotations

import logging
import queue
import threading
import time

from .device import RawChunk, StreamStats, _usb1
from .errors import CameraDisconnected, CameraError, CameraProtocolError

log = logging.getLogger("rig.camera")

#: seconds between two "consumer too slow" warnings
WARN_INTERVAL_S = 1.0
#: seconds a gone device's cancelled transfers get to be reaped before they are abandoned
GONE_GRACE_S = 0.25


class BulkStream:
    def __init__(self, handle, endpoint: int, transfers: int = 8, size: int = 8192,
                 queue_chunks: int = 1024, *, context=None, stats: StreamStats | None = None,
                 name: str = "camera", event_timeout_s: float = 0.05):
        usb1 = _usb1()
        self._usb1 = usb1
        if not endpoint & 0x80:
            raise CameraError(f"{name}: BulkStream needs an IN endpoint, got 0x{endpoint:02x}")
        if transfers < 1 or size < 1 or queue_chunks < 1:
            raise CameraError(f"{name}: transfers ({transfers}), size ({size}) and queue_chunks "
                              f"({queue_chunks}) must be positive")
        self.handle, self.endpoint, self.name = handle, endpoint, name
        self.size = int(size)
        self.context = context if context is not None else handle._USBDeviceHandle__context
        self.stats = stats if stats is not None else StreamStats()
        self.queue: queue.Queue = queue.Queue(maxsize=int(queue_chunks))
        self._event_timeout = float(event_timeout_s)
        self._stopping = False
        self._abandon = False           # set by close(): the event thread exits even with transfers in flight
        self._gone = False              # a cancel said "no device"
        self.abandoned = 0              # transfers still in flight when close() gave up on them
        self._exited = threading.Event()     # set by the event thread as it exits
        self._failure: CameraError | None = None
        self._failure_seen = threading.Event()
        self._seq = 0
        self._last_warn = 0.0
        self._inflight = 0
        self._lock = threading.Lock()
        self._transfers = []
        self._ok = usb1.TRANSFER_COMPLETED
        self._no_device = usb1.TRANSFER_NO_DEVICE
        self._cancelled = usb1.TRANSFER_CANCELLED
        self._timed_out = usb1.TRANSFER_TIMED_OUT
        self._stall = usb1.TRANSFER_STALL
        self._overflow = usb1.TRANSFER_OVERFLOW
        try:
            for _ in range(int(transfers)):
                t = handle.getTransfer()
                t.setBulk(endpoint, self.size, callback=self._callback, timeout=0)
                self._transfers.append(t)
            for t in self._transfers:
                with self._lock:
                    self._inflight += 1
                try:
                    t.submit()
                except usb1.USBError:
                    with self._lock:
                        self._inflight -= 1
                    raise
        except Exception as exc:
            self._cancel_all()
            from .device import translate_usb_error
            raise translate_usb_error(exc, f"{name}: submitting bulk IN transfers on "
                                           f"0x{endpoint:02x}") from None
        self._thread = threading.Thread(target=self._events, name=f"libusb-events {name}",
                                        daemon=True)
        self._thread.start()

    # libusb event thread ----------------------------------------------------------------
    def _events(self) -> None:
        try:
            self._event_loop()
        finally:
            self._exited.set()

    def _event_loop(self) -> None:
        ctx = self.context
        while True:
            with self._lock:
                if self._abandon or ((self._stopping or self._failure is not None)
                                     and self._inflight == 0):
                    return
            try:
                ctx.handleEventsTimeout(self._event_timeout)
            except self._usb1.USBErrorInterrupted:
                continue
            except Exception as exc:           # the context itself failed: end the stream
                self._fail(CameraDisconnected(f"{self.name}: libusb event handling failed "
                                              f"({exc}); reopen the camera",
                                              chunks=self.stats.transfers,
                                              nbytes=self.stats.bytes))
                with self._lock:
                    self.abandoned = self._inflight     # libusb may still hold them
                    self._inflight = 0
                return

    def _callback(self, transfer) -> None:
        status = transfer.getStatus()
        if status == self._ok:
            n = transfer.getActualLength()
            if n:
                now = time.monotonic_ns()
                data = bytes(transfer.getBuffer()[:n])
                st = self.stats
                st.transfers += 1
                st.bytes += n
                self._seq += 1
                try:
                    self.queue.put_nowait(RawChunk(data, now, time.time_ns(), self._seq))
                    q = self.queue.qsize()
                    if q > st.queue_high_water:
                        st.queue_high_water = q
                except queue.Full:
                    st.dropped_chunks += 1
                    st.dropped_bytes += n
                    mono = now / 1e9
                    if mono - self._last_warn >= WARN_INTERVAL_S:
                        self._last_warn = mono
                        log.warning("%s: consumer too slow, dropped %d chunks (%d bytes) so far; "
                                    "read faster or raise queue_chunks", self.name,
                                    st.dropped_chunks, st.dropped_bytes)
            self._resubmit(transfer)
            return
        if status in (self._timed_out, self._overflow):
            if status == self._overflow:
                self.stats.errors += 1
            self._resubmit(transfer)
            return
        with self._lock:
            self._inflight -= 1
        if status == self._cancelled:
            if not self._stopping:      # cancelled by someone else: the device went away
                self._fail(CameraDisconnected(self._gone_msg("transfer cancelled"),
                                              chunks=self.stats.transfers, nbytes=self.stats.bytes))
            return
        self.stats.errors += 1
        if status == self._stall:
            self._fail(CameraProtocolError(f"{self.name}: bulk IN endpoint 0x{self.endpoint:02x} "
                                           "stalled; stop and restart the stream (or replug)"))
        elif status == self._no_device:
            self._fail(CameraDisconnected(self._gone_msg("no device"), chunks=self.stats.transfers,
                                          nbytes=self.stats.bytes))
        else:
            self._fail(CameraDisconnected(self._gone_msg(f"transfer error status {status}"),
                                          chunks=self.stats.transfers, nbytes=self.stats.bytes))
        self._cancel_all()

    def _resubmit(self, transfer) -> None:
        if self._stopping or self._failure is not None:
            with self._lock:
                self._inflight -= 1
            return
        try:
            transfer.submit()
        except self._usb1.USBError as exc:
            with self._lock:
                self._inflight -= 1
            from .device import translate_usb_error
            err = translate_usb_error(exc, f"{self.name}: resubmitting bulk IN 0x{self.endpoint:02x}")
            why = "no device on resubmit" if isinstance(err, CameraDisconnected) else str(err)
            self._fail(CameraDisconnected(self._gone_msg(why), chunks=self.stats.transfers,
                                          nbytes=self.stats.bytes))
            self._cancel_all()

    def _gone_msg(self, why: str) -> str:
        return (f"{self.name}: the camera was unplugged (disconnected mid-stream: {why}) after "
                f"{self.stats.transfers} transfers / {self.stats.bytes} bytes; everything "
                "received before was delivered; plug it in again and reopen it")

    def _fail(self, err: CameraError) -> None:
        if self._failure is None:
            self._failure = err
            self._failure_seen.set()

    def _cancel_all(self) -> None:
        no_device = self._usb1.USBErrorNoDevice
        for t in self._transfers:
            try:
                if t.isSubmitted():
                    t.cancel()
            except no_device:
                self._gone = True
            except Exception:
                pass

    # consumer side ----------------------------------------------------------------------
    @property
    def failed(self) -> CameraError | None:
        return self._failure

    def get(self, timeout_s: float | None = 1.0) -> RawChunk | None:
        """The next chunk; None after ``timeout_s`` with nothing received (an idle stream
        is not an error); after a disconnect, the chunks still queued, then the error."""
        try:
            return self.queue.get_nowait()
        except queue.Empty:
            pass
        deadline = None if timeout_s is None else time.monotonic() + max(0.0, timeout_s)
        while True:
            if self._failure is not None:
                try:
                    return self.queue.get_nowait()
                except queue.Empty:
                    raise self._failure from None
            wait = 0.05 if deadline is None else min(0.05, deadline - time.monotonic())
            if wait <= 0:
                return None
            try:
                return self.queue.get(timeout=wait)
            except queue.Empty:
                continue

    @property
    def device_gone(self) -> bool:
        """True once the stream ended by a disconnect or a cancel found no device."""
        return self._gone or isinstance(self._failure, CameraDisconnected)

    @property
    def running(self) -> bool:
        """The libusb event thread has not exited yet."""
        return not self._exited.is_set()

    def close(self, timeout_s: float = 2.0) -> None:
        """Cancel the transfers, wait until libusb has reaped them all, stop the thread.

        A live device's transfers get ``timeout_s``; a gone device's ``GONE_GRACE_S``, then
        the ones still in flight are abandoned (counted in ``abandoned``; see the module
        docstring).  Safe to call again after an interruption (Ctrl-C): the thread's exit is
        an Event, not ``Thread.join``."""
        if self._exited.is_set():
            self._stopping = True
            return
        if self._abandon:                       # an interrupted close(): just let the thread go
            self._exited.wait(max(0.2, 4 * self._event_timeout))
            return
        self._stopping = True
        self._cancel_all()
        t0 = time.monotonic()
        try:
            while not self._exited.wait(0.01):
                waited = time.monotonic() - t0
                if waited >= timeout_s or (self.device_gone and waited >= GONE_GRACE_S):
                    break
        finally:
            if not self._exited.is_set():
                with self._lock:
                    left = self._inflight
                self.abandoned = max(left, 1)
                self._abandon = True            # the thread leaves after its current poll
        if not self.abandoned:
            return
        self._exited.wait(max(0.2, 4 * self._event_timeout))
        log.warning("%s: %d bulk transfers of a %s device not reaped %.2f s after cancelling; "
                    "abandoned (their handle is released without waiting)", self.name, self.abandoned,
                    "gone" if self.device_gone else "silent", time.monotonic() - t0)

    def __enter__(self) -> "BulkStream":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
