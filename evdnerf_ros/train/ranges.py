"""The documented range of every training-config key, and the memory a config will need.

``check_config`` runs when a ``TrainConfig`` is built (from defaults, a dict, a YAML file
or a checkpoint), before anything is allocated: every key must have its type and lie in
its range below, else one ``InputError`` names the source (the YAML file), the key, the
expected type or range and the value.  A number written as text (PyYAML reads ``1e-3``
as a string) is accepted when it reads as a plain decimal number.

``memory_estimates`` sizes what a config allocates for a given training set (field and
optimiser, one iteration's ray samples, the window stack, the occupancy and dynamic
grids); the trainer checks each, and their sum, against the memory budget
(``evdnerf_ros.limits.check_memory``) before building anything.

Ranges (``[a, b]`` inclusive, ``(a, b]`` excludes a; ``int`` keys take whole numbers):
"""

from __future__ import annotations

import inspect

from .. import yamlcheck as yc
from ..limits import check_memory, format_bytes
from ..yamlcheck import Where, boolean, choice, show

BIG = 10 ** 12          # iteration-like counts: far beyond any run, still finite

#: key -> (low, high, kind, low_open); kind "int" or "float"; None allowed where noted below.
NUMBERS = {
    "n_samples": (1, 16384, "int", False),
    "pixel_samples": (1, 8, "int", False),
    "box_fraction": (0.0, 100.0, "float", True),
    "near": (0.0, 1e9, "float", False),
    "far": (0.0, 1e12, "float", True),
    "background": (0.0, 1.0, "float", False),
    "background_cells": (0, 16384, "int", False),
    "occupancy_resolution": (0, 1024, "int", False),
    "occupancy_every": (1, BIG, "int", False),
    "occupancy_warmup": (0, BIG, "int", False),
    "occupancy_threshold": (0.0, 1e9, "float", False),
    "dynamic_resolution": (1, 1024, "int", False),
    "dynamic_min_events": (0, BIG, "int", False),
    "dynamic_dilate_px": (0, 1024, "int", False),
    "dynamic_misses": (0, 1_000_000, "int", False),
    "log_eps": (0.0, 10.0, "float", True),
    "rays": (1, 1 << 24, "int", False),
    "event_ray_fraction": (0.0, 1.0, "float", False),
    "crop_warmup_iters": (0, BIG, "int", False),
    "crop_fraction": (0.0, 1.0, "float", True),
    "span_fraction": (0.0, 1.0, "float", False),
    "time_curriculum": (0.0, 1.0, "float", False),
    "time_curriculum_min": (1, 1 << 20, "int", False),
    "mse_pred_scale": (0.0, 1e9, "float", True),
    "mse_target_scale": (0.0, 1e9, "float", True),
    "no_event_weight": (0.0, 1e9, "float", False),
    "tv_weight": (0.0, 1e9, "float", False),
    "time_smooth_weight": (0.0, 1e9, "float", False),
    "time_l1_weight": (0.0, 1e9, "float", False),
    "empty_weight": (0.0, 1e9, "float", False),
    "empty_points": (1, 1 << 24, "int", False),
    "part_empty_weight": (0.0, 1e9, "float", False),
    "threshold_lr": (0.0, 1e3, "float", True),
    "lr": (0.0, 1e3, "float", True),
    "lr_warmup_iters": (0, BIG, "int", False),
    "lr_warmup_start": (0.0, 1.0, "float", False),
    "lr_final": (0.0, 1.0, "float", True),
    "grad_clip": (0.0, 1e12, "float", False),
    "max_nonfinite_steps": (0, BIG, "int", False),
    "seed": (0, 2 ** 63 - 2, "int", False),
    "iters": (1, BIG, "int", False),             # or null
    "minutes": (0.0, 1e8, "float", True),        # or null
    "eval_every": (0, BIG, "int", False),
    "checkpoint_every": (0, BIG, "int", False),
    "log_every": (0, BIG, "int", False),
}
NULLABLE = ("iters", "minutes", "n_samples", "lr_final", "part_empty_weight")   # all but the first two: the backbone's default
BOOLS = ("perturb", "dynamic_region", "learn_thresholds", "sample_reuse", "camera_grid")
#: windows: 1 to MAX_PHASES counts in [1, MAX_WINDOWS]; window_switch: fractions in (0, 1).
MAX_WINDOWS = 1 << 20
MAX_PHASES = 64
#: box: corners with |coordinate| <= MAX_BOX metres.
MAX_BOX = 1e6

#: Backbone keyword sizes (the ``field`` mapping): key -> (low, high, kind) or a tuple of
#: choices; "int?" allows null.  Keys of the backbone's constructor that are not listed
#: here are passed through unchecked.
FIELD_KEYS = {
    "planes": {"resolutions": ("list", 1, 8192, 16), "time_resolution": (1, 8192, "int"),
               "features": (1, 4096, "int"), "hidden": (1, 65536, "int"),
               "hidden_layers": (0, 64, "int"), "density_activation": ("softplus", "trunc_exp"),
               "density_bias": (-1e3, 1e3, "float"), "init_range": ("pair", -1e3, 1e3),
               "seed": (0, 2 ** 63 - 1, "int?")},
    "dnerf": {"depth": (1, 64, "int"), "width": (1, 65536, "int"), "skip": (0, 64, "int?"),
              "pe_x": (0, 32, "int"), "pe_t": (0, 32, "int"),
              "canonical_depth": (1, 64, "int?"), "canonical_width": (1, 65536, "int?"),
              "density_activation": ("softplus", "sigmoid", "relu"),
              "zero_deform_at_t0": ("bool",)},
    # joint: the rig's joint (train.joint fills it from the training set; the field checks it)
    "hinge": {"resolutions": ("list", 1, 8192, 16), "features": (1, 4096, "int"), "hidden": (1, 65536, "int"),
              "hidden_layers": (0, 64, "int"), "density_activation": ("softplus", "trunc_exp"),
              "density_bias": (-1e3, 1e3, "float"), "init_range": ("pair", -1e3, 1e3),
              "seed": (0, 2 ** 63 - 1, "int?"), "shading": ("bool",),
              "static_time_resolution": (0, 8192, "int")},
}
# track: the moving part's first track (train.track fills it from the events; the field checks it)
FIELD_KEYS["rigid"] = {**FIELD_KEYS["hinge"], "pose_lr_scale": (0.0, 1e3, "float")}

def number(value, where: Where, low, high, kind: str, low_open: bool = False,
           allow_none: bool = False):
    """A number in its range (a plain decimal written as text counts: PyYAML reads ``1e-3``
    as a string), as int for ``kind`` "int", else float."""
    value = yc.number(value, where, low=low, high=high, low_open=low_open,
                      integer=kind == "int", allow_none=allow_none, text_numbers=True)
    if value is None or kind == "int":
        return value
    return float(value)


def number_list(value, where: Where, low, high, kind: str, *, low_open=False, min_len=1,
                max_len=MAX_PHASES) -> list:
    if not isinstance(value, (list, tuple)):
        where.fail(f"expected a list of numbers, got {show(value)}")
    if not min_len <= len(value) <= max_len:
        where.fail(f"expected {min_len} to {max_len} numbers, got {len(value)}")
    return [number(v, where / i, low, high, kind, low_open) for i, v in enumerate(value)]


# ---------------------------------------------------------------------- the config
def check_config(cfg, source: str = "training config") -> None:
    """Check every key of ``cfg`` (a TrainConfig) in place; normalise numbers to int/float."""
    from ..field import BACKBONES
    from .config import AUTO, LOSSES

    top = Where(source)

    def name(key):
        return top / key

    cfg.backbone = choice(cfg.backbone, name("backbone"), [AUTO, *sorted(BACKBONES)])
    cfg.supervision = choice(cfg.supervision, name("supervision"), ("events", "frames"))
    cfg.loss = choice(cfg.loss, name("loss"), LOSSES)
    for key in BOOLS:
        setattr(cfg, key, boolean(getattr(cfg, key), name(key)))
    for key, (low, high, kind, low_open) in NUMBERS.items():
        setattr(cfg, key, number(getattr(cfg, key), name(key), low, high, kind, low_open,
                                 allow_none=key in NULLABLE))
    if not cfg.far > cfg.near:
        name("far").fail(f"must be greater than near ({cfg.near}), got {cfg.far}")
    cfg.windows = number_list(cfg.windows, name("windows"), 1, MAX_WINDOWS, "int")
    cfg.window_switch = number_list(cfg.window_switch, name("window_switch"), 0.0, 1.0, "float",
                                    low_open=True, min_len=0)
    s, w = cfg.window_switch, cfg.windows
    if len(s) != len(w) - 1 or any(f >= 1.0 for f in s) or s != sorted(s):
        name("window_switch").fail(f"must hold {len(w) - 1} increasing fractions in (0, 1) (one "
                                   f"per change of windows {w}), got {s}")
    if cfg.box is not None:
        cfg.box = check_box(cfg.box, name("box"))
    if cfg.background_cells and not (0.0 < cfg.background < 1.0):
        name("background").fail(f"with background_cells the learned background starts at this "
                                f"grey, which must lie strictly between 0 and 1 (e.g. 0.25), "
                                f"got {cfg.background}")
    if cfg.background_cells and cfg.background_cells < 8:
        name("background_cells").fail(f"must be 0 (constant background) or at least 8, "
                                      f"got {cfg.background_cells}")
    if cfg.learn_thresholds and cfg.supervision != "events":
        name("learn_thresholds").fail("needs supervision: events")
    if cfg.pixel_samples > 1 and cfg.supervision != "events":
        name("pixel_samples").fail("needs supervision: events (frames are fitted one ray per pixel); set it to 1")
    if not (isinstance(cfg.part_box, bool) or cfg.part_box == "auto"
            or (cfg.part_box is None and cfg.backbone == AUTO)):
        name("part_box").fail(f"expected true, false or auto, got {show(cfg.part_box)}")
    if cfg.backbone == AUTO:
        # sizes are checked by the rule of a backbone auto may choose; what fits only one backbone
        # is checked again once the trainer has chosen it
        cfg.field = check_auto_field(cfg.field, name("field"))
        return
    from ..field.part import PartField
    if cfg.part_empty_weight and not issubclass(BACKBONES[cfg.backbone], PartField):
        name("part_empty_weight").fail(f"is the moving part's prior, and a {cfg.backbone} field has no part; "
                                       "set it to 0 or train backbone hinge or rigid")
    if cfg.part_box and cfg.backbone != "hinge":
        name("part_box").fail(f"bounds the hinge field's part by its joint, and a {cfg.backbone} field has none; "
                              "set it to false or train backbone hinge")
    if cfg.part_box is True and not (cfg.dynamic_region and cfg.supervision == "events"):
        name("part_box").fail("is cut from the dynamic region (dynamic_region: true, supervision: events); "
                              "set it to false")
    cfg.field = check_field(cfg.backbone, cfg.field, name("field"))


def check_box(box, where: Where) -> list:
    shape_ok = isinstance(box, (list, tuple)) and len(box) == 2 and all(
        isinstance(r, (list, tuple)) and len(r) == 3 for r in box)
    if not shape_ok:
        where.fail(f"expected [[xmin, ymin, zmin], [xmax, ymax, zmax]], got {show(box)}")
    lo, hi = (number_list(r, where / i, -MAX_BOX, MAX_BOX, "float", min_len=3, max_len=3)
              for i, r in enumerate(box))
    if not all(b > a for a, b in zip(lo, hi)):
        where.fail(f"each max must exceed its min, got {[lo, hi]}")
    return [lo, hi]


def check_auto_field(sizes, name: Where) -> dict:
    """``field`` sizes given with ``backbone: auto``: each a size of a backbone auto may choose,
    in that backbone's range (the ranges of a size the backbones share agree)."""
    from ..field import BACKBONES
    from .auto import CHOICES as AUTO_CHOICES

    if not isinstance(sizes, dict):
        name.fail(f"expected a mapping of the backbone's sizes, got {show(sizes)}")
    known = {b: [p for p in inspect.signature(BACKBONES[b].__init__).parameters if p != "self"]
             for b in AUTO_CHOICES}
    out = {}
    for key, value in sizes.items():
        owner = next((b for b in AUTO_CHOICES if key in known[b]), None)
        if owner is None:
            every = sorted({k for ks in known.values() for k in ks})
            (name / str(key)).fail(f"unknown size for backbone auto (which chooses {', '.join(AUTO_CHOICES)}); "
                                   f"known: {', '.join(every)}")
        out.update(check_field(owner, {key: value}, name))
    return out


def check_field(backbone: str, sizes, name: Where) -> dict:
    """The backbone's keyword sizes: known keys only, each in its range."""
    from ..field import BACKBONES

    if not isinstance(sizes, dict):
        name.fail(f"expected a mapping of {backbone} sizes, got {show(sizes)}")
    spec = FIELD_KEYS.get(backbone, {})
    known = [p for p in inspect.signature(BACKBONES[backbone].__init__).parameters
             if p != "self"]
    out = {}
    for key, value in sizes.items():
        where = name / str(key)
        if key not in known:
            where.fail(f"unknown size for backbone {backbone}; known: {', '.join(known)}")
        rule = spec.get(key)
        if rule is None:
            out[key] = value
        elif rule == ("bool",):
            out[key] = boolean(value, where)
        elif rule[0] == "list":
            out[key] = number_list(value, where, rule[1], rule[2], "int", max_len=rule[3])
        elif rule[0] == "pair":
            pair = number_list(value, where, rule[1], rule[2], "float", min_len=2, max_len=2)
            if pair[0] > pair[1]:
                where.fail(f"expected [low, high] with low <= high, got {pair}")
            out[key] = pair
        elif isinstance(rule[0], str):
            out[key] = choice(value, where, rule)
        else:
            low, high, kind = rule
            out[key] = number(value, where, low, high, kind.rstrip("?"),
                              allow_none=kind.endswith("?"))
    return out


# ---------------------------------------------------------------------- memory
def _field_sizes(cfg) -> dict:
    """The backbone's sizes with its defaults filled in."""
    from ..field import BACKBONES

    params = inspect.signature(BACKBONES[cfg.backbone].__init__).parameters
    sizes = {k: p.default for k, p in params.items() if k != "self"}
    sizes.update(cfg.field)
    return sizes


def field_parameters(cfg) -> int:
    """Number of trainable parameters of the configured field (closed form)."""
    f = _field_sizes(cfg)
    if cfg.backbone in ("planes", "hinge", "rigid"):
        res, feat = [int(r) for r in f["resolutions"]], int(f["features"])
        t = int(f["time_resolution"]) if cfg.backbone == "planes" else 0
        n = sum(3 * feat * (r * r + t * r) for r in res)
        d, hidden = feat * len(res), int(f["hidden"])
        for _ in range(int(f["hidden_layers"])):
            n += d * hidden + hidden
            d = hidden
        n += d * 2 + 2
        if cfg.backbone in ("hinge", "rigid"):
            # a static and a moving triplane, each with its head; the moving head's first layer
            # also reads the pose (hinge: cos and sin of the joint angle; rigid: the rotation)
            first = int(f["hidden"]) if int(f["hidden_layers"]) else 2
            n = 2 * n + ((2 if cfg.backbone == "hinge" else 3) * first if f["shading"] else 0)
            n += sum(3 * feat * int(f["static_time_resolution"]) * r for r in res)
        if cfg.backbone == "rigid":
            # centre and rotation at each knot of the track
            from .track import TRACK_KNOTS

            track = f["track"] if isinstance(f["track"], dict) else {}     # not known yet: the default
            n += 6 * len(track.get("centre", range(TRACK_KNOTS)))
        return n + background_parameters(cfg)
    depth, width = int(f["depth"]), int(f["width"])
    cd = depth if f["canonical_depth"] is None else int(f["canonical_depth"])
    cw = width if f["canonical_width"] is None else int(f["canonical_width"])
    dx, dt = 3 * (1 + 2 * int(f["pe_x"])), 1 + 2 * int(f["pe_t"])
    n = 2 * (dx + dt) * width + depth * (width * width + width) + 3 * width
    return n + 2 * dx * cw + cd * (cw * cw + cw) + 2 * cw + background_parameters(cfg)


def background_parameters(cfg) -> int:
    """Parameters of the learned background (``field.BackgroundMap``: two levels)."""
    from ..field.background import COARSE_FRACTION

    cells = int(cfg.background_cells)
    if not cells:
        return 0
    coarse = max(4, cells // COARSE_FRACTION)
    return (cells // 2 + 1) * cells + (coarse // 2 + 1) * coarse


def bytes_per_sample(cfg) -> int:
    """Activations kept for the backward pass per ray sample (both window ends), float32.
    Calibrated on CPU: planes (default sizes) ~5.0 KB measured, 5.6 KB estimated; dnerf
    8 x 256 ~43 KB measured, 49 KB estimated."""
    f = _field_sizes(cfg)
    if cfg.backbone in ("planes", "hinge", "rigid"):
        scales, feat = len(f["resolutions"]), int(f["features"])
        hidden = int(f["hidden"]) * max(1, int(f["hidden_layers"]))
        return 4 * (20 * scales * feat + 6 * hidden + 64)
    depth, width = int(f["depth"]), int(f["width"])
    cd = depth if f["canonical_depth"] is None else int(f["canonical_depth"])
    cw = width if f["canonical_width"] is None else int(f["canonical_width"])
    pe = 3 * (1 + 2 * int(f["pe_x"])) + 1 + 2 * int(f["pe_t"])
    return 4 * (3 * (depth * width + cd * cw) + 4 * pe + 64)


def carving_bytes(resolution: int) -> float:
    """Carving the events' footprints into ``resolution``^3 voxels (the dynamic region, the moving
    part's track): voxel centres and their projection (float64), plus the per-pixel ray march."""
    return 120.0 * resolution ** 3 + 4096 * 7 * resolution * 48.0


def memory_estimates(cfg, *, views: int, pixels: int) -> list[tuple[float, str, str]]:
    """[(bytes, what, fix)] for what ``cfg`` allocates on a set of ``views`` training views
    of ``pixels`` pixels each."""
    out = []
    n_params = field_parameters(cfg)
    # parameter, gradient, two Adam moments, the checkpoint's copy and its serialised bytes
    out.append((24.0 * n_params, f"the {cfg.backbone} field ({n_params:,} parameters, field: "
                f"{cfg.field or 'defaults'})", "lower the sizes in field"))
    sub = cfg.pixel_samples ** 2
    samples = float(cfg.rays) * sub * cfg.n_samples
    out.append((samples * bytes_per_sample(cfg),
                f"one iteration's {cfg.rays} rays x {sub} per pixel x {cfg.n_samples} samples",
                "lower rays, pixel_samples or n_samples"))
    if cfg.supervision == "events":
        per = 24 if cfg.learn_thresholds else 12     # float32 log change (+ counts) and scratch
        if cfg.span_fraction:
            per += 4                                 # the changed-window counts of spans
        n = max(cfg.windows)
        out.append((float(views) * n * pixels * per,
                    f"the window stack ({views} views x {n} windows x {pixels} pixels)",
                    "lower windows"))
        if cfg.dynamic_region:
            r = cfg.dynamic_resolution
            out.append((carving_bytes(r), f"the dynamic region ({r}^3 voxels)", "lower dynamic_resolution"))
    if cfg.occupancy_resolution:
        r = cfg.occupancy_resolution
        out.append((40.0 * r ** 3, f"the occupancy grid ({r}^3 cells)",
                    "lower occupancy_resolution"))
    return out


def check_training_memory(cfg, *, views: int, pixels: int, source: str = "training config") -> None:
    """Each allocation, then their sum, against the memory budget; the error names the key."""
    items = memory_estimates(cfg, views=views, pixels=pixels)
    for nbytes, what, fix in items:
        check_memory(nbytes, f"{source}: {what}", fix)
    total = sum(b for b, _, _ in items)
    fix = max(items)[2]                 # the largest part is the one to shrink
    parts = ", ".join(f"{what} {format_bytes(b)}" for b, what, _ in items)
    check_memory(total, f"{source}: training ({parts})", fix)


def describe_ranges() -> str:
    """The ranges as text (for the module docstring and error hints)."""
    lines = []
    for key, (low, high, kind, low_open) in NUMBERS.items():
        lo = "(" if low_open else "["
        extra = " or null" if key in NULLABLE else ""
        lines.append(f"  {key}: {kind} in {lo}{_num(low)}, {_num(high)}]{extra}")
    lines.append(f"  windows: 1-{MAX_PHASES} ints in [1, {MAX_WINDOWS}]; window_switch: "
                 "len(windows) - 1 increasing fractions in (0, 1)")
    lines.append(f"  box: null or [[xmin, ymin, zmin], [xmax, ymax, zmax]], |value| <= {MAX_BOX:g}")
    lines.append("  " + ", ".join(BOOLS) + ": true or false")
    lines.append("  part_box: true, false or auto (null: the backbone's default)")
    for backbone, spec in FIELD_KEYS.items():
        lines.append(f"  field ({backbone}): " + ", ".join(
            f"{k} {_rule_text(r)}" for k, r in spec.items()))
    return "\n".join(lines)


def _rule_text(rule) -> str:
    if rule == ("bool",):
        return "true/false"
    if rule[0] == "list":
        return f"1-{rule[3]} ints in [{rule[1]}, {rule[2]}]"
    if rule[0] == "pair":
        return f"[low, high] in [{rule[1]:g}, {rule[2]:g}]"
    if isinstance(rule[0], str):
        return "/".join(rule)
    low, high, kind = rule
    return f"{kind.rstrip('?')} in [{_num(low)}, {_num(high)}]" + (" or null" if kind.endswith("?") else "")


def _num(x) -> str:
    if isinstance(x, int):
        return f"2^63-{2 ** 63 - x}" if x > 2 ** 62 else (f"1e{len(str(x)) - 1}" if x == BIG else str(x))
    return f"{x:g}"


__doc__ += describe_ranges() + "\n"
