"""Wheel-soil interaction: the wheels dig their footprints into the surface (paper eq. lower).

h <- min(h, h_ref - s * d) over each circular footprint, where h_ref is the surface before
the robot smoothed over a small disc and s the centrality taper across the wheel.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F


def taper(q: torch.Tensor, flat_fraction: float = 0.0) -> torch.Tensor:
    """Centrality factor s(q) in [0, 1] for q = lateral offset / footprint radius (any shape).

    s = 1 for |q| <= f, then (1 + cos(pi (|q| - f) / (1 - f))) / 2 down to 0 at |q| = 1,
    0 beyond (FORMATS.md section 2).
    """
    a = q.abs()
    u = ((a - flat_fraction) / (1.0 - flat_fraction)).clamp(0.0, 1.0)
    return 0.5 * (1.0 + torch.cos(math.pi * u))


def disc_kernel(radius_cells: float, like: torch.Tensor) -> torch.Tensor:
    """(1, 1, k, k) 0/1 kernel of the cells whose centres lie within radius_cells of the centre."""
    r = int(math.floor(radius_cells))
    ax = torch.arange(-r, r + 1, device=like.device, dtype=like.dtype)
    return ((ax[:, None] ** 2 + ax[None, :] ** 2) <= radius_cells**2 + 1e-9).to(like.dtype)[None, None]


def reference_height(h: torch.Tensor, radius: float, dx: float) -> torch.Tensor:
    """Local reference height h~: mean of h over a disc of `radius` [m] around each cell.

    Near the map edge the mean is over the cells that exist. (B, X, Y) -> (B, X, Y), m.
    """
    k = disc_kernel(radius / dx, h)
    if k.shape[-1] == 1:
        return h
    pad = k.shape[-1] // 2
    num = F.conv2d(h[:, None], k, padding=pad)[:, 0]
    den = F.conv2d(torch.ones_like(h[:1, None]), k, padding=pad)[:, 0]
    return num / den


def sink(h: torch.Tensor, h_ref: torch.Tensor, covered: torch.Tensor, s: torch.Tensor,
         depth: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Dig every footprint in one step (the min over poses commutes; h_ref is fixed).

    Args:
        h: (B, X, Y) surface before the wheels, m.
        h_ref: (B, X, Y) reference height, m.
        covered: (B|1, K, X, Y) bool, cell inside wheel k's swept footprint.
        s: (B|1, K, X, Y) centrality taper of wheel k at the cell.
        depth: (B, K, X, Y) or (B, K, 1, 1) sinkage of wheel k, m.

    Returns:
        h_dug (B, X, Y) and removed height r = h - h_dug >= 0 (B, X, Y), m.
    """
    target = h_ref[:, None] - s * depth
    target = torch.where(covered, target, torch.full_like(target, math.inf)).amin(dim=1)
    h_dug = torch.minimum(h, target)
    return h_dug, h - h_dug
