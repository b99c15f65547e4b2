"""Fields for EvDNeRF: one interface (density and grey at x, t) and two backbones.

- ``DynamicField`` (base): ``forward(x, t) -> (density, grey)`` plus the static-view reuse
  pair ``space_features(x)`` / ``decode(features, t)``.
- ``PlanesField`` (``planes``, default): K-Planes/HexPlane-style factorised 4D field.
- ``DNeRFField`` (``dnerf``): the paper's deformation + canonical MLPs.
- ``render``: rays, ray-box intersection, sampling, volume rendering.
- ``FieldRenderer``: a field as a ``evdnerf_ros.renderer.Renderer`` (``renderer.py``).
- ``OccupancyGrid``: empty-space skipping (from the field or an event footprint).
- ``DynamicRegion``: where the scene may change (visual hull of the event footprints).
"""

from .base import DynamicField, normalized_time
from .dnerf import DNeRFField, positional_encoding
from .dynamic_region import DynamicRegion, event_footprint
from .occupancy import OccupancyGrid
from .planes import PlanesField
from .render import (camera_rays, normalize_points, ray_box_intersect, render_image,
                     render_rays, sample_along_rays, volume_weights)
from .renderer import FieldRenderer

BACKBONES = {"planes": PlanesField, "dnerf": DNeRFField}


def make_field(name: str = "planes", **kwargs) -> DynamicField:
    """Build a backbone by name (``planes`` or ``dnerf``) with its keyword sizes."""
    try:
        cls = BACKBONES[name]
    except KeyError:
        raise ValueError(f"unknown field backbone {name!r}; choose from "
                         f"{sorted(BACKBONES)}") from None
    return cls(**kwargs)


__all__ = ["DynamicField", "PlanesField", "DNeRFField", "OccupancyGrid", "DynamicRegion", "FieldRenderer",
           "event_footprint", "BACKBONES",
           "make_field", "normalized_time", "camera_rays", "normalize_points", "ray_box_intersect",
           "render_image", "render_rays", "sample_along_rays", "volume_weights",
           "positional_encoding"]
