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
    """A run's results (module docstring). pair: the terrain pair (grid, poses, wheels);
    h_sim: (X, Y) simulated H_b or None; passes: (X, Y) wheel passes or None; rows: params.csv
    rows (dicts of floats and the flags string), empty without a fit; names: the fitted
    parameters (d1, d2, chi, beta); window: window length, m; corridor: the ground a window
    fits, m wide; bag: the recording the run came from, when run.json names one that exists."""

    pair: TerrainPair
    path: Path
    h_sim: np.ndarray | None = None
    passes: np.ndarray | None = None
    rows: list[dict] = field(default_factory=list)
    names: list[str] = field(default_factory=list)
    window: float = 0.8
    corridor: float = 3.0
    bag: Path | None = None

    @property
    def grid(self) -> Grid:
        return self.pair.grid

    def final_rows(self) -> list[dict]:
        """Each window's last visit (the row painted on its cells), in order of s."""
        last: dict[float, dict] = {}
        for r in self.rows:
            key = round(r["s"], 6)
            if key not in last or r.get("visit", 0) >= last[key].get("visit", 0):
                last[key] = r
        return [last[k] for k in sorted(last)]


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
    if found is None:
        tiles = " (its heightmaps were left as tiles in tiles/: a drive longer than estimator.online.max_cells, " \
                "which export does not read yet)" if (path / "tiles").is_dir() else ""
        raise RunError(f"{path}: holds none of simulated.npz, terrain_pair.npz, terrain.npz{tiles}")
    pair = TerrainPair.load(found)
    run = Run(pair, path, h_sim=pair.extras.get("h_sim"))
    if found != sim and sim.is_file():
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
    out = {k: v for k, v in LAYERS.items() if k not in ("h_sim", "residual") or run.rows or k == "h_sim"}
    if run.h_sim is None:
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
    from torchsoil.estimate.windows import path_index

    p = run.pair
    X, Y = p.h_front.shape
    i1, j1 = X if i1 is None else i1, Y if j1 is None else j1
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
    rows = run.final_rows()
    if rows:
        centres = np.array([r["s"] for r in rows])
        s = index.s
        ok = np.isfinite(s) & (index.offset <= run.corridor / 2)
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
    return {name: out[name] for name in layer_units(run)}


def _wheel_passes(pair: TerrainPair, sub: Grid) -> np.ndarray:
    from torchsoil.estimate.visits import wheel_passes

    visit_time = np.zeros((1, *sub.shape), np.float32)   # one visit per cell
    if pair.visit_time is not None:
        i0 = int(round((sub.origin[0] - pair.origin[0]) / pair.dx))
        j0 = int(round((sub.origin[1] - pair.origin[1]) / pair.dx))
        visit_time = pair.visit_time[:, i0:i0 + sub.shape[0], j0:j0 + sub.shape[1]]
    return wheel_passes(pair.poses, pair.wheels, pair.wheel_width, sub, visit_time).sum(0).astype(np.float32)
