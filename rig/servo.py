"""Serial client of the servo-rig firmware (protocol: firmware/PROTOCOL.md).

``ServoClient(port)`` opens a real port (``/dev/ttyACM0``) or the virtual Arduino's pty,
waits for the firmware (an Uno resets when the port opens), checks the protocol version
with ``HELLO``, and then sends one command at a time, tagged ``@<seq>`` so a late reply to
an earlier, timed-out command can never be taken for the current one.  A background thread
reads every line: tagged replies go to the waiting command, ``START`` / ``DONE`` /
``STOPPED`` / ``BOOT`` reports go to an event queue with their host receive time.  An
untagged ``ERR`` (the firmware could not read the tag of a garbled line) answers the command
waiting at once, never a timeout.  Arguments are range-checked against the firmware's limits
before anything is sent (``ServoInputError``, an InputError naming the argument), and
malformed replies or noise from the device end in ``ServoProtocolError``, never a traceback.

Device time is the firmware's ``micros()`` (uint32, unwrapped here).  ``sync_clock()`` sends
timestamped pings and fits ``host_ns = offset_ns + scale * device_us`` by least squares
(offset and drift); ``device_to_host_ns`` then maps START / DONE times onto the host clock.
"""

from __future__ import annotations

import errno
import itertools
import math
import os
import queue
import stat
import threading
import time
from dataclasses import dataclass, field

import numpy as np

from evdnerf_ros.errors import EvdnerfError, InputError
from evdnerf_ros.limits import check_number
from evdnerf_ros.geometry.servo_profile import RunProfile
from rig.clock import ClockMap  # noqa: F401  (moved to rig.clock; re-exported here)

PROTOCOL_VERSION = 1
FIRMWARE_NAME = "rig_servo"
BAUDRATE = 115200

# The firmware's ranges (firmware/PROTOCOL.md); checked here before anything is sent.
ANGLE_RANGE = (0, 180)              # degrees, whole millidegrees
DURATION_MS_RANGE = (1, 65535)
SPEED_DPS_RANGE = (1, 6000)
PULSE_US_RANGE = (400, 2600)
MAX_SEGMENTS = 8
TAG_MODULO = 1 << 32                # tags are @0..4294967295
MAX_QUEUED_EVENTS = 10_000          # unread START/DONE/... reports kept (oldest dropped)


class ServoError(EvdnerfError):
    """Base of the servo client's errors."""


class ServoPortError(ServoError):
    """The serial port cannot be opened (missing, busy, no permission) or was lost."""


class ServoTimeout(ServoError):
    """No reply (or report) within the timeout, retries included."""


class ServoProtocolError(ServoError):
    """The device does not speak this protocol (wrong firmware, wrong version, bad reply)."""


class ServoInputError(ServoError, InputError):
    """An argument outside the firmware's range; raised before anything is sent."""


class ServoCommandError(ServoError):
    """The firmware answered ERR; ``code`` is its error code (BUSY, OUT_OF_RANGE, ...).

    ``untagged`` marks an ERR without a tag: the firmware could not read the command's tag
    (the line arrived garbled or bytes were lost), so it answered the line as a whole.
    """

    def __init__(self, command: str, code: str, reason: str, untagged: bool = False):
        why = (" (reply without its tag: the line reached the firmware garbled; nothing was "
               "executed)" if untagged else "")
        super().__init__(f"servo refused `{command}`: {code} {reason}".rstrip() + why)
        self.command, self.code, self.reason, self.untagged = command, code, reason, untagged


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
    untagged: bool = False


def _checked(value, name, **kw):
    try:
        return check_number(value, name, **kw)
    except InputError as exc:
        raise ServoInputError(str(exc)) from None


def check_angle(value, name: str = "angle") -> float:
    """A finite angle in 0..180 deg with at most 3 decimals (the firmware's whole mdeg)."""
    lo, hi = ANGLE_RANGE
    value = float(_checked(value, f"{name} (degrees)", low=lo, high=hi))
    if abs(value * 1000 - round(value * 1000)) > 1e-6:
        raise ServoInputError(f"{name}: at most 3 decimals (whole millidegrees), got {value!r}")
    return round(value * 1000) / 1000


def check_duration_ms(value, name: str = "duration") -> int:
    lo, hi = DURATION_MS_RANGE
    return int(_checked(value, f"{name} (ms)", low=lo, high=hi, integer=True))


def check_limits(limits: "Limits", name: str = "limits") -> "Limits":
    """The firmware's SET LIMITS ranges: 0 <= min < max <= 180, speed 1..6000,
    400 <= pulse_min < pulse_max <= 2600."""
    lo = check_angle(limits.min_deg, f"{name} MIN_DEG")
    hi = check_angle(limits.max_deg, f"{name} MAX_DEG")
    if not lo < hi:
        raise ServoInputError(f"{name}: MIN_DEG {lo} must be below MAX_DEG {hi}")
    speed = int(_checked(limits.max_speed_dps, f"{name} MAX_SPEED_DPS",
                         low=SPEED_DPS_RANGE[0], high=SPEED_DPS_RANGE[1], integer=True))
    pmin, pmax = (int(_checked(v, f"{name} {n}", low=PULSE_US_RANGE[0],
                               high=PULSE_US_RANGE[1], integer=True))
                  for v, n in ((limits.pulse_min_us, "PULSE_MIN_US"),
                               (limits.pulse_max_us, "PULSE_MAX_US")))
    if not pmin < pmax:
        raise ServoInputError(f"{name}: PULSE_MIN_US {pmin} must be below PULSE_MAX_US {pmax}")
    return Limits(lo, hi, speed, pmin, pmax)


def check_profile(start_deg, segments, name: str = "profile") -> RunProfile:
    """A RUN profile the firmware accepts: start and segment angles 0..180 deg (3 decimals),
    1..8 segments of 1..65535 ms."""
    segments = list(segments)
    if not 1 <= len(segments) <= MAX_SEGMENTS:
        raise ServoInputError(f"{name}: {len(segments)} segments; the firmware takes 1.."
                              f"{MAX_SEGMENTS} (angle, ms) pairs")
    start = check_angle(start_deg, f"{name} start angle")
    segs = tuple((check_angle(a, f"{name} segment {k + 1} angle"),
                  check_duration_ms(ms, f"{name} segment {k + 1} duration"))
                 for k, (a, ms) in enumerate(segments))
    return RunProfile(start_deg=start, segments=segs)


def _deg(x: float) -> str:
    """Degrees with at most 3 decimals, as the firmware parses them."""
    try:
        mdeg = round(float(x) * 1000)
    except (TypeError, ValueError, OverflowError):
        raise ServoInputError(f"angle {x!r}: expected a finite number of degrees") from None
    if abs(float(x) * 1000 - mdeg) > 1e-6:
        raise ServoInputError(f"angle {x} deg: the firmware takes whole millidegrees")
    s = f"{mdeg / 1000:.3f}".rstrip("0").rstrip(".")
    return s if s not in ("-0", "") else "0"


def _finite(word: str) -> float:
    v = float(word)
    if not math.isfinite(v):
        raise ValueError(word)
    return v


def _u32(word: str) -> int:
    if not (word.isascii() and word.isdigit()) or int(word) >= TAG_MODULO:
        raise ValueError(word)
    return int(word)


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split()) or type(exc).__name__


_PORT_HINT = ("check the cable and the port name (ls /dev/ttyACM* /dev/ttyUSB*), your access "
              "(group dialout), or use --virtual")


def _check_port(port: str) -> None:
    """Name the usual mistakes before pyserial does it in its own words."""
    if not port:
        raise ServoPortError(f"servo port: empty name; {_PORT_HINT}")
    try:
        st = os.stat(port)
    except FileNotFoundError:
        raise ServoPortError(f"{port}: no such serial port; {_PORT_HINT}") from None
    except OSError as exc:
        raise ServoPortError(f"{port}: cannot open the servo port: {exc.strerror}; "
                             f"{_PORT_HINT}") from None
    if not stat.S_ISCHR(st.st_mode):
        kind = "a folder" if stat.S_ISDIR(st.st_mode) else "a regular file" \
            if stat.S_ISREG(st.st_mode) else "not a character device"
        raise ServoPortError(f"{port}: not a serial device ({kind}); give the Arduino's port, "
                             "e.g. /dev/ttyACM0, or use --virtual")
    if not os.access(port, os.R_OK | os.W_OK):
        raise ServoPortError(f"{port}: permission denied; add yourself to the group that owns "
                             "it (usually dialout: sudo usermod -aG dialout $USER, then log in "
                             "again)")


class ServoClient:
    """Client of the rig_servo firmware on a serial port; a context manager."""

    def __init__(self, port: str, *, baudrate: int = BAUDRATE, timeout: float | None = None,
                 retries: int = 2, boot_timeout: float = 4.0, open_serial=None):
        if timeout is None:     # a board simulated on a busy machine answers late: the virtual rig sets it
            timeout = float(os.environ.get("EVDNERF_SERVO_TIMEOUT_S", "1.0"))
        self.port_name = port
        self.baudrate = baudrate
        self.timeout = float(_checked(timeout, "servo timeout (s)", low=0, low_open=True,
                                      high=3600))
        self.retries = int(_checked(retries, "servo retries", low=0, high=100, integer=True))
        self.boot_timeout = float(_checked(boot_timeout, "servo boot timeout (s)", low=0,
                                           low_open=True, high=3600))
        self._open_serial = open_serial
        self._ser = None
        self._seq = itertools.count(1)
        self._pending: dict[int, _Pending] = {}
        self._lock = threading.Lock()          # one command at a time
        self._plock = threading.Lock()         # pending table
        self._events: queue.Queue[Event] = queue.Queue(maxsize=MAX_QUEUED_EVENTS)
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
                _check_port(self.port_name)
                import serial

                self._ser = serial.Serial(self.port_name, self.baudrate, timeout=0.05,
                                          write_timeout=self.timeout)
        except ServoPortError:
            raise
        except Exception as exc:  # serial.SerialException, OSError, ValueError
            raise ServoPortError(f"{self.port_name}: cannot open the servo port: "
                                 f"{_one_line(exc)}; {_PORT_HINT}") from None
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
            except ServoCommandError as exc:
                if not exc.untagged:
                    raise ServoProtocolError(f"{self.port_name}: the device rejects PING; it "
                                             "does not run the rig_servo firmware (evdnerf "
                                             "flash)") from None
                # the board's reset ate the start of a line: ask again
                if time.monotonic() > deadline:
                    raise ServoProtocolError(
                        f"{self.port_name}: the device answers only garbled lines; check the "
                        "baud rate (115200)") from None
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
        count_waiting = True
        while not self._stop.is_set():
            try:
                want = 1
                if count_waiting:
                    try:
                        want = self._ser.in_waiting or 1
                    except OSError as exc:
                        # a port that cannot count its input (a pty under an ioctl
                        # interposer such as umockdev's): read byte by byte instead
                        if exc.errno != errno.ENOTTY:
                            raise
                        count_waiting = False
                chunk = self._ser.read(want)                        # returns at the first byte
            except Exception as exc:
                self._reader_error = exc
                break
            if not chunk:
                continue
            now = time.monotonic_ns()
            buf += chunk
            *lines, buf = buf.split(b"\n")
            for raw in lines:
                try:
                    self._dispatch(raw.decode("ascii", "replace").strip(), now)
                except (ValueError, IndexError, OverflowError):
                    pass        # garbage from the device must never stop the reader
            if len(buf) > 4096:
                buf = b""       # no line is that long: noise on the wire
        # wake any waiter: the port is gone
        with self._plock:
            for p in self._pending.values():
                p.event.set()

    def _dispatch(self, line: str, now: int) -> None:
        if not line:
            return
        words = line.split()
        if words[0].startswith("@"):
            digits = words[0][1:]
            if not (digits.isascii() and digits.isdigit()):
                return
            with self._plock:
                p = self._pending.get(int(digits))
                if p is not None:
                    p.line, p.recv_ns = " ".join(words[1:]), now
                    p.event.set()
            return          # a late reply to a command that timed out: dropped
        if words[0] == "ERR":
            # An untagged ERR answers a line whose tag the firmware could not read; this client
            # tags every line and sends one at a time, so it answers the command now waiting.
            with self._plock:
                if len(self._pending) == 1:
                    p = next(iter(self._pending.values()))
                    if p.line is None:
                        p.line, p.recv_ns, p.untagged = line, now, True
                        p.event.set()
            return
        kind = words[0]
        if kind in ("START", "DONE", "STOPPED") and len(words) >= 3:
            dev = self._unwrap(_u32(words[2]))       # ValueError: dropped by the reader
            self._put_event(Event(kind, words[1], dev, now, tuple(words[3:])))
        elif kind == "BOOT":
            self._raw_last = None       # the device clock restarted
            self._clock_samples.clear()
            self.clock = None
            self._put_event(Event("BOOT", "", None, now, tuple(words[1:])))

    def _put_event(self, ev: Event) -> None:
        """Queue a report; a device flooding reports nobody reads loses the oldest ones
        instead of growing the queue without bound."""
        while True:
            try:
                self._events.put_nowait(ev)
                return
            except queue.Full:
                try:
                    self._events.get_nowait()
                except queue.Empty:
                    pass

    # ------------------------------------------------------------------ commands
    def command(self, line: str, *, timeout: float | None = None,
                retries: int | None = None) -> Reply:
        """Send one command; return the OK reply, raise ServoCommandError on ERR."""
        if self._ser is None:
            raise ServoPortError(f"{self.port_name}: the servo port is not open")
        timeout = self.timeout if timeout is None else timeout
        retries = self.retries if retries is None else retries
        if "\n" in line or "\r" in line or not line.isascii():
            raise ServoInputError(f"command {line!r}: one line of ASCII text")
        with self._lock:
            for attempt in range(retries + 1):
                p = _Pending(next(self._seq) % TAG_MODULO)
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
                if p.line is not None and not (p.untagged and attempt < retries):
                    break           # a garbled line had no effect: safe to send it again
                if self._reader_error is not None:
                    raise ServoPortError(f"{self.port_name}: the servo port was lost: "
                                         f"{self._reader_error}")
            else:
                raise ServoTimeout(f"{self.port_name}: no reply to `{line}` within {timeout} s "
                                   f"({retries + 1} attempts)")
        words = p.line.split()
        if words and words[0] == "ERR":
            raise ServoCommandError(line, words[1] if len(words) > 1 else "?",
                                    " ".join(words[2:]), untagged=p.untagged)
        if not words or words[0] != "OK":
            raise ServoProtocolError(f"{self.port_name}: bad reply to `{line}`: {p.line!r}")
        return Reply(words, sent, p.recv_ns)

    def _parse(self, reply: Reply, expect: str, parse):
        """parse(words) of an OK reply, or ServoProtocolError naming the reply: a device that
        answers garbage gets a clear error, never an IndexError."""
        w = reply.words
        try:
            if len(w) < 2 or w[1] != expect:
                raise ValueError
            return parse(w)
        except (ValueError, IndexError, TypeError, OverflowError, InputError):
            raise ServoProtocolError(f"{self.port_name}: malformed {expect} reply "
                                     f"{' '.join(w)[:200]!r}; is this the rig_servo firmware "
                                     "of this checkout (evdnerf flash)?") from None

    def ping(self) -> tuple[int, int, int]:
        """(device_us, host_send_ns, host_recv_ns); also a clock-sync sample."""
        r = self.command("PING")
        dev = self._unwrap(self._parse(r, "PONG", lambda w: _u32(w[2])))
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
        a = check_angle(angle_deg, "move angle")
        ms = check_duration_ms(duration_ms, "move duration")
        return self._motion(f"MOVE {_deg(a)} {ms}", "MOVE", wait, ms)

    def turn(self, angle_deg: float, duration_ms: int, wait: bool = True) -> Motion | None:
        a = check_angle(angle_deg, "turn angle")
        ms = check_duration_ms(duration_ms, "turn duration")
        return self._motion(f"TURN {_deg(a)} {ms}", "TURN", wait, ms)

    def home(self, duration_ms: int = 1000, wait: bool = True) -> Motion | None:
        ms = check_duration_ms(duration_ms, "home duration")
        return self._motion(f"HOME {ms}", "HOME", wait, ms)

    def run(self, wait: bool = True, expected_ms: int | None = None) -> Motion | None:
        if expected_ms is None:
            expected_ms = self.get_profile().duration_ns // 1_000_000 if wait else 0
        return self._motion("RUN", "RUN", wait, expected_ms)

    def stop(self) -> None:
        self.command("STOP")

    def status(self) -> dict:
        def parse(w):
            if len(w) != 6:
                raise ValueError
            return {"servo_deg": _finite(w[2]), "turntable_deg": _finite(w[3]),
                    "servo": w[4], "turntable": w[5]}
        return self._parse(self.command("STATUS"), "STATUS", parse)

    def get_limits(self) -> Limits:
        return self._parse(self.command("GET LIMITS"), "LIMITS", self._limits)

    def set_limits(self, limits: Limits) -> Limits:
        limits = check_limits(limits)
        return self._parse(self.command(
            f"SET LIMITS {_deg(limits.min_deg)} {_deg(limits.max_deg)} {int(limits.max_speed_dps)}"
            f" {int(limits.pulse_min_us)} {int(limits.pulse_max_us)}", retries=0),
            "LIMITS", self._limits)

    @staticmethod
    def _limits(w) -> Limits:
        if len(w) != 7:
            raise ValueError
        return Limits(_finite(w[2]), _finite(w[3]), int(w[4]), int(w[5]), int(w[6]))

    def get_profile(self) -> RunProfile:
        return self._parse(self.command("GET PROFILE"), "PROFILE", self._profile)

    def set_profile(self, profile: RunProfile) -> RunProfile:
        profile = check_profile(profile.start_deg, profile.segments)
        segs = " ".join(f"{_deg(a)} {int(ms)}" for a, ms in profile.segments)
        return self._parse(self.command(f"SET PROFILE {_deg(profile.start_deg)} {segs}",
                                        retries=0), "PROFILE", self._profile)

    @staticmethod
    def _profile(w) -> RunProfile:
        vals = w[3:]
        if len(vals) % 2:
            raise ValueError
        return RunProfile(start_deg=_finite(w[2]),
                          segments=tuple((_finite(vals[i]), int(vals[i + 1]))
                                         for i in range(0, len(vals), 2)))
