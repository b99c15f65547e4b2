"""Event losses on the predicted log change dL_hat against the ground truth dL.

``dl`` is the GT change of a window, C+ N+ - C- N- (paper Eq. 5); thresholds are floats or
learned 0-d tensors; ``dl_hat`` is
log(B1 + eps) - log(B0 + eps) from the two renders.  All functions return the mean over
the rays given (a 0-d tensor; 0 for no rays).
"""

from __future__ import annotations

import torch


def bin_bounds(dl: torch.Tensor, c_pos, c_neg, *, paper: bool = False):
    """The quantisation bin [lo, hi) of every GT change.

    ``paper=False`` (polarity-aware): positive dL -> [dL, dL + C+), negative dL ->
    (dL - C-, dL], no events -> (-C-, C+): every true change that produces exactly the
    observed count.  ``paper=True``: the paper code's [dL, dL + C) for every sign, with C
    the threshold of the polarity of dL (C+ at zero), so a zero-event pixel only frees
    [0, C+).
    """
    dl = dl.to(torch.float32)
    c_pos, c_neg = _threshold(c_pos), _threshold(c_neg)
    if paper:
        return dl, dl + torch.where(dl < 0, c_neg, c_pos)
    lo = torch.where(dl > 0, dl, dl - c_neg)
    hi = torch.where(dl < 0, dl, dl + c_pos)
    return lo, hi


def bin_loss(dl_hat: torch.Tensor, dl: torch.Tensor, c_pos, c_neg, *,
             paper: bool = False) -> torch.Tensor:
    """Dead-zone bin loss: 0 inside the bin of ``dl``, else (dl_hat - bin centre)^2."""
    if dl_hat.numel() == 0:
        return dl_hat.sum()
    lo, hi = bin_bounds(dl, c_pos, c_neg, paper=paper)
    centre = 0.5 * (lo + hi)
    inside = (dl_hat >= lo) & (dl_hat <= hi) if not paper else (dl_hat >= lo) & (dl_hat < hi)
    err = (dl_hat - centre) ** 2
    return torch.where(inside, torch.zeros_like(err), err).mean()


def mse_loss(dl_hat: torch.Tensor, dl: torch.Tensor, pred_scale: float = 1.0,
             target_scale: float = 1.0) -> torch.Tensor:
    """mean((dl_hat / pred_scale - dl / target_scale)^2); the paper code uses 2.2 and
    max|E_train|."""
    if dl_hat.numel() == 0:
        return dl_hat.sum()
    return ((dl_hat / pred_scale - dl.to(torch.float32) / target_scale) ** 2).mean()


def no_event_hinge(dl_hat: torch.Tensor, dl: torch.Tensor, c_pos, c_neg,
                   no_event: torch.Tensor | None = None) -> torch.Tensor:
    """E-NeRF's relu(|dL_hat| - C) averaged over the rays without events (C+ for a
    positive prediction, C- for a negative one).  ``no_event`` (bool mask) defaults to
    ``dl == 0``; no such rays -> 0."""
    mask = (dl == 0) if no_event is None else no_event
    if not bool(mask.any()):
        return dl_hat.sum() * 0.0
    d = dl_hat[mask]
    c = torch.where(d < 0, _threshold(c_neg), _threshold(c_pos))
    return torch.relu(d.abs() - c).mean()


def _threshold(c) -> torch.Tensor:
    """A threshold as a float32 tensor: a float, or a learned 0-d tensor (keeps its gradient)."""
    return c.to(torch.float32) if torch.is_tensor(c) else torch.tensor(float(c))
