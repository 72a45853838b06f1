"""The paper's cost (eq. cost): weighted mean L1 height difference over valid cells, m."""

from __future__ import annotations

import torch


def weighted_l1(h: torch.Tensor, target: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
    """sum(w |h - target|) / sum(w).

    Args:
        h: (B, X, Y) or (X, Y) heights, m.
        target: (X, Y) measured heights, m (finite wherever weight > 0).
        weight: (X, Y) cell weights (0/1 in the paper).

    Returns:
        (B,) or () cost in metres; NaN when the weights sum to zero.
    """
    w = weight.to(h.dtype)
    total = w.sum()
    diff = (h - target).abs() * w
    return diff.flatten(-2).sum(-1) / total if total > 0 else diff.flatten(-2).sum(-1) * float("nan")
