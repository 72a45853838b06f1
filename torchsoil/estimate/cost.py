"""The paper's cost (eq. cost): weighted mean L1 height difference over valid cells, m; and the
raster's blur that a simulated surface is seen through before it is compared with H_b."""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F


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


def raster_blur(h: torch.Tensor, sigma: float) -> torch.Tensor:
    """A Gaussian blur of sigma cells over (B, X, Y) or (X, Y) heights [m] (separable, edge cells
    repeated beyond the crop), differentiable; sigma = 0 returns h itself.

    A lidar heightmap is not the ground sampled at cell centres: each cell averages points
    whose positions carry the sweeps' pose errors, the beams' spots and the de-skew, so a rut's
    sharp wall comes out spread over a cell or two. The simulated change is seen through this
    blur before it is compared with H_b (estimator.after_blur); its total is kept (the kernel
    sums to 1)."""
    if sigma <= 0:
        return h
    r = max(1, math.ceil(3 * sigma))
    x = torch.arange(-r, r + 1, dtype=h.dtype, device=h.device)
    k = torch.exp(-0.5 * (x / sigma) ** 2)
    k = k / k.sum()
    flat = h.reshape(-1, 1, *h.shape[-2:])
    flat = F.conv2d(F.pad(flat, (0, 0, r, r), mode="replicate"), k.view(1, 1, -1, 1))
    flat = F.conv2d(F.pad(flat, (r, r, 0, 0), mode="replicate"), k.view(1, 1, 1, -1))
    return flat.reshape(h.shape)
