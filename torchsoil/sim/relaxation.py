"""Surface relaxation: the Exner update with a steepest-descent flux (paper eqs. exner-flux).

    q = max(|grad h| - tan(beta), 0) * grad h / |grad h|        (q = -phi, downhill flux)
    dh[i,j] = dx / eps_scale * (q_x[i,j] - q_x[i-1,j] + q_y[i,j] - q_y[i,j-1])

with forward-difference gradients, epsilon = eps_scale / dx^2 (paper: 4 / dx^2) and no flux
across the map edge or out of the relaxation domain. Each batch element iterates until
max |grad h| - tan(beta) < tau on its own; elements that have converged are frozen, so the
result does not depend on what else is in the batch.

Two backends compute the same update: `torch` (reference; runs on CUDA; autograd through
the loop) and `numba` (a fused CPU kernel with a hand-written adjoint for autograd).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from torchsoil.sim.stencil import EPS2, RelaxResult, face_masks, numba_ok


def _step_terms(h, tan_beta, fx, fy):
    """Flux q_x, q_y and slope excess |grad h| - tan(beta), all (B, X, Y); fx, fy are the
    face masks divided by dx."""
    gx = F.pad((h[:, 1:] - h[:, :-1]), (0, 0, 0, 1)) * fx
    gy = F.pad((h[:, :, 1:] - h[:, :, :-1]), (0, 1)) * fy
    n = torch.sqrt(gx * gx + gy * gy + EPS2)
    excess = n - tan_beta
    f = torch.relu(excess) / n
    return f * gx, f * gy, excess


def relax_torch(h, tan_beta, dx, domain=None, tau=0.01, max_iter=2000, fixed_iter=None,
                eps_scale=4.0, check_every=8) -> RelaxResult:
    """Reference relaxation in torch ops. Shapes as in `relax`."""
    fx, fy = face_masks(domain, h.shape[1:], h.device)
    fxs, fys = fx.to(h.dtype) / dx, fy.to(h.dtype) / dx
    coef = dx / eps_scale
    B = h.shape[0]
    iters = torch.zeros(B, dtype=torch.int64, device=h.device)
    n_max = max_iter if fixed_iter is None else fixed_iter
    active = torch.ones(B, dtype=torch.bool, device=h.device)
    for it in range(n_max):
        qx, qy, excess = _step_terms(h, tan_beta, fxs, fys)
        if fixed_iter is None:
            active = excess.flatten(1).amax(1) >= tau
        div = qx - F.pad(qx[:, :-1], (0, 0, 1, 0)) + qy - F.pad(qy[:, :, :-1], (1, 0))
        h = h + (coef * div) * active[:, None, None].to(h.dtype)
        iters = iters + active
        if fixed_iter is None and (it + 1) % check_every == 0 and not bool(active.any()):
            break
    else:
        if fixed_iter is None:
            active = _step_terms(h, tan_beta, fxs, fys)[2].flatten(1).amax(1) >= tau
    capped = active if fixed_iter is None else torch.zeros_like(active)
    return RelaxResult(h, iters, capped)


def max_slope_excess(h, tan_beta, dx, domain=None) -> torch.Tensor:
    """(B,) max over the domain of |grad h| - tan(beta) (forward differences, no-flux edges;
    a (B, X, Y) tan_beta as `relax` reads it)."""
    if tan_beta.ndim == 3 and tan_beta.shape[-2:] != (1, 1):
        tan_beta = face_tan(tan_beta)
    fx, fy = face_masks(domain, h.shape[1:], h.device)
    return _step_terms(h, tan_beta, fx.to(h.dtype) / dx, fy.to(h.dtype) / dx)[2].flatten(1).amax(1)


def relax(h: torch.Tensor, tan_beta: torch.Tensor, dx: float, domain: torch.Tensor | None = None,
          tau: float = 0.01, max_iter: int = 2000, fixed_iter: int | None = None,
          eps_scale: float = 4.0, backend: str = "auto") -> RelaxResult:
    """Relax a batch of surfaces to the angle of repose.

    Args:
        h: (B, X, Y) heights, m.
        tan_beta: (B,) or (B, X, Y) tangent of the angle of repose (per cell for models whose
            walls and deposits settle at different angles; see `face_tan`).
        dx: cell edge, m.
        domain: (X, Y) bool cells that may exchange soil (None: the whole map).
        tau: stop when max abs(grad h) - tan(beta) < tau.
        max_iter: iteration cap; elements that hit it are flagged `capped`.
        fixed_iter: run exactly this many iterations (the paper's "capped relaxation").
        eps_scale: epsilon = eps_scale / dx^2.
        backend: "numba" (CPU), "torch", or "auto" (numba on CPU when available).
    """
    if tan_beta.ndim == 1:
        tan_beta = tan_beta[:, None, None]
    elif tan_beta.shape[-2:] != (1, 1):
        tan_beta = face_tan(tan_beta)
    if backend == "auto":
        backend = "numba" if h.device.type == "cpu" and numba_ok() else "torch"
    if backend == "torch":
        return relax_torch(h, tan_beta, dx, domain, tau, max_iter, fixed_iter, eps_scale)
    if backend != "numba":
        raise ValueError(f"unknown relaxation backend {backend!r}; use auto, numba or torch")
    from torchsoil.sim import _relax_numba

    return _relax_numba.relax(h, tan_beta, dx, domain, tau, max_iter, fixed_iter, eps_scale)


def face_tan(tan_beta: torch.Tensor) -> torch.Tensor:
    """(B, X, Y) per-cell tan(beta) -> the tan each cell's stencil uses.

    The update measures a cell's slope on its +x and +y faces, so a per-cell angle would
    hold a wall on one side of a rut and not on the other. Each face settles instead at the
    steeper angle of the two cells it joins (a cut face in cohesive soil stands whichever
    side it faces): the cell takes the largest tan of itself and its +x and +y neighbours."""
    t = tan_beta
    nx = torch.cat([t[:, 1:], t[:, -1:]], 1)
    ny = torch.cat([t[:, :, 1:], t[:, :, -1:]], 2)
    return torch.maximum(t, torch.maximum(nx, ny))


