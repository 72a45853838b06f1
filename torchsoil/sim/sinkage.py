"""Wheel-soil interaction: the wheels dig their footprints into the surface (paper eq. lower).

h <- min(h, h_ref - s * d) over each circular footprint, where h_ref is the surface before
the robot smoothed over a small disc and s the centrality taper across the wheel.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F


def taper(q: torch.Tensor, flat_fraction: float = 0.0, exponent: float = 1.0) -> torch.Tensor:
    """Centrality factor s(q) in [0, 1] for q = lateral offset / footprint radius (any shape).

    s = 1 for |q| <= f, then (1 + cos(pi (|q| - f) / (1 - f))) / 2 down to 0 at |q| = 1,
    0 beyond (docs/formats.md section 2); raised to `exponent` e (1: that taper; below 1 fuller
    shoulders: about a rounded, elliptic section at f = 0, e = 0.2, a crowned, parabolic one
    at f = 0.1, e = 0.5).
    """
    u = ((q.abs() - flat_fraction) / (1.0 - flat_fraction)).clamp(0.0, 1.0)
    s = 0.5 * (1.0 + torch.cos(math.pi * u))
    return s if exponent == 1.0 else s.clamp(min=0.0) ** exponent


def disc_offsets(radius_cells: float) -> list[tuple[int, int]]:
    """Integer cell offsets (di, dj) whose centres lie within radius_cells of the centre."""
    r = int(math.floor(radius_cells))
    return [(i, j) for i in range(-r, r + 1) for j in range(-r, r + 1)
            if i * i + j * j <= radius_cells**2 + 1e-9]


def _disc_sum(hp: torch.Tensor, half: dict[int, int], r: int, X: int, Y: int) -> torch.Tensor:
    """Sum of hp (B, X + 2r, Y + 2r), padded by r, over a disc given row by row: row offset i
    spans columns -half[i]..half[i]. A run of width 2w + 1 is the run of width 2w - 1 and its
    two ends, so the disc takes about 4r additions where a shift per cell took about 3r^2."""
    runs = [hp[:, :, r:r + Y]]
    for w in range(1, max(half.values()) + 1):
        runs.append(runs[-1] + hp[:, :, r - w:r - w + Y] + hp[:, :, r + w:r + w + Y])
    return sum(runs[w][:, r + i:r + i + X] for i, w in half.items())


def reference_height(h: torch.Tensor, radius: float, dx: float) -> torch.Tensor:
    """Local reference height h~: mean of h over a disc of `radius` [m] around each cell.

    Near the map edge the mean is over the cells that exist. (B, X, Y) -> (B, X, Y), m.
    """
    offsets = disc_offsets(radius / dx)
    r = max(max(abs(i), abs(j)) for i, j in offsets)
    if r == 0:
        return h
    half: dict[int, int] = {}
    for i, j in offsets:
        half[i] = max(half.get(i, 0), abs(j))
    X, Y = h.shape[1:]
    hp = F.pad(h[:, None], (r, r, r, r))[:, 0]
    ones = F.pad(torch.ones_like(h[:1, None]), (r, r, r, r))[:, 0]
    return _disc_sum(hp, half, r, X, Y) / _disc_sum(ones, half, r, X, Y)


def contact_height(h: torch.Tensor, radius: float, dx: float) -> torch.Tensor:
    """Reference height of a wheel coming back over ground that wheels dug before: the mean of
    h over the wheel's whole footprint, a disc of `radius` [m] (half the wheel width).

    A wheel cannot follow relief narrower than itself: on a rut of its own width it rests on
    the walls and shoulders as much as on the floor. Pressed into soft ground, a rigid
    footprint comes to the level at which it holds the same soil as flat ground would (the
    shoulders it presses fill the hollow beneath it): the mean height under it, from which it
    sinks d. On flat or planar ground this is the surface itself, as `reference_height` over
    the paper's smaller disc. (B, X, Y) -> (B, X, Y), m."""
    return reference_height(h, radius, dx)


def revisit_reference(h: torch.Tensor, h_ref: torch.Tensor, dug: torch.Tensor, how: str, ref_radius: float,
                      radius: float, dx: float) -> torch.Tensor:
    """Reference height over a surface h (B, X, Y) [m] part of which earlier wheel passes dug
    (`dug`, (X, Y) or (B, X, Y) bool): `contact_height` of h there (how "footprint", the
    footprint radius `radius` [m]) or the disc of ref_radius * radius (how "disc"), h_ref
    (B|1, X, Y) [m] elsewhere."""
    if how not in ("footprint", "disc"):
        raise ValueError(f"revisit reference must be 'footprint' or 'disc', got {how!r}")
    ref = contact_height(h, radius, dx) if how == "footprint" else reference_height(h, ref_radius * radius, dx)
    return torch.where(dug, ref, h_ref)


def sink(h: torch.Tensor, h_ref: torch.Tensor, cell: torch.Tensor, covered: torch.Tensor,
         s: torch.Tensor, depth: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Dig every footprint at once (the min over poses commutes because h_ref is fixed).

    Args:
        h: (B|1, X, Y) surface before the wheels, m.
        h_ref: (B|1, X, Y) reference height, m.
        cell: (E,) int64 flat cell index of each wheel-cell entry.
        covered: (B|1, E) bool, the entry's cell is inside its wheel's footprint.
        s: (B|1, E) centrality taper of the entry.
        depth: (B, E) sinkage of the entry's wheel at its pose, m.

    Returns:
        h_dug (B, X, Y) and removed height r = h - h_dug >= 0 (B, X, Y), m.
    """
    B = max(h.shape[0], depth.shape[0])
    h = h.expand(B, -1, -1)
    target = (h_ref.flatten(1)[:, cell] - s * depth).expand(B, -1)
    target = target.masked_fill(~covered, math.inf)
    floor = torch.full((B, h[0].numel()), math.inf, dtype=h.dtype, device=h.device)
    floor = floor.scatter_reduce(1, cell.expand(B, -1), target, "amin")
    h_dug = torch.minimum(h, floor.reshape(h.shape))
    return h_dug, h - h_dug
