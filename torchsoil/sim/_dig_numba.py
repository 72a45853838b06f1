"""Fused CPU kernel for `dig.dig`: `sinkage.sink` then `deposition.deposit` in one pass over
the wheel-cell entries, and its adjoint for autograd.

The same arithmetic as the torch ops, in the same order (the scatters add entries in index
order, as torch does on one thread), so the surfaces agree to the bit; the gradients follow
torch's conventions where a min is tied (the gradient is shared evenly among the entries that
reach the min, and between h and the floor where they are equal). Tested against the torch ops.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from numba import njit, prange


@njit(cache=True, nogil=True)
def _rows(b, h, href, covered, s, owner, band):
    """Row of each (B|1, ...) input that batch element b reads (b - b, not 0: a parallel loop's
    unsigned index and a signed 0 would unify to a float)."""
    z = b - b
    return (b if h.shape[0] > 1 else z, b if href.shape[0] > 1 else z, b if covered.shape[0] > 1 else z,
            b if s.shape[0] > 1 else z, b if owner.shape[0] > 1 else z, b if band.shape[0] > 1 else z)


@njit(cache=True, nogil=True)
def _dig_one(h, href, cell, covered, s, depth, owner, band, bins, n_bins, floor, removed, raw):
    """One batch element: floor, removed and raw (XY,) written, the lost height returned."""
    floor[:] = math.inf
    for e in range(cell.shape[0]):
        if covered[e]:
            t = href[cell[e]] - s[e] * depth[e]
            if t < floor[cell[e]]:
                floor[cell[e]] = t
    for c in range(h.shape[0]):
        removed[c] = h[c] - min(h[c], floor[c])
    vol = np.zeros(n_bins, floor.dtype)
    count = np.zeros(n_bins, floor.dtype)
    for e in range(cell.shape[0]):
        if owner[e]:
            vol[bins[e]] += removed[cell[e]]
        if band[e]:
            count[bins[e]] += 1.0
    gone = vol[:0].sum()            # 0 in the surface's dtype
    for k in range(n_bins):
        if count[k] > 0:
            vol[k] = vol[k] / count[k]
        else:
            gone += vol[k]
            vol[k] = 0.0
    raw[:] = 0.0
    for e in range(cell.shape[0]):
        if band[e]:
            raw[cell[e]] += vol[bins[e]]
    return gone


def _forward_py(h, href, cell, covered, s, depth, owner, band, bins, n_bins, floor, removed, raw, lost):
    for b in prange(depth.shape[0]):
        bh, br, bc, bs, bo, bb = _rows(b, h, href, covered, s, owner, band)
        lost[b] = _dig_one(h[bh], href[br], cell, covered[bc], s[bs], depth[b], owner[bo], band[bb], bins, n_bins,
                           floor[b], removed[b], raw[b])


@njit(cache=True, nogil=True)
def _spoil_adjoint(g_a, cell, band, bins, n_bins, chi):
    """Band cells per bin (n_bins,) and the gradient of each bin's share (n_bins,) from that of
    the heights added beside the ruts g_a (XY,), for one batch element (band: (E,))."""
    count = np.zeros(n_bins, g_a.dtype)
    g_vol = np.zeros(n_bins, g_a.dtype)
    for e in range(cell.shape[0]):
        if band[e]:
            count[bins[e]] += 1.0
            g_vol[bins[e]] += chi * g_a[cell[e]]
    return count, g_vol


def _backward_py(h, href, cell, covered, s, depth, owner, band, bins, n_bins, chi, floor, raw,
                 g_pre, g_rem, g_add, g_lost, gh, ghref, gs, gdepth, gchi):
    B = depth.shape[0]
    E = cell.shape[0]
    for b in prange(B):
        bh, br, bc, bs, bo, bb = _rows(b, h, href, covered, s, owner, band)
        # h_pre = h_dug + added, added = chi * raw
        g_a = g_pre[b] + g_add[b]
        gchi[b] = np.sum(g_a * raw[b])
        count, g_vol = _spoil_adjoint(g_a, cell, band[bb], bins, n_bins, chi[b])
        for k in range(n_bins):
            g_vol[k] = g_vol[k] / count[k] if count[k] > 0 else g_lost[b]
        g_removed = g_rem[b].copy()
        for e in range(E):
            if owner[bo, e]:
                g_removed[cell[e]] += g_vol[bins[e]]
        g_floor = _min_adjoint(h[bh], floor[b], g_pre[b], g_removed, gh[b])
        _floor_adjoint(href[br], cell, covered[bc], s[bs], depth[b], floor[b], g_floor, ghref[b], gs[b], gdepth[b])


@njit(cache=True, nogil=True)
def _min_adjoint(h, floor, g_pre, g_removed, gh):
    """removed = h - h_dug, h_dug = min(h, floor): add to gh (XY,) the gradient of h, return that
    of floor (XY,); equal h and floor share it (torch.minimum's convention)."""
    g_floor = np.zeros(h.shape[0], h.dtype)
    for c in range(h.shape[0]):
        g_dug = g_pre[c] - g_removed[c]
        if h[c] < floor[c]:
            gh[c] += g_removed[c] + g_dug
        elif h[c] > floor[c]:
            gh[c] += g_removed[c]
            g_floor[c] = g_dug
        else:
            gh[c] += g_removed[c] + 0.5 * g_dug
            g_floor[c] = 0.5 * g_dug
    return g_floor


@njit(cache=True, nogil=True)
def _floor_adjoint(href, cell, covered, s, depth, floor, g_floor, ghref, gs, gdepth):
    """floor = min from +inf over the covered entries' href[cell] - s * depth: its gradient
    g_floor (XY,) shared evenly among the entries at the min (torch's scatter_reduce "amin")."""
    ties = np.zeros(floor.shape[0], floor.dtype)
    for c in range(floor.shape[0]):
        if floor[c] == math.inf:
            ties[c] = 1.0
    for e in range(cell.shape[0]):
        if covered[e] and href[cell[e]] - s[e] * depth[e] == floor[cell[e]]:
            ties[cell[e]] += 1.0
    for e in range(cell.shape[0]):
        c = cell[e]
        if covered[e] and g_floor[c] != 0.0 and href[c] - s[e] * depth[e] == floor[c]:
            g = g_floor[c] / ties[c]
            ghref[c] += g
            gdepth[e] = -s[e] * g
            gs[e] = -depth[e] * g


_fs, _fp = njit(cache=True, nogil=True)(_forward_py), njit(parallel=True, cache=True, nogil=True)(_forward_py)
_bs, _bp = njit(cache=True, nogil=True)(_backward_py), njit(parallel=True, cache=True, nogil=True)(_backward_py)


def _np(t: torch.Tensor, dtype=None) -> np.ndarray:
    a = t.detach().cpu()
    a = a.numpy() if dtype is None else a.numpy().astype(dtype, copy=False)
    return np.ascontiguousarray(a)


class _Dig(torch.autograd.Function):
    @staticmethod
    def forward(ctx, h, href, s, depth, chi, cell, covered, owner, band, bins, n_bins):
        B, XY = depth.shape[0], h.shape[1] * h.shape[2]
        dt = np.float64 if depth.dtype == torch.float64 else np.float32
        args = (_np(h.reshape(h.shape[0], -1), dt), _np(href.reshape(href.shape[0], -1), dt), _np(cell),
                _np(covered, np.uint8), _np(s, dt), _np(depth, dt), _np(owner, np.uint8), _np(band, np.uint8),
                _np(bins), int(n_bins))
        chi_n = _np(chi, dt)
        floor, removed, raw = (np.empty((B, XY), dt) for _ in range(3))
        lost = np.empty(B, dt)
        (_fp if B > 1 else _fs)(*args, floor, removed, raw, lost)
        added = chi_n[:, None] * raw
        ctx.args, ctx.chi, ctx.floor, ctx.raw = args, chi_n, floor, raw
        ctx.shapes = (h.shape, href.shape, s.shape)
        shape = (B, h.shape[1], h.shape[2])
        pre = torch.from_numpy((np.minimum(args[0], floor) + added).reshape(shape))
        return (pre.to(depth.device), torch.from_numpy(removed.reshape(shape)).to(depth.device),
                torch.from_numpy(added.reshape(shape)).to(depth.device), torch.from_numpy(lost).to(depth.device))

    @staticmethod
    def backward(ctx, g_pre, g_rem, g_add, g_lost):
        args, floor, raw = ctx.args, ctx.floor, ctx.raw
        (h_shape, href_shape, s_shape), dt = ctx.shapes, floor.dtype
        B, XY = floor.shape

        def grad(g, shape):
            return np.zeros(shape, dt) if g is None else _np(g.reshape(shape), dt)

        gp, gr, ga, gl = grad(g_pre, (B, XY)), grad(g_rem, (B, XY)), grad(g_add, (B, XY)), grad(g_lost, (B,))
        gh, ghref = np.zeros((B, XY), dt), np.zeros((B, XY), dt)
        gs, gdepth, gchi = np.zeros((B, args[2].shape[0]), dt), np.zeros((B, args[2].shape[0]), dt), np.zeros(B, dt)
        (_bp if B > 1 else _bs)(*args, ctx.chi, floor, raw, gp, gr, ga, gl, gh, ghref, gs, gdepth, gchi)
        dev = g_pre.device if g_pre is not None else torch.device("cpu")

        def out(a, shape, needed):
            if not needed:
                return None
            t = torch.from_numpy(a)
            t = t.sum(0, keepdim=True) if shape[0] == 1 and B > 1 else t
            return t.reshape(shape).to(dev)

        need = ctx.needs_input_grad
        return (out(gh, h_shape, need[0]), out(ghref, href_shape, need[1]), out(gs, s_shape, need[2]),
                out(gdepth, gdepth.shape, need[3]), out(gchi, gchi.shape, need[4]), None, None, None, None, None, None)


def dig(h, h_ref, cell, covered, s, depth, owner, band, bins, n_bins, chi):
    """Numba `dig.dig` with autograd; arguments and results as there."""
    return _Dig.apply(h, h_ref, s, depth, chi, cell, covered, owner, band, bins, n_bins)
