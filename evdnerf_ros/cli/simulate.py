"""`evdnerf simulate` and `evdnerf demo`: the virtual rig."""

from __future__ import annotations

from pathlib import Path

from ..options import add_options, options_from_args


def _cmd_demo(args) -> int:
    from ..demo import DemoOptions, run_demo

    run_demo(Path(args.output), options_from_args(DemoOptions, args), overwrite=args.overwrite)
    return 0


def _cmd_simulate(args) -> int:
    from ..sim.simulate import SimulationOptions, simulate_session

    options = options_from_args(SimulationOptions, args)
    simulate_session(args.scene, Path(args.output), options, overwrite=args.overwrite)
    return 0


def register(sub) -> None:
    p = sub.add_parser("demo", help="run the end-to-end demo on the embedded virtual scene",
                       description="Capture a session of the servo-swung fork on the closed-loop "
                                   "virtual rig (firmware in simavr, camera twin on emulated USB), or "
                                   "simulate one (one rosbag2 per view), convert a recording to every "
                                   "container and check it is bit-exact, draw event images and event-rate plots, "
                                   "sync the views, convert to a training set, train the field on "
                                   "the events, evaluate it on validation views and report "
                                   "events-PSNR against wall time.")
    p.add_argument("-o", "--output", default="demo_output", help="output folder (default: %(default)s)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output folder")
    from ..demo import DemoOptions

    add_options(p, DemoOptions)
    p.set_defaults(func=_cmd_demo)

    from ..sim.simulate import SimulationOptions

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
    add_options(p, SimulationOptions)
    p.add_argument("--overwrite", action="store_true", help="replace an existing session folder")
    p.set_defaults(func=_cmd_simulate)
