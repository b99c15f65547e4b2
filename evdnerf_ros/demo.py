"""`evdnerf demo`: the end-to-end job on the virtual rig's embedded default scene.

It grows with each part of the toolkit. Today:
1. simulate a small capture session of the `fork` preset (the real rig's servo-swung fork):
   one rosbag2 per view with evt3 events, trigger edges, camera info, pose and servo topics,
   each view in its own clock;
2. convert the first view's recording into every container we speak, read each back and
   check it is bit-exact;
3. draw each view's event image at mid-swing and the event-rate curves of all views (their
   onsets differ by the injected clock offsets);
4. sync the views (trigger edges, START times, event-rate onsets) and compare the recovered
   offsets with the injected ones;
5. convert the synced session into a training set (TRAIN.h5) and read a dL image back;
6. train the default `planes` field on the events for ``train_minutes`` (metrics.jsonl:
   validation events-PSNR against wall time), evaluate it on the validation views (10
   degrees off the training views) at the trained and 4x finer windows, write the GT vs
   prediction event images and the error-against-run-time report.
"""

from __future__ import annotations

import json
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from .atomic import atomic_output
from .errors import EvdnerfError
from .events import event_image, event_rate, plot_event_rate, save_png, time_slice
from .io.event_files import EventFile, read_event_file, write_event_file
from .io.info import describe, format_info
from .io.trainingset import TrainingSet
from .eval.evaluate import run_eval, validation_eval
from .eval.figures import run_report
from .session.convert import run_convert
from .session.sync import run_sync
from .sim.simulate import SimulationOptions, simulate_session
from .train.trainer import run_train

SCENE = "fork"
OPTIONS = SimulationOptions(views=4, val_views=2, moving_views=1, resolution=(96, 72),
                            frame_rate_hz=30, blur_samples=4, gt_times=3)
#: The demo's training config: 16 then 32 windows over the 1 s swing, 1024 rays.
TRAIN_CONFIG = {"windows": [16, 32], "window_switch": [0.5], "n_samples": 32, "eval_every": 100}
TRAIN_MINUTES = 2.0

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


def run_demo(out_dir: Path, *, overwrite: bool = False, train_minutes: float = TRAIN_MINUTES,
             log=print) -> dict:
    with atomic_output(out_dir, overwrite=overwrite, directory=True) as tmp:
        tmp.mkdir()
        summary = _run(tmp, out_dir, log, train_minutes)
        (tmp / "summary.json").write_text(json.dumps(summary, indent=2))
    log(f"demo finished: outputs in {out_dir}/ (session/ with sync.png, conversions/, train.h5, "
        "event_images.png, event_rates.png, run/ with metrics.jsonl and eval_events.png, "
        "report/report.png, summary.json)")
    return summary


def _run(out: Path, final_dir: Path, log_final, train_minutes: float) -> dict:
    def log(msg) -> None:  # show the final paths, not the temporary folder being written
        log_final(str(msg).replace(str(out), str(final_dir)))

    start = time.perf_counter()
    session = simulate_session(SCENE, out / "session", OPTIONS, log=log)
    sim_seconds = time.perf_counter() - start
    views = session["views"]
    first = out / "session" / views[0]["bag"]
    log(format_info(describe(first)))

    recorded = read_event_file(first)
    summary = {"scene": SCENE, "views": len(views), "simulate_seconds": round(sim_seconds, 2),
               "events_per_view": [v["events"] for v in views], "round_trips": {}}
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

    images, curves = [], {}
    servo_start = session["servo"]["start_ns_scene"]
    for v in views:
        data = recorded if v is views[0] else read_event_file(out / "session" / v["bag"])
        offset = v["ground_truth"]["clock_offset_ns"]
        mid_swing = servo_start + 350_000_000 + offset          # mid-way through the swing
        window = time_slice(data.events, mid_swing, mid_swing + 20_000_000)
        images.append(event_image(window, data.width, data.height))
        curves[v["name"]] = event_rate(data.events["t"], 5_000_000)
    gap = np.full((images[0].shape[0], 4, 3), 128, np.uint8)
    sheet = np.concatenate([x for img in images for x in (img, gap)][:-1], axis=1)
    save_png(out / "event_images.png", sheet, upscale=3)
    plot_event_rate(out / "event_rates.png", curves,
                    title="event rate per view (5 ms bins), each in its own clock", t_origin_ns=0)

    synced = run_sync(out / "session", log=log)
    motion_start = session["time"]["motion_start_ns"]
    errors_us = {v["name"]: (synced["views"][v["name"]]["offset_ns"]
                             - v["ground_truth"]["clock_offset_ns"] - motion_start) / 1000
                 for v in views}
    log("sync error against the injected offsets: "
        + ", ".join(f"{k} {e:+.1f} us" for k, e in errors_us.items()))
    summary["sync_error_us"] = errors_us

    run_convert(out / "session", out / "train.h5", log=log)
    with TrainingSet(out / "train.h5") as ts:
        t0, t1 = ts.time_range
        d_l = ts.log_change(ts.views[0], t0, t1)
        summary["train_h5"] = {"views": len(ts.views), "time_range_ns": [int(t0), int(t1)],
                               "dl_abs_sum_view0": float(abs(d_l).sum())}

    log(f"training the planes field for {train_minutes:g} min on the events of "
        f"{OPTIONS.views} views")
    trained = run_train(out / "train.h5", out / "run", config=dict(TRAIN_CONFIG),
                        minutes=train_minutes, eval_fn=validation_eval(), log=log)
    result = run_eval(out / "run", out / "train.h5", factors=(1, 4),
                      image_path=out / "run" / "eval_events.png", log=log)
    run_report([out / "run"], out / "report")
    val = result["val_windows_x1"]
    summary["training"] = {"iterations": trained["iterations"],
                           "train_seconds": round(trained["wall_s"], 1),
                           "val_events_psnr": val["continuous"]["psnr"],
                           "val_zero_floor_psnr": val["zero_floor"]["psnr"],
                           "val_x4_events_psnr": result["val_windows_x4"]["continuous"]["psnr"],
                           "val_x4_zero_floor_psnr": result["val_windows_x4"]["zero_floor"]["psnr"],
                           "moving_events_psnr": result["moving_windows_x1"]["continuous"]["psnr"],
                           "moving_zero_floor_psnr": result["moving_windows_x1"]["zero_floor"]["psnr"]}
    return summary


def _check_same(path, got: EventFile, want: EventFile) -> None:
    if not np.array_equal(got.events, want.events):
        raise EvdnerfError(f"{path}: events read back differ from those written")
    if not np.array_equal(got.triggers, want.triggers):
        raise EvdnerfError(f"{path}: trigger events read back differ from those written")
