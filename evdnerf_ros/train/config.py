"""Training configuration: every knob of ``evdnerf train`` in one dataclass.

Defaults live here and nowhere else.  A YAML file holds a mapping of field names to
values (any subset), read and checked with ``evdnerf_ros.yamlcheck``; an unknown key is
an error that names it.  ``field`` holds the
keyword sizes of the chosen backbone (``evdnerf_ros.field.make_field``).  Every key has a
type and a documented range (``train/ranges.py``), checked whenever a config is built
(defaults, dict, YAML file, checkpoint) and before anything is allocated; the error names
the file and the key.
"""

from __future__ import annotations

import copy
import dataclasses
from dataclasses import dataclass, field as dc_field
from pathlib import Path
from typing import Any

from ..events.logmap import LOG_EPS
from ..yamlcheck import Where, load_yaml, mapping
from .ranges import check_config

LOSSES = ("bin", "bin_paper", "mse")

#: The backbone the trainer chooses from the training set (``train/auto.py``).
AUTO = "auto"

#: Keys that may differ between a checkpoint and the resuming run (they do not change
#: the optimisation itself, only how often it is observed or saved).
RESUME_FREE_KEYS = ("eval_every", "checkpoint_every", "log_every")

#: Keys added after runs were first saved, with the value that keeps such a run what it was: a
#: saved config (a checkpoint's) that lacks one gets this value, not today's default.
ADDED_KEYS = {"backbone": "planes", "background_cells": 0, "span_fraction": 0.0, "empty_weight": 0.0, "part_empty_weight": 0.0,
              "camera_grid": False, "pixel_samples": 1, "part_box": False}

#: Options whose default depends on the backbone (None or left out: the backbone's value).
#: ``rigid``: its learned poses settle only as the learning rate decays, and its part is sampled
#: finer (Jet-Down 128x128, 5 min: margin closed 45 % with the plain defaults, 61 % with the
#: decay, 64 % with both); ``hinge`` settles with the decay too (the demo's fork set: moving
#: camera -20 % against -40 %); ``planes`` is better without it (docs/results.md).
#: ``hinge`` keeps its part sparse (``part_empty_weight``; the demo's fork set: moving camera
#: -0.1 % against -27 %, validation 18.6 against 16.4 %; 3 and more empty the part within the
#: demo's 2 minutes).
#: ``hinge`` bounds its part to the slab along the joint that can hold it where the training
#: views' pixels are finer than the scene box's cells (``part_box: auto``; the demo's 96x72 fork
#: set, four seeds: validation x1 and x4 and the moving camera higher on every seed; the virtual
#: rig's 48x36 set, two seeds: 1-3 points lower pooled).
PLAIN_DEFAULTS = {"n_samples": 48, "lr_final": 1.0, "part_empty_weight": 0.0, "part_box": False}
BACKBONE_DEFAULTS = {"rigid": {"n_samples": 64, "lr_final": 0.1},
                     "hinge": {"lr_final": 0.1, "part_empty_weight": 1.0, "part_box": "auto"}}


def backbone_defaults(backbone) -> dict:
    """The backbone-dependent options' defaults for ``backbone`` (None for ``auto``: they wait
    for the choice)."""
    if backbone == AUTO:
        return dict.fromkeys(PLAIN_DEFAULTS)
    return {**PLAIN_DEFAULTS, **BACKBONE_DEFAULTS.get(backbone if isinstance(backbone, str) else "", {})}

#: A config file larger than this is not a config (a training set passed by mistake?).
MAX_CONFIG_BYTES = 1 << 20


@dataclass
class TrainConfig:
    # ---- model
    backbone: str = AUTO
    """Field backbone: ``auto`` (default: the trainer chooses ``hinge``, ``rigid`` or ``planes``
    from the training set, logs why and records the choice; ``train/auto.py``), ``planes``
    (K-Planes style), ``dnerf`` (the paper's MLPs),
    ``hinge`` (a static world and one rigid part on the rig's joint, recorded in the training
    set: ``field.joint``) or ``rigid`` (a static world and one rigid part whose pose is learned,
    starting from the events' per-time visual hulls: ``field.track``)."""
    field: dict = dc_field(default_factory=dict)
    """Keyword sizes for the backbone (e.g. ``{resolutions: [16, 32], features: 8}``)."""

    # ---- rendering
    n_samples: int | None = None
    """Samples per ray inside the scene box (stratified during training); None: the
    backbone's (48; ``rigid`` 64)."""
    pixel_samples: int = 1
    """Rays per pixel side: a pixel's brightness is the mean of its ``pixel_samples`` x
    ``pixel_samples`` sub-pixel rays' (the light its area gathers, as the simulator renders
    it), in training, evaluation and publishing alike; 1: one ray through its centre."""
    box: list | None = None
    """Scene box [[xmin, ymin, zmin], [xmax, ymax, zmax]] in metres; None: the training
    set's ``scene_bounds`` if present, else a cube around the views' common look-at point
    of half-size ``box_fraction`` x the mean camera distance."""
    box_fraction: float = 0.35
    near: float = 0.0
    """Near clip (metres along the ray)."""
    far: float = 1e9
    """Far clip (metres along the ray)."""
    background: float = 0.25
    """Grey of rays that leave the box unoccluded (linear intensity); with
    ``background_cells`` the learned background's starting grey (then in (0, 1))."""
    background_cells: int = 512
    """Azimuth cells of a learned background (``field.BackgroundMap``: grey per ray
    direction, an environment at infinity such as a simulated scene's backdrop or a far
    wall; elevation gets half as many; 512: about one cell per pixel of a 64-pixel, 40
    degree view); 0 keeps the constant ``background``.  Jet-Down 64x64 proxy, 500
    iterations: margin closed at 32 windows -1.1 % with it, -6.5 % with a constant 0.25;
    with spans 11.8 % against 9.2 %."""
    perturb: bool = True
    """Stratified (random) sample positions within each bin while training."""
    occupancy_resolution: int = 0
    """Cells per side of an occupancy grid for empty-space skipping during training
    (``field.OccupancyGrid``, max density over time); 0 disables."""
    occupancy_every: int = 100
    """Iterations between occupancy-grid updates (the first after ``occupancy_warmup``)."""
    occupancy_warmup: int = 200
    occupancy_threshold: float = 0.01
    """Density (per metre) below which a cell counts as empty (the grid is dilated by one cell)."""
    dynamic_region: bool = True
    """Carve the region where the scene may change from the static training views' event
    footprints (``field.DynamicRegion``); outside it the field is static and rays that
    cross no dynamic voxel are skipped (their change is exactly zero)."""
    dynamic_resolution: int = 64
    """Voxels per side of the dynamic region."""
    dynamic_min_events: int = 1
    """Events a pixel needs over the whole sequence to count in a view's footprint."""
    dynamic_dilate_px: int = 1
    """Footprint dilation in pixels (covers sub-pixel projection error)."""
    dynamic_misses: int = 0
    """Views that may see a voxel off their footprint and still keep it dynamic (occlusion)."""
    log_eps: float = LOG_EPS
    """eps of L = log(I + eps), the toolkit's one log rule (events.logmap.LOG_EPS)."""

    # ---- rays
    rays: int = 1024
    """Rays per iteration."""
    event_ray_fraction: float = 0.5
    """Share of the rays through pixels with events in the sampled window (the rest are
    uniform over the image; a view with no events there falls back to uniform)."""

    crop_warmup_iters: int = 0
    """For this many first iterations the uniform rays come from a centred crop around
    each view's event centroid (paper: 2k iterations, 50% crop); 0 disables."""
    crop_fraction: float = 0.5
    """Side of that crop as a fraction of the image side."""

    # ---- windows: varied batching and time curriculum
    windows: list = dc_field(default_factory=lambda: [32, 64, 128])
    """Number of equal windows the sequence is cut into, per phase (paper: 32 -> 64 -> 128)."""
    window_switch: list = dc_field(default_factory=lambda: [0.5, 0.75])
    """Fractions of the run at which the next entry of ``windows`` takes over
    (len(windows) - 1 increasing values in (0, 1); paper: 100k/200k, 150k/200k)."""
    span_fraction: float = 0.5
    """Share of batches drawn over a span of consecutive windows (a uniform pair of distinct
    window edges among the usable ones) instead of one window: the span's summed events give
    the log change between two distant times, a frame-like comparison that single short
    windows only build up step by step (``train/rays.py``).  Jet-Down 64x64 proxy, 500
    iterations, with the background map: margin closed at 32 / 128 windows 11.8 / 8.0 % with
    0.5, -1.1 / -3.6 % with 0; 0.8 gave 12.9 / 6.8 %."""
    time_curriculum: float = 0.1
    """Fraction of the run over which the usable windows grow from the first
    ``time_curriculum_min`` to all of them (paper: 20k of 200k); 0 disables."""
    time_curriculum_min: int = 3

    # ---- loss
    supervision: str = "events"
    """``events`` (EvDNeRF) or ``frames``: fit the blurred grey frames instead, each rendered
    at its mid-exposure time with an MSE on linear intensity (the paper's DNeRF-on-blurred-
    frames baseline; windows, event rays and event losses are then unused)."""
    loss: str = "mse"
    """``bin``: dead zone on the quantisation bin of the GT change, polarity-aware
    (positive: [dL, dL+C+), negative: (dL-C-, dL], none: (-C-, C+)), squared distance to
    the bin centre outside it; ``bin_paper``: the paper code's [dL, dL+C) for every sign;
    ``mse``: mean((dL_hat/mse_pred_scale - dL/mse_target_scale)^2) (paper code: 2.2 and
    max|E_train|).  ``mse`` is the default: the protocol scores the continuous dL_hat, and
    the squared error is minimised by the mean change, which the bin losses do not seek
    (tiny fork set, 600 iterations: validation 27.2 dB with mse vs 25.0 with bin)."""
    mse_pred_scale: float = 1.0
    mse_target_scale: float = 1.0
    no_event_weight: float = 0.0
    """Weight of E-NeRF's hinge relu(|dL_hat| - C) on rays whose pixel had no events."""
    tv_weight: float = 0.0
    """Total variation on the space planes (``planes`` only)."""
    time_smooth_weight: float = 0.0
    """Second-difference smoothness along time of the time planes (``planes`` only)."""
    time_l1_weight: float = 0.0
    """L1 of (time planes - 1) (``planes`` only; 1 means static)."""
    empty_weight: float = 0.0
    """Weight of a sparsity prior: the mean opacity of one sample's length at ``empty_points``
    uniform random points of the box (static field).  Events never ask for density where
    nothing is seen to change, so without it the field keeps its initial fog everywhere.
    Off by default: on the Jet-Down 64x64 proxy (500 iterations) 0.1 raised the margin closed
    at 32 / 128 windows from 11.8 / 8.0 % to 15.1 / 11.5 % (1: 15.4 / 11.7 %), but at 128x128
    in 5 minutes it matched the run without it at equal iterations (21.0 against 21.5 % at
    1000) and cost 30 % more per iteration, so it ended lower (20.5 against 24.1 %)."""
    empty_points: int = 4096
    part_empty_weight: float | None = None
    """Weight of the moving part's sparsity prior (``hinge`` and ``rigid`` only): the part's mean
    opacity over one sample's length at ``empty_points`` uniform random points of its own frame,
    each at a random time. Static training views constrain the part only along their own rays,
    so it keeps faint copies (a mirrored fork, the table near the joint) that a novel, moving
    camera sees sweep past. None: the backbone's default (``BACKBONE_DEFAULTS``)."""
    part_box: bool | str | None = None
    """``hinge`` only: the moving part's planes span only the box that can hold the part (the
    dynamic region's extent along the joint's axis, within the scene box across it;
    ``train.joint.part_box``) instead of the whole scene box, so the same planes resolve the
    part's thickness finer (the fork's tines are thinner than a cell of the scene box); the
    part is empty outside that box. Needs the dynamic region. ``auto``: on where the training
    views' pixels, at the joint, are smaller than the finest planes' cells of the scene box
    along the axis (``train.joint.part_box_pays``; finer cells than the pixels show buy
    nothing); the trainer records what it chose. None: the backbone's default (``hinge``:
    auto, else false)."""
    learn_thresholds: bool = False
    """Learn the balance of C+ and C- (their mean stays the training set's, since events fix
    log changes only up to one scale); see ``train/thresholds.py``.  Events supervision only."""
    threshold_lr: float = 1e-2
    """Adam learning rate of the threshold balance (follows the LR warm-up)."""
    sample_reuse: bool = True
    """Render both ends of a window from the same ray samples and space features (a static
    training camera's samples do not move); False renders them separately (for measuring
    the saving: twice the space work, and independent sample jitter in dL_hat)."""
    camera_grid: bool = False
    """Where the training set records that its cameras drew the scene only on a grid of frame
    times (the virtual rig's camera twin: ``provenance.truth.render_grid``), render each window
    edge as that camera saw it: the two frames around it joined linearly in log (4 renders per
    window instead of 2, sharing their samples); a set without one is unaffected.  Off by default:
    on the virtual rig's demo set (2 min, two seeds, ``bench_quality.py --rig``) it closed 14.1 / 12.5 %
    of the validation margin against 14.2 / 12.1 % at exact times, at 164 against 133 ms/it.  (Evaluation always
    renders a prediction through the recorded camera, as the true-scene reference does.)"""

    # ---- optimiser
    lr: float = 2e-2
    """Adam learning rate (planes like ~2e-2; the paper's dnerf uses 1e-4)."""
    lr_warmup_iters: int = 100
    """Linear LR warm-up from ``lr_warmup_start`` x lr over this many iterations (paper: 1k)."""
    lr_warmup_start: float = 0.1
    lr_final: float | None = None
    """Learning rate at the end of the run as a fraction of ``lr``: after the warm-up it
    decays exponentially with run progress (iterations, or training seconds with a
    ``minutes`` budget) from lr to lr_final x lr; 1 keeps it constant; None: the backbone's
    (1; ``rigid`` and ``hinge`` 0.1)."""
    grad_clip: float = 1.0
    """Max global gradient norm; 0 disables clipping."""
    max_nonfinite_steps: int = 20
    """Non-finite losses/gradients skip the step; more than this many skips stops the run."""
    seed: int = 0

    # ---- budget, logging, checkpoints
    iters: int | None = None
    """Iteration budget (the CLI's --iters wins); None with no minutes: 2000."""
    minutes: float | None = None
    """Wall-clock budget in minutes of training (the CLI's --minutes wins)."""
    eval_every: int = 100
    """Iterations between metrics.jsonl lines (and eval-hook calls)."""
    checkpoint_every: int = 500
    """Iterations between checkpoints (one is always written at the end)."""
    log_every: int = 50
    """Iterations between progress lines."""

    def __post_init__(self):
        self._backbone_defaults()
        self.validate()

    def _backbone_defaults(self, unset=()) -> None:
        """Options at None (or ``unset``: not given) take the backbone's default."""
        for key, value in backbone_defaults(self.backbone).items():
            if key in unset or getattr(self, key) is None:
                setattr(self, key, value)

    def validate(self, source: str = "training config") -> None:
        """Every key's type and documented range (``train/ranges.py``); numbers are
        normalised to int / float.  Errors name ``source`` and the key."""
        check_config(self, source)
        self.source = source           # where it came from, for later errors (not a key)

    def with_backbone(self, backbone: str, **field_keys) -> "TrainConfig":
        """A copy with ``backbone`` (the choice ``auto`` waited for) and ``field_keys`` added to
        ``field``; options left to the backbone take its defaults; checked as a whole."""
        cfg = copy.deepcopy(self)      # not dataclasses.replace: its check would name no source
        cfg.backbone, cfg.field = backbone, {**self.field, **field_keys}
        cfg._backbone_defaults()
        cfg.validate(self.source)
        return cfg

    # ---- (de)serialisation
    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict, *, source: str = "training config",
                  saved: bool = False) -> "TrainConfig":
        """``saved``: ``data`` is a trained run's own config (its checkpoint's), so keys it
        predates take their ``ADDED_KEYS`` value."""
        if data is None:
            data = {}
        if saved and isinstance(data, dict):
            data = {**ADDED_KEYS, **data}
        names = sorted(f.name for f in dataclasses.fields(cls))
        mapping(data, Where(source), allowed=names, what="a mapping of option names to values")
        cfg = cls()                     # defaults, then the given keys, checked as one
        for key, value in data.items():
            setattr(cfg, key, value)
        cfg._backbone_defaults(unset=[k for k in PLAIN_DEFAULTS if k not in data])
        cfg.validate(source)
        return cfg

    @classmethod
    def load(cls, path) -> "TrainConfig":
        """Read a YAML mapping of option names; a file that is not one (empty, not UTF-8,
        not YAML, too big) is an InputError naming it."""
        path = Path(path)
        data = load_yaml(path, what="training config (a YAML file)", max_bytes=MAX_CONFIG_BYTES,
                         empty="give at least one option (e.g. `rays: 1024`), or leave out "
                               "--config for the defaults")
        return cls.from_dict(data, source=str(path))

    def dump(self) -> str:
        import yaml
        return yaml.safe_dump(self.to_dict(), sort_keys=False)

    def diff(self, other: "TrainConfig", ignore=RESUME_FREE_KEYS + ("iters", "minutes")) -> list[str]:
        """Names of the options whose values differ (JSON-normalised)."""
        a, b = _normal(self.to_dict()), _normal(other.to_dict())
        return [k for k in a if k not in ignore and a[k] != b.get(k)]


def _normal(obj: Any):
    if isinstance(obj, dict):
        return {str(k): _normal(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_normal(v) for v in obj]
    if isinstance(obj, float) and obj.is_integer():
        return obj
    return obj


def field_from_config(cfg: TrainConfig):
    """The untrained field a config describes: its backbone and sizes, and its learned
    background when ``background_cells`` is set."""
    from ..errors import InputError
    from ..field import make_field

    if cfg.backbone == AUTO:
        raise InputError(f"{cfg.source}: backbone auto is chosen from a training set, by the trainer; "
                         "name a backbone (planes, hinge, rigid or dnerf) to build a field without one")
    return make_field(cfg.backbone, background_cells=cfg.background_cells,
                      background_grey=cfg.background, **cfg.field)


def resolve_config(config) -> TrainConfig:
    """None -> defaults; a TrainConfig -> itself; a dict -> from_dict; else a YAML path."""
    if config is None:
        return TrainConfig()
    if isinstance(config, TrainConfig):
        return config
    if isinstance(config, dict):
        return TrainConfig.from_dict(config)
    return TrainConfig.load(config)
