"""The servo motion profile: the same formulas the rig firmware runs, as pure functions of time.

Two views of one profile live here:

* the **physical angle** (float degrees) used by the renderer: the smooth curve the servo
  horn follows, a pure function of int64-ns elapsed time;
* the **firmware command** (integer millidegrees): exactly what the firmware computes
  with integer arithmetic at each servo frame, so that the C code can be tested against
  this module value by value (`command_mdeg`).

Minimum-jerk MOVE
-----------------
A MOVE from angle ``a0`` to ``a1`` over a duration ``D > 0`` started at time 0 follows::

    tau      = clamp(e / D, 0, 1)                 e = elapsed time since the move started
    s(tau)   = tau^3 * (10 - 15 tau + 6 tau^2)    (= 10 tau^3 - 15 tau^4 + 6 tau^5)
    angle(e) = a0 + (a1 - a0) * s(tau)

s(0) = 0, s(1) = 1, s'(0) = s'(1) = 0 and s''(0) = s''(1) = 0 (zero velocity and zero
acceleration at both ends), and s is strictly increasing on (0, 1), so a single MOVE is
monotone.  The float version computes ``tau`` as ``e_ns / D_ns`` from int64 nanoseconds
(one correctly rounded division; no large absolute times enter the arithmetic).

Integer mirror (what the firmware runs)
---------------------------------------
Time is whole microseconds (``micros()``), angles are int32 millidegrees, all
intermediates are unsigned/signed 64-bit, ``>>`` is applied to non-negative values only
and ``/`` is integer division of non-negative values (identical in C and Python)::

    ONE = 65536                                  # Q16 fixed point
    if e_us <= 0:        s = 0
    elif e_us >= D_us:   s = ONE
    else:
        u  = (e_us * ONE) / D_us                 # tau in Q16, 0 <= u < ONE
        u3 = (u * u * u) >> 24                   # tau^3 in Q24, < 2^24
        p  = 10*ONE*ONE - 15*ONE*u + 6*u*u       # 10 - 15 tau + 6 tau^2 in Q32, < 2^36
        s  = (u3 * p) >> 40                      # Q16; u3 * p < 2^60
    d   = (a1_mdeg - a0_mdeg) * s                # signed 64-bit
    cmd = a0_mdeg + sign(d) * ((|d| + 32768) >> 16)    # round half away from zero

``s`` is non-decreasing in ``e_us`` (checked exhaustively for every u in the tests), so the
commanded angle of a single MOVE is monotone too; it starts at exactly ``a0`` and ends at
exactly ``a1``; s is within 1.04 Q16 units of the exact polynomial.  ``u * u * u``,
``u3 * p`` and ``e_us * ONE`` need 64-bit integers (all stay below 2^63).  Host code
converts int64 ns to the firmware's microseconds with ``e_us = e_ns // 1000`` (floor).  The float angle
and the integer command agree within 0.01 deg + |a1 - a0| * 2^-14 (tested).

RUN profile
-----------
A stored, repeatable profile: a start angle (where RUN begins; the firmware's HOME) and
a list of segments ``(angle_deg, duration_ms)``; segment k is a minimum-jerk MOVE from
the previous segment's target (the start angle for k = 0) to ``angle_deg`` over
``duration_ms``.  Segment k starts at the sum of the previous durations (whole ms, so
whole us and ns: no rounding anywhere).  Before the RUN starts the angle is the start
angle, after it ends it is the last target.  Angles must be whole millidegrees and
durations whole milliseconds (1..65535 ms) so the firmware can store them exactly.
The default fork swing, ``DEFAULT_RUN``, starts at 90 deg and swings 90 -> 135 -> 45 -> 90
deg in 250 + 500 + 250 ms (1 s).  Because the profile is a pure function of elapsed time
it repeats to the nanosecond: two RUNs started at different times give identical angles
at identical elapsed times.
"""

from __future__ import annotations

from dataclasses import dataclass
from decimal import Decimal, InvalidOperation

import numpy as np

from ..errors import InputError

ONE_Q16 = 1 << 16
NS_PER_US = 1_000
NS_PER_MS = 1_000_000


# ----------------------------------------------------------------------------- float form

def min_jerk(tau):
    """s(tau) = tau^3 (10 - 15 tau + 6 tau^2), tau clamped to [0, 1]; scalar or array."""
    tau = np.clip(tau, 0.0, 1.0)
    return tau * tau * tau * (10.0 + tau * (-15.0 + 6.0 * tau))


def min_jerk_rate(tau):
    """ds/dtau = 30 tau^2 (1 - tau)^2 (zero outside [0, 1])."""
    tau = np.asarray(tau, dtype=np.float64)
    inside = (tau > 0) & (tau < 1)
    return np.where(inside, 30.0 * tau * tau * (1.0 - tau) ** 2, 0.0)


def move_angle_deg(elapsed_ns, duration_ns: int, a0_deg: float, a1_deg: float):
    """Physical angle (deg) of a MOVE a0 -> a1 over duration_ns, at int64-ns elapsed time."""
    if int(duration_ns) <= 0:
        raise InputError(f"servo MOVE duration must be positive, got {duration_ns} ns")
    tau = np.asarray(elapsed_ns, dtype=np.int64) / np.int64(duration_ns)
    return a0_deg + (a1_deg - a0_deg) * min_jerk(tau)


# --------------------------------------------------------------------------- integer form

def min_jerk_q16(elapsed: int, duration: int) -> int:
    """The firmware's s in Q16 (0..65536) for integer elapsed/duration in the same unit."""
    e, d = int(elapsed), int(duration)
    if d <= 0:
        raise InputError(f"servo MOVE duration must be positive, got {duration}")
    if e <= 0:
        return 0
    if e >= d:
        return ONE_Q16
    return int(min_jerk_q16_from_u((e * ONE_Q16) // d))


def min_jerk_q16_from_u(u: np.ndarray) -> np.ndarray:
    """Vectorised s for given Q16 tau values u (0 <= u < 65536); used to test monotonicity."""
    u = np.asarray(u, dtype=np.int64)
    u3 = (u * u * u) >> 24
    p = 10 * ONE_Q16 * ONE_Q16 - 15 * ONE_Q16 * u + 6 * u * u
    return (u3 * p) >> 40


def move_command_mdeg(elapsed_us: int, duration_us: int, a0_mdeg: int, a1_mdeg: int) -> int:
    """The firmware's commanded angle (millidegrees) of a MOVE, integer math only."""
    s = min_jerk_q16(elapsed_us, duration_us)
    d = (int(a1_mdeg) - int(a0_mdeg)) * s
    q = (abs(d) + (ONE_Q16 >> 1)) >> 16
    return int(a0_mdeg) + (q if d >= 0 else -q)


# ----------------------------------------------------------------------------- profiles

def _whole(value, scale: int, what: str) -> int:
    try:
        x = Decimal(str(value)) * scale
    except (InvalidOperation, ValueError):
        raise InputError(f"{what}: {value!r} is not a number") from None
    if not x.is_finite() or x != x.to_integral_value():
        raise InputError(f"{what}: {value!r} must be a finite multiple of {Decimal(1) / scale}")
    return int(x)


@dataclass(frozen=True)
class RunProfile:
    """A stored servo profile: start angle and (angle_deg, duration_ms) minimum-jerk segments."""

    start_deg: float
    segments: tuple[tuple[float, int], ...]

    def __post_init__(self):
        segs = tuple((float(a), int(ms)) for a, ms in self.segments)
        object.__setattr__(self, "segments", segs)
        object.__setattr__(self, "start_deg", float(self.start_deg))
        _whole(self.start_deg, 1000, "servo start angle (millidegrees)")
        if not segs:
            raise InputError("servo profile: needs at least one (angle_deg, duration_ms) segment")
        for k, (a, ms) in enumerate(segs):
            _whole(a, 1000, f"servo profile segment {k} angle (millidegrees)")
            if not 1 <= ms <= 65535:
                raise InputError(f"servo profile segment {k}: duration {ms} ms must be in "
                                 "1..65535 ms")

    # boundaries ---------------------------------------------------------------------
    @property
    def targets_deg(self) -> list[float]:
        return [self.start_deg] + [a for a, _ in self.segments]

    @property
    def boundaries_ns(self) -> np.ndarray:
        """Start of each segment and end of the last, in ns since RUN start (int64)."""
        return np.concatenate([[0], np.cumsum([ms for _, ms in self.segments])]).astype(
            np.int64) * NS_PER_MS

    @property
    def duration_ns(self) -> int:
        return int(self.boundaries_ns[-1])

    # physical angle -------------------------------------------------------------------
    def _segment(self, elapsed_ns):
        """(targets, segment index, segment duration ns, tau in its segment) per time."""
        e = np.asarray(elapsed_ns, dtype=np.int64)
        b = self.boundaries_ns
        k = np.clip(np.searchsorted(b, e, side="right") - 1, 0, len(self.segments) - 1)
        dur = b[k + 1] - b[k]
        tau = (e - b[k]) / dur
        return np.asarray(self.targets_deg), k, dur, tau

    def angle_deg(self, elapsed_ns):
        """Smooth physical angle (deg) at int64-ns time(s) since RUN start; scalar or array."""
        tg, k, dur, tau = self._segment(elapsed_ns)
        out = tg[k] + (tg[k + 1] - tg[k]) * min_jerk(tau)
        return float(out) if out.ndim == 0 else out

    def velocity_deg_s(self, elapsed_ns):
        """Analytic angular velocity (deg/s)."""
        tg, k, dur, tau = self._segment(elapsed_ns)
        out = (tg[k + 1] - tg[k]) * min_jerk_rate(tau) / (dur * 1e-9)
        return float(out) if out.ndim == 0 else out

    # firmware command -------------------------------------------------------------------
    def command_mdeg(self, elapsed_ns: int) -> int:
        """The firmware's integer command (millidegrees) at ``elapsed_ns`` (floored to us)."""
        e_us = int(elapsed_ns) // NS_PER_US
        start = 0
        a0 = _whole(self.start_deg, 1000, "start")
        for a, ms in self.segments:
            a1 = _whole(a, 1000, "angle")
            d_us = ms * 1000
            if e_us < start + d_us:
                return move_command_mdeg(e_us - start, d_us, a0, a1)
            start += d_us
            a0 = a1
        return a0

    def to_dict(self) -> dict:
        return {"start_deg": self.start_deg,
                "segments": [[a, ms] for a, ms in self.segments]}


#: The fork swing the rig runs by default (RUN): 90 -> 135 -> 45 -> 90 deg in 1 s.
DEFAULT_RUN = RunProfile(start_deg=90.0, segments=((135.0, 250), (45.0, 500), (90.0, 250)))


def move_profile(from_deg: float, to_deg: float, duration_ms: int) -> RunProfile:
    """A single MOVE expressed as a one-segment profile."""
    return RunProfile(start_deg=from_deg, segments=((to_deg, duration_ms),))
