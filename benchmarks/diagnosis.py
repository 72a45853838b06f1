"""Diagnosis benchmark: wall time of a whole diagnosis of the 20 m `speed_dependent_sinkage`
drive (10 m with quick=True) and what it found (fitted coefficient, held-out z, costs)."""

from __future__ import annotations

import time


def run(quick: bool = False) -> dict[str, float]:
    from torchsoil.diagnosis import diagnose
    from torchsoil.settings import merge
    from torchsoil.synth.scenario import load_scenario, make_terrain_pair
    from torchsoil.terrain import TerrainPair

    scn = load_scenario("speed_dependent_sinkage")
    if quick:
        scn = load_scenario(merge(scn.model_dump(), {"trajectory": {
            "segments": [{"straight": 2.0, "speed": v} for v in (1.0, 0.5, 1.5, 0.6, 1.4)],
            "accel_limit": 1.0}}))
    pair = TerrainPair.from_mapping(make_terrain_pair(scn, seed=0))
    t0 = time.perf_counter()
    diag = diagnose(pair)
    secs = time.perf_counter() - t0
    fit = {f.ext.id: f for f in diag.fits}.get("speed_dependent_sinkage")
    s = diag.summary
    return {
        "diagnosis_seconds": secs,
        "diagnosis_named_speed": float(s["missing_physics"] == "speed_dependent_sinkage"),
        "diagnosis_k_speed": fit.k if fit else float("nan"),
        "diagnosis_heldout_z": fit.z if fit else float("nan"),
        "diagnosis_prediction_before_mm": 1e3 * s["cost_before"]["prediction"],
        "diagnosis_prediction_after_mm": 1e3 * s["cost_after"]["prediction"],
    }
