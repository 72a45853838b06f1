"""Fused CPU kernels for `relaxation.relax`: the same update as `relax_torch`, one pass over
the cells per iteration, and its adjoint for autograd. Tested to agree with the torch ops."""

from __future__ import annotations

import math

import numpy as np
import torch
from numba import njit, prange

from torchsoil.sim.stencil import EPS2, RelaxResult


@njit(cache=True, nogil=True, inline="always")
def slope_adjoint(gbx, gby, inv_dx, lam):
    """Add to the heights' adjoint lam (X, Y), in place, that of the forward-difference slopes
    whose adjoints are gbx, gby (X, Y)."""
    X, Y = lam.shape
    for i in range(X):
        for j in range(Y):
            d = -gbx[i, j] - gby[i, j]
            if i > 0:
                d += gbx[i - 1, j]
            if j > 0:
                d += gby[i, j - 1]
            lam[i, j] += inv_dx * d


def compile_kernels(forward_py, backward_py):
    """The forward and backward kernels compiled by numba, each called as serial code on one
    batch element (a thread pool only costs there) and with a thread per element on several."""
    fs, fp = njit(cache=True, nogil=True)(forward_py), njit(parallel=True, cache=True, nogil=True)(forward_py)
    bs, bp = njit(cache=True, nogil=True)(backward_py), njit(parallel=True, cache=True, nogil=True)(backward_py)

    def forward(h, *args):
        return (fp if h.shape[0] > 1 else fs)(h, *args)

    def backward(hist, *args):
        return (bp if hist.shape[0] > 1 else bs)(hist, *args)

    return forward, backward


def _forward_py(h, tb, fx, fy, inv_dx, coef, tau, n_iter, fixed, done, iters, hist, counts, store):
    B, X, Y = h.shape
    for b in prange(B):
        if done[b]:
            continue
        qx = np.zeros((X, Y))
        qy = np.zeros((X, Y))
        for it in range(n_iter):
            active = False
            for i in range(X):
                for j in range(Y):
                    gx = (h[b, i + 1, j] - h[b, i, j]) * inv_dx if fx[i, j] else 0.0
                    gy = (h[b, i, j + 1] - h[b, i, j]) * inv_dx if fy[i, j] else 0.0
                    n2 = gx * gx + gy * gy + EPS2
                    t = tb[b, i, j]
                    if n2 > t * t:  # slope above the angle of repose: soil flows (sqrt only here)
                        n = math.sqrt(n2)
                        ex = n - t
                        if ex >= tau:
                            active = True
                        f = ex / n
                        qx[i, j] = f * gx
                        qy[i, j] = f * gy
                    else:
                        qx[i, j] = 0.0
                        qy[i, j] = 0.0
            if not fixed and not active:
                done[b] = 1
                break
            if store:
                hist[b, it] = h[b]
            for i in range(X):
                for j in range(Y):
                    d = qx[i, j] + qy[i, j]
                    if i > 0:
                        d -= qx[i - 1, j]
                    if j > 0:
                        d -= qy[i, j - 1]
                    h[b, i, j] += coef * d
            iters[b] += 1
            counts[b] += 1


def _backward_py(hist, counts, lam, tbar, tb, fx, fy, inv_dx, coef):
    B, X, Y = lam.shape
    for b in prange(B):
        gbx = np.zeros((X, Y))
        gby = np.zeros((X, Y))
        for it in range(counts[b] - 1, -1, -1):
            for i in range(X):
                for j in range(Y):
                    gx = (hist[b, it, i + 1, j] - hist[b, it, i, j]) * inv_dx if fx[i, j] else 0.0
                    gy = (hist[b, it, i, j + 1] - hist[b, it, i, j]) * inv_dx if fy[i, j] else 0.0
                    n2 = gx * gx + gy * gy + EPS2
                    if n2 > tb[b, i, j] * tb[b, i, j]:
                        n = math.sqrt(n2)
                        ex = n - tb[b, i, j]
                        qbx = coef * (lam[b, i, j] - (lam[b, i + 1, j] if i + 1 < X else 0.0))
                        qby = coef * (lam[b, i, j] - (lam[b, i, j + 1] if j + 1 < Y else 0.0))
                        f = ex / n
                        dot = qbx * gx + qby * gy
                        k = dot * tb[b, i, j] / (n * n * n)
                        gbx[i, j] = (qbx * f + k * gx) if fx[i, j] else 0.0
                        gby[i, j] = (qby * f + k * gy) if fy[i, j] else 0.0
                        tbar[b, i, j] -= dot / n
                    else:
                        gbx[i, j] = 0.0
                        gby[i, j] = 0.0
            slope_adjoint(gbx, gby, inv_dx, lam[b])


_forward, _backward = compile_kernels(_forward_py, _backward_py)


class _Relax(torch.autograd.Function):
    @staticmethod
    def forward(ctx, h, tan_beta, fx, fy, dx, tau, max_iter, fixed_iter, eps_scale):
        store = ctx.needs_input_grad[0] or ctx.needs_input_grad[1]
        hn = h.detach().cpu().numpy().copy()
        # a writable copy: a read-only view would compile the kernels a second time
        tb = np.array(np.broadcast_to(tan_beta.detach().cpu().numpy(), hn.shape), order="C")
        fxn, fyn = fx, fy
        B = hn.shape[0]
        done = np.zeros(B, np.uint8)
        iters = np.zeros(B, np.int64)
        total = max_iter if fixed_iter is None else fixed_iter
        chunks, chunk, ran = [], 32, 0
        dummy = np.zeros((1, 1, 1, 1), hn.dtype)
        while ran < total and not done.all():
            n = min(chunk, total - ran)
            hist = np.empty((B, n, *hn.shape[1:]), hn.dtype) if store else dummy
            counts = np.zeros(B, np.int64)
            _forward(hn, tb, fxn, fyn, 1.0 / dx, dx / eps_scale, tau, n, fixed_iter is not None,
                     done, iters, hist, counts, store)
            if store:
                chunks.append((hist, counts))
            ran += n
            chunk *= 2
        capped = np.zeros(B, bool)
        if fixed_iter is None and not done.all():  # cap reached: did the last update converge?
            probe = done.copy()
            _forward(hn.copy(), tb, fxn, fyn, 1.0 / dx, dx / eps_scale, tau, 1, False, probe,
                     np.zeros(B, np.int64), dummy, np.zeros(B, np.int64), False)
            capped = probe == 0
        ctx.chunks = chunks
        ctx.meta = (tb, fxn, fyn, dx, eps_scale, tan_beta.shape)
        out = torch.from_numpy(hn).to(h.device)
        return out, torch.from_numpy(iters), torch.from_numpy(np.asarray(capped, bool))

    @staticmethod
    def backward(ctx, grad_h, _gi, _gc):
        tb, fxn, fyn, dx, eps_scale, tb_shape = ctx.meta
        lam = grad_h.detach().cpu().numpy().astype(tb.dtype, copy=True)
        tbar = np.zeros_like(tb)
        for hist, counts in reversed(ctx.chunks):
            _backward(hist, counts, lam, tbar, tb, fxn, fyn, 1.0 / dx, dx / eps_scale)
        g_tb = torch.from_numpy(tbar)
        g_tb = g_tb.sum(dim=tuple(d for d in range(3) if tb_shape[d] == 1), keepdim=True)
        return (torch.from_numpy(lam).to(grad_h.device), g_tb.reshape(tb_shape), None, None,
                None, None, None, None, None)


def _face_masks(domain, shape) -> tuple[np.ndarray, np.ndarray]:
    """`stencil.face_masks` as the kernels read them: (X, Y) uint8 numpy arrays."""
    d = np.ones(tuple(shape), bool) if domain is None else domain.detach().cpu().numpy()
    fx, fy = np.zeros(d.shape, np.uint8), np.zeros(d.shape, np.uint8)
    fx[:-1] = d[:-1] & d[1:]
    fy[:, :-1] = d[:, :-1] & d[:, 1:]
    return fx, fy


def relax(h, tan_beta, dx, domain, tau, max_iter, fixed_iter, eps_scale) -> RelaxResult:
    """Numba relaxation with autograd; arguments as `relaxation.relax` (tan_beta (B|1, 1|X, 1|Y))."""
    fx, fy = _face_masks(domain, h.shape[1:])
    tan_beta = tan_beta.to(h.dtype).expand(h.shape[0], -1, -1) if tan_beta.shape[0] == 1 else tan_beta
    out, iters, capped = _Relax.apply(h, tan_beta.to(h.dtype), fx, fy, float(dx), float(tau),
                                      int(max_iter), fixed_iter, float(eps_scale))
    return RelaxResult(out, iters, capped)
