"""What the relaxations and their kernels share: the face masks of the stencil, the epsilon
that keeps a flat cell's slope differentiable, the result type, and whether numba is there."""

from __future__ import annotations

from typing import NamedTuple

import torch

EPS2 = 1e-20  # m^2/m^2, keeps |grad h| differentiable at a flat cell


class RelaxResult(NamedTuple):
    """h: (B, X, Y) relaxed heights, m; iterations: (B,) int64 updates applied;
    capped: (B,) bool, stopped by the iteration cap before converging."""

    h: torch.Tensor
    iterations: torch.Tensor
    capped: torch.Tensor


def face_masks(domain: torch.Tensor | None, shape, device) -> tuple[torch.Tensor, torch.Tensor]:
    """(X, Y) bool masks of the +x and +y faces that carry flux (both cells in the domain)."""
    X, Y = shape
    if domain is None:
        domain = torch.ones(X, Y, dtype=torch.bool, device=device)
    fx = torch.zeros(X, Y, dtype=torch.bool, device=device)
    fy = torch.zeros(X, Y, dtype=torch.bool, device=device)
    fx[:-1] = domain[:-1] & domain[1:]
    fy[:, :-1] = domain[:, :-1] & domain[:, 1:]
    return fx, fy


_NUMBA = None


def numba_ok() -> bool:
    global _NUMBA
    if _NUMBA is None:
        try:
            import numba  # noqa: F401

            _NUMBA = True
        except ImportError:
            _NUMBA = False
    return _NUMBA
