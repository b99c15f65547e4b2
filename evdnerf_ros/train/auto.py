"""``backbone: auto``: the field that fits what the training set records.

- ``hinge`` where the set records the rig's joint (``provenance.joint``: the servo is the scene's
  only motion, and its angle over time is known), so only the part's shape is learned;
- ``rigid`` where the events show one compact moving part: ``train.track.find_track`` finds its
  per-time visual hull in at least ``MIN_TRACKED`` of the time bins, and the part's radius is at
  most ``MAX_PART_RADIUS`` of the scene box's half-diagonal (a hull that fills the box is
  several parts or a deforming scene);
- else ``planes``, which learns any change (and ``planes`` for frames supervision, whose
  baseline the paper runs on a general field).

Each choice comes with the reason the trainer logs and records.
"""

from __future__ import annotations

import numpy as np

#: The backbones ``auto`` chooses from.
CHOICES = ("hinge", "planes", "rigid")
#: Share of the time bins whose hull must hold the part for a track to count as found.
MIN_TRACKED = 0.5
#: Largest part radius, as a share of the scene box's half-diagonal, that ``rigid`` takes.
MAX_PART_RADIUS = 0.5


def choose_backbone(train_set, box, cfg) -> tuple[str, str, dict]:
    """(backbone, why, field keys it found on the way) for ``train_set`` in the scene ``box``
    (``cfg``: the dynamic region's carving options). The keys are ``{"track": ...}`` where
    ``rigid`` is chosen, so its track is carved once."""
    from .track import find_track

    if cfg.supervision != "events":
        return "planes", f"supervision is {cfg.supervision}", {}
    if train_set.provenance.get("joint"):
        return "hinge", "the training set records the rig's joint", {}
    found = find_track(train_set, box, resolution=cfg.dynamic_resolution, min_events=cfg.dynamic_min_events,
                       dilate_px=cfg.dynamic_dilate_px, misses=cfg.dynamic_misses)
    if found is None:
        return "planes", "the set has no static training view to track a moving part with", {}
    if found.track is None:
        return "planes", "no time bin's events agree on a moving part between the training views", {}
    if found.bins_found < MIN_TRACKED * found.bins:
        return "planes", (f"a moving part was found in {found.bins_found} of {found.bins} time bins "
                          f"(rigid needs {MIN_TRACKED:.0%})"), {}
    lo, hi = (np.asarray(b, np.float64) for b in box)
    share = found.track["radius"] / float(np.linalg.norm((hi - lo) / 2.0))
    if share > MAX_PART_RADIUS:
        return "planes", (f"what moves spans {share:.2f} of the scene box's half-diagonal (rigid takes one "
                          f"compact part, up to {MAX_PART_RADIUS})"), {}
    return "rigid", (f"one moving part tracked in {found.bins_found} of {found.bins} time bins, radius "
                     f"{share:.2f} of the scene box's half-diagonal"), {"track": found.track}
