"""The virtual Arduino's pins as the closed-loop virtual rig's physical signals.

The harness logs every edge of D8 (trigger out), D9 (scene servo) and D10 (turntable) with the
host's monotonic time at which it simulated the edge (rig.virtual_arduino). ``PinFeed`` follows
that log while the harness writes it and turns it into what the rest of the rig sees:

* each servo frame's D9 / D10 pulse width into the commanded angle, with the firmware's own
  mapping ``width = pulse_min + angle * (pulse_max - pulse_min) / 180`` (PROTOCOL.md; the 0.5 µs
  timer tick makes that exact to 0.09 millidegree per microsecond of range);
* the joint's angle at any host time: the commanded angles of successive frames joined linearly
  (a servo follows its 50 Hz commands smoothly; the firmware's commands are the profile sampled
  at the frames, so this is the simulator's servo motion sampled at 50 Hz), the power-up angle
  before the first pulse;
* D8's rising edges (the trigger pulse the firmware raises at each servo motion's first frame),
  in host time, for the camera's trigger input.

Times are ``time.monotonic_ns()`` (what the camera twins' clocks and the servo client use).
"""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np

from .virtual_arduino import PIN_SERVO, PIN_TRIGGER, PIN_TURNTABLE, parse_pin_lines

#: The turntable's power-up angle (PROTOCOL.md).
TURNTABLE_HOME_DEG = 90.0


class JointTrack:
    """Commanded angles of one servo at its frames' host times, joined linearly. The feed's
    thread extends it while the camera twin reads it: readers take one snapshot of the pair."""

    def __init__(self, initial_deg: float):
        self.initial_deg = float(initial_deg)
        self._frames = (np.empty(0, np.int64), np.empty(0, np.float64))

    def extend(self, t_ns: np.ndarray, deg: np.ndarray) -> None:
        if t_ns.size:
            t, d = self._frames
            self._frames = (np.concatenate([t, t_ns.astype(np.int64)]),
                            np.concatenate([d, deg.astype(np.float64)]))

    @property
    def frames(self) -> tuple[np.ndarray, np.ndarray]:
        """(host ns, degrees) of every frame so far (one snapshot)."""
        return self._frames

    @property
    def last_ns(self) -> int | None:
        t = self._frames[0]
        return int(t[-1]) if t.size else None

    def deg(self, t_ns):
        """Angle (degrees) at host time(s) ``t_ns``; after the last known frame, its angle."""
        ft, fd = self._frames
        t = np.asarray(t_ns, np.int64)
        if not ft.size:
            out = np.full(t.shape, self.initial_deg)
        else:
            out = np.interp(t.astype(np.float64), ft.astype(np.float64), fd, left=self.initial_deg)
        return float(out) if out.ndim == 0 else out

    def changes(self, a_ns: int, b_ns: int) -> bool:
        """Whether the angle differs anywhere in [a_ns, b_ns] (joined linearly, its extremes
        lie at the ends or at frames inside)."""
        ft = self._frames[0]
        inside = ft[(ft > a_ns) & (ft < b_ns)]
        vals = self.deg(np.concatenate([[a_ns], inside, [b_ns]]))
        return bool(np.ptp(vals) > 0)


class PinFeed:
    """Follows a harness pin log (see the module docstring). Thread-safe; call :meth:`poll` to
    read what the harness has flushed since the last call."""

    def __init__(self, log_path, *, pulse_min_us: float, pulse_max_us: float, servo_start_deg: float,
                 turntable_start_deg: float = TURNTABLE_HOME_DEG):
        if not pulse_min_us < pulse_max_us:
            raise ValueError(f"pulse range {pulse_min_us}..{pulse_max_us} µs is empty")
        self.path = Path(log_path)
        self.pulse_min_us, self.pulse_max_us = float(pulse_min_us), float(pulse_max_us)
        self.servo = JointTrack(servo_start_deg)
        self.turntable = JointTrack(turntable_start_deg)
        self.trigger_rises_ns: list[int] = []
        self.covered_ns = 0                    # host time up to which the log has been read
        self._offset = 0
        self._partial = b""
        self._rise: dict[str, tuple[int, int] | None] = {PIN_SERVO: None, PIN_TURNTABLE: None}
        self._lock = threading.Lock()

    def angle_of_width(self, width_ns):
        span = self.pulse_max_us - self.pulse_min_us
        return (np.asarray(width_ns, np.float64) / 1000.0 - self.pulse_min_us) * 180.0 / span

    def poll(self) -> list[int]:
        """Read the log's new complete lines; returns the new D8 rising edges (host ns)."""
        with self._lock:
            try:
                with open(self.path, "rb") as f:
                    f.seek(self._offset)
                    data = f.read()
            except FileNotFoundError:
                return []
            if not data:
                return []
            self._offset += len(data)
            data = self._partial + data
            cut = data.rfind(b"\n") + 1
            self._partial = data[cut:]
            rows = parse_pin_lines(data[:cut].decode("ascii", "replace").splitlines())
            if not rows.size:
                return []
            self.covered_ns = max(self.covered_ns, int(rows["host_ns"].max()))
            for pin, track in ((PIN_SERVO, self.servo), (PIN_TURNTABLE, self.turntable)):
                self._pulses(rows[rows["pin"] == pin], pin, track)
            tr = rows[(rows["pin"] == PIN_TRIGGER) & (rows["level"] == 1)]["host_ns"]
            new = [int(t) for t in tr]
            self.trigger_rises_ns += new
            return new

    def _pulses(self, rows, pin: str, track: JointTrack) -> None:
        """Complete high pulses of one pin (a rise may come in an earlier poll than its fall)."""
        times, widths = [], []
        rise = self._rise[pin]
        for t_sim, level, host in zip(rows["t_ns"].tolist(), rows["level"].tolist(), rows["host_ns"].tolist()):
            if level:
                rise = (t_sim, host)
            elif rise is not None:
                times.append(rise[1])
                widths.append(t_sim - rise[0])      # the width in the chip's own time: exact
                rise = None
        self._rise[pin] = rise
        if times:
            track.extend(np.array(times, np.int64), self.angle_of_width(np.array(widths, np.int64)))


def follow(feed: PinFeed, on_trigger, stop: threading.Event, interval_s: float = 0.002) -> threading.Thread:
    """A daemon thread polling ``feed`` every ``interval_s`` and calling ``on_trigger(host_ns)``
    for each new D8 rising edge, until ``stop`` is set."""

    def run():
        while not stop.wait(interval_s):
            for t in feed.poll():
                on_trigger(t)
        for t in feed.poll():
            on_trigger(t)

    th = threading.Thread(target=run, name="pin-feed", daemon=True)
    th.start()
    return th


__all__ = ["PinFeed", "JointTrack", "follow", "TURNTABLE_HOME_DEG"]
