"""Where the moving part is over time, from the events alone: the ``rigid`` field's first track.

A static camera sees events where something moved during a time bin, so the visual hull of the
views' event footprints *in one bin* (``field.dynamic_region.carve``) holds what moved then: its
centroid is a first guess of the part's centre at that bin's middle (space carving per time, as
the dynamic region is for the whole span). Bins with an empty hull (nothing moved, or it was out
of sight) take their neighbours' centre (linear between, flat beyond). The field refines it.
Only voxels seen by half the views count (a box corner seen by one view is carved by nothing).
How far the hulls reach from their centroids (the median over the bins of the 99th percentile of
the voxels' distances, with a margin) bounds the part: its ``radius``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import InputError
from ..field.dynamic_region import carve, event_footprints

#: Time bins carved (each ~1/16 of the span: long enough for every view to see the part's edges
#: move, short enough that the part moves less than its size).
TRACK_BINS = 16
#: Pose knots over the span (~1/32 of it apart; the field learns them).
TRACK_KNOTS = 33
#: The part's radius over the hulls' reach (a hull is the part swept over its bin, plus what
#: the views cannot carve away: an overestimate already; the margin keeps the border empty).
RADIUS_MARGIN = 1.15


@dataclass(frozen=True)
class FoundTrack:
    """What carving the events per time bin found: the track (None where no bin's hull holds
    anything) and in how many of the ``bins`` bins a hull was found."""
    track: dict | None
    bins_found: int
    bins: int


def find_track(train_set, box, *, bins: int = TRACK_BINS, knots: int = TRACK_KNOTS,
               resolution: int = 64, min_events: int = 1, dilate_px: int = 1,
               misses: int = 0) -> FoundTrack | None:
    """The moving part's track for the scene ``box`` (``RigidField``'s ``track``: the centre,
    box-normalised, at ``knots`` times over the span, the box's half extents and the part's
    radius in metres) and how many time bins it rests on; None where the set has no static
    training view to carve with."""
    static = [v for v in train_set.train_views if train_set.poses(v) is None]
    if not static:
        return None
    t0, t1 = (int(v) for v in train_set.time_range)
    edges = t0 + (np.arange(bins + 1, dtype=np.int64) * (t1 - t0)) // bins
    edges[-1] = t1 + 1                               # the last bin keeps events at t1
    footprints = {v: event_footprints(train_set, v, edges, min_events=min_events, dilate_px=dilate_px)
                  for v in static}
    hulls = carve(train_set, box, footprints, resolution=resolution, misses=misses,
                  min_seen=(len(static) + 1) // 2)
    r = hulls.shape[1]
    axis = (np.arange(r) + 0.5) / r * 2.0 - 1.0      # voxel centres, box-normalised
    grid = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3)
    found = [b for b in range(bins) if hulls[b].any()]
    if not found:
        return FoundTrack(None, 0, bins)
    lo, hi = (np.asarray(b, np.float64) for b in box)
    half = (hi - lo) / 2.0
    centres, reach = [], []
    for b in found:
        voxels = grid[hulls[b].reshape(-1)]
        centres.append(voxels.mean(0))
        reach.append(np.percentile(np.linalg.norm((voxels - centres[-1]) * half, axis=1), 99))
    centres = np.stack(centres)
    voxel = float(np.linalg.norm(half * 2.0 / r))
    mid = (np.asarray(found, np.float64) + 0.5) / bins
    u = np.linspace(0.0, 1.0, int(knots))
    track = np.stack([np.interp(u, mid, centres[:, i]) for i in range(3)], 1)
    return FoundTrack({"centre": track.round(6).tolist(), "half": half.tolist(),
                       "radius": round(RADIUS_MARGIN * float(np.median(reach)) + voxel, 6)},
                      len(found), bins)


def track_from_events(train_set, box, **carving) -> dict:
    """``find_track``'s track; an InputError naming the set where there is none."""
    where = getattr(train_set, "path", "training set")
    found = find_track(train_set, box, **carving)
    if found is None:
        raise InputError(f"{where}: backbone rigid tracks the moving part with static training views, "
                         "and the set has none; train with backbone planes")
    if found.track is None:
        raise InputError(f"{where}: backbone rigid found no moving part (no time bin's events agree "
                         "between the training views); train with backbone planes")
    return found.track
