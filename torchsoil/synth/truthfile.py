"""Reading a recording's truth back (PATH.truth.npz + PATH.truth.json beside the bag), for
evaluations and tests; the tools under test never read it.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from torchsoil.grid import Grid


@dataclass
class TruthFile:
    """grid: the truth's corridor grid; arrays: every array of PATH.truth.npz (h_before,
    h_after (X, Y) m, states (V+1, X, Y), visit_time (V, X, Y) s at which each visit ended,
    pass_time (V, X, Y) s at which base_link passed closest in it, n_visits, t_last_wheel,
    poses (N, 7), soil_d / soil_chi / soil_beta / soil_moisture, cylinders, boxes, and where a
    cell was visited twice or more the noise-free visit_front / visit_back (V, X, Y) m, ...);
    meta: PATH.truth.json (scenario, seed, effects, expected, extrinsics, clock)."""

    grid: Grid
    arrays: dict[str, np.ndarray]
    meta: dict

    def __getitem__(self, key: str) -> np.ndarray:
        return self.arrays[key]

    @property
    def t0(self) -> float:
        """Bag time [s] of truth time 0."""
        return self.meta["bag_time_of_t0_ns"] / 1e9

    @property
    def expected(self) -> dict:
        """What a correct diagnosis says of the recording (`effects.expected`: verdict,
        missing_physics, cross_track, covariate, and for a learned law parameter and direction),
        from the JSON's `expected` (older files: worked out from its `effects`)."""
        from torchsoil.synth import effects as fx

        return self.meta.get("expected") or fx.expected(self.meta.get("effects") or {})

    @property
    def scenario(self):
        """The recording's scenario (settings.SynthConfig) from the JSON's `scenario_spec`
        (written with SynthConfig.model_dump(mode="json"); older files wrote `robot: null`
        for the default robot)."""
        from torchsoil.synth.scenario import load_scenario

        spec = {k: v for k, v in self.meta["scenario_spec"].items() if not (k == "robot" and v is None)}
        return load_scenario(spec)

    def on_grid(self, key: str, grid: Grid) -> np.ndarray:
        """A (X, Y) truth layer sampled at the cell centres of another grid (nearest cell;
        NaN outside the truth's corridor)."""
        layer = self.arrays[key]
        if layer.shape != self.grid.shape:
            raise ValueError(f"truth layer {key!r} has shape {layer.shape}, not the grid's {self.grid.shape}")
        xs, ys = grid.centers()
        ij = self.grid.index(np.stack(np.meshgrid(xs, ys, indexing="ij"), -1))
        ok = ((ij[..., 0] >= 0) & (ij[..., 0] < self.grid.shape[0])
              & (ij[..., 1] >= 0) & (ij[..., 1] < self.grid.shape[1]))
        out = np.full(grid.shape, np.nan)
        out[ok] = layer[ij[ok][:, 0], ij[ok][:, 1]]
        return out


def load_truth(bag_path: str | Path) -> TruthFile:
    """The truth written beside the bag directory `bag_path` by `make_recording`."""
    bag_path = Path(bag_path)
    npz = bag_path.with_name(bag_path.name + ".truth.npz")
    js = bag_path.with_name(bag_path.name + ".truth.json")
    for f in (npz, js):
        if not f.is_file():
            raise FileNotFoundError(f"no truth file {f} beside the recording {bag_path}")
    with np.load(npz) as d:
        arrays = {k: d[k] for k in d.files}
    grid = Grid(float(arrays["dx"]), tuple(arrays["origin"]), arrays["h_before"].shape)
    return TruthFile(grid, arrays, json.loads(js.read_text()))
