"""Fused CPU kernels for `cohesive.relax_two_angle`: the same update as its torch ops, one pass
over the cells per stage, and the hand-written adjoint for autograd. Tested to agree with the
torch reference (values and gradients)."""

from __future__ import annotations

import math

import numpy as np
import torch
from numba import njit, prange

from torchsoil.sim._relax_numba import compile_kernels, slope_adjoint
from torchsoil.sim.stencil import EPS2, face_masks


@njit(cache=True, nogil=True, inline="always")
def _stencil(h, L, tl, ti, fx, fy, inv_dx, coef, gx, gy, nn, fi, fe, O, r):
    """Slopes, |grad h| (tan(beta_loose) where the slope is below it: nothing flows there) and
    the intact / loose-excess flux factors of every stencil; the loose outflow O of every cell
    and the share r <= 1 of it the cell can give (its neighbours' stencils at -x and -y come
    first in the sweep)."""
    X, Y = h.shape
    for i in range(X):
        for j in range(Y):
            a = (h[i + 1, j] - h[i, j]) * inv_dx if fx[i, j] else 0.0
            c = (h[i, j + 1] - h[i, j]) * inv_dx if fy[i, j] else 0.0
            n2 = a * a + c * c + EPS2
            t = tl[i, j]
            gx[i, j], gy[i, j] = a, c
            if n2 > t * t:     # above the loose angle (sqrt only here)
                n = math.sqrt(n2)
                f_i = max(n - ti[i, j], 0.0) / n
                nn[i, j], fi[i, j], fe[i, j] = n, f_i, (n - t) / n - f_i
            else:
                nn[i, j], fi[i, j], fe[i, j] = t, 0.0, 0.0
            e = fe[i, j]
            o = max(-e * a, 0.0) + max(-e * c, 0.0)
            if i > 0:
                o += max(fe[i - 1, j] * gx[i - 1, j], 0.0)
            if j > 0:
                o += max(fe[i, j - 1] * gy[i, j - 1], 0.0)
            O[i, j] = coef * o
            r[i, j] = L[i, j] / O[i, j] if O[i, j] > L[i, j] else 1.0


@njit(cache=True, nogil=True, inline="always")
def _fluxes(gx, gy, nn, fi, fe, r, tl, ti, tau, qx, qy, out):
    """Face fluxes (positive: from the +x / +y neighbour down to the cell) and each cell's
    outflow; returns whether any slope exceeds the angle it flows at by tau (`cohesive._terms`)."""
    X, Y = gx.shape
    out[:] = 0.0
    active = False
    for i in range(X):
        for j in range(Y):
            a, c = gx[i, j], gy[i, j]
            rx = r[i + 1, j] if a > 0 else r[i, j]
            ry = r[i, j + 1] if c > 0 else r[i, j]
            t = tl[i, j]
            if nn[i, j] - ti[i, j] >= tau or max((abs(a) - t) * rx, (abs(c) - t) * ry) >= tau:
                active = True
            qx[i, j] = fi[i, j] * a + fe[i, j] * a * rx
            qy[i, j] = fi[i, j] * c + fe[i, j] * c * ry
            if qx[i, j] > 0:
                out[i + 1, j] += qx[i, j]
            else:
                out[i, j] -= qx[i, j]
            if qy[i, j] > 0:
                out[i, j + 1] += qy[i, j]
            else:
                out[i, j] -= qy[i, j]
    return active


def _forward_py(h, L, tl, ti, fx, fy, inv_dx, coef, tau, n_iter, fixed, done, iters, hh, hl,
                counts, store):
    B, X, Y = h.shape
    for b in prange(B):
        if done[b]:
            continue
        w = np.zeros((10, X, Y))
        gx, gy, nn, fi, fe, O, r, qx, qy, out = w[0], w[1], w[2], w[3], w[4], w[5], w[6], w[7], w[8], w[9]
        for it in range(n_iter):
            _stencil(h[b], L[b], tl[b], ti[b], fx, fy, inv_dx, coef, gx, gy, nn, fi, fe, O, r)
            active = _fluxes(gx, gy, nn, fi, fe, r, tl[b], ti[b], tau, qx, qy, out)
            if not fixed and not active:
                done[b] = 1
                break
            if store:
                hh[b, it] = h[b]
                hl[b, it] = L[b]
            for i in range(X):
                for j in range(Y):
                    d = qx[i, j] + qy[i, j]
                    inn = max(qx[i, j], 0.0) + max(qy[i, j], 0.0)
                    if i > 0:
                        d -= qx[i - 1, j]
                        inn += max(-qx[i - 1, j], 0.0)
                    if j > 0:
                        d -= qy[i, j - 1]
                        inn += max(-qy[i, j - 1], 0.0)
                    h[b, i, j] += coef * d
                    L[b, i, j] = max(L[b, i, j] - coef * out[i, j], 0.0) + coef * inn
            iters[b] += 1
            counts[b] += 1


@njit(cache=True, nogil=True, inline="always")
def _flux_adjoint(L, qx, qy, gx, gy, fe, out, fx, fy, lam, lamL, coef, qbx, qby, rbar):
    """The face fluxes' adjoints (qbx, qby) from the heights' and loose thickness' (lam,
    lamL), and the limiter share's (rbar) from them."""
    X, Y = L.shape
    rbar[:] = 0.0
    for i in range(X):
        for j in range(Y):
            s = 1.0 if L[i, j] - coef * out[i, j] > 0 else 0.0
            for k in range(2):
                q = qx[i, j] if k == 0 else qy[i, j]
                ii, jj = (i + 1, j) if k == 0 else (i, j + 1)
                if not (fx[i, j] if k == 0 else fy[i, j]):
                    qb = 0.0
                else:
                    qb = coef * (lam[i, j] - lam[ii, jj])
                    if q > 0:
                        so = 1.0 if L[ii, jj] - coef * out[ii, jj] > 0 else 0.0
                        qb += coef * (lamL[i, j] - so * lamL[ii, jj])
                    elif q < 0:
                        qb += coef * (s * lamL[i, j] - lamL[ii, jj])
                g = gx[i, j] if k == 0 else gy[i, j]
                if g > 0:
                    rbar[ii, jj] += qb * fe[i, j] * g
                else:
                    rbar[i, j] += qb * fe[i, j] * g
                if k == 0:
                    qbx[i, j] = qb
                else:
                    qby[i, j] = qb


@njit(cache=True, nogil=True, inline="always")
def _limiter_adjoint(L, O, rbar, Obar, Lbar):
    """The limiter r = L / O where O > L: the outflow's and loose thickness' adjoints."""
    X, Y = L.shape
    for i in range(X):
        for j in range(Y):
            if O[i, j] > L[i, j]:
                Obar[i, j] = -rbar[i, j] * L[i, j] / (O[i, j] * O[i, j])
                Lbar[i, j] = rbar[i, j] / O[i, j]
            else:
                Obar[i, j] = 0.0
                Lbar[i, j] = 0.0


@njit(cache=True, nogil=True, inline="always")
def _stencil_adjoint(gx, gy, nn, fi, fe, r, qbx, qby, Obar, tl, ti, fx, fy, coef, tlbar, tibar, gbx, gby):
    """Through the stencils' flux factors to the slopes' adjoints (gbx, gby) and the angles'
    (tlbar, tibar, accumulated)."""
    X, Y = gx.shape
    for i in range(X):
        for j in range(Y):
            a, c, n = gx[i, j], gy[i, j], nn[i, j]
            rx = r[i + 1, j] if a > 0 else r[i, j]
            ry = r[i, j + 1] if c > 0 else r[i, j]
            lx, ly = fe[i, j] * a, fe[i, j] * c
            lbx = coef * (Obar[i + 1, j] if lx > 0 else (-Obar[i, j] if lx < 0 else 0.0))
            lby = coef * (Obar[i, j + 1] if ly > 0 else (-Obar[i, j] if ly < 0 else 0.0))
            fib = qbx[i, j] * a + qby[i, j] * c
            feb = qbx[i, j] * a * rx + qby[i, j] * c * ry + lbx * a + lby * c
            gbx[i, j] = qbx[i, j] * (fi[i, j] + fe[i, j] * rx) + lbx * fe[i, j]
            gby[i, j] = qby[i, j] * (fi[i, j] + fe[i, j] * ry) + lby * fe[i, j]
            fib = fib - feb                       # fe = f_loose - f_intact
            nb = 0.0
            if n > tl[i, j]:
                nb += feb * tl[i, j] / (n * n)
                tlbar[i, j] -= feb / n
            if n > ti[i, j]:
                nb += fib * ti[i, j] / (n * n)
                tibar[i, j] -= fib / n
            gbx[i, j] = (gbx[i, j] + nb * a / n) if fx[i, j] else 0.0
            gby[i, j] = (gby[i, j] + nb * c / n) if fy[i, j] else 0.0


def _backward_py(hh, hl, counts, lam, lamL, tlbar, tibar, tl, ti, fx, fy, inv_dx, coef):
    B, X, Y = lam.shape
    for b in prange(B):
        w = np.zeros((17, X, Y))
        gx, gy, nn, fi, fe, O, r, qx, qy, out = w[0], w[1], w[2], w[3], w[4], w[5], w[6], w[7], w[8], w[9]
        qbx, qby, rbar, Obar, Lbar, gbx, gby = w[10], w[11], w[12], w[13], w[14], w[15], w[16]
        for it in range(counts[b] - 1, -1, -1):
            h, L = hh[b, it], hl[b, it]
            _stencil(h, L, tl[b], ti[b], fx, fy, inv_dx, coef, gx, gy, nn, fi, fe, O, r)
            _fluxes(gx, gy, nn, fi, fe, r, tl[b], ti[b], 0.0, qx, qy, out)
            _flux_adjoint(L, qx, qy, gx, gy, fe, out, fx, fy, lam[b], lamL[b], coef, qbx, qby, rbar)
            _limiter_adjoint(L, O, rbar, Obar, Lbar)
            _stencil_adjoint(gx, gy, nn, fi, fe, r, qbx, qby, Obar, tl[b], ti[b], fx, fy, coef, tlbar[b],
                             tibar[b], gbx, gby)
            for i in range(X):
                for j in range(Y):
                    s = 1.0 if L[i, j] - coef * out[i, j] > 0 else 0.0
                    lamL[b, i, j] = s * lamL[b, i, j] + Lbar[i, j]
            slope_adjoint(gbx, gby, inv_dx, lam[b])


_forward, _backward = compile_kernels(_forward_py, _backward_py)


def _sum_to(g: np.ndarray, shape) -> torch.Tensor:
    """A (B, X, Y) gradient summed over the dimensions a broadcast input of `shape` had as 1."""
    t = torch.from_numpy(g)
    dims = tuple(d for d in range(3) if shape[d] == 1 and g.shape[d] != 1)
    return (t.sum(dim=dims, keepdim=True) if dims else t).reshape(shape)


class _TwoAngle(torch.autograd.Function):
    @staticmethod
    def forward(ctx, h, loose, tl, ti, fx, fy, dx, tau, max_iter, fixed_iter, eps_scale):
        store = any(ctx.needs_input_grad[:4])
        hn = h.detach().cpu().numpy().copy()
        ln = np.array(np.broadcast_to(loose.detach().cpu().numpy(), hn.shape), order="C")
        tln, tin = (np.array(np.broadcast_to(t.detach().cpu().numpy(), hn.shape), order="C") for t in (tl, ti))
        fxn, fyn = fx.cpu().numpy().astype(np.uint8), fy.cpu().numpy().astype(np.uint8)
        B = hn.shape[0]
        done, iters = np.zeros(B, np.uint8), np.zeros(B, np.int64)
        total = max_iter if fixed_iter is None else fixed_iter
        chunks, chunk, ran = [], 32, 0
        dummy = np.zeros((1, 1, 1, 1), hn.dtype)
        args = (tln, tin, fxn, fyn, 1.0 / dx, dx / eps_scale, tau)
        while ran < total and not done.all():
            n = min(chunk, total - ran)
            hh, hl = ((np.empty((B, n, *hn.shape[1:]), hn.dtype) for _ in range(2)) if store else (dummy, dummy))
            counts = np.zeros(B, np.int64)
            _forward(hn, ln, *args, n, fixed_iter is not None, done, iters, hh, hl, counts, store)
            if store:
                chunks.append((hh, hl, counts))
            ran += n
            chunk *= 2
        capped = np.zeros(B, bool)
        if fixed_iter is None and not done.all():  # cap reached: did the last update converge?
            probe = done.copy()
            _forward(hn.copy(), ln.copy(), *args, 1, False, probe, np.zeros(B, np.int64), dummy, dummy,
                     np.zeros(B, np.int64), False)
            capped = probe == 0
        ctx.chunks = chunks
        ctx.meta = (tln, tin, fxn, fyn, dx, eps_scale, loose.shape, tl.shape, ti.shape)
        return (torch.from_numpy(hn).to(h.device), torch.from_numpy(ln).to(h.device), torch.from_numpy(iters),
                torch.from_numpy(capped))

    @staticmethod
    def backward(ctx, grad_h, grad_l, _gi, _gc):
        tln, tin, fxn, fyn, dx, eps_scale, l_shape, tl_shape, ti_shape = ctx.meta
        lam = grad_h.detach().cpu().numpy().astype(tln.dtype, copy=True)
        lam_l = (np.zeros_like(lam) if grad_l is None else grad_l.detach().cpu().numpy().astype(tln.dtype, copy=True))
        tlbar, tibar = np.zeros_like(tln), np.zeros_like(tin)
        for hh, hl, counts in reversed(ctx.chunks):
            _backward(hh, hl, counts, lam, lam_l, tlbar, tibar, tln, tin, fxn, fyn, 1.0 / dx, dx / eps_scale)
        dev = grad_h.device
        return (torch.from_numpy(lam).to(dev), _sum_to(lam_l, l_shape).to(dev), _sum_to(tlbar, tl_shape).to(dev),
                _sum_to(tibar, ti_shape).to(dev), None, None, None, None, None, None, None)


def relax_two_angle(h, loose, tl, ti, dx, domain, tau, max_iter, fixed_iter, eps_scale):
    """Numba two-angle relaxation with autograd; arguments as `cohesive.relax_two_angle` (tl, ti
    (B, 1|X, 1|Y))."""
    fx, fy = face_masks(domain, h.shape[1:], h.device)
    tl, ti = (t.to(h.dtype).expand(h.shape[0], -1, -1) if t.shape[0] == 1 else t.to(h.dtype) for t in (tl, ti))
    return _TwoAngle.apply(h, loose.to(h.dtype), tl, ti, fx, fy, float(dx), float(tau), int(max_iter), fixed_iter,
                           float(eps_scale))
