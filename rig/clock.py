"""Device-clock -> host-clock mapping shared by the servo client and the camera drivers.

``ClockMap`` is ``host_ns = offset_ns + scale * (device_us - device_ref_us)``.  Two ways to
fit one:

* ``fit_clock_map(device_us, host_ns)``: least squares over (device time, host time) pairs
  whose host time is the midpoint of a round trip (the servo's pings: symmetric error);
* ``fit_clock_map(..., one_sided=True)``: pairs whose host time is an *arrival* time, always
  later than the true host time of the device stamp by a positive, variable latency (a
  camera's USB transfers).  The fit then follows the lower envelope: per time bin the sample
  of least latency, a straight line through those, shifted down so that no sample lies below
  it (a sample can never arrive before it was stamped).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from evdnerf_ros.errors import EvdnerfError


class ClockFitError(EvdnerfError):
    """Too few or degenerate (device, host) samples to fit a clock map."""


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

    def sensor_ns_to_host_ns(self, sensor_ns) -> np.ndarray | int:
        """Map int64 sensor nanoseconds (a camera's unwrapped event times) to host ns.

        Computed from the int64 difference to the reference, so no precision is lost
        for long recordings."""
        s = np.asarray(sensor_ns, dtype=np.int64) - np.int64(self.device_ref_us) * 1000
        out = np.rint(self.offset_ns + self.scale * (s.astype(np.float64) / 1000.0)).astype(np.int64)
        return int(out) if out.ndim == 0 else out


    def host_ns_to_sensor_ns(self, host_ns) -> np.ndarray | int:
        """The inverse of :meth:`sensor_ns_to_host_ns`: the sensor time (int64 ns) that the
        fitted clock maps to host time ``host_ns``."""
        h = np.asarray(host_ns, dtype=np.int64)
        d = (h - np.int64(round(self.offset_ns))).astype(np.float64) - (self.offset_ns - round(self.offset_ns))
        out = np.rint(d / self.scale * 1000.0).astype(np.int64) + np.int64(self.device_ref_us) * 1000
        return int(out) if out.ndim == 0 else out


def fit_clock_map(device_us, host_ns, *, one_sided: bool = False, bins: int = 16,
                  source: str = "clock samples") -> ClockMap:
    """Fit a ClockMap to paired samples (see the module docstring for ``one_sided``)."""
    d = np.asarray(device_us, dtype=np.float64).ravel()
    h = np.asarray(host_ns, dtype=np.float64).ravel()
    if d.shape != h.shape:
        raise ClockFitError(f"{source}: {d.size} device times but {h.size} host times")
    if d.size < 2:
        raise ClockFitError(f"{source}: a clock fit needs at least 2 samples, got {d.size}")
    ref = int(np.min(d))
    x = d - ref
    if np.ptp(x) == 0:
        raise ClockFitError(f"{source}: the device time did not advance between samples")
    y = h - h[0]                       # fit in a small range; add h[0] back at the end
    if one_sided:
        # lower envelope: least-latency sample per bin of device time
        nb = int(max(2, min(bins, d.size)))
        edges = np.linspace(0.0, x.max(), nb + 1)
        b = np.clip(np.searchsorted(edges, x, side="right") - 1, 0, nb - 1)
        lat = y - 1000.0 * x           # latency against a nominal clock, up to a constant
        order = np.lexsort((lat, b))
        first = np.ones(order.size, bool)
        first[1:] = b[order][1:] != b[order][:-1]
        pick = order[first]
        if np.ptp(x[pick]) == 0:
            pick = np.array([int(np.argmin(x)), int(np.argmax(x))])
        scale, offset = np.polyfit(x[pick], y[pick], 1)
        resid = y - (offset + scale * x)
        offset += float(resid.min())   # no sample may arrive before it was stamped
        resid = y - (offset + scale * x)
    else:
        scale, offset = np.polyfit(x, y, 1)
        resid = y - (offset + scale * x)
    return ClockMap(float(offset + h[0]), float(scale), ref,
                    float(np.sqrt(np.mean(resid ** 2))), int(d.size))
