"""Serial client of the servo-rig firmware (protocol: firmware/PROTOCOL.md).

``ServoClient(port)`` opens a real port (``/dev/ttyACM0``) or the virtual Arduino's pty,
waits for the firmware (an Uno resets when the port opens), checks the protocol version
with ``HELLO``, and then sends one command at a time, tagged ``@<seq>`` so a late reply to
an earlier, timed-out command can never be taken for the current one.  A background thread
reads every line: tagged replies go to the waiting command, ``START`` / ``DONE`` /
``STOPPED`` / ``BOOT`` reports go to an event queue with their host receive time.

Device time is the firmware's ``micros()`` (uint32, unwrapped here).  ``sync_clock()`` sends
timestamped pings and fits ``host_ns = offset_ns + scale * device_us`` by least squares
(offset and drift); ``device_to_host_ns`` then maps START / DONE times onto the host clock.
"""

from __future__ import annotations

import itertools
import queue
import threading
import time
from dataclasses import dataclass, field

import numpy as np

from evdnerf_ros.errors import EvdnerfError
from evdnerf_ros.sim.servo_profile import RunProfile

PROTOCOL_VERSION = 1
FIRMWARE_NAME = "rig_servo"
BAUDRATE = 115200


class ServoError(EvdnerfError):
    """Base of the servo client's errors."""


class ServoPortError(ServoError):
    """The serial port cannot be opened (missing, busy, no permission) or was lost."""


class ServoTimeout(ServoError):
    """No reply (or report) within the timeout, retries included."""


class ServoProtocolError(ServoError):
    """The device does not speak this protocol (wrong firmware, wrong version, bad reply)."""


class ServoCommandError(ServoError):
    """The firmware answered ERR; ``code`` is its error code (BUSY, OUT_OF_RANGE, ...)."""

    def __init__(self, command: str, code: str, reason: str):
        super().__init__(f"servo refused `{command}`: {code} {reason}".rstrip())
        self.command, self.code, self.reason = command, code, reason


@dataclass(frozen=True)
class Reply:
    words: list[str]
    host_send_ns: int
    host_recv_ns: int


@dataclass(frozen=True)
class Event:
    """An unsolicited report: kind START / DONE / STOPPED / BOOT."""
    kind: str
    motion: str
    device_us: int | None      # unwrapped device microseconds (None for BOOT)
    host_recv_ns: int
    words: tuple[str, ...] = ()


@dataclass(frozen=True)
class Motion:
    start: Event
    end: Event

    @property
    def duration_us(self) -> int:
        return self.end.device_us - self.start.device_us


@dataclass(frozen=True)
class ClockMap:
    """host_ns = offset_ns + scale * (device_us - device_ref_us); fitted from pings."""
    offset_ns: float
    scale: float                # host ns per device us (1000 for a perfect clock)
    device_ref_us: int
    residual_ns: float          # RMS residual of the fit
    samples: int

    @property
    def drift_ppm(self) -> float:
        return (self.scale / 1000.0 - 1.0) * 1e6

    def to_host_ns(self, device_us) -> np.ndarray | int:
        d = np.asarray(device_us, dtype=np.float64) - self.device_ref_us
        out = np.rint(self.offset_ns + self.scale * d).astype(np.int64)
        return int(out) if out.ndim == 0 else out


@dataclass(frozen=True)
class Limits:
    min_deg: float
    max_deg: float
    max_speed_dps: int
    pulse_min_us: int
    pulse_max_us: int


@dataclass
class _Pending:
    seq: int
    event: threading.Event = field(default_factory=threading.Event)
    line: str | None = None
    recv_ns: int = 0


def _deg(x: float) -> str:
    """Degrees with at most 3 decimals, as the firmware parses them."""
    mdeg = round(float(x) * 1000)
    if abs(float(x) * 1000 - mdeg) > 1e-6:
        raise ServoError(f"angle {x} deg: the firmware takes whole millidegrees")
    s = f"{mdeg / 1000:.3f}".rstrip("0").rstrip(".")
    return s if s not in ("-0", "") else "0"


class ServoClient:
    """Client of the rig_servo firmware on a serial port; a context manager."""

    def __init__(self, port: str, *, baudrate: int = BAUDRATE, timeout: float = 1.0,
                 retries: int = 2, boot_timeout: float = 4.0, open_serial=None):
        self.port_name = port
        self.baudrate = baudrate
        self.timeout = timeout
        self.retries = retries
        self.boot_timeout = boot_timeout
        self._open_serial = open_serial
        self._ser = None
        self._seq = itertools.count(1)
        self._pending: dict[int, _Pending] = {}
        self._lock = threading.Lock()          # one command at a time
        self._plock = threading.Lock()         # pending table
        self._events: queue.Queue[Event] = queue.Queue()
        self._reader: threading.Thread | None = None
        self._stop = threading.Event()
        self._reader_error: BaseException | None = None
        self._raw_last: int | None = None
        self._unwrapped_last = 0
        self._clock_samples: list[tuple[int, int, int]] = []   # (device_us, host_mid_ns, rtt)
        self.clock: ClockMap | None = None
        self.hello: dict[str, str] = {}

    # ------------------------------------------------------------------ connection
    def open(self) -> "ServoClient":
        if self._ser is not None:
            return self
        try:
            if self._open_serial is not None:
                self._ser = self._open_serial(self.port_name, self.baudrate)
            else:
                import serial

                self._ser = serial.Serial(self.port_name, self.baudrate, timeout=0.05,
                                          write_timeout=self.timeout)
        except Exception as exc:  # serial.SerialException, OSError, ValueError
            raise ServoPortError(f"{self.port_name}: cannot open the servo port: {exc}; check "
                                 "the cable and the port name (ls /dev/ttyACM* /dev/ttyUSB*), "
                                 "your access (group dialout), or use --virtual") from None
        self._stop.clear()
        self._reader = threading.Thread(target=self._read_loop, name="servo-reader", daemon=True)
        self._reader.start()
        try:
            self.handshake()
        except BaseException:
            self.close()
            raise
        return self

    def close(self) -> None:
        self._stop.set()
        if self._reader is not None:
            self._reader.join(2)
            self._reader = None
        if self._ser is not None:
            try:
                self._ser.close()
            except Exception:
                pass
            self._ser = None

    def __enter__(self) -> "ServoClient":
        return self.open()

    def __exit__(self, *exc) -> None:
        self.close()

    def handshake(self) -> dict[str, str]:
        """Wait for the firmware (PING until it answers), then HELLO and check the version."""
        deadline = time.monotonic() + self.boot_timeout
        while True:
            try:
                self.command("PING", timeout=min(self.timeout, 0.5), retries=0)
                break
            except ServoTimeout:
                if time.monotonic() > deadline:
                    raise ServoTimeout(f"{self.port_name}: no answer to PING within "
                                       f"{self.boot_timeout} s; is the rig_servo firmware "
                                       "flashed (evdnerf flash) and the baud rate 115200?") from None
            except ServoCommandError:
                raise ServoProtocolError(f"{self.port_name}: the device rejects PING; it does "
                                         "not run the rig_servo firmware (evdnerf flash)") from None
        words = self.command("HELLO").words
        if len(words) < 3 or words[1] != "HELLO" or words[2].lower() != FIRMWARE_NAME:
            raise ServoProtocolError(f"{self.port_name}: unexpected HELLO reply {' '.join(words)!r}"
                                     f"; expected firmware {FIRMWARE_NAME}")
        info = dict(w.split("=", 1) for w in words[3:] if "=" in w)
        info = {k.lower(): v for k, v in info.items()}
        if info.get("proto") != str(PROTOCOL_VERSION):
            raise ServoProtocolError(
                f"{self.port_name}: firmware speaks protocol {info.get('proto')}, this client "
                f"{PROTOCOL_VERSION}; flash the firmware of this checkout (evdnerf flash)")
        self.hello = info
        return info

    # ------------------------------------------------------------------ reader
    def _unwrap(self, raw: int) -> int:
        if self._raw_last is None:
            self._raw_last, self._unwrapped_last = raw, raw
            return raw
        delta = ((raw - self._raw_last + (1 << 31)) % (1 << 32)) - (1 << 31)
        value = self._unwrapped_last + delta
        if delta > 0:
            self._raw_last, self._unwrapped_last = raw, value
        return value

    def _read_loop(self) -> None:
        buf = b""
        while not self._stop.is_set():
            try:
                chunk = self._ser.read(self._ser.in_waiting or 1)   # returns at the first byte
            except Exception as exc:
                self._reader_error = exc
                break
            if not chunk:
                continue
            now = time.monotonic_ns()
            buf += chunk
            *lines, buf = buf.split(b"\n")
            for raw in lines:
                self._dispatch(raw.decode("ascii", "replace").strip(), now)
            if len(buf) > 4096:
                buf = b""
        # wake any waiter: the port is gone
        with self._plock:
            for p in self._pending.values():
                p.event.set()

    def _dispatch(self, line: str, now: int) -> None:
        if not line:
            return
        words = line.split()
        if words[0].startswith("@"):
            try:
                seq = int(words[0][1:])
            except ValueError:
                return
            with self._plock:
                p = self._pending.get(seq)
                if p is not None:
                    p.line, p.recv_ns = " ".join(words[1:]), now
                    p.event.set()
            return          # a late reply to a command that timed out: dropped
        kind = words[0]
        if kind in ("START", "DONE", "STOPPED") and len(words) >= 3:
            try:
                dev = self._unwrap(int(words[2]))
            except ValueError:
                return
            self._events.put(Event(kind, words[1], dev, now, tuple(words[3:])))
        elif kind == "BOOT":
            self._raw_last = None       # the device clock restarted
            self._clock_samples.clear()
            self.clock = None
            self._events.put(Event("BOOT", "", None, now, tuple(words[1:])))

    # ------------------------------------------------------------------ commands
    def command(self, line: str, *, timeout: float | None = None,
                retries: int | None = None) -> Reply:
        """Send one command; return the OK reply, raise ServoCommandError on ERR."""
        if self._ser is None:
            raise ServoPortError(f"{self.port_name}: the servo port is not open")
        timeout = self.timeout if timeout is None else timeout
        retries = self.retries if retries is None else retries
        with self._lock:
            for attempt in range(retries + 1):
                p = _Pending(next(self._seq))
                with self._plock:
                    self._pending[p.seq] = p
                try:
                    sent = time.monotonic_ns()
                    try:
                        self._ser.write(f"@{p.seq} {line}\n".encode("ascii"))
                        self._ser.flush()
                    except Exception as exc:
                        raise ServoPortError(f"{self.port_name}: write failed: {exc}") from None
                    p.event.wait(timeout)
                finally:
                    with self._plock:
                        self._pending.pop(p.seq, None)
                if p.line is not None:
                    break
                if self._reader_error is not None:
                    raise ServoPortError(f"{self.port_name}: the servo port was lost: "
                                         f"{self._reader_error}")
            else:
                raise ServoTimeout(f"{self.port_name}: no reply to `{line}` within {timeout} s "
                                   f"({retries + 1} attempts)")
        words = p.line.split()
        if words and words[0] == "ERR":
            raise ServoCommandError(line, words[1] if len(words) > 1 else "?",
                                    " ".join(words[2:]))
        if not words or words[0] != "OK":
            raise ServoProtocolError(f"{self.port_name}: bad reply to `{line}`: {p.line!r}")
        return Reply(words, sent, p.recv_ns)

    def ping(self) -> tuple[int, int, int]:
        """(device_us, host_send_ns, host_recv_ns); also a clock-sync sample."""
        r = self.command("PING")
        dev = self._unwrap(int(r.words[2]))
        self._clock_samples.append((dev, (r.host_send_ns + r.host_recv_ns) // 2,
                                    r.host_recv_ns - r.host_send_ns))
        return dev, r.host_send_ns, r.host_recv_ns

    def sync_clock(self, pings: int = 20, interval_s: float = 0.0) -> ClockMap:
        """Fit host_ns = offset + scale * device_us to all ping samples so far (+ new ones).

        Each sample pairs the device time with the midpoint of the ping's host send/receive
        times; samples whose round trip exceeds 2x the median are dropped (delayed replies).
        """
        for _ in range(pings):
            self.ping()
            if interval_s:
                time.sleep(interval_s)
        s = np.array(self._clock_samples, dtype=np.float64)
        if len(s) < 2:
            raise ServoError("clock sync needs at least 2 pings")
        keep = s[:, 2] <= 2 * np.median(s[:, 2])
        if keep.sum() >= 2:
            s = s[keep]
        ref = int(s[0, 0])
        x = s[:, 0] - ref
        if np.ptp(x) == 0:
            raise ServoError("clock sync: the device time did not advance between pings")
        scale, offset = np.polyfit(x, s[:, 1], 1)
        resid = s[:, 1] - (offset + scale * x)
        self.clock = ClockMap(float(offset), float(scale), ref,
                              float(np.sqrt(np.mean(resid ** 2))), int(len(s)))
        return self.clock

    def device_to_host_ns(self, device_us):
        if self.clock is None:
            self.sync_clock()
        return self.clock.to_host_ns(device_us)

    # ------------------------------------------------------------------ events
    def next_event(self, timeout: float | None = None) -> Event:
        try:
            return self._events.get(timeout=self.timeout if timeout is None else timeout)
        except queue.Empty:
            raise ServoTimeout(f"{self.port_name}: no START/DONE report within "
                               f"{self.timeout if timeout is None else timeout} s") from None

    def drain_events(self) -> list[Event]:
        out = []
        while True:
            try:
                out.append(self._events.get_nowait())
            except queue.Empty:
                return out

    def wait_motion(self, motion: str, timeout: float) -> Motion:
        """Wait for START and DONE (or STOPPED) of ``motion``; other reports are skipped."""
        deadline = time.monotonic() + timeout
        start = None
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                raise ServoTimeout(f"{self.port_name}: {motion} did not "
                                   f"{'start' if start is None else 'finish'} within {timeout} s")
            ev = self.next_event(left)
            if ev.motion != motion:
                continue
            if ev.kind == "START":
                start = ev
            elif ev.kind in ("DONE", "STOPPED") and start is not None:
                return Motion(start, ev)

    def _motion(self, line: str, name: str, wait: bool, expected_ms: int) -> Motion | None:
        self.drain_events()
        self.command(line, retries=0)    # never repeat a motion command
        if not wait:
            return None
        return self.wait_motion(name, timeout=expected_ms / 1000 + 2 * self.timeout + 1.0)

    def move(self, angle_deg: float, duration_ms: int, wait: bool = True) -> Motion | None:
        return self._motion(f"MOVE {_deg(angle_deg)} {int(duration_ms)}", "MOVE", wait,
                            int(duration_ms))

    def turn(self, angle_deg: float, duration_ms: int, wait: bool = True) -> Motion | None:
        return self._motion(f"TURN {_deg(angle_deg)} {int(duration_ms)}", "TURN", wait,
                            int(duration_ms))

    def home(self, duration_ms: int = 1000, wait: bool = True) -> Motion | None:
        return self._motion(f"HOME {int(duration_ms)}", "HOME", wait, int(duration_ms))

    def run(self, wait: bool = True, expected_ms: int | None = None) -> Motion | None:
        if expected_ms is None:
            expected_ms = self.get_profile().duration_ns // 1_000_000 if wait else 0
        return self._motion("RUN", "RUN", wait, expected_ms)

    def stop(self) -> None:
        self.command("STOP")

    def status(self) -> dict:
        w = self.command("STATUS").words
        return {"servo_deg": float(w[2]), "turntable_deg": float(w[3]),
                "servo": w[4], "turntable": w[5]}

    def get_limits(self) -> Limits:
        return self._limits(self.command("GET LIMITS").words)

    def set_limits(self, limits: Limits) -> Limits:
        return self._limits(self.command(
            f"SET LIMITS {_deg(limits.min_deg)} {_deg(limits.max_deg)} {int(limits.max_speed_dps)}"
            f" {int(limits.pulse_min_us)} {int(limits.pulse_max_us)}", retries=0).words)

    @staticmethod
    def _limits(w) -> Limits:
        return Limits(float(w[2]), float(w[3]), int(w[4]), int(w[5]), int(w[6]))

    def get_profile(self) -> RunProfile:
        return self._profile(self.command("GET PROFILE").words)

    def set_profile(self, profile: RunProfile) -> RunProfile:
        segs = " ".join(f"{_deg(a)} {int(ms)}" for a, ms in profile.segments)
        return self._profile(self.command(f"SET PROFILE {_deg(profile.start_deg)} {segs}",
                                          retries=0).words)

    @staticmethod
    def _profile(w) -> RunProfile:
        vals = w[3:]
        return RunProfile(start_deg=float(w[2]),
                          segments=tuple((float(vals[i]), int(vals[i + 1]))
                                         for i in range(0, len(vals), 2)))
