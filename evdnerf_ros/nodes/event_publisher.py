"""The event publisher node: the events a camera on a robot would see in a synthetic scene
or a trained field, published as ROS 2 topics over DDS and/or recorded into a rosbag2.

Per chunk of ``chunk`` seconds of trajectory time the node renders the scene along the
camera's pose (robot pose interpolated from the trajectory, times the extrinsics),
drives ONE stateful :class:`~evdnerf_ros.sim.generator.EventGenerator` through it with
the adaptive time sampler (or at a fixed rate), packetises the events exactly as the
bag writer does (EventPacket evt3 by default; evt2, mono or dvs EventArray) and publishes
them on ``~/events`` with ``~/camera_info``. Stamps are trajectory times (int64 ns).
``render_ahead`` samples several chunks in one go (a moving camera's per-pixel sampler: fewer,
larger batched renders) and still publishes them chunk by chunk.
With ``realtime_factor`` > 0 each chunk is published when the wall clock reaches its end
(divided by the factor); 0 runs as fast as possible. The node logs its real-time factor
(trajectory seconds per wall second).

On DDS the node is a ROS 2 graph member (``ros2 node list``, ``/rosout``) with parameter
services: the thresholds and noise (``c_pos``, ``c_neg``, ``threshold_sigma``,
``refractory_ns``, ``shot_noise_hz``, ``leak_rate_hz``) change live with ``ros2 param set``;
the others refuse with the reason. It also publishes the robot pose on ``/tf``, the
extrinsics on ``/tf_static`` and, when not real time, trajectory time on ``/clock``.

Executable: ``event_publisher --ros-args -p scene:=fork -p trajectory:=traj.yaml ...``;
``evdnerf publish`` runs the same node without DDS (bag only) unless ``--dds``.
"""

from __future__ import annotations

import sys
import time
from dataclasses import asdict, dataclass, field

import numpy as np

from ..errors import EvdnerfError, InputError
from ..ros.node import Node
from ..ros.parameters import ParameterSpec as Param
from ..sim.noise import DEFAULT_THRESHOLD

NS = 1_000_000_000
MAX_SECONDS = 4e9          # ~127 years: every time parameter stays well inside int64 nanoseconds

PARAMETERS = [
    Param("scene", "fork", "synthetic scene: a preset name (fork, jet-down, ...) or a scene YAML; unused with run_dir"),
    Param("run_dir", "", "trained run folder (checkpoint.pt from `evdnerf train`); empty: render `scene`", read_only=True),
    Param("field_duration", 0.0, "seconds of scene time the field's normalised time 0..1 spans (0: the "
      "trajectory's span)", min=0.0, max=MAX_SECONDS),
    Param("scene_time_offset", 0.0, "scene time (s) at the trajectory's first pose", min=-MAX_SECONDS, max=MAX_SECONDS),
    Param("trajectory", "", "robot poses: a bag (nav_msgs/Odometry, PoseStamped or /tf), .yaml or .csv; empty: a "
      "static camera at the scene's first ring view for `duration` seconds, or for a trained run once round "
      "its training views over its training span"),
    Param("trajectory_topic", "", "pose topic inside a trajectory bag (empty: the only pose topic)"),
    Param("trajectory_child_frame", "base_link", "robot frame (child_frame_id) when reading /tf"),
    Param("trajectory_max_gap", 0.5, "largest gap (s) between poses that is interpolated", min=1e-6, max=MAX_SECONDS),
    Param("duration", 0.0, "seconds to publish (0: the whole trajectory, or the scene's duration; else at least 1 ns)",
      min=0.0, max=MAX_SECONDS),
    Param("camera.xyz", [0.0, 0.0, 0.0], "camera position in the robot frame (m)"),
    Param("camera.rpy_deg", [0.0, 0.0, 0.0], "camera orientation in the robot frame: roll, pitch, yaw (deg, fixed "
      "axes x, y, z); the camera frame is OpenCV (x right, y down, z forward)"),
    Param("camera.quat", [], "camera orientation as a quaternion (x, y, z, w); overrides rpy_deg", type=list),
    Param("camera.matrix", [], "T_robot_cam as 16 row-major numbers; overrides xyz/rpy/quat", type=list),
    Param("camera.width", 0, "image width in pixels (0: the scene's)", min=0, max=65535),
    Param("camera.height", 0, "image height in pixels (0: the scene's)", min=0, max=65535),
    Param("camera.fov_deg", 0.0, "horizontal field of view (0: the scene's; 40 for a trained run)", min=0.0, max=179.0),
    Param("camera.K", [], "pinhole intrinsics [fx, fy, cx, cy] in pixels; overrides fov_deg", type=list),
    Param("supersample", 1, "s x s rays per pixel of the synthetic renderer", min=1, max=8),
    # dynamic: `ros2 param set` changes these while the node runs (applied at the next chunk)
    Param("c_pos", DEFAULT_THRESHOLD, "ON contrast threshold (log units)", min=1e-4, dynamic=True),
    Param("c_neg", DEFAULT_THRESHOLD, "OFF contrast threshold (log units)", min=1e-4, dynamic=True),
    Param("threshold_sigma", 0.0, "per-pixel threshold mismatch (std, log units)", min=0.0, dynamic=True),
    Param("refractory_ns", 0, "refractory period (ns)", min=0, dynamic=True),
    Param("shot_noise_hz", 0.0, "shot-noise events per pixel per second", min=0.0, dynamic=True),
    Param("leak_rate_hz", 0.0, "leak events per pixel per second", min=0.0, dynamic=True),
    Param("seed", 0, "seed of every random draw (noise, mismatch)", min=0),
    Param("adaptive", True, "adaptive time sampling (skip steps where nothing moves); false: fixed render_rate_hz"),
    Param("tolerance_c", 0.1, "adaptive sampling: allowed midpoint deviation from linear, in units of C", min=1e-6),
    Param("min_step_ns", 100_000, "adaptive sampling: finest step (ns)", min=1),
    Param("max_step_ns", 10_000_000, "adaptive sampling: coarsest step (ns)", min=1),
    Param("per_pixel", "auto", "trained field, adaptive sampling: true refines each pixel's time steps on its own and "
      "renders the pixels of many times in one batch; false renders whole images, every pixel at every time any "
      "pixel needs; auto: true when the camera moves during the published span (a static camera's whole images "
      "reuse their static part instead)", choices=("auto", "true", "false"), read_only=True),
    Param("max_travel_px", 4.0, "trained field, moving camera, adaptive sampling: a piece over which anything in "
      "view may move further than this in the image (pixels) is split whatever its midpoint test says (the motion "
      "guard: a there-and-back change between three renders is invisible to the test); 0: no guard", min=0.0),
    Param("render_rate_hz", 1000.0, "fixed sampling rate when adaptive is false", min=1e-3),
    Param("leave_out", True, "render only pixels whose rays can hit something (scene primitives' screen boxes / the "
      "field's occupancy grid)"),
    Param("reuse_static", True, "trained field, static camera: render the rays and samples outside the run's dynamic "
      "region once and per time only the dynamic samples (same events; false: every sample at every render)"),
    Param("static_world", "auto", "trained field: what rays see outside the run's dynamic region: field (the static "
      "field and learned background as trained), flat (nothing, in front of one constant grey: no events from a "
      "static world the static training views could not show; only rays through the region are rendered) or auto "
      "(flat when the camera moves during the published span and the run has a dynamic region, else field)", choices=("auto", "field", "flat"),
      read_only=True),
    Param("bake_resolution", 0, "trained field: play back the field baked into a grid of this many vertices per axis "
      "(an approximation: faster, slightly different events; 0: the field itself)", min=0, max=512),
    Param("bake_times", 0, "trained field, baked: frames over the field's time 0..1 (0: 4 per time texel)", min=0,
      max=4096),
    Param("prefetch_levels", -1, "trained field, static camera, adaptive whole images: render each top piece's first "
      "N levels of midpoints ahead in one batch, needed or not (the same events; 0: one render at a time); -1: auto, "
      "3 where a batch costs about one render (a baked field, whose lookups take every time at once, or a GPU), "
      "else 0 (the field itself on the CPU pays for every render of a batch); off with reuse_static false", min=-1, max=8,
      read_only=True),
    Param("device", "auto", "where a trained field is evaluated: auto (cuda when available), cpu or cuda",
      choices=("auto", "cpu", "cuda"), read_only=True),
    Param("ray_chunk", 16384, "trained field: rays rendered per batch (a bound on memory; a GPU, where each batch is "
      "a round trip of many small launches, may take far more)", min=1, max=1 << 24, read_only=True),
    Param("encoding", "evt3", "event message: evt3, evt2 or mono EventPacket, or array (dvs_msgs/EventArray)",
      choices=("evt3", "evt2", "mono", "array")),
    Param("packet_ns", 1_000_000, "longest time span of one event message (ns)", min=1),
    Param("chunk", 0.01, "seconds of trajectory rendered and published per step", min=1e-6, max=MAX_SECONDS),
    Param("render_ahead", -1.0, "seconds of trajectory sampled in one go, then published chunk by chunk (a whole "
      "number of chunks; the same events as one chunk at a time when chunk is a whole number of min_step_ns "
      "and of max_step_ns if longer): fewer, larger batched renders "
      "for a moving camera's per-pixel sampling, at the cost of that much latency; thresholds and noise set while "
      "running apply from the next such span; -1: auto, 0.05 s with per-pixel sampling, else one chunk",
      min=-1.0, max=MAX_SECONDS, read_only=True),
    Param("realtime_factor", 1.0, "1: real time; 2: twice as fast; 0: as fast as possible", min=0.0),
    Param("frame_id", "event_camera", "header.frame_id of events and camera info"),
    Param("qos", "default", "QoS profile of the published topics (default = reliable, keep-last 10; sensor_data = "
      "best effort)", choices=("default", "sensor_data", "transient_local")),
    Param("camera_info_period", 1.0, "seconds of trajectory time between CameraInfo messages (also sent at once "
      "when a new subscriber appears)", min=1e-3, max=MAX_SECONDS),
    Param("bag", "", "also record into this rosbag2 (must not exist); empty: no bag", read_only=True),
    Param("bag_storage", "mcap", "rosbag2 storage of the bag", choices=("mcap", "sqlite3"), read_only=True),
    Param("wait_for_subscribers", 0, "wait until this many subscribers match ~/events before starting", min=0),
    Param("wait_timeout", 10.0, "seconds to wait for subscribers", min=0.0, max=MAX_SECONDS),
    Param("publish_tf", True, "with DDS: the robot pose on /tf (world_frame -> robot_frame, every chunk) and the "
      "extrinsics on /tf_static (robot_frame -> frame_id)"),
    Param("world_frame", "world", "parent frame of the robot pose on /tf"),
    Param("robot_frame", "base_link", "the robot's frame on /tf and /tf_static"),
    Param("publish_clock", "auto", "with DDS: trajectory time on /clock every chunk, for nodes run with "
      "use_sim_time:=true (auto: when realtime_factor is not 1)", choices=("auto", "true", "false")),
]


#: The most camera poses made ahead for one chunk of per-pixel sampling (``_plan_poses``: 2 MB).
POSE_GRID_MAX = 1 << 14
#: ``render_ahead`` auto with per-pixel sampling (s): 5 default chunks a batch (orbit at 64x64 on 2 cores: RTF x1.5)
AUTO_RENDER_AHEAD_S = 0.05
#: A paced run this far behind its schedule (s, and at least two chunks) says so, once, with the lever to pull.
LATE_WARN_S = 0.5


@dataclass
class PublishReport:
    messages: int = 0
    events: int = 0
    bytes: int = 0
    sim_seconds: float = 0.0
    wall_seconds: float = 0.0
    render_seconds: float = 0.0
    renders: int = 0             # distinct times rendered
    render_calls: int = 0        # calls to the renderer (a batch is one)
    pixels_rendered: int = 0     # per-pixel sampling: pixel values rendered (whole images: 0)
    frames_fed: int = 0
    rays_total: int = 0          # render work without leave-out (scene: ray-primitive tests; field: rays)
    rays_rendered: int = 0       # render work done (same unit)
    samples_total: int = 0       # trained field: field evaluations of a full render of every traced ray per call
    samples_evaluated: int = 0   # trained field: field evaluations done (static-camera reuse, baking)
    interrupted: bool = False
    fell_behind: bool = False    # a paced run (realtime_factor > 0) fell LATE_WARN_S behind its schedule
    rtf: float = 0.0
    source_seconds: float = 0.0  # loading the scene or run before publishing (a trained run: baking included)
    topics: dict = field(default_factory=dict)

    def as_dict(self) -> dict:
        return asdict(self)


class EventPublisher(Node):
    NAME = "event_publisher"
    PARAMETERS = PARAMETERS

    def __init__(self, argv=(), **kwargs):
        super().__init__(argv, **kwargs)
        p = self.params
        if p["min_step_ns"] > p["max_step_ns"]:
            raise InputError(f"min_step_ns {p['min_step_ns']} is larger than max_step_ns {p['max_step_ns']}")
        self.scene = None
        if not p["run_dir"]:
            from ..sim.scene import load_scene

            self.scene = load_scene(p["scene"], check_cameras=False)
        self.camera = self._camera()
        from ..limits import check_memory

        # the renderer's per-ray working arrays dominate: ~256 bytes per ray at the peak
        rays = self.camera.width * self.camera.height * (p["supersample"] ** 2 if self.scene is not None else 1)
        check_memory(256.0 * rays, f"camera {self.camera.width}x{self.camera.height} with supersample "
                     f"{p['supersample']}", "lower camera.width / camera.height or supersample")
        if p["encoding"] in ("evt3", "evt2") and max(self.camera.width, self.camera.height) > 2048:
            raise InputError(f"encoding {p['encoding']} carries at most 2048x2048 pixels; use encoding mono or array")
        self.t0, self.t1, self.track, self.T_robot_cam = self._trajectory()
        wall0 = time.perf_counter()
        self.source = self._source()
        source_seconds = time.perf_counter() - wall0
        from ..sim.generator import EventGenerator

        self.generator = EventGenerator(
            self.camera.width, self.camera.height, c_pos=p["c_pos"], c_neg=p["c_neg"],
            threshold_sigma=p["threshold_sigma"], refractory_ns=p["refractory_ns"],
            shot_noise_rate_hz=p["shot_noise_hz"], leak_rate_hz=p["leak_rate_hz"], seed=p["seed"])
        self.events_pub = self.create_publisher("~/events", "dvs_msgs/msg/EventArray" if p["encoding"] == "array"
                                                else "event_camera_msgs/msg/EventPacket", p["qos"])
        self.info_pub = self.create_publisher("~/camera_info", "sensor_msgs/msg/CameraInfo", p["qos"])
        self._tf_pubs = self._clock_pub = None
        if self.dds is not None:
            from ..ros import tf as _tf

            if p["publish_tf"]:
                self._tf_pubs = (self.create_publisher("/tf", _tf.TF_TYPE, _tf.TF_QOS),
                                 self.create_publisher("/tf_static", _tf.TF_TYPE, _tf.TF_STATIC_QOS))
            if p["publish_clock"] == "true" or (p["publish_clock"] == "auto" and p["realtime_factor"] != 1.0):
                self._clock_pub = self.create_publisher("/clock", _tf.CLOCK_TYPE, _tf.CLOCK_QOS)
        self._live: dict = {}          # dynamic parameters set while running, applied at the next chunk
        self._pose_grid = None         # (times, camera poses, t0, step) of the span sampled per pixel (_plan_poses)
        self.params.listeners.append(self._live.update)
        if p["bag"]:
            self.record_to(p["bag"], storage=p["bag_storage"])
        self.report = PublishReport(source_seconds=source_seconds)

    # ----- inputs
    def _camera(self):
        from ..geometry.camera import PinholeCamera

        p = self.params
        base = self.scene.camera if self.scene is not None else self._run().train_camera
        if base is not None and not (p["camera.width"] or p["camera.height"] or p["camera.K"] or p["camera.fov_deg"]):
            return base                  # the scene's camera, or the camera the run was trained on
        w = p["camera.width"] or (base.width if base else 0)
        h = p["camera.height"] or (base.height if base else 0)
        if not w or not h:
            raise InputError("camera.width and camera.height are needed with a run that did not record its "
                             "training camera (e.g. 346 x 260)")
        K = p["camera.K"]
        if K:
            if len(K) != 4 or not all(isinstance(v, (int, float)) for v in K):
                raise InputError(f"parameter 'camera.K': expected [fx, fy, cx, cy], got {K}")
            return PinholeCamera(w, h, float(K[0]), float(K[1]), float(K[2]), float(K[3]))
        fov = p["camera.fov_deg"] or (base.fov_x_deg if base else 40.0)
        return PinholeCamera.from_fov(w, h, fov)

    def _trajectory(self):
        """(t0, t1, PoseTrack of T_world_robot, T_robot_cam)."""
        from ..io.poses import extrinsics, load_poses, matrix_extrinsics
        from ..geometry.pose_track import PoseTrack

        p = self.params
        dur = int(round(p["duration"] * NS))
        if p["duration"] > 0 and dur == 0:
            raise InputError(f"duration {p['duration']} s is less than 1 ns; give 0 for the whole trajectory "
                             "or at least 1e-9 s")
        if p["trajectory"]:
            t, T = load_poses(p["trajectory"], topic=p["trajectory_topic"] or None,
                              child_frame=p["trajectory_child_frame"])
            track = PoseTrack(t, T, max_gap_ns=int(round(p["trajectory_max_gap"] * NS)), source=p["trajectory"])
            t0, t1 = track.span_ns
            if p["camera.matrix"]:
                T_robot_cam = matrix_extrinsics(p["camera.matrix"], what="parameter 'camera.matrix' (T_robot_cam)")
            else:
                T_robot_cam = extrinsics(p["camera.xyz"], p["camera.rpy_deg"], p["camera.quat"] or None,
                                         what="parameters 'camera.xyz' / 'camera.rpy_deg' / 'camera.quat'")
        elif self.scene is None:       # a trained run: once round its training views
            run = self._run()
            span = run.time_range_ns[1] - run.time_range_ns[0] if run.time_range_ns else 0
            t, T = run.orbit(int(round(p["field_duration"] * NS)) or dur or span or NS)
            t0, t1 = 0, int(t[-1])
            track = PoseTrack(t, T, source=f"{p['run_dir']}: orbit of its training views")
            T_robot_cam = np.eye(4)
        else:      # a static camera at the scene's first ring view: that pose is the camera's own
            T = self.scene.camera_poses("train")[0]
            t0, t1 = 0, dur or int(self.scene.duration_ns)
            track = PoseTrack([t0, max(t1, t0 + 1)], [T, T], source="static camera")
            T_robot_cam = np.eye(4)
        if dur:
            t1 = min(t1, t0 + dur)
        if t1 <= t0:
            raise InputError(f"nothing to publish: the time span [{t0}, {t1}] ns is empty")
        return t0, t1, track, T_robot_cam

    def _run(self):
        """The trained run (loaded once)."""
        if getattr(self, "_trained_run", None) is None:
            from ..train.run import TrainedRun

            self._trained_run = TrainedRun.load(self.params["run_dir"])
        return self._trained_run

    def _source(self):
        from .sources import FieldSource, SceneSource

        p = self.params
        if self.scene is not None:
            return SceneSource(self.scene, self.camera, supersample=p["supersample"], leave_out=p["leave_out"])
        duration = int(round(p["field_duration"] * NS)) or (self.t1 - self.t0)
        from ..field.renderer import resolve_static_world

        world = resolve_static_world(p["static_world"], moving=self._camera_moves(),
                                     has_region=self._run().dynamic is not None)
        self.logger.info(f"trained field: static world {world}")
        return FieldSource(self._run(), self.camera, duration_ns=duration, leave_out=p["leave_out"],
                           reuse_static=p["reuse_static"], static_world=world, bake_resolution=p["bake_resolution"],
                           bake_times=p["bake_times"], chunk=p["ray_chunk"], device=p["device"])

    def _camera_moves(self) -> bool:
        """Whether the camera pose changes during the published span (at its ends and every pose
        between them: the track interpolates between poses)."""
        from ..field.renderer import POSE_SAME

        knots = self.track.t[(self.track.t > self.t0) & (self.track.t < self.t1)]
        first = self.camera_pose(self.t0)
        return any(float(np.abs(self.camera_pose(int(t)) - first).max()) > POSE_SAME
                   for t in (*knots, self.t1))

    def camera_pose(self, t_ns: int) -> np.ndarray:
        return self.track(t_ns) @ self.T_robot_cam

    def render(self, t_ns: int) -> np.ndarray:
        return self.source(self.camera_pose(t_ns), int(self._scene_time(t_ns)))

    def _scene_time(self, t_ns):
        return np.asarray(t_ns, np.int64) - self.t0 + int(round(self.params["scene_time_offset"] * NS))

    def _batched_renders(self, static_field: bool) -> dict:
        """simulate_renderer's batch arguments: a trained field seen by a static camera renders
        ``prefetch_levels`` of each top piece's midpoints at once (not with reuse_static false,
        which promises every sample at every render: a batch shares its static part)."""
        levels = int(self.params["prefetch_levels"]) if self.params["reuse_static"] else 0
        if levels < 0 and static_field:
            batches = hasattr(self.source.field, "decode_times") or self.source.device.type == "cuda"
            levels = 3 if batches else 0
        if not static_field or levels == 0:
            return {}
        pose = self.camera_pose(self.t0)
        return {"render_many": lambda times: self.source.render_times(pose, self._scene_time(times)),
                "prefetch_levels": levels}

    def _field_travel(self, t0: int, t1: int):
        """The motion guard of a moving camera past a trained field over [t0, t1]
        (``sim.motion.box_travel`` of what the field can show); None when it shows nothing."""
        from ..sim.motion import box_travel, motion_sample_times

        box = self.source.content_box()
        if box is None:
            return None
        knots = self.track.t[(self.track.t > t0) & (self.track.t < t1)]
        times = motion_sample_times(t0, t1, self.params["min_step_ns"], knots)
        return box_travel(box, self.camera, times, self._camera_poses(times),
                          infinity=self.source.shows_infinity)

    def render_pixels(self, t_ns: np.ndarray, pixels: np.ndarray) -> np.ndarray:
        """Row-major pixels at trajectory times, many in one batch (``sim.sampling.simulate_pixels``)."""
        times, which, poses = self._distinct_poses(np.asarray(t_ns, np.int64))
        t_scene = times - self.t0 + int(round(self.params["scene_time_offset"] * NS))
        return self.source.render_pixels(poses, t_scene, which, pixels)

    def _distinct_poses(self, t_ns: np.ndarray):
        """(sorted distinct times, index of each of ``t_ns`` among them, their camera poses). Times on
        the chunk's grid (``_plan_poses``, all of them in the sampler's calls) are found by division
        and a count, not by sorting every pixel's time (np.unique: 6x slower, a tenth of a 128x128
        moving camera's publish on the CPU)."""
        grid = self._pose_grid
        if grid is not None and t_ns.size:
            times, poses, t0, step = grid
            # the grid's point j is t0 + j step, its last the span's end
            k = np.where(t_ns == times[-1], times.size - 1, np.clip((t_ns - t0) // step, 0, times.size - 1))
            if np.array_equal(times[k], t_ns):
                used = np.bincount(k, minlength=times.size) > 0
                return times[used], (np.cumsum(used) - 1)[k], poses[used]
        times, which = np.unique(t_ns, return_inverse=True)
        return times, which.ravel(), self._camera_poses(times)

    def _plan_poses(self, t0: int, t1: int, step: int) -> None:
        """Make the camera poses of a chunk's sampling grid (``simulate_pixels``' grid times) at once:
        its many small renders look them up rather than each interpolating the trajectory afresh
        (~0.2 ms a call); none beyond ``POSE_GRID_MAX`` grid times."""
        from ..sim.sampling import pixel_grid_size, pixel_grid_times

        n = pixel_grid_size(t0, t1, step)
        if n + 1 > POSE_GRID_MAX:
            self._pose_grid = None
            return
        times = pixel_grid_times(np.arange(n + 1, dtype=np.int64), t0, t1, step)
        self._pose_grid = (times, self.track.poses(times) @ self.T_robot_cam, t0, step)

    def _camera_poses(self, times: np.ndarray) -> np.ndarray:
        """(K, 4, 4) camera poses at the sorted distinct trajectory times ``times``: those on the
        chunk's grid (``_plan_poses``) looked up, the others interpolated."""
        grid = self._pose_grid
        if grid is None or not times.size:
            return self.track.poses(times) @ self.T_robot_cam
        grid_times, grid_poses = grid[:2]
        k = np.minimum(np.searchsorted(grid_times, times), grid_times.size - 1)
        on = grid_times[k] == times
        if on.all():
            return grid_poses[k]
        poses = np.empty((times.size, 4, 4))
        poses[on] = grid_poses[k[on]]
        poses[~on] = self.track.poses(times[~on]) @ self.T_robot_cam
        return poses

    def _chunks_ahead(self, chunk: int, per_pixel: bool) -> int:
        """Chunks sampled in one go (``render_ahead``: at least one)."""
        ahead = self.params["render_ahead"]
        if ahead < 0:
            ahead = AUTO_RENDER_AHEAD_S if per_pixel else 0.0
        return max(1, int(round(ahead * NS / chunk)))

    def _speed_hint(self, moving: bool) -> str:
        """The lever that buys this run the most speed for its error (bench/bench_publish.py)."""
        p = self.params
        if p["run_dir"] and not p["bake_resolution"]:
            return ("bake_resolution:=64 plays the trained field back from a grid, 3.5x faster on the fork's orbit at 64x64 "
                    "for a few % fewer events (its error: the publish benchmark)")
        if p["adaptive"] and p["min_step_ns"] < 1_000_000:
            return "a larger min_step_ns renders fewer times, at the cost of the finest event timing"
        return "a smaller camera (camera.width / camera.height) or a lower realtime_factor"

    # ----- run
    def _camera_info(self, stamp_ns: int) -> None:
        from ..io.messages import camera_info
        from ..io.typestore import ros2_typestore

        msg = camera_info(self.camera.width, self.camera.height, self.camera.K, frame_id=self.params["frame_id"],
                          stamp_ns=stamp_ns)
        self.info_pub.publish_raw(ros2_typestore().serialize_cdr(msg, self.info_pub.msgtype), stamp_ns)

    def _publish_tf_static(self, stamp_ns: int) -> None:
        if self._tf_pubs is not None:
            from ..ros import tf as _tf

            p = self.params
            self._tf_pubs[1].publish_raw(_tf.tf_message([_tf.transform_stamped(
                self.T_robot_cam, p["robot_frame"], p["frame_id"], stamp_ns)]), stamp_ns)

    def _publish_tf_clock(self, t_ns: int) -> None:
        from ..ros import tf as _tf

        if self._clock_pub is not None:
            self._clock_pub.publish_raw(_tf.clock_message(t_ns), t_ns)
        if self._tf_pubs is not None:
            p = self.params
            self._tf_pubs[0].publish_raw(_tf.tf_message([_tf.transform_stamped(
                self.track(t_ns), p["world_frame"], p["robot_frame"], t_ns)]), t_ns)

    def _apply_live(self, t_ns: int) -> None:
        """Apply dynamic parameters set since the last chunk. Noise rates and the refractory
        period change in place; new thresholds start a generator with them from the current
        log image (every pixel re-armed at t_ns, as a sensor after a bias change)."""
        if not self._live:
            return
        changes = {}
        while self._live:        # popitem is atomic: a set arriving meanwhile waits for the next chunk
            k, v = self._live.popitem()
            changes[k] = v
        g, p = self.generator, self.params
        if {"c_pos", "c_neg", "threshold_sigma"} & changes.keys():
            from ..sim.generator import EventGenerator

            new = EventGenerator(g.width, g.height, c_pos=p["c_pos"], c_neg=p["c_neg"],
                                 threshold_sigma=p["threshold_sigma"], refractory_ns=p["refractory_ns"],
                                 shot_noise_rate_hz=p["shot_noise_hz"], leak_rate_hz=p["leak_rate_hz"], seed=p["seed"])
            if g.initialized:
                new.reset_log(g.last_log(), g.t_ns)
            self.generator = g = new
        g.refractory_ns = int(p["refractory_ns"])
        g.shot_noise_rate_hz = float(p["shot_noise_hz"])
        g.leak_rate_hz = float(p["leak_rate_hz"])
        self.logger.info(f"applied at t = {(t_ns - self.t0) / NS:.3f} s: {changes}")

    def _wait_for_subscribers(self, n: int, timeout_s: float) -> None:
        pub = self.events_pub
        deadline = time.monotonic() + timeout_s
        self.logger.info(f"waiting for {n} subscriber(s) on {pub.topic}")
        while not pub.dds.wait_for_subscribers(n, 0.1) and self.ok():
            if time.monotonic() > deadline:
                self.logger.warn(f"{pub.topic}: only {pub.subscribers()} subscriber(s) after {timeout_s} s; "
                                 "publishing anyway")
                return

    def run(self, on_events=None) -> PublishReport:
        """Publish the whole span; ``on_events(events)`` (optional) also gets every chunk's events
        as published (evt encodings: quantised to whole microseconds)."""
        from ..events.codecs import quantize_to_us
        from ..io.packetizer import Packetizer
        from ..sim.sampling import simulate_pixels, simulate_renderer

        p = self.params
        rep = self.report
        if p["wait_for_subscribers"] and self.dds is not None:
            self._wait_for_subscribers(p["wait_for_subscribers"], p["wait_timeout"])

        def sink(topic, msgtype, data, stamp):
            self.events_pub.publish_raw(data, stamp)

        encoder = Packetizer(sink)
        chunk = max(1, int(round(p["chunk"] * NS)))
        info_every = int(round(p["camera_info_period"] * NS))
        factor = p["realtime_factor"]
        evt = p["encoding"] in ("evt3", "evt2")
        field = hasattr(self.source, "render_pixels")          # a trained field (a scene has neither switch)
        moving = field and self._camera_moves()
        per_pixel = p["adaptive"] and field and (p["per_pixel"] == "true" or (p["per_pixel"] == "auto" and moving))
        guard = p["adaptive"] and moving and p["max_travel_px"] > 0
        batched = self._batched_renders(field and not moving)
        if per_pixel:
            self.source.warm_up()      # the compiled single-pixel passes, loaded before the clock starts
        self.logger.info(f"publishing {(self.t1 - self.t0) / NS:.3f} s of events from the {self.source.kind} on "
                         f"{self.events_pub.topic} ({p['encoding']}, {self.camera.width}x{self.camera.height}"
                         f"{', DDS domain %d' % self.dds.domain_id if self.dds is not None else ', no DDS'}"
                         f"{', bag ' + str(self.bag.path) if self.bag is not None else ''})")
        if field and p["adaptive"]:
            self.logger.info(f"adaptive sampling {'per pixel' if per_pixel else 'of whole images'}, min step "
                             f"{p['min_step_ns'] / 1e6:g} ms, "
                             + (f"motion guard {p['max_travel_px']:g} px" if guard else "no motion guard"))
        ahead_chunks = self._chunks_ahead(chunk, per_pixel)
        wall0 = time.perf_counter()
        last_report = wall0
        next_info = self.t0
        info_subs = 0
        t = self.t0
        self._publish_tf_static(self.t0)
        while t < self.t1 and self.ok():
            t_ahead = min(t + ahead_chunks * chunk, self.t1)
            self._apply_live(t)
            # a moving camera's image travel: the guard's bound, and per pixel where anything can change
            if per_pixel and moving:
                self._plan_poses(t, t_ahead, p["min_step_ns"])
            travel = self._field_travel(t, t_ahead) if guard or (per_pixel and moving) else None
            # top pieces no longer than a chunk: sampled ahead, the chunks' pieces are those of one at a time
            adaptive = dict(tolerance_c=p["tolerance_c"], min_step_ns=p["min_step_ns"],
                            max_step_ns=min(p["max_step_ns"], chunk, t_ahead - t), travel_px=travel if guard else None,
                            max_travel_px=p["max_travel_px"])
            if per_pixel:
                sampled, st = simulate_pixels(self.render_pixels, t, t_ahead, self.generator, **adaptive,
                                              reach_px=None if travel is None else travel.reach)
            elif p["adaptive"]:
                sampled, st = simulate_renderer(self.render, t, t_ahead, self.generator, **adaptive, **batched)
            else:
                sampled, st = simulate_renderer(self.render, t, t_ahead, self.generator, mode="fixed",
                                                rate_hz=p["render_rate_hz"])
            rep.render_seconds += st.render_seconds
            rep.renders += st.renders
            rep.render_calls += st.render_calls
            rep.pixels_rendered += st.pixels_rendered
            rep.frames_fed += st.frames_fed
            # the events of (t, t_ahead], sorted by time, published one chunk after the other
            ends = np.arange(t + chunk, t_ahead + chunk, chunk).clip(max=t_ahead)
            cuts = np.searchsorted(sampled["t"], ends, side="right")
            for tb, first, last in zip(ends.tolist(), [0, *cuts[:-1].tolist()], cuts.tolist()):
                if not self.ok():
                    break
                self._publish_tf_clock(t)
                subs = self.info_pub.subscribers()
                if t >= next_info or subs > info_subs:     # periodically, and at once for a new subscriber
                    self._camera_info(t)
                    next_info = t + info_every
                info_subs = subs
                events = sampled[first:last]
                if evt and events.size:
                    events = quantize_to_us(events, time_base_ns=self.t0)
                if factor > 0:
                    ahead = wall0 + (tb - self.t0) / NS / factor - time.perf_counter()
                    if -ahead > max(LATE_WARN_S, 2 * chunk / NS / factor) and not rep.fell_behind:
                        rep.fell_behind = True
                        self.logger.warn(f"falling behind real time x{factor:g} by {-ahead:.2f} s at t = "
                                         f"{(tb - self.t0) / NS:.3f} s: {self._speed_hint(moving)}")
                    self.sleep(ahead)
                if on_events is not None:
                    on_events(events)
                rep.messages += encoder.write_events(self.events_pub.topic, events, width=self.camera.width,
                                                     height=self.camera.height, encoding=p["encoding"],
                                                     packet_ns=p["packet_ns"], frame_id=p["frame_id"])
                rep.events += int(events.size)
                t = tb
                rep.sim_seconds = (t - self.t0) / NS
                now = time.perf_counter()
                if now - last_report > 2.0:
                    self.check_qos()
                    last_report = now
                    self.logger.info(f"t = {rep.sim_seconds:.3f} s, {rep.events} events, real-time factor "
                                     f"{rep.sim_seconds / (now - wall0):.3g}")
        rep.wall_seconds = time.perf_counter() - wall0
        rep.interrupted = t < self.t1
        rep.rtf = rep.sim_seconds / rep.wall_seconds if rep.wall_seconds > 0 else float("inf")
        rep.bytes = self.events_pub.bytes
        rep.rays_total = self.source.rays_total
        rep.rays_rendered = self.source.rays_rendered
        rep.samples_total = int(getattr(self.source, "samples_total", 0))
        rep.samples_evaluated = int(getattr(self.source, "samples_evaluated", 0))
        rep.topics = {pub.topic: pub.messages for pub in self.publishers.values()}
        self.check_qos()
        self.logger.info(f"{'stopped' if rep.interrupted else 'done'}: {rep.sim_seconds:.3f} s of events in "
                         f"{rep.wall_seconds:.2f} s wall (real-time factor {rep.rtf:.3g}), {rep.events} events in "
                         f"{rep.messages} messages, {rep.renders} renders")
        return rep


def usage() -> str:
    lines = ["usage: event_publisher --ros-args [-p name:=value] [--params-file FILE] [-r from:=to] "
             "[-r __node:=NAME] [-r __ns:=NS] [--log-level LEVEL]", "",
             "Publishes ~/events and ~/camera_info (DDS domain ROS_DOMAIN_ID; ROS_LOCALHOST_ONLY=1 for loopback).",
             "", "parameters:"]
    for spec in PARAMETERS:
        rng = "" if spec.min is None and spec.max is None else \
            f", range [{'' if spec.min is None else f'{spec.min:g}'}, {'' if spec.max is None else f'{spec.max:g}'}]"
        lines.append(f"  {spec.name} ({spec.type_name()}, default {spec.default!r}{rng}): {spec.description}")
    return "\n".join(lines)


def run_node(argv=(), **kwargs) -> PublishReport:
    """Build, run and shut the node down (bag closed even on SIGINT / SIGTERM)."""
    node = EventPublisher(argv, **kwargs)
    node.install_signal_handlers()
    with node:
        return node.run()


def main(argv=None) -> int:
    """Console script ``event_publisher`` (what ``ros2 run rig event_publisher`` starts)."""
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] in (["-h"], ["--help"]):
        print(usage())
        return 0
    try:
        run_node(argv)
    except EvdnerfError as exc:
        print(f"event_publisher: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
