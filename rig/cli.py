"""`evdnerf flash`, `evdnerf servo ...` and `evdnerf camera ...`: registered as an
`evdnerf.commands` plugin.

evdnerf_ros (the CLI's home) never imports rig; setup.py's entry point
`evdnerf.commands: rig = rig.cli:register` makes the CLI find these commands.
"""

from __future__ import annotations

import json
import sys

#: Virtual twins `evdnerf camera ... --virtual MODEL` can host.
TWINS = ("dvxplorer", "davis346", "evk4")


def _cmd_flash(args) -> int:
    from .flash import flash

    res = flash(args.port, board=args.board, hex_path=args.hex)
    print(f"{args.port}: flashed {res.hex_path} ({args.board}, {' '.join(res.command)})")
    return 0


def _servo_action(client, args) -> None:
    a = args.action
    if a == "hello":
        print(json.dumps(client.hello))
    elif a == "ping":
        rtts = []
        for _ in range(args.count):
            dev, t0, t1 = client.ping()
            rtts.append((t1 - t0) / 1e6)
            print(f"device {dev} us, round trip {rtts[-1]:.2f} ms")
        if args.count >= 2:
            c = client.sync_clock(pings=0)
            print(f"clock: host_ns = {c.offset_ns:.0f} + {c.scale:.6f} * (device_us - "
                  f"{c.device_ref_us}); drift {c.drift_ppm:.1f} ppm, residual "
                  f"{c.residual_ns / 1e3:.1f} us over {c.samples} pings")
    elif a in ("move", "turn"):
        m = getattr(client, a)(args.angle, args.ms)
        print(f"{a.upper()} {args.angle} deg in {args.ms} ms: START {m.start.device_us} us, "
              f"{m.end.kind} {m.end.device_us} us ({m.duration_us / 1000:.1f} ms)")
    elif a == "home":
        m = client.home(args.ms)
        print(f"HOME: START {m.start.device_us} us, {m.end.kind} {m.end.device_us} us")
    elif a == "run":
        m = client.run()
        print(f"RUN: START {m.start.device_us} us, {m.end.kind} {m.end.device_us} us "
              f"({m.duration_us / 1000:.1f} ms)")
    elif a == "stop":
        client.stop()
        print("stopped")
    elif a == "status":
        print(json.dumps(client.status()))
    elif a == "get-limits":
        print(json.dumps(client.get_limits().__dict__))
    elif a == "set-limits":
        print(json.dumps(client.set_limits(args.limits).__dict__))
    elif a == "get-profile":
        print(json.dumps(client.get_profile().to_dict()))
    elif a == "set-profile":
        print(json.dumps(client.set_profile(args.profile).to_dict()))


MAX_PINGS = 10_000


def _check_servo_args(args) -> None:
    """Range-check every number against the firmware's limits (PROTOCOL.md) before a port is
    opened or a virtual Arduino started: one line naming the argument, never a traceback."""
    from evdnerf_ros.errors import InputError
    from evdnerf_ros.limits import check_number

    from .servo import Limits, check_angle, check_duration_ms, check_limits, check_profile

    check_number(args.timeout, "servo --timeout (s)", low=0, low_open=True, high=3600)
    if args.eeprom is not None and not args.virtual:
        raise InputError("servo --eeprom: only with --virtual (a real board keeps its own EEPROM)")
    a = args.action
    if a == "ping":
        check_number(args.count, "servo ping --count", low=1, high=MAX_PINGS, integer=True)
    elif a in ("move", "turn"):
        args.angle = check_angle(args.angle, f"servo {a} ANGLE")
        args.ms = check_duration_ms(args.ms, f"servo {a} MS")
    elif a == "home":
        args.ms = check_duration_ms(args.ms, "servo home MS")
    elif a == "set-limits":
        args.limits = check_limits(Limits(*args.values), "servo set-limits")
    elif a == "set-profile":
        v = args.values
        if len(v) < 3 or len(v) % 2 == 0:
            raise InputError("servo set-profile START DEG MS [DEG MS ...]: give a start angle "
                             f"and (angle, ms) pairs; got {len(v)} numbers")
        args.profile = check_profile(v[0], [(v[i], v[i + 1]) for i in range(1, len(v), 2)],
                                     "servo set-profile")


def _cmd_servo(args) -> int:
    from .servo import ServoClient

    _check_servo_args(args)
    va = None
    try:
        if args.virtual:
            from .virtual_arduino import VirtualArduino

            va = VirtualArduino(eeprom=args.eeprom)
            port = va.start()
        else:
            port = args.port
        with ServoClient(port, timeout=args.timeout) as client:
            _servo_action(client, args)
    except BaseException:
        if va is not None:
            va.close(check=False)       # the first error is the one to report
        raise
    if va is not None:
        va.close()                      # raises when the EEPROM image could not be saved
    return 0


def _make_twin(model: str, scene: str, size: tuple[int, int]):
    """The virtual twin of `model` streaming `scene`, rendered at `size` in the sensor's centre
    (hosted by this process)."""
    from .camera.virtual.scene_source import CenteredSource, GivenEvents, SceneEventSource

    if model == "dvxplorer":
        from .camera.dvxplorer import DVXplorer as driver
        from .camera.virtual.dvxplorer import VirtualDVXplorer as twin
    elif model == "davis346":
        from .camera.davis346 import DAVIS346 as driver
        from .camera.virtual.davis346 import VirtualDAVIS346 as twin
    else:
        from .camera.evk4 import EVK4 as driver
        from .camera.virtual.evk4 import VirtualEVK4 as twin
    # One period of the (repeating) scene is generated before the twin is plugged in, so serving
    # transfers costs no rendering: generated on demand, a scene's renders compete with the
    # register replies of the camera's start sequence. Its thresholds are then those of the
    # default biases (a bias change reaches only a twin generating on demand).
    if size[0] > driver.width or size[1] > driver.height:
        from evdnerf_ros.errors import InputError

        raise InputError(f"--scene-size {size[0]}x{size[1]} does not fit the {driver.width}x{driver.height} "
                         "sensor; choose a smaller size")
    src = SceneEventSource(scene, *size)
    print(f"rendering {src.period_ns / 1e9:g} s of {scene} at {size[0]}x{size[1]} for the virtual camera ...",
          file=sys.stderr)
    events = src.events_until(src.period_ns - 1000)
    looped = GivenEvents(events, *size, loop=True, period_ns=src.period_ns, source=f"scene {scene}")
    return twin(CenteredSource(looped, driver.width, driver.height))


def _camera_with_twin(args) -> int:
    """Host the twin here and run the same command against it in a child process: the driver must
    not share a process with the emulator (a driver holding the GIL in libusb would deadlock)."""
    from .camera.errors import CameraError
    from .camera.virtual.usb import VirtualUsbBus, spawn_child, umockdev_available

    ok, why = umockdev_available()
    if not ok:
        raise CameraError(f"--virtual needs umockdev: {why}; run `bash quickstart.sh` as root to install it")
    twin = _make_twin(args.virtual, args.scene, args.scene_size)
    argv = [sys.executable, "-m", "evdnerf_ros", "camera", args.action]
    if args.action in ("info", "record"):
        argv += ["--serial", twin.serial]
    if args.action == "record":
        argv += ["-o", args.output, "--duration", str(args.duration), "--storage", args.storage]
        if args.biases:
            argv += ["--biases", args.biases]
    with VirtualUsbBus() as bus:
        bus.add(twin)
        print(f"virtual {args.virtual} (serial {twin.serial}) streaming {args.scene}", file=sys.stderr)
        proc = spawn_child(argv, bus, stdout=None, stderr=None)
        try:
            return proc.wait()
        except KeyboardInterrupt:
            proc.terminate()
            return proc.wait()


def _size(text: str) -> tuple[int, int]:
    import argparse

    w, sep, h = text.lower().partition("x")
    if not (sep and w.isdigit() and h.isdigit() and 0 < int(w) <= 4096 and 0 < int(h) <= 4096):
        raise argparse.ArgumentTypeError(f"expected WxH such as 128x96, got {text!r}")
    return int(w), int(h)


def _checked_camera(args) -> int:
    from evdnerf_ros.errors import InputError

    if args.action == "record" and not args.output:
        raise InputError("camera record: give the bag to write with -o BAG")
    if not 0 < args.duration <= 86400:
        raise InputError(f"camera: --duration must be in (0, 86400] s, got {args.duration}")
    if args.scene != "fork" and not args.virtual:
        raise InputError("camera: --scene applies to --virtual twins only")
    return _cmd_camera(args)


def _cmd_camera(args) -> int:
    if args.virtual:
        return _camera_with_twin(args)
    from .camera import list_cameras, open_camera

    if args.action == "list":
        cams = list_cameras()
        for cam in cams:
            print(cam)
        if not cams:
            print("no event camera found (DVXplorer, DAVIS, EVK4); for a virtual one: "
                  "evdnerf camera list --virtual dvxplorer|davis346|evk4")
        return 0
    with open_camera(serial=args.serial) as cam:
        if args.action == "info":
            print(json.dumps({"model": cam.model, "serial": cam.serial, "firmware_version": cam.firmware_version,
                              "logic_version": cam.logic_version, "width": cam.width, "height": cam.height,
                              "encoding": cam.encoding, "biases": cam.biases, "roi": cam.roi}, indent=2))
            return 0
        if args.biases:
            from .camera.biases import read_bias_file

            cam.set_biases(read_bias_file(args.biases))
        from .camera.record import record

        record(cam, args.output, duration_s=args.duration, storage=args.storage)
    return 0


def register(subparsers) -> None:
    """Add `flash`, `servo`, `camera` and `capture` to the `evdnerf` command (entry point `evdnerf.commands`)."""
    from .flash import BOARDS

    p = subparsers.add_parser("flash", help="flash the servo-rig firmware with avrdude",
                              description="Build firmware/build/rig_servo.hex if needed and "
                                          "write it through the board's bootloader "
                                          "(avrdude -c arduino).")
    p.add_argument("--port", required=True, help="serial port, e.g. /dev/ttyACM0")
    p.add_argument("--board", choices=sorted(BOARDS), default="uno",
                   help="uno: optiboot 115200 baud; nano: old bootloader 57600 (default uno)")
    p.add_argument("--hex", help="firmware hex to write (default: the built rig_servo.hex)")
    p.set_defaults(func=_cmd_flash)

    p = subparsers.add_parser("servo", help="talk to the servo-rig firmware",
                              description="Manual moves, profiles and pings over the rig_servo "
                                          "protocol (firmware/PROTOCOL.md).")
    where = p.add_mutually_exclusive_group(required=True)
    where.add_argument("--port", help="serial port of the Arduino")
    where.add_argument("--virtual", action="store_true",
                       help="start the virtual Arduino (firmware in simavr) for this command")
    p.add_argument("--eeprom", help="with --virtual: EEPROM image file (1024 bytes) kept "
                                     "between runs; checked readable and writable at start")
    p.add_argument("--timeout", type=float, default=1.0,
                   help="reply timeout in s, > 0 and <= 3600 (default 1)")
    acts = p.add_subparsers(dest="action", metavar="ACTION", required=True)
    acts.add_parser("hello", help="firmware name and protocol version")
    q = acts.add_parser("ping", help="round trip and device clock")
    q.add_argument("-n", "--count", type=int, default=1,
                   help=f"pings, 1..{MAX_PINGS} (>= 2 fits the clock)")
    for name in ("move", "turn"):
        q = acts.add_parser(name, help=f"{'scene servo' if name == 'move' else 'turntable'}: "
                                       "minimum-jerk move to DEG over MS")
        q.add_argument("angle", type=float, help="target angle in degrees, 0..180 (3 decimals max)")
        q.add_argument("ms", type=int, help="duration in ms (1..65535)")
    q = acts.add_parser("home", help="move to the profile's start angle")
    q.add_argument("ms", type=int, nargs="?", default=1000,
                   help="duration in ms, 1..65535 (default 1000)")
    acts.add_parser("run", help="run the stored profile (the fork swing)")
    acts.add_parser("stop", help="stop any motion where it is")
    acts.add_parser("status", help="angles and motion states")
    acts.add_parser("get-limits", help="angle, speed and pulse limits")
    q = acts.add_parser("set-limits", help="set and store the limits in EEPROM",
                        description="0 <= MIN_DEG < MAX_DEG <= 180, MAX_SPEED_DPS 1..6000, "
                                    "400 <= PULSE_MIN_US < PULSE_MAX_US <= 2600")
    q.add_argument("values", type=float, nargs=5,
                   metavar=("MIN_DEG", "MAX_DEG", "MAX_SPEED_DPS", "PULSE_MIN_US", "PULSE_MAX_US"))
    acts.add_parser("get-profile", help="the stored RUN profile")
    q = acts.add_parser("set-profile", help="set and store the RUN profile in EEPROM")
    q.add_argument("values", type=float, nargs="+", metavar="START DEG MS",
                   help="start angle then 1..8 (angle, ms) pairs; angles 0..180 deg with at "
                        "most 3 decimals, durations 1..65535 ms")
    p.set_defaults(func=_cmd_servo)

    from .capture_cli import register as register_capture

    register_capture(subparsers)

    p = subparsers.add_parser("camera", help="event cameras over USB: list, info, record (real or virtual)",
                              description="iniVation DVXplorer and Prophesee EVK4 over USB with the toolkit's "
                                          "own drivers (rig.camera); --virtual MODEL runs the camera's twin, "
                                          "which streams a simulated scene through emulated USB (umockdev).")
    p.add_argument("action", choices=["list", "info", "record"])
    p.add_argument("--serial", help="camera serial (default: the first camera found)")
    p.add_argument("--virtual", choices=TWINS, help="use the virtual twin of this model instead of hardware")
    p.add_argument("--scene", default="fork", help="with --virtual: scene preset or YAML it streams (default fork)")
    p.add_argument("--scene-size", type=_size, default=(128, 96), metavar="WxH",
                   help="with --virtual: the scene is rendered at this size in the sensor's centre, the rest of "
                        "the pixel array quiet; a full 1280x720 render runs far below real time on a laptop "
                        "CPU (default 128x96)")
    p.add_argument("-o", "--output", help="record: rosbag2 to write (must not exist)")
    p.add_argument("--duration", type=float, default=5.0,
                   help="record: wall seconds to record, > 0 and <= 86400 (default 5)")
    p.add_argument("--biases", help="record: bias file (`value %% name` lines, as Prophesee .bias files)")
    p.add_argument("--storage", choices=["mcap", "sqlite3"], default="mcap", help="record: bag storage")
    p.set_defaults(func=_checked_camera)
