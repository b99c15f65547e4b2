"""Fields for EvDNeRF: one interface (density and grey at x, t) and four backbones.

- ``DynamicField`` (base): ``forward(x, t) -> (density, grey)`` plus the static-view reuse
  pair ``space_features(x)`` / ``decode(features, t)``.
- ``PlanesField`` (``planes``, default): K-Planes/HexPlane-style factorised 4D field.
- ``DNeRFField`` (``dnerf``): the paper's deformation + canonical MLPs.
- ``HingeField`` (``hinge``): a static world and one rigid part on the rig's known joint.
- ``RigidField`` (``rigid``): a static world and one rigid part whose pose is learned.
- ``render``: rays, ray-box intersection, sampling, volume rendering.
- ``FieldRenderer``: a field as a ``evdnerf_ros.renderer.Renderer`` (``renderer.py``).
- ``OccupancyGrid``: empty-space skipping (from the field or an event footprint).
- ``DynamicRegion``: where the scene may change (visual hull of the event footprints).
"""

from .background import BackgroundMap
from .base import DynamicField, normalized_time
from .dnerf import DNeRFField, positional_encoding
from .dynamic_region import DynamicRegion, event_footprint
from .occupancy import OccupancyGrid
from .hinge import HingeField
from .planes import PlanesField
from .rigid import RigidField
from .render import (camera_rays, normalize_points, ray_box_intersect, render_image,
                     render_rays, sample_along_rays, volume_weights)
from .renderer import FieldRenderer

BACKBONES = {"planes": PlanesField, "dnerf": DNeRFField, "hinge": HingeField, "rigid": RigidField}


def make_field(name: str = "planes", *, background_cells: int = 0, background_grey: float = 0.5,
               **kwargs) -> DynamicField:
    """Build a backbone by name (``planes``, ``dnerf``, ``hinge`` or ``rigid``) with its keyword sizes; with
    ``background_cells`` > 0 it carries a learned ``BackgroundMap`` of that many azimuth
    cells, starting at ``background_grey`` everywhere."""
    try:
        cls = BACKBONES[name]
    except KeyError:
        raise ValueError(f"unknown field backbone {name!r}; choose from "
                         f"{sorted(BACKBONES)}") from None
    field = cls(**kwargs)
    if background_cells:
        field.background_map = BackgroundMap(background_cells, background_grey)
    return field


__all__ = ["BackgroundMap", "DynamicField", "PlanesField", "DNeRFField", "HingeField", "RigidField", "OccupancyGrid", "DynamicRegion", "FieldRenderer",
           "event_footprint", "BACKBONES",
           "make_field", "normalized_time", "camera_rays", "normalize_points", "ray_box_intersect",
           "render_image", "render_rays", "sample_along_rays", "volume_weights",
           "positional_encoding"]
