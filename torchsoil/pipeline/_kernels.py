"""Compiled inner loops of the lidar pipeline (numba, cached on disk, released interpreter
lock so the two re-registration threads run in parallel). Each replaces a chain of numpy
calls on a few thousand points whose cost was allocation and call overhead; the numpy
formulation they replace is kept in the docstrings and tested against them.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

_OPTS = {"cache": True, "nogil": True, "fastmath": False}
_OFFSET = 1 << 20


@njit(**_OPTS)
def voxel_keys(points, voxel):
    """(N, 3) -> (N,) int64 voxel keys, as icp.voxel_keys."""
    n = points.shape[0]
    out = np.empty(n, np.int64)
    for i in range(n):
        a = np.int64(math.floor(points[i, 0] / voxel + 0.5)) + _OFFSET
        b = np.int64(math.floor(points[i, 1] / voxel + 0.5)) + _OFFSET
        c = np.int64(math.floor(points[i, 2] / voxel + 0.5)) + _OFFSET
        out[i] = a + (b << 21) + (c << 42)
    return out


@njit(**_OPTS)
def first_of_keys(keys):
    """(N,) int64 keys -> (first (U,) index of the first point of each distinct key, in order of
    first appearance; inverse (N,) slot of each point in `first`). An open-addressing hash."""
    n = keys.shape[0]
    size = 16
    while size < 2 * n:
        size *= 2
    mask = size - 1
    table = np.full(size, -1, np.int64)
    first = np.empty(n, np.int64)
    inv = np.empty(n, np.int64)
    u = 0
    for i in range(n):
        key = keys[i]
        j = ((key * np.int64(-7046029254386353131)) >> np.int64(24)) & mask
        while True:
            s = table[j]
            if s < 0:
                table[j] = u
                first[u] = i
                inv[i] = u
                u += 1
                break
            if keys[first[s]] == key:
                inv[i] = s
                break
            j = (j + 1) & mask
    return first[:u], inv


@njit(**_OPTS)
def centroids(points, inv, u):
    """Mean of the points (N, 3) per slot inv (N,) in [0, u) -> (u, 3)."""
    out = np.zeros((u, 3))
    cnt = np.zeros(u)
    for i in range(points.shape[0]):
        s = inv[i]
        out[s, 0] += points[i, 0]
        out[s, 1] += points[i, 1]
        out[s, 2] += points[i, 2]
        cnt[s] += 1.0
    for s in range(u):
        out[s, 0] /= cnt[s]
        out[s, 1] /= cnt[s]
        out[s, 2] /= cnt[s]
    return out


@njit(**_OPTS)
def transform(points, R, t):
    """(N, 3) points -> R p + t, float64."""
    n = points.shape[0]
    out = np.empty((n, 3))
    for i in range(n):
        x, y, z = points[i, 0], points[i, 1], points[i, 2]
        for r in range(3):
            out[i, r] = R[r, 0] * x + R[r, 1] * y + R[r, 2] * z + t[r]
    return out


@njit(**_OPTS)
def deskew(points, t, rotvec, shift, dt):
    """Each point p at time tau -> R(tau / dt * rotvec) p + tau / dt * shift (Rodrigues:
    the axis is common to all points, only the angle scales with time)."""
    n = points.shape[0]
    out = np.empty((n, 3))
    angle = math.sqrt(rotvec[0] ** 2 + rotvec[1] ** 2 + rotvec[2] ** 2)
    kx, ky, kz = 0.0, 0.0, 0.0
    if angle > 0:
        kx, ky, kz = rotvec[0] / angle, rotvec[1] / angle, rotvec[2] / angle
    for i in range(n):
        s = t[i] / dt
        x, y, z = points[i, 0], points[i, 1], points[i, 2]
        if angle > 0:
            th = s * angle
            co, si = math.cos(th), math.sin(th)
            dot = (kx * x + ky * y + kz * z) * (1.0 - co)
            cx, cy, cz = ky * z - kz * y, kz * x - kx * z, kx * y - ky * x
            x, y, z = x * co + cx * si + kx * dot, y * co + cy * si + ky * dot, z * co + cz * si + kz * dot
        out[i, 0] = x + s * shift[0]
        out[i, 1] = y + s * shift[1]
        out[i, 2] = z + s * shift[2]
    return out


@njit(**_OPTS)
def icp_system(p, idx, tp, tn, c, ground_z, use_ground, one_sided, steep, kernel, H, g):
    """Point-to-plane normal equations at one ICP iteration (see icp.register).

    p (S, 3) source points at the current pose; idx (S,) their nearest target point (len(tp)
    where none within the gate); tp, tn target points and normals; c (3,) sensor position.
    Fills H (6, 6) and g (6,) with sum w J J^T and sum w J r over the matches used; returns
    (matches within the gate, matches used after the one-sided test).
    """
    m = tp.shape[0]
    k2 = kernel * kernel
    for a in range(6):
        g[a] = 0.0
        for b in range(6):
            H[a, b] = 0.0
    J = np.empty(6)
    n_ok = 0
    n_used = 0
    for i in range(p.shape[0]):
        j = idx[i]
        if j >= m:
            continue
        n_ok += 1
        nx, ny, nz = tn[j, 0], tn[j, 1], tn[j, 2]
        px, py, pz = p[i, 0], p[i, 1], p[i, 2]
        if one_sided and abs(nz) < steep:
            if nx * (c[0] - px) + ny * (c[1] - py) + nz * (c[2] - pz) <= 0:
                continue
        n_used += 1
        r = (px - tp[j, 0]) * nx + (py - tp[j, 1]) * ny + (pz - tp[j, 2]) * nz
        dx, dy, dz = px - c[0], py - c[1], pz - c[2]
        J[0] = dy * nz - dz * ny
        J[1] = dz * nx - dx * nz
        J[2] = dx * ny - dy * nx
        J[3] = nx
        J[4] = ny
        J[5] = nz
        if use_ground and nz > ground_z:
            J[2] = 0.0
            J[3] = 0.0
            J[4] = 0.0
        w = k2 / (k2 + r * r)
        w = w * w
        for a in range(6):
            wa = w * J[a]
            g[a] += wa * r
            for b in range(a, 6):
                H[a, b] += wa * J[b]
    for a in range(6):
        for b in range(a):
            H[a, b] = H[b, a]
    return n_ok, n_used


@njit(**_OPTS)
def icp_residual(p, idx, tp, tn, c, one_sided, steep, kernel):
    """Final evaluation of icp.register: (matches used, sum of w, sum of w r^2)."""
    m = tp.shape[0]
    k2 = kernel * kernel
    n_used = 0
    sw = 0.0
    swr = 0.0
    for i in range(p.shape[0]):
        j = idx[i]
        if j >= m:
            continue
        nx, ny, nz = tn[j, 0], tn[j, 1], tn[j, 2]
        px, py, pz = p[i, 0], p[i, 1], p[i, 2]
        if one_sided and abs(nz) < steep:
            if nx * (c[0] - px) + ny * (c[1] - py) + nz * (c[2] - pz) <= 0:
                continue
        n_used += 1
        r = (px - tp[j, 0]) * nx + (py - tp[j, 1]) * ny + (pz - tp[j, 2]) * nz
        w = k2 / (k2 + r * r)
        w = w * w
        sw += w
        swr += w * r * r
    return n_used, sw, swr


@njit(**_OPTS)
def fresh(held, keys):
    """Indices (in order) of the first point of each distinct key of keys (N,) that is not
    among `held` (M,) keys: the points that open a voxel not occupied yet."""
    m = held.shape[0]
    size = 16
    while size < 2 * (m + keys.shape[0]):
        size *= 2
    mask = size - 1
    table = np.full(size, -1, np.int64)  # slot -> index into `held` (< m) or m + index into keys
    for i in range(m):
        key = held[i]
        j = ((key * np.int64(-7046029254386353131)) >> np.int64(24)) & mask
        while table[j] >= 0:
            j = (j + 1) & mask
        table[j] = i
    out = np.empty(keys.shape[0], np.int64)
    u = 0
    for i in range(keys.shape[0]):
        key = keys[i]
        j = ((key * np.int64(-7046029254386353131)) >> np.int64(24)) & mask
        while True:
            s = table[j]
            if s < 0:
                table[j] = m + i
                out[u] = i
                u += 1
                break
            if (held[s] if s < m else keys[s - m]) == key:
                break
            j = (j + 1) & mask
    return out[:u]


# ---- exact nearest neighbours within a bounded distance on a hashed voxel grid ----

@njit(**_OPTS)
def _cell_key(a, b, c):
    return (a + _OFFSET) + ((b + _OFFSET) << 21) + ((c + _OFFSET) << 42)


@njit(**_OPTS)
def _slot(table, ckeys, key):
    """Cell index of `key` in the grid's hash table, -1 if the cell is empty."""
    mask = table.shape[0] - 1
    j = ((key * np.int64(-7046029254386353131)) >> np.int64(24)) & mask
    while True:
        s = table[j]
        if s < 0 or ckeys[s] == key:
            return s
        j = (j + 1) & mask


@njit(**_OPTS)
def grid_build(points, h):
    """Points (M, 3) bucketed into cubic cells of edge h: (hash table, cell keys (U,),
    cell start (U + 1,) into perm, perm (M,) point order by cell, points in that order)."""
    n = points.shape[0]
    size = 16
    while size < 2 * n:
        size *= 2
    mask = size - 1
    table = np.full(size, -1, np.int64)
    ckeys = np.empty(n, np.int64)
    inv = np.empty(n, np.int64)
    u = 0
    for i in range(n):
        key = _cell_key(np.int64(math.floor(points[i, 0] / h)), np.int64(math.floor(points[i, 1] / h)),
                        np.int64(math.floor(points[i, 2] / h)))
        j = ((key * np.int64(-7046029254386353131)) >> np.int64(24)) & mask
        while True:
            s = table[j]
            if s < 0:
                table[j] = u
                ckeys[u] = key
                inv[i] = u
                u += 1
                break
            if ckeys[s] == key:
                inv[i] = s
                break
            j = (j + 1) & mask
    start = np.zeros(u + 1, np.int64)
    for i in range(n):
        start[inv[i] + 1] += 1
    for s in range(u):
        start[s + 1] += start[s]
    fill = start[:u].copy()
    perm = np.empty(n, np.int64)
    for i in range(n):
        s = inv[i]
        perm[fill[s]] = i
        fill[s] += 1
    sp = np.empty((n, 3))
    for i in range(n):
        sp[i, 0] = points[perm[i], 0]
        sp[i, 1] = points[perm[i], 1]
        sp[i, 2] = points[perm[i], 2]
    return table, ckeys[:u].copy(), start, perm, sp


@njit(**_OPTS)
def _box_d2(d, u):
    """Squared distance, in cell units, from position u in [0, 1) of a cell to the cell d away."""
    if d > 0:
        return (d - u) * (d - u)
    if d < 0:
        return (u - d - 1) * (u - d - 1)
    return 0.0


@njit(**_OPTS)
def grid_knn(q, k, r, h, table, ckeys, start, perm, sp, offs, lbs):
    """The k nearest grid points closer than r to each query (Q, 3), nearest first: distances
    (Q, k) (inf where fewer) and indices (Q, k) into the original points (M where fewer).
    Cells are visited in order of their least possible distance (offs, lbs: offsets within
    ceil(r / h) cells and their lower bounds in cell units squared), skipping those farther
    than the current k-th best, so the result is exact."""
    nq = q.shape[0]
    m = perm.shape[0]
    d_out = np.full((nq, k), np.inf)
    i_out = np.full((nq, k), m, np.int64)
    h2 = h * h
    bd = np.empty(k)
    bt = np.empty(k, np.int64)
    for qi in range(nq):
        x, y, z = q[qi, 0], q[qi, 1], q[qi, 2]
        fx, fy, fz = math.floor(x / h), math.floor(y / h), math.floor(z / h)
        a0, b0, c0 = np.int64(fx), np.int64(fy), np.int64(fz)
        ux, uy, uz = x / h - fx, y / h - fy, z / h - fz
        nf = 0
        worst = r * r
        for o in range(offs.shape[0]):
            if lbs[o] * h2 >= worst:
                break
            dx, dy, dz = offs[o, 0], offs[o, 1], offs[o, 2]
            if (_box_d2(dx, ux) + _box_d2(dy, uy) + _box_d2(dz, uz)) * h2 >= worst:
                continue
            s = _slot(table, ckeys, _cell_key(a0 + dx, b0 + dy, c0 + dz))
            if s < 0:
                continue
            for t in range(start[s], start[s + 1]):
                ex, ey, ez = sp[t, 0] - x, sp[t, 1] - y, sp[t, 2] - z
                d2 = ex * ex + ey * ey + ez * ez
                if d2 < worst:
                    p = nf if nf < k else k - 1
                    while p > 0 and bd[p - 1] > d2:
                        bd[p] = bd[p - 1]
                        bt[p] = bt[p - 1]
                        p -= 1
                    bd[p] = d2
                    bt[p] = t
                    if nf < k:
                        nf += 1
                    if nf == k:
                        worst = bd[k - 1]
        for a in range(nf):
            d_out[qi, a] = math.sqrt(bd[a])
            i_out[qi, a] = perm[bt[a]]
    return d_out, i_out


@njit(**_OPTS)
def _scan_cell(table, ckeys, start, sp, key, x, y, z, best, bi):
    s = _slot(table, ckeys, key)
    if s >= 0:
        for t in range(start[s], start[s + 1]):
            ex, ey, ez = sp[t, 0] - x, sp[t, 1] - y, sp[t, 2] - z
            d2 = ex * ex + ey * ey + ez * ez
            if d2 < best:
                best = d2
                bi = t
    return best, bi


@njit(**_OPTS)
def grid_nn(q, r, h, table, ckeys, start, perm, sp):
    """Nearest grid point closer than r to each query (Q, 3): distances (Q,) (inf where
    none) and indices (Q,) into the original points (M where none). The query's own cell
    first, then the cells of the box reaching the current best distance that can hold a
    closer point, so the result is exact."""
    nq = q.shape[0]
    m = perm.shape[0]
    d_out = np.full(nq, np.inf)
    i_out = np.full(nq, m, np.int64)
    h2 = h * h
    for qi in range(nq):
        x, y, z = q[qi, 0], q[qi, 1], q[qi, 2]
        fx, fy, fz = math.floor(x / h), math.floor(y / h), math.floor(z / h)
        a0, b0, c0 = np.int64(fx), np.int64(fy), np.int64(fz)
        ux, uy, uz = x / h - fx, y / h - fy, z / h - fz
        best, bi = _scan_cell(table, ckeys, start, sp, _cell_key(a0, b0, c0), x, y, z, r * r, -1)
        reach = math.sqrt(best) / h
        lx, hx = np.int64(math.floor(ux - reach)), np.int64(math.floor(ux + reach))
        ly, hy = np.int64(math.floor(uy - reach)), np.int64(math.floor(uy + reach))
        lz, hz = np.int64(math.floor(uz - reach)), np.int64(math.floor(uz + reach))
        for dx in range(lx, hx + 1):
            bx = _box_d2(dx, ux)
            for dy in range(ly, hy + 1):
                bxy = bx + _box_d2(dy, uy)
                for dz in range(lz, hz + 1):
                    if dx == 0 and dy == 0 and dz == 0:
                        continue
                    if (bxy + _box_d2(dz, uz)) * h2 >= best:
                        continue
                    best, bi = _scan_cell(table, ckeys, start, sp, _cell_key(a0 + dx, b0 + dy, c0 + dz),
                                          x, y, z, best, bi)
        if bi >= 0:
            d_out[qi] = math.sqrt(best)
            i_out[qi] = perm[bi]
    return d_out, i_out


@njit(**_OPTS)
def _nn2(x, y, z, R2, h, table, ckeys, start, sp):
    """The nearest grid point (its position in sp, -1 if none) closer than sqrt(R2) to
    (x, y, z), its squared distance, and the squared distance of the second nearest (R2
    where there is none within; each a bound on every other point): as grid_nn, pruned by
    the second distance."""
    h2 = h * h
    fx, fy, fz = math.floor(x / h), math.floor(y / h), math.floor(z / h)
    a0, b0, c0 = np.int64(fx), np.int64(fy), np.int64(fz)
    ux, uy, uz = x / h - fx, y / h - fy, z / h - fz
    b1, b2, bi = R2, R2, -1
    s = _slot(table, ckeys, _cell_key(a0, b0, c0))     # the query's own cell first
    if s >= 0:
        for t in range(start[s], start[s + 1]):
            ex, ey, ez = sp[t, 0] - x, sp[t, 1] - y, sp[t, 2] - z
            d2 = ex * ex + ey * ey + ez * ez
            if d2 < b1:
                b2, b1, bi = b1, d2, t
            elif d2 < b2:
                b2 = d2
    reach = math.sqrt(b2) / h
    lx, hx = np.int64(math.floor(ux - reach)), np.int64(math.floor(ux + reach))
    ly, hy = np.int64(math.floor(uy - reach)), np.int64(math.floor(uy + reach))
    lz, hz = np.int64(math.floor(uz - reach)), np.int64(math.floor(uz + reach))
    for dx in range(lx, hx + 1):
        bx = _box_d2(dx, ux)
        for dy in range(ly, hy + 1):
            bxy = bx + _box_d2(dy, uy)
            for dz in range(lz, hz + 1):
                if dx == 0 and dy == 0 and dz == 0:
                    continue
                if (bxy + _box_d2(dz, uz)) * h2 >= b2:
                    continue
                s = _slot(table, ckeys, _cell_key(a0 + dx, b0 + dy, c0 + dz))
                if s < 0:
                    continue
                for t in range(start[s], start[s + 1]):
                    ex, ey, ez = sp[t, 0] - x, sp[t, 1] - y, sp[t, 2] - z
                    d2 = ex * ex + ey * ey + ez * ez
                    if d2 < b1:
                        b2, b1, bi = b1, d2, t
                    elif d2 < b2:
                        b2 = d2
    return bi, b1, b2


@njit(**_OPTS)
def grid_match(q, r, R, h, table, ckeys, start, perm, sp, data, at, near, bound, idx):
    """Nearest neighbours closer than r of the queries q (S, 3) into idx (S,) (index into
    the grid's points `data` (M, 3), M where none): the same as grid_nn, but a query that
    moved little since its last search keeps its answer when that cannot have changed.

    Per query the state of its last search: at (S, 3) where it was made (NaN: none yet),
    near (S,) the nearest point within R >= r (M: none) and bound (S,) the distance of the
    second nearest (R where none: no other point is closer). A query now delta from `at`
    keeps `near` as its nearest when its distance to it plus 1e-6 m is below bound - delta
    (every other point is at least that far), and keeps having none within r when
    r + 1e-6 < bound - delta; otherwise it is searched again (within R) and its state
    renewed. The margin covers the rounding of these distances, so idx is what grid_nn
    returns. Returns how many queries were searched."""
    m = data.shape[0]
    r2, R2 = r * r, R * R
    searched = 0
    for i in range(q.shape[0]):
        x, y, z = q[i, 0], q[i, 1], q[i, 2]
        ex, ey, ez = x - at[i, 0], y - at[i, 1], z - at[i, 2]
        delta = math.sqrt(ex * ex + ey * ey + ez * ez)
        j = near[i]
        if j < m:
            ex, ey, ez = data[j, 0] - x, data[j, 1] - y, data[j, 2] - z
            d2 = ex * ex + ey * ey + ez * ez
            if math.sqrt(d2) + 1e-6 < bound[i] - delta:
                idx[i] = j if d2 < r2 else m
                continue
        elif r + 1e-6 < bound[i] - delta:
            idx[i] = m
            continue
        searched += 1
        bi, b1, b2 = _nn2(x, y, z, R2, h, table, ckeys, start, sp)
        at[i, 0], at[i, 1], at[i, 2] = x, y, z
        near[i] = perm[bi] if bi >= 0 else m
        bound[i] = math.sqrt(b2)
        idx[i] = perm[bi] if bi >= 0 and b1 < r2 else m
    return searched


@njit(**_OPTS)
def grid_any_newer(q, since, born, r, h, table, ckeys, start, perm, sp, offs, lbs):
    """(Q,) True where some grid point closer than r to q[i] has born[point] > since[i]."""
    nq = q.shape[0]
    out = np.zeros(nq, np.bool_)
    h2 = h * h
    r2 = r * r
    for qi in range(nq):
        x, y, z = q[qi, 0], q[qi, 1], q[qi, 2]
        fx, fy, fz = math.floor(x / h), math.floor(y / h), math.floor(z / h)
        a0, b0, c0 = np.int64(fx), np.int64(fy), np.int64(fz)
        ux, uy, uz = x / h - fx, y / h - fy, z / h - fz
        e = since[qi]
        found = False
        for o in range(offs.shape[0]):
            if found or lbs[o] * h2 >= r2:
                break
            dx, dy, dz = offs[o, 0], offs[o, 1], offs[o, 2]
            if (_box_d2(dx, ux) + _box_d2(dy, uy) + _box_d2(dz, uz)) * h2 >= r2:
                continue
            s = _slot(table, ckeys, _cell_key(a0 + dx, b0 + dy, c0 + dz))
            if s < 0:
                continue
            for t in range(start[s], start[s + 1]):
                if born[perm[t]] > e:
                    ex, ey, ez = sp[t, 0] - x, sp[t, 1] - y, sp[t, 2] - z
                    if ex * ex + ey * ey + ez * ez < r2:
                        found = True
                        break
        out[qi] = found
    return out


@njit(**_OPTS)
def covariances(points, idx, d):
    """Covariance (Q, 3, 3) and count (Q,) of the neighbours points[idx[q, a]] with finite
    d[q, a] (as icp.pca_normals: mean-centred, divided by the count)."""
    nq, k = idx.shape
    cov = np.zeros((nq, 3, 3))
    cnt = np.zeros(nq, np.int64)
    for q in range(nq):
        n = 0
        mx, my, mz = 0.0, 0.0, 0.0
        for a in range(k):
            if math.isfinite(d[q, a]):
                j = idx[q, a]
                mx += points[j, 0]
                my += points[j, 1]
                mz += points[j, 2]
                n += 1
        cnt[q] = n
        if n == 0:
            continue
        mx, my, mz = mx / n, my / n, mz / n
        sxx, sxy, sxz, syy, syz, szz = 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
        for a in range(k):
            if math.isfinite(d[q, a]):
                j = idx[q, a]
                x, y, z = points[j, 0] - mx, points[j, 1] - my, points[j, 2] - mz
                sxx += x * x
                sxy += x * y
                sxz += x * z
                syy += y * y
                syz += y * z
                szz += z * z
        cov[q, 0, 0], cov[q, 0, 1], cov[q, 0, 2] = sxx / n, sxy / n, sxz / n
        cov[q, 1, 0], cov[q, 1, 1], cov[q, 1, 2] = sxy / n, syy / n, syz / n
        cov[q, 2, 0], cov[q, 2, 1], cov[q, 2, 2] = sxz / n, syz / n, szz / n
    return cov, cnt


@njit(**_OPTS)
def rotvec_of(R):
    """(3, 3) rotation matrix -> (3,) rotation vector (quaternion route, as scipy's Rotation)."""
    tr = R[0, 0] + R[1, 1] + R[2, 2]
    q = np.empty(4)
    i = 0
    if R[1, 1] > R[i, i]:
        i = 1
    if R[2, 2] > R[i, i]:
        i = 2
    if tr >= R[i, i]:
        q[0], q[1], q[2], q[3] = R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1], 1.0 + tr
    else:
        j, k = (i + 1) % 3, (i + 2) % 3
        q[i] = 1.0 - tr + 2.0 * R[i, i]
        q[j] = R[j, i] + R[i, j]
        q[k] = R[k, i] + R[i, k]
        q[3] = R[k, j] - R[j, k]
    nq = math.sqrt(q[0] ** 2 + q[1] ** 2 + q[2] ** 2 + q[3] ** 2)
    if q[3] < 0:
        nq = -nq
    x, y, z, w = q[0] / nq, q[1] / nq, q[2] / nq, q[3] / nq
    angle = 2.0 * math.atan2(math.sqrt(x * x + y * y + z * z), w)
    if angle <= 1e-3:
        scale = 2.0 + angle ** 2 / 12.0 + 7.0 * angle ** 4 / 2880.0
    else:
        scale = angle / math.sin(angle / 2.0)
    out = np.empty(3)
    out[0], out[1], out[2] = scale * x, scale * y, scale * z
    return out


@njit(**_OPTS)
def rotation(w):
    """(3,) rotation vector -> (3, 3) rotation matrix (quaternion route, as scipy's Rotation)."""
    angle = math.sqrt(w[0] ** 2 + w[1] ** 2 + w[2] ** 2)
    if angle <= 1e-3:
        scale = 0.5 - angle ** 2 / 48.0 + angle ** 4 / 3840.0
    else:
        scale = math.sin(angle / 2.0) / angle
    x, y, z, s = scale * w[0], scale * w[1], scale * w[2], math.cos(angle / 2.0)
    R = np.empty((3, 3))
    R[0, 0] = 1.0 - 2.0 * (y * y + z * z)
    R[0, 1] = 2.0 * (x * y - z * s)
    R[0, 2] = 2.0 * (x * z + y * s)
    R[1, 0] = 2.0 * (x * y + z * s)
    R[1, 1] = 1.0 - 2.0 * (x * x + z * z)
    R[1, 2] = 2.0 * (y * z - x * s)
    R[2, 0] = 2.0 * (x * z - y * s)
    R[2, 1] = 2.0 * (y * z + x * s)
    R[2, 2] = 1.0 - 2.0 * (x * x + y * y)
    return R


def icp_step(T, H, g):
    """One Gauss-Newton update of icp.register: solve (H + 1e-9 I) delta = -g, turn delta
    (rotation about the sensor position T[:3, 3], then translation) into a (4, 4) step and
    return (step @ T, max |delta|). Plain numpy: a 6 x 6 solve once per iteration, where
    compiling numba's linalg.solve took most of the pipeline kernels' compile time."""
    A = H.copy()
    for a in range(6):
        A[a, a] += 1e-9
    delta = -np.linalg.solve(A, g)
    R = rotation(delta[:3])
    step = np.eye(4)
    for a in range(3):
        step[a, 3] = T[a, 3] + delta[3 + a]
        for b in range(3):
            step[a, b] = R[a, b]
            step[a, 3] -= R[a, b] * T[b, 3]
    return step @ T, np.abs(delta).max()


@njit(**_OPTS)
def local_merge(points, normals, good, age, views, keys, new_points, new_keys, center, radius):
    """One LocalMap update: the held voxels (points, normals, good, age + 1, views, keys)
    followed by the new ones (zero normal, not good, age 0, seen from center), keeping those
    within `radius` of center horizontally. Returns the six arrays and the number of held
    voxels kept (they come first)."""
    n_old, n_new = points.shape[0], new_points.shape[0]
    m = n_old + n_new
    P = np.empty((m, 3))
    N = np.empty((m, 3))
    G = np.empty(m, np.bool_)
    A = np.empty(m, np.int64)
    V = np.empty((m, 3))
    K = np.empty(m, np.int64)
    u = 0
    for i in range(n_old):
        dx, dy = points[i, 0] - center[0], points[i, 1] - center[1]
        if math.sqrt(dx * dx + dy * dy) < radius:
            for a in range(3):
                P[u, a] = points[i, a]
                N[u, a] = normals[i, a]
                V[u, a] = views[i, a]
            G[u] = good[i]
            A[u] = age[i] + 1
            K[u] = keys[i]
            u += 1
    kept_old = u
    for i in range(n_new):
        dx, dy = new_points[i, 0] - center[0], new_points[i, 1] - center[1]
        if math.sqrt(dx * dx + dy * dy) < radius:
            for a in range(3):
                P[u, a] = new_points[i, a]
                N[u, a] = 0.0
                V[u, a] = center[a]
            G[u] = False
            A[u] = 0
            K[u] = new_keys[i]
            u += 1
    return P[:u].copy(), N[:u].copy(), G[:u].copy(), A[:u].copy(), V[:u].copy(), K[:u].copy(), kept_old


@njit(**_OPTS)
def table_insert(table, held, n_held, keys):
    """Insert the keys (N,) not yet in the open-addressing `table` (slots hold indices into
    `held`, -1 when free; `held` has room after its first n_held entries): each distinct new
    key is appended to `held` and its table slot set. Returns the indices (into keys) of the
    first point of each new key, in order. The table must stay below half full."""
    mask = table.shape[0] - 1
    out = np.empty(keys.shape[0], np.int64)
    u = 0
    for i in range(keys.shape[0]):
        key = keys[i]
        j = ((key * np.int64(-7046029254386353131)) >> np.int64(24)) & mask
        while True:
            s = table[j]
            if s < 0:
                table[j] = n_held + u
                held[n_held + u] = key
                out[u] = i
                u += 1
                break
            if held[s] == key:
                break
            j = (j + 1) & mask
    return out[:u]


@njit(**_OPTS)
def table_build(held, n_held, size):
    """Open-addressing table of `size` slots (a power of two) over held[:n_held]."""
    mask = size - 1
    table = np.full(size, -1, np.int64)
    for i in range(n_held):
        j = ((held[i] * np.int64(-7046029254386353131)) >> np.int64(24)) & mask
        while table[j] >= 0:
            j = (j + 1) & mask
        table[j] = i
    return table


@njit(**_OPTS)
def within_range(points, max_range):
    """Indices of the points (N, 3) closer than max_range to the origin."""
    out = np.empty(points.shape[0], np.int64)
    u = 0
    for i in range(points.shape[0]):
        x, y, z = points[i, 0], points[i, 1], points[i, 2]
        if math.sqrt(x * x + y * y + z * z) < max_range:
            out[u] = i
            u += 1
    return out[:u]


# ---- heightmap tiles ----

@njit(**_OPTS)
def tile_cells(xy, dx, size):
    """Points xy (N, >= 2) [m, columns x, y] -> the tiles of `size` x `size` lattice cells
    they fall in (cell (I, J) centred at (I dx, J dx)): keys (T, 2) in order of first hit,
    order (N,) of the points tile by tile (in point order within a tile), start (T + 1,) of
    each tile's run in `order`, and cell (N,) each point's cell within its tile,
    (I - A size) size + (J - B size)."""
    n = xy.shape[0]
    ta = np.empty(n, np.int64)
    tb = np.empty(n, np.int64)
    cell = np.empty(n, np.int64)
    for i in range(n):
        ci = np.int64(np.rint(xy[i, 0] / dx))
        cj = np.int64(np.rint(xy[i, 1] / dx))
        ta[i], tb[i] = ci // size, cj // size
        cell[i] = (ci - ta[i] * size) * size + (cj - tb[i] * size)
    a0, b0 = (ta.min(), tb.min()) if n else (0, 0)
    na, nb = (ta.max() - a0 + 1, tb.max() - b0 + 1) if n else (1, 1)
    if na * nb <= 4 * n + 4096:    # tile -> slot by a table over the points' box of tiles
        lookup = np.full(na * nb, -1, np.int64)
        first = np.empty(n, np.int64)
        slot = np.empty(n, np.int64)
        t = 0
        for i in range(n):
            f = (ta[i] - a0) * nb + (tb[i] - b0)
            if lookup[f] < 0:
                lookup[f] = t
                first[t] = i
                t += 1
            slot[i] = lookup[f]
        first = first[:t]
    else:                          # points spread far: hashed
        first, slot = first_of_keys((ta - a0) * nb + (tb - b0))
        t = first.shape[0]
    keys = np.empty((t, 2), np.int64)
    for u in range(t):
        keys[u, 0], keys[u, 1] = ta[first[u]], tb[first[u]]
    start = np.zeros(t + 1, np.int64)
    for i in range(n):
        start[slot[i] + 1] += 1
    for u in range(t):
        start[u + 1] += start[u]
    fill = start[:t].copy()
    order = np.empty(n, np.int64)
    for i in range(n):
        order[fill[slot[i]]] = i
        fill[slot[i]] += 1
    return keys, order, start, cell


@njit(**_OPTS)
def tile_add(tile, scratch, z, order, cell, a, b):
    """Add the points order[a:b] (one tile's run of `tile_cells`) of heights z (N,) [m] into
    tile (3, size * size): per cell the count, the sum of z and of z^2 of its points, each
    summed in point order from zero in `scratch` (3, size * size; all zero, and left so) and
    then added to the tile (as numpy's `tile += sums` of the sweep's own sums)."""
    touched = np.empty(b - a, np.int64)
    m = 0
    for q in range(a, b):
        i = order[q]
        c = cell[i]
        if scratch[0, c] == 0.0:
            touched[m] = c
            m += 1
        h = z[i]
        scratch[0, c] += 1.0
        scratch[1, c] += h
        scratch[2, c] += h * h
    for u in range(m):
        c = touched[u]
        for r in range(3):
            tile[r, c] += scratch[r, c]
            scratch[r, c] = 0.0


@njit(**_OPTS)
def tile_count_le(tile, row, t, order, cell, a, b, out):
    """For the points order[a:b] (one tile's run of `tile_cells`): out[i] = how many of the
    rows row, row + 2, ... of tile (R, size * size) hold at cell[i] a value <= t[i] (NaN
    counts as none), as (tile[row::2][:, cell] <= t).sum(0)."""
    for q in range(a, b):
        i = order[q]
        c = cell[i]
        n = 0
        for r in range(row, tile.shape[0], 2):
            if tile[r, c] <= t[i]:
                n += 1
        out[i] = n
