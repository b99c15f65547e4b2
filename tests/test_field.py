"""Fields: interface, backbones, rendering in the scene box, occupancy, sample reuse."""

import math
import time

import numpy as np
import pytest
import torch

from evdnerf_ros.field import (DNeRFField, DynamicField, OccupancyGrid, PlanesField,
                               make_field, ray_box_intersect, render_image, render_rays)
from evdnerf_ros.field.render import camera_rays
from evdnerf_ros.geometry.camera import PinholeCamera, look_at

BOX = ((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0))


def small_planes(seed=0, time_resolution=6):
    return PlanesField(resolutions=(8, 16), time_resolution=time_resolution, features=8, hidden=16,
                       seed=seed)


def small_dnerf():
    torch.manual_seed(0)
    return DNeRFField(depth=3, width=16, skip=1, pe_x=4, pe_t=2)


class ConstantField(DynamicField):
    def __init__(self, sigma, grey=0.7):
        super().__init__()
        self.sigma, self.grey = sigma, grey

    def forward(self, x, t):
        n = x.shape[0]
        return torch.full((n,), self.sigma), torch.full((n,), self.grey)

    def decode_static(self, x):
        return self.forward(x, torch.zeros(x.shape[0], 1))


class BallField(DynamicField):
    """Density 5 inside a ball of radius 0.3 (normalised coords) at c, zero elsewhere."""

    def __init__(self, c=(0.2, -0.1, 0.0)):
        super().__init__()
        self.c = torch.tensor(c)

    def forward(self, x, t):
        r = (x - self.c).norm(dim=1)
        inside = r < 0.3
        return torch.where(inside, 5.0, 0.0), 0.3 + 0.5 * x[:, 0].abs()

    def decode_static(self, x):
        return self.forward(x, torch.zeros(x.shape[0], 1))


@pytest.mark.parametrize("field", [small_planes(), small_dnerf()], ids=["planes", "dnerf"])
def test_shapes_and_dtypes(field):
    x = torch.rand(17, 3) * 2 - 1
    t = torch.rand(17, 1)
    dens, grey = field(x, t)
    assert dens.shape == (17,) and grey.shape == (17,)
    assert dens.dtype == torch.float32 and grey.dtype == torch.float32
    assert bool((dens >= 0).all()) and bool(((grey > 0) & (grey < 1)).all())


def test_make_field():
    assert isinstance(make_field("planes", resolutions=(4,), time_resolution=2), PlanesField)
    with pytest.raises(ValueError):
        make_field("nope")


def test_planes_independent_of_time_at_init():
    f = small_planes()
    x = torch.rand(50, 3) * 2 - 1
    d0, g0 = f(x, torch.zeros(50, 1))
    d1, g1 = f(x, torch.rand(50, 1))
    # time planes of ones: bilinear weights that sum to 1 only to rounding, so equal to float precision
    torch.testing.assert_close(d0, d1, rtol=1e-6, atol=1e-7)
    torch.testing.assert_close(g0, g1, rtol=1e-6, atol=1e-7)
    for p in f.time_planes:
        assert torch.equal(p.data, torch.ones_like(p))


@pytest.mark.parametrize("field", [small_planes(), small_dnerf()], ids=["planes", "dnerf"])
def test_static_view_reuse_bit_identical(field):
    if isinstance(field, PlanesField):          # make the time planes matter
        with torch.no_grad():
            for p in field.time_planes:
                p.add_(0.3 * torch.randn_like(p))
    x = torch.rand(40, 3) * 2 - 1
    t0, t1 = torch.full((40, 1), 0.25), torch.full((40, 1), 0.75)
    (da, ga), (db, gb) = field.evaluate_times(x, [t0, t1])
    assert torch.equal(da, field(x, t0)[0]) and torch.equal(ga, field(x, t0)[1])
    assert torch.equal(db, field(x, t1)[0]) and torch.equal(gb, field(x, t1)[1])
    # and through the renderer
    o = torch.tensor([[0.0, 0.0, -3.0]]).repeat(5, 1)
    d = torch.nn.functional.normalize(torch.tensor([[0.05 * i, 0.02, 1.0] for i in range(5)]), dim=1)
    pair = render_rays(field, o, d, [0.25, 0.75], BOX, 16)
    assert torch.equal(pair[0]["grey"], render_rays(field, o, d, 0.25, BOX, 16)["grey"])
    assert torch.equal(pair[1]["grey"], render_rays(field, o, d, 0.75, BOX, 16)["grey"])
    if isinstance(field, PlanesField):
        assert not torch.equal(pair[0]["grey"], pair[1]["grey"])


def test_ray_box_intersection_hand_computed():
    box = ((0.0, 0.0, 0.0), (2.0, 1.0, 1.0))
    o = torch.tensor([[-1.0, 0.5, 0.5],      # along +x through the box: enters 1, exits 3
                      [1.0, 0.5, 0.5],       # starts inside: 0 .. 1 (along +x)
                      [-1.0, 2.0, 0.5],      # misses (above in y)
                      [-1.0, -1.0, 0.5],     # diagonal in xy: enters at t = sqrt(2)
                      [1.0, 0.5, 3.0]])      # along -z: enters 2, exits 3
    d = torch.tensor([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 0.0, 0.0],
                      [1 / math.sqrt(2), 1 / math.sqrt(2), 0.0], [0.0, 0.0, -1.0]])
    tn, tf, hit = ray_box_intersect(o, d, box)
    assert hit.tolist() == [True, True, False, True, True]
    torch.testing.assert_close(tn[[0, 1, 3, 4]], torch.tensor([1.0, 0.0, math.sqrt(2), 2.0]))
    torch.testing.assert_close(tf[[0, 1, 3, 4]],
                               torch.tensor([3.0, 1.0, 2 * math.sqrt(2), 3.0]))
    # clipping by near / far
    tn, tf, hit = ray_box_intersect(o[:1], d[:1], box, near=1.5, far=2.5)
    assert hit.item() and tn.item() == pytest.approx(1.5) and tf.item() == pytest.approx(2.5)
    tn, tf, hit = ray_box_intersect(o[:1], d[:1], box, near=0.0, far=0.5)
    assert not hit.item()


def test_constant_density_matches_analytic_transmittance():
    sigma, grey, bg = 0.8, 0.7, 0.1
    f = ConstantField(sigma, grey)
    o = torch.tensor([[-3.0, 0.0, 0.0], [-3.0, -3.0, 0.2]])
    d = torch.nn.functional.normalize(torch.tensor([[1.0, 0.0, 0.0], [1.0, 1.0, 0.0]]), dim=1)
    lengths = torch.tensor([2.0, 2.0 * math.sqrt(2)])
    out = render_rays(f, o, d, 0.5, BOX, 7, background=bg, perturb=True,
                      generator=torch.Generator().manual_seed(1))
    opacity = 1 - torch.exp(-sigma * lengths)
    torch.testing.assert_close(out["opacity"], opacity)
    torch.testing.assert_close(out["grey"], opacity * grey + (1 - opacity) * bg)


def test_rays_missing_the_box_return_background():
    f = ConstantField(100.0, 0.9)
    o = torch.tensor([[-3.0, 5.0, 0.0], [-3.0, 0.0, 0.0]])
    d = torch.tensor([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]])    # parallel outside; pointing away
    out = render_rays(f, o, d, 0.0, BOX, 8, background=0.25)
    assert out["grey"].tolist() == [0.25, 0.25]
    assert out["opacity"].tolist() == [0.0, 0.0]


def test_render_image_matches_simulator_camera_axes():
    cam = PinholeCamera.from_fov(9, 7, 60.0)
    T = look_at((0.0, -4.0, 0.0), (0.0, 0.0, 0.0))
    o, d = camera_rays(cam, T)
    assert o.shape == (63, 3) and d.shape == (63, 3)
    centre = d.reshape(7, 9, 3)[3, 4]          # principal point pixel -> optical axis
    torch.testing.assert_close(centre, torch.tensor([0.0, 1.0, 0.0]), atol=1e-6, rtol=0)
    img = render_image(ConstantField(1.0, 0.5), cam, T, 0.0, BOX, 8, chunk=10)
    assert img.shape == (7, 9) and img.dtype == torch.float32
    assert float(img[3, 4]) == pytest.approx(0.5 * (1 - math.exp(-2.0)), rel=1e-5)


def test_occupancy_skipping_gives_the_same_image():
    f = BallField()
    cam = PinholeCamera.from_fov(16, 16, 40.0)
    T = look_at((3.0, 1.0, 1.0), (0.0, 0.0, 0.0))
    grid = OccupancyGrid(16).update(f, times=(0.0, 1.0), dilate=1)
    assert 0.0 < grid.fraction_occupied < 0.2
    ref = render_image(f, cam, T, 0.5, BOX, 64)
    skip = render_image(f, cam, T, 0.5, BOX, 64, occupancy=grid)
    assert float(ref.max()) > 0.1
    torch.testing.assert_close(skip, ref, atol=1e-6, rtol=0)
    grid.enabled = False
    assert bool(grid.query(torch.zeros(3, 3)).all())
    # from an event footprint (voxel grid over the box), resampled to the grid
    fp = np.zeros((8, 8, 8), dtype=bool)
    fp[4, 3, 4] = True
    g2 = OccupancyGrid.from_footprint(fp, resolution=16)
    assert int(g2.occupied.sum()) == 8
    g3 = OccupancyGrid.from_footprint(fp, dilate=1)
    assert int(g3.occupied.sum()) == 27
    assert bool(g3.query(torch.tensor([[0.125, -0.125, 0.125]]))[0])
    assert not bool(g3.query(torch.tensor([[-0.9, -0.9, -0.9]]))[0])


def test_planes_fit_a_tiny_target_image():
    torch.manual_seed(0)
    f = small_planes()
    cam = PinholeCamera.from_fov(8, 8, 40.0)
    T = look_at((0.0, -4.0, 0.5), (0.0, 0.0, 0.0))
    o, d = camera_rays(cam, T)
    yy, xx = torch.meshgrid(torch.arange(8.0), torch.arange(8.0), indexing="ij")
    target = (0.2 + 0.6 * ((xx + yy) % 4 < 2).float()).reshape(-1)
    opt = torch.optim.Adam(f.parameters(), lr=0.05)

    def loss_now():
        return ((render_rays(f, o, d, 0.3, BOX, 16)["grey"] - target) ** 2).mean()

    with torch.no_grad():
        l0 = float(loss_now())
    for _ in range(30):
        opt.zero_grad()
        loss = loss_now()
        loss.backward()
        opt.step()
    with torch.no_grad():
        l1 = float(loss_now())
    assert l1 < 0.5 * l0


@pytest.mark.parametrize("make", [small_planes, small_dnerf], ids=["planes", "dnerf"])
def test_forward_backward_extreme_inputs_finite(make):
    f = make()
    faces = torch.tensor([[-1.0, 0.0, 0.3], [1.0, 0.2, -0.1], [0.5, -1.0, 1.0],
                          [1.0, 1.0, 1.0], [-1.0, -1.0, -1.0], [0.0, 0.0, 0.0]])
    for tv in (0.0, 1.0):
        t = torch.full((faces.shape[0], 1), tv)
        dens, grey = f(faces, t)
        (dens.sum() + grey.sum()).backward()
        assert torch.isfinite(dens).all() and torch.isfinite(grey).all()
        for p in f.parameters():
            assert p.grad is None or torch.isfinite(p.grad).all()
    # rays grazing the box faces and a ray along an edge, rendered at t = 0 and 1
    o = torch.tensor([[-3.0, 1.0, 0.0], [-3.0, -1.0, -1.0], [0.0, 0.0, -3.0]])
    d = torch.tensor([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    outs = render_rays(f, o, d, [0.0, 1.0], BOX, 8)
    (outs[0]["grey"].sum() - outs[1]["grey"].sum()).backward()
    for r in outs:
        assert torch.isfinite(r["grey"]).all()
    for p in f.parameters():
        assert p.grad is None or torch.isfinite(p.grad).all()


def test_normalized_time_from_int64_differences():
    from evdnerf_ros.field import normalized_time
    t0 = 10_000 * 10**9 + 123                  # absolute timestamps around 1e4 s
    t = np.array([t0, t0 + 1_000, t0 + 500_000_000, t0 + 10**9, t0 + 2 * 10**9], np.int64)
    u = normalized_time(t, t0, t0 + 10**9)
    assert u.dtype == torch.float32
    assert u.tolist() == [0.0, pytest.approx(1e-6, rel=1e-6), 0.5, 1.0, 1.0]


def test_dynamic_field_is_abstract():
    with pytest.raises(TypeError):
        DynamicField()


def test_planes_decode_at_one_time_equals_decode():
    """The publisher's playback path (rows blended at t, then gathered at precomputed columns)
    gives decode's density and grey to float rounding, at texel times, between them, at 0
    and 1, and for points on the box faces."""
    f = small_planes().eval()
    with torch.no_grad():
        for p in f.time_planes:
            p.add_(0.3 * torch.randn_like(p, generator=torch.Generator().manual_seed(1)))
    x = torch.rand(300, 3, generator=torch.Generator().manual_seed(2)) * 2 - 1
    x[:4] = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0], [1.0, -1.0, 0.3], [0.0, 0.0, 0.0]])
    with torch.no_grad():
        sf = f.space_features(x)
        pf = f.playback_features(sf)
        for t in (0.0, 0.2, 1 / 3, 0.5, 0.999, 1.0):
            (da, ga), (db, gb) = f.decode_per_point(sf, torch.full((300, 1), t)), f.decode_at(pf, t)
            assert float((da - db).abs().max()) < 1e-5 and float((ga - gb).abs().max()) < 1e-6


@pytest.mark.parametrize("times", [6, 2])
def test_planes_decode_at_one_time_has_the_bilinear_gradient(times):
    """Training batches share one time per window edge, so ``decode`` takes the row-blend path
    there: its values and the gradients of every plane and decoder weight equal the bilinear
    lookup's (to float rounding), with several time rows or the fewest (2); mixed times take
    the bilinear path itself."""
    def grads(decode, t):
        f = small_planes(time_resolution=times)
        with torch.no_grad():
            for p in f.time_planes:
                p.add_(0.3 * torch.randn_like(p, generator=torch.Generator().manual_seed(1)))
        x = torch.rand(200, 3, generator=torch.Generator().manual_seed(2)) * 2 - 1
        density, grey = decode(f, f.space_features(x), t)
        (density.square().sum() + grey.sum()).backward()
        return density.detach(), [p.grad.clone() for p in f.parameters()]

    for t in (0.0, 0.37, 1.0):
        column = torch.full((200, 1), t)
        a, ga = grads(lambda f, sf, t: f.decode(sf, t), column)
        b, gb = grads(lambda f, sf, t: f.decode_per_point(sf, t), column)
        assert torch.allclose(a, b, atol=1e-5)
        assert all(torch.allclose(u, v, atol=1e-5, rtol=1e-4) for u, v in zip(ga, gb))
    mixed = torch.linspace(0, 1, 200).reshape(-1, 1)
    a, _ = grads(lambda f, sf, t: f.decode(sf, t), mixed)
    b, _ = grads(lambda f, sf, t: f.decode_per_point(sf, t), mixed)
    assert torch.equal(a, b)

