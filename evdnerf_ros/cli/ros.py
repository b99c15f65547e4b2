"""`evdnerf publish` and `evdnerf echo`: the ROS 2 nodes without ROS."""

from __future__ import annotations

import json

from ..errors import EvdnerfError
from ..options import add_options, options_from_args
from .common import number



def _cmd_publish(args) -> int:
    from ..nodes.event_publisher import run_node
    from ..ros.args import parse_value

    overrides = {k: v for k, v in (
        ("scene", args.scene), ("run_dir", args.run), ("trajectory", args.trajectory),
        ("bag", args.output), ("encoding", args.encoding), ("duration", args.duration),
        ("realtime_factor", args.realtime_factor), ("device", args.device)) if v is not None}
    if args.realtime_factor is None and not args.params_file:
        overrides["realtime_factor"] = 0.0     # a bag does not need real-time pace
    if args.resolution:
        overrides["camera.width"], overrides["camera.height"] = args.resolution
    for item in args.param or ():
        name, sep, value = item.partition("=")
        if not sep or not name:
            raise EvdnerfError(f"-p {item!r}: expected name=value (e.g. -p c_pos=0.3)")
        overrides[name] = parse_value(value, f"-p {name}")
    if not args.dds and not overrides.get("bag"):
        raise EvdnerfError("without --dds the events go only into a bag: give -o BAG")
    argv = ["--ros-args", "--params-file", args.params_file] if args.params_file else []
    report = run_node(argv, overrides=overrides, dds=args.dds)
    if args.json:
        print(json.dumps(report.as_dict(), indent=2))
    return 130 if report.interrupted else 0


def _cmd_echo(args) -> int:
    from ..nodes.echo import EchoOptions, format_report, run_echo

    o = options_from_args(EchoOptions, args)
    rep = run_echo(args.topic, o.type, qos=o.qos, depth=o.depth, count=o.count, duration=o.duration, idle=o.idle,
                   png=o.png, npz=o.save_events, overwrite=o.overwrite,
                   print_fn=(lambda *_: None) if args.json else print)
    if args.json:
        print(json.dumps(rep.as_dict(), indent=2))
    else:
        print(format_report(rep))
    return 0


def register(sub) -> None:
    p = sub.add_parser("publish", help="publish the events a robot-mounted camera would see (bag and/or DDS)",
                       description="Run the event publisher node (the `event_publisher` executable) without "
                                   "ROS: render a synthetic scene or a trained run along a robot trajectory, "
                                   "generate a continuous event stream and write it (EventPacket evt3 + "
                                   "CameraInfo) into a rosbag2; --dds also publishes on Cyclone DDS with ROS 2 "
                                   "naming (ROS_DOMAIN_ID, ROS_LOCALHOST_ONLY). Every node parameter can be set "
                                   "with -p name=value or --params-file (see docs/reference/node-event_publisher.md).")
    p.add_argument("-o", "--output", help="rosbag2 to write (must not exist)")
    p.add_argument("--dds", action="store_true", help="also publish over DDS")
    p.add_argument("--scene", help="scene preset or YAML (default fork)")
    p.add_argument("--run", help="trained run folder instead of a synthetic scene (without --trajectory: once round "
                                  "its training views, with the camera it was trained with)")
    p.add_argument("--trajectory", help="robot poses: bag (Odometry, PoseStamped, /tf), .yaml or .csv")
    p.add_argument("--resolution", type=number(int, low=1, high=16_384), nargs=2, metavar=("W", "H"),
                   help="camera size, 1..16384 each (default: the scene's)")
    p.add_argument("--encoding", choices=["evt3", "evt2", "mono", "array"], help="event message (default evt3)")
    p.add_argument("--duration", type=number(float, low=0, low_open=True), help="seconds to publish (default: all)")
    p.add_argument("--realtime-factor", type=number(float, low=0, high=1e6),
                   help="1 = real time, 0 = as fast as possible (default 0 here unless --params-file; "
                        "1 for event_publisher)")
    p.add_argument("--device", type=str.lower, choices=["auto", "cpu", "cuda"],
                   help="where a trained run's field is evaluated (default auto: cuda when available)")
    p.add_argument("-p", "--param", action="append", metavar="NAME=VALUE", help="any node parameter (repeatable)")
    p.add_argument("--params-file", help="ros__parameters YAML (as config/event_publisher.yaml)")
    p.add_argument("--json", action="store_true", help="print the run report as JSON")
    p.set_defaults(func=_cmd_publish)

    p = sub.add_parser("echo", help="show what is on a DDS topic: rate, sizes, an event image",
                       description="Subscribe to a ROS 2 topic over Cyclone DDS (ROS_DOMAIN_ID, "
                                   "ROS_LOCALHOST_ONLY) and report message rate, bandwidth and size; event "
                                   "topics are decoded and drawn as an ASCII event image (and --png).")
    p.add_argument("topic", help="absolute topic, e.g. /event_publisher/events")
    from ..nodes.echo import EchoOptions

    add_options(p, EchoOptions)
    p.add_argument("--json", action="store_true", help="print the report as JSON")
    p.set_defaults(func=_cmd_echo)
