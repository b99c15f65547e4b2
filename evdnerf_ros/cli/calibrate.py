"""`evdnerf calibrate`: camera intrinsics and view poses from events of a ChArUco board."""

from __future__ import annotations

from ..options import add_options, options_from_args
from .common import number


def _cmd_calibrate(args) -> int:
    from ..atomic import atomic_output, check_output
    from ..calib.board import load_board
    from ..calib.run import CalibrationOptions, run_calibration
    from ..errors import InputError

    options = options_from_args(CalibrationOptions, args)
    board = load_board(args.board) if args.board else options.board()
    if args.board_image:
        import cv2

        path = check_output(args.board_image, overwrite=args.overwrite)
        img = board.image(args.px_per_square, args.margin_px)
        ok, buf = cv2.imencode(path.suffix or ".png", img)
        if not ok:
            raise InputError(f"{path}: OpenCV cannot write {path.suffix!r} images; use .png")
        with atomic_output(path, overwrite=args.overwrite) as tmp:
            tmp.write_bytes(buf.tobytes())
        print(f"wrote {path}: {board.squares_x}x{board.squares_y} squares, print them "
              f"{board.square_m * 1000:g} mm wide")
        if not (args.inputs or args.view_poses or args.intrinsics):
            return 0
    if args.output is None:
        raise InputError("calibrate: give -o CALIB.yaml for the calibration")
    run_calibration(args.inputs, args.output, options, board=board, intrinsics=args.intrinsics,
                    view_poses=args.view_poses, write_session=args.write_session,
                    overwrite=args.overwrite)
    return 0


def register(sub) -> None:
    from ..calib.run import CalibrationOptions

    p = sub.add_parser(
        "calibrate", help="intrinsics and view poses from events of a ChArUco board",
        description="Make board images from events of a ChArUco board (a board blinking on a "
                    "screen, held still at each pose: the ON events of a blink-on, OFF of a "
                    "blink-off; or edge images of a moving board with --style window), detect "
                    "its corners (OpenCV aruco), fit K and distortion (cv2.calibrateCamera: "
                    "RMS and per-view errors reported) and, with --view-poses SESSION, each "
                    "view's pose from the board lying at the rig's origin. Writes a calibration "
                    "YAML; --write-session puts K, D and the poses into the session's "
                    "session.yaml. Default board: 7x5 squares of 30 mm, 22 mm DICT_5X5_100 "
                    "markers (print it with --board-image board.png).")
    p.add_argument("inputs", nargs="*", help="board recordings: bags, event files or session "
                                             "folders (every view)")
    p.add_argument("-o", "--output", help="calibration YAML to write")
    p.add_argument("--board", metavar="FILE", help="board YAML (squares_x, squares_y, square_m, "
                                                   "marker_m, dictionary) or a calibration file")
    p.add_argument("--intrinsics", metavar="CALIB.yaml",
                   help="use these intrinsics (a file this command wrote) instead of fitting")
    p.add_argument("--view-poses", metavar="SESSION",
                   help="session whose every view recorded the board at the rig's origin: "
                        "estimate each view's T_world_cam")
    p.add_argument("--write-session", action="store_true",
                   help="write K, D and the view poses into SESSION/session.yaml")
    p.add_argument("--board-image", metavar="PNG", help="write the board's picture to print")
    p.add_argument("--px-per-square", type=number(int, low=10, high=2000), default=200,
                   help="board picture: pixels per square, in [10, 2000] (default %(default)s)")
    p.add_argument("--margin-px", type=number(int, low=0, high=10000), default=40,
                   help="board picture: white margin, pixels, in [0, 10000] (default %(default)s)")
    add_options(p, CalibrationOptions)
    p.add_argument("--overwrite", action="store_true", help="replace an existing output")
    p.set_defaults(func=_cmd_calibrate)
