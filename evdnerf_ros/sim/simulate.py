"""`evdnerf simulate`: a capture session of a synthetic scene, in the layout of a real rig.

For each camera of the scene's ring (training views, then validation views offset by
`validation_offset_deg`) this renders the scene, runs the exact event generator with
adaptive time sampling, and records what the real rig would record, in that view's own
clock:

```
<session>/session.yaml             scene, camera, thresholds, per-view pose / angle / split,
                                   and the injected clock offsets as ground truth
<session>/view_00/ ...             one rosbag2 (MCAP) per view:
    /event_camera/events             event_camera_msgs/msg/EventPacket (evt3, with an
                                     EXT_TRIGGER pulse at the start of the scene's motion)
    /event_camera/camera_info        sensor_msgs/msg/CameraInfo
    /rig/camera_pose                 geometry_msgs/msg/PoseStamped (static camera: one;
                                     a moving view: its trajectory at 1 kHz)
    /rig/servo/joint_states          sensor_msgs/msg/JointState (servo scenes, 50 Hz)
    /rig/servo/trigger               sensor_msgs/msg/TimeReference START / DONE (servo scenes)
<session>/frames/<view>.npz        motion-blurred grey frames (the DNeRF baseline's input)
<session>/ground_truth/<view>.npz  intensity and depth at chosen times (scene clock)
```

Everything is written through :mod:`evdnerf_ros.session.recorder` (the one writer of the
session layout; topic names from :mod:`evdnerf_ros.topics`).

Views: ``--views N`` training views on the scene's ring (default: the ring's), and
validation views offset by ``validation_offset_deg``: ``--val-views M`` of them, or by
default as many as there are training views, at most the scene's own number of validation
views (``validation_views``, else its ring's ``views``); without ``--views`` the scene's
number. So ``--views 6`` on an 18-view scene renders 6 + 6 views, not 6 + 18.
``--val-views 0`` renders none.

Trigger: like a rig whose trigger cable feeds the camera's EXT_TRIGGER input, every view's
event stream carries a rising edge at the start of the scene's motion (a servo scene: the
servo's start, when its board raises trigger-out; any other scene: the first moment
anything moves) and the falling edge ``TRIGGER_PULSE_NS`` later, in the view's clock on the
sensor's microsecond tick, so that ``evdnerf sync`` can align every simulated session by
its trigger. A scene in which nothing moves gets no edge.

Clocks: the scene clock starts at the scene's `time.start_s`. View v's camera clock reads
`scene time + clock_offset_ns[v]` (drawn from the seed, recorded under `ground_truth` in
session.yaml) and ticks whole microseconds, as a real sensor does; the servo's device
clock (`micros()`) reads `scene time + device_offset_ns[v]`. Sync has to find these offsets.

Views run in worker processes (--jobs). On Ctrl-C or SIGTERM the parent ends its workers
before it re-raises (so the half-written session can be removed with nobody writing into
it), and a worker dies with its parent even if the parent is SIGKILLed.

Only what the data needs is computed: before the first and after the last moment anything
moves, the image is static, so one render stands for the whole span (no events there
without noise); inside the motion span the adaptive sampler renders only as often as the
log image departs from linear by `tolerance_c` thresholds and the scene's motion guard
allows (nothing may move more than a pixel within a piece: `sim/motion.py`), and the
generator touches only pixels whose intensity changed.
"""

from __future__ import annotations

import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np
from ..atomic import atomic_output
from ..errors import InputError
from ..limits import check_memory
from ..options import check_value, flag_name, option, option_fields
from ..events.types import empty_triggers, make_triggers
from ..session.recorder import (ViewRecorder, camera_record, servo_record, session_document,
                                view_record, write_session_yaml)
from ..geometry.camera import PinholeCamera
from .generator import EventGenerator
from .joint import joint_record
from ..events.logmap import LOG_EPS
from .noise import DEFAULT_THRESHOLD, MIN_THRESHOLD
from .motion import image_travel
from .render import SceneRenderer
from .sampling import simulate_renderer
from .scene import Scene, load_scene

JOINT_STATE_PERIOD_NS = 20_000_000    # servo frame: 50 Hz
MOVING_POSE_PERIOD_NS = 1_000_000     # a moving view's pose topic: 1 kHz
TRIGGER_PULSE_NS = 1_000_000          # trigger-out pulse width at motion start


@dataclass(frozen=True)
class SimulationOptions:
    """Every knob of `evdnerf simulate` (the CLI flags map one to one).

    Each value has a documented range (its field's option, checked by `checked()` before the
    scene is even loaded); what scales with the values (rays per render, blurred frames,
    ground truth, moving-view poses, renders per view) is estimated before anything is
    allocated, and an error names the flag to change.
    """

    views: int | None = option(None, "training views", kind=int, low=1, high=10_000,
                               none_help="the scene's ring")
    val_views: int | None = option(None, "validation views; 0: none", kind=int, low=0, high=10_000,
                                   none_help="as many as --views, at most the scene's validation views")
    resolution: tuple[int, int] | None = option(None, "image size", kind=int, nargs=2, metavar=("W", "H"),
                                                low=1, high=16_384, none_help="the scene's intrinsics")
    seed: int = option(0, "clock offsets and noise", low=0, high=2**63 - 1)
    c_pos: float = option(DEFAULT_THRESHOLD, "positive contrast threshold C+", low=MIN_THRESHOLD, high=10.0)
    c_neg: float = option(DEFAULT_THRESHOLD, "negative contrast threshold C-", low=MIN_THRESHOLD, high=10.0)
    eps: float = option(LOG_EPS, "log offset: L = log(I + eps), white = 1", low=0.0, high=1.0, low_open=True)
    threshold_sigma: float = option(0.0, "per-pixel threshold mismatch std (fixed per view seed)",
                                    flag="--sigma", low=0.0, high=1.0)
    refractory_ns: int = option(0, "refractory period in ns", low=0, high=10_000_000_000)
    tolerance_c: float = option(0.1, "adaptive sampling: allowed midpoint deviation from linear, in units of C",
                                low=0.0, high=10.0, low_open=True)
    # finest step: edges in rendered images are steps, so the linearity check alone would bisect to it
    min_step_ns: int = option(1_000_000, "adaptive sampling: finest step", flag="--min-step", duration=True,
                              low=1_000, high=100_000_000_000)
    max_step_ns: int = option(10_000_000, "adaptive sampling: coarsest step", flag="--max-step", duration=True,
                              low=1_000, high=3_600_000_000_000)
    supersample: int = option(2, "antialiasing: s x s rays per pixel", low=1, high=16)
    frame_rate_hz: float = option(30.0, "blurred grey frames per second; 0: none", flag="--frame-rate",
                                  low=0.0, high=100_000.0)
    blur_samples: int = option(8, "renders averaged per frame exposure", low=1, high=1024)
    gt_times: int = option(5, "ground-truth intensity/depth renders per view", low=0, high=10_000)
    moving_views: int = option(0, "extra validation views whose camera sweeps along the ring while the scene "
                                  "moves; poses at 1 kHz on the pose topic", low=0, high=10_000)
    moving_train_views: int = option(0, "extra training views whose camera sweeps along the ring (starting "
                                        "halfway between two training views): the static world passing by, "
                                        "which static views never record", low=0, high=10_000)
    moving_arc_deg: float = option(20.0, "azimuth a moving view sweeps over the scene's time",
                                   low=-3600.0, high=3600.0)
    max_clock_offset_s: float = option(5.0, "per-view camera clock offsets are drawn in [0, this) seconds",
                                       flag="--max-clock-offset", low=0.0, high=86_400.0)
    jobs: int = option(0, "worker processes; 0 = one per CPU (at most one per view)", low=0, high=1024)

    def check(self) -> None:
        """Raise InputError naming the flag of the first value outside its documented range."""
        self.checked()

    def checked(self) -> "SimulationOptions":
        """These options with every value range-checked (the ranges of their fields) and whole
        numbers made ints; nothing is allocated before this passes."""
        values = {f.name: check_value(getattr(self, f.name), f, spec, f"simulate: {flag_name(f, spec)}")
                  for f, spec in option_fields(SimulationOptions)}
        if values["min_step_ns"] > values["max_step_ns"]:
            raise InputError(f"simulate: --min-step {values['min_step_ns']} ns is longer than "
                             f"--max-step {values['max_step_ns']} ns; make --min-step <= "
                             "--max-step")
        return replace(self, **values)


#: Largest --resolution side (the scene files' intrinsics allow the same).
MAX_IMAGE_SIDE = 16384
#: Renders one view may plan (grid steps of the adaptive sampler, blurred-frame samples):
#: beyond this a run takes days, which is a typo more often than a plan.
MAX_RENDERS_PER_VIEW = 2_000_000
#: Bytes per ray of one render (measured peak: ~30-160 for the presets) and per pixel of the
#: event generator's state plus the sampler's cached log frames.
RENDER_BYTES_PER_RAY = 256
GENERATOR_BYTES_PER_PIXEL = 256


@dataclass
class ViewTask:
    name: str
    index: int
    split: str
    azimuth_deg: float
    T_world_cam: np.ndarray
    clock_offset_ns: int
    device_offset_ns: int
    seed: int
    arc_deg: float = 0.0                  # a moving view: azimuth swept from azimuth_deg


@dataclass
class ViewResult:
    name: str
    events: int
    triggers: int
    renders: int
    seconds: float
    stats: dict = field(default_factory=dict)


def simulate_session(scene_ref, out_dir, options: SimulationOptions = SimulationOptions(), *,
                     overwrite: bool = False, log=print) -> dict:
    """Write a whole session for `scene_ref` (preset name or YAML path); returns session.yaml."""
    options = options.checked()
    scene = load_scene(scene_ref)
    camera = scene.camera
    if options.resolution is not None:
        camera = camera.resized(*options.resolution)
    _check_budget(scene, camera, options)
    tasks = _view_tasks(scene, options)
    wall0 = time.perf_counter()
    with atomic_output(out_dir, overwrite=overwrite, directory=True) as tmp:
        (tmp / "frames").mkdir(parents=True)
        (tmp / "ground_truth").mkdir()
        results = _run_views(scene, camera, tasks, options, tmp, log)
        session = _session_yaml(scene, scene_ref, camera, options, tasks, results)
        write_session_yaml(tmp, session)
    total = time.perf_counter() - wall0
    log(f"simulate: {len(tasks)} views, {sum(r.events for r in results)} events in "
        f"{total:.1f} s -> {out_dir}")
    return session


def _view_counts(scene: Scene, options: SimulationOptions) -> tuple[int, int]:
    """(training views, validation views): --views, else the ring's; --val-views, else as
    many as training views, at most the scene's validation views (module doc)."""
    ring = scene.cameras.ring
    scene_val = ring.validation_views or ring.views
    train = ring.views if options.views is None else options.views
    if options.val_views is not None:
        return train, options.val_views
    return train, scene_val if options.views is None else min(options.views, scene_val)


def _n_views(scene: Scene, options: SimulationOptions) -> int:
    train, val = _view_counts(scene, options)
    return train + val + options.moving_views + options.moving_train_views


def _workers(options: SimulationOptions, n_views: int) -> int:
    return max(1, min(options.jobs or (os.cpu_count() or 1), n_views))


def _frame_count(scene: Scene, rate_hz: float) -> tuple[int, int]:
    """(number of blurred frames, frame period ns); (0, 0) when not even one fits."""
    if rate_hz == 0 or rate_hz * (scene.end_ns - scene.start_ns) < 1e9:
        return 0, 0
    period = max(1, int(round(1e9 / rate_hz)))
    return (scene.end_ns - scene.start_ns) // period, period


def _check_budget(scene: Scene, camera: PinholeCamera, options: SimulationOptions) -> None:
    """Refuse, before anything is allocated, a run whose renders per view or memory would
    run away; the message names the flag to change."""
    duration = scene.end_ns - scene.start_ns
    span = scene.motion_span_ns()
    moving_views = options.moving_views + options.moving_train_views
    moving = duration if moving_views else (
        0 if span is None else max(0, min(span[1], scene.end_ns) - max(span[0], scene.start_ns)))
    steps = moving // options.min_step_ns + 1
    if steps > MAX_RENDERS_PER_VIEW:
        raise InputError(f"simulate: --min-step {options.min_step_ns} ns over {moving / 1e9:g} s "
                         f"of motion plans up to {steps} renders per view (at most "
                         f"{MAX_RENDERS_PER_VIEW}); raise --min-step")
    frames, _ = _frame_count(scene, options.frame_rate_hz)
    if frames * options.blur_samples > MAX_RENDERS_PER_VIEW:
        raise InputError(f"simulate: --frame-rate {options.frame_rate_hz:g} with --blur-samples "
                         f"{options.blur_samples} over {duration / 1e9:g} s plans "
                         f"{frames * options.blur_samples} renders per view (at most "
                         f"{MAX_RENDERS_PER_VIEW}); lower --frame-rate or --blur-samples "
                         "(--frame-rate 0 writes no frames)")
    w, h, s = camera.width, camera.height, options.supersample
    rays = (w * s) * (h * s)
    n_views = _n_views(scene, options)
    poses = duration // MOVING_POSE_PERIOD_NS + 2
    parts = [
        (rays * RENDER_BYTES_PER_RAY + w * h * GENERATOR_BYTES_PER_PIXEL,
         f"--resolution {w} {h} with --supersample {s} ({rays} rays per render)",
         "lower --resolution or --supersample"),
        (frames * w * h * 4, f"--frame-rate {options.frame_rate_hz:g} ({frames} blurred "
                             f"{w}x{h} frames per view)",
         "lower --frame-rate or --resolution (--frame-rate 0 writes no frames)"),
        (options.gt_times * w * h * 18, f"--gt-times {options.gt_times} (ground truth of "
                                        f"{w}x{h} per view)", "lower --gt-times or --resolution"),
        (min(moving_views, 1) * poses * 400,
         f"--moving-views / --moving-train-views over a {duration / 1e9:g} s scene ({poses} poses at 1 kHz per view)",
         "shorten the scene's time span or drop --moving-views / --moving-train-views"),
    ]
    workers = _workers(options, n_views)
    total = sum(b for b, _, _ in parts) * workers + moving_views * poses * 400
    _, what, fix = max(parts, key=lambda part: part[0])
    check_memory(total, f"simulate: {what} x {workers} parallel view(s)",
                 f"{fix}, or lower --jobs")


def _view_tasks(scene: Scene, options: SimulationOptions) -> list[ViewTask]:
    rng = np.random.default_rng(options.seed)
    max_offset = int(round(options.max_clock_offset_s * 1e9))
    ring = scene.cameras.ring
    tasks = []
    n_train, n_val = _view_counts(scene, options)
    rings = [("train", "view", n_train), ("val", "val", n_val),
             ("moving", "moving", options.moving_views), ("sweep", "sweep", options.moving_train_views)]
    for kind, prefix, n in rings:
        if kind != "train" and n == 0:
            continue
        # moving views start halfway between two validation views (training sweeps: two training
        # views) and sweep moving_arc_deg
        sweeping = kind in ("moving", "sweep")
        azimuths = ring.azimuths_deg({"moving": "val", "sweep": "train"}.get(kind, kind), n)
        if sweeping:
            azimuths = [a + 180.0 / n for a in azimuths]
        for k, az in enumerate(azimuths):
            tasks.append(ViewTask(
                name=f"{prefix}_{k:02d}", index=len(tasks), split="val" if kind in ("val", "moving") else "train",
                azimuth_deg=float(az), T_world_cam=ring.pose_at(az),
                clock_offset_ns=int(rng.integers(0, max_offset)) if max_offset > 0 else 0,
                device_offset_ns=int(rng.integers(1_000_000_000, 60_000_000_000)),
                seed=int(rng.integers(0, 2 ** 31)),
                arc_deg=float(options.moving_arc_deg) if sweeping else 0.0))
    poses = [(t.name, T) for t in tasks for T in _pose_samples(scene, t)]
    scene.check_cameras([T for _, T in poses], [name for name, _ in poses])
    return tasks


def _pose_samples(scene: Scene, task: ViewTask) -> list[np.ndarray]:
    """The view's pose (static) or its sampled trajectory (moving: one pose per 1 ms)."""
    if task.arc_deg == 0.0:
        return [task.T_world_cam]
    _, Ts = _moving_poses(scene, task)
    return list(Ts)


def _moving_poses(scene: Scene, task: ViewTask) -> tuple[np.ndarray, np.ndarray]:
    """(t (M,) scene ns, T_world_cam (M, 4, 4)): a constant-rate sweep along the ring."""
    start, end = scene.start_ns, scene.end_ns
    t = np.arange(start, end, MOVING_POSE_PERIOD_NS, dtype=np.int64)
    t = np.append(t, np.int64(end))
    frac = (t - start) / float(max(1, end - start))
    Ts = np.stack([scene.cameras.ring.pose_at(task.azimuth_deg + task.arc_deg * f) for f in frac])
    return t, Ts


def _pose_function(task: ViewTask, track):
    """t_ns -> T_world_cam of the view: its fixed pose, or (a moving view, ``track`` from
    ``_moving_poses``) its sampled poses interpolated exactly as a consumer of its pose
    topic would."""
    if track is None:
        return lambda t: task.T_world_cam
    from ..geometry.pose_track import PoseTrack

    return PoseTrack(*track, source=f"view {task.name} trajectory")


def _run_views(scene, camera, tasks, options, out: Path, log) -> list[ViewResult]:
    jobs = _workers(options, len(tasks))
    bar = _progress(len(tasks))
    results = []
    try:
        if jobs == 1:
            for task in tasks:
                results.append(_simulate_view(scene, camera, task, options, out))
                _report(bar, log, results[-1])
        else:
            pool = ProcessPoolExecutor(max_workers=jobs, initializer=_worker_init,
                                       initargs=(os.getpid(),))
            try:
                futures = [pool.submit(_simulate_view, scene, camera, t, options, out)
                           for t in tasks]
                for fut in futures:
                    results.append(fut.result())
                    _report(bar, log, results[-1])
            except BaseException:
                # Ctrl-C, SIGTERM (the CLI raises KeyboardInterrupt for it) or a failed view:
                # no worker may go on writing into the output that is about to be removed.
                _stop_pool(pool)
                raise
            pool.shutdown(wait=True)
    finally:
        if bar is not None:
            bar.close()
    return results


def _worker_init(parent_pid: int) -> None:
    """In each worker: die with the parent, and leave signals to the parent.

    SIGINT from a terminal reaches the whole process group; the parent stops the workers
    itself, so a worker ignores it (no traceback per worker). SIGTERM gets its default
    action back (the parent's handler was inherited through fork). If the parent is
    SIGKILLed, Linux delivers SIGKILL to the worker (PR_SET_PDEATHSIG); elsewhere a thread
    watches the parent's pid.
    """
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    if not _set_parent_death_signal(signal.SIGKILL):
        import threading

        threading.Thread(target=_watch_parent, args=(parent_pid,), daemon=True).start()
    if os.getppid() != parent_pid:        # the parent died before the signal was armed
        os._exit(1)


def _set_parent_death_signal(sig: int) -> bool:
    if not sys.platform.startswith("linux"):
        return False
    try:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        PR_SET_PDEATHSIG = 1
        return libc.prctl(PR_SET_PDEATHSIG, int(sig), 0, 0, 0) == 0
    except (OSError, AttributeError):
        return False


def _watch_parent(parent_pid: int) -> None:
    while os.getppid() == parent_pid:
        time.sleep(0.5)
    os._exit(1)


def _stop_pool(pool: ProcessPoolExecutor) -> None:
    """End the worker processes, then the executor (its pending futures fail as broken;
    cancelling them first would race with the executor's own thread)."""
    # The executor has no public handle on its processes before Python 3.14.
    procs = list((getattr(pool, "_processes", None) or {}).values())
    if not procs and hasattr(pool, "terminate_workers"):
        pool.terminate_workers()
    for p in procs:
        if p.is_alive():
            p.terminate()
    for p in procs:
        p.join(timeout=5)
        if p.is_alive():
            p.kill()
            p.join(timeout=5)
    pool.shutdown(wait=True, cancel_futures=True)


def _progress(n):
    if not sys.stderr.isatty():
        return None
    from tqdm import tqdm

    return tqdm(total=n, unit="view", desc="simulate")


def _report(bar, log, r: ViewResult) -> None:
    line = (f"  {r.name}: {r.events} events, {r.renders} renders, {r.seconds:.2f} s")
    if bar is None:
        log(line)
    else:
        bar.set_postfix_str(line.strip())
        bar.update(1)


def _servo_objects(scene: Scene):
    return [o for o in scene.all_objects() if o.servo is not None]


def _simulate_view(scene: Scene, camera: PinholeCamera, task: ViewTask,
                   options: SimulationOptions, out: Path) -> ViewResult:
    """One view: events, bag, blurred frames and ground truth (runs in a worker process)."""
    from ..events.codecs import quantize_to_us

    t0 = time.perf_counter()
    renderer = SceneRenderer(scene, camera, options.supersample)
    track = _moving_poses(scene, task) if task.arc_deg != 0.0 else None
    pose_at = _pose_function(task, track)
    start, end = scene.start_ns, scene.end_ns
    span = scene.motion_span_ns()
    m0, m1 = (start, start) if span is None else (max(start, span[0]), min(end, span[1]))
    if task.arc_deg != 0.0:                  # a moving camera sees change all the time
        m0, m1 = start, end
    gen = EventGenerator(camera.width, camera.height, c_pos=options.c_pos, c_neg=options.c_neg,
                         eps=options.eps, threshold_sigma=options.threshold_sigma,
                         refractory_ns=options.refractory_ns, seed=task.seed)
    first = renderer(pose_at(start), start)
    gen.reset(first, start)
    chunks, renders, stats = [], 1, {}
    if m1 > m0:
        if m0 > start:                       # static lead-in: one render stands for it
            chunks.append(gen.step_log(gen.last_log(), m0))
        travel = image_travel(scene, camera, pose_at, m0, m1, options.min_step_ns)
        ev, st = simulate_renderer(lambda t: renderer(pose_at(t), t), m0, m1, gen, mode="adaptive",
                                   tolerance_c=options.tolerance_c,
                                   min_step_ns=options.min_step_ns,
                                   max_step_ns=options.max_step_ns, travel_px=travel)
        chunks.append(ev)
        renders += st.renders
        stats = {k: v for k, v in asdict(st).items() if k not in ("mode",)}
    if end > gen.t_ns:                       # static tail (or a static scene)
        chunks.append(gen.step_log(gen.last_log(), end))
    events = np.concatenate(chunks)
    stats["static_spans_ns"] = int((m0 - start) + (end - max(m1, m0)))

    # The camera's clock: offset, then whole microseconds (the sensor's tick).
    events = events.copy()
    events["t"] += task.clock_offset_ns
    events = quantize_to_us(events)
    servos = _servo_objects(scene)
    servo_times = []
    if servos:
        drive = servos[0].servo
        servo_times = [(drive.start_ns, "START"), (drive.start_ns + drive.profile.duration_ns, "DONE")]
    triggers = _trigger_edges(scene, task)

    off = task.clock_offset_ns
    rec_start = start + off
    with ViewRecorder(out / task.name, width=camera.width, height=camera.height) as rec:
        rec.camera_info(_K(camera), stamp_ns=rec_start)
        if track is None:
            rec.pose(task.T_world_cam, rec_start)
        else:
            rec.poses(track[0] + off, track[1])
        for t_scene, what in servo_times:
            device = t_scene + task.device_offset_ns       # the board's micros(): whole µs
            rec.servo_trigger(what, t_scene + off, device - device % 1000)
        for drive_obj in servos[:1]:
            for t_scene in range(start, end + 1, JOINT_STATE_PERIOD_NS):
                rec.servo_joint_state([drive_obj.name], [drive_obj.servo.angle_rad(t_scene)], t_scene + off)
        rec.events(events, triggers)

    renders += _write_frames(renderer, pose_at, scene, (m0, m1), task, options,
                             out / "frames" / f"{task.name}.npz")
    renders += _write_ground_truth(renderer, pose_at, scene, task, options,
                                   out / "ground_truth" / f"{task.name}.npz")
    return ViewResult(task.name, int(events.size), int(len(triggers)), renders,
                      time.perf_counter() - t0, stats)


def _trigger_edges(scene: Scene, task: ViewTask) -> np.ndarray:
    """The view's EXT_TRIGGER pulse (module doc): rising at the start of the scene's motion
    (a servo scene: the servo's start), falling TRIGGER_PULSE_NS later, edges outside the
    scene's time dropped; in the view's clock, on the sensor's microsecond tick."""
    servos = _servo_objects(scene)
    if servos:
        t_on = servos[0].servo.start_ns
    else:
        span = scene.motion_span_ns()
        if span is None:
            return empty_triggers()
        t_on = span[0]
    edges = [(t, v) for t, v in ((t_on, 1), (t_on + TRIGGER_PULSE_NS, 0))
             if scene.start_ns <= t <= scene.end_ns]
    if not edges:
        return empty_triggers()
    tt = np.array([t for t, _ in edges], np.int64) + task.clock_offset_ns
    return make_triggers(tt - tt % 1000, np.zeros(len(edges)), [v for _, v in edges])


def _K(camera: PinholeCamera) -> np.ndarray:
    return np.array([[camera.fx, 0, camera.cx], [0, camera.fy, camera.cy], [0, 0, 1]], np.float64)


def _write_frames(renderer, pose_at, scene, motion, task, options, path) -> int:
    """Motion-blurred frames: the mean of `blur_samples` renders over each exposure."""
    start = scene.start_ns
    n, period = _frame_count(scene, options.frame_rate_hz)
    if n < 1:
        return 0
    m0, m1 = motion
    k = options.blur_samples
    frames = np.empty((n, renderer.camera.height, renderer.camera.width), np.float32)
    cache: dict[int, np.ndarray] = {}
    renders = 0
    for i in range(n):
        a = start + i * period
        acc = np.zeros(frames.shape[1:], np.float64)
        for j in range(k):
            t = a + (2 * j + 1) * period // (2 * k)
            # Outside the motion span the image equals the one at the span's edge.
            key = min(max(t, m0), m1) if m1 > m0 else start
            if task.arc_deg != 0.0:
                key = t
            img = cache.get(key)
            if img is None:
                img = renderer(pose_at(key), key)
                renders += 1
                if not (m0 < key < m1):
                    cache[key] = img
            acc += img
        frames[i] = acc / k
    t_exp = start + period * np.arange(n + 1, dtype=np.int64) + task.clock_offset_ns
    with atomic_output(path) as tmp, open(tmp, "wb") as f:
        np.savez_compressed(f, frames=frames, t_start=t_exp[:-1], t_end=t_exp[1:],
                            t=t_exp[:-1] + period // 2)
    return renders


def _write_ground_truth(renderer, pose_at, scene, task, options, path) -> int:
    n = options.gt_times
    if n == 0:
        return 0
    t = np.array([scene.start_ns + ((scene.end_ns - scene.start_ns) * i) // max(1, n - 1)
                  for i in range(n)], np.int64)
    results = [renderer.render_result(pose_at(int(ti)), int(ti)) for ti in t]
    with atomic_output(path) as tmp, open(tmp, "wb") as f:
        np.savez_compressed(f, t_scene=t, t_view=t + task.clock_offset_ns,
                            intensity=np.stack([r.intensity for r in results]),
                            depth=np.stack([r.depth for r in results]),
                            mask=np.stack([r.mask for r in results]))
    return n


def _scene_ref(scene_ref) -> str:
    """A preset's name, or a scene file's absolute path (so a later evaluation finds it)."""
    p = Path(str(scene_ref))
    return str(p.resolve()) if p.is_file() else str(scene_ref)


def _session_yaml(scene, scene_ref, camera, options, tasks, results) -> dict:
    by_name = {r.name: r for r in results}
    span = scene.motion_span_ns()
    servos = _servo_objects(scene)
    views = []
    for task in tasks:
        r = by_name[task.name]
        views.append(view_record(
            task.name, task.split, task.T_world_cam, azimuth_deg=task.azimuth_deg,
            moving_arc_deg=task.arc_deg if task.arc_deg else None,
            events=r.events,
            trigger_events=r.triggers,
            frames=f"frames/{task.name}.npz" if options.frame_rate_hz else None,
            ground_truth={
                "clock_offset_ns": task.clock_offset_ns,
                "device_offset_ns": task.device_offset_ns,
                "file": f"ground_truth/{task.name}.npz" if options.gt_times else None,
            },
            simulation={"renders": r.renders, "seconds": round(r.seconds, 3), **r.stats}))
    ring = scene.cameras.ring
    return session_document(
        source={"kind": "simulation", "scene": scene.name, "scene_ref": _scene_ref(scene_ref),
                "seed": options.seed},
        rig={"kind": "virtual", "ring_radius_m": ring.radius,
             "elevation_deg": ring.elevation_deg, "look_at": list(map(float, ring.look_at)),
             "firmware_version": None, "device_serial": "virtual"},
        camera=camera_record(camera.width, camera.height, _K(camera)),
        servo=servo_record(servos[0].name, start_ns_scene=servos[0].servo.start_ns,
                           **(joint_record(scene) or {})) if servos else None,
        thresholds={"c_pos": options.c_pos, "c_neg": options.c_neg, "eps": options.eps,
                    "threshold_sigma": options.threshold_sigma,
                    "refractory_ns": options.refractory_ns},
        time={"scene_start_ns": scene.start_ns, "scene_end_ns": scene.end_ns,
              "motion_start_ns": None if span is None else span[0],
              "motion_end_ns": None if span is None else span[1]},
        frames={"rate_hz": options.frame_rate_hz, "blur_samples": options.blur_samples},
        options={k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(options).items()},
        views=views)
