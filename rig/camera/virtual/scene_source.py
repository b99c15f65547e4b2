"""What a virtual camera twin streams: events in sensor time from the twin's start.

Two sources share one small interface (``width``, ``height``, ``t_ns``, ``events_until``,
``set_thresholds``, ``restart``):

* ``SceneEventSource``: a simulated scene (a preset name such as ``"fork"`` or a scene YAML)
  seen by a static camera of the twin's resolution from one of the scene's ring views,
  rendered by ``evdnerf_ros.sim.SceneRenderer`` and turned into events by the project's exact
  generator (``EventGenerator`` driven by ``simulate_renderer``: by default frames at a fixed
  1 kHz, the log intensity interpolated linearly between them; ``mode="adaptive"`` uses the
  adaptive sampling with the scene's motion guard, exact but ~50x more renders: 300 s for
  the fork's 1.2 s at 96x72 against 6.5 s), generated lazily in chunks as the twin asks for them, so a long
  stream never sits in memory.  The scene's time span repeats (``loop=True``: the rig's
  motion is repeatable) so the stream never ends.  Times are int64 ns on the sensor's
  1 us tick, from 0 at the twin's start.  Thresholds are settable while running (a twin maps
  its bias registers to thresholds); a change takes effect from the current time on.
* ``GivenEvents``: a fixed event array (tests, replay), delivered in time order.
"""

from __future__ import annotations

import abc
import time

import numpy as np

from evdnerf_ros.errors import InputError
from evdnerf_ros.events.types import EVENT_DTYPE, as_events, empty_events, validate_events

#: generation chunk of the scene source (sensor ns); bounded memory for any stream length
DEFAULT_CHUNK_NS = 20_000_000


class EventSource(abc.ABC):
    """Interface of a twin's event supply."""

    width: int
    height: int

    @property
    @abc.abstractmethod
    def t_ns(self) -> int:
        """Sensor time up to which events have been handed out."""

    @abc.abstractmethod
    def events_until(self, t_ns: int) -> np.ndarray:
        """The events with time in (self.t_ns, t_ns] (sorted, EVENT_DTYPE); advances t_ns."""

    @abc.abstractmethod
    def set_thresholds(self, c_pos: float, c_neg: float) -> None:
        """Contrast thresholds from now on (a twin maps its bias registers to them)."""

    @abc.abstractmethod
    def restart(self) -> None:
        """Back to sensor time 0 (a twin's timestamp reset / new start)."""

    def ready_ns(self, t_ns: int) -> int:
        """How far (<= t_ns) events can be handed out now without waiting: a source generating
        in the background lets a live twin stream only what it has (its control requests are
        never held up by rendering)."""
        return t_ns


class GivenEvents(EventSource):
    """A given event array in sensor time (t >= 0); ``loop`` repeats it with period
    ``period_ns`` (default: last event time + 1 us)."""

    def __init__(self, events, width: int, height: int, *, loop: bool = False,
                 period_ns: int | None = None, source: str = "given events"):
        ev = validate_events(as_events(events, source=source), width=width, height=height,
                             source=source)
        if ev.size and int(ev["t"][0]) < 0:
            raise InputError(f"{source}: sensor times start at 0; got t={int(ev['t'][0])} ns "
                             "(subtract the first time)")
        self.events = ev
        self.width, self.height = int(width), int(height)
        self.loop = bool(loop)
        last = int(ev["t"][-1]) if ev.size else 0
        self.period_ns = int(period_ns) if period_ns is not None else last + 1000
        if self.loop and (self.period_ns <= last):
            raise InputError(f"{source}: loop period {self.period_ns} ns must exceed the last "
                             f"event time {last} ns")
        self.c_pos = self.c_neg = None
        self._t = -1

    @property
    def t_ns(self) -> int:
        """-1 before the first call (so events at t = 0 are handed out), then the last t."""
        return self._t

    def set_thresholds(self, c_pos: float, c_neg: float) -> None:
        """Recorded only: a given stream does not depend on thresholds."""
        self.c_pos, self.c_neg = float(c_pos), float(c_neg)

    def restart(self) -> None:
        self._t = -1

    def events_until(self, t_ns: int) -> np.ndarray:
        t_ns = int(t_ns)
        if t_ns <= self._t:
            return empty_events()
        a, self._t = self._t, t_ns
        t = self.events["t"]
        if not self.loop:
            i, j = np.searchsorted(t, [a, t_ns], side="right")
            return self.events[i:j].copy()
        P = self.period_ns
        out = []
        k0, k1 = max(a, 0) // P, t_ns // P
        for k in range(k0, k1 + 1):                     # periods touched (few per call)
            lo, hi = a - k * P, t_ns - k * P
            i, j = np.searchsorted(t, [lo, hi], side="right")
            if j > i:
                part = self.events[i:j].copy()
                part["t"] += np.int64(k * P)
                out.append(part)
        return np.concatenate(out) if out else empty_events()


class SceneEventSource(EventSource):
    """Events of a simulated scene seen by a static camera (see the module docstring).

    ``scene``: preset name or YAML path (or a loaded Scene); ``view``: index of the scene's
    training ring pose the camera sits at; ``fov_deg``: default the scene's; ``mode`` /
    ``rate_hz`` / ``tolerance_c`` / ``min_step_ns`` / ``max_step_ns``: simulate_renderer's
    sampling; ``supersample``: the renderer's.
    """

    def __init__(self, scene="fork", width: int = 640, height: int = 480, *, view: int = 0,
                 c_pos: float = 0.2, c_neg: float = 0.2, fov_deg: float | None = None,
                 loop: bool = True, chunk_ns: int = DEFAULT_CHUNK_NS, supersample: int = 1,
                 mode: str = "fixed", rate_hz: float | None = 1000.0, tolerance_c: float = 0.1,
                 min_step_ns: int = 10_000, max_step_ns: int = 5_000_000,
                 refractory_ns: int = 0, seed: int = 0):
        from evdnerf_ros.geometry.camera import PinholeCamera
        from evdnerf_ros.sim.motion import image_travel
        from evdnerf_ros.sim.render import SceneRenderer
        from evdnerf_ros.sim.scene import Scene, load_scene

        self.scene = scene if isinstance(scene, Scene) else load_scene(scene)
        self.width, self.height = int(width), int(height)
        fov = self.scene.cameras.fov_deg if fov_deg is None else float(fov_deg)
        self.camera = PinholeCamera.from_fov(self.width, self.height, fov)
        poses = self.scene.camera_poses("train")
        if not 0 <= int(view) < len(poses):
            raise InputError(f"{self.scene.source}: view {view} does not exist; the scene's ring "
                             f"has views 0..{len(poses) - 1}")
        self.T_world_cam = np.asarray(poses[int(view)], np.float64)
        self.renderer = SceneRenderer(self.scene, self.camera, supersample)
        self.loop = bool(loop)
        if int(chunk_ns) < 1000 or int(chunk_ns) % 1000:
            raise InputError(f"chunk_ns {chunk_ns}: use a positive whole number of microseconds")
        self.chunk_ns = int(chunk_ns)
        self.period_ns = int(self.scene.duration_ns)
        if mode == "fixed" and rate_hz is None:
            raise InputError("SceneEventSource: mode='fixed' needs rate_hz (frames per second)")
        if self.period_ns <= 0:
            raise InputError(f"{self.scene.source}: the scene has no duration")
        self._sampling = dict(mode=mode, rate_hz=rate_hz, tolerance_c=tolerance_c,
                              min_step_ns=int(min_step_ns), max_step_ns=int(max_step_ns))
        self._gen_args = dict(refractory_ns=int(refractory_ns), seed=int(seed))
        self.c_pos, self.c_neg = float(c_pos), float(c_neg)
        span = self.scene.motion_span_ns()
        self._motion = None if span is None else (max(span[0], self.scene.start_ns),
                                                  min(span[1], self.scene.end_ns))
        pose = self.T_world_cam
        self._travel = (None if self._motion is None or mode != "adaptive" else
                        image_travel(self.scene, self.camera, lambda t: pose, self._motion[0],
                                     self._motion[1], int(min_step_ns)))
        self._pending = empty_events()          # generated but not handed out yet
        self.restart()

    # state -----------------------------------------------------------------------------
    @property
    def t_ns(self) -> int:
        return self._handed

    @property
    def thresholds(self) -> tuple[float, float]:
        return self.c_pos, self.c_neg

    def _new_generator(self):
        from evdnerf_ros.sim import EventGenerator
        return EventGenerator(self.width, self.height, c_pos=self.c_pos, c_neg=self.c_neg,
                              **self._gen_args)

    def restart(self) -> None:
        self.gen = self._new_generator()
        self.gen.reset(self._render(0), 0)
        self._generated = 0                    # sensor time the generator has reached
        self._handed = 0
        self._pending = empty_events()

    def set_thresholds(self, c_pos: float, c_neg: float) -> None:
        """New ON / OFF thresholds from the current generation time on (each pixel's
        reference level restarts at its current log intensity)."""
        from evdnerf_ros.sim.noise import MIN_THRESHOLD
        for name, v in (("c_pos", c_pos), ("c_neg", c_neg)):
            if not np.isfinite(v) or v < MIN_THRESHOLD:
                raise InputError(f"threshold {name}={v}: must be >= {MIN_THRESHOLD}")
        if (float(c_pos), float(c_neg)) == (self.c_pos, self.c_neg):
            return
        self.c_pos, self.c_neg = float(c_pos), float(c_neg)
        last = self.gen.last_log()
        self.gen = self._new_generator()
        self.gen.reset_log(last, self._generated)

    # generation --------------------------------------------------------------------------
    def _scene_time(self, t_sensor: int) -> int:
        if self.loop:
            return self.scene.start_ns + int(t_sensor) % self.period_ns
        return self.scene.start_ns + min(int(t_sensor), self.period_ns)

    def _render(self, t_sensor: int) -> np.ndarray:
        return self.renderer(self.T_world_cam, self._scene_time(t_sensor))

    def _moving(self, a: int, b: int) -> bool:
        """Whether anything moves in sensor interval [a, b] (within one period)."""
        if self._motion is None:
            return False
        sa, sb = self._scene_time(a), self._scene_time(b)
        if sb < sa:                             # b is the period's end
            sb = self.scene.end_ns
        return sa < self._motion[1] and sb > self._motion[0]

    def _generate(self, a: int, b: int) -> np.ndarray:
        """Events on (a, b], a..b inside one period (b may be its end)."""
        from evdnerf_ros.events.logmap import log_intensity
        from evdnerf_ros.sim import simulate_renderer
        base = a - (self._scene_time(a) - self.scene.start_ns)  # sensor time of period start
        if not self._moving(a, b):
            st = min(self.scene.start_ns + (b - base), self.scene.end_ns)
            return self.gen.step_log(log_intensity(self.renderer(self.T_world_cam, st),
                                                   self.gen.eps), b)
        travel = None
        if self._travel is not None:
            tr, s0 = self._travel, self.scene.start_ns
            travel = lambda x, y: tr(s0 + (x - base), s0 + (y - base))  # noqa: E731

        def render(t):
            st = self.scene.start_ns + (t - base)   # no wrap inside a period
            return self.renderer(self.T_world_cam, min(st, self.scene.end_ns))
        ev, _stats = simulate_renderer(render, a, b, self.gen, travel_px=travel,
                                       **self._sampling)
        return ev

    def _advance(self, t_end: int) -> None:
        from evdnerf_ros.events.codecs import quantize_to_us
        out = [self._pending]
        while self._generated < t_end:
            a = self._generated
            b = min(a + self.chunk_ns, max(t_end, a + 1000))
            b = -(-b // 1000) * 1000                       # whole microseconds
            if self.loop:                                  # stop at the period boundary
                nxt = (a // self.period_ns + 1) * self.period_ns
                b = min(b, nxt)
            elif a >= self.period_ns:                      # after a non-looping scene: static
                b = max(b, a + 1000)
            ev = self._generate(a, b)
            self._generated = b
            if ev.size:
                out.append(quantize_to_us(ev))
        self._pending = np.concatenate(out) if len(out) > 1 else out[0]

    def events_until(self, t_ns: int) -> np.ndarray:
        t_ns = int(t_ns)
        if t_ns <= self._handed:
            return empty_events()
        if self._generated < t_ns:
            self._advance(t_ns)
        p = self._pending
        j = int(np.searchsorted(p["t"], t_ns, side="right"))
        out, self._pending = p[:j], p[j:]
        self._handed = t_ns
        return out.astype(EVENT_DTYPE, copy=False)


class CenteredSource(EventSource):
    """``inner``'s events (a smaller sensor) placed at the centre of a ``width`` x ``height``
    sensor: a twin streams a scene rendered at a size this machine renders in real time, the rest
    of its pixel array quiet (``evdnerf camera ... --virtual MODEL --scene-size WxH``)."""

    def __init__(self, inner: EventSource, width: int, height: int):
        if inner.width > width or inner.height > height:
            raise InputError(f"a {inner.width}x{inner.height} scene does not fit a {width}x{height} sensor; "
                             "choose a smaller scene size")
        self.inner = inner
        self.width, self.height = int(width), int(height)
        self.dx, self.dy = (self.width - inner.width) // 2, (self.height - inner.height) // 2

    @property
    def t_ns(self) -> int:
        return self.inner.t_ns

    def events_until(self, t_ns: int) -> np.ndarray:
        ev = self.inner.events_until(t_ns)
        ev["x"] += np.uint16(self.dx)
        ev["y"] += np.uint16(self.dy)
        return ev

    def set_thresholds(self, c_pos: float, c_neg: float) -> None:
        self.inner.set_thresholds(c_pos, c_neg)

    def restart(self) -> None:
        self.inner.restart()

    def ready_ns(self, t_ns: int) -> int:
        return self.inner.ready_ns(t_ns)


def live_sensor_us(source: EventSource, t0_ns: int, latency_us: int) -> int:
    """The sensor time (us) a live twin streams up to now: the wall clock since its sensor zero
    (``t0_ns``, time.monotonic_ns()) less its pipeline ``latency_us``, and no further than the
    source has rendered (``ready_ns``)."""
    now = (time.monotonic_ns() - t0_ns) // 1000 - latency_us
    return min(now, source.ready_ns(1000 * now) // 1000)


class EmittedTruth:
    """What a twin has streamed, in order: its truth for tests and benchmarks. A twin appends to
    ``_emitted`` / ``_emitted_tr`` under its ``lock`` as it encodes."""

    _emitted: list
    _emitted_tr: list
    _t0_ns: int

    @property
    def sensor_zero_host_ns(self) -> int:
        """time.monotonic_ns() at the twin's sensor time 0 (its clock's truth)."""
        return self._t0_ns

    def emitted_events(self) -> np.ndarray:
        with self.lock:
            return np.concatenate(self._emitted) if self._emitted else empty_events()

    def emitted_triggers(self) -> np.ndarray:
        from evdnerf_ros.events.types import empty_triggers

        with self.lock:
            return np.concatenate(self._emitted_tr) if self._emitted_tr else empty_triggers()
