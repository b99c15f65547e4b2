"""The Renderer protocol: the scene renderer and the trained field both implement it, and the
time sampler / event generator take either through the same code path."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from evdnerf_ros.errors import InputError
from evdnerf_ros.geometry.camera import PinholeCamera, look_at
from evdnerf_ros.renderer import Renderer, along, check_renderer
from evdnerf_ros.sim.generator import EventGenerator
from evdnerf_ros.sim.render import SceneRenderer
from evdnerf_ros.sim.sampling import simulate_renderer
from evdnerf_ros.sim.scene import load_scene

CAM = PinholeCamera.from_fov(24, 18, 50.0)


def _field_run(tmp_path):
    """A run folder holding an untrained planes field (static in time) and its records; a black
    constant background, so the random field's fog shows with contrast to a circling camera."""
    from evdnerf_ros.train.checkpoint import save_checkpoint
    from evdnerf_ros.train.config import TrainConfig, field_from_config

    cfg = TrainConfig(backbone="planes", n_samples=16, field=dict(resolutions=[8], time_resolution=4, features=4, hidden=8),
                      background_cells=0, background=0.0)
    torch.manual_seed(3)
    field = field_from_config(cfg)
    run = tmp_path / "run"
    run.mkdir()
    save_checkpoint(run / "checkpoint.pt", field=field, optimizer=None, iteration=7,
                    config=cfg.to_dict(), backbone=cfg.backbone, rng={},
                    box=[[-1, -1, -1], [1, 1, 1]],
                    extra={"train_set": {"time_range_ns": [5_000, 1_000_005_000],
                                         "thresholds": [0.25, 0.15]}})
    return run


def _renderers(tmp_path):
    from evdnerf_ros.train.run import TrainedRun

    scene = SceneRenderer(load_scene("fork", check_cameras=False), CAM, 1)
    field = TrainedRun.load(_field_run(tmp_path)).renderer(CAM)
    return {"scene": scene, "field": field}


def _moving_pose(t_ns: int) -> np.ndarray:
    """A camera circling the origin, 3 m away (int64 ns in, 4x4 out)."""
    a = 2 * np.pi * (int(t_ns) / 1e9) * 0.2
    return look_at([3.0 * np.sin(a), -3.0 * np.cos(a), 0.8], [0.0, 0.0, 0.2])


@pytest.mark.parametrize("kind", ["scene", "field"])
def test_both_renderers_implement_the_protocol(tmp_path, kind):
    r = _renderers(tmp_path)[kind]
    assert isinstance(r, Renderer) and check_renderer(r) is r
    assert (r.width, r.height) == (CAM.width, CAM.height) and r.camera is CAM
    T = _moving_pose(0)
    img = r.render(T, 100_000_000)
    assert img.shape == (CAM.height, CAM.width) and img.dtype == np.float32
    assert np.all(np.isfinite(img)) and np.all(img >= 0) and img.max() > 0
    np.testing.assert_array_equal(r(T, 100_000_000), img)           # calling it is the same
    for bad in (0.1, 1.5, "1"):                                      # times are int64 ns only
        with pytest.raises(InputError, match="nanoseconds"):
            r.render(T, bad)
    with pytest.raises(InputError, match="T_world_cam"):
        r.render(2 * np.eye(4), 0)


def test_scene_renderer_result_and_intensity_agree():
    r = SceneRenderer(load_scene("fork", check_cameras=False), CAM, 2)
    T = _moving_pose(0)
    res = r.render_result(T, 300_000_000)
    np.testing.assert_array_equal(res.intensity, r.render(T, 300_000_000))
    assert res.depth.shape == res.mask.shape == (CAM.height, CAM.width) and res.mask.any()


@pytest.mark.parametrize("kind", ["scene", "field"])
def test_the_generator_takes_either_renderer(tmp_path, kind):
    """Fixed-rate sampling through `along` gives exactly the events of the frames rendered
    by hand at the same times and fed to the generator."""
    r = _renderers(tmp_path)[kind]
    t0, t1, rate = 0, 200_000_000, 100.0
    gen = EventGenerator(r.width, r.height, c_pos=0.1, c_neg=0.1)
    events, stats = simulate_renderer(along(r, _moving_pose), t0, t1, gen, mode="fixed", rate_hz=rate)
    times = np.arange(t0, t1 + 1, 10_000_000, dtype=np.int64)
    ref = EventGenerator(r.width, r.height, c_pos=0.1, c_neg=0.1)
    frames = np.stack([r.render(_moving_pose(int(t)), int(t)) for t in times])
    expect = ref.generate(frames, times)
    assert events.size > 100, "a circling camera must see changes"
    np.testing.assert_array_equal(events, expect)
    assert np.all(np.diff(events["t"]) >= 0) and events["t"].min() > t0 and events["t"].max() <= t1


def test_along_a_fixed_pose_and_bad_renderers():
    r = SceneRenderer(load_scene("fork", check_cameras=False), CAM, 1)
    T = _moving_pose(0)
    np.testing.assert_array_equal(along(r, T)(400_000_000), r.render(T, 400_000_000))
    with pytest.raises(InputError, match="4x4"):
        along(r, np.eye(3))
    with pytest.raises(InputError, match="not a Renderer.*render"):
        along(lambda T, t: None, T)
    assert not isinstance(object(), Renderer)


def test_field_renderer_time_mapping_and_leave_out(tmp_path):
    """Scene time maps to the field's 0..1 over the training span (clamped); leave-out
    renders fewer rays and the same image."""
    from evdnerf_ros.train.run import TrainedRun

    run = TrainedRun.load(_field_run(tmp_path))
    r = run.renderer(CAM)                                            # the training set's span
    assert r.duration_ns == 1_000_000_000
    assert r.normalized_time(500_000_000) == 0.5 and r.normalized_time(-10) == 0.0
    assert r.normalized_time(10**18) == 1.0
    shifted = run.renderer(CAM, duration_ns=2_000_000_000, t_origin_ns=10**12)
    assert shifted.normalized_time(10**12 + 500_000_000) == 0.25
    # many times at once (single-pixel batches), as one by one; float times are refused
    many = np.array([10**12 - 5, 10**12, 10**12 + 333_333_333, 10**12 + 2_000_000_000, 10**18], np.int64)
    np.testing.assert_array_equal(shifted.normalized_times(many),
                                  np.float32([shifted.normalized_time(int(t)) for t in many]))
    assert shifted.normalized_times(np.zeros(0, np.int64)).shape == (0,)
    with pytest.raises(InputError, match="int64 nanoseconds"):
        shifted.normalized_times(np.array([0.5]))
    with pytest.raises(InputError, match="positive whole number of nanoseconds"):
        run.renderer(CAM, duration_ns=0)
    full = run.renderer(CAM, leave_out=False)
    T = look_at([0.0, -4.0, 0.5], [0.0, 0.0, 0.0])
    np.testing.assert_allclose(r.render(T, 0), full.render(T, 0), rtol=0, atol=1e-6)
    assert full.rays_rendered == full.rays_total == CAM.width * CAM.height
    assert r.rays_rendered <= r.rays_total == CAM.width * CAM.height


def test_publisher_sources_are_renderers(tmp_path):
    from evdnerf_ros.nodes.sources import FieldSource, SceneSource

    scene = SceneSource("fork", CAM)
    field = FieldSource(_field_run(tmp_path), CAM, duration_ns=10**9)
    for src, kind in ((scene, "scene"), (field, "field")):
        assert isinstance(src, Renderer) and src.kind == kind
        img = src.render(_moving_pose(0), 0)
        assert img.shape == (CAM.height, CAM.width) and src.rays_total > 0
    with pytest.raises(InputError, match="field_duration"):
        FieldSource(tmp_path / "run", CAM, duration_ns=0)



def _dense_planes_field(seed):
    """A small planes field dense enough to show, changing everywhere in time."""
    from evdnerf_ros.field import make_field

    torch.manual_seed(seed)
    field = make_field("planes", resolutions=[8], time_resolution=4, features=4, hidden=8).eval()
    with torch.no_grad():
        for tp in field.time_planes:
            tp.uniform_(0.0, 3.0)
        for sp in field.space_planes:
            sp.uniform_(1.0, 3.0)
    return field


def _dense_hinge_field(seed):
    """A small hinge field dense enough to show, its part swinging half a turn over the span."""
    from evdnerf_ros.field import make_field

    torch.manual_seed(seed)
    joint = {"pivot": [0.0, 0.1, -0.2], "axis": [0.3, 0.0, 1.0], "half": [0.55, 0.55, 0.55],
             "angles_rad": [0.0, 1.0, 3.0]}
    field = make_field("hinge", joint=joint, resolutions=[8], features=4, hidden=8).eval()
    with torch.no_grad():
        for part in (field.static, field.moving):
            for sp in part.planes:
                sp.uniform_(1.0, 3.0)
    return field


def _dense_rigid_field(seed):
    """A small rigid field dense enough to show, its part falling and turning over the span."""
    from evdnerf_ros.field import make_field

    torch.manual_seed(seed)
    track = {"centre": [[0.0, 0.1, 0.6], [0.1, 0.0, -0.5]], "half": [0.55, 0.55, 0.55], "radius": 0.4}
    field = make_field("rigid", track=track, resolutions=[8], features=4, hidden=8).eval()
    with torch.no_grad():
        field.rotation.copy_(torch.tensor([[0.0, 0.0, 0.0], [0.3, 0.2, 1.0]]))
        for part in (field.static, field.moving):
            for sp in part.planes:
                sp.uniform_(1.0, 3.0)
    return field


@pytest.mark.parametrize("world", ["field", "flat"])
def test_field_renderer_places_only_samples_near_the_cells_and_draws_the_same(world):
    """With an occupancy grid (and, flat, a dynamic region) smaller than the box, only the samples
    of each ray that can fall in the box around their cells are placed and looked up: the
    images at a moving camera's poses equal a full render of every sample (render_image)."""
    from evdnerf_ros.field import render_image
    from evdnerf_ros.field.dynamic_region import DynamicRegion
    from evdnerf_ros.field.occupancy import OccupancyGrid
    from evdnerf_ros.field.render import flat_background
    from evdnerf_ros.field.renderer import FieldRenderer

    field = _dense_planes_field(5)
    box = [[-0.6, -0.5, -0.4], [0.5, 0.6, 0.7]]
    cells = torch.zeros(10, 10, 10, dtype=torch.bool)               # inside the box, not touching it
    cells[2:8, 2:6, 2:8] = torch.rand(6, 4, 6) > 0.3
    occ = OccupancyGrid.from_footprint(cells)
    mask = torch.zeros((8, 8, 8), dtype=torch.bool)
    mask[3:6, 2:5, 3:7] = True
    region = DynamicRegion(mask)
    flat = world == "flat"
    r = FieldRenderer(field, CAM, box, duration_ns=10 ** 9, n_samples=24, occupancy=occ, dynamic=region,
                      static_world=world, background=0.3)
    grey = flat_background(field, 0.3) if flat else None
    from evdnerf_ros.field.render import camera_rays, ray_box_intersect, sample_along_rays

    o, d = camera_rays(CAM, look_at([0.05, -2.5, 0.1], [0.0, 0.0, 0.1]))
    t_near, t_far, hit = ray_box_intersect(o, d, box)
    window = r._sample_window(o, d, t_near, sample_along_rays(t_near, t_far, 24)[1], hit)
    assert window is not None and window.shape[1] < 24                 # the narrowing is exercised
    for i, t in enumerate((100_000_000, 400_000_000, 900_000_000)):
        T = _moving_pose(t) if i else look_at([0.05, -2.5, 0.1], [0.0, 0.0, 0.1])
        want = render_image(field, CAM, T, t / 1e9, box, 24, occupancy=occ, dynamic=region, background=0.3,
                            flat_background=grey).detach().numpy()
        np.testing.assert_allclose(r.render(T, t), np.maximum(want, 0), rtol=0, atol=1e-6)
        assert np.ptp(want) > 0.01


@pytest.mark.parametrize("backbone", ["planes", "hinge", "rigid"])
@pytest.mark.parametrize("world", ["field", "flat"])
def test_render_pixels_draws_pixels_of_many_poses_and_times_as_render(world, backbone):
    """``render_pixels`` (the per-pixel sampler's batch): pixels of several poses and times in one
    call, in any order, equal to the images ``render`` draws, and it checks what it is given."""
    from evdnerf_ros.field.dynamic_region import DynamicRegion
    from evdnerf_ros.field.occupancy import OccupancyGrid
    from evdnerf_ros.field.renderer import FieldRenderer

    field = {"planes": _dense_planes_field, "hinge": _dense_hinge_field, "rigid": _dense_rigid_field}[backbone](6)
    box = [[-0.6, -0.5, -0.4], [0.5, 0.6, 0.7]]
    cells = torch.zeros(10, 10, 10, dtype=torch.bool)
    cells[2:8, 2:6, 2:8] = True
    mask = torch.zeros((8, 8, 8), dtype=torch.bool)
    mask[3:6, 2:5, 3:7] = True
    r = FieldRenderer(field, CAM, box, duration_ns=10 ** 9, n_samples=24, occupancy=OccupancyGrid.from_footprint(cells),
                      dynamic=DynamicRegion(mask), static_world=world, background=0.3, chunk=200)
    times = np.array([100_000_000, 400_000_000, 900_000_000], np.int64)
    poses = np.stack([_moving_pose(t) for t in times])
    n = CAM.width * CAM.height
    rng = np.random.default_rng(0)
    which = rng.integers(0, 3, 900)
    pixels = rng.integers(0, n, 900)
    assert r.compiled_rays                      # on the CPU the samples are placed in compiled passes
    got = r.render_pixels(poses, times, which, pixels)
    cost = (r.rays_rendered, r.samples_evaluated)
    assert got.shape == (900,) and got.dtype == np.float32 and min(cost) > 0
    images = [r.render(poses[k], int(times[k])).ravel() for k in range(3)]
    assert max(np.ptp(im) for im in images) > 0.01
    np.testing.assert_allclose(got, [images[k][p] for k, p in zip(which, pixels)], rtol=0, atol=1e-6)
    r.compiled_rays = False                     # the tensor path (CUDA's): the same values and work
    before = (r.rays_rendered, r.samples_evaluated)
    np.testing.assert_allclose(r.render_pixels(poses, times, which, pixels), got, rtol=0, atol=1e-6)
    assert (r.rays_rendered - before[0], r.samples_evaluated - before[1]) == cost
    r.compiled_rays = True
    with pytest.raises(InputError, match="pixel index is outside"):
        r.render_pixels(poses, times, [0], [n])
    with pytest.raises(InputError, match="one length"):
        r.render_pixels(poses, times, [0, 1], [0])
    with pytest.raises(InputError, match="2 times for 3 poses"):
        r.render_pixels(poses, times[:2], [0], [0])
    bent = poses.copy()
    bent[1, 0, 0] = 2.0
    with pytest.raises(InputError, match=r"T_world_cam\[1\].*not a rigid"):
        r.render_pixels(bent, times, [0], [0])


@pytest.mark.parametrize("world", ["field", "flat"])
@pytest.mark.parametrize("grids", [True, False])
def test_a_baked_field_marches_pixels_as_the_tensor_path_renders_them(world, grids):
    """A baked field on the CPU draws ``render_pixels`` in one compiled pass (``field.baked_rays``):
    the same values as the tensor path's images (float64 against float32: within 1e-5, except the
    rare sample that rounding moves across a cell face), the same counts of rays traced, and the
    backdrop alone where no cell can show anything."""
    from evdnerf_ros.field.baked import BakedField
    from evdnerf_ros.field.dynamic_region import DynamicRegion
    from evdnerf_ros.field.occupancy import OccupancyGrid
    from evdnerf_ros.field.renderer import FieldRenderer

    box = [[-0.6, -0.5, -0.4], [0.5, 0.6, 0.7]]
    cells = torch.zeros(10, 10, 10, dtype=torch.bool)
    cells[2:8, 2:6, 2:8] = True
    mask = torch.zeros((8, 8, 8), dtype=torch.bool)
    mask[3:6, 2:5, 3:7] = True
    region = DynamicRegion(mask) if grids or world == "flat" else None
    baked = BakedField.bake(_dense_planes_field(6), resolution=12, times=5, dynamic=region)
    r = FieldRenderer(baked, CAM, box, duration_ns=10 ** 9, n_samples=24, dynamic=region, static_world=world,
                      occupancy=OccupancyGrid.from_footprint(cells) if grids else None, background=0.3)
    assert r.compiled_rays and r._baked
    times = np.array([100_000_000, 400_000_000, 900_000_000], np.int64)
    poses = np.stack([_moving_pose(t) for t in times])
    n = CAM.width * CAM.height
    which = np.repeat(np.arange(3), n)
    pixels = np.tile(np.arange(n), 3)
    got = r.render_pixels(poses, times, which, pixels)
    traced = r.rays_rendered
    assert got.shape == (3 * n,) and got.dtype == np.float32
    images = np.concatenate([r.render(poses[k], int(times[k])).ravel() for k in range(3)])
    assert np.ptp(images) > 0.05
    err = np.abs(got - images)
    assert np.mean(err > 1e-5) < 0.01 and err.max() < 0.05, (np.mean(err > 1e-5), err.max())
    assert traced == r.rays_rendered - traced > 0          # as many rays traced as the images traced
    assert r.samples_evaluated > 0
    if world == "flat":                                    # a region no ray crosses: the flat grey alone
        away = np.stack([look_at([0.0, -3.0, 5.0], [0.0, -9.0, 5.0])] * 3)
        np.testing.assert_array_equal(r.render_pixels(away, times, which[:50], pixels[:50]),
                                      np.float32(r.flat_grey))


def test_a_flat_world_bakes_no_static_grid():
    """``keep_static=False`` (what a flat static world bakes) leaves the static grid out: the same
    flat renders, and the static world is refused rather than drawn from nothing."""
    from evdnerf_ros.field.baked import BakedField
    from evdnerf_ros.field.dynamic_region import DynamicRegion
    from evdnerf_ros.field.renderer import FieldRenderer

    mask = torch.zeros((8, 8, 8), dtype=torch.bool)
    mask[3:6, 2:5, 3:7] = True
    region = DynamicRegion(mask)
    field = _dense_planes_field(6)
    full, lean = (BakedField.bake(field, resolution=12, times=5, dynamic=region, keep_static=k) for k in (True, False))
    assert lean.nbytes < full.nbytes
    box = [[-0.6, -0.5, -0.4], [0.5, 0.6, 0.7]]
    renderers = [FieldRenderer(f, CAM, box, duration_ns=10 ** 9, n_samples=24, dynamic=region, static_world="flat",
                               background=0.3) for f in (full, lean)]
    a, b = (np.stack([r.render(_moving_pose(t), t) for t in (100_000_000, 400_000_000, 900_000_000)])
            for r in renderers)
    np.testing.assert_array_equal(a, b)
    assert np.ptp(a) > 0.05
    with pytest.raises(RuntimeError, match="without its static grid"):
        lean.decode_static(torch.zeros(2, 3))


def test_the_baked_marcher_on_extreme_rays_and_densities():
    """The compiled marcher against the tensor path where rounding and overflow bite: a camera
    inside the box, rays parallel to the box's faces (zero direction components), a huge density
    (opacity 1 at the first sample: no NaN, no overflow) and no density at all (the backdrop)."""
    from evdnerf_ros.field.baked import BakedField
    from evdnerf_ros.field.dynamic_region import DynamicRegion
    from evdnerf_ros.field.renderer import FieldRenderer

    mask = torch.zeros((8, 8, 8), dtype=torch.bool)
    mask[2:6, 2:6, 2:6] = True
    region = DynamicRegion(mask)
    box = [[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]
    inside = np.eye(4)
    inside[:3, 3] = [0.05, 0.02, -0.9]                  # looking along +z from inside the box
    cam = PinholeCamera(5, 5, 4.0, 4.0, 2.0, 2.0)      # the centre pixel's ray is exactly (0, 0, 1)
    times = np.array([0, 500_000_000], np.int64)
    poses = np.stack([inside, look_at([0.0, -3.0, 0.0], [0.0, 0.0, 0.0])])
    which, pixels = np.repeat([0, 1], 25), np.tile(np.arange(25), 2)
    base = BakedField.bake(_dense_planes_field(6), resolution=9, times=3, dynamic=region)
    for scale in (1.0, 1e30, 0.0):
        field = BakedField(base.static * torch.tensor([scale, 1.0])[:, None, None, None],
                           base.frames * torch.tensor([scale, 1.0])[None, :, None, None, None],
                           base.frame_lo, base.frame_hi)
        for world in ("field", "flat"):
            r = FieldRenderer(field, cam, box, duration_ns=10 ** 9, n_samples=16, dynamic=region, static_world=world,
                              background=0.25)
            got = r.render_pixels(poses, times, which, pixels)
            want = np.concatenate([r.render(poses[k], int(times[k])).ravel() for k in range(2)])
            assert np.all(np.isfinite(got)), (scale, world)
            np.testing.assert_allclose(got, want, rtol=0, atol=1e-5, err_msg=f"density x{scale:g}, {world}")
            if scale == 0.0:
                assert np.all(got == np.float32(0.25) if world == "field" else got == np.float32(r.flat_grey))


@pytest.mark.parametrize("world", ["field", "flat"])
def test_compiled_sample_placement_on_extreme_rays(world):
    """The compiled sample placement against the tensor path where float32 rounding bites: a camera
    inside the box, rays parallel to the box's faces (zero direction components), a camera far away
    (tiny bins), and a pose whose rays all miss the box."""
    from evdnerf_ros.field.dynamic_region import DynamicRegion
    from evdnerf_ros.field.occupancy import OccupancyGrid
    from evdnerf_ros.field.renderer import FieldRenderer

    mask = torch.zeros((8, 8, 8), dtype=torch.bool)
    mask[2:6, 2:6, 2:6] = True
    cells = torch.zeros(10, 10, 10, dtype=torch.bool)
    cells[1:9, 1:9, 1:9] = True
    inside = np.eye(4)
    inside[:3, 3] = [0.05, 0.02, -0.9]                  # looking along +z from inside the box
    cam = PinholeCamera(5, 5, 4.0, 4.0, 2.0, 2.0)      # the centre pixel's ray is exactly (0, 0, 1)
    poses = np.stack([inside, look_at([0.0, -3.0, 0.0], [0.0, 0.0, 0.0]), look_at([0.0, -900.0, 0.0], [0.0, 0.0, 0.0]),
                      look_at([0.0, -3.0, 0.0], [0.0, -9.0, 0.0])])
    times = np.array([0, 300_000_000, 600_000_000, 900_000_000], np.int64)
    which, pixels = np.repeat(np.arange(4), 25), np.tile(np.arange(25), 4)
    r = FieldRenderer(_dense_planes_field(6), cam, [[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]], duration_ns=10 ** 9,
                      n_samples=16, dynamic=DynamicRegion(mask), occupancy=OccupancyGrid.from_footprint(cells),
                      static_world=world, background=0.25)
    got = r.render_pixels(poses, times, which, pixels)
    r.compiled_rays = False
    want = r.render_pixels(poses, times, which, pixels)
    assert np.all(np.isfinite(got)) and np.ptp(want[:75]) > 0.01
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-6)
    assert np.all(got[75:] == (np.float32(0.25) if world == "field" else np.float32(r.flat_grey)))
