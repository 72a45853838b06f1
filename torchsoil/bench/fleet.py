"""Many-recordings benchmark: four short synthetic drives (terrain pairs of 16 m straight drives,
4 m with quick=True) estimated with default settings on the local engine, by 1 worker and by 2
workers. Wall time of each whole run [s], including the workers' start (spawned processes
that import torch), mean task time [s], and fleet_speedup_4 = time with 1 worker / time with 2
workers (at most 2 on 2 cores; less when other jobs share the cores, fleet_loadavg = the
1-minute load average before the runs, or when the start-up dominates short drives)."""

from __future__ import annotations

import os
import tempfile
import time
from pathlib import Path


def drives(root: Path, n: int, length: float) -> list:
    """n terrain pairs of straight drives `length` m long (seeds 0..n-1), as fleet inputs (FleetInput)."""
    import numpy as np

    from torchsoil.jobs.fleet import FleetInput
    from torchsoil.synth.scenario import make_terrain_pair

    doc = {"name": "bench", "trajectory": {"segments": [{"straight": length, "speed": 1.0}]},
           "terrain": {"margin": 0.5}, "landmarks": {"poles": 0, "trunks": 0, "shed": False, "fence": False}}
    recs = []
    for k in range(n):
        path = root / f"drive{k}.npz"
        np.savez_compressed(path, **make_terrain_pair(doc, seed=k))
        recs.append(FleetInput(str(path), path.stem))
    return recs


def run(quick: bool = False) -> dict[str, float]:
    from torchsoil.jobs.fleet import run_fleet

    out: dict[str, float] = {}
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        recs = drives(root, 4, 4.0 if quick else 16.0)
        out["fleet_loadavg"] = os.getloadavg()[0]
        for workers in (1, 2):
            t0 = time.perf_counter()
            rows = run_fleet("estimate", recs, root / f"workers{workers}", workers=workers, tensorboard=False,
                             echo=lambda line: None)
            out[f"fleet_seconds_4_workers{workers}"] = time.perf_counter() - t0
            failed = [r["error"] for r in rows if r["status"] != "ok"]
            if failed:
                raise RuntimeError(f"fleet benchmark: {failed}")
            out[f"fleet_task_seconds_workers{workers}"] = sum(float(r["seconds"]) for r in rows) / len(rows)
    out["fleet_speedup_4"] = out["fleet_seconds_4_workers1"] / out["fleet_seconds_4_workers2"]
    return out
