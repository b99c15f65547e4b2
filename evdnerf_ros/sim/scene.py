"""Synthetic dynamic scenes: dataclasses and YAML loading with validation.

A scene is a YAML mapping.  Every key is checked: an unknown key, a wrong type or a bad
value raises ``InputError`` naming the file, the key path (``objects[2].motion.keyframes[0].t_s``)
and what is allowed.  World axes are z-up, lengths in metres, angles in degrees in YAML
(radians inside), times in seconds in YAML (int64 ns inside, converted exactly through
decimal text: ``0.1`` is exactly 100000000 ns; strings such as ``"20ms"`` work too).

Limits: the file is UTF-8 YAML of at most 16 MiB, not empty; every number is finite and
within +-1e6 (metres, degrees, intensities), every time within +-1e6 s; texture scales are
>= 1e-6; a scene has at most 10,000 objects (YAML aliases count each time they are used).

Schema (``?`` = optional, with its default)::

    name?: str                          (file stem)
    description?: str
    time?: {start_s: 0, end_s: 1}       end_s > start_s
    background?: {intensity: 0.2 (> 0), texture?: TEXTURE}
                                        a background texture is a function of the ray
                                        direction; its ``scale`` is then in degrees
    lights?:
      ambient: 0.3                      > 0 (keeps every pixel strictly positive)
      directional: [{direction: [x, y, z], intensity: 0.7}]
                                        direction the light travels (towards the scene);
                                        default one light along [-0.4, 0.3, -1]
      shadows: true                     hard shadows from the directional lights
    objects: [OBJECT, ...]              at least one
    cameras?:
      ring?: {views: 18, radius: 4, elevation_deg: 20, look_at: [0, 0, 0],
              offset_deg: 0, validation_offset_deg: 10, validation_views?: views}
      intrinsics?: {width: 256, height: 256, fov_deg: 40}     (fov_deg is horizontal)

    OBJECT:
      name?: str                        unique; default the key path, e.g. "objects[1]"
      type: box | sphere | cylinder | ellipsoid | group | mesh
      box:       size: [sx, sy, sz]     full edge lengths, > 0
      sphere:    radius: r              > 0
      cylinder:  radius: r, height: h   axis = local z, centred, with caps
      ellipsoid: radii: [a, b, c]       > 0
      mesh:      path: file.obj | .ply | .glb | .stl (relative to the YAML file),
                 scale?: 1 (or [sx, sy, sz])
      group:     children: [OBJECT, ...]     (no albedo / texture)
      albedo?: 0.7                      grey reflectance in (0, 1]
      texture?: TEXTURE                 evaluated in the object's own coordinates
      pose?: {position: [0, 0, 0], rotation: ROTATION}
      motion?: {keyframes: [...]} | {hinge: {...}}      (exactly one)
        keyframes: [{t_s, position?: [x, y, z], rotation?: ROTATION}, ...]
                   strictly increasing t_s; a key given in one keyframe must be given in all
        hinge: {parent?: name, axis: [x, y, z], pivot?: [0, 0, 0],
                angle_keyframes: [{t_s, angle_deg}, ...]  |  servo: SERVO}
      children?: [...]                  groups only

    ROTATION: {euler_deg: [rx, ry, rz]} (extrinsic XYZ, R = Rz Ry Rx, as Blender's 'XYZ')
              | {quaternion: [w, x, y, z]}  | [rx, ry, rz] (euler_deg) | [w, x, y, z]
    TEXTURE:  {type: checker | stripes | noise, scale: metres (> 0), contrast?: 0.5 in [0, 1),
               seed?: 0 (noise only), axis?: x (stripes only: x | y | z)}
              | {type: image, path: FILE (.npy, or .png / .pgm / .jpg read with Pillow),
                 size: [w, h] metres (> 0), contrast?: 0.5 in [0, 1)}
              An image texture is a picture on the object's local xy plane (objects only, not
              the background): its rows run along -y and its columns along +x, centred on the
              local origin and ``size`` metres wide and high, so a thin box seen from +z shows it
              upright; grey levels in [0, 1] (8/16-bit images are scaled, colour is averaged)
              give the factor ``1 + contrast * (2 g - 1)``; outside the picture g = 0.5.  A
              library caller passes the array itself (``Texture("image", ..., image=array,
              size=(w, h))``), e.g. a calibration board.
    SERVO:    {profile: run | move, start_s?: time.start_s, start_deg?: 90, zero_deg?: start_deg,
               segments?: [[angle_deg, duration_ms], ...] (run; default the stored fork swing),
               angle_deg, duration_ms (move)}

Transforms: an object's transform in its parent frame is ``M(t) @ P`` where ``P`` is its
static ``pose`` and ``M(t)`` its motion (identity without one; the keyframe pose; or the
hinge rotation ``T(pivot) R(axis, angle(t)) T(-pivot)``).  The parent frame is the
enclosing group, or for a hinge the named ``parent`` object (default: the enclosing group,
or the world for a top-level object).  A servo hinge turns by ``servo_angle(t) - zero_deg``
with the profile of ``servo_profile.py`` (the firmware's).  Keyframes use the C1 splines of
``trajectory.py``; outside their span the pose is held.

Cameras must not start inside an object: every ring camera (training and validation) is
checked against every object at the keyframe times and 33 times spread over the time range.

Presets are the YAML files in ``config/scenes/`` of the package's data folder: the source
checkout's, or an install's ``share/rig`` (:func:`evdnerf_ros.share.share_dir` says which).
``load_scene(name_or_path)`` takes a preset name or a YAML path.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from decimal import Decimal, InvalidOperation
from pathlib import Path

import numpy as np

from .. import yamlcheck as yc
from ..errors import InputError
from ..yamlcheck import Where
from . import geometry as geo
from ..geometry.camera import CameraRing, CameraSetup, PinholeCamera
from ..geometry.servo_profile import DEFAULT_RUN, RunProfile, move_profile
from ..geometry.poses import rigid
from ..geometry.rotations import quat_from_euler_deg, quat_normalize, quat_to_matrix
from ..geometry.trajectory import HingeMotion, KeyframeTrajectory, angle_keyframes

#: Largest magnitude of any number in a scene file (metres, degrees, intensities): far
#: beyond any real rig, and small enough that products and float64 texture lookups stay exact.
MAX_MAGNITUDE = 1e6
#: Scene times (time.*, keyframes, servo start) lie within +-1e6 s (int64 ns holds 292 years).
MAX_TIME_NS = 1_000_000 * 1_000_000_000
#: Objects per scene (groups and parts together, YAML aliases counted each time).
MAX_OBJECTS = 10_000
#: Largest scene file read (bytes).
MAX_SCENE_BYTES = 16 << 20
OBJECT_TYPES = ("box", "sphere", "cylinder", "ellipsoid", "group", "mesh")
TEXTURE_TYPES = ("checker", "stripes", "noise", "image")
#: Largest image texture (pixels per side).
MAX_TEXTURE_SIDE = 16384


# ----------------------------------------------------------------------------- dataclasses

@dataclass(frozen=True)
class Texture:
    kind: str                  # checker | stripes | noise
    scale: float               # metres (objects) or radians (background)
    contrast: float = 0.5
    seed: int = 0
    axis: int = 0              # stripes: 0, 1, 2 = x, y, z
    #: image textures: (rows, cols) float64 grey levels in [0, 1], and its (width, height) in metres
    image: np.ndarray | None = field(default=None, compare=False, repr=False)
    size: tuple = (0.0, 0.0)

    def __post_init__(self):
        if self.kind == "image":
            img = np.asarray(self.image, dtype=np.float64) if self.image is not None else None
            if img is None or img.ndim != 2 or min(img.shape) < 1 \
                    or max(img.shape) > MAX_TEXTURE_SIDE or not np.all(np.isfinite(img)) \
                    or img.min() < 0 or img.max() > 1:
                raise InputError("an image texture needs a 2-D array of grey levels in [0, 1] "
                                 f"(at most {MAX_TEXTURE_SIDE} pixels a side)")
            w, h = (float(x) for x in self.size)
            if not (np.isfinite(w) and np.isfinite(h) and w > 0 and h > 0):
                raise InputError(f"an image texture needs a size [w, h] > 0 in metres, got {self.size}")
            img = img.copy()
            img.setflags(write=False)
            object.__setattr__(self, "image", img)
            object.__setattr__(self, "size", (w, h))


@dataclass(frozen=True)
class Background:
    intensity: float = 0.2
    texture: Texture | None = None


@dataclass(frozen=True)
class DirectionalLight:
    direction: np.ndarray      # unit vector: the direction the light travels
    intensity: float


@dataclass(frozen=True)
class Lights:
    ambient: float = 0.3
    directional: tuple[DirectionalLight, ...] = ()
    shadows: bool = True


@dataclass(frozen=True)
class ServoDrive:
    profile: RunProfile
    start_ns: int
    zero_deg: float

    def angle_rad(self, t_ns: int) -> float:
        deg = self.profile.angle_deg(int(t_ns) - self.start_ns)
        return math.radians(deg - self.zero_deg)


@dataclass
class SceneObject:
    name: str
    type: str
    key_path: str
    shape: geo.Primitive | None = None          # None for groups
    albedo: float = 0.7
    texture: Texture | None = None
    pose: np.ndarray = field(default_factory=lambda: np.eye(4))
    motion: KeyframeTrajectory | HingeMotion | None = None
    parent: str | None = None
    children: list["SceneObject"] = field(default_factory=list)
    servo: ServoDrive | None = None

    def local_transform(self, t_ns: int) -> np.ndarray:
        """Transform in the parent frame at t_ns: M(t) @ pose."""
        if self.motion is None:
            return self.pose
        return self.motion(t_ns) @ self.pose

    def motion_span_ns(self) -> tuple[int, int] | None:
        if self.motion is None:
            return None
        if isinstance(self.motion, KeyframeTrajectory):
            return self.motion.span_ns if self.motion.times_ns.size > 1 else None
        return self.motion.span_ns


@dataclass
class Scene:
    name: str
    source: str
    start_ns: int
    end_ns: int
    objects: list[SceneObject]
    background: Background = field(default_factory=Background)
    lights: Lights = field(default_factory=Lights)
    cameras: CameraSetup = field(default_factory=CameraSetup)
    description: str = ""

    def __post_init__(self):
        self._by_name = {o.name: o for o in self.all_objects()}
        self._leaves = [o for o in self.all_objects() if o.shape is not None]

    # structure ---------------------------------------------------------------------
    def all_objects(self) -> list[SceneObject]:
        out = []

        def walk(objs):
            for o in objs:
                out.append(o)
                walk(o.children)
        walk(self.objects)
        return out

    @property
    def leaves(self) -> list[SceneObject]:
        """Renderable objects (everything but groups), in a fixed order."""
        return self._leaves

    def object(self, name: str) -> SceneObject:
        try:
            return self._by_name[name]
        except KeyError:
            raise InputError(f"{self.source}: no object named {name!r}; objects: "
                             f"{', '.join(self._by_name)}") from None

    # time ----------------------------------------------------------------------------
    @property
    def duration_ns(self) -> int:
        return self.end_ns - self.start_ns

    def motion_span_ns(self) -> tuple[int, int] | None:
        """[first, last] ns in which anything can move; None for a static scene."""
        spans = [s for o in self.all_objects() if (s := o.motion_span_ns()) is not None]
        if not spans:
            return None
        return min(s[0] for s in spans), max(s[1] for s in spans)

    def motion_knots_ns(self) -> list[int]:
        """Times where a motion may turn: keyframe times and servo segment boundaries."""
        knots: set[int] = set()
        for o in self.all_objects():
            if o.servo is not None:
                knots.update(int(o.servo.start_ns + b) for b in o.servo.profile.boundaries_ns)
            elif isinstance(o.motion, KeyframeTrajectory):
                knots.update(int(x) for x in o.motion.times_ns)
            elif isinstance(o.motion, HingeMotion):
                spline = getattr(o.motion.angle_rad, "spline", None)
                if spline is not None:
                    knots.update(int(x) for x in spline.times)
                elif o.motion.span_ns is not None:
                    knots.update(o.motion.span_ns)
        return sorted(knots)

    @property
    def is_static(self) -> bool:
        return self.motion_span_ns() is None

    # poses -------------------------------------------------------------------------
    def transforms(self, t_ns: int) -> dict[str, np.ndarray]:
        """T_world_obj (4x4) of every object at int64-ns time t_ns."""
        t = int(t_ns)
        cache: dict[str, np.ndarray] = {}

        def world(o: SceneObject) -> np.ndarray:
            if o.name not in cache:
                base = np.eye(4) if o.parent is None else world(self._by_name[o.parent])
                cache[o.name] = base @ o.local_transform(t)
            return cache[o.name]
        for o in self.all_objects():
            world(o)
        return cache

    def leaf_transforms(self, t_ns: int) -> list[np.ndarray]:
        tf = self.transforms(t_ns)
        return [tf[o.name] for o in self._leaves]

    # cameras -------------------------------------------------------------------------
    @property
    def camera(self) -> PinholeCamera:
        return self.cameras.intrinsics

    def camera_poses(self, split: str = "train", views: int | None = None) -> list[np.ndarray]:
        return self.cameras.ring.poses(split, views)

    def check_cameras(self, poses=None, labels=None) -> None:
        """Raise InputError if a camera lies inside an object at some sampled time."""
        if poses is None:
            poses = self.camera_poses("train") + self.camera_poses("val")
            n = self.cameras.ring.views
            labels = [f"training view {k}" for k in range(n)] + [
                f"validation view {k}" for k in range(len(poses) - n)]
        labels = labels or [f"camera {k}" for k in range(len(poses))]
        centres = np.stack([np.asarray(T)[:3, 3] for T in poses])
        times = set(np.linspace(self.start_ns, self.end_ns, 33).astype(np.int64).tolist())
        for o in self.all_objects():
            if isinstance(o.motion, KeyframeTrajectory):
                times.update(int(x) for x in o.motion.times_ns)
        for t in sorted(times):
            for o, T in zip(self._leaves, self.leaf_transforms(t)):
                local = (centres - T[:3, 3]) @ T[:3, :3]
                inside = o.shape.contains(local)
                if np.any(inside):
                    k = int(np.nonzero(inside)[0][0])
                    c = centres[k]
                    raise InputError(
                        f"{self.source}: cameras: {labels[k]} at ({c[0]:.3f}, {c[1]:.3f}, "
                        f"{c[2]:.3f}) m is inside object {o.name!r} ({o.key_path}) at "
                        f"t = {t / 1e9:.6f} s; move the object or enlarge cameras.ring.radius")


# ----------------------------------------------------------------------------- validation

class _SceneChecker:
    """The scene's checks, bound to one source file: key paths written out as text
    (``objects[2].motion``), every check and message from ``evdnerf_ros.yamlcheck``."""

    def __init__(self, source: str, base_dir: Path | None):
        self.source = source
        self.base_dir = base_dir
        self.top = Where(source)

    def at(self, path: str) -> Where:
        return self.top.at(path)

    def fail(self, path: str, msg: str):
        self.at(path).fail(msg)

    def mapping(self, path, value, allowed, required=()) -> dict:
        return yc.mapping(value, self.at(path), allowed=allowed, required=required)

    def seq(self, path, value, min_len=0) -> list:
        return yc.sequence(value, self.at(path), min_len=min_len)

    def number(self, path, value, *, lo=None, hi=None, lo_open=False, hi_open=False) -> float:
        where = self.at(path)
        x = float(yc.number(value, where, low=lo, high=hi, low_open=lo_open, high_open=hi_open))
        if abs(x) > MAX_MAGNITUDE:
            where.fail(f"must be within +-{MAX_MAGNITUDE:g} (metres, degrees, intensity), got {value!r}")
        return x

    def integer(self, path, value, *, lo=None, hi=None) -> int:
        return yc.number(value, self.at(path), low=lo, high=hi, integer=True)

    def vec(self, path, value, n=3, *, positive=False, nonzero=False) -> np.ndarray:
        if not isinstance(value, list) or len(value) != n:
            self.fail(path, f"expected a list of {n} numbers, got {yc.show(value)}")
        v = np.array([self.number(f"{path}[{i}]", x, lo=0.0 if positive else None,
                                  lo_open=positive) for i, x in enumerate(value)])
        if nonzero and not np.linalg.norm(v) > 0:
            self.fail(path, "must not be the zero vector")
        return v

    def choice(self, path, value, allowed) -> str:
        return yc.choice(value, self.at(path), allowed)

    def string(self, path, value) -> str:
        return yc.text(value, self.at(path))

    def boolean(self, path, value) -> bool:
        return yc.boolean(value, self.at(path))

    def time_ns(self, path, value) -> int:
        """Seconds (number) or a string with a unit (s, ms, us, ns) -> int64 ns, exactly."""
        if isinstance(value, bool) or not isinstance(value, (int, float, str)):
            self.fail(path, f"expected a time in seconds, got {value!r}")
        text = str(value).strip()
        unit = 1_000_000_000
        for suffix, mult in (("ns", 1), ("us", 1_000), ("ms", 1_000_000), ("s", 1_000_000_000)):
            if isinstance(value, str) and text.endswith(suffix):
                text, unit = text[: -len(suffix)].strip(), mult
                break
        try:
            x = Decimal(text)
        except InvalidOperation:
            self.fail(path, f"cannot read {value!r} as a time; write seconds (0.25) or "
                            "'250ms', '250000us', '250000000ns'")
        if not x.is_finite():
            self.fail(path, f"must be finite, got {value!r}")
        ns = x * unit
        if abs(ns) > MAX_TIME_NS:
            self.fail(path, f"must be within +-{MAX_TIME_NS // 1_000_000_000} s, got {value!r}")
        if ns != ns.to_integral_value():
            self.fail(path, f"{value!r} is not a whole number of nanoseconds")
        return int(ns)

    def rotation(self, path, value) -> np.ndarray:
        if isinstance(value, list):
            if len(value) == 3:
                return quat_from_euler_deg(self.vec(path, value, 3))
            if len(value) == 4:
                return self._quat(path, value)
            self.fail(path, f"a rotation list has 3 entries (euler_deg) or 4 (quaternion "
                            f"w, x, y, z), got {len(value)}")
        m = self.mapping(path, value, ("euler_deg", "quaternion"))
        if len(m) != 1:
            self.fail(path, "give exactly one of euler_deg, quaternion")
        if "euler_deg" in m:
            return quat_from_euler_deg(self.vec(_join(path, "euler_deg"), m["euler_deg"], 3))
        return self._quat(_join(path, "quaternion"), m["quaternion"])

    def _quat(self, path, value) -> np.ndarray:
        q = self.vec(path, value, 4)
        if not np.linalg.norm(q) > 1e-9:
            self.fail(path, "quaternion must not be zero")
        return quat_normalize(q)


def _join(path: str, key: str) -> str:
    return f"{path}.{key}" if path else key


# ----------------------------------------------------------------------------- loading

def preset_dir() -> Path:
    """The folder of the preset scenes (``config/scenes`` of the package's data folder)."""
    from ..share import share_dir

    try:
        return share_dir() / "config" / "scenes"
    except FileNotFoundError as exc:
        raise InputError(f"scene presets not found: {exc}") from None


def list_presets() -> list[str]:
    """Names of the preset scenes (YAML files in the presets folder)."""
    return sorted(p.stem for p in preset_dir().glob("*.yaml"))


def preset_path(name: str) -> Path:
    p = preset_dir() / f"{name}.yaml"
    if p.is_file():
        return p
    raise InputError(f"unknown scene preset {name!r}; presets in {preset_dir()}: {', '.join(list_presets())} "
                     "(or give the path of a scene YAML file)")


def load_scene(name_or_path, *, check_cameras: bool = True) -> Scene:
    """Load a preset by name (``jet-down``) or a scene YAML file by path."""
    text = str(name_or_path)
    p = Path(text)
    if p.is_file():
        return load_scene_file(p, check_cameras=check_cameras)
    if p.suffix.lower() in (".yaml", ".yml") or "/" in text:
        raise InputError(f"{text}: scene file not found")
    return load_scene_file(preset_path(text), check_cameras=check_cameras)


def load_scene_file(path, *, check_cameras: bool = True) -> Scene:
    path = Path(path)
    data = yc.load_yaml(path, what="scene file", max_bytes=MAX_SCENE_BYTES,
                        empty="a scene needs at least an 'objects' list (see config/scenes/*.yaml)")
    return scene_from_dict(data, source=str(path), base_dir=path.parent,
                           default_name=path.stem, check_cameras=check_cameras)


def scene_from_dict(data, *, source: str = "<scene>", base_dir=None, default_name="scene",
                    check_cameras: bool = True) -> Scene:
    """Build and validate a Scene from already-parsed YAML data."""
    v = _SceneChecker(source, Path(base_dir) if base_dir is not None else None)
    top = v.mapping("", data, ("name", "description", "time", "background", "lights",
                               "objects", "cameras"), required=("objects",))
    name = v.string("name", top["name"]) if "name" in top else default_name
    desc = top.get("description", "")
    if not isinstance(desc, str):
        v.fail("description", f"must be a string, got {yc.a_type(desc)}")

    start_ns, end_ns = 0, 1_000_000_000
    if "time" in top:
        tm = v.mapping("time", top["time"], ("start_s", "end_s"), required=("start_s", "end_s"))
        start_ns = v.time_ns("time.start_s", tm["start_s"])
        end_ns = v.time_ns("time.end_s", tm["end_s"])
        if end_ns <= start_ns:
            v.fail("time.end_s", f"must be after time.start_s ({tm['start_s']}), got "
                                 f"{tm['end_s']}")

    background = Background()
    if "background" in top:
        b = v.mapping("background", top["background"], ("intensity", "texture"))
        tex = None
        if "texture" in b:
            tex = _texture(v, "background.texture", b["texture"])
            if tex.kind == "image":
                v.fail("background.texture.type", "an image texture goes on an object (a thin "
                                                  "box), not on the background")
            tex = Texture(tex.kind, math.radians(tex.scale), tex.contrast, tex.seed, tex.axis)
        background = Background(
            v.number("background.intensity", b.get("intensity", 0.2), lo=0.0, lo_open=True),
            tex)

    lights = Lights(0.3, (DirectionalLight(_unit([-0.4, 0.3, -1.0]), 0.7),), True)
    if "lights" in top:
        lt = v.mapping("lights", top["lights"], ("ambient", "directional", "shadows"))
        dirs = lights.directional
        if "directional" in lt:
            dirs = []
            for i, d in enumerate(v.seq("lights.directional", lt["directional"])):
                p = f"lights.directional[{i}]"
                m = v.mapping(p, d, ("direction", "intensity"), required=("direction",))
                dirs.append(DirectionalLight(
                    _unit(v.vec(_join(p, "direction"), m["direction"], nonzero=True)),
                    v.number(_join(p, "intensity"), m.get("intensity", 0.7), lo=0.0)))
        lights = Lights(
            v.number("lights.ambient", lt.get("ambient", 0.3), lo=0.0, lo_open=True),
            tuple(dirs),
            v.boolean("lights.shadows", lt.get("shadows", True)))

    cameras = CameraSetup()
    if "cameras" in top:
        cameras = _cameras(v, top["cameras"])

    objs = v.seq("objects", top["objects"], min_len=1)
    names: dict[str, str] = {}
    objects = [_object(v, f"objects[{i}]", o, None, start_ns, names) for i, o in enumerate(objs)]
    scene = Scene(name=name, source=source, start_ns=start_ns, end_ns=end_ns, objects=objects,
                  background=background, lights=lights, cameras=cameras, description=desc)
    _check_parents(v, scene)
    if check_cameras:
        scene.check_cameras()
    return scene


def _unit(x) -> np.ndarray:
    x = np.asarray(x, dtype=np.float64)
    return x / np.linalg.norm(x)


def _cameras(v: _SceneChecker, data) -> CameraSetup:
    c = v.mapping("cameras", data, ("ring", "intrinsics"))
    ring = CameraRing()
    if "ring" in c:
        r = v.mapping("cameras.ring", c["ring"], ("views", "radius", "elevation_deg", "look_at",
                                                  "offset_deg", "validation_offset_deg",
                                                  "validation_views"))
        p = "cameras.ring"
        ring = CameraRing(
            views=v.integer(_join(p, "views"), r.get("views", 18), lo=1, hi=10000),
            radius=v.number(_join(p, "radius"), r.get("radius", 4.0), lo=0.0, lo_open=True),
            elevation_deg=v.number(_join(p, "elevation_deg"), r.get("elevation_deg", 20.0),
                                   lo=-89.0, hi=89.0, lo_open=True, hi_open=True),
            look_at=tuple(v.vec(_join(p, "look_at"), r.get("look_at", [0.0, 0.0, 0.0]))),
            offset_deg=v.number(_join(p, "offset_deg"), r.get("offset_deg", 0.0)),
            validation_offset_deg=v.number(_join(p, "validation_offset_deg"),
                                           r.get("validation_offset_deg", 10.0)),
            validation_views=(v.integer(_join(p, "validation_views"), r["validation_views"],
                                        lo=1, hi=10000) if "validation_views" in r else None))
    fov = 40.0
    intr = PinholeCamera.from_fov(256, 256, fov)
    if "intrinsics" in c:
        p = "cameras.intrinsics"
        m = v.mapping(p, c["intrinsics"], ("width", "height", "fov_deg"))
        fov = v.number(_join(p, "fov_deg"), m.get("fov_deg", 40.0), lo=0.0, hi=180.0,
                       lo_open=True, hi_open=True)
        intr = PinholeCamera.from_fov(v.integer(_join(p, "width"), m.get("width", 256), lo=1,
                                                hi=16384),
                                      v.integer(_join(p, "height"), m.get("height", 256), lo=1,
                                                hi=16384), fov)
    return CameraSetup(ring=ring, intrinsics=intr, fov_deg=fov)


def _texture(v: _SceneChecker, path, data) -> Texture:
    m = v.mapping(path, data, ("type", "scale", "contrast", "seed", "axis", "path", "size"),
                  required=("type",))
    kind = v.choice(_join(path, "type"), m["type"], TEXTURE_TYPES)
    allowed = {"checker": ("type", "scale", "contrast"),
               "stripes": ("type", "scale", "contrast", "axis"),
               "noise": ("type", "scale", "contrast", "seed"),
               "image": ("type", "path", "size", "contrast")}[kind]
    v.mapping(path, m, allowed, required=("path", "size") if kind == "image" else ("scale",))
    if kind == "image":
        size = v.vec(_join(path, "size"), m["size"], positive=True, n=2)
        image = _texture_image(v, _join(path, "path"), v.string(_join(path, "path"), m["path"]))
        return Texture("image", 1.0, v.number(_join(path, "contrast"), m.get("contrast", 0.5),
                                              lo=0.0, hi=1.0, hi_open=True),
                       image=image, size=(float(size[0]), float(size[1])))
    axis = 0
    if "axis" in m:
        axis = "xyz".index(v.choice(_join(path, "axis"), m["axis"], ("x", "y", "z")))
    return Texture(kind,
                   v.number(_join(path, "scale"), m["scale"], lo=1e-6),
                   v.number(_join(path, "contrast"), m.get("contrast", 0.5), lo=0.0, hi=1.0,
                            hi_open=True),
                   v.integer(_join(path, "seed"), m.get("seed", 0), lo=0, hi=2**31 - 1),
                   axis)


def _texture_image(v: _SceneChecker, key: str, rel: str) -> np.ndarray:
    """Grey levels in [0, 1] of an image texture file (relative to the scene file)."""
    p = Path(rel)
    if not p.is_absolute() and v.base_dir is not None:
        p = v.base_dir / p
    if not p.is_file():
        v.fail(key, f"image file {p} not found (paths are relative to the scene file)")
    try:
        if p.suffix.lower() == ".npy":
            img = np.load(p, allow_pickle=False)
        else:
            from PIL import Image

            with Image.open(p) as im:
                img = np.asarray(im)
    except ImportError:
        v.fail(key, f"{p}: reading {p.suffix} images needs Pillow (pip install pillow); or save "
                    "the picture as .npy")
    except (OSError, ValueError) as exc:
        v.fail(key, f"{p}: not a readable image ({exc}); give a .npy, .png, .pgm or .jpg")
    img = np.asarray(img)
    if img.ndim == 3:
        img = img[..., :3].mean(axis=2) if img.dtype.kind != "f" else img.mean(axis=2)
    if img.dtype.kind in "ui":
        img = img.astype(np.float64) / (65535.0 if img.max(initial=0) > 255 else 255.0)
    img = np.asarray(img, dtype=np.float64)
    if img.ndim != 2 or not np.all(np.isfinite(img)) or img.size == 0 or img.min() < 0 \
            or img.max() > 1 or max(img.shape) > MAX_TEXTURE_SIDE:
        v.fail(key, f"{p}: needs a grey (or colour) picture with levels in [0, 1] (floats) or "
                    f"8/16-bit integers, at most {MAX_TEXTURE_SIDE} pixels a side")
    return img


_COMMON = ("name", "type", "albedo", "texture", "pose", "motion")
_SHAPE_KEYS = {"box": ("size",), "sphere": ("radius",), "cylinder": ("radius", "height"),
               "ellipsoid": ("radii",), "mesh": ("path", "scale"), "group": ("children",)}


def _object(v: _SceneChecker, path: str, data, group: SceneObject | None, start_ns: int,
            names: dict[str, str]) -> SceneObject:
    if not isinstance(data, dict):
        v.fail(path, f"must be a mapping describing an object, got {yc.a_type(data)}")
    if "type" not in data:
        v.fail(path, f"missing required key 'type' (one of {', '.join(OBJECT_TYPES)})")
    kind = v.choice(_join(path, "type"), data["type"], OBJECT_TYPES)
    allowed = _COMMON + _SHAPE_KEYS[kind]
    if kind == "group":
        allowed = tuple(k for k in allowed if k not in ("albedo", "texture"))
    required = {"box": ("size",), "sphere": ("radius",), "cylinder": ("radius", "height"),
                "ellipsoid": ("radii",), "mesh": ("path",), "group": ("children",)}[kind]
    m = v.mapping(path, data, allowed, required=required)

    name = v.string(_join(path, "name"), m["name"]) if "name" in m else path
    if len(names) >= MAX_OBJECTS:
        v.fail(path, f"more than {MAX_OBJECTS} objects (YAML aliases count each time they "
                     "are used)")
    if name in names:
        v.fail(_join(path, "name"), f"duplicate object name {name!r} (also {names[name]})")
    names[name] = path

    shape = None
    if kind == "box":
        shape = geo.Box(v.vec(_join(path, "size"), m["size"], positive=True))
    elif kind == "sphere":
        shape = geo.Sphere(v.number(_join(path, "radius"), m["radius"], lo=0.0, lo_open=True))
    elif kind == "ellipsoid":
        shape = geo.Ellipsoid(v.vec(_join(path, "radii"), m["radii"], positive=True))
    elif kind == "cylinder":
        shape = geo.Cylinder(v.number(_join(path, "radius"), m["radius"], lo=0.0, lo_open=True),
                             v.number(_join(path, "height"), m["height"], lo=0.0, lo_open=True))
    elif kind == "mesh":
        rel = v.string(_join(path, "path"), m["path"])
        mp = Path(rel)
        if not mp.is_absolute() and v.base_dir is not None:
            mp = v.base_dir / mp
        scale = 1.0
        if "scale" in m:
            scale = (v.vec(_join(path, "scale"), m["scale"], positive=True)
                     if isinstance(m["scale"], list)
                     else v.number(_join(path, "scale"), m["scale"], lo=0.0, lo_open=True))
        if not mp.is_file():
            v.fail(_join(path, "path"), f"mesh file {mp} not found (paths are relative to "
                                        "the scene file)")
        shape = geo.load_mesh(mp, scale, source=f"{v.source}: {_join(path, 'path')}")

    pose = np.eye(4)
    if "pose" in m:
        pm = v.mapping(_join(path, "pose"), m["pose"], ("position", "rotation"))
        pos = v.vec(_join(path, "pose.position"), pm.get("position", [0.0, 0.0, 0.0]))
        q = v.rotation(_join(path, "pose.rotation"), pm["rotation"]) if "rotation" in pm \
            else np.array([1.0, 0.0, 0.0, 0.0])
        pose = rigid(quat_to_matrix(q), pos)

    obj = SceneObject(name=name, type=kind, key_path=path, shape=shape, pose=pose,
                      parent=group.name if group is not None else None)
    if kind != "group":
        obj.albedo = v.number(_join(path, "albedo"), m.get("albedo", 0.7), lo=0.0, hi=1.0,
                              lo_open=True)
        if "texture" in m:
            obj.texture = _texture(v, _join(path, "texture"), m["texture"])
    if "motion" in m:
        _motion(v, _join(path, "motion"), m["motion"], obj, group, start_ns)
    if kind == "group":
        kids = v.seq(_join(path, "children"), m["children"], min_len=1)
        obj.children = [_object(v, f"{path}.children[{i}]", c, obj, start_ns, names)
                        for i, c in enumerate(kids)]
    return obj


def _keyframe_times(v: _SceneChecker, path, frames) -> np.ndarray:
    times = []
    for i, f in enumerate(frames):
        times.append(v.time_ns(f"{path}[{i}].t_s", f["t_s"]))
        if i and times[-1] <= times[-2]:
            v.fail(f"{path}[{i}].t_s", f"keyframe times must be strictly increasing: "
                                       f"{f['t_s']} s does not come after {frames[i - 1]['t_s']} s")
    return np.array(times, dtype=np.int64)


def _motion(v: _SceneChecker, path, data, obj: SceneObject, group, start_ns):
    m = v.mapping(path, data, ("keyframes", "hinge"))
    if len(m) != 1:
        v.fail(path, "give exactly one of keyframes, hinge")
    if "keyframes" in m:
        kp = _join(path, "keyframes")
        frames = v.seq(kp, m["keyframes"], min_len=1)
        for i, f in enumerate(frames):
            v.mapping(f"{kp}[{i}]", f, ("t_s", "position", "rotation"), required=("t_s",))
        times = _keyframe_times(v, kp, frames)
        for key in ("position", "rotation"):
            have = [key in f for f in frames]
            if any(have) and not all(have):
                i = have.index(False)
                v.fail(f"{kp}[{i}]", f"missing {key!r}: give it in every keyframe or in none")
        pos = np.array([v.vec(f"{kp}[{i}].position", f["position"]) if "position" in f
                        else np.zeros(3) for i, f in enumerate(frames)])
        rot = np.array([v.rotation(f"{kp}[{i}].rotation", f["rotation"]) if "rotation" in f
                        else np.array([1.0, 0.0, 0.0, 0.0]) for i, f in enumerate(frames)])
        for i in range(1, len(frames)):
            if "rotation" in frames[i] and abs(float(np.dot(rot[i - 1], rot[i]))) < 1e-6:
                v.fail(f"{kp}[{i}].rotation", "turns 180 deg from the previous keyframe; the "
                                              "direction is ambiguous: add a keyframe between")
        obj.motion = KeyframeTrajectory(times, pos, rot)
        return
    hp = _join(path, "hinge")
    h = v.mapping(hp, m["hinge"], ("parent", "axis", "pivot", "angle_keyframes", "servo"),
                  required=("axis",))
    drivers = [k for k in ("angle_keyframes", "servo") if k in h]
    if len(drivers) != 1:
        v.fail(hp, "give exactly one of angle_keyframes, servo")
    if "parent" in h:
        parent = v.string(_join(hp, "parent"), h["parent"])
        if group is not None and parent != group.name:
            v.fail(_join(hp, "parent"), f"a part inside group {group.name!r} is hinged to that "
                                        f"group; parent must be {group.name!r} or left out")
        obj.parent = parent
    axis = v.vec(_join(hp, "axis"), h["axis"], nonzero=True)
    pivot = v.vec(_join(hp, "pivot"), h.get("pivot", [0.0, 0.0, 0.0]))
    if "angle_keyframes" in h:
        kp = _join(hp, "angle_keyframes")
        frames = v.seq(kp, h["angle_keyframes"], min_len=1)
        for i, f in enumerate(frames):
            v.mapping(f"{kp}[{i}]", f, ("t_s", "angle_deg"), required=("t_s", "angle_deg"))
        times = _keyframe_times(v, kp, frames)
        ang = np.radians([v.number(f"{kp}[{i}].angle_deg", f["angle_deg"])
                          for i, f in enumerate(frames)])
        span = (int(times[0]), int(times[-1])) if times.size > 1 else None
        obj.motion = HingeMotion(axis, pivot, angle_keyframes(times, ang), span)
        return
    sp = _join(hp, "servo")
    s = v.mapping(sp, h["servo"], ("profile", "start_s", "start_deg", "zero_deg", "segments",
                                   "angle_deg", "duration_ms"), required=("profile",))
    kind = v.choice(_join(sp, "profile"), s["profile"], ("run", "move"))
    allowed = ("profile", "start_s", "start_deg", "zero_deg") + (
        ("segments",) if kind == "run" else ("angle_deg", "duration_ms"))
    v.mapping(sp, s, allowed, required=("angle_deg", "duration_ms") if kind == "move" else ())
    t0 = v.time_ns(_join(sp, "start_s"), s["start_s"]) if "start_s" in s else start_ns
    a0 = v.number(_join(sp, "start_deg"), s.get("start_deg", DEFAULT_RUN.start_deg))
    try:
        if kind == "run":
            segs = DEFAULT_RUN.segments
            if "segments" in s:
                segs = []
                for i, seg in enumerate(v.seq(_join(sp, "segments"), s["segments"], min_len=1)):
                    q = f"{sp}.segments[{i}]"
                    if not isinstance(seg, list) or len(seg) != 2:
                        v.fail(q, f"expected [angle_deg, duration_ms], got {seg!r}")
                    segs.append((v.number(f"{q}[0]", seg[0]),
                                 v.integer(f"{q}[1]", seg[1], lo=1, hi=65535)))
            profile = RunProfile(a0, tuple(segs))
        else:
            profile = move_profile(a0, v.number(_join(sp, "angle_deg"), s["angle_deg"]),
                                   v.integer(_join(sp, "duration_ms"), s["duration_ms"], lo=1,
                                             hi=65535))
    except InputError as exc:
        if str(exc).startswith(v.source):
            raise
        v.fail(sp, str(exc))
    zero = v.number(_join(sp, "zero_deg"), s.get("zero_deg", a0))
    drive = ServoDrive(profile, t0, zero)
    obj.servo = drive
    obj.motion = HingeMotion(axis, pivot, drive.angle_rad, (t0, t0 + profile.duration_ns))


def _check_parents(v: _SceneChecker, scene: Scene):
    names = {o.name: o for o in scene.all_objects()}
    for o in scene.all_objects():
        if o.parent is not None and o.parent not in names:
            v.fail(_join(o.key_path, "motion.hinge.parent"),
                   f"no object named {o.parent!r}; objects: {', '.join(names)}")
    for o in scene.all_objects():
        seen = {o.name}
        p = o.parent
        while p is not None:
            if p in seen:
                v.fail(_join(o.key_path, "motion.hinge.parent"),
                       f"parent chain of {o.name!r} loops back to {p!r}")
            seen.add(p)
            p = names[p].parent
