"""The renderer interface (DESIGN.md): anything that renders a linear intensity image of a
camera pose at a time can drive the event generator.

``Renderer`` is a structural protocol (``typing.Protocol``, checkable with ``isinstance``):

- ``camera``: the :class:`~evdnerf_ros.geometry.camera.PinholeCamera` it renders through;
- ``width``, ``height``: the image size in pixels (the camera's);
- ``render(T_world_cam, t_ns) -> (height, width) float32``: linear intensity (white = 1.0,
  finite, >= 0) seen from ``T_world_cam`` (4x4 float64, camera -> world, OpenCV axes) at
  scene time ``t_ns`` (an int64 number of nanoseconds; never a float);
- ``__call__`` is the same as ``render`` (a renderer is also the plain function the DESIGN
  names).

Implementations: :class:`evdnerf_ros.sim.render.SceneRenderer` (a synthetic scene, exact
ray casting) and :class:`evdnerf_ros.field.renderer.FieldRenderer` (a trained field, from
:meth:`evdnerf_ros.train.run.TrainedRun.renderer`).  The time sampler
(:func:`evdnerf_ros.sim.sampling.simulate_renderer`) takes a function of time only:
:func:`along` binds a renderer to a camera path.

This module is a leaf (it imports nothing of the toolkit but the error class), so the
simulator, the fields, evaluation and the nodes can all import it.
"""

from __future__ import annotations

from typing import Callable, Protocol, runtime_checkable

import numpy as np

from .errors import InputError


@runtime_checkable
class Renderer(Protocol):
    """Renders ``(height, width)`` float32 linear intensity at a pose and an int64-ns time."""

    camera: object
    width: int
    height: int

    def render(self, T_world_cam, t_ns: int) -> np.ndarray: ...

    def __call__(self, T_world_cam, t_ns: int) -> np.ndarray: ...


class CameraRenderer:
    """What every renderer drawing through ``self.camera`` shares: its size, and calling it
    renders.  Subclasses set ``camera`` and implement ``render``."""

    camera: object

    @property
    def width(self) -> int:
        return self.camera.width

    @property
    def height(self) -> int:
        return self.camera.height

    def __call__(self, T_world_cam, t_ns: int) -> np.ndarray:
        return self.render(T_world_cam, t_ns)


def check_renderer(renderer, what: str = "renderer") -> Renderer:
    """``renderer`` if it implements :class:`Renderer`, else an InputError saying what is missing."""
    missing = [a for a in ("camera", "width", "height", "render") if not hasattr(renderer, a)]
    if missing or not callable(getattr(renderer, "render", None)):
        raise InputError(f"{what}: {type(renderer).__name__} is not a Renderer (missing "
                         f"{', '.join(missing) or 'a callable render'}); give a SceneRenderer, "
                         "a FieldRenderer or an object with camera, width, height and "
                         "render(T_world_cam, t_ns)")
    return renderer


def along(renderer: Renderer, pose_at: Callable[[int], np.ndarray] | np.ndarray
          ) -> Callable[[int], np.ndarray]:
    """``render(t_ns)`` of ``renderer`` along a camera path: ``pose_at(t_ns)`` -> T_world_cam,
    or one fixed 4x4 pose for a static camera.  This is what the time sampler and the
    event publisher drive."""
    check_renderer(renderer)
    if callable(pose_at):
        return lambda t_ns: renderer.render(pose_at(t_ns), t_ns)
    T = np.asarray(pose_at, dtype=np.float64)
    if T.shape != (4, 4):
        raise InputError(f"a fixed camera pose must be a 4x4 matrix, got shape {T.shape}")
    return lambda t_ns: renderer.render(T, t_ns)


__all__ = ["Renderer", "along", "check_renderer"]
