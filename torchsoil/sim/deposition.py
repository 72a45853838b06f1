"""Material redistribution: a share chi of the removed volume goes to a band beside the rut.

The removed height under each wheel is gathered per along-path bin (2 cells of arc length)
and spread uniformly over the band cells of the same bin on both sides of that wheel's rut:
deposits land beside the pose that dug them, never ahead of or behind it, and never inside
any rut.
"""

from __future__ import annotations

import torch


def deposit(removed: torch.Tensor, owner: torch.Tensor, band: torch.Tensor,
            bin_index: torch.Tensor, n_bins: int, chi: torch.Tensor
            ) -> tuple[torch.Tensor, torch.Tensor]:
    """Heights added beside the ruts.

    Args:
        removed: (B, X, Y) removed height per cell, m.
        owner: (B|1, K, X, Y) bool, wheel k dug this cell (one wheel per cell).
        band: (B|1, K, X, Y) bool, cell lies in wheel k's deposition band.
        bin_index: (K, X, Y) int64 bin per wheel and cell, in [0, K * n_bins).
        n_bins: bins per wheel.
        chi: (B,) displacement-compaction ratio.

    Returns:
        added (B, X, Y) height, m; lost (B,) removed height (sum over cells, m) whose bin had
        no band cell on the grid, which is not deposited.
    """
    B = removed.shape[0]
    K = bin_index.shape[0]
    idx = bin_index.reshape(1, -1).expand(B, -1)
    per_wheel = (removed[:, None] * owner).reshape(B, -1)
    vol = removed.new_zeros(B, K * n_bins).scatter_add_(1, idx, per_wheel)
    in_band = band.to(removed.dtype).reshape(band.shape[0], -1).expand(B, -1)
    count = removed.new_zeros(B, K * n_bins).scatter_add_(1, idx, in_band)
    has = count > 0
    share = torch.where(has, vol / count.clamp_min(1.0), torch.zeros_like(vol))
    lost = torch.where(has, torch.zeros_like(vol), vol).sum(1)
    added = (share.gather(1, idx).reshape(B, *bin_index.shape) * band).sum(1)
    return chi[:, None, None] * added, lost
