"""Capture a session: one rosbag2 per viewpoint while the servo firmware runs its stored motion.

The camera starts once and streams for the whole session (rig.camera.record.CameraStream: read in
a thread, so its transfer queue drains while the turntable turns and the servo homes; what falls
between views is discarded and counted). Per view: turn the turntable to the view's angle (or ask
the user to move the camera), bring the servo to the profile's start angle, open the view's span
of the stream, record a pre-roll, send ``RUN``, keep recording until the camera's stream has passed
the firmware's ``DONE`` plus the settle time (the span ends there, on the camera's clock: later
transfers are not the view's), close the span. Each view's bag goes through the session recorder
(evdnerf_ros.session.recorder) with the standard topics: the camera's events in its own encoding
passed through untouched (EVT 3.0 transfers as metavision_driver records them, after the driver's
resume words; libcaer packets as libcaer_driver publishes them, trigger edges of a libcaer camera
on their own topic), CameraInfo, the view's pose, the servo's commanded joint angle at every frame
of the motion (JointState; the firmware's own integer profile), START / DONE (TimeReference).
session.yaml is rewritten after every view: rig geometry, camera model / serial / firmware,
intrinsics (a calibration file, or nominal from a field of view), per-view pose and turntable
angle, per-view biases (those in force and every live change, in sensor time) and the contrast
thresholds they give through the driver's bias model (or the options), the software version.

The view's clock is what a reader of its bag decodes (the wall-clock time of the sensor's zero
plus sensor time, rig.camera.record; one zero for the whole stream, so every view shares it);
START / DONE / joint states are placed on it through the servo's ping-fitted clock and the
camera's arrival-fitted clock, both on the host's monotonic clock. The camera's trigger input
sees the firmware's trigger pulse at each motion's first frame, which is what `evdnerf sync`
aligns the views by.

Faults: SIGINT / SIGTERM end the current view's bag validly (everything received is in it), mark
the view ``complete: false`` in session.yaml and re-raise; ``resume=True`` records again only the
views not complete. A camera unplugged or a servo that stops answering mid-view raises a clear
error after the view's bag is closed and marked incomplete; a ``DONE`` that never comes raises
ServoTimeout with the servo's last status. Finished views are never touched. The camera stops
once, at the end or on the fault.
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
from evdnerf_ros.io.trainingset import C_MAX
from evdnerf_ros.options import option
from evdnerf_ros.session.recorder import (ViewRecorder, camera_record, servo_record, session_document,
                                          view_record, write_session_yaml)

from .camera.errors import CameraError
from .camera.record import CameraStream, ChunkWriter
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
#: After DONE + settle, a stream short of it that has not advanced for this long (s) is a fault
#: (the view is incomplete); one that advances is waited for, however late (a camera twin
#: rendering slower than real time on a loaded machine streams every event, only late).
STREAM_STALL_S = 15.0
#: Before a view: how long a lagging stream may take to catch up before it is restarted.
CATCH_UP_S = 3.0
#: How often (s) a view's loop looks at the servo's reports when the stream brings nothing.
POLL_S = 0.01
#: Where session.yaml's thresholds come from (--thresholds-from) and how the views record it.
THRESHOLD_SOURCES = ("bias-model", "options")
BIAS_MODEL, OPTIONS = "bias model", "options"
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
    thresholds_from: str = option("bias-model", "session.yaml's contrast thresholds: 'bias-model' (the camera "
                                                 "driver's bias -> threshold model for each view's biases; the "
                                                 "c_pos / c_neg options where the driver has none) or 'options'",
                                  choices=THRESHOLD_SOURCES)
    c_pos: float = option(0.2, "ON contrast threshold recorded in session.yaml (with --thresholds-from options, "
                               "or a camera without a bias model)", low=0, low_open=True, high=10)
    c_neg: float = option(0.2, "OFF contrast threshold recorded in session.yaml (as c_pos)", low=0, low_open=True,
                          high=10)
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
    #: where the view's wall time went (s): home (the servo to the profile's start, round trips
    #: included; 0 when it stood there), stream_wait (before the view opens, a stream lagging real
    #: time catching up with the present), view_open (bag and span), pre_roll, motion (RUN sent to
    #: DONE received), stream_catch_up (DONE + settle in real time to the camera's stream
    #: reaching it: the camera's latency), bag_close (metadata and the bag's index)
    timing_s: dict = field(default_factory=dict)
    #: the view's span on the host's monotonic clock (ns): bias changes are placed by it
    host_span_ns: tuple[int, int] = (0, 0)


class StreamWatch:
    """Whether a camera's stream has stalled: its sensor time ``reached`` (None: nothing timed
    yet) has not advanced for more than ``stall_s`` seconds since ``since_s`` or its last advance
    (times on the host's monotonic clock, s). A late stream that advances never stalls."""

    def __init__(self, since_s: float, stall_s: float | None = None):
        self.last_s = float(since_s)
        self.stall_s = STREAM_STALL_S if stall_s is None else float(stall_s)
        self.reached: int | None = None

    def stalled(self, now_s: float, reached: int | None) -> bool:
        if reached is not None and (self.reached is None or reached > self.reached):
            if self.reached is not None:        # the first value seen is where it stood, not an advance
                self.last_s = max(self.last_s, now_s)
            self.reached = reached
        return now_s - self.last_s > self.stall_s


class CaptureInterrupted(KeyboardInterrupt):
    """SIGINT / SIGTERM during a capture: the current view was closed and marked incomplete."""


def record_view(stream: CameraStream, servo, path: Path, *, K, D, pose, options: CaptureOptions, profile,
                frame_us: int, stop: threading.Event, log=print) -> tuple[ViewResult, BaseException | None]:
    """Record one view from the running camera ``stream`` (see the module docstring). The bag is
    closed validly whatever happens; returns what was recorded and the camera or servo fault
    that ended the view early (None when it did not; an interrupt is ``stop`` set)."""
    camera = stream.device
    expected_s = profile.duration_ns / 1e9
    settle_ns = int(options.settle_s * 1e9)
    start = done = None
    error: BaseException | None = None
    t0 = time.monotonic()
    timing = {}
    span = None
    with ViewRecorder(path, width=camera.width, height=camera.height, encoding=camera.encoding,
                      storage=options.storage) as rec:
        writer = ChunkWriter(rec, camera, origin=stream.origin)
        servo.drain_events()
        run_sent = None
        done_ns = None                      # DONE's sensor time, once the clocks place it
        watch = None                        # the stream's progress after DONE + settle
        try:
            # a stream lagging real time (a camera twin rendering slower than real time) first
            # catches up with the present, so its lag never adds up over the views of a session
            waited = _catch_up(stream, stop, log)
            if waited:
                timing["stream_wait"] = waited
            span = stream.open_span(writer)
            started = time.monotonic()      # the pre-roll counts from here: RUN never precedes it
            timing["view_open"] = started - t0 - waited
            while not stop.is_set():
                stream.check()
                now = time.monotonic()
                if run_sent is None:
                    if now - started < options.pre_roll_s:
                        stream.wait(min(POLL_S, started + options.pre_roll_s - now))
                        continue
                    servo.run(wait=False)
                    run_sent = time.monotonic()
                    timing["pre_roll"] = run_sent - started
                for ev in servo.drain_events():
                    if ev.motion == "RUN" and ev.kind == "START":
                        start = ev
                    elif ev.motion == "RUN" and ev.kind in ("DONE", "STOPPED") and start is not None:
                        done = ev
                if done is not None:
                    if done_ns is None:
                        done_ns = _sensor_ns_of(writer, camera, servo, start, done.device_us, stream.clock)
                        if done_ns is not None:     # the span ends there: later transfers are not the view's
                            stream.end_span(span, done_ns + settle_ns)
                    # the stream has passed DONE + settle, or has reached the motion's end and been
                    # quiet since (a sensor without activity sends nothing: there is nothing more to
                    # record; a stream still short of the motion's end is late, not quiet)
                    reached = camera.sensor_time_ns
                    if watch is None:
                        watch = StreamWatch(done.host_recv_ns / 1e9 + options.settle_s)
                    if watch.stalled(now, reached):
                        raise CameraError(f"{camera.name}: the camera's stream has not advanced for "
                                          f"{STREAM_STALL_S:g} s, short of the servo's DONE (it reached "
                                          f"{_seconds(reached)}); check the USB link and the machine's load")
                    last = stream.last_chunk_host_ns
                    quiet = last is None or now - last / 1e9 > QUIET_S
                    if done_ns is not None and reached is not None and (
                            reached >= done_ns + settle_ns
                            or (quiet and now > done.host_recv_ns / 1e9 + options.settle_s
                                and reached >= done_ns - QUIET_NEAR_END_NS)):
                        timing["motion"] = done.host_recv_ns / 1e9 - run_sent
                        timing["stream_catch_up"] = max(0.0, now - done.host_recv_ns / 1e9 - options.settle_s)
                        break
                elif now > run_sent + expected_s + options.done_timeout_s:
                    raise ServoTimeout(f"{servo.port_name}: no {'START' if start is None else 'DONE'} of RUN within "
                                       f"{expected_s + options.done_timeout_s:.1f} s; the servo reports "
                                       f"{_status(servo)}")
                stream.wait(POLL_S)
        except (CameraError, ServoError) as exc:
            error = exc
        finally:
            if span is not None:
                stream.close_span(span)     # nothing more is written to the bag from here
        closed = time.monotonic_ns()
        tic = time.monotonic()
        _write_view_metadata(rec, writer, servo, stream.clock, K=K, D=D, pose=pose, profile=profile,
                             frame_us=frame_us, start=start, done=done)
    timing["bag_close"] = time.monotonic() - tic
    complete = error is None and not stop.is_set() and done is not None
    counts = dict(writer.counts, stats=camera.stats.as_dict(), dropped=0 if span is None else span.dropped,
                  discarded_before=dict(span.discarded_before) if span is not None else {})
    result = ViewResult(path.name, complete, counts,
                        None if start is None else int(start.device_us),
                        None if done is None else int(done.device_us), time.monotonic() - t0,
                        None if error is None else str(error), {k: round(v, 4) for k, v in timing.items()},
                        (span.start_host_ns if span is not None else closed, closed))
    return result, error


def _catch_up(stream: CameraStream, stop: threading.Event, log=print) -> float:
    """Wait until the stream has delivered the sensor time of now, or has gone quiet (a sensor
    without activity sends nothing: nothing to wait for); a stream still behind after
    CATCH_UP_S is restarted (its backlog dropped, as a start / stop per view would). Nothing to
    wait for before the stream's first timed transfer. Returns the seconds this took."""
    tic = time.monotonic()
    try:
        target = int(stream.clock.host_ns_to_sensor_ns(time.monotonic_ns()))
    except CameraError:
        return 0.0
    while not stop.is_set():
        stream.check()
        reached = stream.device.sensor_time_ns
        last = stream.last_chunk_host_ns
        if (reached is not None and reached >= target) or \
                (last is not None and time.monotonic() - last / 1e9 > QUIET_S):
            break
        if time.monotonic() - tic > CATCH_UP_S:
            behind = (target - reached) / 1e9 if reached is not None else float("nan")
            stream.restart()
            log(f"the camera's stream was {behind:.1f} s behind real time and did not catch up "
                f"within {CATCH_UP_S:g} s: restarted it (restart {stream.restarts})")
            break
        stream.wait(POLL_S)
    return time.monotonic() - tic


def _sensor_ns_of(writer, camera, servo, start, device_us: int, clock) -> int | None:
    """The camera's sensor time of a servo board time: through the trigger edge of this RUN when
    the camera saw it (exact), else through the servo's fitted clock and the stream's arrival
    clock ``clock`` (rig.camera.record.ArrivalClock: it includes the camera's latency); None
    while neither is known yet."""
    servo_clock = servo.clock if servo.clock is not None else servo.sync_clock()
    anchor = _trigger_anchor(writer, start, servo_clock, clock)
    if anchor is not None:
        return int(anchor[0] + round((int(device_us) - anchor[1]) * servo_clock.scale))
    try:
        through_clocks = [int(clock.host_ns_to_sensor_ns(int(servo_clock.to_host_ns(int(us)))))
                          for us in (device_us, start.device_us if start is not None else device_us)]
    except CameraError:                 # nothing timed has arrived yet
        return None
    if getattr(camera, "trigger_input_enabled", False):
        # the edge may still be on its way (a stream lagging real time): wait until the stream
        # is clearly past where it would be
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


def _write_view_metadata(rec, writer, servo, clock, *, K, D, pose, profile, frame_us, start, done) -> None:
    """CameraInfo and pose at the view's first time; START / DONE and the commanded joint angle of
    every frame of the motion, on the view's clock (``clock``: the stream's ArrivalClock, for a
    view without its trigger edge)."""
    first = writer.counts["first_sensor_ns"]
    if first is None:                               # nothing came: there is no view clock
        return
    stamp0 = int(writer.view_ns(first))
    rec.camera_info(K, D, stamp_ns=stamp0)
    rec.pose(pose, stamp_ns=stamp0)
    servo_clock = servo.clock if servo.clock is not None else servo.sync_clock()
    anchor = _trigger_anchor(writer, start, servo_clock, clock)

    def view_ns(device_us):
        d = np.asarray(device_us, np.int64)
        if anchor is not None:      # the trigger edge and START are the same instant
            sensor = anchor[0] + np.rint((d - anchor[1]) * servo_clock.scale).astype(np.int64)
        else:                       # through both clocks (the camera's includes its USB latency)
            sensor = clock.host_ns_to_sensor_ns(servo_clock.to_host_ns(d))
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


def _trigger_anchor(writer, start, servo_clock, clock) -> tuple[int, int] | None:
    """(sensor ns of the trigger edge, device µs of START) when the camera saw the firmware's
    trigger pulse of this RUN (the only servo motion inside a view's span: the turntable and
    HOME raise no trigger): the rising edge nearest to where the clocks put START. None without
    a trigger cable."""
    if start is None or not writer.rising_ns:
        return None
    try:
        guess = clock.host_ns_to_sensor_ns(int(servo_clock.to_host_ns(start.device_us)))
    except CameraError:                 # no arrival clock: the first edge
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
    also gets every packet (rig.capture_cli.LiveEvents). A camera with ``bias_changes`` (the
    capture node's live biases, rig.capture_cli.SerializedCamera) has them recorded per view.
    Returns a summary."""
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
    profile = servo.get_profile()       # the firmware's stored motion: one for the session
    T_home = options.home_pose()
    changes = getattr(camera, "bias_changes", None)
    first_change = len(changes) if changes is not None else 0
    # read once: after an unplug or a servo fault the session.yaml is still written
    devices = _devices_document(options, camera, servo, K, D, intr_source, T_home)
    biases = BiasLog(devices["camera"]["biases"], changes if changes is not None else [], first_change)
    thresholds = ThresholdModel.of(camera, options, log=log)
    records = []
    summary = {"views": [], "out": str(output)}
    report = _existing_report(output) if resume else {}
    angles = options.turntable_angles()
    stream = CameraStream(camera, live=live)
    reports = Reports(output, options, profile, report, log=log)
    servo_deg = None                    # the scene servo's angle, when known without asking
    try:
        stream.start()
        log(f"camera streaming ({camera.name}, start took {stream.start_s:.2f} s)")
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
            tic = time.monotonic()
            if options.turntable:
                servo.turn(angle, options.turn_ms)
            else:
                input(f"move the camera to view {k + 1} of {len(angles)} (turntable angle {angle:g} deg) and press "
                      "Enter ")
            turn_s = time.monotonic() - tic
            servo_deg, home_s = _home(servo, options, profile, servo_deg)
            log(f"[{k + 1}/{len(angles)}] {name}: turntable {angle:g} deg, recording ...")
            res, error = record_view(stream, servo, output / name, K=K, D=D, pose=pose, options=options,
                                     profile=profile, frame_us=frame_us, stop=stop, log=log)
            res.timing_s.update(turn=round(turn_s, 4), home=round(home_s, 4))
            servo_deg = _after_run(res, profile)
            takes = [res]
            for r in range(1, options.repeats):
                if error is not None or stop.is_set() or not takes[-1].complete:
                    break
                servo_deg, home_s = _home(servo, options, profile, servo_deg)
                (output / REPEATS).mkdir(exist_ok=True)
                log(f"[{k + 1}/{len(angles)}] {name}: take {r + 1} of {options.repeats} ...")
                res_r, error = record_view(stream, servo, output / REPEATS / take_name(name, r), K=K, D=D,
                                           pose=pose, options=options, profile=profile, frame_us=frame_us,
                                           stop=stop, log=log)
                res_r.timing_s.update(home=round(home_s, 4))
                servo_deg = _after_run(res_r, profile)
                takes.append(res_r)
            complete = all(t.complete for t in takes) and len(takes) == options.repeats
            in_force = biases.view_record(takes, camera, thresholds, stream.clock)
            records.append(view_record(name, split, pose,
                                       azimuth_deg=options.home_azimuth_deg + view_azimuth_deg(angle),
                                       turntable_deg=float(angle), complete=complete,
                                       events=int(res.counts.get("events", 0)),
                                       trigger_events=int(res.counts.get("triggers", 0)),
                                       start_device_us=res.start_device_us, done_device_us=res.done_device_us,
                                       dropped_transfers=int(res.counts.get("dropped", 0)), **in_force,
                                       timing_s=[t.timing_s for t in takes],
                                       discarded_before=[t.counts.get("discarded_before", {}) for t in takes]))
            _write_yaml(output, options, devices, records, thresholds)
            summary["views"].append(asdict(res))
            gap = res.counts.get("discarded_before", {})
            log(f"[{k + 1}/{len(angles)}] {name}: {res.counts.get('events', 0)} events, "
                f"{res.counts.get('triggers', 0)} trigger edges, {res.duration_s:.2f} s"
                + ("" if complete else " (INCOMPLETE)")
                + f"; {gap.get('events', 0)} events between views discarded")
            if options.repeats > 1 and complete:
                reports.submit(name)
            if error is not None:
                raise error
            if stop.is_set():
                raise CaptureInterrupted(f"capture interrupted in {name}; it is marked incomplete: run again with "
                                         "--resume to record it")
        stream.stop()
        summary["stream"] = _stream_record(stream, camera)
        _write_yaml(output, options, devices, records, thresholds, stream=summary["stream"])
        reports.finish()                # the last view's report: the camera is stopped already
    finally:
        reports.close()
        stream.stop()
    d = stream.discarded
    log(f"camera stopped (stop took {stream.stop_s:.2f} s); outside the views {d.transfers} transfers, {d.events} "
        f"events, {d.triggers} trigger edges were read and discarded")
    if report:
        summary["repeatability"] = report
    return summary


def _stream_record(stream: CameraStream, camera) -> dict:
    """session.yaml's ``stream``: the camera's one start and stop, and what it streamed outside
    every view (per view: views[].discarded_before)."""
    return {"camera_start_s": round(stream.start_s, 4), "camera_stop_s": round(stream.stop_s, 4),
            "restarts": int(stream.restarts),
            "discarded": dict(vars(stream.discarded)), "discarded_after_last_view": stream.discarded_since_span(),
            "dropped_transfers": int(camera.stats.dropped_chunks)}


def _after_run(res: ViewResult, profile) -> float | None:
    """The scene servo's angle after a take: the profile's last target once RUN reported DONE,
    else unknown (the next HOME asks the servo)."""
    return float(profile.targets_deg[-1]) if res.done_device_us is not None and res.complete else None


# =========================================================================== biases and thresholds


@dataclass
class ThresholdModel:
    """Where each view's contrast thresholds come from: the camera driver's bias -> threshold
    model (``Device.contrast_thresholds``) or the c_pos / c_neg options (--thresholds-from
    options, a driver without a model, or a model value the session layout refuses)."""
    model: str | None           # "module.function" of the driver's model; None: the options
    options: tuple[float, float]
    why_options: str = ""

    @classmethod
    def of(cls, camera, options: CaptureOptions, *, log=print) -> "ThresholdModel":
        opts = (float(options.c_pos), float(options.c_neg))
        if options.thresholds_from == "options":
            return cls(None, opts, "--thresholds-from options")
        model = getattr(camera, "THRESHOLD_MODEL", None)
        if model is None:
            log(f"thresholds: the {camera.model} driver has no bias -> threshold model; session.yaml records "
                f"--c-pos {opts[0]:g} / --c-neg {opts[1]:g}")
            return cls(None, opts, f"the {camera.model} driver has no bias -> threshold model")
        return cls(str(model), opts)

    def of_biases(self, camera, biases: dict) -> tuple[dict, str]:
        """({c_pos, c_neg}, source) for ``biases``."""
        if self.model is not None:
            c_on, c_off = camera.contrast_thresholds(biases)
            if all(0 < c <= C_MAX for c in (c_on, c_off)):
                return {"c_pos": float(c_on), "c_neg": float(c_off)}, BIAS_MODEL
        return {"c_pos": self.options[0], "c_neg": self.options[1]}, OPTIONS

    def describe(self, source: str, camera_model: str) -> str:
        if source == BIAS_MODEL:
            return f"bias model {self.model} of the {camera_model} driver, for the view's biases"
        why = self.why_options or f"the bias model {self.model} gives thresholds outside (0, {C_MAX:g}]"
        return f"options (--c-pos / --c-neg): {why}"


@dataclass
class BiasLog:
    """The camera's biases over the session: those read at its start, then the changes applied
    live (rig.capture_cli.BiasChange, appended by the parameter service's thread)."""
    start: dict
    changes: list
    first: int = 0              # changes before this index are in ``start`` already
    reported: int = 0           # changes since the start already in a view record

    def _since_start(self) -> list:
        return [c for c in list(self.changes)[self.first:] if getattr(c, "host_ns", None) is not None]

    def at(self, host_ns: int) -> dict:
        """The biases in force at host time ``host_ns``."""
        out = dict(self.start)
        for c in self._since_start():
            if c.host_ns <= host_ns:
                out.update({n: int(v) for n, v in c.values.items()})
        return out

    def view_record(self, takes: list, camera, thresholds: ThresholdModel, clock) -> dict:
        """A view record's ``biases`` (in force when its bag began), ``thresholds`` for them and
        ``bias_changes``: each change since the previous view's, once, with its sensor time (its
        host time on the stream's arrival clock ``clock``, the one the views are cut by),
        values, source, the thresholds after it and ``when`` (before the view's recording,
        during it, during its repeat takes)."""
        begin, bag_end = takes[0].host_span_ns
        end = takes[-1].host_span_ns[1]
        biases = self.at(begin)
        th, source = thresholds.of_biases(camera, biases)
        moves = []
        # changes are appended in host-time order; one whose thread appended it only after the
        # previous view's record was made (a loaded machine) goes into this one, "before" it
        new = self._since_start()[self.reported:]
        for c in new[:sum(c.host_ns <= end for c in new)]:
            when = "before" if c.host_ns <= begin else "recording" if c.host_ns <= bag_end else "repeat takes"
            moves.append({"sensor_ns": _sensor_ns_at(clock, c), "when": when,
                          "values": {n: int(v) for n, v in c.values.items()}, "source": c.source,
                          "thresholds": thresholds.of_biases(camera, self.at(c.host_ns))[0]})
        self.reported += len(moves)
        return {"biases": biases, "bias_changes": moves, "thresholds": th, "thresholds_source": source}


def _sensor_ns_at(clock, change) -> int | None:
    """A bias change's sensor time: its host time on ``clock``; else as the node logged it (its
    driver's clock fit, None when that had too few samples). ``clock`` times arrivals, so a change
    made before the first view of a stream that lags real time (a camera twin rendering slower)
    can precede its zero: a negative time, before every view's."""
    try:
        return int(clock.host_ns_to_sensor_ns(int(change.host_ns)))
    except CameraError:                 # nothing timed had arrived
        return None if change.sensor_ns is None else int(change.sensor_ns)


def take_name(view: str, r: int) -> str:
    """The bag folder of take ``r`` (1, 2, ...) of a view, under SESSION/repeats/."""
    return f"{view}_r{r}"


class Reports:
    """The repeatability reports of the views with takes, each computed in a worker thread while
    the next view turns and records (reading three bags takes about a second: off the views'
    critical path); ``repeatability.json`` is rewritten after each. :meth:`finish` waits for them
    all and raises the first one that failed; :meth:`close` waits without raising."""

    def __init__(self, output: Path, options: CaptureOptions, profile, report: dict, *, log=print):
        self.output, self.options, self.profile, self.report, self.log = output, options, profile, report, log
        self._pool = None
        self._pending: list = []

    def submit(self, name: str) -> None:
        if self._pool is None:
            from concurrent.futures import ThreadPoolExecutor

            self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="repeatability")
        self._pending.append(self._pool.submit(self._one, name))

    def _one(self, name: str) -> None:
        self.report[name] = _repeatability(self.output, name, self.options, self.profile, log=self.log)
        _write_report(self.output, self.report)

    def finish(self) -> None:
        pending, self._pending = self._pending, []
        for f in pending:
            f.result()

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True)


def _repeatability(output: Path, name: str, options: CaptureOptions, profile, *, log=print) -> dict:
    """The run-to-run agreement of a view's takes (evdnerf_ros.session.repeatability), aligned at
    their trigger edges over the motion plus the settle time."""
    from evdnerf_ros.session.repeatability import repeatability

    span = int(profile.duration_ns + options.settle_s * 1e9)
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


def _home(servo, options: CaptureOptions, profile, angle: float | None) -> tuple[float, float]:
    """Bring the scene servo to the profile's start angle (RUN refuses otherwise); ``angle``: where
    it stands when known (None: ask it). Returns (its angle now, the wall time this took)."""
    tic = time.monotonic()
    if angle is None:
        st = servo.status()
        angle = float(st.get("servo_deg", profile.start_deg)) if isinstance(st, dict) else profile.start_deg
    if abs(angle - profile.start_deg) > 1e-3:
        servo.home(options.home_ms)
    return float(profile.start_deg), time.monotonic() - tic


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


def _write_yaml(output: Path, options, devices: dict, views: list, thresholds: ThresholdModel, *,
                stream: dict | None = None) -> None:
    extra = {} if stream is None else {"stream": stream}
    doc = session_document(
        source={"kind": "capture", "software_version": __version__}, **devices,
        servo=servo_record(JOINT),
        thresholds=_session_thresholds(views, thresholds, devices["camera"]["model"]),
        options={k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(options).items()},
        **extra, views=views)
    write_session_yaml(output, doc, overwrite=True)


def _session_thresholds(views: list, thresholds: ThresholdModel, camera_model: str) -> dict:
    """session.yaml's one pair (what `evdnerf convert` trains with): the first view's, saying
    whether the others differ (their own are in views[].thresholds)."""
    per_view = [(v["thresholds"], v.get("thresholds_source", OPTIONS)) for v in views
                if isinstance(v.get("thresholds"), dict)]
    if not per_view:
        c = {"c_pos": thresholds.options[0], "c_neg": thresholds.options[1]}
        return dict(c, source=thresholds.describe(OPTIONS if thresholds.model is None else BIAS_MODEL, camera_model),
                    per_view="none recorded yet")
    (first, source), rest = per_view[0], per_view[1:]
    same = all(t == first for t, _ in rest)
    return dict(first, source=thresholds.describe(source, camera_model) + " (the first view's)",
                per_view="the same in every view" if same else
                "differ between views (views[].thresholds); convert trains with this one pair")


def _firmware(servo) -> str | None:
    try:
        return servo.handshake().get("fw")
    except Exception:  # noqa: BLE001 - only recorded
        return None


__all__ = ["CaptureOptions", "capture_session", "record_view", "ViewResult", "CaptureInterrupted", "view_name",
           "ThresholdModel", "BiasLog"]
