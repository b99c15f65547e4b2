"""The `evdnerf demo` session from the closed-loop virtual rig (entry point
``evdnerf.session_sources: virtual-rig``; evdnerf_ros never imports rig, so the demo finds this
through the entry point).

``capture_demo_session(out_dir, log=...)`` captures the demo's scene (the servo-swung ``fork``) on
the virtual rig (rig.virtual_rig: the real firmware in simavr, a camera twin on emulated USB, the
scene driven by the firmware's pins) with `evdnerf capture` in a child process, as
`evdnerf capture --virtual` does: one bag per turntable view, every ``VAL_EVERY``-th a validation
view.  The rig knows its scene, so the session.yaml the capture wrote is then rewritten (through
the session layout's one writer) with that truth, in the keys a simulated session uses:

* ``source``: ``kind: capture`` (it is one) plus ``rig: virtual``, ``scene`` / ``scene_ref`` (the
  preset) and ``supersample`` (the twin's renderer's);
* ``servo.start_ns_scene`` and ``time`` (scene / motion span): the scene's clock, whose servo
  profile is the firmware's stored RUN profile (checked against the firmware's);
* per view ``ground_truth.clock_offset_ns``: the view clock's reading at scene time 0, from the
  twin's record of where it put the firmware's trigger pulse (the motion's START, scene time
  ``start_ns_scene``) on its sensor clock, and the view's sensor-to-bag time offset; a view
  whose edge the twin placed late (the machine fell behind real time) gets none; and
  ``ground_truth.sensor_zero_scene_ns``, the scene time of the twin's sensor zero in that view,
  and ``ground_truth.stale_renders``, the chunks of that view's stream the twin rendered with
  stale joint angles (the harness fell behind real time: then its events are not the scene's,
  and convert claims no true scene for the set);
* ``rig.virtual``: the twin, scene size, render rate, ``frame_ns`` (its renders lie on the grid
  of sensor-time multiples of this, joined linearly in log by its event generator) and
  ``scene_window`` (x y w h: where the scene sits on the sensor, the window to convert with
  ``--crop``), and the late counts.  The true-scene reference renders on that same grid.
"""

from __future__ import annotations

import shutil
import subprocess
import tempfile
from dataclasses import dataclass, field, replace
from pathlib import Path

from evdnerf_ros import __version__
from evdnerf_ros.errors import EvdnerfError, InputError
from evdnerf_ros.session.recorder import servo_record, session_document, write_session_yaml

from .capture import JOINT, CaptureOptions

SOURCE_NAME = "virtual-rig"
#: The scene the rig drives: the simulated demo's preset.
SCENE = "fork"
#: Rendered at this size in the sensor's centre; real time on 2 busy cores with the rate below.
SCENE_SIZE = (48, 36)
RATE_HZ = 125.0
#: 25 turntable views over 0..180 deg (7.5 deg apart), every third for validation: 17 training views
#: + 8 validation views, each 7.5 deg from its nearest training view. Measured with 2 min of training
#: (margin pooled at the trained windows; docs/results.md): the demo closed 20 % with this
#: layout, 13 % with 13 views (9 + 4) and 2-7 % with 7 (5 + 2); on one capture with the same
#: validation views, fewer training views closed less (bench_quality.py --rig). With 6 views the
#: last validation view lay 36 deg beyond the last training view: an extrapolation (-32 %).
VIEWS, VAL_EVERY = 25, 3
#: The capture test's short moves: the demo's time goes to training, not to waiting.
CAPTURE = CaptureOptions(views=VIEWS, val_every=VAL_EVERY, turn_ms=300, home_ms=300, pre_roll_s=0.1,
                         settle_s=0.1)
#: The demo's output is never a long wait on a stuck child: the capture of 25 views takes ~80 s.
CAPTURE_TIMEOUT_S = 600.0


def availability() -> tuple[bool, str]:
    """(True, what runs it) when this machine can run the virtual rig, else (False, what is
    missing, naming the Debian packages)."""
    from .camera.virtual.usb import umockdev_available
    from .virtual_arduino import _install_hint, missing_tools

    missing = [p for p in missing_tools() if p != "avrdude"]       # avrdude only flashes
    if shutil.which("make") is None:
        missing.append("make")
    if missing:
        return False, (f"the virtual Arduino (firmware in simavr) needs the Debian packages {' '.join(missing)}: "
                       + _install_hint(missing))
    ok, why = umockdev_available()
    if not ok:
        return False, f"the virtual camera (emulated USB) is unavailable: {why}"
    return True, "simavr (virtual Arduino) and umockdev (virtual camera) are available"


@dataclass
class VirtualRigSource:
    """A session source of `evdnerf demo`: ``available()`` and ``source(out_dir, log=print)``
    (captures the session folder ``out_dir``, returns its session.yaml document)."""

    scene: str = SCENE
    scene_size: tuple[int, int] = SCENE_SIZE
    rate_hz: float = RATE_HZ
    model: str = "evk4"
    options: CaptureOptions = field(default_factory=lambda: replace(CAPTURE))
    name: str = SOURCE_NAME

    def available(self) -> tuple[bool, str]:
        return availability()

    def __call__(self, out_dir, *, log=print) -> dict:
        ok, why = self.available()
        if not ok:
            raise InputError(f"demo source {self.name}: {why}")
        from .capture_cli import RigChoice, spawn_virtual_capture
        from .virtual_rig import VirtualRig

        out_dir = Path(out_dir)
        w, h = self.scene_size
        with VirtualRig(model=self.model, scene=self.scene, scene_size=(w, h), rate_hz=self.rate_hz) as vr, \
                tempfile.TemporaryDirectory(prefix="evdnerf-demo-capture-") as tmp:
            log(f"virtual rig: firmware in simavr on {vr.port}, {self.model} twin (serial {vr.camera_serial}) "
                f"streaming {self.scene} at {w}x{h}; capturing {self.options.views} views")
            proc = spawn_virtual_capture(vr, RigChoice(output=str(out_dir)), self.options, tmp,
                                         stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
            lines = _follow(proc, log)
            if proc.returncode != 0:
                raise EvdnerfError(f"{out_dir}: the virtual-rig capture failed (exit {proc.returncode}):\n"
                                   + "".join(lines[-20:]))
            src = vr.twin.source
            late_edges = sum(not r.on_time for r in vr.trigger_log if r.sensor_ns is not None)
            virtual = {"model": self.model, "scene_size": [int(w), int(h)], "rate_hz": float(self.rate_hz),
                       "frame_ns": int(vr.source.frame_ns), "latency_us": int(vr.latency_us),
                       "scene_window": [int(src.dx), int(src.dy), int(src.inner.width), int(src.inner.height)],
                       "late_trigger_edges": int(late_edges), "late_renders": int(vr.source.late_renders)}
            if late_edges or vr.source.late_renders:
                log(f"virtual rig: {late_edges} trigger edges placed late, {vr.source.late_renders} chunks rendered "
                    "with stale joint angles (the machine fell behind real time)")
            return add_truth(out_dir, self.scene, vr.profile, vr.trigger_log, virtual, log=log,
                             late_by_stream=dict(vr.source.late_by_stream))


def _follow(proc, log, timeout_s: float = CAPTURE_TIMEOUT_S) -> list[str]:
    """Pass the capture's output on, line by line; stop it (its views are closed validly) when
    it runs past ``timeout_s`` or this process is interrupted."""
    import threading

    lines: list[str] = []
    timer = threading.Timer(timeout_s, proc.terminate)
    timer.start()
    try:
        for line in proc.stdout:
            lines.append(line)
            log(f"  capture: {line.rstrip()}")
        proc.wait()
    except BaseException:
        proc.terminate()
        proc.wait()
        raise
    finally:
        timer.cancel()
    return lines


def add_truth(out_dir, scene_ref: str, profile, trigger_log, virtual: dict, *, log=print,
              late_by_stream: dict | None = None) -> dict:
    """Rewrite ``out_dir``'s session.yaml with what the virtual rig knows (module docstring);
    returns the document written. ``late_by_stream``: the camera twin's chunks rendered with stale
    joint angles per stream (``RigDrivenSource.late_by_stream``), each view's recorded as its
    ``ground_truth.stale_renders``."""
    from evdnerf_ros.io.rosbag2 import read_events
    from evdnerf_ros.session.layout import load_session
    from evdnerf_ros.sim.joint import joint_record
    from evdnerf_ros.sim.scene import load_scene

    from .camera.virtual.rig_source import servo_joint

    session = load_session(out_dir)
    data = session.data
    silent = [v["name"] for v in data["views"] if not v.get("events")]
    if silent:
        raise EvdnerfError(f"{out_dir}: views {silent} recorded no events on the virtual rig (the camera twin "
                           "streamed nothing while the servo moved); nothing to train on from them")
    scene = load_scene(scene_ref)
    servo = servo_joint(scene).servo
    span = scene.motion_span_ns()
    # the scene's clock is the truth only if its servo runs what the firmware ran
    if span is None or abs((span[1] - span[0]) - int(profile.duration_ns)) > 1_000_000:
        raise InputError(f"{scene_ref}: the scene's servo motion ({None if span is None else span[1] - span[0]} ns) "
                         f"is not the firmware's stored RUN profile ({int(profile.duration_ns)} ns); restore the "
                         "firmware's profile (EEPROM) or use a scene with the firmware's profile")
    start_ns_scene = int(servo.start_ns)
    # one placed trigger edge per view, in capture order (HOME and the turntable raise none)
    placed = [r for r in trigger_log if r.sensor_ns is not None]
    if len(placed) != len(session.views):
        log(f"virtual rig: {len(placed)} trigger edges reached the twin for {len(session.views)} views; "
            "no true clock offsets recorded")
        placed = [None] * len(session.views)
    views = []
    for record, view in zip(placed, data["views"]):
        gt = None
        if record is not None:
            gt = {"trigger_sensor_ns": int(record.sensor_ns), "trigger_on_time": bool(record.on_time),
                  "clock_offset_ns": None, "sensor_zero_scene_ns": None,
                  "stale_renders": int((late_by_stream or {}).get(record.stream, 0))}
            if record.on_time:
                # the view clock = the bag's time offset + sensor time; the edge is scene time
                # start_ns_scene, so the clock reads start_ns_scene + offset there
                time_offset = int(read_events(Path(out_dir) / view["bag"]).time_offset_ns)
                gt["clock_offset_ns"] = time_offset + int(record.sensor_ns) - start_ns_scene
                # the twin renders on a grid of its own sensor time (every rig.virtual.frame_ns
                # from its stream's zero): sensor zero is this scene time
                gt["sensor_zero_scene_ns"] = start_ns_scene - int(record.sensor_ns)
        views.append(dict(view, ground_truth=gt))
    source = dict(data.get("source") or {}, kind="capture", software_version=__version__, rig="virtual",
                  scene=scene.name, scene_ref=str(scene_ref), supersample=1)
    doc = session_document(
        source=source, rig=dict(data["rig"], virtual=virtual), camera=data["camera"],
        servo=servo_record((data.get("servo") or {}).get("joint", JOINT), start_ns_scene=start_ns_scene,
                           **(joint_record(scene) or {})),
        thresholds=data["thresholds"],
        time={"scene_start_ns": int(scene.start_ns), "scene_end_ns": int(scene.end_ns),
              "motion_start_ns": int(span[0]), "motion_end_ns": int(span[1])},
        options=data.get("options"), views=views)
    write_session_yaml(out_dir, doc, overwrite=True)
    return doc


#: The entry point `evdnerf.session_sources: virtual-rig` (setup.py).
capture_demo_session = VirtualRigSource()

__all__ = ["VirtualRigSource", "capture_demo_session", "availability", "add_truth", "SCENE", "SCENE_SIZE"]
