"""What the event publisher renders: a synthetic scene or a trained field, both
:class:`evdnerf_ros.renderer.Renderer` s (``render(T_world_cam, t_scene_ns)`` or a call ->
(H, W) linear intensity).

Leave-out (``leave_out=True``): the synthetic renderer tests each primitive only against
the rays inside its projected bounding box (``SceneRenderer(prefilter=True)``); the field
renders only the rays that cross an occupied cell of the run's occupancy grid (or, without
a grid, the scene box) — every other pixel is the background, exactly what the full
render gives there (``field.renderer.FieldRenderer``). ``rays_rendered`` / ``rays_total``
count the saving: for the synthetic scene in ray-primitive intersection tests (done /
without leave-out: every ray against every primitive), for the field in rays.  The field's
further switches (static-camera reuse, baking) are counted in field evaluations
(``samples_evaluated`` / ``samples_total``).
"""

from __future__ import annotations

import numpy as np

from ..errors import InputError
from ..renderer import CameraRenderer
from ..geometry.camera import PinholeCamera


class SceneSource(CameraRenderer):
    """A synthetic scene (preset name, YAML path or Scene) through ``camera``, counting the
    ray-primitive tests leave-out saves."""

    kind = "scene"

    def __init__(self, scene, camera: PinholeCamera, *, supersample: int = 1, leave_out: bool = True):
        from ..sim.render import SceneRenderer
        from ..sim.scene import Scene, load_scene

        self.scene = scene if isinstance(scene, Scene) else load_scene(scene, check_cameras=False)
        self.camera = camera
        self.renderer = SceneRenderer(self.scene, camera, supersample, prefilter=leave_out)
        self.rays_total = 0

    @property
    def rays_rendered(self) -> int:
        return int(self.renderer.stats.tests)

    def render(self, T_world_cam, t_ns: int) -> np.ndarray:
        s = self.renderer.supersample
        self.rays_total += self.camera.width * self.camera.height * s * s * len(self.scene.leaves)
        return self.renderer.render(T_world_cam, t_ns)



def FieldSource(run_dir, camera: PinholeCamera, *, duration_ns: int, leave_out: bool = True,
                reuse_static: bool = True, static_world: str = "field", bake_resolution: int = 0,
                bake_times: int = 0, chunk: int = 16384, device="cpu"):
    """The trained run in ``run_dir`` (``evdnerf train`` output) as a Renderer (a
    ``FieldRenderer``, ``kind`` "field"): scene time [0, duration_ns] maps to the field's
    normalised time [0, 1] (clamped outside).  ``reuse_static``: a static camera renders the
    rays and samples outside the run's dynamic region once; ``static_world``: what rays see
    outside that region (``field``: the trained static field and background; ``flat``: one
    constant grey, only rays through the region traced); ``bake_resolution`` > 0: play back
    the field baked into a grid (an approximation, see ``field.baked``); ``device``: auto, cpu
    or cuda."""
    from ..train.run import TrainedRun

    if isinstance(duration_ns, bool) or not isinstance(duration_ns, (int, np.integer)) or duration_ns <= 0:
        raise InputError(f"{run_dir}: field_duration must be > 0 s (the span the field's time 0..1 covers)")
    run = run_dir if isinstance(run_dir, TrainedRun) else TrainedRun.load(run_dir)
    return run.renderer(camera, duration_ns=int(duration_ns), leave_out=leave_out, reuse_static=reuse_static,
                        static_world=static_world, bake_resolution=bake_resolution, bake_times=bake_times,
                        chunk=chunk, device=device)
