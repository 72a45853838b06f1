"""ROI extraction and rasterization: world points -> heightmap on a shared grid (paper
section III).

The region of interest is a corridor of width d_w around the trajectory. Points are summed
into tiles of a fixed lattice as they come (`Tiles`, which can spill far tiles to disk); every
cell holds the mean z of its points; empty cells with measured neighbours within
`fill_radius` cells are filled by their (count-weighted) local mean, cells without stay
NaN and invalid. Per-cell point count and variance are kept.
"""

from __future__ import annotations

import os
from typing import NamedTuple

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from torchsoil.grid import Grid
from torchsoil.pipeline import _kernels as _k


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


def spill_far(store, xy: np.ndarray, radius: float) -> int:
    """Move to disk the tiles of `store` (its `tiles` {(A, B): array}, `spilled` set, `size`
    cells, `dx` m, `spill_dir`, `_path(key)`) with no cell within `radius` m of any of the (K, 2)
    positions xy (radius -inf: all); returns how many (none without a spill directory)."""
    if store.spill_dir is None or not store.tiles:
        return 0
    side = store.size * store.dx
    keys = list(store.tiles)
    centres = (np.array(keys, dtype=np.float64) + 0.5) * side - store.dx / 2
    d, _ = cKDTree(np.asarray(xy, np.float64)).query(centres)
    far = d > radius + side / np.sqrt(2) if np.isfinite(radius) else np.full(len(keys), radius < 0)
    for k, f in zip(keys, far, strict=True):
        if f:   # replaced whole, never written in place (a pipeline checkpoint links the old file)
            path = store._path(k)
            with open(f"{path}.tmp", "wb") as fh:
                np.save(fh, store.tiles.pop(k))
            os.replace(f"{path}.tmp", path)
            store.spilled.add(k)
    return int(far.sum())


class Tiles:
    """Per-cell count, sum and sum of squares of z over an unbounded lattice of `dx` cells (cell
    (I, J) centred at (I dx, J dx), as every corridor grid), in square tiles of `size` cells
    made as points arrive. Tiles can be spilled to `spill_dir` (`spill`) and are read back
    when points fall in them again or a region is asked for: sums add up, so a spilled and
    reloaded tile is exact. Memory is then set by the tiles near the robot."""

    def __init__(self, dx: float, size: int = 128, spill_dir: str | None = None):
        self.dx, self.size, self.spill_dir = dx, size, spill_dir
        self.tiles: dict[tuple[int, int], np.ndarray] = {}   # (3, size, size): count, sum, sumsq
        self.spilled: set[tuple[int, int]] = set()
        if spill_dir is not None:
            os.makedirs(spill_dir, exist_ok=True)

    def add(self, points: np.ndarray) -> None:
        """Add (N, 3) world points [m]."""
        if len(points) == 0:
            return
        points = np.ascontiguousarray(points, dtype=np.float64)
        keys, order, start, cell = _k.tile_cells(points, float(self.dx), self.size)
        z, scratch = np.ascontiguousarray(points[:, 2]), np.zeros((3, self.size * self.size))
        for u, k in enumerate(map(tuple, keys.tolist())):
            _k.tile_add(self._tile(k, create=True).reshape(3, -1), scratch, z, order, cell, start[u], start[u + 1])

    def _path(self, k: tuple[int, int]) -> str:
        return f"{self.spill_dir}/tile_{k[0]}_{k[1]}.npy"

    def _tile(self, k: tuple[int, int], create: bool = False) -> np.ndarray | None:
        if k in self.tiles:
            return self.tiles[k]
        if k in self.spilled:
            tile = np.load(self._path(k))
            self.spilled.discard(k)
        elif create:
            tile = np.zeros((3, self.size, self.size))
        else:
            return None
        self.tiles[k] = tile
        return tile

    def spill(self, xy: np.ndarray, radius: float) -> int:
        """Write to disk (and drop from memory) the tiles with no cell within `radius` m of any
        of the (K, 2) positions xy (radius -inf: all); returns how many. Without a spill
        directory: none. Each tile is `tile_A_B.npy`, (3, size, size) float64 count, sum and sum
        of squares of z [m] of lattice cells [A size:(A+1) size, B size:(B+1) size]."""
        return spill_far(self, xy, radius)

    def region(self, i0: int, i1: int, j0: int, j1: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """count, sum, sumsq (each (i1 - i0, j1 - j0)) of lattice cells [i0:i1, j0:j1], read from
        memory or disk (spilled tiles read stay on disk)."""
        out = np.zeros((3, i1 - i0, j1 - j0))
        s = self.size
        for a in range(i0 // s, (i1 - 1) // s + 1):
            for b in range(j0 // s, (j1 - 1) // s + 1):
                k = (a, b)
                tile = self.tiles.get(k)
                if tile is None and k in self.spilled:
                    tile = np.load(self._path(k))
                if tile is None:
                    continue
                x0, x1 = max(i0, a * s), min(i1, (a + 1) * s)
                y0, y1 = max(j0, b * s), min(j1, (b + 1) * s)
                out[:, x0 - i0:x1 - i0, y0 - j0:y1 - j0] = tile[:, x0 - a * s:x1 - a * s, y0 - b * s:y1 - b * s]
        return out[0], out[1], out[2]

    def heightmap(self, grid: Grid, mask: np.ndarray, fill_radius: int, rows: int = 256) -> Heightmap:
        """The Heightmap of `grid` (its cell centres on the lattice) within `mask` (X, Y), made
        `rows` grid rows at a time (with `fill_radius` rows either side, all the fill reads), so
        that its float64 sums never span more than a block of a long drive's grid."""
        i0, j0 = (int(round(o / self.dx)) for o in grid.origin)
        X, Y = grid.shape
        out = None
        for a in range(0, X, rows):
            b = min(a + rows, X)
            lo, hi = max(a - fill_radius, 0), min(b + fill_radius, X)
            count, total, sumsq = self.region(i0 + lo, i0 + hi, j0, j0 + Y)
            m = mask[lo:hi]
            part = finish(np.where(m, count, 0).astype(np.int64), np.where(m, total, 0.0), np.where(m, sumsq, 0.0),
                          m, fill_radius)
            if out is None:
                out = Heightmap(*(np.empty((X, Y), f.dtype) for f in part))
            for whole, f in zip(out, part, strict=True):
                whole[a:b] = f[a - lo:b - lo]
        return out

    def memory(self) -> int:
        """Bytes held in memory."""
        return sum(t.nbytes for t in self.tiles.values())
