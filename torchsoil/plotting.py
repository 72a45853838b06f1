"""Plotting helpers every room's figures share: heightmaps coarsened for a figure, and their extent.

Figures are drawn on `matplotlib.figure.Figure` objects (no pyplot, no backend chosen), so the
library never changes matplotlib's process-wide state."""

from __future__ import annotations

import math

import numpy as np


def coarse(img: np.ndarray, max_cells: int = 2000) -> tuple[np.ndarray, int]:
    """An (X, Y) map averaged over blocks of f x f cells (NaN cells left out; NaN where a block
    has none), f the least factor that leaves at most `max_cells` along each side; returns
    (the coarse map, f). A figure cannot show more cells than its pixels, and drawing every
    cell of a long drive's map takes memory in proportion to the drive (a 2000-pixel-wide
    figure of a 10-minute drive: 30,000 cells along)."""
    f = max(1, math.ceil(max(img.shape) / max_cells))
    if f == 1:
        return img, 1
    X, Y = img.shape
    pad = np.full((-(-X // f) * f, -(-Y // f) * f), np.nan, np.float32)
    pad[:X, :Y] = img
    blocks = pad.reshape(pad.shape[0] // f, f, pad.shape[1] // f, f)
    ok = np.isfinite(blocks)
    n = ok.sum(axis=(1, 3))
    blocks[~ok] = 0.0                                    # in place: the padded copy is ours
    total = blocks.sum(axis=(1, 3), dtype=np.float64)
    return np.where(n > 0, total / np.maximum(n, 1), np.nan).astype(np.float32), f


def coarse_extent(origin, dx: float, shape: tuple[int, int], f: int) -> tuple[float, float, float, float]:
    """imshow extent (x0, x1, y0, y1) [m] of a map of `shape` cells averaged over f x f blocks
    (`coarse`), its first cell's centre at `origin` [m] on the fine grid of cell edge dx [m]."""
    x0, y0 = origin
    X, Y = (-(-n // f) for n in shape)
    return (x0 - dx / 2, x0 - dx / 2 + X * f * dx, y0 - dx / 2, y0 - dx / 2 + Y * f * dx)
