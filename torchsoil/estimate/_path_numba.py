"""Compiled search of the path index (numba, cached on disk): the latest path point within a
radius of each cell, over cells binned on a square lattice."""

from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def latest_within(cells, points, radius, h):
    """(C,) int64: the latest index n such that some (K, N, 2) points[k, n] lies within
    radius[c] [m] of cell c of (C, 2) cells (Euclidean, inclusive: the test
    sqrt(dx^2 + dy^2) <= r), -1 where none does. Cells are binned on squares of edge h [m]
    (h >= radius.max() keeps each point's search to 3 x 3 bins); the path is walked from its
    end, so a cell leaves the search at its first hit."""
    C, K, N = cells.shape[0], points.shape[0], points.shape[1]
    last = np.full(C, -1, np.int64)
    if C == 0 or N == 0:
        return last
    x0, y0 = cells[:, 0].min(), cells[:, 1].min()
    nx = int((cells[:, 0].max() - x0) / h) + 1
    ny = int((cells[:, 1].max() - y0) / h) + 1
    bins = np.empty(C, np.int64)
    for c in range(C):
        bins[c] = int((cells[c, 0] - x0) / h) * ny + int((cells[c, 1] - y0) / h)
    order = np.argsort(bins, kind="mergesort")
    start = np.zeros(nx * ny + 1, np.int64)
    for c in range(C):
        start[bins[c] + 1] += 1
    for b in range(nx * ny):
        start[b + 1] += start[b]
    rmax = radius.max()
    left = C
    for n in range(N - 1, -1, -1):
        for k in range(K):
            px, py = points[k, n, 0], points[k, n, 1]
            a0 = max(int(math.floor((px - rmax - x0) / h)), 0)
            a1 = min(int(math.floor((px + rmax - x0) / h)), nx - 1)
            b0 = max(int(math.floor((py - rmax - y0) / h)), 0)
            b1 = min(int(math.floor((py + rmax - y0) / h)), ny - 1)
            for a in range(a0, a1 + 1):
                for b in range(b0, b1 + 1):
                    q = a * ny + b
                    for s in range(start[q], start[q + 1]):
                        c = order[s]
                        if last[c] >= 0:
                            continue
                        dx, dy = px - cells[c, 0], py - cells[c, 1]
                        if math.sqrt(dx * dx + dy * dy) <= radius[c]:
                            last[c] = n
                            left -= 1
        if left == 0:
            break
    return last


@njit(cache=True, nogil=True)
def nearest_between(cells, xy, lo, hi):
    """(C,) int64: for each of (C, 2) cells the index k in [lo[c], hi[c]] of the (N, 2) point
    xy[k] nearest it (squared distance dx^2 + dy^2; the first of equal ones)."""
    out = np.empty(cells.shape[0], np.int64)
    for c in range(cells.shape[0]):
        best, arg = np.inf, lo[c]
        for k in range(lo[c], hi[c] + 1):
            dx, dy = xy[k, 0] - cells[c, 0], xy[k, 1] - cells[c, 1]
            d = dx * dx + dy * dy
            if d < best:
                best, arg = d, k
        out[c] = arg
    return out
