"""Learned contrast thresholds (as in Ev-NeRF / Robust e-NeRF), optional.

The GT change of a window is C+ N+ - C- N- (paper Eq. 5).  Real sensors' C+ and C- are
not known exactly and differ from each other, so the trainer may learn them.  Events alone
fix log-intensity changes only up to one overall scale (halve both thresholds and the
field's contrast and the loss is unchanged), so the mean (C+ + C-)/2 stays at the training
set's value and only the balance is learned:

    C+ = C_mean (1 + tanh a),   C- = C_mean (1 - tanh a),

with ``a`` initialised from the training set's C+/C-: both stay positive and the start
reproduces the fixed-threshold targets exactly.
"""

from __future__ import annotations

import math

import torch


class LearnedThresholds(torch.nn.Module):
    def __init__(self, c_pos: float, c_neg: float):
        super().__init__()
        c_pos, c_neg = float(c_pos), float(c_neg)
        if not (c_pos > 0 and c_neg > 0 and math.isfinite(c_pos + c_neg)):
            raise ValueError(f"thresholds must be finite and > 0, got C+={c_pos}, C-={c_neg}")
        self.c_mean = 0.5 * (c_pos + c_neg)
        self.balance = torch.nn.Parameter(
            torch.tensor(math.atanh((c_pos - c_neg) / (c_pos + c_neg)), dtype=torch.float32))

    def forward(self) -> tuple[torch.Tensor, torch.Tensor]:
        """(C+, C-) as 0-d tensors carrying gradients."""
        b = torch.tanh(self.balance)
        return self.c_mean * (1 + b), self.c_mean * (1 - b)

    def log_change(self, counts: torch.Tensor) -> torch.Tensor:
        """dL = C+ N+ - C- N- of (N, 2) (positive, negative) counts."""
        c_pos, c_neg = self()
        counts = counts.to(torch.float32)
        return c_pos * counts[:, 0] - c_neg * counts[:, 1]

    def values(self) -> tuple[float, float]:
        with torch.no_grad():
            c_pos, c_neg = self()
        return float(c_pos), float(c_neg)
