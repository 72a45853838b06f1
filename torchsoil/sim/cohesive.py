"""Two-angle relaxation: cohesive soil whose intact ground stands steeper than moved soil settles.

Ground that has not moved (native, or freshly cut by a wheel) stands up to the intact angle
beta_i; soil that has moved (deposited beside a rut, or slid since) settles at the loose
angle beta_l <= beta_i. The state is the surface h and the loose thickness L >= 0 on top of
the intact ground (h - L). On the stencil of `relaxation` (forward differences, one slope
|grad h| per cell from its +x and +y faces) the flux splits in two:

    q_i = max(|grad h| - tan(beta_i), 0) * grad h / |grad h|     intact ground fails
    q_l = max(|grad h| - tan(beta_l), 0) * grad h / |grad h| - q_i  loose soil above it slides
    q   = q_i + r(donor) * q_l

where each face's donor is its upslope cell and r = min(1, L / loose outflow) keeps a cell
from shedding more loose soil than it carries. Everything that leaves a cell takes its loose
soil first and arrives loose: L <- max(L - out, 0) + in. Heights change by the divergence
of q as in `relaxation` (volume conserved). Each batch element iterates until no slope
exceeds its angle by tau, the loose angle counting along faces as far as their donors carry
loose soil (`_terms`); with tan(beta_i) = tan(beta_l) this is `relaxation.relax_torch`.

Torch ops only (CPU and CUDA); autograd through the loop gives gradients with respect to the
heights, the loose thickness and both angles.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
import torch.nn.functional as F

from torchsoil.sim.stencil import EPS2, face_masks, numba_ok


class TwoAngleResult(NamedTuple):
    """h: (B, X, Y) relaxed heights, m; loose: (B, X, Y) loose thickness after relaxation, m;
    iterations: (B,) int64 updates applied; capped: (B,) bool, stopped by the iteration cap."""

    h: torch.Tensor
    loose: torch.Tensor
    iterations: torch.Tensor
    capped: torch.Tensor


def _up(a: torch.Tensor, dim: int) -> torch.Tensor:
    """a shifted so that cell i holds a[i + 1] along dim (1: x, 2: y); the last cell keeps 0."""
    return F.pad(a.narrow(dim, 1, a.shape[dim] - 1), (0, 0, 0, 1) if dim == 1 else (0, 1))


def _down(a: torch.Tensor, dim: int) -> torch.Tensor:
    """a shifted so that cell i holds a[i - 1] along dim (1: x, 2: y); the first cell gets 0."""
    return F.pad(a.narrow(dim, 0, a.shape[dim] - 1), (0, 0, 1, 0) if dim == 1 else (1, 0))


def _out_in(qx: torch.Tensor, qy: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Per cell the flux leaving and the flux arriving, both >= 0, from face fluxes qx, qy
    (positive: from cell i + 1 down to cell i)."""
    out = torch.relu(-qx) + _down(torch.relu(qx), 1) + torch.relu(-qy) + _down(torch.relu(qy), 2)
    inn = torch.relu(qx) + _down(torch.relu(-qx), 1) + torch.relu(qy) + _down(torch.relu(-qy), 2)
    return out, inn


def _donor(a: torch.Tensor, g: torch.Tensor, dim: int) -> torch.Tensor:
    """Per face (stored at its lower cell) the value of a at the face's upslope cell."""
    return torch.where(g > 0, _up(a, dim), a)


def _terms(h, loose, tan_l, tan_i, fxs, fys, coef):
    """Face fluxes qx, qy (B, X, Y) of one update and the (B,) largest slope excess: of the
    stencil over the intact angle, or of a face's own slope over the loose one, times the share
    r of its loose flow the face's donor can give (a film of loose soil trickling down an intact
    face is not an excess: it moves less than tau would; nor is loose soil on a gentle face
    beside an intact wall, which flows only through the stencil's slope across the wall)."""
    gx = _up(h, 1).sub(h) * fxs
    gy = _up(h, 2).sub(h) * fys
    n = torch.sqrt(gx * gx + gy * gy + EPS2)
    fi = torch.relu(n - tan_i) / n
    fl = torch.relu(n - tan_l) / n - fi
    lx, ly = fl * gx, fl * gy                      # loose flux above the intact failure
    out_l = _out_in(lx, ly)[0] * coef
    r = torch.where(out_l > loose, loose / out_l.clamp_min(1e-300), torch.ones_like(loose))
    qx = fi * gx + lx * _donor(r, gx, 1)
    qy = fi * gy + ly * _donor(r, gy, 2)
    face = torch.maximum((gx.abs() - tan_l) * _donor(r, gx, 1), (gy.abs() - tan_l) * _donor(r, gy, 2))
    excess = torch.maximum(n - tan_i, face)
    return qx, qy, excess.flatten(1).amax(1)


def relax_two_angle(h: torch.Tensor, loose: torch.Tensor, tan_beta_loose: torch.Tensor,
                    tan_beta_intact: torch.Tensor, dx: float, domain: torch.Tensor | None = None,
                    tau: float = 0.01, max_iter: int = 2000, fixed_iter: int | None = None,
                    eps_scale: float = 4.0, backend: str = "auto") -> TwoAngleResult:
    """Relax a batch of surfaces of two-angle (cohesive) soil (module docstring).

    Args:
        h: (B, X, Y) heights, m.
        loose: (B, X, Y) loose thickness on top of the intact ground, m (>= 0; 0: intact).
        tan_beta_loose: (B,) or (B, X, Y) tangent of the angle moved soil settles at.
        tan_beta_intact: (B,) or (B, X, Y) tangent of the angle intact ground stands up to,
            >= tan_beta_loose.
        dx: cell edge, m.
        domain: (X, Y) bool cells that may exchange soil (None: the whole map).
        tau: stop when no slope exceeds the angle it flows at by tau or more [-].
        max_iter: iteration cap; elements that hit it are flagged `capped`.
        fixed_iter: run exactly this many iterations.
        eps_scale: epsilon = eps_scale / dx^2 (as `relaxation.relax`).
        backend: "numba" (CPU, fused kernels with a hand-written adjoint), "torch" (reference,
            CPU or CUDA), or "auto" (numba on CPU when available).

    Returns:
        TwoAngleResult (h, loose, iterations, capped) on h's device and dtype.
    """
    if h.ndim != 3 or loose.shape != h.shape:
        raise ValueError(f"h and loose must both be (B, X, Y), got {tuple(h.shape)} and {tuple(loose.shape)}")
    tl, ti = (t[:, None, None] if t.ndim == 1 else t for t in (tan_beta_loose, tan_beta_intact))
    if bool((loose.detach() < 0).any()):
        raise ValueError("loose thickness must be >= 0 (m of moved soil on the intact ground)")
    if bool((tl.detach() <= 0).any()) or bool((ti.detach() < tl.detach()).any()):
        raise ValueError("need 0 < tan(beta_loose) <= tan(beta_intact): intact ground stands at least as "
                         "steep as moved soil settles")
    if backend == "auto":
        backend = "numba" if h.device.type == "cpu" and numba_ok() else "torch"
    if backend == "numba":
        from torchsoil.sim import _cohesive_numba

        return TwoAngleResult(*_cohesive_numba.relax_two_angle(h, loose, tl, ti, dx, domain, tau, max_iter,
                                                               fixed_iter, eps_scale))
    if backend != "torch":
        raise ValueError(f"unknown relaxation backend {backend!r}; use auto, numba or torch")
    return _relax_torch(h, loose, tl, ti, dx, domain, tau, max_iter, fixed_iter, eps_scale)


def _relax_torch(h, loose, tl, ti, dx, domain, tau, max_iter, fixed_iter, eps_scale, check_every=8):
    """The reference update in torch ops; arguments as `relax_two_angle`."""
    fx, fy = face_masks(domain, h.shape[1:], h.device)
    fxs, fys = fx.to(h.dtype) / dx, fy.to(h.dtype) / dx
    coef = dx / eps_scale
    B = h.shape[0]
    iters = torch.zeros(B, dtype=torch.int64, device=h.device)
    active = torch.ones(B, dtype=torch.bool, device=h.device)
    n_max = max_iter if fixed_iter is None else fixed_iter
    for it in range(n_max):
        qx, qy, excess = _terms(h, loose, tl, ti, fxs, fys, coef)
        if fixed_iter is None:
            active = excess >= tau
        out, inn = _out_in(qx, qy)
        on = active[:, None, None].to(h.dtype)
        div = qx - _down(qx, 1) + qy - _down(qy, 2)
        h = h + (coef * div) * on
        loose = loose + on * (torch.relu(loose - coef * out) + coef * inn - loose)
        iters = iters + active
        if fixed_iter is None and (it + 1) % check_every == 0 and not bool(active.any()):
            break
    else:
        if fixed_iter is None:
            active = _terms(h, loose, tl, ti, fxs, fys, coef)[2] >= tau
    capped = active if fixed_iter is None else torch.zeros_like(active)
    return TwoAngleResult(h, loose, iters, capped)
