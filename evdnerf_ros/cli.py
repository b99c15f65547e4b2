"""The `evdnerf` command: one subcommand per job.

Bad input prints one line `evdnerf: error: ...` and exits with status 2; outputs are written
atomically, so a failed command leaves nothing half-written.
"""

from __future__ import annotations

import argparse
import errno
import json
import signal
import sys
import threading
import warnings
from pathlib import Path

from . import __version__
from .errors import EvdnerfError

TOPIC_HELP = "event topic inside a bag (default /event_camera/events)"
GEOMETRY_HELP = ("sensor size WxH of a RAW file whose header gives none (neither a geometry line nor a "
                 "known plugin_name), e.g. 640x480")


def geometry(text: str) -> tuple[int, int]:
    """argparse type of --geometry WxH."""
    from .limits import check_number

    w, sep, h = str(text).lower().partition("x")
    try:
        if not sep:
            raise ValueError("no 'x' between width and height")
        return (check_number(int(w), "width", low=1, high=65535),
                check_number(int(h), "height", low=1, high=65535))
    except (ValueError, EvdnerfError) as exc:
        raise argparse.ArgumentTypeError(f"expected WxH such as 640x480, got {text!r} ({exc})") from None


def _cmd_convert_events(args) -> int:
    from .io.event_files import container_kind, read_event_file, write_event_file

    data = read_event_file(args.input, topic=args.topic, geometry=args.geometry)
    out_topic = args.out_topic
    if out_topic is None and container_kind(args.output) in ("rosbag1", "rosbag2"):
        out_topic = args.topic  # keep the input's topic name when writing a bag
    encoding = write_event_file(args.output, data, encoding=args.encoding, topic=out_topic,
                                storage=args.storage)
    print(f"{args.output}: {len(data.events)} events, {len(data.triggers)} triggers, "
          f"{data.width}x{data.height}" + (f", encoding {encoding}" if encoding else ""))
    return 0


def _cmd_salvage_bag(args) -> int:
    from .io.mcap_salvage import salvage_bag

    counts = salvage_bag(args.partial, args.output, storage=args.storage)
    total = sum(counts.values())
    print(f"{args.output}: {total} messages salvaged" +
          "".join(f"\n  {topic}: {n}" for topic, n in counts.items()))
    return 0


def _cmd_info(args) -> int:
    from .io.info import describe

    info = describe(args.input, topic=args.topic)
    if args.json:
        print(json.dumps(info, indent=2))
    else:
        from .io.info import format_info

        print(format_info(info))
    return 0


def _cmd_render_events(args) -> int:
    from .atomic import check_output
    from .events import event_image, event_rate, plot_event_rate, save_png, time_slice
    from .io.event_files import read_event_file
    from .limits import check_memory
    from .units import format_ns, parse_duration_ns

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
    data = read_event_file(args.input, topic=args.topic, geometry=args.geometry)
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


def _cmd_video2events(args) -> int:
    from .sim.video import run_video2events

    n = run_video2events(args.frames, args.output, c_pos=args.c_pos, c_neg=args.c_neg,
                         eps=args.eps, sigma=args.sigma, interval_sigma=args.interval_sigma,
                         refractory_ns=args.refractory_ns, seed=args.seed,
                         gamma_8bit=args.gamma_8bit)
    print(f"{args.output}: {n} events")
    return 0


def _cmd_simulate(args) -> int:
    from .sim.session import SimulationOptions, simulate_session
    from .units import parse_duration_ns

    options = SimulationOptions(
        views=args.views, val_views=args.val_views,
        resolution=tuple(args.resolution) if args.resolution else None, seed=args.seed,
        c_pos=args.c_pos, c_neg=args.c_neg, eps=args.eps, threshold_sigma=args.sigma,
        refractory_ns=args.refractory_ns, tolerance_c=args.tolerance_c,
        min_step_ns=parse_duration_ns(args.min_step, name="--min-step"),
        max_step_ns=parse_duration_ns(args.max_step, name="--max-step"),
        supersample=args.supersample, frame_rate_hz=args.frame_rate,
        blur_samples=args.blur_samples, gt_times=args.gt_times,
        moving_views=args.moving_views, moving_arc_deg=args.moving_arc_deg,
        max_clock_offset_s=args.max_clock_offset, jobs=args.jobs)
    simulate_session(args.scene, Path(args.output), options, overwrite=args.overwrite)
    return 0


def _cmd_sync(args) -> int:
    from .session.sync import run_sync
    from .units import parse_duration_ns

    extra = {k: v for k, v in (("events_topic", args.events_topic),
                               ("trigger_topic", args.trigger_topic)) if v is not None}
    result = run_sync(args.session, bin_ns=parse_duration_ns(args.bin, name="--bin"),
                      method=args.method, reference_view=args.reference,
                      refine=not args.no_refine, plot_path=args.plot, overwrite=args.overwrite,
                      log=None if args.json else print, **extra)
    if args.json:
        print(json.dumps(result, indent=2, default=str))
    return 0


def _cmd_convert(args) -> int:
    from .session.convert import run_convert
    from .units import parse_duration_ns

    if (args.start is None) != (args.end is None):
        raise EvdnerfError("--start and --end go together (or leave both out for the automatic "
                           "motion window)")
    window = None
    if args.start is not None:
        window = (parse_duration_ns(args.start, name="--start"),
                  parse_duration_ns(args.end, name="--end"))
    run_convert(args.session, args.output, fmt=args.format, window=window,
                downsample=args.downsample, offsets=args.offsets, poses=args.poses,
                intrinsics=args.intrinsics, frames=not args.no_frames,
                compression=args.compression, n_windows=args.n_windows,
                event_time=args.event_time, raw_events=not args.no_raw_events,
                overwrite=args.overwrite)
    return 0


def _cmd_import_evdnerf(args) -> int:
    from .io.evdnerf_format import run_import_evdnerf

    run_import_evdnerf(args.source, args.output, c_pos=args.c_pos, c_neg=args.c_neg,
                       overwrite=args.overwrite)
    return 0


def _cmd_train(args) -> int:
    from .eval.evaluate import validation_eval
    from .train import run_train

    if args.minutes is None and args.iters is None:
        raise EvdnerfError("give a budget: --minutes M or --iters N")
    eval_fn = None if args.no_eval else validation_eval(max_views=args.eval_views)
    result = run_train(args.train_set, args.output, config=args.config, minutes=args.minutes,
                       iters=args.iters, init=args.init, overwrite=args.overwrite, eval_fn=eval_fn)
    print(f"{args.output}: {result['iterations']} iterations in {result['wall_s']:.1f} s, "
          f"final loss {result['loss']}")
    return 0


def _cmd_eval(args) -> int:
    from .eval.evaluate import run_eval

    result = run_eval(args.run, args.train_set, n_windows=args.windows, max_views=args.max_views,
                      image_path=Path(args.run) / "eval_events.png",
                      log=(lambda *_: None) if args.json else print)
    if args.json:
        print(json.dumps(result, indent=2))
    return 0


def _cmd_report(args) -> int:
    from .eval.figures import run_report

    result = run_report(args.runs, Path(args.output), overwrite=args.overwrite)
    print(Path(result["md"]).read_text())
    return 0


def _cmd_demo(args) -> int:
    from .demo import run_demo

    run_demo(Path(args.output), overwrite=args.overwrite, train_minutes=args.train_minutes)
    return 0


def _cmd_publish(args) -> int:
    from .nodes.event_publisher import run_node
    from .ros.args import parse_value

    overrides = {k: v for k, v in (
        ("scene", args.scene), ("run_dir", args.run), ("trajectory", args.trajectory),
        ("bag", args.output), ("encoding", args.encoding), ("duration", args.duration),
        ("realtime_factor", args.realtime_factor)) if v is not None}
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
    from .nodes.echo import format_report, run_echo

    rep = run_echo(args.topic, args.type, qos=args.qos, depth=args.depth, count=args.count, duration=args.duration,
                   idle=args.idle, png=args.png, npz=args.save_events, overwrite=args.overwrite,
                   print_fn=(lambda *_: None) if args.json else print)
    if args.json:
        print(json.dumps(rep.as_dict(), indent=2))
    else:
        print(format_report(rep))
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="evdnerf",
        description="EvDNeRF rig toolkit: event files and bags, (later) simulation, sync, "
                    "training and event publishing.")
    parser.add_argument("--version", action="version", version=f"evdnerf {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)

    p = sub.add_parser("demo", help="run the end-to-end demo on the embedded virtual scene",
                       description="Simulate a capture session of the servo-swung fork (one "
                                   "rosbag2 per view), convert a recording to every container and "
                                   "check it is bit-exact, draw event images and event-rate plots, "
                                   "sync the views, convert to a training set, train the field on "
                                   "the events, evaluate it on validation views and report "
                                   "events-PSNR against wall time.")
    p.add_argument("-o", "--output", default="demo_output", help="output folder (default: %(default)s)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output folder")
    p.add_argument("--train-minutes", type=number(float, low=0, low_open=True, high=10_080), default=2.0,
                   help="training budget of the demo's field, in (0, 10080] (default: %(default)s)")
    p.set_defaults(func=_cmd_demo)

    p = sub.add_parser("convert-events", help="convert events between RAW, npz, h5 and bags",
                       description="Convert an event file. The container follows the path: "
                                   ".raw (EVT 3.0 / 2.0 by header), .npz (t int64 ns, x, y, p "
                                   "+1/-1, width, height), .h5, .bag (ROS 1, dvs_msgs/EventArray), "
                                   "a directory / .mcap / .db3 (rosbag2).")
    p.add_argument("input", help="input event file or bag")
    p.add_argument("output", help="output path (must not exist)")
    p.add_argument("--encoding", choices=["evt3", "evt2", "mono", "array"],
                   help="output encoding: evt3/evt2 for .raw; evt3 (EventPacket), mono "
                        "(EventPacket) or array (dvs_msgs/EventArray) for bags (default evt3; "
                        "array for ROS 1)")
    p.add_argument("--topic", help=TOPIC_HELP)
    p.add_argument("--geometry", type=geometry, metavar="WxH", help=GEOMETRY_HELP)
    p.add_argument("--out-topic", help="topic in the output bag (default: same as --topic)")
    p.add_argument("--storage", choices=["mcap", "sqlite3"],
                   help="rosbag2 storage plugin for a directory output (default mcap)")
    p.set_defaults(func=_cmd_convert_events)

    from .events.logmap import LOG_EPS

    p = sub.add_parser("video2events", help="turn a high-speed video into events (exact ESIM)",
                       description="FRAMES.npz holds `frames` (N, H, W) linear intensity "
                                   "(float, white = 1) and `t` (N,) int64 ns. Every threshold "
                                   "crossing between frames is emitted at its linearly "
                                   "interpolated time. OUT takes any format of convert-events.")
    p.add_argument("frames", help="FRAMES.npz")
    p.add_argument("output", help="output event file (format from the path; must not exist)")
    p.add_argument("--c-pos", type=float, default=0.2, help="positive threshold C+ (default %(default)s)")
    p.add_argument("--c-neg", type=float, default=0.2, help="negative threshold C- (default %(default)s)")
    p.add_argument("--eps", type=float, default=LOG_EPS,
                   help="log offset: L = log(I + eps), white = 1 (default %(default)s)")
    p.add_argument("--sigma", type=float, default=0.0,
                   help="per-pixel threshold mismatch std, fixed from --seed (default %(default)s)")
    p.add_argument("--interval-sigma", type=float, default=0.0,
                   help="per-interval threshold noise std, ESIM's model (default %(default)s)")
    p.add_argument("--refractory-ns", type=int, default=0, help="refractory period in ns (default 0)")
    p.add_argument("--seed", type=int, default=0, help="noise seed (default %(default)s)")
    p.add_argument("--gamma-8bit", action="store_true",
                   help="accept 8-bit gamma-encoded frames and linearise them ((v/255)^2.2)")
    p.set_defaults(func=_cmd_video2events)

    from .sim.session import SimulationOptions

    d = SimulationOptions()
    p = sub.add_parser("simulate", help="simulate a capture session of a synthetic scene",
                       description="Render a scene (preset name: jet-down, jet-spiral, jet-land, "
                                   "multi, lego, fork; or a scene YAML) from every camera of its "
                                   "ring, generate exact events with adaptive time sampling, and "
                                   "write a session: session.yaml + one rosbag2 per view "
                                   "(EventPacket evt3, CameraInfo, camera pose, servo JointState "
                                   "and START/DONE for servo scenes), blurred frames and ground "
                                   "truth. Each view gets its own clock offset (ground truth in "
                                   "session.yaml) for sync to find.")
    p.add_argument("scene", help="preset name or scene YAML path")
    p.add_argument("-o", "--output", required=True, help="session folder (must not exist)")
    p.add_argument("--views", type=int, help="training views (default: the scene's ring)")
    p.add_argument("--val-views", type=int, help="validation views (default: the scene's; 0: none)")
    p.add_argument("--resolution", type=int, nargs=2, metavar=("W", "H"),
                   help="image size (default: the scene's intrinsics)")
    p.add_argument("--seed", type=int, default=d.seed, help="clock offsets and noise (default %(default)s)")
    p.add_argument("--c-pos", type=float, default=d.c_pos, help="C+ (default %(default)s)")
    p.add_argument("--c-neg", type=float, default=d.c_neg, help="C- (default %(default)s)")
    p.add_argument("--eps", type=float, default=d.eps, help="log offset, white = 1 (default %(default)s)")
    p.add_argument("--sigma", type=float, default=d.threshold_sigma,
                   help="per-pixel threshold mismatch std (default %(default)s)")
    p.add_argument("--refractory-ns", type=int, default=d.refractory_ns, help="refractory period (ns)")
    p.add_argument("--tolerance-c", type=float, default=d.tolerance_c,
                   help="adaptive sampling: allowed midpoint deviation from linear, in units of C "
                        "(default %(default)s)")
    p.add_argument("--min-step", default=f"{d.min_step_ns}ns",
                   help="adaptive sampling: finest step (default 1ms)")
    p.add_argument("--max-step", default=f"{d.max_step_ns}ns",
                   help="adaptive sampling: coarsest step (default 10ms)")
    p.add_argument("--supersample", type=int, default=d.supersample,
                   help="antialiasing: s x s rays per pixel (default %(default)s)")
    p.add_argument("--frame-rate", type=float, default=d.frame_rate_hz,
                   help="blurred grey frames per second; 0: none (default %(default)s)")
    p.add_argument("--blur-samples", type=int, default=d.blur_samples,
                   help="renders averaged per frame exposure (default %(default)s)")
    p.add_argument("--gt-times", type=int, default=d.gt_times,
                   help="ground-truth intensity/depth renders per view (default %(default)s)")
    p.add_argument("--moving-views", type=int, default=d.moving_views,
                   help="extra validation views whose camera sweeps along the ring while the "
                        "scene moves; poses at 1 kHz on the pose topic (default %(default)s)")
    p.add_argument("--moving-arc-deg", type=float, default=d.moving_arc_deg,
                   help="azimuth a moving view sweeps over the scene's time (default %(default)s)")
    p.add_argument("--max-clock-offset", type=float, default=d.max_clock_offset_s,
                   help="per-view camera clock offsets are drawn in [0, this) seconds "
                        "(default %(default)s)")
    p.add_argument("--jobs", type=int, default=d.jobs,
                   help="worker processes; 0 = one per CPU (default %(default)s)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing session folder")
    p.set_defaults(func=_cmd_simulate)

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
    p.add_argument("--bin", default="1ms", help="event-rate bin (default %(default)s)")
    p.add_argument("--method", choices=["auto", "trigger", "start", "rate", "onset"],
                   default="auto", help="force one method (default: the best each view has)")
    p.add_argument("--reference", help="reference view for refinement (default: first training view)")
    p.add_argument("--no-refine", action="store_true", help="skip the cross-correlation refinement")
    p.add_argument("--plot", help="aligned rate plot path (default SESSION/sync.png)")
    p.add_argument("--events-topic", help="event topic (default from session.yaml)")
    p.add_argument("--trigger-topic", help="servo START/DONE topic (default from session.yaml)")
    p.add_argument("--overwrite", action="store_true",
                   help="replace an existing --plot file (SESSION/sync.png, the default, is the session's own "
                        "and always replaced; a folder never is)")
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
    p.add_argument("--format", choices=["h5", "evdnerf"], default="h5", help="output format (default h5)")
    p.add_argument("--start", help="window start in the synced clock, e.g. 0 or --start=-50ms "
                                   "(with --end; default: the motion window)")
    p.add_argument("--end", help="window end in the synced clock, e.g. 1s")
    p.add_argument("--downsample", type=int, choices=[1, 2], default=1,
                   help="2: sum events over 2x2 pixel blocks, as the paper does (default 1)")
    p.add_argument("--offsets", choices=["sync", "ground-truth"], default="sync",
                   help="clock offsets from `evdnerf sync` (default) or, for simulated sessions, "
                        "the injected ground truth")
    p.add_argument("--poses", choices=["auto", "session", "topic"], default="auto",
                   help="camera poses from session.yaml (static) or the pose topic (moving camera)")
    p.add_argument("--intrinsics", choices=["camera_info", "session"], default="camera_info",
                   help="intrinsics from each bag's CameraInfo (checked against session.yaml) "
                        "or from session.yaml")
    p.add_argument("--no-frames", action="store_true", help="leave out the blurred frames")
    p.add_argument("--compression", choices=["scaleoffset", "gzip"], default="scaleoffset",
                   help="lossless HDF5 filter: scaleoffset (fast) or gzip (smaller)")
    p.add_argument("--n-windows", type=number(int, low=1, high=100_000), default=32,
                   help="--format evdnerf: event frames per view, 1..100000 (default %(default)s)")
    p.add_argument("--event-time", choices=["normalized", "ns"], default="normalized",
                   help="--format evdnerf: time column of their event arrays")
    p.add_argument("--no-raw-events", action="store_true",
                   help="--format evdnerf: leave out their per-view (N, 4) event arrays")
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

    p = sub.add_parser("train", help="fit a dynamic radiance field to the events of TRAIN.h5",
                       description="Train the field (default backbone: planes) on the events "
                                   "alone; RUN holds config.yaml, checkpoint.pt (atomic; a RUN "
                                   "with a checkpoint resumes bit-exactly) and metrics.jsonl "
                                   "(loss and validation events-PSNR against wall time).")
    p.add_argument("train_set", help="TRAIN.h5 from `evdnerf convert`")
    p.add_argument("-o", "--output", required=True, help="run folder")
    p.add_argument("--config", help="training config YAML (keys of TrainConfig)")
    budget = p.add_mutually_exclusive_group()
    budget.add_argument("--minutes", type=float, help="training time budget (whole run)")
    budget.add_argument("--iters", type=int, help="iteration budget (whole run)")
    p.add_argument("--init", help="start from this checkpoint's weights (fork -> knife transfer)")
    p.add_argument("--eval-views", type=number(int, low=0, high=100_000), default=4,
                   help="validation views evaluated periodically (default %(default)s)")
    p.add_argument("--no-eval", action="store_true", help="no periodic validation")
    p.add_argument("--overwrite", action="store_true", help="start RUN afresh")
    p.set_defaults(func=_cmd_train)

    p = sub.add_parser("eval", help="events metrics of a trained run",
                       description="The paper's protocol: validation views, every 4th window "
                                   "(skipping the last), events PSNR with data range "
                                   "2 max|E|, SSIM, MAE, continuous and quantised, next to the "
                                   "all-zero floor; at the trained window count and 4x / 8x "
                                   "finer; on validation and training views.")
    p.add_argument("run", help="run folder")
    p.add_argument("train_set", help="TRAIN.h5")
    p.add_argument("--windows", type=number(int, low=1, high=100_000),
                   help="window count, 1..100000 (default: the trained one)")
    p.add_argument("--max-views", type=number(int, low=1), help="evaluate at most this many views per split")
    p.add_argument("--json", action="store_true", help="print JSON")
    p.set_defaults(func=_cmd_eval)

    p = sub.add_parser("report", help="events-PSNR against wall time for several training runs",
                       description="Read RUN/metrics.jsonl of each run and write report.png "
                                   "(events-PSNR against wall-clock seconds, the all-zero "
                                   "prediction floor dashed) and report.md (a table).")
    p.add_argument("runs", nargs="+", help="run folders")
    p.add_argument("-o", "--output", default=".", help="folder for report.png / report.md")
    p.add_argument("--overwrite", action="store_true", help="replace an existing report.png / report.md")
    p.set_defaults(func=_cmd_report)

    p = sub.add_parser("publish", help="publish the events a robot-mounted camera would see (bag and/or DDS)",
                       description="Run the event publisher node (the `event_publisher` executable) without "
                                   "ROS: render a synthetic scene or a trained run along a robot trajectory, "
                                   "generate a continuous event stream and write it (EventPacket evt3 + "
                                   "CameraInfo) into a rosbag2; --dds also publishes on Cyclone DDS with ROS 2 "
                                   "naming (ROS_DOMAIN_ID, ROS_LOCALHOST_ONLY). Every node parameter can be set "
                                   "with -p name=value or --params-file (see README).")
    p.add_argument("-o", "--output", help="rosbag2 to write (must not exist)")
    p.add_argument("--dds", action="store_true", help="also publish over DDS")
    p.add_argument("--scene", help="scene preset or YAML (default fork)")
    p.add_argument("--run", help="trained run folder instead of a synthetic scene")
    p.add_argument("--trajectory", help="robot poses: bag (Odometry, PoseStamped, /tf), .yaml or .csv")
    p.add_argument("--resolution", type=number(int, low=1, high=16_384), nargs=2, metavar=("W", "H"),
                   help="camera size, 1..16384 each (default: the scene's)")
    p.add_argument("--encoding", choices=["evt3", "evt2", "mono", "array"], help="event message (default evt3)")
    p.add_argument("--duration", type=number(float, low=0, low_open=True), help="seconds to publish (default: all)")
    p.add_argument("--realtime-factor", type=number(float, low=0, high=1e6),
                   help="1 = real time, 0 = as fast as possible (default 0 here unless --params-file; "
                        "1 for event_publisher)")
    p.add_argument("-p", "--param", action="append", metavar="NAME=VALUE", help="any node parameter (repeatable)")
    p.add_argument("--params-file", help="ros__parameters YAML (as config/event_publisher.yaml)")
    p.add_argument("--json", action="store_true", help="print the run report as JSON")
    p.set_defaults(func=_cmd_publish)

    p = sub.add_parser("echo", help="show what is on a DDS topic: rate, sizes, an event image",
                       description="Subscribe to a ROS 2 topic over Cyclone DDS (ROS_DOMAIN_ID, "
                                   "ROS_LOCALHOST_ONLY) and report message rate, bandwidth and size; event "
                                   "topics are decoded and drawn as an ASCII event image (and --png).")
    p.add_argument("topic", help="absolute topic, e.g. /event_publisher/events")
    p.add_argument("--type", default="event_camera_msgs/msg/EventPacket",
                   help="message type (default %(default)s; e.g. dvs_msgs/msg/EventArray)")
    p.add_argument("--qos", choices=["default", "sensor_data", "transient_local"], default="default",
                   help="subscriber QoS profile (default %(default)s: reliable)")
    p.add_argument("--depth", type=number(int, low=1, high=1_000_000), default=1000,
                   help="subscriber history (keep-last) depth; deep so a slow start loses nothing (default %(default)s)")
    p.add_argument("--count", type=number(int, low=0), default=0, help="stop after this many messages (0: no limit)")
    p.add_argument("--duration", type=number(float, low=0, high=4e9), default=0.0, help="stop after this many seconds (0: no limit)")
    p.add_argument("--idle", type=number(float, low=0, high=4e9), default=0.0,
                   help="stop when nothing arrives for this many seconds, counted from the start "
                        "until the first message (0: no limit)")
    p.add_argument("--png", help="write the event image of everything received")
    p.add_argument("--save-events", help="write the decoded events (.npz: t, x, y, p, width, height)")
    p.add_argument("--overwrite", action="store_true", help="replace existing --png / --save-events files")
    p.add_argument("--json", action="store_true", help="print the report as JSON")
    p.set_defaults(func=_cmd_echo)

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
    p.add_argument("--overwrite", action="store_true",
                   help="replace existing PNG files at the output paths (never a folder)")
    p.set_defaults(func=_cmd_render_events)

    # Plugins (e.g. rig's `flash` and `servo`): entry points `evdnerf.commands`, each a
    # function register(subparsers) adding sub-parsers with set_defaults(func=...).
    from importlib.metadata import entry_points

    for ep in entry_points(group="evdnerf.commands"):
        ep.load()(sub)
    return parser


class _Parser(argparse.ArgumentParser):
    """argparse with the toolkit's error contract: one line, exit 2."""

    def error(self, message):
        self.exit(2, f"evdnerf: error: {self.prog}: {message} (see {self.prog} --help)\n")


def number(kind=float, *, low=None, high=None, low_open=False):
    """An argparse type: a finite number of `kind` in the documented range (limits.check_number)."""
    from .limits import check_number

    def parse(text):
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {'a whole number' if kind is int else 'a number'}, "
                                             f"got {text!r}") from None
        try:
            return check_number(value, "value", low=low, high=high, low_open=low_open)
        except EvdnerfError as exc:
            raise argparse.ArgumentTypeError(str(exc).removeprefix("value: ")) from None

    parse.__name__ = kind.__name__          # argparse names the type in its messages
    return parse


class Terminated(KeyboardInterrupt):
    """SIGTERM, delivered like Ctrl-C so every `finally` and cleanup handler runs."""


def _on_sigterm(signum, frame):
    signal.signal(signal.SIGTERM, signal.SIG_IGN)   # one clean-up; a second TERM must not cut it short
    raise Terminated()


def os_error_message(exc: OSError) -> str:
    """One line for an OSError: the path, what went wrong, and what would fix it."""
    where = " -> ".join(str(f) for f in (exc.filename, exc.filename2) if f is not None)
    what = exc.strerror or str(exc)
    hint = {errno.ENOSPC: "free some space or write elsewhere",
            errno.EDQUOT: "free some space or write elsewhere",
            errno.EFBIG: "the file is larger than this system allows; write elsewhere",
            errno.EROFS: "the file system is read-only; write elsewhere",
            errno.EACCES: "check the permissions or choose another path",
            errno.EPERM: "check the permissions or choose another path",
            errno.ENOENT: "check the path",
            errno.EISDIR: "give a file path, not a folder",
            errno.ENOTDIR: "a part of the path is a file, not a folder"}.get(exc.errno)
    return f"{where + ': ' if where else ''}{what}" + (f"; {hint}" if hint else "")


def _fail(message: str) -> int:
    """The one error line (messages quoting a parser's multi-line report are folded) and exit 2."""
    print("evdnerf: error: " + " ".join(message.split()), file=sys.stderr)
    return 2


def _show_warning(message, category, filename, lineno, file=None, line=None):
    """Warnings (dropped events, clamped display ranges) as one line each, like errors."""
    print("evdnerf: warning: " + " ".join(str(message).split()), file=sys.stderr)


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    warnings.showwarning = _show_warning
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, _on_sigterm)
    try:
        return args.func(args)
    except EvdnerfError as exc:
        return _fail(str(exc))
    except OSError as exc:
        if isinstance(exc, BrokenPipeError):         # `evdnerf info x | head`: not an error
            return 0
        return _fail(os_error_message(exc))
    except MemoryError:
        return _fail("out of memory; use a smaller input, window or resolution")
    except Terminated:
        print("evdnerf: terminated", file=sys.stderr)
        return 143
    except KeyboardInterrupt:
        print("evdnerf: interrupted", file=sys.stderr)
        return 130
