"""`evdnerf train`, `eval`, `report`: fitting the field and measuring it."""

from __future__ import annotations

import json
from pathlib import Path

from argparse import SUPPRESS

from ..errors import EvdnerfError
from ..options import add_options, option_fields, options_from_args
from .common import number



def _cmd_train(args) -> int:
    from ..eval.evaluate import validation_eval
    from ..train import run_train

    if args.minutes is None and args.iters is None:
        raise EvdnerfError("give a budget: --minutes M or --iters N")
    eval_fn = None if args.no_eval else validation_eval(max_views=args.eval_views)
    result = run_train(args.train_set, args.output, config=args.config, minutes=args.minutes,
                       iters=args.iters, init=args.init, overwrite=args.overwrite, eval_fn=eval_fn,
                       device=args.device)
    print(f"{args.output}: {result['iterations']} iterations in {result['wall_s']:.1f} s on {result['device']}, "
          f"final loss {result['loss']}")
    return 0


def _cmd_eval(args) -> int:
    from ..eval.evaluate import run_eval
    from ..eval.options import EvalOptions

    options = options_from_args(EvalOptions, args)
    if options.published:
        from ..eval.published import PICTURE_WINDOWS, published_vs_true, side_by_side

        result = published_vs_true(args.run, args.train_set, n_windows=options.windows or options.published_windows,
                                    static=options.published == "static",
                                    publisher={"device": options.device},
                                    log=(lambda *_: None) if args.json else print)
        result.pop("reference")
        result["picture"] = str(side_by_side(result, Path(args.run) / "published_vs_true.png"))
        result.pop("images")
        if args.json:
            print(json.dumps(result, indent=2))
        else:
            print(f"true events (top) and published events (below) in the {PICTURE_WINDOWS} windows with the most "
                  f"true events: {result['picture']}")
        return 0

    result = run_eval(args.run, args.train_set, n_windows=options.windows, max_views=options.max_views,
                      train_views=options.train_views,
                      image_path=Path(args.run) / "eval_events.png",
                      log=(lambda *_: None) if args.json else print, device=options.device,
                      static_world=options.static_world)
    if args.json:
        print(json.dumps(result, indent=2))
    return 0


def _cmd_report(args) -> int:
    from ..eval.figures import run_report

    result = run_report(args.runs, Path(args.output), overwrite=args.overwrite)
    print(Path(result["md"]).read_text())
    return 0


def register(sub) -> None:
    p = sub.add_parser("train", help="fit a dynamic radiance field to the events of TRAIN.h5",
                       description="Train the field on the events alone (backbone auto, the default, "
                                   "chooses hinge, rigid or planes from the training set and logs why); "
                                   "RUN holds config.yaml, checkpoint.pt (atomic; a RUN "
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
    p.add_argument("--device", default="auto", type=str.lower, choices=["auto", "cpu", "cuda"],
                   help="where the field is trained: auto (cuda when available), cpu or cuda; not part of "
                        "the config, so a run may resume on another device (default %(default)s)")
    p.set_defaults(func=_cmd_train)

    p = sub.add_parser("eval", help="events metrics of a trained run",
                       description="The paper's protocol: validation views, every 4th window "
                                   "(skipping the last), events PSNR with data range "
                                   "2 max|E|, SSIM, MAE, continuous and quantised, next to the "
                                   "all-zero floor; at the trained window count and 4x / 8x "
                                   "finer; on validation and training views.")
    p.add_argument("run", help="run folder")
    p.add_argument("train_set", help="TRAIN.h5")
    from ..eval.options import EvalOptions

    add_options(p, EvalOptions)
    # an optional value (the flag alone: orbit) is beyond the generic flags
    published = next(spec for f, spec in option_fields(EvalOptions) if f.name == "published")
    p.add_argument("--published", nargs="?", const="orbit", choices=published.choices, default=SUPPRESS,
                   help=published.help)
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
