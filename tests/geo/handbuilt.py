"""A run folder built by hand for the export tests: a straight 4 m drive along map x at 1 m/s,
two tracks 0.5 m apart with 3 cm ruts, and params.csv rows whose values say which window
they belong to."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np

from torchsoil.io.terrain_pair import TerrainPair

DX = 0.02
T0 = 1.75e9
RUT = 0.03
WHEEL_WIDTH = 0.11                             # no cell centre lies exactly a wheel width from a wheel path
WHEELS = np.array([[0.3, 0.25, 0], [0.3, -0.25, 1], [-0.3, 0.25, 0], [-0.3, -0.25, 1]], dtype=np.float64)
CENTRES = [0.4 * k for k in range(1, 9)]      # window centres s, m (the last at 3.2)
FLAGGED = 1.2                                  # the window whose row carries a flag
CORRIDOR = 2.0


def pair() -> TerrainPair:
    t = np.linspace(0.0, 4.0, 81)
    poses = np.column_stack([T0 + t, t, np.zeros_like(t), np.zeros((len(t), 4))])
    X, Y = 300, 150                            # x from -1 to 5 m, y from -1.5 to 1.5 m
    origin = np.array([-1.0, -1.49])
    x = origin[0] + DX * np.arange(X)
    y = origin[1] + DX * np.arange(Y)
    h_front = np.zeros((X, Y), np.float32) + 0.001 * y[None, :].astype(np.float32)
    rut = (np.abs(np.abs(y)[None, :] - 0.25) <= 0.04) & (x[:, None] >= -0.3) & (x[:, None] <= 4.3)
    h_back = (h_front - RUT * rut).astype(np.float32)
    h_front[0, 0] = np.nan                     # one cell never seen
    return TerrainPair(DX, origin, h_front, h_back, poses, WHEELS, WHEEL_WIDTH)


def row(s: float) -> dict:
    return {"s": s, "visit": 0, "passes_before": 0, "t": T0 + s, "x": s, "y": 0.0, "d1": s / 100, "d2": s / 50,
            "chi": 0.1 * s, "beta": 20.0 + s, "map_offset": 0.0, "rut_depth": RUT, "residual": s / 1000,
            "prediction": s / 900, "iterations": 10, "seconds": 0.01, "latency": "nan",
            "flags": "few_valid" if abs(s - FLAGGED) < 1e-9 else ""}


def write_run(folder: Path) -> Path:
    """The run folder as `estimate` writes it: simulated.npz (the pair and h_sim), params.csv,
    run.json (window 0.8 m, corridor CORRIDOR m)."""
    folder.mkdir(parents=True, exist_ok=True)
    p = pair()
    sim = TerrainPair(p.dx, p.origin, p.h_front, p.h_back, p.poses, p.wheels, p.wheel_width,
                      extras={"h_sim": (p.h_back - 0.002).astype(np.float32)})
    sim.save(folder / "simulated.npz")
    rows = [row(s) for s in CENTRES]
    with open(folder / "params.csv", "w", newline="") as f:
        w = csv.DictWriter(f, list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    (folder / "run.json").write_text(json.dumps({"job": "estimate", "input": {"path": "pair.npz"},
                                                 "settings": {"estimator": {"window": 0.8, "corridor": CORRIDOR}}}))
    return folder
