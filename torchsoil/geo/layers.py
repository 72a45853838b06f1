"""What an export shows, read from a run folder: the raster layers on the run's grid and the
vector features (windows, rut centrelines, the path), all in the run's map frame (metres).

A run folder is what `torchsoil estimate` writes (simulated.npz holds the terrain pair and
the simulated H_b, params.csv the windows, passes.npz the wheel passes of ground driven more
than once) or what `torchsoil process-bag` writes (terrain.npz); a terrain pair .npz alone
gives its heightmaps. Layers are (X, Y) float32 arrays on the pair's grid (docs/formats.md
section 3), NaN where they say nothing.
"""

from __future__ import annotations

import csv
import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from torchsoil.grid import Grid
from torchsoil.io.terrain_pair import TerrainPair

# name -> (unit, what it is); the GeoTIFF's band order
LAYERS = {
    "h_front": ("m", "surface height before the wheels came (front lidar, first view)"),
    "h_back": ("m", "surface height after the wheels left (back lidar, last view)"),
    "h_delta": ("m", "h_back - h_front"),
    "rut_depth": ("m", "max(h_front - h_back, 0) within a wheel width of a wheel path"),
    "passes": ("1", "wheel passes over the cell"),
    "h_sim": ("m", "simulated h_back of the fitted model"),
    "residual": ("m", "the window's residual cost (weighted mean |h_sim - h_back|)"),
    "validity": ("1", "bit 0: h_front and h_back measured; bit 1: fitted by a window; bit 2: that window flagged"),
}
PARAM_UNITS = {"d": ("m", "sinkage of track {k}"), "chi": ("1", "deposited share of the removed volume"),
               "beta": ("deg", "angle of repose")}


class RunError(ValueError):
    """A folder or file that holds no run torchsoil can export; the message says what is missing."""


@dataclass
class Run:
    """A run's results (module docstring). pair: the terrain pair (grid, poses, wheels), or None
    for a drive written as pieces (`pieces`: each piece's terrain pair file and grid, on the
    same lattice; `track`: the whole drive's poses (N, 7) from trajectory.csv); h_sim: (X, Y)
    simulated H_b or None; passes: (X, Y) wheel passes or None; rows: params.csv rows (dicts of
    floats and the flags string), empty without a fit; names: the fitted parameters (d1, d2,
    chi, beta); window: window length, m; corridor: the ground a window fits, m wide; bag: the
    recording the run came from, when run.json names one that exists; arc0: the path length
    before the pair's first pose (a piece of a longer drive), m."""

    pair: TerrainPair | None
    path: Path
    h_sim: np.ndarray | None = None
    passes: np.ndarray | None = None
    rows: list[dict] = field(default_factory=list)
    names: list[str] = field(default_factory=list)
    window: float = 0.8
    corridor: float = 3.0
    bag: Path | None = None
    arc0: float = 0.0
    pieces: list[tuple[Path, Grid]] = field(default_factory=list)
    track: np.ndarray | None = None
    wheels: np.ndarray | None = None
    wheel_width: float = 0.0

    def __post_init__(self):
        if self.pair is not None:
            self.track, self.wheels, self.wheel_width = self.pair.poses, self.pair.wheels, self.pair.wheel_width

    @property
    def poses(self) -> np.ndarray:
        """(N, 7) base_link poses t, x, y, z, roll, pitch, yaw of the whole drive."""
        return self.track

    @property
    def grid(self) -> Grid:
        """The run's grid: the pair's, or the lattice box covering every piece."""
        if self.pair is not None:
            return self.pair.grid
        lo = np.min([g.origin for _, g in self.pieces], 0)
        hi = np.max([np.asarray(g.origin) + (np.asarray(g.shape) - 1) * g.dx for _, g in self.pieces], 0)
        dx = self.pieces[0][1].dx
        return Grid(dx, tuple(lo), tuple(int(v) for v in np.round((hi - lo) / dx) + 1))

    def final_rows(self) -> list[dict]:
        """Each window's last visit (the row painted on its cells), in order of s."""
        last: dict[float, dict] = {}
        for r in self.rows:
            key = round(r["s"], 6)
            if key not in last or r.get("visit", 0) >= last[key].get("visit", 0):
                last[key] = r
        return [last[k] for k in sorted(last)]

    def piece(self, k: int) -> Run:
        """Piece k as a run of its own (its pair, h_sim and arc0; the run's rows)."""
        pair = TerrainPair.load(self.pieces[k][0])
        return Run(pair, self.pieces[k][0], h_sim=pair.extras.get("h_sim"), rows=self.rows, names=self.names,
                   window=self.window, corridor=self.corridor, arc0=float(pair.extras.get("arc0", 0.0)))


def load_run(path: str | Path) -> Run:
    """The run in folder (or terrain pair file) `path`; RunError when there is none."""
    path = Path(path)
    if not path.exists():
        raise RunError(f"{path}: no such run folder or terrain pair")
    if path.is_file():
        return Run(TerrainPair.load(path), path)
    sim = path / "simulated.npz"
    pairs = [sim, path / "terrain_pair.npz", path / "terrain.npz", path / "pipeline" / "terrain.npz"]
    found = next((p for p in pairs if p.is_file()), None)
    pieces = sorted((path / "pieces").glob("piece_*.npz"))
    if found is None and pieces and (path / "trajectory.csv").is_file():
        run = _pieces_run(path, pieces)
    elif found is None:
        tiles = " (its heightmaps were left as tiles in tiles/ and no pieces/ were written: an estimate of an " \
                "earlier version; estimate it again)" if (path / "tiles").is_dir() else ""
        raise RunError(f"{path}: holds none of simulated.npz, terrain_pair.npz, terrain.npz, pieces/{tiles}")
    else:
        pair = TerrainPair.load(found)
        run = Run(pair, path, h_sim=pair.extras.get("h_sim"))
    if found is not None and found != sim and sim.is_file():
        with np.load(sim) as f:
            run.h_sim = f["h_sim"] if "h_sim" in f.files else None
    if (path / "passes.npz").is_file():
        with np.load(path / "passes.npz") as f:
            run.passes = f["passes"].astype(np.float32)
    if (path / "params.csv").is_file():
        run.rows, run.names = read_params(path / "params.csv")
    meta = path / "run.json"
    if meta.is_file():
        rec = json.loads(meta.read_text())
        est = (rec.get("settings") or {}).get("estimator") or {}
        run.window, run.corridor = float(est.get("window", run.window)), float(est.get("corridor", run.corridor))
        bag = Path((rec.get("input") or {}).get("path", ""))
        run.bag = bag if bag.suffix != ".npz" and bag.exists() and str(bag) not in ("", ".") else None
    return run


def _pieces_run(path: Path, pieces: list[Path]) -> Run:
    """A drive written as pieces (jobs.estimate.write_pieces): each piece's grid from its keys,
    the drive's poses from trajectory.csv, the wheels from the first piece."""
    grids = []
    for p in pieces:
        with np.load(p) as f:
            grids.append(Grid(float(f["dx"]), tuple(f["origin"]), tuple(int(v) for v in f["grid_shape"])))
        if len(grids) == 1:
            with np.load(p) as f:
                wheels, width = f["wheels"], float(f["wheel_width"])
    track = np.loadtxt(path / "trajectory.csv", delimiter=",", skiprows=1, ndmin=2)
    return Run(None, path, pieces=list(zip(pieces, grids, strict=True)), track=track, wheels=wheels,
               wheel_width=width)


def read_params(path: Path) -> tuple[list[dict], list[str]]:
    """params.csv rows (numbers as floats, flags as text) and the parameter names in it."""
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    out = []
    for r in rows:
        out.append({k: (v if k == "flags" else _num(v)) for k, v in r.items()})
    cols = list(rows[0]) if rows else []
    names = [c for c in cols if c == "chi" or c == "beta" or (c.startswith("d") and c[1:].isdigit())]
    return out, names


def _num(v: str) -> float:
    try:
        return float(v)
    except (TypeError, ValueError):
        return math.nan


def layer_units(run: Run) -> dict[str, tuple[str, str]]:
    """The layers this run has, in band order: name -> (unit, description)."""
    out = dict(LAYERS)
    if run.h_sim is None and not run.pieces:
        out.pop("h_sim", None)
    if not run.rows:
        out.pop("residual", None)
    params = {}
    for n in run.names:
        base = "d" if n.startswith("d") else n
        unit, text = PARAM_UNITS[base]
        params[n] = (unit, text.format(k=n[1:]))
    validity = out.pop("validity")
    return {**out, **params, "validity": validity}


def raster_layers(run: Run, i0: int = 0, i1: int | None = None, j0: int = 0, j1: int | None = None
                  ) -> dict[str, np.ndarray]:
    """The layers (layer_units) on cells [i0:i1, j0:j1] of the run's grid, (x, y) float32 each.

    A window's parameters and residual are painted on the cells of its ground (within
    corridor / 2 of the path) whose arc length lies nearer its centre than any other
    window's: the central stride of each window. beta in degrees, as params.csv.
    """
    X, Y = run.grid.shape
    i1, j1 = X if i1 is None else i1, Y if j1 is None else j1
    if run.pieces:
        return _pieces_layers(run, i0, i1, j0, j1)
    return _pair_layers(run, i0, i1, j0, j1)


def _pieces_layers(run: Run, i0: int, i1: int, j0: int, j1: int) -> dict[str, np.ndarray]:
    """raster_layers of a drive in pieces: each piece overlapping the block in time order, a
    later piece's finite values over an earlier's (the last visit's fit), passes added up."""
    grid = run.grid
    names = layer_units(run)
    out = {n: np.full((i1 - i0, j1 - j0), np.nan, np.float32) for n in names}
    out["passes"][:] = 0.0
    out["validity"][:] = 0.0
    fitted = {*run.names, "residual"}
    for k, (_, g) in enumerate(run.pieces):
        oi, oj = (int(round((g.origin[d] - grid.origin[d]) / grid.dx)) for d in (0, 1))
        a0, a1 = max(i0, oi), min(i1, oi + g.shape[0])
        b0, b1 = max(j0, oj), min(j1, oj + g.shape[1])
        if a0 >= a1 or b0 >= b1:
            continue
        part = _pair_layers(run.piece(k), a0 - oi, a1 - oi, b0 - oj, b1 - oj, joined=k > 0)
        own = part.pop("_own")   # cells behind a piece's first pose are the piece before's (its fill differs)
        painted = part.pop("_painted")
        here = (slice(a0 - i0, a1 - i0), slice(b0 - j0, b1 - j0))
        for n in names:
            was = out[n][here]
            if n in fitted:       # a window's values, NaN ones too, over an earlier piece's on its ground
                out[n][here] = np.where(painted, part[n], was)
            elif n == "passes":
                out[n][here] += np.nan_to_num(part[n])
            elif n == "validity":   # a later fit's bits over an earlier's
                out[n][here] = np.where(own & (part[n] > 0), part[n], np.maximum(was, part[n]))
            elif n in part:
                take = np.isfinite(part[n]) & (own | np.isnan(was))
                out[n][here] = np.where(take, part[n], was)
    return out


def _pair_layers(run: Run, i0: int, i1: int, j0: int, j1: int, joined: bool | None = None
                 ) -> dict[str, np.ndarray]:
    """raster_layers on a pair. joined (a piece of a longer drive; None: not a piece): whether
    it continues a piece before it, whose cells (nearest the first pose) it leaves unpainted;
    a piece's layers then come with `_own`, the cells it speaks for over earlier pieces."""
    from torchsoil.estimate.windows import path_index

    p = run.pair
    sub = p.grid.crop(i0, i1, j0, j1)
    hf, hb = p.h_front[i0:i1, j0:j1].astype(np.float32), p.h_back[i0:i1, j0:j1].astype(np.float32)
    robot = p.robot
    index = path_index(sub, p.poses, robot, run.corridor / 2)
    near = index.wheel_dist <= robot.wheel_width
    out = {"h_front": hf, "h_back": hb, "h_delta": hb - hf,
           "rut_depth": np.where(near, np.maximum(hf - hb, 0.0), np.nan).astype(np.float32)}
    if run.passes is not None:
        out["passes"] = run.passes[i0:i1, j0:j1].astype(np.float32)
    else:
        out["passes"] = _wheel_passes(p, sub)
    if run.h_sim is not None:
        out["h_sim"] = run.h_sim[i0:i1, j0:j1].astype(np.float32)
    measured = np.isfinite(hf) & np.isfinite(hb)
    validity = measured.astype(np.float32)
    interior = ~(index.s <= 0.0) if joined else np.ones(index.s.shape, dtype=bool)
    rows = run.final_rows()
    if rows:
        centres = np.array([r["s"] for r in rows])
        s = index.s + run.arc0
        ok = np.isfinite(s) & (index.offset <= run.corridor / 2) & interior
        k = np.clip(np.searchsorted(centres, np.where(ok, s, 0.0)), 1, len(centres)) if len(centres) > 1 else \
            np.zeros(s.shape, np.int64)
        if len(centres) > 1:
            k = np.where(np.abs(s - centres[k - 1]) <= np.abs(s - centres[np.minimum(k, len(centres) - 1)]),
                         k - 1, np.minimum(k, len(centres) - 1))
        ok &= np.abs(np.where(ok, s, np.inf) - centres[k]) <= run.window / 2
        for name in [*run.names, "residual"]:
            vals = np.array([r.get(name, math.nan) for r in rows], dtype=np.float64)
            out[name] = np.where(ok, vals[k], np.nan).astype(np.float32)
        flagged = np.array([bool(str(r.get("flags", "") or "").strip()) for r in rows])
        validity += 2.0 * ok + 4.0 * (ok & flagged[k])
    out["validity"] = validity.astype(np.float32)
    layers = {name: out[name] for name in layer_units(run)}
    if joined is not None:
        layers["_own"] = interior
        layers["_painted"] = ok if rows else np.zeros(interior.shape, dtype=bool)
    return layers


def rut_depth_at(run: Run, xy: np.ndarray) -> np.ndarray:
    """(M,) max(h_front - h_back, 0) [m] at the cells under the (M, 2) map points (NaN outside
    the measured ground); a drive in pieces is read a piece at a time."""
    out = np.full(len(xy), np.nan)
    for pair in ([run.pair] if run.pair is not None else (run.piece(k).pair for k in range(len(run.pieces)))):
        ij = pair.grid.index(xy)
        X, Y = pair.h_front.shape
        inside = (ij[:, 0] >= 0) & (ij[:, 0] < X) & (ij[:, 1] >= 0) & (ij[:, 1] < Y)
        ii, jj = ij[inside, 0], ij[inside, 1]
        d = np.maximum(pair.h_front[ii, jj] - pair.h_back[ii, jj], 0.0)
        idx = np.flatnonzero(inside)
        fin = np.isfinite(d)
        out[idx[fin]] = d[fin]
    return out


def _wheel_passes(pair: TerrainPair, sub: Grid) -> np.ndarray:
    from torchsoil.estimate.visits import wheel_passes

    visit_time = np.zeros((1, *sub.shape), np.float32)   # one visit per cell
    if pair.visit_time is not None:
        i0 = int(round((sub.origin[0] - pair.origin[0]) / pair.dx))
        j0 = int(round((sub.origin[1] - pair.origin[1]) / pair.dx))
        visit_time = pair.visit_time[:, i0:i0 + sub.shape[0], j0:j0 + sub.shape[1]]
    return wheel_passes(pair.poses, pair.wheels, pair.wheel_width, sub, visit_time).sum(0).astype(np.float32)
