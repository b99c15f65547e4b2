"""`evdnerf capture` and the ROS executable `capture` (what `ros2 launch rig capture.launch.py` runs).

Both take the same settings: the capture node's options (rig.capture.CaptureOptions) plus where
the session goes and which rig runs it:

    evdnerf capture -o SESSION [--camera-serial S] --servo-port /dev/ttyACM0 [--views 8] ...
    evdnerf capture -o SESSION --virtual [--virtual-model evk4] [--scene fork] [--scene-size 64x48]
    evdnerf capture --params-file config/capture.yaml [-o SESSION]
    capture --ros-args --params-file config/capture.yaml -p output:=SESSION -p virtual:=true

``--virtual`` runs the closed-loop virtual rig (rig.virtual_rig): the firmware in simavr, the
camera's twin on emulated USB, the scene driven by the firmware's pins; the capture itself then
runs in a child process (the camera driver needs umockdev's preload) with the rig's truth as its
calibration, geometry and thresholds. SIGINT / SIGTERM stop after closing the current view (it is
marked incomplete in session.yaml); ``--resume`` records only the views not complete.

On DDS (``--live``) the node's options are read-only parameters (a run-time set is refused with the
reason) and, once the camera is open, each camera bias is a dynamic integer parameter
``biases.<name>`` (``ros2 param set /capture biases.bias_diff_on 20``), as metavision_driver and
libcaer_driver allow: checked by the driver's own range checks, applied to the camera while it
records, and logged (also on /rosout) with the time it took effect; session.yaml records, per view,
the biases in force, each change with its sensor time, and the thresholds the driver's bias model
gives for them.
"""

from __future__ import annotations

import argparse
import signal
import sys
import tempfile
import threading
import time
from dataclasses import asdict, dataclass, fields
from pathlib import Path

import yaml

from evdnerf_ros.errors import InputError
from evdnerf_ros.options import add_options, check_value, option, option_fields, options_from_args
from evdnerf_ros.ros.node import Node, stop_signal_handler

from .capture import CaptureInterrupted, CaptureOptions, capture_session

NODE = "capture"


@dataclass
class RigChoice:
    """Where the session goes and which rig records it (the rest is CaptureOptions)."""

    output: str | None = option(None, "session folder to write", kind=str, flag="--output")
    resume: bool = option(False, "record only the views of OUTPUT that are not complete")
    virtual: bool = option(False, "capture on the closed-loop virtual rig (firmware in simavr, camera twin)")
    virtual_model: str = option("evk4", "camera twin of the virtual rig", choices=("evk4", "dvxplorer", "davis346"))
    scene: str = option("fork", "scene of the virtual rig (preset or YAML with one servo joint)", kind=str)
    scene_size: tuple = option((64, 48), "the virtual rig's scene is rendered at this size in the sensor's centre",
                               nargs=2, kind=int, low=1, high=4096, metavar=("W", "H"))
    rate_hz: float = option(500.0, "the virtual rig's render rate while something moves (Hz)", low=1, high=100_000)
    live: bool = option(False, "also publish the events live on ~/events (and ~/triggers), best effort, as "
                               "metavision_driver does (DDS)")


def _parameter_specs():
    """The node's declared parameters: one per option, same default, range and help."""
    from evdnerf_ros.ros.parameters import ParameterSpec

    specs = []
    for cls in (RigChoice, CaptureOptions):
        for f, spec in option_fields(cls):
            default = list(f.default) if isinstance(f.default, tuple) else f.default
            kind = list if isinstance(default, list) else (spec.kind or type(default))
            if default is None:
                default, kind = "", str            # ROS has no null: "" means "not set"
            scalar = kind is not list             # ROS ranges are for numbers (the items were checked at start-up)
            specs.append(ParameterSpec(f.name, default, spec.help, type=kind, read_only=True,
                                       min=spec.low if scalar else None, max=spec.high if scalar else None,
                                       choices=spec.choices))
    return specs


class CaptureNode(Node):
    """The capture node's ROS face: declared parameters, live event topics, logging."""
    NAME = NODE
    PARAMETERS = _parameter_specs()


class LiveEvents:
    """Publishes what the capture records, live: the camera's packets on ``~/events`` (and a
    libcaer camera's trigger edges on ``~/triggers``), best effort, through a node's publishers."""

    def __init__(self, node):
        from evdnerf_ros.io.packetizer import EVENT_PACKET, Packetizer

        self.events = node.create_publisher("~/events", EVENT_PACKET, qos="sensor_data")
        self.triggers = node.create_publisher("~/triggers", EVENT_PACKET, qos="sensor_data")
        pubs = {self.events.topic: self.events, self.triggers.topic: self.triggers}
        self.packetizer = Packetizer(lambda topic, _type, data, t: pubs[topic].publish_raw(data, t), name=node.name)
        self.camera = None                      # (width, height, encoding) of the camera, set by for_camera

    def for_camera(self, camera) -> "LiveEvents":
        self.camera = (camera.width, camera.height, camera.encoding)
        return self

    # the ViewRecorder methods rig.camera.record.ChunkWriter writes through
    def raw_packet(self, payload, *, stamp_ns: int, time_base: int = 0) -> int:
        w, h, enc = self.camera
        return self.packetizer.write_raw_packet(self.events.topic, payload, encoding=enc, width=w, height=h,
                                                stamp_ns=stamp_ns, time_base=time_base)

    def trigger_edges(self, triggers) -> int:
        from evdnerf_ros.events.types import empty_events

        w, h, _ = self.camera
        return self.packetizer.write_events(self.triggers.topic, empty_events(), triggers=triggers, width=w,
                                            height=h, encoding="evt3")


# --------------------------------------------------------------------------- live biases


def bias_limits(device) -> dict[str, tuple[int, int]]:
    """{bias: (lowest, highest)} that the driver ``device`` accepts, inclusive; {} for a driver
    without a range table (its set_biases still checks)."""
    ranges = getattr(device, "bias_ranges", None)
    if ranges is not None:                      # EVK4: OpenEB's allowed ranges (offsets from the factory values)
        return {name: (int(r.lo), int(r.hi)) for name, r in ranges.items()}
    from .camera import davis346, dvxplorer

    if isinstance(device, dvxplorer.DVXplorer):     # (register, mask, shift, top)
        return {name: (0, int(spec[3])) for name, spec in dvxplorer.BIASES.items()}
    if isinstance(device, davis346.DAVIS346):       # (parameter, shift, bits)
        return {name: (0, (1 << int(spec[2])) - 1) for name, spec in davis346.BIASES.items()}
    return {}


def check_bias_values(device, values: dict, limits: dict) -> dict[str, int]:
    """The checks ``device.set_biases(values)`` makes before it writes anything (names, integers,
    ranges), without writing; raises the driver's CameraError with its text."""
    from .camera.errors import CameraError

    if hasattr(device, "check_bias_values"):    # the EVK4's own check (its warnings come with the write)
        return device.check_bias_values(values, warn_recommended=False)
    device.check_bias_names(values, limits)
    out = {}
    for name, value in values.items():          # the libcaer drivers' inline check, same text
        lo, hi = limits[name]
        if isinstance(value, bool) or not isinstance(value, int) or not lo <= value <= hi:
            raise CameraError(f"{device.name}: bias {name} = {value!r} is out of range; use an integer {lo}..{hi}")
        out[name] = int(value)
    return out


@dataclass(frozen=True)
class BiasChange:
    """Biases applied while the node ran, and when they took effect on the camera."""
    values: dict            # {bias: value the camera holds afterwards}
    wall_ns: int            # time.time_ns() when the write returned: the bags' stamps are on this clock
    sensor_ns: int | None   # the camera's sensor time then (its clock fit); None when not streaming
    source: str             # "parameter service" or "bias file"
    host_ns: int | None = None  # time.monotonic_ns() then: the capture places it among its views by it


class LiveBiases:
    """The opened camera's biases as the capture node's dynamic parameters ``biases.<name>``.

    A set is checked by the driver's own checks (a validator: a refusal carries the driver's
    text and nothing is written) and applied with ``set_biases`` (a listener, in the parameter
    service's thread); the parameters then hold what the camera reads back. Every bias read and
    write, the session's own included (use :meth:`camera`), goes under ``lock``: the libcaer
    drivers read-modify-write shared bias words without a lock of their own, and a set must not
    reach a camera that is being closed (:meth:`close` first)."""

    PREFIX = "biases."

    def __init__(self, node, device):
        from evdnerf_ros.ros.parameters import ParameterSpec

        self.node, self.device = node, device
        self.lock = threading.RLock()
        self.changes: list[BiasChange] = []
        self.limits = bias_limits(device)
        self._open = True
        with self.lock:
            self.held = {name: int(v) for name, v in device.biases.items()}
        for name, value in self.held.items():
            lo, hi = self.limits.get(name, (None, None))
            node.params.declare(ParameterSpec(self.PREFIX + name, value, f"{device.model} bias {name}; changes the "
                                              "camera while it records", type=int, dynamic=True, min=lo, max=hi))
        node.params.validators.append(self._validate)
        node.params.listeners.append(self._apply)
        self._announce(new={self.PREFIX + n: v for n, v in self.held.items()})

    def camera(self) -> "SerializedCamera":
        """The camera for capture_session: its bias reads and writes under ``lock``."""
        return SerializedCamera(self.device, self)

    def close(self) -> None:
        """The camera is about to close: later sets are refused with the reason."""
        with self.lock:
            self._open = False

    # ----- the parameter service's side (its thread, the parameters' lock held)
    def _ours(self, changes: dict) -> dict[str, int]:
        return {k[len(self.PREFIX):]: v for k, v in changes.items() if k.startswith(self.PREFIX)}

    def _validate(self, changes: dict):
        from .camera.errors import CameraError

        values = self._ours(changes)
        if not values:
            return None
        with self.lock:
            if not self._open:
                return (f"{self.device.name}: the capture has ended and the camera is closing; biases change only "
                        "while the capture node records")
        try:
            check_bias_values(self.device, values, self.limits)
        except CameraError as exc:
            return str(exc)
        return None

    def _apply(self, changes: dict) -> None:
        from .camera.errors import CameraError

        values = self._ours(changes)
        if not values:
            return
        try:
            self._write(values, "parameter service")
        except CameraError as exc:
            # the reply already said yes (listeners cannot refuse): the parameters go back to what
            # the camera last held, and the error is logged (also on /rosout)
            kept = {n: self.held[n] for n in values if n in self.held}
            self._hold(kept)
            self.node.logger.error(f"biases {values} not applied: {exc}; the parameters keep the camera's values "
                                   f"{kept}")

    # ----- both sides
    def read(self) -> dict[str, int]:
        with self.lock:
            return self.device.biases

    def _write(self, values: dict, source: str) -> BiasChange:
        """set_biases, the time it took effect, the camera's values read back into the parameters."""
        with self.lock:
            if not self._open:
                from .camera.errors import CameraError

                raise CameraError(f"{self.device.name}: the camera is closing; biases {values} not applied")
            self.device.set_biases(values)
            wall_ns, host_ns = time.time_ns(), time.monotonic_ns()
            back = {name: int(v) for name, v in self.device.biases.items()}
            self.held = back
            change = BiasChange({n: back[n] for n in values if n in back}, wall_ns, self._sensor_ns(host_ns), source,
                                host_ns)
            self.changes.append(change)
            self._hold({n: back[n] for n in values if n in back})
        self._log(change, values)
        return change

    def _sensor_ns(self, host_ns: int) -> int | None:
        from .camera.errors import CameraError

        if not self.device.is_streaming:
            return None
        try:
            return int(self.device.clock.host_ns_to_sensor_ns(host_ns))
        except CameraError:                       # too few clock samples yet
            return None

    def _hold(self, values: dict) -> None:
        """The parameters take the camera's values (a clamp or a failed write shows)."""
        from evdnerf_ros.errors import InputError

        try:
            self.node.params.apply({self.PREFIX + n: int(v) for n, v in values.items()}, "camera", startup=True)
        except InputError as exc:                 # a read-back outside the declared range: only logged
            self.node.logger.warn(f"biases read back {values}: {exc}")

    def _announce(self, *, new=None, changed=None) -> None:
        server = getattr(self.node.ros, "params", None)
        if server is not None:
            server.publish_event(new=new, changed=changed)

    def _log(self, change: BiasChange, asked: dict) -> None:
        when = f"{change.wall_ns} ns wall clock (the bags' time base)"
        if change.sensor_ns is not None:
            when += f", sensor time {change.sensor_ns} ns"
        else:
            when += ", sensor time not known yet" if self.device.is_streaming else ", camera not streaming"
        self.node.logger.info(f"biases {change.values} applied ({change.source}) at {when}")
        off = {n: (v, change.values.get(n)) for n, v in asked.items() if change.values.get(n) != int(v)}
        if off:
            self.node.logger.warn(f"the camera holds other values than were set: {off} (set, held)")


class SerializedCamera:
    """The opened driver as capture_session drives it: ``biases`` / ``set_biases`` go through
    LiveBiases (its lock; a bias file applied by the session shows in the parameters), the rest
    is the driver's own."""

    def __init__(self, device, live: LiveBiases):
        self._device = device
        self._live = live

    def __getattr__(self, name):
        return getattr(self._device, name)

    @property
    def biases(self) -> dict[str, int]:
        return self._live.read()

    @property
    def bias_changes(self) -> list[BiasChange]:
        """Every change applied so far, in order (the session records them per view)."""
        return self._live.changes

    def set_biases(self, biases: dict) -> None:
        live = self._live
        change = live._write(dict(biases), "bias file")
        live._announce(changed={live.PREFIX + n: v for n, v in change.values.items()})


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "capture", help="capture a session: one bag per view while the servo runs its motion (real or virtual rig)",
        description="Capture one rosbag2 per viewpoint while the servo firmware runs its stored motion; "
                    "--virtual runs the closed-loop virtual rig. Settings: flags, --config FILE (YAML of "
                    "option: value) or --params-file FILE (ros__parameters of node 'capture', as "
                    "config/capture.yaml).")
    p.add_argument("-o", dest="output", default=argparse.SUPPRESS, help="session folder to write (same as --output)")
    p.add_argument("--params-file", help="ros__parameters YAML (node 'capture'), as config/capture.yaml")
    add_options(p, RigChoice, config=False)
    add_options(p, CaptureOptions)
    # the virtual rig's child process: the ROS face of the process that launched it (NodeFace)
    p.add_argument("--node-face", help=argparse.SUPPRESS)
    p.set_defaults(func=_cmd_capture)


def _split_params(params: dict, where: str) -> dict:
    """ROS parameters -> checked option values of RigChoice and CaptureOptions."""
    known = {f.name: (f, spec) for cls in (RigChoice, CaptureOptions) for f, spec in option_fields(cls)}
    out = {}
    for key, value in params.items():
        name = str(key).replace("-", "_")
        if name not in known:
            raise InputError(f"{where}: {key}: unknown parameter of node {NODE!r}; known: {', '.join(sorted(known))}")
        f, spec = known[name]
        if f.default is None and value == "":     # ROS has no null: "" is "not set"
            out[name] = None
            continue
        if spec.nargs is not None and isinstance(value, list):
            value = tuple(value)
        out[name] = check_value(value, f, spec, f"{where}: {key}")
    return out


def _resolve(args) -> tuple[RigChoice, CaptureOptions]:
    """Flags typed > --config FILE > --params-file FILE > defaults; one file may hold the keys of
    both option sets."""
    files = []
    if getattr(args, "config", None):
        from evdnerf_ros.yamlcheck import load_yaml

        data = load_yaml(args.config, what="config file") or {}
        if not isinstance(data, dict):
            raise InputError(f"{args.config}: expected a mapping of option: value")
        files.append((data, args.config))
        del args.config
    if getattr(args, "params_file", None):
        from evdnerf_ros.ros.parameters import load_params_file

        files.append((load_params_file(args.params_file, NODE), args.params_file))
    for data, where in files:
        for name, value in _split_params(data, where).items():
            if not hasattr(args, name):           # what was typed (or came earlier) wins
                setattr(args, name, value)
    rig = options_from_args(RigChoice, args)
    opts = options_from_args(CaptureOptions, args).check()
    if not rig.output:
        raise InputError("capture: give the session folder to write with -o SESSION (or output: in the params file)")
    return rig, opts


@dataclass(frozen=True)
class NodeFace:
    """What the capture node shows ROS: its ``--ros-args`` identity (name, namespace, remaps, log
    level, use_sim_time) and the parameter values it reports. Under ``--virtual`` the child process
    that opens the camera carries the launched process's face, not its own settings (the rig's
    temporary servo port, the twin's calibration)."""
    ros_argv: tuple = ()
    values: dict | None = None          # None: the settings the node runs with

    def save(self, path) -> None:
        Path(path).write_text(yaml.safe_dump({"ros_argv": list(self.ros_argv), "values": self.values}))

    @classmethod
    def load(cls, path) -> "NodeFace":
        from evdnerf_ros.yamlcheck import load_yaml

        data = load_yaml(path, what="capture node face") or {}
        return cls(tuple(data.get("ros_argv") or ()), data.get("values"))


def ros_identity_argv(ros, use_sim_time=None) -> tuple:
    """``--ros-args`` tokens of a parsed RosArgs that name the node (no parameters)."""
    out = ["--ros-args"]
    if ros.node_name:
        out += ["-r", f"__node:={ros.node_name}"]
    if ros.namespace:
        out += ["-r", f"__ns:={ros.namespace}"]
    for src, dst in ros.remaps.items():
        out += ["-r", f"{src}:={dst}"]
    if ros.log_level:
        out += ["--log-level", ros.log_level]
    if use_sim_time is not None:
        out += ["-p", f"use_sim_time:={'true' if use_sim_time else 'false'}"]
    return tuple(out) if len(out) > 1 else ()


def _cmd_capture(args) -> int:
    face = NodeFace.load(args.node_face) if getattr(args, "node_face", None) else NodeFace()
    if hasattr(args, "node_face"):
        del args.node_face
    rig, opts = _resolve(args)
    return run(rig, opts, face)


def run(rig: RigChoice, opts: CaptureOptions, face: NodeFace = NodeFace()) -> int:
    if rig.virtual:
        return _run_virtual(rig, opts, face)
    return _run_real(rig, opts, face)


def _run_real(rig: RigChoice, opts: CaptureOptions, face: NodeFace = NodeFace()) -> int:
    from .camera import open_camera
    from .servo import ServoClient

    if not opts.servo_port:
        raise InputError("capture: give the servo board's port with --servo-port (e.g. /dev/ttyACM0), or "
                         "--virtual for the virtual rig")
    stop = threading.Event()
    got: list[int] = []

    on_signal = stop_signal_handler(stop, got.append)
    old = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    node = None
    try:
        live = None
        if rig.live:
            node = CaptureNode(list(face.ros_argv), overrides=face.values or _node_values(rig, opts))
            live = LiveEvents(node)
        with open_camera(serial=opts.camera_serial, model=opts.camera_model) as cam, \
                ServoClient(opts.servo_port) as servo:
            biases = LiveBiases(node, cam) if node is not None and node.dds is not None else None
            try:
                capture_session(rig.output, cam if biases is None else biases.camera(), servo, opts,
                                resume=rig.resume, stop=stop, live=None if live is None else live.for_camera(cam),
                                log=print if node is None else node.logger.info)
            finally:
                if biases is not None:
                    biases.close()              # no set may reach the camera open_camera now closes
    except CaptureInterrupted as exc:
        print(f"evdnerf: {exc}", file=sys.stderr)
        return 143 if got and got[-1] == signal.SIGTERM else 130
    finally:
        for s, h in old.items():
            signal.signal(s, h)
        if node is not None:
            node.shutdown()
    return 0


def _node_values(rig: RigChoice, opts: CaptureOptions) -> dict:
    """The node's parameters as ROS holds them (lists for tuples, "" for None)."""
    out = {}
    for obj in (rig, opts):
        for k, v in asdict(obj).items():
            out[k] = "" if v is None else (list(v) if isinstance(v, tuple) else v)
    return out


def spawn_virtual_capture(vr, rig: RigChoice, opts: CaptureOptions, workdir, face: NodeFace = NodeFace(),
                          **popen_kw):
    """Start `evdnerf capture` against the running virtual rig ``vr`` in a child process (the
    camera driver needs umockdev's preload), with the rig's truth as its calibration, geometry,
    thresholds, camera serial and servo port; its node shows ``face`` (default: the settings
    asked for, ``rig`` and ``opts``). Returns the Popen."""
    from .camera.virtual.usb import spawn_child

    workdir = Path(workdir)
    ring = vr.ring()
    c_pos, c_neg = vr.twin.thresholds()
    cal = workdir / "calibration.yaml"
    cal.write_text(yaml.safe_dump(vr.calibration_document()))
    values = {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(opts).items()}
    values.update(camera_serial=vr.camera_serial, camera_model=None, servo_port=vr.port, calibration=str(cal),
                  ring_radius_m=float(ring.radius), elevation_deg=float(ring.elevation_deg),
                  look_at=[float(v) for v in ring.look_at], home_azimuth_deg=float(ring.offset_deg),
                  c_pos=float(c_pos), c_neg=float(c_neg), live=bool(rig.live))
    config = workdir / "capture.yaml"
    config.write_text(yaml.safe_dump(values))
    face_file = workdir / "node_face.yaml"
    NodeFace(face.ros_argv, face.values or _node_values(rig, opts)).save(face_file)
    argv = [sys.executable, "-m", "evdnerf_ros", "capture", "-o", str(rig.output), "--config", str(config),
            "--node-face", str(face_file)]
    if rig.resume:
        argv.append("--resume")
    return spawn_child(argv, vr.bus, env=vr.env(popen_kw.pop("env", None)), **popen_kw)


def _run_virtual(rig: RigChoice, opts: CaptureOptions, face: NodeFace = NodeFace()) -> int:
    """The virtual rig here; the capture, against it, in a child process."""
    from .virtual_rig import VirtualRig

    with VirtualRig(model=rig.virtual_model, scene=rig.scene, scene_size=tuple(rig.scene_size),
                    rate_hz=rig.rate_hz) as vr, tempfile.TemporaryDirectory(prefix="evdnerf-capture-") as tmp:
        print(f"virtual rig: firmware in simavr on {vr.port}, {rig.virtual_model} twin (serial {vr.camera_serial}) "
              f"streaming {rig.scene} at {rig.scene_size[0]}x{rig.scene_size[1]}", file=sys.stderr)
        proc = spawn_virtual_capture(vr, rig, opts, tmp, face, stdout=None, stderr=None)

        def forward(signum, _frame):
            proc.send_signal(signum)              # the child closes its view and exits

        old = {s: signal.signal(s, forward) for s in (signal.SIGINT, signal.SIGTERM)}
        try:
            code = proc.wait()
        finally:
            for s, h in old.items():
                signal.signal(s, h)
        late = sum(not r.on_time for r in vr.trigger_log if r.sensor_ns is not None)
        if late or vr.source.late_renders:
            print(f"virtual rig: {late} trigger edges placed late, {vr.source.late_renders} chunks rendered with "
                  "stale joint angles (the machine fell behind real time)", file=sys.stderr)
        return code


# --------------------------------------------------------------------------- ROS executable


def main(argv=None) -> int:
    """Console script ``capture``: ``capture --ros-args --params-file F -p name:=value``."""
    from evdnerf_ros.errors import EvdnerfError
    from evdnerf_ros.ros.args import parse_ros_args

    argv = sys.argv[1:] if argv is None else list(argv)
    if argv[:1] in (["-h"], ["--help"]):
        print(__doc__)
        print("parameters:", ", ".join(f.name for cls in (RigChoice, CaptureOptions) for f in fields(cls)))
        return 0
    try:
        ros, rest = parse_ros_args(argv, NODE)
        if rest:
            raise InputError(f"capture: unexpected arguments {rest}; settings go in --ros-args -p name:=value "
                             "or --params-file")
        from evdnerf_ros.ros.parameters import load_params_file

        node_name = ros.node_name or NODE
        params = {}
        for path in ros.params_files:
            params.update(load_params_file(path, node_name, ros.namespace or "/"))
        params.update(ros.params)
        use_sim_time = params.pop("use_sim_time", None)   # every node's own parameter (Node), not an option
        ns = argparse.Namespace(**_split_params(params, "--ros-args"))
        rig, opts = _resolve(ns)
        code = run(rig, opts, NodeFace(ros_identity_argv(ros, use_sim_time)))
    except EvdnerfError as exc:
        print(f"capture: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 0
    # a stop asked for by SIGINT / SIGTERM (Ctrl-C, ros2 launch's shutdown) is a clean end for ROS
    # tools (launch: "process has finished cleanly"); the view it cut is marked incomplete
    return 0 if code in (130, 143) else code


__all__ = ["RigChoice", "NodeFace", "ros_identity_argv", "CaptureNode", "LiveEvents", "LiveBiases", "BiasChange", "bias_limits", "check_bias_values",
           "register", "run", "main", "spawn_virtual_capture"]
