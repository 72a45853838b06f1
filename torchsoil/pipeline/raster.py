"""ROI extraction and rasterization: world points -> heightmap on a shared grid (paper
section III).

The region of interest is a corridor of width d_w around the trajectory. Every cell
holds the mean z of its points; empty cells with measured neighbours within
`fill_radius` cells are filled by their (count-weighted) local mean, cells without stay
NaN and invalid. Per-cell point count and variance are kept.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from torchsoil.grid import Grid


class Heightmap(NamedTuple):
    """h (X, Y) float32 mean height [m], NaN where invalid; valid (X, Y) bool; measured
    (X, Y) bool cells holding points (valid & ~measured: filled by interpolation);
    count (X, Y) int32 points per cell; var (X, Y) float32 height variance [m^2]."""

    h: np.ndarray
    valid: np.ndarray
    measured: np.ndarray
    count: np.ndarray
    var: np.ndarray


def corridor(trajectory_xy: np.ndarray, width: float, dx: float, step: float = 0.05
             ) -> tuple[Grid, np.ndarray]:
    """Grid covering the corridor of `width` m around a (N, 2) path [m], and its (X, Y) mask
    of cells within width / 2 of the path (resampled every `step` m)."""
    xy = np.asarray(trajectory_xy, dtype=np.float64)
    if xy.ndim != 2 or xy.shape[1] != 2 or len(xy) == 0 or not np.all(np.isfinite(xy)):
        raise ValueError(f"trajectory must be (N, 2) finite x, y, got shape {xy.shape}")
    seg = np.linalg.norm(np.diff(xy, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    si = np.arange(0.0, s[-1] + step, step) if s[-1] > 0 else np.zeros(1)
    dense = np.stack([np.interp(si, s, xy[:, 0]), np.interp(si, s, xy[:, 1])], 1)
    half = width / 2
    lo, hi = dense.min(0) - half, dense.max(0) + half
    lo = np.floor(lo / dx) * dx  # cells aligned on multiples of dx
    grid = Grid.covering(lo[0], lo[1], hi[0], hi[1], dx)
    cx, cy = grid.centers()
    X, Y = np.meshgrid(cx, cy, indexing="ij")
    d, _ = cKDTree(dense).query(np.stack([X.ravel(), Y.ravel()], 1), distance_upper_bound=half)
    return grid, np.isfinite(d).reshape(grid.shape)


class Accumulator:
    """Running per-cell count, sum and sum of squares of z over a grid."""

    def __init__(self, grid: Grid, mask: np.ndarray):
        self.grid, self.mask = grid, mask
        n = grid.shape[0] * grid.shape[1]
        self.count = np.zeros(n, dtype=np.int64)
        self.sum = np.zeros(n)
        self.sumsq = np.zeros(n)

    def add(self, points: np.ndarray) -> int:
        """Add (N, 3) world points [m]; returns how many fell in the corridor."""
        ij = self.grid.index(points[:, :2])
        X, Y = self.grid.shape
        inside = (ij[:, 0] >= 0) & (ij[:, 0] < X) & (ij[:, 1] >= 0) & (ij[:, 1] < Y)
        ij, z = ij[inside], points[inside, 2]
        keep = self.mask[ij[:, 0], ij[:, 1]]
        flat = ij[keep, 0] * Y + ij[keep, 1]
        z = z[keep]
        n = len(self.count)
        self.count += np.bincount(flat, minlength=n)
        self.sum += np.bincount(flat, weights=z, minlength=n)
        self.sumsq += np.bincount(flat, weights=z * z, minlength=n)
        return int(keep.sum())

    def heightmap(self, fill_radius: int) -> Heightmap:
        return finish(self.count.reshape(self.grid.shape), self.sum.reshape(self.grid.shape),
                      self.sumsq.reshape(self.grid.shape), self.mask, fill_radius)


def finish(count: np.ndarray, total: np.ndarray, sumsq: np.ndarray, mask: np.ndarray,
           fill_radius: int) -> Heightmap:
    """Per-cell sums (X, Y) -> Heightmap, empty cells filled from neighbours."""
    measured = count > 0
    mean = np.where(measured, total / np.maximum(count, 1), 0.0)
    var = np.where(measured, sumsq / np.maximum(count, 1) - mean**2, np.nan)
    h = np.where(measured, mean, np.nan)
    if fill_radius > 0:
        size = 2 * fill_radius + 1
        w = measured.astype(np.float64)
        num = ndimage.uniform_filter(mean * w, size=size, mode="constant")
        den = ndimage.uniform_filter(w, size=size, mode="constant")
        fill = ~measured & (den > 1e-9) & mask
        h[fill] = num[fill] / den[fill]
    valid = np.isfinite(h) & mask
    h[~valid] = np.nan
    return Heightmap(h.astype(np.float32), valid, measured & mask, count.astype(np.int32),
                     np.maximum(var, 0).astype(np.float32))
