"""A trained run folder read back: ``TrainedRun.load(RUN)``, the one loader of what
``evdnerf train -o RUN`` wrote (evaluation, the event publisher and resuming all use it).

It reads and checks ``RUN/checkpoint.pt`` (checksum, format, software version:
``train/checkpoint.py``) and gives:

- ``config``: the run's :class:`TrainConfig` (checked like any config; errors name
  ``RUN/checkpoint.pt (config)`` and the key);
- ``iteration``, ``box`` (scene box, (2, 3) float64);
- ``field``: the backbone the config describes with the trained weights, in eval mode
  (built on first use, so resuming, which only needs the state, never builds it twice);
- ``occupancy`` (:class:`OccupancyGrid` or None) and ``dynamic`` (:class:`DynamicRegion`
  or None), as the trainer last had them;
- ``thresholds``: (C+, C-) the run trained with: the learned balance if it learned one,
  else the training set's; ``time_range_ns``: the training set's [t_start, t_end] (int64
  ns), which its normalised time 0..1 spans; both None for checkpoints written before
  they were recorded;
- ``checkpoint``: the whole checked dict (optimiser and RNG states for resuming);
- ``renderer(camera, ...)``: a :class:`~evdnerf_ros.field.renderer.FieldRenderer`, the
  :class:`~evdnerf_ros.renderer.Renderer` of the field.

Every problem is one :class:`CheckpointError` (an ``InputError``) naming the run folder or
file and what to do: a missing folder, a folder without a checkpoint, a damaged checkpoint
or one whose pieces do not fit together.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from ..errors import InputError
from ..geometry.camera import PinholeCamera, common_look_at
from ..geometry.poses import check_rigid
from .checkpoint import CheckpointError, load_checkpoint
from .config import TrainConfig
from .rundir import CHECKPOINT_NAME

#: What the checkpoint of a run must hold besides its format fields.
REQUIRED_KEYS = ("iteration", "config", "field", "box")
RETRAIN = "train again into this folder (`evdnerf train TRAIN.h5 -o RUN --overwrite`)"


#: A ring of training views with a gap in azimuth wider than this is open (``TrainedRun.orbit``): a
#: turntable's half circle (a 180 degree gap) is, a ring of three or more views spread round is not.
OPEN_RING_RAD = float(np.radians(135.0))


class TrainedRun:
    """What ``evdnerf train`` left in a run folder (module docstring)."""

    def __init__(self, run_dir, checkpoint: dict, *, checkpoint_path=None):
        self.run_dir = Path(run_dir)
        self.checkpoint_path = Path(checkpoint_path or self.run_dir / CHECKPOINT_NAME)
        where = self.checkpoint_path
        data = checkpoint
        missing = [k for k in REQUIRED_KEYS if k not in data]
        if missing:
            raise CheckpointError(f"{where}: holds no {', '.join(missing)}: damaged or not written by "
                                  f"`evdnerf train`; {RETRAIN}")
        self.checkpoint = data
        self.config = TrainConfig.from_dict(data["config"], source=f"{where} (config)", saved=True)
        it = data["iteration"]
        if isinstance(it, bool) or not isinstance(it, (int, np.integer)) or it < 0:
            raise CheckpointError(f"{where}: iteration {it!r} is not a count; damaged checkpoint; {RETRAIN}")
        self.iteration = int(it)
        try:
            box = np.asarray(data["box"], np.float64)
        except (TypeError, ValueError):
            box = None
        if box is None or box.shape != (2, 3) or not np.all(np.isfinite(box)) or not np.all(box[1] > box[0]):
            raise CheckpointError(f"{where}: scene box {data['box']!r} is not [[xmin, ymin, zmin], "
                                  f"[xmax, ymax, zmax]] with max > min; damaged checkpoint; {RETRAIN}")
        self.box = box
        extra = data.get("extra") or {}
        if not isinstance(extra, dict):
            raise CheckpointError(f"{where}: its 'extra' record is a {type(extra).__name__}, not a "
                                  f"mapping; damaged checkpoint; {RETRAIN}")
        self.extra = extra
        self.occupancy = self._occupancy(extra.get("occupied"))
        self.dynamic = self._dynamic(extra.get("dynamic"))
        ts = extra.get("train_set") or {}
        self.time_range_ns = _time_range(ts.get("time_range_ns"), where)
        self.thresholds = self._thresholds(extra.get("thresholds"), ts.get("thresholds"))
        self.train_camera = self._train_camera(ts.get("camera"), where)
        self.ring = None if ts.get("ring") is None else check_rigid(ts["ring"], f"{where}: training ring")
        self._field = None

    # ------------------------------------------------------------------ loading
    @classmethod
    def load(cls, run_dir) -> "TrainedRun":
        """Read RUN/checkpoint.pt; one clear error naming RUN when anything is missing or damaged."""
        run_dir = Path(run_dir)
        if not run_dir.exists():
            raise CheckpointError(f"{run_dir}: no such run folder; give the folder "
                                  "`evdnerf train TRAIN.h5 -o RUN` wrote")
        if not run_dir.is_dir():
            raise CheckpointError(f"{run_dir}: is a file, not a run folder; give the folder "
                                  f"`evdnerf train -o RUN` wrote (it holds {CHECKPOINT_NAME})")
        path = run_dir / CHECKPOINT_NAME
        if not path.exists() and not path.is_symlink():
            raise CheckpointError(f"{run_dir}: holds no {CHECKPOINT_NAME}, so it is not a trained run "
                                  "(or training stopped before its first checkpoint); run "
                                  "`evdnerf train TRAIN.h5 -o RUN` to make one")
        if not path.is_file():
            raise CheckpointError(f"{path}: is not a regular file; {RETRAIN}")
        return cls(run_dir, load_checkpoint(path), checkpoint_path=path)

    @property
    def field(self):
        """The trained field (eval mode), built and loaded on first use."""
        if self._field is None:
            from .config import field_from_config

            cfg, where = self.config, self.checkpoint_path
            field = field_from_config(cfg)
            state = self.checkpoint["field"]
            if not isinstance(state, dict):
                raise CheckpointError(f"{where}: its field weights are a {type(state).__name__}, not a "
                                      f"state dict; damaged checkpoint; {RETRAIN}")
            try:
                field.load_state_dict(state)
            except (RuntimeError, TypeError, ValueError) as exc:
                raise CheckpointError(f"{where}: the weights do not fit the {cfg.backbone} field its "
                                      f"config describes ({' '.join(str(exc).split())[:300]}); damaged "
                                      f"checkpoint; {RETRAIN}") from None
            field.eval()
            self._field = field
        return self._field

    # ------------------------------------------------------------------ pieces
    def _grid(self, value, what: str):
        if value is None:
            return None
        if not isinstance(value, torch.Tensor) or value.dim() != 3 or min(value.shape) < 1:
            raise CheckpointError(f"{self.checkpoint_path}: its {what} is not a 3-D grid "
                                  f"({type(value).__name__}); damaged checkpoint; {RETRAIN}")
        return value.bool().clone()

    def _occupancy(self, value):
        from ..field import OccupancyGrid

        grid = self._grid(value, "occupancy grid")
        if grid is None:
            return None
        occ = OccupancyGrid(tuple(grid.shape))
        occ.occupied = grid
        return occ

    def _dynamic(self, value):
        from ..field import DynamicRegion

        grid = self._grid(value, "dynamic region")
        return None if grid is None else DynamicRegion(grid)

    def _thresholds(self, learned, of_set):
        where = self.checkpoint_path
        base = None
        if of_set is not None:
            base = _pair(of_set, where, "training-set thresholds")
        if learned is None or base is None:     # (older checkpoints: the learned balance alone
            return base                         # does not give the values)
        from .thresholds import LearnedThresholds

        th = LearnedThresholds(*base)
        try:
            th.load_state_dict(learned)
        except (RuntimeError, TypeError, ValueError, AttributeError) as exc:
            raise CheckpointError(f"{where}: learned thresholds unreadable ({exc}); damaged "
                                  f"checkpoint; {RETRAIN}") from None
        return th.values()

    # ------------------------------------------------------------------ use
    def _train_camera(self, value, where):
        if value is None:
            return None
        ok = isinstance(value, (list, tuple)) and len(value) == 6 and all(
            isinstance(v, (int, float)) and not isinstance(v, bool) and np.isfinite(v) and v > 0 for v in value[:4])
        if not ok:
            raise CheckpointError(f"{where}: training camera {value!r} is not [width, height, fx, fy, cx, cy]; "
                                  f"damaged checkpoint; {RETRAIN}")
        return PinholeCamera(int(value[0]), int(value[1]), *map(float, value[2:]))

    def orbit(self, duration_ns: int) -> tuple[np.ndarray, np.ndarray]:
        """Poses (t (M,) int64 ns from 0, T_world_cam (M, 4, 4)) going once round the training
        views in azimuth order over ``duration_ns`` and back to the first: the trajectory a run
        is published along when none is given. A ring open by more than ``OPEN_RING_RAD`` (a
        turntable's half circle) is swept along its views and back: closing it would cut straight
        across the gap, through the scene. CheckpointError for runs that did not record it."""
        if self.ring is None or len(self.ring) < 2:
            raise CheckpointError(f"{self.checkpoint_path}: records no ring of static training views (trained "
                                  "before they were recorded, or with fewer than 2); give a trajectory")
        d = self.ring[:, :3, 3] - common_look_at(self.ring)
        azimuth = np.arctan2(d[:, 1], d[:, 0])
        order = np.argsort(azimuth)
        a = azimuth[order]
        gaps = np.diff(np.r_[a, a[0] + 2.0 * np.pi])        # to each next view; the last closes the ring
        widest = int(np.argmax(gaps))
        if gaps[widest] > OPEN_RING_RAD:
            arc = np.roll(order, -(widest + 1))              # from one end of the arc to the other
            T = self.ring[np.r_[arc, arc[-2::-1]]]
        else:
            T = self.ring[np.r_[order, order[:1]]]
        t = np.linspace(0, int(duration_ns), len(T)).round().astype(np.int64)
        return t, T

    def renderer(self, camera, *, duration_ns: int | None = None, t_origin_ns: int = 0,
                 leave_out: bool = True, reuse_static: bool = True, static_world: str = "field",
                 bake_resolution: int = 0, bake_times: int = 0, chunk: int = 16384, device="cpu"):
        """The field as a Renderer through ``camera``.  Scene time ``t_origin_ns`` ..
        ``t_origin_ns + duration_ns`` spans the field's time 0..1; ``duration_ns`` None: the
        training set's span (an error for checkpoints that do not record it).  The run's
        dynamic region is applied as in training.  ``leave_out`` / ``reuse_static``: the
        renderer's savings and ``static_world`` (field or flat) what rays see outside the dynamic
        region (``field.renderer``); ``bake_resolution`` > 0 plays back the field
        baked into a grid of that many vertices per axis and ``bake_times`` frames (0: auto;
        ``field.baked``); ``device``: auto, cpu or cuda (``evdnerf_ros.device``)."""
        from ..device import resolve_device
        from ..field.renderer import FieldRenderer

        if duration_ns is None:
            if self.time_range_ns is None:
                raise InputError(f"{self.checkpoint_path}: does not record the training set's time "
                                 "span; give the span the field's time 0..1 covers (field_duration)")
            duration_ns = self.time_range_ns[1] - self.time_range_ns[0]
        cfg = self.config
        dev = resolve_device(device, f"{self.run_dir}: device")
        field = self.field.to(dev)
        if int(bake_resolution) > 0:
            from ..field.baked import BakedField

            field = BakedField.bake(field, resolution=int(bake_resolution), times=int(bake_times),
                                    dynamic=self.dynamic, keep_static=static_world != "flat", device=dev)
        return FieldRenderer(field, camera, self.box, duration_ns=duration_ns,
                             t_origin_ns=t_origin_ns, n_samples=cfg.n_samples, near=cfg.near,
                             far=cfg.far, background=cfg.background, occupancy=self.occupancy,
                             dynamic=self.dynamic, leave_out=leave_out, reuse_static=reuse_static,
                             static_world=static_world, chunk=chunk, device=dev, source=str(self.run_dir),
                             pixel_samples=cfg.pixel_samples)

    def __repr__(self) -> str:
        return (f"TrainedRun({str(self.run_dir)!r}, iteration={self.iteration}, "
                f"backbone={self.config.backbone!r})")


def train_set_record(train_set) -> dict:
    """What a checkpoint records of its training set (``extra["train_set"]``): its time span,
    thresholds and path, and its camera (size and intrinsics of the first training view) and the
    static training views' poses, so that a run can be published without the set."""
    t0, t1 = train_set.time_range
    c_pos, c_neg = train_set.thresholds
    record = {"time_range_ns": [int(t0), int(t1)], "thresholds": [float(c_pos), float(c_neg)],
              "path": str(getattr(train_set, "path", ""))}
    views = [v for v in train_set.train_views if train_set.poses(v) is None]
    if views:
        K = train_set.K(views[0])
        record["camera"] = [int(train_set.width), int(train_set.height), float(K[0, 0]), float(K[1, 1]),
                            float(K[0, 2]), float(K[1, 2])]
        record["ring"] = [train_set.pose(v).tolist() for v in views]
    return record


def _pair(value, where, what) -> tuple[float, float]:
    try:
        a, b = (float(v) for v in value)
    except (TypeError, ValueError):
        raise CheckpointError(f"{where}: its {what} {value!r} are not two numbers; damaged "
                              f"checkpoint; {RETRAIN}") from None
    if not (a > 0 and b > 0 and np.isfinite(a + b)):
        raise CheckpointError(f"{where}: its {what} {value!r} are not positive; damaged checkpoint; {RETRAIN}")
    return a, b


def _time_range(value, where):
    if value is None:
        return None
    ok = isinstance(value, (list, tuple)) and len(value) == 2 and all(
        isinstance(v, (int, np.integer)) and not isinstance(v, bool) for v in value)
    if not ok or int(value[1]) <= int(value[0]):
        raise CheckpointError(f"{where}: its training-set time range {value!r} is not two increasing "
                              f"int64 ns times; damaged checkpoint; {RETRAIN}")
    return int(value[0]), int(value[1])


__all__ = ["TrainedRun", "train_set_record", "REQUIRED_KEYS"]
