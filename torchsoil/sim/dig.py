"""The wheels dig and lay their spoil beside the ruts: `sinkage.sink` then `deposition.deposit`,
as torch ops or as one fused numba kernel on the CPU (the same surfaces, `_dig_numba`)."""

from __future__ import annotations

import torch

from torchsoil.sim.deposition import deposit
from torchsoil.sim.sinkage import sink
from torchsoil.sim.stencil import numba_ok


def dig(h: torch.Tensor, h_ref: torch.Tensor, cell: torch.Tensor, covered: torch.Tensor, s: torch.Tensor,
        depth: torch.Tensor, owner: torch.Tensor, band: torch.Tensor, bins: torch.Tensor, n_bins: int,
        chi: torch.Tensor, backend: str = "auto"
        ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Dig every footprint (`sink`) and deposit a share chi of the removed soil (`deposit`).

    Args:
        h: (B|1, X, Y) surface before the wheels, m.  h_ref: (B|1, X, Y) reference height, m.
        cell: (E,) int64 flat cell of each wheel-cell entry.  covered, owner, band: (B|1, E)
            bool (`geometry.Footprint`).  s: (B|1, E) centrality taper.  depth: (B, E) sinkage, m.
        bins: (E,) int64 deposition bin of each entry, in [0, n_bins).  chi: (B,).
        backend: "numba" (CPU), "torch", or "auto" (numba on CPU when available).

    Returns:
        h_unrelaxed = h_dug + added (B, X, Y), removed (B, X, Y), added (B, X, Y), all m, and
        lost (B,) removed height whose bin had no band cell (summed over cells, m).
    """
    if backend == "auto":
        backend = "numba" if depth.device.type == "cpu" and numba_ok() else "torch"
    if backend == "numba":
        from torchsoil.sim import _dig_numba

        return _dig_numba.dig(h, h_ref, cell, covered, s, depth, owner, band, bins, n_bins, chi)
    if backend != "torch":
        raise ValueError(f"unknown dig backend {backend!r}; use auto, numba or torch")
    h_dug, removed = sink(h, h_ref, cell, covered, s, depth)
    added, lost = deposit(removed, cell, owner, band, bins, n_bins, chi)
    return h_dug + added, removed, added, lost
