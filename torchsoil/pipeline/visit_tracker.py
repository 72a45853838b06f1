"""Visits per cell: when base_link's path came over each cell of the lattice, visit by visit
(docs/formats.md section 3, visits v1.1).

A *visit* of a cell is one stretch of the drive during which the cell lies within `reach` [m]
of base_link. A new visit starts when the cell comes within reach after base_link travelled
more than `gap` [m] of path (arc length) since the cell was last within reach: a tight turn
that keeps a cell near stays one visit, and standing still adds none. `VisitTracker` is fed
base_link's path in time order and keeps, per cell and visit, the time the visit started
and the time base_link passed closest (the terrain pair's `visit_time`). The path is taken
as straight between the given positions, so both times are exact for that polyline.

Cells lie on the lattice of `raster.Tiles` (cell (I, J) centred at (I dx, J dx)), held in
square tiles of `size` cells made as the path reaches them; tiles can be spilled to disk
and are read back when the path or a query comes near them again.
"""

from __future__ import annotations

import os

import numpy as np

from torchsoil.pipeline import _kernels as _k
from torchsoil.robot import Robot

PIECE = 1.0    # m: longer segments of the path are cut into pieces (bounded work areas)
BATCH = 4.0    # m of path updated on one block of cells


def visit_reach(robot: Robot, margin: float) -> float:
    """How far from base_link [m] a cell counts as visited: the larger of (a) the outermost
    wheel's |y| plus half a wheel width plus `margin` wheel widths of relaxation (the
    simulator's reach, windows.sim_reach, with sim.relax_margin = margin: the ground a pass
    changes beside a straight drive) and (b) the farthest wheel centre's distance from
    base_link plus half a wheel width (the ground under a corner wheel's footprint: in a
    pivot or a tight turn base_link need never come nearer to it than that)."""
    wheels, w = robot.wheels[:, :2], robot.wheel_width
    return float(max(np.abs(wheels[:, 1]).max() + w * (0.5 + margin), np.hypot(*wheels.T).max() + 0.5 * w))


def visit_gap(robot: Robot) -> float:
    """base_link travel [m] after which the wheels coming back over some ground make a new
    visit: twice the wheelbase plus a wheel width (as the recorder's world counts them)."""
    return 2.0 * float(np.ptp(robot.wheels[:, 0]) + robot.wheel_width)


class VisitTracker:
    """Per-cell visits of a path, fed incrementally.

    Args:
        dx: cell edge, m.
        reach: a cell is within reach while base_link is at most this far from it, m (> 0).
        gap: base_link travel after which coming within reach again starts a new visit, m (> 0).
        size: tile edge, cells.
        spill_dir: directory for spilled tiles (None: all kept in memory).

    Each tile is a (2 + 2 V, size, size) float64 stack: the arc length [m] at which base_link
    last had the cell within reach (-inf: never), the closest distance of the visit under way
    [m] (inf: none), then per visit v its start time and closest-pass time [s] (NaN: no such
    visit). Times are those the path is fed with.
    """

    def __init__(self, dx: float, reach: float, gap: float, size: int = 128, spill_dir: str | None = None):
        for name, value in (("dx", dx), ("reach", reach), ("gap", gap)):
            if not (np.isfinite(value) and value > 0):
                raise ValueError(f"VisitTracker: {name} must be a positive length in metres, got {value!r}")
        self.dx, self.reach, self.gap, self.size = float(dx), float(reach), float(gap), int(size)
        self.spill_dir = spill_dir
        self.tiles: dict[tuple[int, int], np.ndarray] = {}
        self.spilled: set[tuple[int, int]] = set()
        self.last: tuple[float, np.ndarray, float] | None = None    # (t, xy, arc) of the last position fed
        if spill_dir is not None:
            os.makedirs(spill_dir, exist_ok=True)

    # ------------------------------------------------------------------ input
    def add(self, t: np.ndarray, xy: np.ndarray) -> None:
        """Feed base_link's positions xy (N, 2) [m] at times t (N,) [s], in time order and
        after those fed before."""
        t = np.asarray(t, np.float64).reshape(-1)
        xy = np.asarray(xy, np.float64)
        if xy.ndim != 2 or xy.shape != (len(t), 2):
            raise ValueError(f"VisitTracker.add: xy must be (N, 2) for N = {len(t)} times, got shape {xy.shape}")
        if not (np.all(np.isfinite(t)) and np.all(np.isfinite(xy))):
            raise ValueError("VisitTracker.add: times and positions must be finite")
        if len(t) == 0:
            return
        prev = self.last
        if (prev is not None and t[0] < prev[0]) or np.any(np.diff(t) < 0):
            raise ValueError("VisitTracker.add: times must not go backwards (the path is fed in time order)")
        if prev is None:                      # the first position: a segment of no length
            prev = (float(t[0]), xy[0], 0.0)
            t, xy = np.r_[t[0], t], np.vstack([xy[:1], xy])
        else:
            t, xy = np.r_[prev[0], t], np.vstack([prev[1][None], xy])
        t, xy = _pieces(t, xy, PIECE)
        arc = prev[2] + np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(xy, axis=0), axis=1))]
        start = 0
        while start < len(t) - 1:
            stop = max(int(np.searchsorted(arc, arc[start] + BATCH, side="right")), start + 2)
            stop = min(stop, len(t))
            self._update(t[start:stop], xy[start:stop], arc[start:stop])
            start = stop - 1
        self.last = (float(t[-1]), xy[-1].copy(), float(arc[-1]))

    def _update(self, t: np.ndarray, xy: np.ndarray, arc: np.ndarray) -> None:
        """The segments between consecutive positions (n,) t, (n, 2) xy, (n,) arc on one block."""
        r, dx = self.reach, self.dx
        i0, j0 = np.floor((xy.min(0) - r) / dx).astype(int)
        i1, j1 = np.ceil((xy.max(0) + r) / dx).astype(int) + 1
        block = self._read(i0, i1, j0, j1, create=True)
        n = np.isfinite(block[2::2]).sum(0)
        for k in range(len(t) - 1):
            p0, p1 = xy[k], xy[k + 1]
            x0, y0 = np.floor((np.minimum(p0, p1) - r) / dx).astype(int) - (i0, j0)
            x1, y1 = np.ceil((np.maximum(p0, p1) + r) / dx).astype(int) + 1 - (i0, j0)
            sub = (slice(x0, x1), slice(y0, y1))
            ax = p0[0] - (np.arange(x0, x1) + i0)[:, None] * dx     # (X, Y) from each cell to p0
            ay = p0[1] - (np.arange(y0, y1) + j0)[None, :] * dx
            d = p1 - p0
            L2 = float(d @ d)
            ad, aa = ax * d[0] + ay * d[1], ax * ax + ay * ay
            u = np.clip(-ad / L2, 0.0, 1.0) if L2 > 0 else np.zeros_like(aa)   # closest point p0 + u d
            dist = np.sqrt(np.maximum(aa + 2 * u * ad + u * u * L2, 0.0))
            hit = dist <= r
            if not hit.any():
                continue
            if L2 > 0:                                                # within reach for u in [enter, leave]
                root = np.sqrt(np.maximum(ad * ad - L2 * (aa - r * r), 0.0))
                enter, leave = np.clip((-ad - root) / L2, 0.0, 1.0), np.clip((-ad + root) / L2, 0.0, 1.0)
            else:
                enter, leave = np.zeros_like(aa), np.ones_like(aa)
            ds, dt = arc[k + 1] - arc[k], t[k + 1] - t[k]
            new = hit & (arc[k] + enter * ds - block[0][sub] > self.gap)
            nn = n[sub]
            if new.any() and 2 + 2 * int(nn[new].max()) >= len(block):
                block = np.concatenate([block, np.full((2, *block.shape[1:]), np.nan)])
            last, close = block[0][sub], block[1][sub]
            ii, jj = np.nonzero(new)
            v = nn[ii, jj]
            block[2 + 2 * v, ii + x0, jj + y0] = t[k] + enter[ii, jj] * dt   # a visit starts
            block[3 + 2 * v, ii + x0, jj + y0] = t[k] + u[ii, jj] * dt
            close[new] = dist[new]
            nn[new] += 1
            ii, jj = np.nonzero(hit & ~new & (dist < close))                # the visit under way comes nearer
            block[1 + 2 * nn[ii, jj], ii + x0, jj + y0] = t[k] + u[ii, jj] * dt
            close[ii, jj] = dist[ii, jj]
            last[hit] = arc[k] + leave[hit] * ds
        self._write(i0, j0, block)

    # ------------------------------------------------------------------ tiles
    def _path(self, k: tuple[int, int]) -> str:
        return f"{self.spill_dir}/visits_{k[0]}_{k[1]}.npy"

    def _empty(self, v: int = 1, shape: tuple[int, int] | None = None) -> np.ndarray:
        """A stack of `v` visits over `shape` cells (default a tile) with no visit yet."""
        tile = np.full((2 + 2 * v, *(shape or (self.size, self.size))), np.nan)
        tile[0], tile[1] = -np.inf, np.inf
        return tile

    def _tile(self, k: tuple[int, int], keep: bool) -> np.ndarray | None:
        """Tile k from memory or disk (kept in memory when `keep`), None where there is none."""
        if k in self.tiles:
            return self.tiles[k]
        if k not in self.spilled:
            return None
        tile = np.load(self._path(k))
        if keep:
            self.spilled.discard(k)
            self.tiles[k] = tile
        return tile

    def _read(self, i0: int, i1: int, j0: int, j1: int, create: bool = False) -> np.ndarray:
        """The (2 + 2 V, i1 - i0, j1 - j0) stack of lattice cells [i0:i1, j0:j1] (V: the most
        visits of the tiles it covers), tiles made where missing when `create`."""
        s = self.size
        parts = []
        for a in range(i0 // s, (i1 - 1) // s + 1):
            for b in range(j0 // s, (j1 - 1) // s + 1):
                tile = self._tile((a, b), keep=create)
                if tile is None and create:
                    tile = self.tiles[(a, b)] = self._empty()
                if tile is not None:
                    parts.append(((a, b), tile))
        v = max([(len(p) - 2) // 2 for _, p in parts], default=1)
        out = self._empty(v, (i1 - i0, j1 - j0))
        for (a, b), tile in parts:
            x0, x1 = max(i0, a * s), min(i1, (a + 1) * s)
            y0, y1 = max(j0, b * s), min(j1, (b + 1) * s)
            out[:len(tile), x0 - i0:x1 - i0, y0 - j0:y1 - j0] = tile[:, x0 - a * s:x1 - a * s, y0 - b * s:y1 - b * s]
        return out

    def _write(self, i0: int, j0: int, block: np.ndarray) -> None:
        """Store a stack read by `_read` (tiles in memory, grown to its visits where fewer)."""
        s = self.size
        i1, j1 = i0 + block.shape[1], j0 + block.shape[2]
        for a in range(i0 // s, (i1 - 1) // s + 1):
            for b in range(j0 // s, (j1 - 1) // s + 1):
                tile = self.tiles[(a, b)]
                if len(tile) < len(block):
                    tile = self.tiles[(a, b)] = np.concatenate(
                        [tile, np.full((len(block) - len(tile), s, s), np.nan)])
                x0, x1 = max(i0, a * s), min(i1, (a + 1) * s)
                y0, y1 = max(j0, b * s), min(j1, (b + 1) * s)
                tile[:len(block), x0 - a * s:x1 - a * s, y0 - b * s:y1 - b * s] = \
                    block[:, x0 - i0:x1 - i0, y0 - j0:y1 - j0]

    def spill(self, xy: np.ndarray, radius: float) -> int:
        """Write to disk (and drop from memory) the tiles with no cell within `radius` m of any
        of the (K, 2) positions xy (radius -inf: all); returns how many (none without a spill
        directory). Each tile is `visits_A_B.npy`, the (2 + 2 V, size, size) stack of the class
        docstring of lattice cells [A size:(A+1) size, B size:(B+1) size]."""
        from torchsoil.pipeline.raster import spill_far

        return spill_far(self, xy, radius)

    def memory(self) -> int:
        """Bytes held in memory."""
        return sum(t.nbytes for t in self.tiles.values())

    # ---------------------------------------------------------------- queries
    def region(self, i0: int, i1: int, j0: int, j1: int) -> tuple[np.ndarray, np.ndarray]:
        """Start times and closest-pass times [s] (each (V, i1 - i0, j1 - j0), NaN where the cell
        has fewer than v + 1 visits) of lattice cells [i0:i1, j0:j1]; V >= 1."""
        block = self._read(i0, i1, j0, j1)
        return block[2::2], block[3::2]

    def started(self, xy: np.ndarray, t) -> np.ndarray:
        """(N,) int: visits of the cells of points xy (N, 2) [m] that started at or before t
        (scalar or (N,) s)."""
        return self._count(xy, t, 2)

    def passed(self, xy: np.ndarray, t) -> np.ndarray:
        """(N,) int: visits of the cells of points xy (N, 2) [m] in which base_link passed its
        closest at or before t (scalar or (N,) s): those started by t, less the one under way
        while base_link is still coming nearer (the path must be fed beyond t)."""
        return self._count(xy, t, 3)

    def _count(self, xy: np.ndarray, t, row: int) -> np.ndarray:
        """(N,) visits whose time in rows row, row + 2, ... of the stack is at most t."""
        xy = np.asarray(xy, np.float64).reshape(-1, 2)
        t = np.broadcast_to(np.asarray(t, np.float64), (len(xy),))
        out = np.zeros(len(xy), np.int64)
        if len(xy) == 0:
            return out
        t = np.ascontiguousarray(t)
        keys, order, start, cell = _k.tile_cells(np.ascontiguousarray(xy), self.dx, self.size)
        for u, k in enumerate(map(tuple, keys.tolist())):
            tile = self._tile(k, keep=False)
            if tile is not None:
                _k.tile_count_le(tile.reshape(len(tile), -1), row, t, order, cell, start[u], start[u + 1], out)
        return out


def _pieces(t: np.ndarray, xy: np.ndarray, piece: float) -> tuple[np.ndarray, np.ndarray]:
    """The polyline (n,) t, (n, 2) xy with segments longer than `piece` m cut into equal
    pieces (times linear along each segment)."""
    seg = np.linalg.norm(np.diff(xy, axis=0), axis=1)
    m = np.maximum(1, np.ceil(seg / piece).astype(np.int64))
    if np.all(m == 1):
        return t, xy
    k = np.repeat(np.arange(len(seg)), m)
    f = np.concatenate([np.arange(c) / c for c in m])[:, None]
    xy2 = np.vstack([xy[k] + f * (xy[k + 1] - xy[k]), xy[-1:]])
    t2 = np.r_[t[k] + f[:, 0] * (t[k + 1] - t[k]), t[-1]]
    return t2, xy2
