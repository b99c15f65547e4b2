"""`evdnerf demo`: the end-to-end job on the virtual rig's embedded default scene.

It grows with each part of the toolkit. Today:
1. make a small capture session of the `fork` preset (the real rig's servo-swung fork): one
   rosbag2 per view with events, trigger edges, camera info, pose and servo topics, each view
   in its own clock. The session's source (``--source``):
   ``virtual-rig``: captured on the closed-loop virtual rig (the real firmware in simavr, a
   camera twin on emulated USB): a session source of the entry-point group
   ``evdnerf.session_sources`` (the rig package's ``rig.demo_capture``; evdnerf_ros never
   imports rig), which also records the truth the rig knows (scene, true clock offsets, the
   scene's window on the sensor, which convert crops to); no moving-camera view;
   ``simulate``: simulated (evdnerf_ros.sim), 4 training + 2 validation + 1 moving view;
   ``auto`` (default): the virtual rig when it is installed and this machine can run it, else
   simulate; the demo says which and why;
2. convert the first view's recording into every container we speak, read each back and
   check it is bit-exact;
3. sync the views (trigger edges, START times, event-rate onsets) and compare the recovered
   offsets with the true ones (injected, or the twin's);
4. draw each view's event image at mid-swing and the event-rate curves of all views (their
   onsets differ by the views' clock offsets);
5. convert the synced session into a training set (TRAIN.h5) and read a dL image back;
6. train the field (backbone ``auto``: ``hinge`` where the set records the rig's joint) on the
   events for ``train_iterations`` (at most ``train_minutes``; metrics.jsonl: validation
   events-PSNR against wall time),
   evaluate it on the validation views (10 degrees off the training views; between them on the
   rig) at the trained and 4x finer windows, write the GT vs prediction event images and the
   error-against-run-time report;
7. publish from the trained run the events a camera moving once round its training views would
   see (the event publisher's default path for a run, its field baked at ``PUBLISH_BAKE``
   vertices per axis: faster than real time on two cores) into the rosbag2 ``published/``, and
   score them against the events that camera would truly see (``eval --published``), with the
   busiest windows side by side (``published_vs_true.png``).
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable

import numpy as np

from .atomic import atomic_output
from .errors import EvdnerfError, InputError
from .events import event_image, event_rate, plot_event_rate, save_png, time_slice
from .io.event_files import EventFile, read_event_file, write_event_file
from .io.info import describe, format_info
from .options import option
from .session.convert import run_convert
from .session.sync import run_sync
from .sim.simulate import SimulationOptions, simulate_session

SCENE = "fork"
OPTIONS = SimulationOptions(views=4, val_views=2, moving_views=1, resolution=(96, 72),
                            frame_rate_hz=30, blur_samples=4, gt_times=3)
#: The demo's training config: 16 then 32 windows over the 1 s swing, 1024 rays.
TRAIN_CONFIG = {"windows": [16, 32], "window_switch": [0.5], "n_samples": 32, "eval_every": 100}
#: The demo's training budget: iterations, so that a busy machine gets the same field, later
#: (about two minutes on two idle cores, docs/demo.md) ...
TRAIN_ITERATIONS = 1200
#: ... with minutes as an upper bound only.
TRAIN_MINUTES = 20.0
#: The published orbit plays the run back from a grid of this many vertices per axis
#: (``bake_resolution``): 3.5x the field's own speed on the fork's orbit for none of its events PSNR.
PUBLISH_BAKE = 64
#: ... and renders it 0.1 s at a time: a bag, nothing paced, so longer chunks only batch the renders
#: (fewer, larger calls; the same events as the node's default 10 ms chunks).
PUBLISH_CHUNK_S = 0.1
#: ... and scores it against the true events at the training's finest windows.
PUBLISH_WINDOWS = max(TRAIN_CONFIG["windows"])
#: ... where the true scene's events along the orbit are simulated at steps of at least this (ns):
#: on the virtual rig's ring (bench_demo.py's truth sampling, 2 idle cores) 1 961 renders in 22 s
#: where the publisher's 0.1 ms default takes 9 718 in 97 s, the true event images within 47 dB
#: (PSNR) of those and 1.2 % fewer events; the published run keeps the publisher's default.
TRUTH_MIN_STEP_NS = 500_000


# (file name, encoding, carries trigger events): every container the demo round-trips through.
CONVERSIONS = [
    ("events_evt3.raw", "evt3", True),
    ("events_evt2.raw", "evt2", True),
    ("events.npz", None, True),
    ("events.h5", None, True),
    ("events_mono", "mono", False),
    ("events_array.db3", "array", False),
    ("events_ros1.bag", "array", False),
]


#: --source choices; ``auto`` takes the virtual rig where it can run, else the simulator.
SOURCES = ("auto", "virtual-rig", "simulate")


@dataclass(frozen=True)
class DemoOptions:
    """The knobs of `evdnerf demo` (flags, ``--config FILE`` keys and library defaults)."""

    train_iterations: int = option(TRAIN_ITERATIONS, "training budget of the demo's field, in iterations (the same "
                                   "field on a busy machine, later); 0: the minutes alone", low=0)
    train_minutes: float = option(TRAIN_MINUTES, "upper bound of the demo's training time, in minutes (whichever "
                                  "of the two budgets comes first)", low=0, low_open=True, high=10_080)
    source: str = option("auto", "where the session comes from: the virtual rig (needs simavr and umockdev), "
                         "the simulator, or auto: the virtual rig where it can run, else the simulator",
                         choices=SOURCES)


#: Entry-point group of session sources: name -> an object with ``available() -> (ok, why)``
#: and ``__call__(session_dir, *, log) -> session.yaml document`` (rig.demo_capture).
SOURCE_GROUP = "evdnerf.session_sources"
VIRTUAL_RIG = "virtual-rig"
#: Where the event images are drawn: mid-way through the swing (after the servo's start).
MID_SWING_NS = 350_000_000


@dataclass
class SessionSource:
    name: str                                  # "virtual-rig" | "simulate"
    why: str                                   # why this source was taken (printed)
    make: Callable[..., dict]                  # make(session_dir, log=...) -> session.yaml document


def choose_source(choice: str = "auto") -> SessionSource:
    """The demo's session source for ``--source choice``. ``virtual-rig`` that cannot run here
    is an InputError naming what is missing; ``auto`` then falls back to simulate."""
    if choice not in SOURCES:
        raise InputError(f"demo: --source {choice!r} is not one of {', '.join(SOURCES)}")
    simulate = lambda why: SessionSource("simulate", why, lambda d, log: simulate_session(SCENE, d, OPTIONS, log=log))  # noqa: E731
    if choice == "simulate":
        return simulate("--source simulate")
    from importlib.metadata import entry_points

    found = [ep for ep in entry_points(group=SOURCE_GROUP) if ep.name == VIRTUAL_RIG]
    if not found:
        why = (f"no session source {VIRTUAL_RIG!r} is installed (entry point group {SOURCE_GROUP} of the rig "
               "package, rig.demo_capture); install the package: pip install -e .")
    else:
        try:
            source = found[0].load()
            ok, why = source.available()
        except Exception as exc:  # noqa: BLE001 - a broken plugin is reported, and auto still runs
            ok, why = False, f"session source {found[0].value} failed to load ({exc!r})"
        if ok:
            return SessionSource(VIRTUAL_RIG, f"{choice}: {why}", lambda d, log: source(d, log=log))
    if choice == VIRTUAL_RIG:
        raise InputError(f"demo --source {VIRTUAL_RIG}: {why}; or run the demo with --source simulate")
    return simulate(f"auto: the virtual rig cannot run here: {why}")


def run_demo(out_dir: Path, options: DemoOptions | None = None, *, overwrite: bool = False, log=print) -> dict:
    options = options or DemoOptions()
    train_minutes = options.train_minutes
    chosen = choose_source(options.source)     # before any output: a missing source writes nothing
    with atomic_output(out_dir, overwrite=overwrite, directory=True) as tmp:
        tmp.mkdir()
        summary = _run(tmp, out_dir, log, train_minutes, chosen, options.train_iterations or None)
        (tmp / "summary.json").write_text(json.dumps(summary, indent=2))
    log(f"demo finished: outputs in {out_dir}/ (session/ with sync.png, conversions/, train.h5, "
        "event_images.png, event_rates.png, run/ with metrics.jsonl and eval_events.png, "
        "report/report.png, published/, published_vs_true.png, summary.json)")
    return summary


def _run(out: Path, final_dir: Path, log_final, train_minutes: float, source: SessionSource,
         train_iterations: int | None = None) -> dict:
    # torch is imported here, not with the module: every `evdnerf` command reads this module's
    # constants when it builds its parser
    from .eval.evaluate import run_eval, validation_eval
    from .eval.figures import run_report
    from .io.trainingset import TrainingSet
    from .train.trainer import run_train

    def log(msg) -> None:  # show the final paths, not the temporary folder being written
        log_final(str(msg).replace(str(out), str(final_dir)))

    log(f"session source: {source.name} ({source.why})")
    start = time.perf_counter()
    stages, last = {}, [start]

    def lap(stage: str) -> None:           # the wall time of each stage, for summary.json
        now = time.perf_counter()
        stages[stage] = round(now - last[0], 1)
        last[0] = now

    session = source.make(out / "session", log=log)
    session_seconds = time.perf_counter() - start
    lap("session")
    views = session["views"]
    # a capture's scene fills only a window of the sensor: the pictures and the training set keep it
    crop = ((session.get("rig") or {}).get("virtual") or {}).get("scene_window")
    first = out / "session" / views[0]["bag"]
    log(format_info(describe(first)))

    recorded, shift_ns = _on_us_grid(read_event_file(first))
    if shift_ns:
        log(f"  times shifted by -{shift_ns} ns for the round trip: the view's clock starts off the microsecond "
            "grid (the sensor's zero in wall-clock time) and RAW files carry whole microseconds")
    summary = {"scene": SCENE, "source": source.name, "source_reason": source.why, "views": len(views),
               "session_seconds": round(session_seconds, 2),
               "events_per_view": [v["events"] for v in views], "round_trips": {}}
    if source.name == "simulate":
        summary["simulate_seconds"] = summary["session_seconds"]
    (out / "conversions").mkdir()
    for name, encoding, keeps_triggers in CONVERSIONS:
        path = out / "conversions" / name
        t0 = time.perf_counter()
        carried = recorded if keeps_triggers else replace(recorded, triggers=recorded.triggers[:0])
        write_event_file(path, carried, encoding=encoding)
        _check_same(path, read_event_file(path), carried)
        size = sum(f.stat().st_size for f in path.rglob("*")) if path.is_dir() else path.stat().st_size
        n = max(1, len(recorded.events))
        summary["round_trips"][name] = {"encoding": encoding, "bytes_per_event": round(size / n, 3),
                                        "seconds": round(time.perf_counter() - t0, 4),
                                        "bit_exact": True}
        log(f"  {name:<20} {encoding or '-':<6} {size / n:6.2f} B/event  bit-exact")

    lap("round_trips")
    synced = run_sync(out / "session", log=log)
    motion_start = session["time"]["motion_start_ns"]
    truth = {v["name"]: (v.get("ground_truth") or {}).get("clock_offset_ns") for v in views}
    errors_us = {name: (synced["views"][name]["offset_ns"] - gt - motion_start) / 1000
                 for name, gt in truth.items() if gt is not None}
    what = "the injected offsets" if source.name == "simulate" else "the twin's true clock offsets"
    log(f"sync error against {what}: " + ", ".join(f"{k} {e:+.1f} us" for k, e in errors_us.items()))
    if len(errors_us) < len(views):
        log("  no true clock offset (sync not checked) for: "
            + ", ".join(k for k, gt in truth.items() if gt is None))
    summary["sync_error_us"] = errors_us
    lap("sync")

    images, curves = [], {}
    servo_start = session["servo"]["start_ns_scene"]
    for v in views:
        data = read_event_file(out / "session" / v["bag"]) if v is not views[0] or shift_ns else recorded
        # the view clock at the servo's start: the true offset, else the synced one
        at_start = (servo_start + truth[v["name"]] if truth[v["name"]] is not None
                    else synced["views"][v["name"]]["offset_ns"] - motion_start + servo_start)
        mid_swing = at_start + MID_SWING_NS
        window = time_slice(data.events, mid_swing, mid_swing + 20_000_000)
        images.append(event_image(*_in_window(window, crop, data.width, data.height)))
        curves[v["name"]] = event_rate(data.events["t"], 5_000_000)
    gap = np.full((images[0].shape[0], 4, 3), 128, np.uint8)
    sheet = np.concatenate([x for img in images for x in (img, gap)][:-1], axis=1)
    save_png(out / "event_images.png", sheet, upscale=3)
    plot_event_rate(out / "event_rates.png", curves,
                    title="event rate per view (5 ms bins), each in its own clock", t_origin_ns=0)

    lap("pictures")
    run_convert(out / "session", out / "train.h5", log=log, crop=None if crop is None else tuple(crop))
    with TrainingSet(out / "train.h5") as ts:
        t0, t1 = ts.time_range
        d_l = ts.log_change(ts.views[0], t0, t1)
        summary["train_h5"] = {"views": len(ts.views), "time_range_ns": [int(t0), int(t1)],
                               "size": [int(ts.width), int(ts.height)], "crop": crop,
                               "dl_abs_sum_view0": float(abs(d_l).sum())}
    lap("convert")

    n_train = sum(v["split"] == "train" and not v.get("moving_arc_deg") for v in views)
    budget = (f"{train_iterations} iterations (at most {train_minutes:g} min)" if train_iterations
              else f"{train_minutes:g} min")
    log(f"training the field for {budget} on the events of {n_train} views")
    trained = run_train(out / "train.h5", out / "run", config=TRAIN_CONFIG,
                        minutes=train_minutes, iters=train_iterations, eval_fn=validation_eval(), log=log)
    stopped_by = "iterations" if train_iterations and trained["iterations"] >= train_iterations else "minutes"
    if train_iterations and stopped_by == "minutes":
        log(f"the {train_minutes:g}-minute bound stopped training at {trained['iterations']} of {train_iterations} "
            "iterations (a slow or busy machine): this field is younger than the demo's")
    summary["backbone"] = {"chosen": trained["backbone"], "why": trained["backbone_reason"]}
    lap("train")
    result = run_eval(out / "run", out / "train.h5", factors=(1, 4),
                      image_path=out / "run" / "eval_events.png", log=log)
    run_report([out / "run"], out / "report")
    val = result["val_windows_x1"]
    summary["training"] = {"iterations": trained["iterations"], "budget_iterations": train_iterations,
                           "budget_minutes": train_minutes, "stopped_by": stopped_by,
                           "train_seconds": round(trained["wall_s"], 1),
                           "val_events_psnr": val["continuous"]["psnr"],
                           "val_zero_floor_psnr": val["zero_floor"]["psnr"],
                           "val_x4_events_psnr": result["val_windows_x4"]["continuous"]["psnr"],
                           "val_x4_zero_floor_psnr": result["val_windows_x4"]["zero_floor"]["psnr"],
                           "true_scene": result.get("true_scene"),
                           "true_scene_note": result.get("true_scene_note"),
                           "val": _against_truth(val)}
    moving = result.get("moving_windows_x1")
    if moving is not None:
        summary["training"].update(moving_events_psnr=moving["continuous"]["psnr"],
                                   moving_zero_floor_psnr=moving["zero_floor"]["psnr"],
                                   moving=_against_truth(moving))
    else:
        log("moving-camera view: skipped (a turntable capture records static views only)"
            if source.name == VIRTUAL_RIG else "moving-camera view: none in this session")
    lap("eval")
    summary["published"] = _publish(out / "run", out / "train.h5", out, log)
    lap("publish")
    for split, scores in (("validation views", val), ("moving camera", moving)):
        if scores is not None:
            log(_verdict(split, _against_truth(scores)))
    summary["wall_seconds"] = round(time.perf_counter() - start, 1)
    summary["stage_seconds"] = stages
    return summary


def _publish(run_dir: Path, train_h5: Path, out: Path, log) -> dict:
    """The event publisher on the trained run without a trajectory (once round its training views
    over its training span: a moving camera no training view was), into a bag, as fast as it goes;
    where the set records its true scene, scored against the events the camera would truly see
    along the same path (``eval --published``) and drawn beside them. What it did."""
    from .eval.published import PICTURE_WINDOWS, published_vs_true, side_by_side
    from .io.trainingset import TrainingSet
    from .nodes.event_publisher import run_node

    bag = out / "published"
    params = {"bag": str(bag), "bake_resolution": PUBLISH_BAKE, "chunk": PUBLISH_CHUNK_S}
    with TrainingSet(train_h5) as ts:
        truth = bool(ts.provenance.get("truth"))
    if not truth:
        rep = run_node(("--ros-args", "--log-level", "warn"), dds=False,
                       overrides={"run_dir": str(run_dir), "realtime_factor": 0.0, **params})
        log(f"published {rep.sim_seconds:.3f} s of events ({rep.events} events) into {bag.name}/; not scored: "
            "the training set records no true scene")
        return {"bag": bag.name, "events": rep.events, "sim_seconds": rep.sim_seconds,
                "wall_seconds": round(rep.wall_seconds, 3), "rtf": rep.rtf, "scored": False}
    result = published_vs_true(run_dir, train_h5, n_windows=PUBLISH_WINDOWS, publisher=params,
                               truth_publisher={"min_step_ns": TRUTH_MIN_STEP_NS}, log=log)
    picture = side_by_side(result, out / "published_vs_true.png")
    counts, cost = result["counts"], result["publisher"]
    published = counts["published_on"] + counts["published_off"]
    true = counts["true_on"] + counts["true_off"]
    summary = {"bag": bag.name, "path": result["path"], "windows": PUBLISH_WINDOWS, "scored": True,
               "events": published, "true_events": true,
               "count_rel_diff": (published - true) / true if true else None,
               "psnr": result["published"]["psnr"], "zero_floor_psnr": result["zero_floor"]["psnr"],
               "true_render_psnr": result["true_render"]["psnr"], "margin_closed": result["margin_closed"],
               "first_events_matched": result["first_events"]["matched"],
               # what static training views can teach (the moving parts) apart from the world sweeping past
               "split": result["split"], "picture": picture.name,
               "sim_seconds": result["span_s"], "wall_seconds": round(cost["wall_s"], 3), "rtf": cost["rtf"],
               "bake_resolution": PUBLISH_BAKE, "source_seconds": round(cost["source_s"], 3),
               "truth_min_step_ns": TRUTH_MIN_STEP_NS, "truth_wall_seconds": round(result["true_publisher"]["wall_s"], 3)}
    log(f"published into {bag.name}/ {result['span_s']:.3f} s of the events a camera going round the training views "
        f"would see ({published} events; it would truly see {true}) at {cost['rtf']:.2f}x real time; "
        f"margin closed {_percent(result['margin_closed'])} at {PUBLISH_WINDOWS} windows (pooled, on the moving parts' "
        f"cells {_percent(result['split']['moving_parts'].get('margin_closed'))}, on the static world's "
        f"{_percent(result['split']['static_world'].get('margin_closed'))}); {picture.name}: true "
        f"(top) and published (below) events in the {PICTURE_WINDOWS} busiest windows")
    return summary


def _percent(value) -> str:
    return "n/a" if value is None else f"{100 * value:.0f} %"


def _verdict(split: str, scores: dict) -> str:
    """One line for the user: is the field's event stream closer to the recording than no events?
    (pooled over the windows, where the protocol's per-window mean may have no margin)."""
    p = scores["psnr_pooled"]
    field, floor, truth = p["field"], p["floor"], p["true_scene"]
    margin = (scores.get("margin_closed") or {}).get("pooled")
    where = (f"{field:.2f} dB against {floor:.2f} for predicting no events"
             + (f" and {truth:.2f} for the true scene" if truth is not None else ""))
    if field <= floor:
        return (f"{split}: the field's events are further from the recording than no events at all "
                f"({where}, pooled over the windows): docs/training.md says why "
                "and docs/results.md what each lever does")
    return (f"{split}: the field's events are closer to the recording than no events ({where}, pooled"
            + (f"; {100 * margin:.0f} % of the margin to the true scene closed)" if margin is not None else ")"))


def _against_truth(scores: dict) -> dict:
    """Field, floor and true scene of one split, by the protocol (mean over windows) and pooled
    (one MSE over all windows), with the margins closed (None: no true scene, or no margin)."""
    truth = scores.get("truth", {}).get("continuous", {})
    return {"psnr": {"field": scores["continuous"]["psnr"], "floor": scores["zero_floor"]["psnr"],
                     "true_scene": truth.get("psnr")},
            "psnr_pooled": {"field": scores["continuous"]["psnr_pooled"],
                            "floor": scores["zero_floor"]["psnr_pooled"],
                            "true_scene": truth.get("psnr_pooled")},
            "margin_closed": scores.get("margin_closed")}


def _on_us_grid(data: EventFile) -> tuple[EventFile, int]:
    """(``data`` with every time moved back by the common sub-microsecond remainder, the shift):
    a recording whose clock is sensor microseconds plus an arbitrary ns origin, ready for the
    microsecond containers. Unchanged (shift 0) when the times have no one remainder."""
    times = np.concatenate([data.events["t"], data.triggers["t"]])
    if not times.size:
        return data, 0
    rem = times % 1000
    shift = int(rem[0])
    if shift == 0 or np.any(rem != shift):
        return data, 0
    events, triggers = data.events.copy(), data.triggers.copy()
    events["t"] -= np.int64(shift)
    triggers["t"] -= np.int64(shift)
    return replace(data, events=events, triggers=triggers), shift


def _in_window(events: np.ndarray, crop, width: int, height: int) -> tuple[np.ndarray, int, int]:
    """(events inside the sensor window crop = x y w h, shifted to it; its size), or all of them."""
    if crop is None:
        return events, width, height
    x, y, w, h = map(int, crop)
    keep = (events["x"] >= x) & (events["x"] < x + w) & (events["y"] >= y) & (events["y"] < y + h)
    inside = events[keep]              # a copy: shifting it leaves the recording as read
    inside["x"] -= np.uint16(x)
    inside["y"] -= np.uint16(y)
    return inside, w, h


def _check_same(path, got: EventFile, want: EventFile) -> None:
    if not np.array_equal(got.events, want.events):
        raise EvdnerfError(f"{path}: events read back differ from those written")
    if not np.array_equal(got.triggers, want.triggers):
        raise EvdnerfError(f"{path}: trigger events read back differ from those written")
