"""The knobs of `evdnerf eval` (flags, ``--config FILE`` keys and library defaults from one place)."""

from __future__ import annotations

from dataclasses import dataclass

from ..device import DEVICE_CHOICES
from ..options import option


@dataclass(frozen=True)
class EvalOptions:
    windows: int | None = option(None, "window count", kind=int, low=1, high=100_000,
                                 none_help="the trained one")
    max_views: int | None = option(None, "evaluate at most this many views per split, spread evenly over it "
                                   "(a ring's first views would be neighbours)", kind=int, low=1,
                                   high=100_000, none_help="every view")
    train_views: int = option(4, "training views scored, spread evenly over the set (a check of the fit; the "
                              "protocol's metric is on the validation views); 0: every one", low=0, high=100_000)
    device: str = option("auto", "where the field is evaluated: auto (cuda when available), cpu or cuda",
                         choices=DEVICE_CHOICES)
    static_world: str = option("auto", "what the field shows outside its dynamic region: field (as trained), "
                               "flat (nothing, one constant grey) or auto (flat for moving views, as the "
                               "publisher plays back a moving camera; static views as trained)",
                               choices=("auto", "field", "flat"))
    published: str | None = option(None, "instead: publish from the run along its orbit (or a static novel "
                                   "view) and score the events against the simulator's along the same path "
                                   "(simulated training sets only); the flag alone means orbit", kind=str,
                                   choices=("orbit", "static"), cli=False)
    published_windows: int = option(32, "windows of the published-vs-true comparison", low=1, high=100_000,
                                    cli=False)
