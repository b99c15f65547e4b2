"""Dynamic region: carving from event footprints, static decoding, skipped rays."""

import numpy as np
import pytest
import torch

from evdnerf_ros.field import DynamicRegion, PlanesField, DNeRFField, event_footprint, render_rays
from evdnerf_ros.field.render import camera_rays, normalize_points
from evdnerf_ros.io.trainingset import TrainingSet
from evdnerf_ros.geometry.camera import PinholeCamera, look_at
from evdnerf_ros.train.rays import camera_of, default_box

BOX = ((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0))


def moving_planes(seed=0):
    """A planes field whose time planes are random, so it changes everywhere."""
    f = PlanesField(resolutions=(8, 16), time_resolution=6, features=8, hidden=16, seed=seed)
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for tp in f.time_planes:
            tp.copy_(torch.rand(tp.shape, generator=g) * 2)
    return f


def half_region(res=8):
    mask = torch.zeros(res, res, res, dtype=torch.bool)
    mask[res // 2:] = True                         # x > 0 may change
    return DynamicRegion(mask)


@pytest.mark.parametrize("field", [moving_planes(), DNeRFField(depth=3, width=16, skip=1, pe_x=4, pe_t=2)],
                         ids=["planes", "dnerf"])
def test_evaluate_times_static_points_take_the_static_field(field):
    torch.manual_seed(1)
    x = torch.rand(40, 3) * 2 - 1
    t0, t1 = torch.full((40, 1), 0.2), torch.full((40, 1), 0.9)
    dyn = x[:, 0] > 0
    (d0, g0), (d1, g1) = field.evaluate_times(x, [t0, t1], dyn)
    sd, sg = field.decode_static(field.space_features(x[~dyn]))
    assert torch.equal(d0[~dyn], sd) and torch.equal(d1[~dyn], sd) and torch.equal(g1[~dyn], sg)
    full = field.evaluate_times(x[dyn], [t0[dyn], t1[dyn]])
    assert torch.allclose(d0[dyn], full[0][0]) and torch.allclose(g1[dyn], full[1][1])
    assert not torch.allclose(d0[dyn], d1[dyn])    # the dynamic part does change


def test_planes_static_decode_is_the_initial_field():
    """Time planes start at 1, so the untrained field equals its static decoding."""
    f = PlanesField(resolutions=(8, 16), time_resolution=6, features=8, hidden=16, seed=3)
    x = torch.rand(30, 3) * 2 - 1
    d, g = f(x, torch.full((30, 1), 0.7))
    sd, sg = f.decode_static(f.space_features(x))
    assert torch.allclose(d, sd) and torch.allclose(g, sg)


def _rays():
    cam = PinholeCamera(width=12, height=10, fx=10.0, fy=10.0, cx=5.5, cy=4.5)
    return camera_rays(cam, look_at(np.array([3.0, 0.4, 0.5]), np.zeros(3)))


def test_full_region_renders_like_no_region_and_empty_region_changes_nothing():
    field = moving_planes()
    o, d = _rays()
    plain = render_rays(field, o, d, [0.1, 0.8], BOX, 16)
    full = render_rays(field, o, d, [0.1, 0.8], BOX, 16,
                       dynamic=DynamicRegion(torch.ones(4, 4, 4, dtype=torch.bool)))
    for a, b in zip(plain, full):
        assert torch.allclose(a["grey"], b["grey"], atol=1e-6)
    empty = DynamicRegion(torch.zeros(4, 4, 4, dtype=torch.bool))
    r0, r1 = render_rays(field, o, d, [0.1, 0.8], BOX, 16, dynamic=empty)
    assert torch.equal(r0["grey"], r1["grey"])
    assert not torch.allclose(plain[0]["grey"], plain[1]["grey"])
    s0, s1 = render_rays(field, o, d, [0.1, 0.8], BOX, 16, dynamic=empty, changes_only=True)
    assert torch.equal(s0["grey"], s1["grey"]) and float(s0["opacity"].abs().max()) == 0.0


def test_changes_only_skips_exactly_the_rays_that_cross_nothing_dynamic():
    field = moving_planes(2)
    o, d = _rays()
    region = half_region()
    crossing = region.rays_crossing(o, d, BOX)
    assert 0 < int(crossing.sum()) < len(crossing)
    with torch.no_grad():
        r0, r1 = render_rays(field, o, d, [0.3, 0.6], BOX, 32, dynamic=region)
    s0, s1 = render_rays(field, o, d, [0.3, 0.6], BOX, 32, dynamic=region, changes_only=True)
    dl_full = torch.log(r1["grey"] + 1e-3) - torch.log(r0["grey"] + 1e-3)
    dl_skip = torch.log(s1["grey"] + 1e-3) - torch.log(s0["grey"] + 1e-3)
    assert torch.allclose(dl_full, dl_skip, atol=1e-5)
    assert float(dl_full[~crossing].abs().max()) == 0.0
    assert float(dl_full[crossing].abs().max()) > 1e-3
    with pytest.raises(ValueError, match="dynamic region"):
        render_rays(field, o, d, [0.3, 0.6], BOX, 8, changes_only=True)


def test_region_from_the_fork_footprints(tiny_train_h5):
    with TrainingSet(tiny_train_h5) as ts:
        box = default_box(ts)
        region = DynamicRegion.from_event_footprint(ts, box, resolution=32)
        assert 0.0 < region.fraction < 0.05           # a swept fan, not the box
        # the fork swings +-45 degrees about the x axis through its pivot (0, 0, -0.95): a
        # point 0.6 m from the pivot at 41.6 degrees from vertical is swept; the box corner is not
        pts = torch.tensor(np.array([[0.0, 0.4, -0.5], box[1] - 0.05]), dtype=torch.float32)
        assert region.query(normalize_points(pts, box)).tolist() == [True, False]
        # carving: every dynamic voxel centre projects onto the footprint of every view
        idx = torch.nonzero(region.mask).numpy()
        lo, hi = box
        centres = lo + (idx + 0.5) / 32 * (hi - lo)
        for v in ts.train_views:
            fp = event_footprint(ts, v)
            T, K = ts.pose(v), ts.K(v)
            pc = (centres - T[:3, 3]) @ T[:3, :3]
            u = np.rint(K[0, 0] * pc[:, 0] / pc[:, 2] + K[0, 2]).astype(int)
            w = np.rint(K[1, 1] * pc[:, 1] / pc[:, 2] + K[1, 2]).astype(int)
            inside = (u >= 0) & (u < ts.width) & (w >= 0) & (w < ts.height)
            assert fp[w[inside], u[inside]].all()
        # tolerating misses can only grow the region
        loose = DynamicRegion.from_event_footprint(ts, box, resolution=32, misses=1)
        assert bool((loose.mask | region.mask).eq(loose.mask).all()) and loose.fraction > region.fraction
        # the pixels whose rays cross it are few; they hold most event pixels of a view
        # (the rest: fork tips too thin for events in the edge-on views, which carve them
        # away; allowing one miss keeps nearly all)
        cam = camera_of(ts.K(ts.train_views[0]), ts.width, ts.height)
        o, d = camera_rays(cam, ts.pose(ts.train_views[0]))
        crossing = region.rays_crossing(o, d, box).numpy()
        fp = event_footprint(ts, ts.train_views[0], dilate_px=0).reshape(-1)
        assert crossing.mean() < 0.5 and crossing[fp].mean() > 0.5
        assert loose.rays_crossing(o, d, box).numpy()[fp].mean() > 0.9


def test_footprint_dilation_and_min_events(tiny_train_h5):
    with TrainingSet(tiny_train_h5) as ts:
        v = ts.train_views[0]
        raw = event_footprint(ts, v, dilate_px=0)
        dil = event_footprint(ts, v, dilate_px=1)
        strict = event_footprint(ts, v, dilate_px=0, min_events=5)
        assert raw.any() and (dil | raw).sum() == dil.sum() and dil.sum() > raw.sum()
        assert (strict & ~raw).sum() == 0 and strict.sum() < raw.sum()


def test_region_mask_validation():
    with pytest.raises(ValueError, match="3D boolean grid"):
        DynamicRegion(torch.ones(4, 4, dtype=torch.bool))


def _crossing_every_step(region, o, d, box, near=0.0):
    """The reference: every quarter-voxel step of every ray inside the box tested."""
    from evdnerf_ros.field.render import ray_box_intersect

    lo, hi = np.asarray(box, np.float64)
    n = max(2, int(np.ceil(np.linalg.norm(hi - lo) / (np.min((hi - lo) / np.array(region.resolution)) / 4))) + 1)
    t0, t1, hit = ray_box_intersect(o, d, box, near, float("inf"))
    z = t0[:, None] + (t1 - t0)[:, None] * torch.linspace(0.0, 1.0, n)[None, :]
    pts = o[:, None, :] + d[:, None, :] * z[..., None]
    return hit & region.query(normalize_points(pts.reshape(-1, 3), box)).reshape(-1, n).any(dim=1)


def test_rays_crossing_tests_only_steps_near_the_region_with_the_same_answer():
    """The steps outside the box around the dynamic voxels are skipped: the answer is the one of
    testing every step, for solid and sparse regions, rays from inside and outside the box."""
    rng = np.random.default_rng(0)
    box = np.array([[-1.0, -0.5, -2.0], [1.5, 1.0, 0.5]])
    for trial in range(12):
        mask = torch.zeros(16, 16, 16, dtype=torch.bool)
        a0 = rng.integers(0, 14, 3)
        a1 = np.minimum(a0 + rng.integers(1, 6, 3), 16)
        block = torch.ones(tuple(a1 - a0), dtype=torch.bool) if trial % 2 else \
            torch.from_numpy(rng.random(a1 - a0) > 0.5)
        mask[a0[0]:a1[0], a0[1]:a1[1], a0[2]:a1[2]] = block
        region = DynamicRegion(mask)
        o = torch.from_numpy(rng.normal(size=(2000, 3)) * 2).float()
        d = torch.from_numpy(rng.normal(size=(2000, 3))).float()
        got = region.rays_crossing(o, d, box, near=0.1, chunk=700)
        assert torch.equal(got, _crossing_every_step(region, o, d, box, near=0.1)), trial
        assert 0 < int(got.sum()) < got.numel()
    empty = DynamicRegion(torch.zeros(8, 8, 8, dtype=torch.bool))
    assert not bool(empty.rays_crossing(o, d, box).any())


def test_grid_lookup_reads_the_nearest_cell_clamped():
    from evdnerf_ros.field.occupancy import grid_lookup

    g = torch.rand(5, 3, 7) > 0.5
    x = torch.cat([torch.rand(5000, 3) * 2.4 - 1.2, torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])])
    idx = [np.clip(((x[:, a].numpy() + 1.0) * 0.5 * n).astype(np.int64), 0, n - 1) for a, n in enumerate(g.shape)]
    np.testing.assert_array_equal(grid_lookup(g, x).numpy(), g.numpy()[idx[0], idx[1], idx[2]])


def test_inner_weight_fades_to_zero_at_the_region_boundary():
    """A flat static world's fade (``inner_weight``): 1 at the centre of a cell deep inside, 0 in
    every cell outside a box-shaped region, and continuous across its faces."""
    mask = torch.zeros(8, 8, 8, dtype=torch.bool)
    mask[2:6, 2:6, 2:6] = True
    region = DynamicRegion(mask)
    centre = lambda i, j, k: torch.tensor([[(i + 0.5) / 4 - 1, (j + 0.5) / 4 - 1, (k + 0.5) / 4 - 1]])  # noqa: E731
    assert float(region.inner_weight(centre(3, 3, 3))) == 1.0
    x = torch.rand(20000, 3) * 2 - 1
    w = region.inner_weight(x)
    assert float(w.min()) >= 0.0 and float(w.max()) <= 1.0
    assert not bool(w[~region.query(x)].any())                    # nothing outside the region
    line = torch.zeros(4001, 3)
    line[:, 0] = torch.linspace(-1, 1, 4001)                     # across two faces, through the centre
    line[:, 1:] = 0.01
    wl = region.inner_weight(line)
    assert float(wl.max()) == 1.0 and float(wl[0]) == 0.0
    # at most the steepest slope (2 per cell width, a cell is 0.25 wide) times the step
    assert float(wl.diff().abs().max()) <= 8.0 * (2 / 4000) + 1e-6


def test_region_lookups_follow_the_points_device():
    """A region loaded on the CPU answers points on another device (a GPU field's samples) in
    both lookups, hard and soft, on that device; the meta device stands in for a GPU here (the
    soft one once failed there with a device mismatch, found on a GPU)."""
    region = DynamicRegion(torch.ones(4, 4, 4, dtype=torch.bool))
    x = torch.zeros(5, 3, device="meta")
    assert region.query(x).device.type == "meta"
    assert region.inner_weight(x).device.type == "meta"
    assert region.inner_weight(torch.zeros(5, 3)).device.type == "cpu"   # and back
    assert region.mask.device.type == "cpu"                               # the region itself unmoved
