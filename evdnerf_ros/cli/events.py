"""`evdnerf convert-events`, `info`, `render-events`, `salvage-bag`, `video2events`: event files and bags."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from ..errors import EvdnerfError
from ..options import add_options, options_from_args
from .common import GEOMETRY_HELP, STRICT_HELP, TIME_UNIT_HELP, TOPIC_HELP, geometry, number



def _cmd_convert_events(args) -> int:
    from ..io.event_files import container_kind, read_event_file, write_event_file

    bags = ("rosbag1", "rosbag2")
    kinds = container_kind(args.input), container_kind(args.output)
    if kinds[0] in bags and kinds[1] in bags and args.out_topic is None:
        return _reencode(args, same_family=kinds[0] == kinds[1])
    if args.repacketize or args.events_only:
        raise EvdnerfError("--repacketize and --events-only apply to bag -> bag conversions only (and not "
                           "with --out-topic)")
    data = read_event_file(args.input, topic=args.topic, geometry=args.geometry, time_unit=args.time_unit,
                           strict=args.strict)
    out_topic = args.out_topic
    if out_topic is None and container_kind(args.output) in ("rosbag1", "rosbag2"):
        out_topic = args.topic  # keep the input's topic name when writing a bag
    encoding = write_event_file(args.output, data, encoding=args.encoding, topic=out_topic,
                                storage=args.storage)
    print(f"{args.output}: {len(data.events)} events, {len(data.triggers)} triggers, "
          f"{data.width}x{data.height}" + (f", encoding {encoding}" if encoding else ""))
    return 0


def _reencode(args, *, same_family: bool) -> int:
    """Bag -> bag: the event topic re-encoded, message by message with its stamps, seq and frame_id,
    and every other topic copied byte for byte (only between bags of one ROS version)."""
    from ..io.reencode import reencode_bag

    r = reencode_bag(args.input, args.output, encoding=args.encoding, storage=args.storage, topic=args.topic,
                     repacketize=args.repacketize, packet_ns=args.packet,
                     other_topics=same_family and not args.events_only)
    print(f"{args.output}: {r['events']} events in {r['messages']} messages on {r['topic']}, encoding "
          f"{r['encoding']}" + "".join(f"\n  {t}: {n} messages copied" for t, n in r["copied"].items()))
    return 0


def _cmd_video2events(args) -> int:
    from ..sim.video import VideoOptions, run_video2events

    n = run_video2events(args.frames, args.output, options_from_args(VideoOptions, args))
    print(f"{args.output}: {n} events")
    return 0


def _cmd_salvage_bag(args) -> int:
    from ..io.mcap_salvage import salvage_bag

    counts = salvage_bag(args.partial, args.output, storage=args.storage)
    total = sum(counts.values())
    print(f"{args.output}: {total} messages salvaged" +
          "".join(f"\n  {topic}: {n}" for topic, n in counts.items()))
    return 0


def _cmd_info(args) -> int:
    from ..io.info import describe

    info = describe(args.input, topic=args.topic, time_unit=args.time_unit, geometry=args.geometry,
                    strict=args.strict)
    if args.json:
        print(json.dumps(info, indent=2))
    else:
        from ..io.info import format_info

        print(format_info(info))
    return 0


def _cmd_render_events(args) -> int:
    from ..atomic import check_output
    from ..events import event_image, event_rate, plot_event_rate, save_png, time_slice
    from ..io.event_files import read_event_file
    from ..limits import check_memory
    from ..units import format_ns, parse_duration_ns

    start = parse_duration_ns(args.start, name="--start")
    window = parse_duration_ns(args.window, name="--window")
    if window <= 0:
        raise EvdnerfError(f"--window must be positive, got {args.window}")
    rate_bin = parse_duration_ns(args.rate_bin, name="--rate-bin") if args.rate else None
    if rate_bin is not None and rate_bin <= 0:
        raise EvdnerfError(f"--rate-bin must be positive, got {args.rate_bin}")
    output = Path(args.output)
    rate_path = output.with_name(output.stem + "_rate.png")
    # Outputs are checked before the input is read: nothing is decoded for an unwritable path.
    for path in (output, rate_path) if args.rate else (output,):
        check_output(path, overwrite=args.overwrite)
    data = read_event_file(args.input, topic=args.topic, geometry=args.geometry, time_unit=args.time_unit,
                           strict=args.strict)
    ev = data.events
    if ev.size == 0:
        raise EvdnerfError(f"{args.input}: holds no events; nothing to render")
    check_memory(data.width * data.height * args.upscale ** 2 * 4.0,
                 f"--upscale {args.upscale} of a {data.width}x{data.height} image", "use a smaller --upscale")
    t0 = start if args.absolute else int(ev["t"][0]) + start
    sl = time_slice(ev, t0, t0 + window)
    rate = event_rate(ev["t"], rate_bin, name="--rate-bin") if args.rate else None   # sized before writing
    save_png(output, event_image(sl, data.width, data.height, saturation=args.saturation),
             upscale=args.upscale, overwrite=args.overwrite)
    print(f"{output}: {len(sl)} events in [{format_ns(t0)}, {format_ns(t0 + window)})")
    if args.rate:
        plot_event_rate(rate_path, {Path(args.input).name: rate},
                        title=f"event rate ({args.rate_bin} bins)", overwrite=args.overwrite)
        print(f"{rate_path}: event-rate plot")
    return 0


def _duration(text: str) -> int:
    from ..units import parse_duration_ns

    try:
        ns = parse_duration_ns(text, name="--packet")
    except EvdnerfError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    if not 0 < ns <= 3_600 * 10**9:
        raise argparse.ArgumentTypeError(f"must be in (0, 3600s], got {text!r}")
    return ns


def register(sub) -> None:
    from ..io.h5events import TIME_UNITS

    p = sub.add_parser("convert-events", help="convert events between RAW, npz, h5 and bags",
                       description="Convert an event file. The container follows the path: "
                                   ".raw (EVT 3.0 / 2.0 by header), .npz (t int64 ns, x, y, p "
                                   "+1/-1, width, height), .h5, .bag (ROS 1, dvs_msgs/EventArray), "
                                   "a directory / .mcap / .db3 (rosbag2).")
    p.add_argument("input", help="input event file or bag")
    p.add_argument("output", help="output path (must not exist)")
    from ..io.packetizer import DEFAULT_PACKET_NS, WRITE_ENCODINGS

    p.add_argument("--encoding", choices=WRITE_ENCODINGS,
                   help="output encoding: evt3/evt2 for .raw; evt3, evt2, mono, libcaer, libcaer_cmp "
                        "(EventPacket) or array (dvs_msgs/EventArray) for bags (default evt3; "
                        "array for ROS 1)")
    p.add_argument("--topic", help=TOPIC_HELP)
    p.add_argument("--geometry", type=geometry, metavar="WxH", help=GEOMETRY_HELP)
    p.add_argument("--time-unit", choices=TIME_UNITS, help=TIME_UNIT_HELP)
    p.add_argument("--strict", action="store_true", help=STRICT_HELP)
    p.add_argument("--out-topic", help="topic in the output bag (default: same as --topic)")
    p.add_argument("--storage", choices=["mcap", "sqlite3"],
                   help="rosbag2 storage plugin for a directory output (default mcap)")
    p.add_argument("--repacketize", action="store_true",
                   help="bag -> bag: cut new packets of --packet length instead of keeping each message "
                        "(its stamp, seq and frame_id)")
    p.add_argument("--packet", type=_duration, default=DEFAULT_PACKET_NS, metavar="DURATION",
                   help="bag -> bag with --repacketize: packet length (default 1ms)")
    p.add_argument("--events-only", action="store_true",
                   help="bag -> bag: write only the event topic (default: every other topic is copied "
                        "byte for byte; between ROS 1 and ROS 2 bags only the event topic is written)")
    p.set_defaults(func=_cmd_convert_events)

    p = sub.add_parser("video2events", help="turn a high-speed video into events (exact ESIM)",
                       description="FRAMES.npz holds `frames` (N, H, W) linear intensity "
                                   "(float, white = 1) and `t` (N,) int64 ns. Every threshold "
                                   "crossing between frames is emitted at its linearly "
                                   "interpolated time. OUT takes any format of convert-events.")
    p.add_argument("frames", help="FRAMES.npz")
    p.add_argument("output", help="output event file (format from the path; must not exist)")
    from ..sim.video import VideoOptions

    add_options(p, VideoOptions)
    p.set_defaults(func=_cmd_video2events)

    p = sub.add_parser("salvage-bag", help="write out the messages of a recording that was killed",
                       description="A recording killed outright (SIGKILL, power loss) leaves its bag in a "
                                   "hidden .BAG.<pid>.<id>.partial folder: an MCAP file without its summary, "
                                   "which no reader opens. Recorders flush a chunk about once a second; this "
                                   "reads every complete chunk and writes its messages into a new rosbag2.")
    p.add_argument("partial", help="the .partial folder (or the .mcap file inside it)")
    p.add_argument("-o", "--output", required=True, help="rosbag2 to write (must not exist)")
    p.add_argument("--storage", choices=["mcap", "sqlite3"], default="mcap",
                   help="storage of the new bag (default %(default)s)")
    p.set_defaults(func=_cmd_salvage_bag)

    p = sub.add_parser("info", help="summarise an event file or bag",
                       description="Print topics, message types and counts (bags), event count, "
                                   "duration, mean rate and resolution.")
    p.add_argument("input")
    p.add_argument("--topic", help=TOPIC_HELP)
    p.add_argument("--json", action="store_true", help="print JSON instead of text")
    p.add_argument("--geometry", type=geometry, metavar="WxH", help=GEOMETRY_HELP)
    p.add_argument("--time-unit", choices=TIME_UNITS, help=TIME_UNIT_HELP)
    p.add_argument("--strict", action="store_true", help=STRICT_HELP)
    p.set_defaults(func=_cmd_info)

    p = sub.add_parser("render-events", help="draw an event image of one time window",
                       description="Red = positive, blue = negative events in [start, "
                                   "start + window). Times take s (default), ms, us or ns "
                                   "suffixes and are relative to the first event unless "
                                   "--absolute.")
    p.add_argument("input")
    p.add_argument("--start", required=True, help="window start, e.g. 0.5 or 500ms")
    p.add_argument("--window", required=True, help="window length, e.g. 10ms")
    p.add_argument("-o", "--output", required=True, help="PNG path")
    p.add_argument("--absolute", action="store_true", help="--start is an absolute time")
    p.add_argument("--saturation", type=number(int, low=1), default=1,
                   help="net event count drawn at full colour, >= 1 (default %(default)s)")
    p.add_argument("--upscale", type=number(int, low=1, high=64), default=1,
                   help="repeat each pixel this many times for viewing, 1..64 (default %(default)s)")
    p.add_argument("--rate", action="store_true",
                   help="also plot the event rate of the whole recording (<output>_rate.png)")
    p.add_argument("--rate-bin", default="1ms", help="rate histogram bin (default %(default)s)")
    p.add_argument("--topic", help=TOPIC_HELP)
    p.add_argument("--geometry", type=geometry, metavar="WxH", help=GEOMETRY_HELP)
    p.add_argument("--time-unit", choices=TIME_UNITS, help=TIME_UNIT_HELP)
    p.add_argument("--strict", action="store_true", help=STRICT_HELP)
    p.add_argument("--overwrite", action="store_true",
                   help="replace existing PNG files at the output paths (never a folder)")
    p.set_defaults(func=_cmd_render_events)
