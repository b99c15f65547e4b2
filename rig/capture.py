"""Capture a session: one rosbag2 per viewpoint while the servo firmware runs its stored motion.

Per view: turn the turntable to the view's angle (or ask the user to move the camera), bring the
servo to the profile's start angle, start the camera, record a pre-roll, send ``RUN``, keep
recording until the camera's stream has passed the firmware's ``DONE`` plus the settle time, stop.
Each view's bag goes through the session recorder (evdnerf_ros.session.recorder) with the standard
topics: the camera's events in its own encoding passed through untouched (EVT 3.0 transfers as
metavision_driver records them, libcaer packets as libcaer_driver publishes them, trigger edges of a
libcaer camera on their own topic), CameraInfo, the view's pose, the servo's commanded joint angle
at every frame of the motion (JointState; the firmware's own integer profile), START / DONE
(TimeReference). session.yaml is rewritten after every view: rig geometry, camera model / serial /
firmware, intrinsics (a calibration file, or nominal from a field of view), per-view pose and
turntable angle, the thresholds, the biases, the software version.

The view's clock is what a reader of its bag decodes (the wall-clock time of the sensor's zero
plus sensor time, rig.camera.record); START / DONE / joint states are placed on it through the servo's
ping-fitted clock and the camera's arrival-fitted clock, both on the host's monotonic clock. The
camera's trigger input sees the firmware's trigger pulse at each motion's first frame, which is
what `evdnerf sync` aligns the views by.

Faults: SIGINT / SIGTERM end the current view's bag validly (everything received is in it), mark
the view ``complete: false`` in session.yaml and re-raise; ``resume=True`` records again only the
views not complete. A camera unplugged or a servo that stops answering mid-view raises a clear
error after the view's bag is closed and marked incomplete; a ``DONE`` that never comes raises
ServoTimeout with the servo's last status. Finished views are never touched.
"""

from __future__ import annotations

import shutil
import threading
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import yaml

from evdnerf_ros import __version__
from evdnerf_ros.errors import InputError, OutputExistsError
from evdnerf_ros.options import option
from evdnerf_ros.session.recorder import (ViewRecorder, camera_record, servo_record, session_document,
                                          view_record, write_session_yaml)

from .camera.errors import CameraError
from .camera.record import ChunkWriter
from .servo import ServoError, ServoTimeout
from .turntable import turntable_pose, view_azimuth_deg

#: The servo joint's name in JointState messages and session.yaml.
JOINT = "servo"
STORAGES = ("mcap", "sqlite3")
#: After DONE, a camera stream quiet for this long (s) has nothing more to record, once it has
#: come within QUIET_NEAR_END_NS of the motion's end (a motion's last events lie at its end).
QUIET_S = 0.5
QUIET_NEAR_END_NS = 100_000_000
#: --repeats: the extra takes' folder, the report, and how the takes are compared
#: With a trigger input but no edge seen yet, the clocks' estimate of START is trusted only once
#: the stream has passed it by this much (ns): a rig without a trigger cable.
TRIGGER_GRACE_NS = 1_000_000_000
#: After DONE + settle, a stream still this far (s) from reaching it is a fault (the view is incomplete).
STREAM_LAG_S = 15.0
REPEATS = "repeats"
REPEATABILITY = "repeatability.json"
REPEAT_BIN_NS = 5_000_000         # coarser than a twin's render grid, finer than a servo's motion
REPEAT_WINDOWS = 16


@dataclass
class CaptureOptions:
    """Every knob of the capture node / `evdnerf capture` (defaults in one place)."""

    camera_serial: str | None = option(None, "camera serial number", kind=str, none_help="the first camera found")
    camera_model: str | None = option(None, "camera model (DVXplorer, DAVIS346, EVK4)", kind=str,
                                      none_help="any")
    bias_file: str | None = option(None, "bias file (.bias, as Metavision writes it) applied before recording", kind=str,
                                none_help="the camera's defaults")
    servo_port: str | None = option(None, "serial port of the servo board", kind=str,
                                    none_help="required on a real rig")
    views: int = option(4, "viewpoints to record", low=1, high=360)
    turntable_range_deg: tuple = option((0.0, 180.0), "turntable angles of the first and last view (evenly "
                                        "spaced between)", nargs=2, kind=float, low=0, high=180,
                                        metavar=("FIRST", "LAST"))
    val_every: int = option(0, "every N-th view is a validation view (0: none)", low=0, high=360)
    repeats: int = option(1, "takes per view: N > 1 records each view N times (the extra takes in "
                             "SESSION/repeats/) and reports their run-to-run agreement in repeatability.json",
                          low=1, high=100)
    turntable: bool = option(True, "the turntable servo turns the scene between views (off: the capture "
                                   "waits for you to move the camera)")
    turn_ms: int = option(1500, "turntable move duration (ms)", low=1, high=65535)
    home_ms: int = option(1000, "servo move to the profile's start angle (ms)", low=1, high=65535)
    settle_s: float = option(0.3, "recording after DONE (s)", low=0, high=60)
    pre_roll_s: float = option(0.3, "recording before RUN (s)", low=0, high=60)
    done_timeout_s: float = option(3.0, "wait this long for DONE beyond the profile's duration (s)",
                                   low=0.1, high=600)
    ring_radius_m: float = option(4.0, "camera distance from the turntable axis (m)", low=0, low_open=True,
                                  high=1e3)
    elevation_deg: float = option(15.0, "camera elevation above the look-at point (deg)", low=-89, high=89)
    look_at: tuple = option((0.0, 0.0, -0.3), "point the camera looks at (m, world frame)", nargs=3,
                            kind=float, low=-1e3, high=1e3, metavar=("X", "Y", "Z"))
    home_azimuth_deg: float = option(0.0, "camera azimuth when the turntable is at 90 deg", low=-360, high=360)
    calibration: str | None = option(None, "intrinsics file (evdnerf calibrate, or a ROS camera_info YAML)",
                                     kind=str, none_help="nominal, from --fov-deg")
    fov_deg: float = option(40.0, "horizontal field of view for nominal intrinsics", low=1, high=179)
    c_pos: float = option(0.2, "ON contrast threshold recorded in session.yaml", low=0, low_open=True, high=10)
    c_neg: float = option(0.2, "OFF contrast threshold recorded in session.yaml", low=0, low_open=True, high=10)
    storage: str = option("mcap", "rosbag2 storage", choices=STORAGES)

    def check(self) -> "CaptureOptions":
        lo, hi = self.turntable_range_deg
        if self.views > 1 and lo == hi:
            raise InputError(f"capture: {self.views} views need a turntable range, got {lo}..{hi} deg")
        return self

    def turntable_angles(self) -> list[float]:
        lo, hi = map(float, self.turntable_range_deg)
        return [lo] if self.views == 1 else [float(a) for a in np.linspace(lo, hi, self.views)]

    def split(self, k: int) -> str:
        return "val" if self.val_every and (k + 1) % self.val_every == 0 else "train"

    def home_pose(self) -> np.ndarray:
        from evdnerf_ros.geometry.camera import CameraRing

        return CameraRing(radius=self.ring_radius_m, elevation_deg=self.elevation_deg,
                          look_at=tuple(self.look_at)).pose_at(self.home_azimuth_deg)


def view_name(k: int) -> str:
    return f"view_{k:02d}"


# =========================================================================== one view


@dataclass
class ViewResult:
    name: str
    complete: bool
    counts: dict
    start_device_us: int | None
    done_device_us: int | None
    duration_s: float
    error: str | None = None
    #: where the view's wall time went (s): camera_start, motion (RUN sent to DONE received),
    #: stream_catch_up (DONE + settle in real time to the camera's stream reaching it: the
    #: camera's latency), camera_stop, bag_close
    timing_s: dict = field(default_factory=dict)


class CaptureInterrupted(KeyboardInterrupt):
    """SIGINT / SIGTERM during a capture: the current view was closed and marked incomplete."""


def record_view(camera, servo, path: Path, *, K, D, pose, options: CaptureOptions, frame_us: int,
                stop: threading.Event, live=None, log=print) -> tuple[ViewResult, BaseException | None]:
    """Record one view (see the module docstring). The bag is closed validly whatever happens;
    returns what was recorded and the camera or servo fault that ended the view early (None when
    it did not; an interrupt is ``stop`` set)."""
    profile = servo.get_profile()
    expected_s = profile.duration_ns / 1e9
    start = done = None
    error: BaseException | None = None
    t0 = time.monotonic()
    with ViewRecorder(path, width=camera.width, height=camera.height, encoding=camera.encoding,
                      storage=options.storage) as rec:
        writer = ChunkWriter(rec, camera, also=[live] if live is not None else ())
        servo.drain_events()
        run_sent = None
        last_chunk = time.monotonic()
        timing = {}
        try:
            tic = time.monotonic()
            camera.start()
            started = time.monotonic()          # the pre-roll counts from here: RUN never precedes it
            timing["camera_start"] = started - tic
            while not stop.is_set():
                chunk = camera.read(timeout_s=0.02)
                if chunk is not None:
                    writer.write(chunk)
                now = time.monotonic()
                if run_sent is None and now - started >= options.pre_roll_s:
                    servo.run(wait=False)
                    run_sent = now
                for ev in servo.drain_events():
                    if ev.motion == "RUN" and ev.kind == "START":
                        start = ev
                    elif ev.motion == "RUN" and ev.kind in ("DONE", "STOPPED") and start is not None:
                        done = ev
                if chunk is not None:
                    last_chunk = now
                if done is not None:
                    # the stream has passed DONE + settle, or has reached the motion's end and been
                    # quiet since (a sensor without activity sends nothing: there is nothing more to
                    # record; a stream still short of the motion's end is late, not quiet)
                    reached = camera.sensor_time_ns
                    end = _sensor_ns_of(writer, camera, servo, start, done.device_us)
                    if now > done.host_recv_ns / 1e9 + options.settle_s + STREAM_LAG_S:
                        raise CameraError(f"{camera.name}: the camera's stream is more than {STREAM_LAG_S:g} s behind "
                                          f"the servo's DONE (it reached {_seconds(reached)}); check the USB "
                                          "link and the machine's load")
                    if (reached is not None and end is not None and reached >= end + int(options.settle_s * 1e9)) \
                            or (now - last_chunk > QUIET_S and now > done.host_recv_ns / 1e9 + options.settle_s
                                and reached is not None and end is not None and reached >= end - QUIET_NEAR_END_NS):
                        timing["motion"] = done.host_recv_ns / 1e9 - run_sent
                        timing["stream_catch_up"] = max(0.0, now - done.host_recv_ns / 1e9 - options.settle_s)
                        break
                elif run_sent is not None and now > run_sent + expected_s + options.done_timeout_s:
                    raise ServoTimeout(f"{servo.port_name}: no {'START' if start is None else 'DONE'} of RUN within "
                                       f"{expected_s + options.done_timeout_s:.1f} s; the servo reports "
                                       f"{_status(servo)}")
        except (CameraError, ServoError) as exc:
            error = exc
        finally:
            tic = time.monotonic()
            try:
                camera.stop()
            except CameraError:
                pass
            timing["camera_stop"] = time.monotonic() - tic
        _write_view_metadata(rec, writer, camera, servo, K=K, D=D, pose=pose, profile=profile,
                             frame_us=frame_us, start=start, done=done)
        tic = time.monotonic()
    timing["bag_close"] = time.monotonic() - tic
    complete = error is None and not stop.is_set() and done is not None
    result = ViewResult(path.name, complete, dict(writer.counts, stats=camera.stats.as_dict()),
                        None if start is None else int(start.device_us),
                        None if done is None else int(done.device_us), time.monotonic() - t0,
                        None if error is None else str(error), {k: round(v, 4) for k, v in timing.items()})
    return result, error


def _sensor_ns_of(writer, camera, servo, start, device_us: int) -> int | None:
    """The camera's sensor time of a servo board time: through the trigger edge of this RUN when
    the camera saw it (exact), else through both fitted clocks (the camera's includes its
    pipeline latency); None while neither is known yet."""
    servo_clock = servo.clock if servo.clock is not None else servo.sync_clock()
    anchor = _trigger_anchor(writer, start, servo_clock)
    if anchor is not None:
        return int(anchor[0] + round((int(device_us) - anchor[1]) * servo_clock.scale))
    try:
        through_clocks = [int(camera.clock.host_ns_to_sensor_ns(servo_clock.to_host_ns(int(us))))
                          for us in (device_us, start.device_us if start is not None else device_us)]
    except Exception:  # noqa: BLE001 - no camera clock fit yet
        return None
    if getattr(camera, "trigger_input_enabled", False):
        # the edge may still be on its way (a stream lagging real time; a clock fit over a
        # lagging stream is off too): wait until the stream is clearly past where it would be
        reached = camera.sensor_time_ns
        if reached is None or reached < through_clocks[1] + TRIGGER_GRACE_NS:
            return None
    return through_clocks[0]


def _seconds(sensor_ns) -> str:
    return "nothing" if sensor_ns is None else f"sensor time {sensor_ns / 1e9:.3f} s"


def _status(servo) -> str:
    try:
        return str(servo.status())
    except Exception as exc:  # noqa: BLE001 - the status is only for the message
        return f"no status ({exc})"


def _write_view_metadata(rec, writer, camera, servo, *, K, D, pose, profile, frame_us, start, done) -> None:
    """CameraInfo and pose at the view's first time; START / DONE and the commanded joint angle of
    every frame of the motion, on the view's clock."""
    first = writer.counts["first_sensor_ns"]
    if first is None:                               # nothing came: there is no view clock
        return
    stamp0 = int(writer.view_ns(first))
    rec.camera_info(K, D, stamp_ns=stamp0)
    rec.pose(pose, stamp_ns=stamp0)
    servo_clock = servo.clock if servo.clock is not None else servo.sync_clock()
    anchor = _trigger_anchor(writer, start, servo_clock)
    if anchor is None:
        try:
            cam_clock = camera.clock
        except Exception:  # noqa: BLE001 - too few samples: no servo times on this view's clock
            return

    def view_ns(device_us):
        d = np.asarray(device_us, np.int64)
        if anchor is not None:      # the trigger edge and START are the same instant
            sensor = anchor[0] + np.rint((d - anchor[1]) * servo_clock.scale).astype(np.int64)
        else:                       # through both clocks (the camera's includes its USB latency)
            sensor = cam_clock.host_ns_to_sensor_ns(servo_clock.to_host_ns(d))
        return writer.view_ns(sensor)

    if start is not None:
        rec.servo_trigger("START", int(view_ns(start.device_us)), int(start.device_us) * 1000)
        frames = int(-(-profile.duration_ns // (frame_us * 1000))) + 1
        k = np.arange(frames, dtype=np.int64)
        stamps = np.atleast_1d(view_ns(int(start.device_us) + k * frame_us))
        for kk, stamp in zip(k.tolist(), stamps.tolist()):
            deg = profile.command_mdeg(kk * frame_us * 1000) / 1000.0
            rec.servo_joint_state([JOINT], [float(np.radians(deg))], int(stamp))
    if done is not None and start is not None:
        rec.servo_trigger("DONE", int(view_ns(done.device_us)), int(done.device_us) * 1000)


def _trigger_anchor(writer, start, servo_clock) -> tuple[int, int] | None:
    """(sensor ns of the trigger edge, device µs of START) when the camera saw the firmware's
    trigger pulse of this RUN (the only servo motion inside a view: the turntable raises no
    trigger and HOME comes before the camera starts): the rising edge nearest to where the clocks
    put START. None without a trigger cable."""
    if start is None or not writer.rising_ns:
        return None
    try:
        guess = writer.device.clock.host_ns_to_sensor_ns(servo_clock.to_host_ns(start.device_us))
    except Exception:  # noqa: BLE001 - no camera clock fit: the first edge
        return writer.rising_ns[0], int(start.device_us)
    return min(writer.rising_ns, key=lambda t: abs(t - guess)), int(start.device_us)


# =========================================================================== the session


def _intrinsics(options: CaptureOptions, camera) -> tuple[np.ndarray, np.ndarray, str]:
    if options.calibration:
        from evdnerf_ros.session.importer import read_calibration

        cal = read_calibration(options.calibration)
        if (cal["width"], cal["height"]) != (camera.width, camera.height):
            raise InputError(f"{options.calibration}: calibrated for {cal['width']}x{cal['height']}, but the "
                             f"camera is {camera.width}x{camera.height}; calibrate this camera")
        return np.asarray(cal["K"], np.float64), np.asarray(cal["D"], np.float64), cal["source"]
    from evdnerf_ros.geometry.camera import PinholeCamera

    K = np.asarray(PinholeCamera.from_fov(camera.width, camera.height, options.fov_deg).K, np.float64)
    return K, np.zeros(5), f"nominal from a {options.fov_deg:g} deg field of view"


def _existing_views(output: Path) -> dict[str, dict]:
    path = output / "session.yaml"
    if not path.is_file():
        return {}
    data = yaml.safe_load(path.read_text()) or {}
    return {v["name"]: v for v in data.get("views") or [] if isinstance(v, dict) and "name" in v}


def capture_session(output, camera, servo, options: CaptureOptions | None = None, *, resume: bool = False,
                    stop: threading.Event | None = None, live=None, log=print) -> dict:
    """Capture every view into the session folder ``output`` with an opened camera driver
    (rig.camera.Device) and an opened servo client (rig.servo.ServoClient); ``live``: a sink that
    also gets every packet (rig.capture_cli.LiveEvents). Returns a summary."""
    options = (options or CaptureOptions()).check()
    stop = stop or threading.Event()
    output = Path(output)
    done_views = _existing_views(output) if resume else {}
    if output.exists() and not resume:
        raise OutputExistsError(output)
    if resume and not (output / "session.yaml").is_file():
        raise InputError(f"{output}: nothing to resume (no session.yaml); capture without --resume")
    output.mkdir(parents=True, exist_ok=True)
    if options.bias_file:
        from .camera.biases import read_bias_file

        camera.set_biases(read_bias_file(options.bias_file))
    camera.enable_trigger_input(True)
    K, D, intr_source = _intrinsics(options, camera)
    hello = servo.handshake()
    frame_us = int(hello.get("frame_us", 20000))
    servo.sync_clock()
    T_home = options.home_pose()
    # read once: after an unplug or a servo fault the session.yaml is still written
    devices = _devices_document(options, camera, servo, K, D, intr_source, T_home)
    records = []
    summary = {"views": [], "out": str(output)}
    report = _existing_report(output) if resume else {}
    angles = options.turntable_angles()
    for k, angle in enumerate(angles):
        name = view_name(k)
        old = done_views.get(name)
        pose = turntable_pose(T_home, angle)
        split = options.split(k)
        if old is not None and old.get("complete", True) and (output / name).is_dir():
            records.append(old)
            log(f"[{k + 1}/{len(angles)}] {name}: complete, kept")
            continue
        for earlier in [output / name, *sorted((output / REPEATS).glob(f"{name}_r*"))]:
            if earlier.exists():                     # an incomplete earlier attempt: recorded again
                shutil.rmtree(earlier)
        if options.turntable:
            servo.turn(angle, options.turn_ms)
        else:
            input(f"move the camera to view {k + 1} of {len(angles)} (turntable angle {angle:g} deg) and press "
                  "Enter ")
        _home(servo, options)
        log(f"[{k + 1}/{len(angles)}] {name}: turntable {angle:g} deg, recording ...")
        res, error = record_view(camera, servo, output / name, K=K, D=D, pose=pose, options=options,
                                 frame_us=frame_us, stop=stop, live=live, log=log)
        takes = [res]
        for r in range(1, options.repeats):
            if error is not None or stop.is_set() or not takes[-1].complete:
                break
            _home(servo, options)
            (output / REPEATS).mkdir(exist_ok=True)
            log(f"[{k + 1}/{len(angles)}] {name}: take {r + 1} of {options.repeats} ...")
            res_r, error = record_view(camera, servo, output / REPEATS / take_name(name, r), K=K, D=D, pose=pose,
                                       options=options, frame_us=frame_us, stop=stop, live=live, log=log)
            takes.append(res_r)
        complete = all(t.complete for t in takes) and len(takes) == options.repeats
        records.append(view_record(name, split, pose, azimuth_deg=options.home_azimuth_deg + view_azimuth_deg(angle),
                                   turntable_deg=float(angle), complete=complete,
                                   events=int(res.counts.get("events", 0)),
                                   trigger_events=int(res.counts.get("triggers", 0)),
                                   start_device_us=res.start_device_us, done_device_us=res.done_device_us,
                                   dropped_transfers=int(res.counts.get("stats", {}).get("dropped_chunks", 0)),
                                   timing_s=[t.timing_s for t in takes]))
        _write_yaml(output, options, devices, records)
        summary["views"].append(asdict(res))
        log(f"[{k + 1}/{len(angles)}] {name}: {res.counts.get('events', 0)} events, "
            f"{res.counts.get('triggers', 0)} trigger edges, {res.duration_s:.2f} s"
            + ("" if complete else " (INCOMPLETE)"))
        if options.repeats > 1 and complete:
            report[name] = _repeatability(output, name, options, servo, log=log)
            _write_report(output, report)
        if error is not None:
            raise error
        if stop.is_set():
            raise CaptureInterrupted(f"capture interrupted in {name}; it is marked incomplete: run again with "
                                     "--resume to record it")
    if report:
        summary["repeatability"] = report
    return summary


def take_name(view: str, r: int) -> str:
    """The bag folder of take ``r`` (1, 2, ...) of a view, under SESSION/repeats/."""
    return f"{view}_r{r}"


def _repeatability(output: Path, name: str, options: CaptureOptions, servo, *, log=print) -> dict:
    """The run-to-run agreement of a view's takes (evdnerf_ros.session.repeatability), aligned at
    their trigger edges over the motion plus the settle time."""
    from evdnerf_ros.session.repeatability import repeatability

    span = int(servo.get_profile().duration_ns + options.settle_s * 1e9)
    bags = [output / name] + [output / REPEATS / take_name(name, r) for r in range(1, options.repeats)]
    rep = repeatability(bags, span_ns=span, bin_ns=REPEAT_BIN_NS, windows=REPEAT_WINDOWS)
    w = rep["worst"]
    fmt = (lambda v, f: "n/a" if v is None else format(v, f))
    log(f"    {name}: {options.repeats} takes agree: rate corr >= {fmt(w['rate_corr'], '.3f')} "
        f"({fmt(w['rate_corr_aligned'], '.3f')} once aligned), |lag| <= {fmt(w['abs_lag_ms'], '.1f')} ms, image corr >= {fmt(w['image_corr'], '.3f')}, "
        f"image L1 diff <= {fmt(w['image_rel_l1'], '.3f')}")
    return rep


def _existing_report(output: Path) -> dict:
    path = output / REPEATABILITY
    if not path.is_file():
        return {}
    import json

    return json.loads(path.read_text())


def _write_report(output: Path, report: dict) -> None:
    import json

    from evdnerf_ros.atomic import atomic_output

    with atomic_output(output / REPEATABILITY, overwrite=True) as tmp:
        tmp.write_text(json.dumps(report, indent=2))


def _home(servo, options: CaptureOptions) -> None:
    """Bring the scene servo to the profile's start angle (RUN refuses otherwise)."""
    profile = servo.get_profile()
    st = servo.status()
    angle = float(st.get("servo_deg", profile.start_deg)) if isinstance(st, dict) else profile.start_deg
    if abs(angle - profile.start_deg) > 1e-3:
        servo.home(options.home_ms)


def _devices_document(options, camera, servo, K, D, intr_source: str, T_home) -> dict:
    """session.yaml's rig and camera sections, read from the devices at the session's start."""
    return {
        "rig": {"kind": "turntable" if options.turntable else "manual",
                "ring_radius_m": float(options.ring_radius_m), "elevation_deg": float(options.elevation_deg),
                "look_at": [float(v) for v in options.look_at], "home_azimuth_deg": float(options.home_azimuth_deg),
                "T_world_cam_home": np.asarray(T_home).tolist(), "firmware_version": _firmware(servo),
                "device_serial": servo.port_name},
        "camera": dict(camera_record(camera.width, camera.height, K, D), model=camera.model, serial=camera.serial,
                       firmware_version=int(camera.firmware_version),
                       logic_version=None if camera.logic_version is None else int(camera.logic_version),
                       encoding=camera.encoding, intrinsics_source=intr_source,
                       biases={k: int(v) for k, v in camera.biases.items()}),
    }


def _write_yaml(output: Path, options, devices: dict, views: list) -> None:
    doc = session_document(
        source={"kind": "capture", "software_version": __version__}, **devices,
        servo=servo_record(JOINT),
        thresholds={"c_pos": float(options.c_pos), "c_neg": float(options.c_neg)},
        options={k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(options).items()},
        views=views)
    write_session_yaml(output, doc, overwrite=True)


def _firmware(servo) -> str | None:
    try:
        return servo.handshake().get("fw")
    except Exception:  # noqa: BLE001 - only recorded
        return None


__all__ = ["CaptureOptions", "capture_session", "record_view", "ViewResult", "CaptureInterrupted", "view_name"]
