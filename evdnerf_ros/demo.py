"""`evdnerf demo`: the end-to-end job on the embedded virtual scene.

It grows with each part of the toolkit. Today: generate the rotating-bar scene's events
and trigger edges, record them as a rosbag2 (EventPacket evt3 + CameraInfo), convert that
bag into every container we speak, read each back and check it bit-exact, render an event
image and the event-rate plot, and write a summary.
"""

from __future__ import annotations

import json
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from .atomic import atomic_output
from .demo_scene import RotatingBar
from .errors import EvdnerfError
from .events import event_image, event_rate, plot_event_rate, save_png, time_slice
from .io.event_files import DEFAULT_TOPIC, EventFile, read_event_file, write_event_file
from .io.info import describe, format_info

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


def run_demo(out_dir: Path, *, overwrite: bool = False, log=print) -> dict:
    scene = RotatingBar()
    with atomic_output(out_dir, overwrite=overwrite, directory=True) as tmp:
        tmp.mkdir()
        summary = _run(scene, tmp, out_dir, log)
        (tmp / "summary.json").write_text(json.dumps(summary, indent=2))
    log(f"demo finished: outputs in {out_dir}/ (summary.json, event_image.png, event_rate.png)")
    return summary


def _run(scene: RotatingBar, out: Path, final_dir: Path, log) -> dict:
    from .io.messages import camera_info
    from .io.rosbag2 import BagWriter

    events, triggers = scene.events(), scene.triggers()
    log(f"scene: rotating bar {scene.width}x{scene.height}, {len(events)} events, "
        f"{len(triggers)} trigger edges")

    bag_path = out / "recording"
    fx = 0.9 * scene.width
    K = np.array([[fx, 0, (scene.width - 1) / 2], [0, fx, (scene.height - 1) / 2], [0, 0, 1]])
    with BagWriter(bag_path) as bag:
        bag.write("/event_camera/camera_info", "sensor_msgs/msg/CameraInfo",
                  camera_info(scene.width, scene.height, K, stamp_ns=int(events["t"][0])), int(events["t"][0]))
        bag.write_events(DEFAULT_TOPIC, events, width=scene.width, height=scene.height,
                         encoding="evt3", triggers=triggers)
    recorded = read_event_file(bag_path)
    _check_same(bag_path, recorded, events, triggers, with_triggers=True)
    log(format_info(describe(bag_path)).replace(str(out), str(final_dir)))

    summary = {"scene": "rotating-bar", "events": int(len(events)),
               "triggers": int(len(triggers)), "round_trips": {}}
    for name, encoding, keeps_triggers in CONVERSIONS:
        path = out / name
        start = time.perf_counter()
        carried = recorded if keeps_triggers else replace(recorded, triggers=recorded.triggers[:0])
        write_event_file(path, carried, encoding=encoding)
        back = read_event_file(path)
        _check_same(path, back, events, triggers, with_triggers=keeps_triggers)
        seconds = time.perf_counter() - start
        size = sum(f.stat().st_size for f in path.rglob("*")) if path.is_dir() else path.stat().st_size
        summary["round_trips"][name] = {"encoding": encoding, "bytes": size,
                                        "bytes_per_event": size / len(events),
                                        "seconds": round(seconds, 4), "bit_exact": True}
        log(f"  {name:<20} {encoding or '-':<6} {size / len(events):6.2f} B/event  bit-exact")

    window_start = scene.start_ns + 250_000_000
    window = time_slice(events, window_start, window_start + 20_000_000)
    save_png(out / "event_image.png", event_image(window, scene.width, scene.height), upscale=4)
    plot_event_rate(out / "event_rate.png",
                    {"rotating bar": event_rate(events["t"], 10_000_000, t_start=0)},
                    title="demo scene: event rate (10 ms bins; motion starts at 0.2 s)")
    return summary


def _check_same(path, got: EventFile, events, triggers, *, with_triggers: bool) -> None:
    if not np.array_equal(got.events, events):
        raise EvdnerfError(f"{path}: events read back differ from those written")
    if with_triggers and not np.array_equal(got.triggers, triggers):
        raise EvdnerfError(f"{path}: trigger events read back differ from those written")
