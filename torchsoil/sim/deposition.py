"""Material redistribution: a share chi of the removed volume goes to a band beside the rut.

The height removed under each wheel is gathered per along-path bin (2 cells of arc length)
and spread uniformly over the band cells of the same bin on both sides of that wheel's rut:
deposits land beside the pose that dug them, never ahead of or behind it, and never inside
any footprint.
"""

from __future__ import annotations

import torch


def deposit(removed: torch.Tensor, cell: torch.Tensor, owner: torch.Tensor, band: torch.Tensor,
            bins: torch.Tensor, n_bins: int, chi: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Heights added beside the ruts.

    Args:
        removed: (B, X, Y) removed height per cell, m.
        cell: (E,) int64 flat cell index of each wheel-cell entry.
        owner: (B|1, E) bool, the entry's wheel dug its cell.
        band: (B|1, E) bool, the entry's cell is in its wheel's deposition band.
        bins: (E,) int64 deposition bin of each entry, in [0, n_bins).
        n_bins: total number of bins.
        chi: (B,) displacement-compaction ratio.

    Returns:
        added (B, X, Y) height, m; lost (B,) removed height (summed over cells, m) whose bin
        had no band cell on the grid and so was not deposited.
    """
    B = removed.shape[0]
    idx = bins.expand(B, -1)
    dug = removed.flatten(1)[:, cell] * owner
    vol = removed.new_zeros(B, n_bins).scatter_add(1, idx, dug)
    count = removed.new_zeros(B, n_bins).scatter_add(1, idx, band.to(removed.dtype).expand(B, -1))
    has = count > 0
    share = torch.where(has, vol / count.clamp_min(1.0), torch.zeros_like(vol))
    lost = torch.where(has, torch.zeros_like(vol), vol).sum(1)
    added = removed.new_zeros(B, removed[0].numel()).scatter_add(
        1, cell.expand(B, -1), share.gather(1, idx) * band)
    return chi[:, None, None] * added.reshape(removed.shape), lost
