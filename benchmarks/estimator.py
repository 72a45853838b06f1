"""Estimator benchmark on the synthetic `watered` scenario (terrain pair straight from the
truth, 3 mm per-cell noise): milliseconds per window (median over windows) for autograd and
finite-difference gradients, converged and capped relaxation, and the update rules."""

from __future__ import annotations

import numpy as np
import torch

from torchsoil.estimator import Estimator
from torchsoil.settings import load_settings
from torchsoil.terrain import TerrainPair

VARIANTS = {
    "": [],
    "_fd": ["estimator.grad=fd"],
    "_capped": ["sim.fixed_iter=5"],
    "_fd_capped": ["estimator.grad=fd", "sim.fixed_iter=5"],
    "_gd": ["estimator.optimizer=gd"],
}


def run(quick: bool = False) -> dict[str, float]:
    from torchsoil.synth.scenario import make_terrain_pair

    pair = TerrainPair.from_mapping(make_terrain_pair("watered", seed=0))
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # as scripts/estimate.py runs
    n = 12 if quick else None
    out: dict[str, float] = {}
    for suffix, overrides in VARIANTS.items():
        if quick and suffix not in ("", "_fd"):
            continue
        settings = load_settings(overrides=overrides)
        est = Estimator(pair, settings.estimator, settings.sim)
        rows = []
        for k, o in enumerate(est.run()):
            rows.append(o.row)
            if n and k + 1 >= n:
                break
        secs = np.array([r["seconds"] for r in rows])
        out[f"estimate_window_ms_dx0.02{suffix}"] = 1e3 * float(np.median(secs))
        out[f"estimate_iterations_median{suffix}"] = float(np.median([r["iterations"] for r in rows]))
        out[f"estimate_residual_mm{suffix}"] = 1e3 * float(np.nanmean([r["residual"] for r in rows]))
        out[f"estimate_prediction_mm{suffix}"] = 1e3 * float(np.nanmean([r["prediction"] for r in rows]))
    torch.set_num_threads(threads)
    return out
