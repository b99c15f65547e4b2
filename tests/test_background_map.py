"""The learned background (``field.BackgroundMap``): grey per ray direction, carried by the
field through training, checkpoints, evaluation and the publisher's renderer."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from evdnerf_ros.errors import InputError
from evdnerf_ros.field import BackgroundMap, make_field, render_rays
from evdnerf_ros.geometry.camera import PinholeCamera, look_at
from evdnerf_ros.train.config import TrainConfig, field_from_config


def _dirs(azimuth_deg, elevation_deg):
    a, e = np.radians(azimuth_deg), np.radians(elevation_deg)
    return torch.tensor(np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], -1),
                        dtype=torch.float32)


def test_starts_at_its_grey_and_wraps_in_azimuth():
    m = BackgroundMap(16, 0.25)
    d = _dirs(np.linspace(-180, 180, 37), np.linspace(-90, 90, 37))
    np.testing.assert_allclose(m(d).detach().numpy(), 0.25, rtol=0, atol=1e-6)
    with torch.no_grad():
        m.fine.normal_(generator=torch.Generator().manual_seed(0))
        m.coarse.normal_(generator=torch.Generator().manual_seed(1))
    # azimuth +180 and -180 are one direction; so are 179.999 and -179.999 (nearly)
    both = m(_dirs([180.0, -180.0, 179.999, -179.999], [10.0, 10.0, -20.0, -20.0])).detach().numpy()
    assert both[0] == pytest.approx(both[1], abs=1e-6)
    assert both[2] == pytest.approx(both[3], abs=1e-3)
    # length of the direction does not matter; grey stays in (0, 1)
    d2 = _dirs([33.0], [12.0])
    with torch.no_grad():
        assert float(m(d2)) == pytest.approx(float(m(3.7 * d2)), abs=1e-6)
    g = m(_dirs(np.linspace(-180, 180, 101), np.linspace(-90, 90, 101))).detach().numpy()
    assert np.all((g > 0) & (g < 1))


def test_bad_sizes_are_refused():
    with pytest.raises(ValueError, match="at least 8"):
        BackgroundMap(4, 0.5)
    with pytest.raises(ValueError, match=r"\(0, 1\)"):
        BackgroundMap(16, 0.0)
    with pytest.raises(InputError, match="background_cells"):
        TrainConfig(background_cells=4, background=0.25)
    with pytest.raises(InputError, match="background.*strictly between 0 and 1"):
        TrainConfig(background_cells=64, background=0.0)       # background 0: no logit
    assert TrainConfig(background_cells=64, background=0.25).background_cells == 64


def test_a_run_saved_before_the_map_and_spans_loads_as_it_was():
    """A checkpoint's config written before background_cells, span_fraction and empty_weight existed (with
    the old constant background 0) keeps that behaviour; a new config gets today's defaults."""
    old = {k: v for k, v in TrainConfig(backbone="planes").to_dict().items()
           if k not in ("background_cells", "span_fraction", "empty_weight")}
    old["background"] = 0.0
    cfg = TrainConfig.from_dict(old, saved=True)
    assert cfg.background_cells == 0 and cfg.span_fraction == 0.0 and cfg.background == 0.0
    assert cfg.empty_weight == 0.0
    assert getattr(field_from_config(cfg), "background_map", None) is None
    with pytest.raises(InputError, match="background"):
        TrainConfig.from_dict(old)                             # read as a new config: refused
    assert TrainConfig().background_cells > 0 and TrainConfig().span_fraction > 0


def test_rays_missing_the_box_see_the_map_and_it_learns():
    """A ray that leaves the box unoccluded renders the map's grey of its direction; a
    gradient step on such rays moves only the map (no field sample lies on them)."""
    torch.manual_seed(0)
    field = make_field("planes", resolutions=[4], time_resolution=2, features=2, hidden=4,
                       background_cells=32, background_grey=0.3)
    box = [[-1, -1, -1], [1, 1, 1]]
    o = torch.tensor([[0.0, -5.0, 3.0], [0.0, -5.0, -3.0]])          # rays passing above / below
    d = torch.nn.functional.normalize(torch.tensor([[0.0, 1.0, 0.1], [0.0, 1.0, -0.2]]), dim=1)
    r = render_rays(field, o, d, 0.5, box, 8, background=0.9)          # the constant is not used
    np.testing.assert_allclose(r["grey"].detach().numpy(), 0.3, atol=1e-6)
    assert float(r["opacity"].abs().max()) == 0.0
    target = torch.tensor([0.6, 0.1])
    opt = torch.optim.Adam(field.background_map.parameters(), lr=0.1)
    for _ in range(200):
        opt.zero_grad()
        loss = ((render_rays(field, o, d, 0.5, box, 8)["grey"] - target) ** 2).sum()
        loss.backward()
        opt.step()
    np.testing.assert_allclose(render_rays(field, o, d, 0.5, box, 8)["grey"].detach().numpy(),
                               target.numpy(), atol=0.02)


def test_config_builds_it_and_a_checkpoint_keeps_it(tmp_path):
    from evdnerf_ros.train.checkpoint import save_checkpoint
    from evdnerf_ros.train.ranges import field_parameters
    from evdnerf_ros.train.run import TrainedRun

    cfg = TrainConfig(backbone="planes", background=0.25, background_cells=64, n_samples=8,
                      field=dict(resolutions=[8], time_resolution=4, features=4, hidden=8))
    torch.manual_seed(2)
    field = field_from_config(cfg)
    assert field.background_map is not None
    assert field_parameters(cfg) == sum(p.numel() for p in field.parameters())
    with torch.no_grad():
        field.background_map.fine.uniform_(-1, 1)
    save_checkpoint(tmp_path / "checkpoint.pt", field=field, optimizer=None, iteration=1,
                    config=cfg.to_dict(), backbone=cfg.backbone, rng={}, box=[[-1, -1, -1], [1, 1, 1]],
                    extra={"train_set": {"time_range_ns": [0, 10 ** 9], "thresholds": [0.2, 0.2]}})
    run = TrainedRun.load(tmp_path)
    d = _dirs(np.linspace(-170, 170, 9), np.linspace(-60, 60, 9))
    np.testing.assert_array_equal(run.field.background_map(d).detach().numpy(),
                                  field.background_map(d).detach().numpy())
    plain = field_from_config(TrainConfig(backbone="planes", background_cells=0))
    assert getattr(plain, "background_map", None) is None


@pytest.mark.parametrize("bake", [False, True])
def test_publisher_renderer_draws_the_map_like_render_image(tmp_path, bake):
    """The publisher's planned renderer (leave-out, static reuse, baked or not) gives every
    pixel the map's grey where its ray leaves the box, as the plain render does."""
    from evdnerf_ros.field import render_image
    from evdnerf_ros.field.baked import BakedField
    from evdnerf_ros.field.renderer import FieldRenderer

    torch.manual_seed(5)
    field = make_field("planes", resolutions=[8], time_resolution=4, features=4, hidden=8,
                       background_cells=32, background_grey=0.4).eval()
    with torch.no_grad():
        field.background_map.fine.uniform_(-2, 2)
    box = [[-0.5, -0.5, -0.5], [0.5, 0.5, 0.5]]
    if bake:
        field = BakedField.bake(field, resolution=9, times=3)
        assert field.background_map is not None
    cam = PinholeCamera.from_fov(20, 16, 60.0)
    T = look_at([0.3, -3.0, 0.8], [0.0, 0.0, 0.0])
    r = FieldRenderer(field, cam, box, duration_ns=10 ** 9, n_samples=12)
    with torch.no_grad():
        want = render_image(field, cam, T, 0.5, box, 12).numpy()
    for _ in range(2):                                   # the second call reuses the plan
        np.testing.assert_allclose(r.render(T, 500_000_000), want, rtol=0, atol=1e-6)
    assert r.rays_rendered < r.rays_total                 # rays missing the box were left out
    assert np.ptp(want) > 0.1 and not math.isnan(float(want.sum()))


def test_flat_static_world_is_the_field_without_its_static_part():
    """``static_world="flat"``: every sample outside the dynamic region is empty and every ray
    ends on one grey (the background map's mean over the sphere), and only rays through the
    region are traced: equal to a full render of that field, at a moving camera's poses."""
    from evdnerf_ros.errors import InputError
    from evdnerf_ros.field import render_image
    from evdnerf_ros.field.dynamic_region import DynamicRegion
    from evdnerf_ros.field.render import flat_background
    from evdnerf_ros.field.renderer import FieldRenderer

    torch.manual_seed(7)
    field = make_field("planes", resolutions=[8], time_resolution=4, features=4, hidden=8,
                       background_cells=32, background_grey=0.4).eval()
    with torch.no_grad():
        field.background_map.fine.uniform_(-2, 2)
        for tp in field.time_planes:
            tp.uniform_(0.0, 3.0)
        for sp in field.space_planes:                   # dense enough to show against the backdrop
            sp.uniform_(1.0, 3.0)
    box = [[-0.5, -0.5, -0.5], [0.5, 0.5, 0.5]]
    mask = torch.zeros((8, 8, 8), dtype=torch.bool)
    mask[3:5, 3:5, 2:6] = True
    region = DynamicRegion(mask)
    grey = flat_background(field, 0.25)
    assert 0.0 < grey < 1.0 and grey != pytest.approx(0.4, abs=1e-3)     # the map's mean, not its start

    class EmptyOutside(torch.nn.Module):     # the reference: the static field made empty, the region faded
        def __init__(self, f):
            super().__init__()
            self.f = f

        def space_features(self, x):
            return self.f.space_features(x)

        def evaluate_times(self, x, times, is_dynamic):
            out = []
            fade = region.inner_weight(x)
            for dens, g in self.f.evaluate_times(x, times, is_dynamic):
                out.append((torch.where(is_dynamic, dens * fade, torch.zeros_like(dens)), g))
            return out

    cam = PinholeCamera.from_fov(20, 16, 60.0)
    r = FieldRenderer(field, cam, box, duration_ns=10 ** 9, n_samples=12, dynamic=region, static_world="flat")
    for k, t in enumerate((200_000_000, 700_000_000)):              # a moving camera: new pose each time
        T = look_at([0.3 + 0.2 * k, -3.0, 0.8], [0.0, 0.0, 0.0])
        with torch.no_grad():
            want = render_image(EmptyOutside(field), cam, T, t / 1e9, box, 12, dynamic=region,
                                background=grey).numpy()
        np.testing.assert_allclose(r.render(T, t), want, rtol=0, atol=1e-6)
        with torch.no_grad():                            # render_image's own flat static world
            flat = render_image(field, cam, T, t / 1e9, box, 12, dynamic=region, flat_background=grey).numpy()
        np.testing.assert_allclose(flat, want, rtol=0, atol=1e-6)
        assert np.ptp(want) > 0.01
    assert r.rays_rendered < 0.5 * r.rays_total            # only rays through the region were traced
    with pytest.raises(InputError, match="dynamic region"):
        FieldRenderer(field, cam, box, duration_ns=10 ** 9, static_world="flat")
    with pytest.raises(InputError, match="static_world"):
        FieldRenderer(field, cam, box, duration_ns=10 ** 9, dynamic=region, static_world="none")
    # an empty region: nothing to trace, every pixel the flat grey
    empty = DynamicRegion(torch.zeros((8, 8, 8), dtype=torch.bool))
    r = FieldRenderer(field, cam, box, duration_ns=10 ** 9, n_samples=12, dynamic=empty, static_world="flat")
    img = r.render(look_at([0.3, -3.0, 0.8], [0.0, 0.0, 0.0]), 500_000_000)
    assert r.rays_rendered == 0 and np.all(img == np.float32(grey))


def test_flat_background_of_a_uniform_map_is_its_grey():
    from evdnerf_ros.field.render import flat_background

    field = make_field("planes", resolutions=[8], time_resolution=4, features=4, hidden=8,
                       background_cells=32, background_grey=0.3)
    assert flat_background(field, 0.25) == pytest.approx(0.3, abs=1e-6)
    assert flat_background(make_field("planes", resolutions=[8], time_resolution=4, features=4, hidden=8,
                                       background_cells=0), 0.25) == 0.25
