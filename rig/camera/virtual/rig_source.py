"""What a camera twin sees on the closed-loop virtual rig: the scene at the joint angles the
firmware actually commands.

``RigDrivenSource`` renders a scene whose one servo joint (the object with a ``servo`` hinge in
the scene file) follows the commanded angle of the virtual Arduino's D9 pulses, seen from the
view the turntable's D10 angle makes, at the twin's sensor time mapped to host time through the
twin's own clock (``zero_host_ns()``: the host time of sensor time 0). The joint tracks come from
a :class:`rig.pin_feed.PinFeed`; nothing of the scene's stored RUN profile is used, so a profile
changed with ``SET PROFILE`` is what the camera sees.

Cost follows the data: while neither joint moves, nothing is rendered (the generator only
advances); while one moves, frames at ``rate_hz`` are rendered on a fixed grid and joined by the
exact generator (as ``SceneEventSource``'s fixed mode). "Moves" means more than ``STILL_DEG``
from the angle last rendered: the harness's pin edges carry host times, whose jitter makes a
still servo's pulse widths wobble by about a microsecond (0.1 deg), which a real servo's dead
band ignores too; a camera that streams for a whole session would otherwise have its scene
rendered without end and fall ever further behind real time.  Generation runs in its own thread, ahead of
what the twin has streamed (``ready_ns``): the twin streams only what is rendered, so a machine
that renders slower than real time makes the stream lag, never the camera's control requests wait.
Frames are rendered only once the feed knows the joints beyond their time (the firmware's frames
come every 20 ms); if the harness falls behind for longer than ``max_wait_s``, the last known
angles are held and the chunk is counted in ``late_renders`` and, per stream (each sensor-time
zero the twin starts: one per recorded view), in ``late_by_stream`` (never silent: that view's
events are not the scene's, so its true-scene reference is not claimed).
"""

from __future__ import annotations

import math
import threading
import time

import numpy as np

from evdnerf_ros.errors import InputError
from evdnerf_ros.events.types import EVENT_DTYPE, empty_events

from ...turntable import turntable_pose
from .scene_source import DEFAULT_CHUNK_NS, EventSource

#: A joint closer than this (deg) to the angle last rendered is still (module doc): above the
#: pin edges' jitter (~0.1 deg), within a hobby servo's dead band (1-8 us of pulse, 0.2-1.4 deg).
STILL_DEG = 0.25


def servo_joint(scene):
    """The scene's one servo-driven object; other moving objects are refused (the rig moves
    nothing else)."""
    from evdnerf_ros.geometry.trajectory import HingeMotion

    servos = [o for o in scene.all_objects() if o.servo is not None]
    others = [o.name for o in scene.all_objects() if o.motion is not None and o.servo is None]
    if len(servos) != 1 or others or not isinstance(servos[0].motion, HingeMotion):
        raise InputError(f"{scene.source}: the virtual rig drives scenes whose only motion is one servo "
                         f"hinge (found servo joints {[o.name for o in servos]}, other moving objects "
                         f"{others}); use a scene such as fork")
    return servos[0]


class RigDrivenSource(EventSource):
    """See the module docstring. ``view``: the scene's ring view the camera sits at while the
    turntable is at ``turntable_home_deg``. Call :meth:`close` to stop its thread."""

    def __init__(self, scene, width: int, height: int, feed, *, view: int = 0, c_pos: float = 0.2,
                 c_neg: float = 0.2, rate_hz: float = 500.0, supersample: int = 1,
                 turntable_home_deg: float = 90.0, chunk_ns: int = 10_000_000,
                 lookahead_ns: int = 50_000_000, max_wait_s: float = 1.0):
        from evdnerf_ros.geometry.camera import PinholeCamera
        from evdnerf_ros.geometry.trajectory import HingeMotion
        from evdnerf_ros.sim.render import SceneRenderer
        from evdnerf_ros.sim.scene import Scene, load_scene

        self.scene = scene if isinstance(scene, Scene) else load_scene(scene)
        joint = servo_joint(self.scene)
        zero = float(joint.servo.zero_deg)
        track = feed.servo
        joint.motion = HingeMotion(joint.motion.axis, joint.motion.pivot,
                                   lambda t: math.radians(track.deg(int(t)) - zero), None)
        self.joint_name = joint.name
        self.feed = feed
        self.width, self.height = int(width), int(height)
        self.camera = PinholeCamera.from_fov(self.width, self.height, self.scene.cameras.fov_deg)
        poses = self.scene.camera_poses("train")
        if not 0 <= int(view) < len(poses):
            raise InputError(f"{self.scene.source}: view {view} does not exist (ring views 0..{len(poses) - 1})")
        self.T_home = np.asarray(poses[int(view)], np.float64)
        self.turntable_home_deg = float(turntable_home_deg)
        self.renderer = SceneRenderer(self.scene, self.camera, int(supersample))
        if not rate_hz > 0:
            raise InputError(f"rate_hz must be > 0, got {rate_hz}")
        self.rate_hz = float(rate_hz)
        # frames on a fixed grid, so the cost follows rate_hz, not how often the twin asks
        self.frame_ns = max(1000, int(round(1e9 / self.rate_hz / 1000)) * 1000)
        self.chunk_ns = max(self.frame_ns, int(chunk_ns) // self.frame_ns * self.frame_ns)
        self.lookahead_ns = int(lookahead_ns)
        self.max_wait_s = float(max_wait_s)
        self.thresholds = (float(c_pos), float(c_neg))
        self.zero_host_ns = lambda: 0          # set by the rig: the twin's host time of sensor 0
        self.renders = 0
        self.late_renders = 0
        self.late_by_stream: dict[int, int] = {}     # stream (``stream``) -> its late renders
        self.error: BaseException | None = None      # why the renderer thread stopped, if it did
        self._cv = threading.Condition()
        self._epoch = 0
        self._stop = False
        self.restart()
        self._thread = threading.Thread(target=self._run, name="rig-source", daemon=True)
        self._thread.start()

    @property
    def stream(self) -> int:
        """The stream now generated: a new number at every ``restart`` (the twin's sensor-time zero)."""
        return self._epoch

    # --- EventSource (called by the twin, under its lock) -------------------------------------
    @property
    def t_ns(self) -> int:
        return self._handed

    def restart(self) -> None:
        with self._cv:
            self._epoch += 1
            self._gen = None
            self._rendered_deg = None       # (servo, turntable) angles of the last render
            self._gen_thresholds = None
            self._ready = 0                 # sensor time generated up to
            self._wanted = 0                # furthest sensor time the twin asked about
            self._handed = 0
            self._pending = [empty_events()]
            self._cv.notify_all()

    def set_thresholds(self, c_pos: float, c_neg: float) -> None:
        self.thresholds = (float(c_pos), float(c_neg))     # from the next generated chunk on

    def ready_ns(self, t_ns: int) -> int:
        with self._cv:
            if t_ns > self._wanted:
                self._wanted = int(t_ns)
                self._cv.notify_all()
            return min(int(t_ns), self._ready)

    def events_until(self, t_ns: int) -> np.ndarray:
        with self._cv:
            t_ns = min(int(t_ns), self._ready)
            if t_ns <= self._handed:
                return empty_events()
            p = np.concatenate(self._pending) if len(self._pending) > 1 else self._pending[0]
            j = int(np.searchsorted(p["t"], t_ns, side="right"))
            self._pending = [p[j:]]
            self._handed = t_ns
            return p[:j].astype(EVENT_DTYPE, copy=False)

    def close(self) -> None:
        with self._cv:
            self._stop = True
            self._cv.notify_all()
        self._thread.join(5)

    # --- rendering ----------------------------------------------------------------------------
    def pose_at(self, host_ns: int) -> np.ndarray:
        return turntable_pose(self.T_home, self.feed.turntable.deg(int(host_ns)), self.turntable_home_deg)

    def render_at(self, host_ns: int) -> np.ndarray:
        self.renders += 1
        return self.renderer(self.pose_at(host_ns), int(host_ns))

    def _moving(self, a_ns: int, b_ns: int, rendered) -> bool:
        """Whether a joint is more than STILL_DEG from ``rendered`` (its angles at the last
        render) anywhere on the render grid of [a_ns, b_ns]."""
        if rendered is None:
            return True
        t = np.append(np.arange(a_ns, b_ns, self.frame_ns, dtype=np.int64), b_ns)
        return any(float(np.max(np.abs(track.deg(t) - deg))) > STILL_DEG
                   for track, deg in zip((self.feed.servo, self.feed.turntable), rendered))

    def _angles(self, host_ns: int) -> tuple[float, float]:
        return float(self.feed.servo.deg(int(host_ns))), float(self.feed.turntable.deg(int(host_ns)))

    def _wait_for_joints(self, host_ns: int, stream: int) -> None:
        """Until the feed knows both joints at or beyond ``host_ns`` (frames come every 20 ms); a
        chunk of ``stream`` that waited ``max_wait_s`` in vain is counted late."""
        deadline = time.monotonic() + self.max_wait_s
        while not self._stop:
            s, t = self.feed.servo.last_ns, self.feed.turntable.last_ns
            if s is not None and t is not None and min(s, t) >= host_ns:
                return
            if time.monotonic() >= deadline:
                self.late_renders += 1
                self.late_by_stream[stream] = self.late_by_stream.get(stream, 0) + 1
                return
            time.sleep(0.001)

    def _run(self) -> None:
        try:
            self._generate_forever()
        except BaseException as exc:  # noqa: BLE001 - reported: the twin's stream stops advancing
            self.error = exc
            import sys
            import traceback

            print(f"virtual rig: the scene renderer failed: {exc!r}", file=sys.stderr)
            traceback.print_exc()

    def _generate_forever(self) -> None:
        from evdnerf_ros.events.codecs import quantize_to_us
        from evdnerf_ros.sim import EventGenerator, simulate_renderer

        while True:
            with self._cv:
                while not self._stop and self._wanted <= self._ready:
                    self._cv.wait(0.1)
                if self._stop:
                    return
                epoch, a, gen, rendered = self._epoch, self._ready, self._gen, self._rendered_deg
                target = self._wanted + self.lookahead_ns
            zero = int(self.zero_host_ns())
            # never ahead of real time: the joints are not known there yet
            target = min(target, time.monotonic_ns() - zero)
            b = min(-(-target // self.frame_ns) * self.frame_ns, a + self.chunk_ns)
            if b <= a:
                time.sleep(0.001)
                continue
            th = self.thresholds
            if gen is None:
                self._wait_for_joints(zero, epoch)
                gen = EventGenerator(self.width, self.height, c_pos=th[0], c_neg=th[1])
                gen.reset(self.render_at(zero), 0)
                rendered = self._angles(zero)
            elif th != self._gen_thresholds:        # new biases: each pixel's reference restarts
                last = gen.last_log()
                gen = EventGenerator(self.width, self.height, c_pos=th[0], c_neg=th[1])
                gen.reset_log(last, a)
            self._wait_for_joints(zero + b, epoch)
            ev = None
            if self._moving(zero + a, zero + b, rendered):
                ev, _ = simulate_renderer(lambda t: self.render_at(zero + t), a, b, gen,
                                          mode="fixed", rate_hz=self.rate_hz)
                ev = quantize_to_us(ev) if ev.size else None
                rendered = self._angles(zero + b)
            else:                                   # nothing moves: the image is the last one
                gen.step_log(gen.last_log(), b)
            with self._cv:
                if self._epoch != epoch:            # restarted meanwhile: this chunk is void
                    continue
                self._gen, self._gen_thresholds, self._ready = gen, th, b
                self._rendered_deg = rendered
                if ev is not None:
                    self._pending.append(ev)
