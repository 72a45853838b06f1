"""Estimator benchmark on the synthetic `watered` scenario (terrain pair straight from the
truth, 3 mm per-cell noise): milliseconds per window (median over windows) for autograd and
finite-difference gradients, converged and capped relaxation, and the update rules; and the
seconds to index a field's revisited ground as the estimator does (`path_index_s_lawn`: six
40 m lanes half a track apart, each wheel running where the last lane's other one ran, dx
0.02 m)."""

from __future__ import annotations

import numpy as np
import torch

from torchsoil.estimate.estimator import Estimator
from torchsoil.estimate.windows import path_index, sim_reach
from torchsoil.io.terrain_pair import TerrainPair
from torchsoil.settings import load_settings

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
    out["path_index_s_lawn"] = _lawn_index_seconds(20.0 if quick else 40.0)
    return out


def _lawn_index_seconds(length: float, lanes: int = 6, gap: float = 0.5) -> float:
    """Seconds of `path_index` on a lawnmower drive: `lanes` lanes `length` m long, `gap` m apart."""
    import time

    from torchsoil.grid import Grid
    from torchsoil.robot import paper_platform

    robot = paper_platform()
    x = np.concatenate([np.arange(0, length, 0.05)[:: 1 if k % 2 == 0 else -1] for k in range(lanes)])
    per = len(x) // lanes
    y = np.repeat(np.arange(lanes) * gap, per)
    yaw = np.repeat(np.where(np.arange(lanes) % 2 == 0, 0.0, np.pi), per)
    t = 0.05 * np.arange(len(x))
    poses = np.column_stack([t, x, y, 0 * t, 0 * t, 0 * t, yaw])
    grid = Grid(0.02, (-1.5, -1.5), (int((length + 3) / 0.02), int((lanes * gap + 3) / 0.02)))
    t0 = time.perf_counter()
    path_index(grid, poses, robot, 1.6, sim_reach(robot, load_settings().sim))    # as the estimator does
    return time.perf_counter() - t0
