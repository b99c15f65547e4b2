"""`evdnerf flash` and `evdnerf servo ...`: registered as an `evdnerf.commands` plugin.

evdnerf_ros (the CLI's home) never imports rig; setup.py's entry point
`evdnerf.commands: rig = rig.cli:register` makes the CLI find these commands.
"""

from __future__ import annotations


import json


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


def register(subparsers) -> None:
    """Add `flash` and `servo` to the `evdnerf` command (entry point `evdnerf.commands`)."""
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



