"""Fused CPU kernels of one env step: the soil step of `core.soil_step` and the patches of
`core.observation`, one thread per robot, no per-cell torch tensors.

`soil_step` computes what the torch path computes (`dynamics.wheel_windows`, `dynamics.deform`
with the simulator's stages `taper`, `reference_height`, `sink`, `deposit` and the numba
relaxation, then the write-back), cell by cell in the same float32 operations; the relaxation
is the update of `torchsoil.sim._relax_numba` (same order, same float64 fluxes), so results
agree with the torch path with the numba backend to float32 rounding (tests/envs/test_fused.py).
Each robot's K windows are cut from the field before the step and written back in wheel
order (a later window overwrites an earlier one on a shared cell), as `index_copy_` does.
The cost is mostly memory: a thread reads ahead the cache lines of its next robot's windows
while it steps one (`touch`), and the relaxation visits only the cells a flux can reach.

Lengths in metres, the field layers (N, X, Y) float32, windows W x W cells.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from numba import njit, prange

from envs import dynamics as dyn
from torchsoil.sim.sinkage import disc_offsets
from torchsoil.sim.stencil import EPS2


def _serial_and_parallel(fn):
    """fn compiled twice: serial for one robot (a thread pool only costs there), a thread per
    robot for several. The returned function picks by the first argument's length."""
    serial = njit(cache=True, nogil=True)(fn)
    parallel = njit(parallel=True, cache=True, nogil=True)(fn)

    def run(first, *args):
        return (parallel if first.shape[0] > 1 else serial)(first, *args)

    run.__doc__ = fn.__doc__
    return run


@njit(cache=True, nogil=True, inline="always")
def relax_pass(h, tb, inv_dx, coef, tau, qx, box):
    """One relaxation update of h (W, W) float32 in place, no flux across its edges: the
    update of `torchsoil.sim._relax_numba` (its float64 fluxes, the same sums), in one pass
    (a cell's fluxes read only cells not yet updated). tb: (W, W) face tan(beta); qx: (W,)
    float64 scratch. box: (4,) int64 rows i0..i1, columns j0..j1 (inclusive) that hold every
    cell with a flux; only cells there or one row or column beyond can change, and only those
    are visited. It becomes the box of the next update (empty: i0 > i1). Returns whether
    max |grad h| - tan(beta) >= tau before the update."""
    X, Y = h.shape
    lo_i, hi_i, lo_j, hi_j = box[0], min(box[1] + 1, X - 1), box[2], min(box[3] + 1, Y - 1)
    box[0], box[1], box[2], box[3] = X, -1, Y, -1
    active = False
    for j in range(lo_j, hi_j + 1):
        qx[j] = 0.0
    for i in range(lo_i, hi_i + 1):
        qy_left = 0.0                               # qy of the cell before, qx[j] of the row before
        for j in range(lo_j, hi_j + 1):
            hij = h[i, j]
            gx = (h[i + 1, j] - hij) * inv_dx if i + 1 < X else 0.0
            gy = (h[i, j + 1] - hij) * inv_dx if j + 1 < Y else 0.0
            n2 = gx * gx + gy * gy + EPS2
            t = tb[i, j]
            fx = 0.0
            fy = 0.0
            if n2 > t * t:                          # slope above the angle of repose: soil flows
                n = math.sqrt(n2)
                ex = n - t
                if ex >= tau:
                    active = True
                f = ex / n
                fx = f * gx
                fy = f * gy
                box[0], box[1] = min(box[0], i), max(box[1], i)
                box[2], box[3] = min(box[2], j), max(box[3], j)
            d = fx + fy
            if i > 0:
                d -= qx[j]
            if j > 0:
                d -= qy_left
            h[i, j] = hij + coef * d
            qx[j] = fx
            qy_left = fy
    if box[0] <= box[1]:                            # fluxes of the next update: one cell further
        box[0], box[1] = max(box[0] - 1, 0), min(box[1] + 1, X - 1)
        box[2], box[3] = max(box[2] - 1, 0), min(box[3] + 1, Y - 1)
    return active


@njit(cache=True, nogil=True, inline="always")
def relax_window(h, tb, inv_dx, coef, tau, n_iter, fixed, qx, save):
    """Relax one window h (W, W) float32 in place (`relax_pass`): exactly n_iter updates
    (fixed), or until max |grad h| - tan(beta) < tau, at most n_iter (save: (W, W) float32
    scratch). Returns the updates applied."""
    box = np.array([0, h.shape[0] - 1, 0, h.shape[1] - 1])
    for it in range(n_iter):
        if not fixed:
            save[:] = h
        if not relax_pass(h, tb, inv_dx, coef, tau, qx, box) and not fixed:
            h[:] = save                             # converged before this update: undo it
            return it
    return n_iter


@njit(cache=True, nogil=True, inline="always")
def disc_mean(h, disc, out):
    """out (W, W) = mean of h (W, W) over the cell offsets `disc` (D, 2) around each cell,
    over the offsets that fall inside the window (`sinkage.reference_height`)."""
    W = h.shape[0]
    for a in range(W):
        for b in range(W):
            acc = np.float32(0.0)
            cnt = np.float32(0.0)
            for m in range(disc.shape[0]):
                i, j = a + disc[m, 0], b + disc[m, 1]
                if 0 <= i < W and 0 <= j < W:
                    acc += h[i, j]
                    cnt += np.float32(1.0)
            out[a, b] = acc / cnt


@njit(cache=True, nogil=True, inline="always")
def face_tan(table, i0, j0, Y, tb):
    """tb (W, W) = the face tan(beta) of the window at field cell (i0, j0): the largest
    tan(beta) (column 0 of `table`) of a cell and its +x and +y neighbours in the window
    (`relaxation.face_tan`)."""
    W = tb.shape[0]
    for a in range(W):
        for b in range(W):
            c = (i0 + a) * Y + j0 + b
            t = table[c, 0]
            tx = table[c + Y, 0] if a + 1 < W else t
            ty = table[c + 1, 0] if b + 1 < W else t
            tb[a, b] = max(t, max(tx, ty))


@njit(cache=True, nogil=True, inline="always")
def dig_window(hw, rw, ow, table, i0, j0, Y, seg, col, odom, disc, geo, href, hp, cov, vis, band, binw, vol, cnt):
    """Dig the window's wheel footprint and deposit the spoil in its bands, into hp (W, W).

    hw, rw, ow: (W, W) float32 surface [m], visit reference height [m] and odometer [m] of
    the window before the step. seg: (5,) float32 wheel start x, y [m], unit direction x, y
    and length [m] of its segment. col: the `table` column of the wheel's sinkage. odom:
    odometer after the step, m. disc, geo: as `_soil_step_py`. Out, all (W, W): hp the
    surface to relax [m]; cov (under the wheel), vis (in an ongoing visit), band (in a
    deposition band); href the reference height dug from [m] and binw the deposition bin
    (set where the wheel or a band may reach). vol, cnt: (n_bins,) scratch. Returns the
    removed and the added height summed over the window, m.
    """
    W, n_bins = hw.shape[0], vol.shape[0]
    ox, oy, dx, radius, flat, taper_span, band_hi, r2, dx2, visit_len = (
        geo[0], geo[1], geo[2], geo[3], geo[4], geo[5], geo[6], geo[7], geo[8], geo[9])
    sx, sy, ex, ey, ln = seg[0], seg[1], seg[2], seg[3], seg[4]
    one, zero, half = np.float32(1.0), np.float32(0.0), np.float32(0.5)
    lim = ln + r2
    # cells beyond these bounds (half a cell of slack) are neither under the wheel nor in a band
    far_lat, far_lo, far_hi = band_hi + half * dx, -(radius + half * dx), ln + radius + half * dx
    smooth = disc.shape[0] > 0
    if smooth:
        disc_mean(hw, disc, href)
    vol[:] = zero
    cnt[:] = zero
    removed = 0.0
    for a in range(W):
        rx = (ox + np.float32(i0 + a) * dx) - sx
        for b in range(W):
            ry = (oy + np.float32(j0 + b) * dx) - sy
            along = rx * ex + ry * ey
            lateral = ry * ex - rx * ey
            hc = hw[a, b]
            if abs(lateral) > far_lat or along < far_lo or along > far_hi:
                hp[a, b], cov[a, b], band[a, b] = hc, False, False
                continue
            foot = min(max(along, zero), ln)
            fx, fy = rx - foot * ex, ry - foot * ey
            cv = np.sqrt(fx * fx + fy * fy) <= radius
            vs = (odom - ow[a, b]) <= visit_len
            hr = rw[a, b] if vs else (href[a, b] if smooth else hc)
            hd = hc
            c = (i0 + a) * Y + j0 + b
            if cv:
                u = min(max((abs(lateral / radius) - flat) / taper_span, zero), one)
                hd = min(hc, hr - half * (one + np.cos(np.float32(math.pi) * u)) * table[c, col])
            pos = along + radius
            lat = abs(lateral)
            bd = (lat > radius) and (lat <= band_hi) and (pos >= zero) and (pos <= lim) and not cv and not vs
            bn = min(max(int(np.floor(pos / dx2)), 0), n_bins - 1)
            if cv:
                vol[bn] += (hc - hd) * table[c, table.shape[1] - 2]
                removed += hc - hd
            if bd:
                cnt[bn] += one
            hp[a, b], href[a, b], binw[a, b] = hd, hr, bn
            cov[a, b], vis[a, b], band[a, b] = cv, vs, bd
    added = 0.0
    for a in range(W):
        for b in range(W):
            if band[a, b]:
                share = vol[binw[a, b]] / max(cnt[binw[a, b]], one)
                hp[a, b] = hp[a, b] + share
                added += share
    return removed, added


@njit(cache=True, nogil=True, inline="always")
def write_window(h, ref, ref_odom, passes, n, i0, j0, hp, href, rw, ow, pw, cov, vis, odom, table, every):
    """Write the window at field cell (i0, j0) of robot n back into the (N, X, Y) layers: the
    relaxed surface hp, and where the wheel is (cov) the reference height href it dug from,
    and where it entered (cov and not vis) the odometer and one more pass (all (W, W)).
    every: also write the pre-step values rw, ow, pw of every other cell (a window that
    overlaps another one of the robot). Returns the deepest rut below the initial surface
    under the wheel [m] (0 if none) and the cells entered again after an earlier visit."""
    W, Y = hp.shape[0], h.shape[2]
    one = np.float32(1.0)
    rut, repeat = np.float32(0.0), 0
    for a in range(W):
        i = i0 + a
        for b in range(W):
            j = j0 + b
            h[n, i, j] = hp[a, b]
            if cov[a, b]:
                rut = max(rut, table[i * Y + j, 1] - hp[a, b])
                entered = not vis[a, b]
                p = pw[a, b]
                if entered:
                    repeat += p > 0
                    ref_odom[n, i, j] = odom
                    passes[n, i, j] = p + one
                elif every:
                    ref_odom[n, i, j] = ow[a, b]
                    passes[n, i, j] = p
                ref[n, i, j] = href[a, b]
            elif every:
                ref[n, i, j] = rw[a, b]
                ref_odom[n, i, j] = ow[a, b]
                passes[n, i, j] = pw[a, b]
    return rut, repeat


@njit(cache=True, nogil=True, inline="always")
def overlapping(w0, W):
    """Whether any two of the windows of first cells w0 (K, 2), W cells per side, share a cell."""
    K = w0.shape[0]
    for k in range(K):
        for m in range(k + 1, K):
            if abs(w0[k, 0] - w0[m, 0]) < W and abs(w0[k, 1] - w0[m, 1]) < W:
                return True
    return False


@njit(cache=True, nogil=True, inline="always")
def touch(h, ref, ref_odom, passes, n, w0, W):
    """Read one cell of each cache line robot n's windows will use (every row of h, the
    middle rows of the other layers), so that these memory loads run while the robot before
    it is stepped (a software prefetch). Returns their sum, to be used by the caller."""
    total = np.float32(0.0)
    for k in range(w0.shape[1]):
        i0, j0 = w0[n, k, 0], w0[n, k, 1]
        for a in range(W):
            total += h[n, i0 + a, j0] + h[n, i0 + a, j0 + W - 1]
        for a in range(W // 4, W - W // 4):
            j = j0 + W // 2
            total += ref[n, i0 + a, j] + ref_odom[n, i0 + a, j] + passes[n, i0 + a, j]
    return total


def _soil_step_py(h, ref, ref_odom, passes, table, track, w0, W, seg, odom, disc, geo, n_bins, n_iter, fixed,
                  tau, inv_dx, coef, out_removed, out_added, out_rut, out_repeat, out_iters, lead_sums):
    """Dig, deposit, relax and write back every robot's K windows, in place.

    h, ref, ref_odom, passes: (N, X, Y) float32 layers (`core.TraverseState`).
    table: (X*Y, T + 4) float32 `params.cell_table`. track: (K,) int64.
    w0: (N, K, 2) int64 first cell of each window, W cells per side. seg: (N, K, 5) float32
    wheel start x, y [m], unit direction x, y and length [m] of its segment
    (`dynamics.segment_frames`). odom: (N,) float32 odometer after the step, m.
    disc: (D, 2) int64 reference-disc offsets (D = 0: the cell itself). geo: (11,) float32
    origin x, y, dx, footprint radius, tyre taper f, 1 - f, radius + band width, 2 radius,
    2 dx, visit length [m], cell area [m^2]. n_bins: deposition bins per window (2 dx each).
    n_iter, fixed, tau: `relax_window`; inv_dx, coef: 1 / dx [1/m] and dx / eps_scale [m].
    Out (N,): removed and added volume [m^3], deepest rut [m], repeat cells, updates;
    lead_sums (32,) float32 scratch for the sums of `touch`.

    Windows of a robot that share no cell are read and written in place; if any two
    overlap, all K are copied first and written back whole in wheel order.
    """
    N, K = w0.shape[:2]
    Y = h.shape[2]
    chunks = min(N, 32)
    for ch in prange(chunks):                   # scratch allocated once per chunk of robots
        hw, rw = np.empty((K, W, W), np.float32), np.empty((K, W, W), np.float32)
        ow, pw = np.empty((K, W, W), np.float32), np.empty((K, W, W), np.float32)
        href, hp = np.empty((W, W), np.float32), np.empty((W, W), np.float32)
        tb, save = np.empty((W, W), np.float32), np.empty((W, W), np.float32)
        binw = np.empty((W, W), np.int64)
        cov, vis, band = np.empty((W, W), np.bool_), np.empty((W, W), np.bool_), np.empty((W, W), np.bool_)
        vol, cnt, qx = np.empty(n_bins, np.float32), np.empty(n_bins, np.float32), np.empty(W)
        first, last, lead = ch * N // chunks, (ch + 1) * N // chunks, np.float32(0.0)
        for n in range(first, last):
            if n + 1 < last:
                lead += touch(h, ref, ref_odom, passes, n + 1, w0, W)
            every = overlapping(w0[n], W)
            if every:                           # every window cut before any is written back
                for k in range(K):
                    i0, j0 = w0[n, k, 0], w0[n, k, 1]
                    hw[k] = h[n, i0:i0 + W, j0:j0 + W]
                    rw[k] = ref[n, i0:i0 + W, j0:j0 + W]
                    ow[k] = ref_odom[n, i0:i0 + W, j0:j0 + W]
                    pw[k] = passes[n, i0:i0 + W, j0:j0 + W]
            removed, added, rut, repeat, iters = 0.0, 0.0, np.float32(0.0), 0, 0
            for k in range(K):
                i0, j0 = w0[n, k, 0], w0[n, k, 1]
                if every:
                    hk, rk, ok, pk = hw[k], rw[k], ow[k], pw[k]
                else:
                    hk, rk = h[n, i0:i0 + W, j0:j0 + W], ref[n, i0:i0 + W, j0:j0 + W]
                    ok, pk = ref_odom[n, i0:i0 + W, j0:j0 + W], passes[n, i0:i0 + W, j0:j0 + W]
                dr, da = dig_window(hk, rk, ok, table, i0, j0, Y, seg[n, k], 2 + track[k], odom[n], disc, geo,
                                    href, hp, cov, vis, band, binw, vol, cnt)
                removed, added = removed + dr, added + da
                face_tan(table, i0, j0, Y, tb)
                iters = max(iters, relax_window(hp, tb, inv_dx, coef, tau, n_iter, fixed, qx, save))
                wr, wn = write_window(h, ref, ref_odom, passes, n, i0, j0, hp, href, rk, ok, pk, cov, vis,
                                      odom[n], table, every)
                rut, repeat = max(rut, wr), repeat + wn
            out_removed[n] = np.float32(removed) * geo[10]
            out_added[n] = np.float32(added) * geo[10]
            out_rut[n] = rut
            out_repeat[n] = repeat
            out_iters[n] = iters
        lead_sums[ch] = lead                    # used, so the prefetch loads stay


def _observe_py(h, table, pose, cos, sin, offsets, geo, height, soil):
    """Observation patches of N robots: height (N, 2, M) and soil (N, T + 2, M) float32, filled
    in (`core.observation`; 0 off the field).

    h: (N, X, Y) float32 surface, m. table: `params.cell_table`. pose: (N, 3) float32;
    cos, sin: (N,) float32 of its yaw. offsets: (M, 2) float32 body-frame points, m.
    geo: (3,) float32 field origin x, y and dx, m.
    """
    N, X, Y = h.shape
    ox, oy, dx = geo[0], geo[1], geo[2]
    lo, hi, zero = np.float32(-2.0), np.float32(2.0), np.float32(0.0)
    for n in prange(N):
        px, py, c, s = pose[n, 0], pose[n, 1], cos[n], sin[n]
        ci = min(max(int(np.rint((px - ox) / dx)), 0), X - 1)
        cj = min(max(int(np.rint((py - oy) / dx)), 0), Y - 1)
        hc = h[n, ci, cj]
        for m in range(offsets.shape[0]):
            bx, by = offsets[m, 0], offsets[m, 1]
            i = int(np.rint(((px + c * bx - s * by) - ox) / dx))
            j = int(np.rint(((py + s * bx + c * by) - oy) / dx))
            if 0 <= i < X and 0 <= j < Y:
                v = h[n, i, j]
                height[n, 0, m] = min(max(v - hc, lo), hi)
                height[n, 1, m] = min(max(v - table[i * Y + j, 1], lo), hi)
                for t in range(soil.shape[1]):
                    soil[n, t, m] = table[i * Y + j, 2 + t]
            else:
                height[n, 0, m] = zero
                height[n, 1, m] = zero
                for t in range(soil.shape[1]):
                    soil[n, t, m] = zero


_soil_step = _serial_and_parallel(_soil_step_py)
_observe = _serial_and_parallel(_observe_py)


def _np(t: torch.Tensor) -> np.ndarray:
    """A numpy view of a contiguous CPU tensor (a copy only where it is not contiguous)."""
    return t.detach().contiguous().numpy()


def soil_step(params, state, start: torch.Tensor, end: torch.Tensor, heading: torch.Tensor,
              odom: torch.Tensor) -> tuple[dyn.Damage, torch.Tensor]:
    """`core.soil_step` in one kernel call: the field layers of `state` are updated in place.

    Args:
        params: `envs.params.TraverseParams` on the CPU.
        state: `core.TraverseState`, its (N, X, Y) float32 layers contiguous.
        start, end: (N, K, 2) wheel centres before and after the step, m.
        heading: (N,) yaw before the step, rad.  odom: (N,) odometer after the step, m.

    Returns:
        the step's `dynamics.Damage` and (N,) int64 relaxation updates (most over a robot's windows).
    """
    s, g, W, r = params.config.sim, params.grid, params.window, params.radius
    N = state.num_envs
    w0, ux, uy, length = dyn.segment_frames(start, end, heading, W, g)
    seg = torch.cat([start, ux[..., None], uy[..., None], length[..., None]], -1)   # (N, K, 5)
    n_bins = int((length.max().item() + 2 * r) // (2 * g.dx)) + 1
    disc = disc_offsets(s.ref_radius * r / g.dx)
    disc = np.array(disc if max(max(abs(i), abs(j)) for i, j in disc) > 0 else [], np.int64).reshape(-1, 2)
    f = params.robot.wheel_flat_fraction
    geo = np.array([g.origin[0], g.origin[1], g.dx, r, f, 1.0 - f, r + s.band_width * g.dx, 2 * r, 2 * g.dx,
                    params.visit_length, g.dx * g.dx], np.float32)
    fixed = s.fixed_iter is not None
    out = [np.zeros(N, np.float32) for _ in range(4)] + [np.zeros(N, np.int64)]
    for layer in (state.h, state.ref, state.ref_odom, state.passes):
        if not layer.is_contiguous() or layer.dtype != torch.float32:
            raise ValueError("the fused step needs contiguous float32 field layers")
    _soil_step(state.h.numpy(), state.ref.numpy(), state.ref_odom.numpy(), state.passes.numpy(),
               _np(params.cell_table), _np(params.track), _np(w0), W, _np(seg), _np(odom), disc, geo, n_bins,
               s.fixed_iter if fixed else s.max_iter, fixed, float(s.tau), 1.0 / g.dx, g.dx / s.eps_scale, *out,
               np.empty(32, np.float32))
    removed, added, rut, repeat = (torch.from_numpy(a) for a in out[:4])
    return dyn.Damage(removed, (removed - added).clamp_min(0), rut, repeat), torch.from_numpy(out[4])


def observe(params, pose: torch.Tensor, h: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
    """The patches of `core.observation`: heightmap (N, 2, S, S) [m] and the true soil
    (N, T + 2, S, S) float32, from poses (N, 3) and the surface h (N, X, Y) [m]."""
    N, S, g = pose.shape[0], params.config.obs_size, params.grid
    M, T2 = S * S, params.cell_table.shape[1] - 2
    height = np.empty((N, 2, M), np.float32)
    soil = np.empty((N, T2, M), np.float32)
    geo = np.array([g.origin[0], g.origin[1], g.dx], np.float32)
    yaw = pose[:, 2]
    _observe(_np(h), _np(params.cell_table), _np(pose), _np(torch.cos(yaw)), _np(torch.sin(yaw)),
             _np(params.obs_offsets), geo, height, soil)
    return height.reshape(N, 2, S, S), soil.reshape(N, T2, S, S)
