"""The simulated height change stitched over windows as they come, in tiles spilled to disk."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from torchsoil.io.terrain_pair import TerrainPair


def sim_piece(w) -> tuple:
    """A LiveWindow's simulated height change on its ground: lattice indices (i0, j0) of its
    crop, h_sim minus the surface its simulation started from (X, Y) [m], and each cell's
    distance to the window centre along the drive (inf off its ground). The change, not h_sim:
    a window fitted before the world frame's levelling was corrected (an IMU bias told at the
    end) or on a stretch with its own map offset lies in another frame than the final maps
    (on the demo drive a ramp of 0.5 mm per metre in the stitched H_b)."""
    o, pair = w.output, w.pair
    i0, _, j0, _ = o.data.crop
    gi, gj = (int(round(v / pair.dx)) for v in pair.origin)
    dist = np.where(o.data.ground.cpu().numpy(), w.dist, np.inf).astype(np.float32)
    change = (o.h_sim - o.data.h_front[0]).detach().cpu().numpy().astype(np.float32)
    return gi + i0, gj + j0, change, dist


class SimTiles:
    """The simulated height change stitched over windows as they come, in square tiles of `size`
    lattice cells (cell (I, J) at (I dx, J dx), as the corridor grids): per cell the change [m]
    (NaN where no window simulated) of the window whose centre is nearest along the drive, and
    that distance [m] (inf: none), as `estimator.Stitcher`. Tiles no window touched in the last
    `keep` windows go to `spill_dir` (None: all kept in memory), so memory is set by the ground
    near the robot, not by the drive's length (a tile of 128 x 128 cells: 128 kB)."""

    def __init__(self, spill_dir: str | Path | None = None, size: int = 128, keep: int = 20):
        self.size, self.keep, self.spill_dir = size, keep, spill_dir
        self.tiles: dict[tuple[int, int], np.ndarray] = {}   # (2, size, size) float32: change, distance
        self.used: dict[tuple[int, int], int] = {}          # the window that last touched each tile
        self.spilled: set[tuple[int, int]] = set()
        self.n = 0
        if spill_dir is not None:
            Path(spill_dir).mkdir(parents=True, exist_ok=True)

    def _path(self, k: tuple[int, int]) -> Path:
        return Path(self.spill_dir) / f"sim_{k[0]}_{k[1]}.npy"

    def _tile(self, k: tuple[int, int], create: bool) -> np.ndarray | None:
        if k in self.tiles:
            return self.tiles[k]
        if k in self.spilled:
            return np.load(self._path(k))
        if not create:
            return None
        tile = np.empty((2, self.size, self.size), np.float32)
        tile[0], tile[1] = np.nan, np.inf
        return tile

    def add(self, i0: int, j0: int, change: np.ndarray, dist: np.ndarray) -> None:
        """A window's piece (`sim_piece`): its change (X, Y) [m] and each cell's distance to its
        centre [m] (inf off its ground) at lattice cells [i0:i0+X, j0:j0+Y]."""
        s, (ni, nj) = self.size, change.shape
        for a in range(i0 // s, (i0 + ni - 1) // s + 1):
            for b in range(j0 // s, (j0 + nj - 1) // s + 1):
                k = (a, b)
                tile = self._tile(k, create=True)
                self.tiles[k], self.used[k] = tile, self.n
                self.spilled.discard(k)
                x0, x1, y0, y1 = max(i0, a * s), min(i0 + ni, (a + 1) * s), max(j0, b * s), min(j0 + nj, (b + 1) * s)
                d = dist[x0 - i0:x1 - i0, y0 - j0:y1 - j0]
                t = tile[:, x0 - a * s:x1 - a * s, y0 - b * s:y1 - b * s]
                take = d < t[1]
                t[1][take] = d[take]
                t[0][take] = change[x0 - i0:x1 - i0, y0 - j0:y1 - j0][take]
        self.n += 1
        self.flush(self.n - self.keep)

    def flush(self, before: float = np.inf) -> None:
        """The tiles no window touched since window `before` (default: all) to spill_dir (when there
        is one): `sim_A_B.npy`, (2, size, size) float32 change [m] and distance [m] of lattice cells
        [A size:(A+1) size, B size:(B+1) size]."""
        if self.spill_dir is None:
            return
        for k in [k for k, n in self.used.items() if n < before]:
            np.save(self._path(k), self.tiles.pop(k))
            self.spilled.add(k)
            del self.used[k]

    def region(self, i0: int, i1: int, j0: int, j1: int) -> np.ndarray:
        """The stitched change (i1 - i0, j1 - j0) [m] of lattice cells [i0:i1, j0:j1] (NaN where
        no window simulated), read from memory or disk."""
        out = np.full((i1 - i0, j1 - j0), np.nan, np.float32)
        s = self.size
        for a in range(i0 // s, (i1 - 1) // s + 1):
            for b in range(j0 // s, (j1 - 1) // s + 1):
                tile = self._tile((a, b), create=False)
                if tile is None:
                    continue
                x0, x1, y0, y1 = max(i0, a * s), min(i1, (a + 1) * s), max(j0, b * s), min(j1, (b + 1) * s)
                out[x0 - i0:x1 - i0, y0 - j0:y1 - j0] = tile[0, x0 - a * s:x1 - a * s, y0 - b * s:y1 - b * s]
        return out


def stitch_tiles(pair: TerrainPair, sims: SimTiles) -> np.ndarray:
    """Simulated height change over the whole pair's grid (NaN where no window simulated)."""
    gi, gj = (int(round(v / pair.dx)) for v in pair.origin)
    return sims.region(gi, gi + pair.h_front.shape[0], gj, gj + pair.h_front.shape[1])
