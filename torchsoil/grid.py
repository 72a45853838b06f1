"""The regular heightmap grid shared by all stages (docs/formats.md section 3)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Grid:
    """Cell [i, j] is centred at (origin[0] + i*dx, origin[1] + j*dx); i runs along world x.

    Attributes:
        dx: cell edge, m.
        origin: world (x, y) of the centre of cell [0, 0], m.
        shape: (X, Y) number of cells.
    """

    dx: float
    origin: tuple[float, float]
    shape: tuple[int, int]

    def __post_init__(self):
        if not (np.isfinite(self.dx) and self.dx > 0):
            raise ValueError(f"dx must be a positive length in metres, got {self.dx}")
        if len(self.shape) != 2 or min(self.shape) < 1:
            raise ValueError(f"grid shape must be (X, Y) with X, Y >= 1, got {self.shape}")
        object.__setattr__(self, "origin", (float(self.origin[0]), float(self.origin[1])))
        object.__setattr__(self, "shape", (int(self.shape[0]), int(self.shape[1])))

    @classmethod
    def covering(cls, xmin: float, ymin: float, xmax: float, ymax: float, dx: float) -> Grid:
        """Smallest grid of cell edge dx whose cells cover the box [xmin, xmax] x [ymin, ymax]."""
        nx = int(np.floor((xmax - xmin) / dx)) + 1
        ny = int(np.floor((ymax - ymin) / dx)) + 1
        return cls(dx, (xmin, ymin), (nx, ny))

    def centers(self) -> tuple[np.ndarray, np.ndarray]:
        """World x (X,) and y (Y,) of the cell centres, m."""
        x = self.origin[0] + self.dx * np.arange(self.shape[0])
        y = self.origin[1] + self.dx * np.arange(self.shape[1])
        return x, y

    def index(self, xy: np.ndarray) -> np.ndarray:
        """(..., 2) world points -> (..., 2) integer cell indices (may fall outside the grid)."""
        o = np.asarray(self.origin)
        return np.round((np.asarray(xy) - o) / self.dx).astype(np.int64)

    def crop(self, i0: int, i1: int, j0: int, j1: int) -> Grid:
        """Sub-grid of cells [i0:i1, j0:j1]."""
        return Grid(self.dx, (self.origin[0] + i0 * self.dx, self.origin[1] + j0 * self.dx),
                    (i1 - i0, j1 - j0))
