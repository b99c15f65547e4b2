"""`evdnerf sync`, `convert`, `import-evdnerf`, `import-bags`: from a session to a training set."""

from __future__ import annotations

import json

from ..errors import EvdnerfError
from ..options import add_options, options_from_args
from .common import number



def _cmd_sync(args) -> int:
    from dataclasses import asdict

    from ..session.sync import SyncOptions, run_sync

    options = options_from_args(SyncOptions, args)
    result = run_sync(args.session, log=None if args.json else print, **asdict(options))
    if args.json:
        print(json.dumps(result, indent=2, default=str))
    return 0


def _cmd_convert(args) -> int:
    from ..session.convert import ConvertOptions, run_convert
    from ..units import parse_duration_ns

    if (args.start is None) != (args.end is None):
        raise EvdnerfError("--start and --end go together (or leave both out for the automatic "
                           "motion window)")
    window = {}
    if args.start is not None:
        window["window"] = (parse_duration_ns(args.start, name="--start"),
                            parse_duration_ns(args.end, name="--end"))
    run_convert(args.session, args.output, options_from_args(ConvertOptions, args, **window),
                overwrite=args.overwrite)
    return 0


def _cmd_import_evdnerf(args) -> int:
    from ..io.evdnerf_format import run_import_evdnerf

    run_import_evdnerf(args.source, args.output, c_pos=args.c_pos, c_neg=args.c_neg,
                       overwrite=args.overwrite)
    return 0


def _cmd_import_bags(args) -> int:
    from ..session.importer import ImportOptions, import_bags

    options = options_from_args(ImportOptions, args)
    result = import_bags(args.bags, args.output, options, overwrite=args.overwrite, log=print)
    rate = result.events / result.seconds / 1e6 if result.seconds > 0 else 0.0
    print(f"{result.root}: {len(result.views)} view(s), {result.events} events from {len(result.inputs)} bag(s) "
          f"in {result.seconds:.2f} s ({rate:.1f} Mev/s); next: evdnerf sync {result.root}")
    return 0


def register(sub) -> None:
    p = sub.add_parser("sync", help="align the views' clocks of a session",
                       description="Find each view's motion onset in its own clock: from "
                                   "EXT_TRIGGER edges in the event stream (exact), the firmware's "
                                   "START TimeReference, or the event-rate curve (robust onset "
                                   "with hot-pixel removal, refined by cross-correlating rate "
                                   "curves at 100 us). Writes the offsets into session.yaml "
                                   "(never the bags), reports how far the methods disagree and "
                                   "saves a plot of the aligned rate curves. Rate-based sync "
                                   "needs a sudden motion onset.")
    p.add_argument("session", help="session folder")
    from ..session.sync import SyncOptions

    add_options(p, SyncOptions)
    p.add_argument("--json", action="store_true", help="print the result as JSON")
    p.set_defaults(func=_cmd_sync)

    p = sub.add_parser("convert", help="turn a synced session into a training set",
                       description="Decode every view, apply the sync offsets (t = 0 at the "
                                   "common motion onset), crop the time window, optionally sum "
                                   "2x2 pixel blocks, and write TRAIN.h5 (chunked, compressed, "
                                   "with a 1 ms time index per view) or, with --format evdnerf, "
                                   "the EvDNeRF paper's transforms_*.json + data_frames_*.npy.")
    p.add_argument("session", help="session folder (session.yaml + one bag per view)")
    p.add_argument("-o", "--output", required=True, help="TRAIN.h5 or, for --format evdnerf, a folder")
    p.add_argument("--start", help="window start in the synced clock, e.g. 0 or --start=-50ms "
                                   "(with --end; default: the motion window)")
    p.add_argument("--end", help="window end in the synced clock, e.g. 1s")
    from ..session.convert import ConvertOptions

    add_options(p, ConvertOptions)
    p.add_argument("--overwrite", action="store_true", help="replace an existing output")
    p.set_defaults(func=_cmd_convert)

    p = sub.add_parser("import-evdnerf", help="read a dataset in the EvDNeRF paper's format",
                       description="Read transforms_{train,val}.json + data_frames_*.npy (and "
                                   "per-view event arrays when present) into our TRAIN.h5, "
                                   "converting Blender/OpenGL poses to OpenCV axes. Their event "
                                   "files may be pickles: import only datasets you trust.")
    p.add_argument("source", help="dataset folder")
    p.add_argument("-o", "--output", required=True, help="TRAIN.h5")
    p.add_argument("--c-pos", type=number(float, low=0, low_open=True, high=10),
                   help="C+ if the dataset does not say, in (0, 10]")
    p.add_argument("--c-neg", type=number(float, low=0, low_open=True, high=10),
                   help="C- if the dataset does not say, in (0, 10]")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output")
    p.set_defaults(func=_cmd_import_evdnerf)

    p = sub.add_parser("import-bags", help="a session from bags recorded without this toolkit",
                       description="Build a capture session from bags recorded by metavision_driver, "
                                   "libcaer_driver or `ros2 bag record` of dvs_msgs/EventArray (rosbag2 "
                                   "folders, .mcap, .db3, ROS 1 .bag): one bag per view, or one bag cut into "
                                   "views at its trigger edges or servo START messages (--split-at). "
                                   "EventPacket topics of whole bags are passed through byte for byte; split "
                                   "views and dvs_msgs arrays are re-encoded (times unchanged). Intrinsics from "
                                   "--calibration, the bags' CameraInfo or --fov; poses from --poses or --ring. "
                                   "Then: evdnerf sync SESSION; evdnerf convert SESSION -o TRAIN.h5.")
    p.add_argument("bags", nargs="+", metavar="BAG", help="input bags, one per view (in view order)")
    p.add_argument("-o", "--output", required=True, help="session folder to write")
    from ..session.importer import ImportOptions

    add_options(p, ImportOptions)
    p.add_argument("--overwrite", action="store_true", help="replace a session folder this toolkit wrote")
    p.set_defaults(func=_cmd_import_bags)
