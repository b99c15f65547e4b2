"""Board images from events: what a frame camera would have seen, made from an event stream.

Two recording styles (docs/calibration.md):

* **blink** (the Prophesee SDK's blinking-pattern calibration): the board blinks on a screen
  (or a lamp behind a print) while camera and board hold still, then one of them is moved to
  the next pose, and so on. Each blink-on is a burst of ON events on the board's white squares
  (the black squares barely change), each blink-off a burst of OFF events there. The events
  are binned (``bin_ns``); bins with many events (``>= burst_fraction`` of the busiest bin's
  count, and >= ``min_events``) joined across gaps of at most ``gap_ns`` form bursts; a burst
  whose events are at least ``min_polarity_share`` of one polarity is a blink (an edge burst
  of a moving board has both polarities and is dropped), and its image is the per-pixel count
  of that polarity's events: white squares bright, black squares and background dark.
* **window** (a board moved in front of the camera): the count of all events per pixel in
  consecutive windows of ``window_ns``: edge images of the moving board. Without a blinking
  board these show only the square edges; ChArUco detection then works only with slow,
  sharp motion (an e2calib-style intensity reconstruction is not done here).

Everything is vectorised: one ``np.bincount`` per image, burst finding on the binned counts.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import InputError


@dataclass
class BoardImage:
    """One image made from events: (height, width) float32 counts and where it came from."""

    image: np.ndarray
    t_start_ns: int
    t_end_ns: int
    polarity: int          # +1: ON events (blink-on), -1: OFF (blink-off), 0: both (window)
    events: int            # events counted into the image
    source: str = ""       # the file / view it came from


def _check(events, width: int, height: int, where: str) -> np.ndarray:
    if events.dtype.names is None or not {"t", "x", "y", "p"} <= set(events.dtype.names):
        raise InputError(f"{where}: not an event array (needs fields t, x, y, p)")
    if not (isinstance(width, (int, np.integer)) and isinstance(height, (int, np.integer))
            and width > 0 and height > 0):
        raise InputError(f"{where}: sensor size unknown ({width}x{height}); give the geometry")
    if events.size and (int(events["x"].max()) >= width or int(events["y"].max()) >= height):
        raise InputError(f"{where}: events lie outside the {width}x{height} sensor; wrong geometry")
    return events


def count_image(events: np.ndarray, width: int, height: int) -> np.ndarray:
    """(height, width) float32 count of `events` per pixel."""
    idx = events["y"].astype(np.int64) * width + events["x"].astype(np.int64)
    return np.bincount(idx, minlength=width * height).reshape(height, width).astype(np.float32)


def blink_images(events: np.ndarray, width: int, height: int, *, bin_ns: int = 1_000_000,
                 gap_ns: int = 2_000_000, burst_fraction: float = 0.05, min_events: int = 50,
                 min_polarity_share: float = 0.8, polarity: str = "both",
                 source: str = "events") -> tuple[list[BoardImage], dict]:
    """Board images of the blinks in `events` (sorted by t); see the module doc.

    `polarity`: ``on`` keeps blink-on images, ``off`` blink-off ones, ``both`` both.
    Returns (images, counts) where counts says how many bursts were found and why any were
    dropped (``mixed``: no dominant polarity, ``polarity``: not the one asked for)."""
    _check(events, width, height, source)
    if polarity not in ("on", "off", "both"):
        raise InputError(f"polarity must be on, off or both, got {polarity!r}")
    if not (bin_ns > 0 and gap_ns >= 0 and 0 < burst_fraction <= 1 and min_events >= 1
            and 0.5 < min_polarity_share <= 1):
        raise InputError("blink detection: need bin_ns > 0, gap_ns >= 0, burst_fraction in "
                         "(0, 1], min_events >= 1, min_polarity_share in (0.5, 1]")
    counts = {"bursts": 0, "mixed": 0, "polarity": 0}
    if events.size == 0:
        return [], counts
    t = events["t"]
    t0 = int(t[0])
    b = (t - t0) // int(bin_ns)                     # int64 bin of every event
    nb = int(b[-1]) + 1
    if nb > 50_000_000:
        raise InputError(f"{source}: {nb} bins of {bin_ns} ns: the recording is too long for this "
                         "bin size; give a larger --bin")
    per_bin = np.bincount(b, minlength=nb)
    level = max(float(min_events), burst_fraction * float(per_bin.max()))
    active = np.flatnonzero(per_bin >= level)
    if active.size == 0:
        return [], counts
    # runs of active bins, joined over gaps of at most gap_ns
    max_gap = int(gap_ns) // int(bin_ns) + 1
    breaks = np.flatnonzero(np.diff(active) > max_gap)
    first = np.concatenate([[active[0]], active[breaks + 1]])
    last = np.concatenate([active[breaks], [active[-1]]])
    lo = np.searchsorted(b, first, side="left")
    hi = np.searchsorted(b, last, side="right")
    on = np.concatenate([[0], np.cumsum(events["p"] > 0)])
    images = []
    for a, z in zip(lo.tolist(), hi.tolist()):
        counts["bursts"] += 1
        n = z - a
        n_on = int(on[z] - on[a])
        share_on = n_on / n
        if max(share_on, 1 - share_on) < min_polarity_share:
            counts["mixed"] += 1
            continue
        pol = 1 if share_on >= 0.5 else -1
        if (polarity == "on" and pol < 0) or (polarity == "off" and pol > 0):
            counts["polarity"] += 1
            continue
        part = events[a:z]
        part = part[(part["p"] > 0) == (pol > 0)]
        images.append(BoardImage(count_image(part, width, height), int(t[a]), int(t[z - 1]), pol,
                                 int(part.size), source))
    return images, counts


def window_images(events: np.ndarray, width: int, height: int, *, window_ns: int = 10_000_000,
                  min_events: int = 50, source: str = "events") -> tuple[list[BoardImage], dict]:
    """Event-count (edge) images over consecutive windows of `window_ns`; windows with fewer
    than `min_events` events are skipped (counted as ``empty``)."""
    _check(events, width, height, source)
    if not window_ns > 0:
        raise InputError(f"window must be > 0 ns, got {window_ns}")
    counts = {"windows": 0, "empty": 0}
    if events.size == 0:
        return [], counts
    t = events["t"]
    t0 = int(t[0])
    w = (t - t0) // int(window_ns)
    edges = np.flatnonzero(np.diff(w)) + 1
    lo = np.concatenate([[0], edges])
    hi = np.concatenate([edges, [t.size]])
    images = []
    for a, z in zip(lo.tolist(), hi.tolist()):
        counts["windows"] += 1
        if z - a < min_events:
            counts["empty"] += 1
            continue
        k = int(w[a])
        images.append(BoardImage(count_image(events[a:z], width, height), t0 + k * int(window_ns),
                                 t0 + (k + 1) * int(window_ns) - 1, 0, z - a, source))
    return images, counts
