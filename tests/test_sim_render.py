"""The scene renderer: analytic geometry, occlusion, shadows, antialiasing, presets."""

import math

import numpy as np
import pytest
import yaml

from evdnerf_ros.errors import InputError
from evdnerf_ros.geometry.camera import PinholeCamera, look_at
from evdnerf_ros.sim.render import SceneRenderer, render
from evdnerf_ros.sim.scene import list_presets, load_scene, scene_from_dict

PLAIN = {"background": {"intensity": 0.1},
         "lights": {"ambient": 0.2, "directional": [{"direction": [0, 0, -1], "intensity": 0.6}],
                    "shadows": True}}


def scene(objects, **kw):
    d = {"time": {"start_s": 0, "end_s": 1}, **PLAIN, "objects": objects}
    d.update(kw)
    return scene_from_dict(d, check_cameras=False)


CAM = PinholeCamera.from_fov(65, 65, 40.0)


def test_sphere_mask_area_and_centre_depth():
    r, dist = 0.5, 3.0
    sc = scene([{"type": "sphere", "radius": r}])
    T = look_at([dist, 0, 0], [0, 0, 0])
    res = render(sc, T, 0, CAM, supersample=1)
    assert res.intensity.dtype == np.float32 and res.depth.dtype == np.float32
    assert res.depth[32, 32] == np.float32(dist - r)
    # silhouette: a circle of radius f * tan(asin(r / d)) around the principal point
    R = CAM.fx * math.tan(math.asin(r / dist))
    v, u = np.mgrid[0:65, 0:65]
    rho = np.hypot(u - CAM.cx, v - CAM.cy)
    expect = rho <= R
    near_edge = np.abs(rho - R) < 1e-6
    assert np.array_equal(res.mask[~near_edge], expect[~near_edge])
    assert abs(res.mask.sum() - math.pi * R * R) / (math.pi * R * R) < 0.02
    assert np.all(np.isinf(res.depth[~res.mask])) and np.all(np.isfinite(res.depth[res.mask]))
    # depth at every hit pixel: distance along the ray to the sphere
    d = CAM.ray_directions(1)
    dw = d @ T[:3, :3].T
    o = T[:3, 3]
    b = dw @ o
    t = -b - np.sqrt(np.maximum(b * b - (o @ o - r * r), 0))
    assert np.allclose(res.depth[res.mask], t[res.mask], rtol=1e-6)
    # even supersampling uses a centre pass for depth and mask: identical geometry
    res2 = render(sc, T, 0, CAM, supersample=2)
    assert np.array_equal(res2.mask, res.mask) and np.array_equal(res2.depth, res.depth)


def test_box_face_depth():
    sc = scene([{"type": "box", "size": [1.0, 1.0, 1.0]}])
    T = look_at([3, 0, 0], [0, 0, 0])
    res = render(sc, T, 0, CAM, supersample=1)
    assert res.depth[32, 32] == np.float32(2.5)
    d = CAM.ray_directions(1)
    # the front face is the plane at z_cam = 2.5: depth * cos(angle to the axis) = 2.5
    assert np.allclose((res.depth * d[..., 2])[res.mask], 2.5, rtol=1e-6)


def test_cylinder_and_ellipsoid_depth():
    sc = scene([{"type": "cylinder", "radius": 0.3, "height": 1.0}])
    res = render(sc, look_at([3, 0, 0], [0, 0, 0]), 0, CAM, supersample=1)
    assert np.isclose(res.depth[32, 32], 2.7)
    res = render(sc, look_at([0, 0.001, 3], [0, 0, 0]), 0, CAM, supersample=1)   # cap
    assert np.isclose(res.depth[32, 32], 2.5, atol=1e-6)
    sc = scene([{"type": "ellipsoid", "radii": [0.2, 0.4, 0.8]}])
    res = render(sc, look_at([3, 0, 0], [0, 0, 0]), 0, CAM, supersample=1)
    assert np.isclose(res.depth[32, 32], 2.8)
    assert res.mask[:, 32].sum() > 2 * res.mask[32, :].sum()     # taller (z) than wide (y)


def test_occlusion_order_independent_of_listing():
    near = {"name": "near", "type": "sphere", "radius": 0.3, "albedo": 0.9,
            "pose": {"position": [1.0, 0, 0]}}
    far = {"name": "far", "type": "box", "size": [0.5, 2, 2], "albedo": 0.3}
    T = look_at([4, 0, 0], [0, 0, 0])
    a = render(scene([near, far]), T, 0, CAM, supersample=1)
    b = render(scene([far, near]), T, 0, CAM, supersample=1)
    assert np.array_equal(a.intensity, b.intensity) and np.array_equal(a.depth, b.depth)
    assert np.isclose(a.depth[32, 32], 2.7)                 # the sphere in front
    assert np.isclose(a.depth[15, 32] * CAM.ray_directions(1)[15, 32, 2], 3.75)  # the box behind


def test_shadow_darkens_region_below_object():
    floor = {"name": "floor", "type": "box", "size": [3, 3, 0.1], "albedo": 0.5,
             "pose": {"position": [0, 0, -0.05]}}
    ball = {"name": "ball", "type": "sphere", "radius": 0.25, "pose": {"position": [0, 0, 0.6]}}
    T = look_at([2.5, 0, 1.5], [0, 0, 0])
    cam = PinholeCamera.from_fov(96, 96, 50.0)
    on = render(scene([floor, ball]), T, 0, cam, supersample=1)
    off = SceneRenderer(scene([floor, ball]), cam, 1, shadows=False).render_result(T, 0)

    def pixel(p):
        pc = (np.asarray(p, float) - T[:3, 3]) @ T[:3, :3]
        u, v = cam.project(pc[None])[0]
        return int(round(v)), int(round(u))
    under, lit = pixel([0, 0, 0]), pixel([0.5, 0.6, 0])
    assert np.isclose(on.intensity[under], 0.5 * 0.2, rtol=1e-6)           # ambient only
    assert np.isclose(off.intensity[under], 0.5 * 0.8, rtol=1e-6)
    assert np.isclose(on.intensity[lit], 0.5 * 0.8, rtol=1e-6)
    # the shadow is a disc of radius 0.25 under the ball (light straight down)
    d = cam.ray_directions(1) @ T[:3, :3].T
    t = -T[2, 3] / d[..., 2]
    hit = T[:3, 3] + t[..., None] * d
    floor_px = on.mask & (np.abs(on.depth - t) < 1e-4)
    rad = np.hypot(hit[..., 0], hit[..., 1])
    dark = np.isclose(on.intensity, 0.1, rtol=1e-5)
    assert np.all(dark[floor_px & (rad < 0.24)]) and not np.any(dark[floor_px & (rad > 0.26)])


def test_supersampling_converges_and_is_positive():
    sc = scene([{"type": "box", "size": [0.8, 0.8, 0.8], "pose": {"rotation": [20, 30, 40]},
                 "texture": {"type": "checker", "scale": 0.2, "contrast": 0.6}}])
    T = look_at([3, 0.5, 0.8], [0, 0, 0])
    cam = PinholeCamera.from_fov(48, 48, 40.0)
    ref = SceneRenderer(sc, cam, 8)(T, 0)
    err = [np.abs(SceneRenderer(sc, cam, s)(T, 0) - ref).mean() for s in (1, 2, 4)]
    assert err[0] > err[1] > err[2] and err[2] < 0.35 * err[0]
    assert ref.min() > 0 and np.all(np.isfinite(ref))


def test_deterministic_and_time_dependence():
    sc = load_scene("lego")
    cam = PinholeCamera.from_fov(48, 48, 40.0)
    T = sc.camera_poses()[3]
    r1, r2 = SceneRenderer(sc, cam, 2), SceneRenderer(sc, cam, 2)
    a, b = r1(T, 400_000_000), r2(T, 400_000_000)
    assert np.array_equal(a, b) and np.array_equal(a, r1(T, 400_000_000))
    assert np.abs(r1(T, 600_000_000) - a).max() > 0.05           # the bucket moved
    static = scene([{"type": "box", "size": [1, 1, 1], "texture": {"type": "noise",
                                                                   "scale": 0.1}}])
    rs = SceneRenderer(static, cam, 2)
    assert np.array_equal(rs(T, 0), rs(T, 987_654_321))
    # the fork holds still before its servo starts, then swings
    fork = load_scene("fork")
    rf = SceneRenderer(fork, cam, 1)
    Tf = fork.camera_poses()[0]
    assert np.array_equal(rf(Tf, 0), rf(Tf, 99_999_999))
    assert not np.array_equal(rf(Tf, 0), rf(Tf, 300_000_000))


@pytest.mark.parametrize("name", list_presets())
def test_every_preset_renders_every_view(name):
    sc = load_scene(name)
    cam = PinholeCamera.from_fov(64, 64, sc.cameras.fov_deg)
    r = SceneRenderer(sc, cam, 1)
    t = (sc.start_ns + sc.end_ns) // 2
    for T in sc.camera_poses("train"):
        res = r.render_result(T, t)
        assert res.intensity.shape == (64, 64) and res.intensity.dtype == np.float32
        assert np.all(np.isfinite(res.intensity)) and res.intensity.min() > 0
        assert res.mask.sum() > 20


def test_bbox_prefilter_gives_identical_images_with_fewer_tests():
    sc = load_scene("multi")
    cam = PinholeCamera.from_fov(48, 48, 40.0)
    T = sc.camera_poses()[2]
    a = SceneRenderer(sc, cam, 2, prefilter=True)
    b = SceneRenderer(sc, cam, 2, prefilter=False)
    ra, rb = a.render_result(T, 300_000_000), b.render_result(T, 300_000_000)
    assert np.array_equal(ra.intensity, rb.intensity) and np.array_equal(ra.depth, rb.depth)
    assert a.stats.tests < 0.6 * b.stats.tests


def test_mesh_matches_analytic_sphere(tmp_path):
    trimesh = pytest.importorskip("trimesh")
    trimesh.creation.icosphere(subdivisions=3, radius=0.5).export(tmp_path / "ball.obj")
    d = {"time": {"start_s": 0, "end_s": 1}, **PLAIN,
         "objects": [{"type": "mesh", "path": "ball.obj", "albedo": 0.6}]}
    (tmp_path / "s.yaml").write_text(yaml.safe_dump(d))
    sc = load_scene(tmp_path / "s.yaml")
    T = look_at([3, 0, 0], [0, 0, 0])
    res = render(sc, T, 0, CAM, supersample=1)
    ref = render(scene([{"type": "sphere", "radius": 0.5, "albedo": 0.6}]), T, 0, CAM,
                 supersample=1)
    assert abs(res.mask.sum() - ref.mask.sum()) <= 0.03 * ref.mask.sum()
    assert abs(res.depth[32, 32] - 2.5) < 0.01
    both = res.mask & ref.mask
    assert np.abs(res.intensity[both] - ref.intensity[both]).mean() < 0.02


def test_render_bad_input():
    sc = scene([{"name": "ball", "type": "sphere", "radius": 0.5}])
    r = SceneRenderer(sc, CAM, 1)
    with pytest.raises(InputError, match="int64 nanoseconds"):
        r(look_at([3, 0, 0], [0, 0, 0]), 0.5)
    with pytest.raises(InputError, match="inside object 'ball'"):
        r(look_at([0.1, 0, 0], [1, 0, 0]), 0)
    bad = np.eye(4)
    bad[0, 0] = 2
    with pytest.raises(InputError, match="orthonormal"):
        r(bad, 0)
    with pytest.raises(InputError, match="supersample"):
        SceneRenderer(sc, CAM, 0)


def _moving_scene(t0: str):
    """Keyframes, a hinge and a servo, with every time shifted by t0 seconds (decimal text)."""
    from decimal import Decimal

    sh = lambda x: str(Decimal(t0) + Decimal(x))    # noqa: E731
    kf = [{"t_s": sh("0"), "position": [0, -0.5, 0], "rotation": [0, 0, 0]},
          {"t_s": sh("0.4"), "position": [0, 0.1, 0.2], "rotation": [0, 0, 50]},
          {"t_s": sh("1"), "position": [0, 0.6, 0], "rotation": [0, 0, 90]}]
    hinge = {"parent": "box", "axis": [1, 0, 0], "pivot": [0, 0, 0.3],
             "angle_keyframes": [{"t_s": sh("0"), "angle_deg": 0},
                                 {"t_s": sh("1"), "angle_deg": 70}]}
    servo = {"axis": [1, 0, 0], "pivot": [0, 0, -0.4],
             "servo": {"profile": "run", "start_s": sh("0.1")}}
    return scene([
        {"name": "box", "type": "box", "size": [0.4, 0.4, 0.4],
         "texture": {"type": "checker", "scale": 0.1}, "motion": {"keyframes": kf}},
        {"name": "arm", "type": "box", "size": [0.05, 0.6, 0.05],
         "pose": {"position": [0, 0.3, 0.3]}, "motion": {"hinge": hinge}},
        {"name": "flag", "type": "box", "size": [0.02, 0.3, 0.2],
         "pose": {"position": [0, 0, -0.6]}, "motion": {"hinge": servo}}],
        time={"start_s": sh("0"), "end_s": sh("1.2")})


def test_large_time_offset_renders_bit_identically():
    a, b = _moving_scene("0"), _moving_scene("10000")
    T = look_at([3, 0.4, 0.5], [0, 0, 0])
    cam = PinholeCamera.from_fov(40, 40, 50.0)
    ra, rb = SceneRenderer(a, cam, 2), SceneRenderer(b, cam, 2)
    off = 10_000 * 10**9
    for t in (0, 123_456_789, 400_000_000, 777_777_777, 1_100_000_001):
        assert np.array_equal(ra(T, t), rb(T, off + t))
    assert not np.array_equal(ra(T, 0), ra(T, 500_000_000))


def test_renderer_pickles_for_worker_processes():
    import pickle

    sc = load_scene("lego")
    cam = PinholeCamera.from_fov(32, 32, 40.0)
    r = SceneRenderer(sc, cam, 1)
    T = sc.camera_poses()[1]
    assert np.array_equal(pickle.loads(pickle.dumps(r))(T, 300_000_000), r(T, 300_000_000))
