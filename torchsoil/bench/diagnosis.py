"""Diagnosis benchmark: wall time of a whole diagnosis of the 20 m `speed_dependent_sinkage`
drive (10 m with quick=True) and what it found (fitted coefficient, held-out z, costs); the
same diagnosis run again on its kept passes (`diagnosis.checkpoint`, an interrupted run's
resume); and, without quick, the time per window of the base pass and of a hardening
candidate's pass on out-and-back drives 20 and 100 m long (a diagnosis grows with the drive),
and `torchsoil diagnose` on 20 and 200 m speed drives: `diagnosis_peak_rss_mb_*`,
`diagnosis_seconds_per_m_*` and `diagnosis_ms_per_window_pass_*`, in one process and, keys
ending `_workers2`, with `--pass-workers 2` (peak: the largest process's)."""

from __future__ import annotations

import tempfile
import time
from pathlib import Path


def run(quick: bool = False) -> dict[str, float]:
    from torchsoil.diagnosis import diagnose
    from torchsoil.diagnosis.checkpoint import PassCache
    from torchsoil.io.terrain_pair import TerrainPair
    from torchsoil.settings import merge
    from torchsoil.synth.scenario import load_scenario, make_terrain_pair

    scn = load_scenario("speed_dependent_sinkage")
    if quick:
        scn = load_scenario(merge(scn.model_dump(), {"trajectory": {
            "segments": [{"straight": 2.0, "speed": v} for v in (1.0, 0.5, 1.5, 0.6, 1.4)],
            "accel_limit": 1.0}}))
    pair = TerrainPair.from_mapping(make_terrain_pair(scn, seed=0))
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        diag = diagnose(pair, cache=PassCache(tmp, {"bench": "diagnosis"}))
        secs = time.perf_counter() - t0
        again = PassCache(tmp, {"bench": "diagnosis"})
        t0 = time.perf_counter()
        diagnose(pair, cache=again)
        resume = time.perf_counter() - t0
    fit = {f.ext.id: f for f in diag.fits}.get("speed_dependent_sinkage")
    s = diag.summary
    scaling = {} if quick else {f"diagnosis_{name}_{length}m": v
                                for length in (20, 100) for name, v in _pass_times(length).items()}
    if not quick:
        scaling.update(_field_length())
    return {
        **scaling,
        "diagnosis_resume_seconds": resume,
        "diagnosis_passes_kept": float(again.hits),
        "diagnosis_seconds": secs,
        "diagnosis_named_speed": float(s["missing_physics"] == "speed_dependent_sinkage"),
        "diagnosis_k_speed": fit.k if fit else float("nan"),
        "diagnosis_heldout_z": fit.z if fit else float("nan"),
        "diagnosis_prediction_before_mm": 1e3 * s["cost_before"]["prediction"],
        "diagnosis_prediction_after_mm": 1e3 * s["cost_after"]["prediction"],
    }


def _pass_times(length: float) -> dict[str, float]:
    """ms per window of the base pass (preparing the windows too) and of a hardening pass at
    k -0.5 (windows prepared), and the seconds an estimator's setup takes (path index, map
    offset, view), on an out-and-back drive of `length` m: all three should grow no faster
    than the drive."""
    from torchsoil.diagnosis.catalogue import ExtensionModel, get
    from torchsoil.diagnosis.covariates import DriveSignals
    from torchsoil.diagnosis.fit import run_pass, shared_of
    from torchsoil.diagnosis.study_cases import scenario
    from torchsoil.estimate.estimator import Estimator
    from torchsoil.io.terrain_pair import TerrainPair
    from torchsoil.settings import Settings
    from torchsoil.synth.scenario import make_terrain_pair

    sc = scenario("multi_pass_hardening")
    sc["trajectory"] = {"segments": [{"straight": length / 2, "speed": 1.0},
                                     {"arc": 1.5, "angle_deg": 180, "speed": 0.8},
                                     {"straight": length / 2, "speed": 1.0}]}
    pair = TerrainPair.from_mapping(make_terrain_pair(sc, seed=1))
    st = Settings()
    t0 = time.perf_counter()
    Estimator(pair, st.estimator, st.sim)
    t_setup = time.perf_counter() - t0
    t0 = time.perf_counter()
    base = run_pass(pair, st.estimator, st.sim, profiles=True)
    t_base = time.perf_counter() - t0
    model = ExtensionModel(get("multi_pass_hardening"), -0.5, DriveSignals.from_poses(pair.poses, pair.robot),
                           pair.robot, base.view, st.sim.dig_order)
    t0 = time.perf_counter()
    run_pass(pair, st.estimator, st.sim, model, profiles=True, **shared_of(base))
    t_hard = time.perf_counter() - t0
    n = len(base.rows)
    return {"base_pass_ms_per_window": 1e3 * t_base / n, "hardening_pass_ms_per_window": 1e3 * t_hard / n,
            "estimator_setup_seconds": t_setup}


def _field_length(lengths: tuple[float, ...] = (20.0, 200.0), workers: tuple[int, ...] = (1, 2)) -> dict[str, float]:
    """Peak resident memory [MB] and wall time per metre [s/m] of `torchsoil diagnose` on the
    speed drive's stretches (5 m each at 1.0, 0.5, 1.5, 0.6, 1.4 m/s) repeated to each length,
    in one process and (keys ending _workers2) with --pass-workers 2: its peak is the largest
    process's (the main one or a worker), not their sum."""
    from torchsoil.bench._memory import peak_rss_mb
    from torchsoil.io.terrain_pair import TerrainPair
    from torchsoil.settings import merge
    from torchsoil.synth.scenario import load_scenario, make_terrain_pair

    out: dict[str, float] = {}
    speeds = (1.0, 0.5, 1.5, 0.6, 1.4)
    with tempfile.TemporaryDirectory() as tmp:
        for length in lengths:
            segments = [{"straight": 5.0, "speed": speeds[i % 5]} for i in range(int(round(length / 5.0)))]
            scn = load_scenario(merge(load_scenario("speed_dependent_sinkage").model_dump(),
                                      {"trajectory": {"segments": segments}}))
            path = Path(tmp) / f"speed_{length:g}m.npz"
            TerrainPair.from_mapping(make_terrain_pair(scn, seed=0)).save(path)
            for n in workers:
                tag = f"{length:g}m" + ("" if n == 1 else f"_workers{n}")
                t0 = time.perf_counter()
                run = Path(tmp) / f"diag{tag}"
                out[f"diagnosis_peak_rss_mb_{tag}"] = peak_rss_mb(["diagnose", str(path), "--out", str(run),
                                                                   "--no-tensorboard", "--pass-workers", str(n)])
                wall = time.perf_counter() - t0
                out[f"diagnosis_seconds_per_m_{tag}"] = wall / length
                out[f"diagnosis_ms_per_window_pass_{tag}"] = 1e3 * wall / _window_passes(run / "passes")
    return out


def _window_passes(kept: Path) -> float:
    """Windows fitted by a diagnosis, from its kept passes (checkpoint.PassCache): each full pass
    fits every window of the base pass, each tyre-section score every third. A longer drive may
    put more candidates to the test (more passes), so time per metre alone overstates its cost."""
    import pickle

    with next(kept.glob("base-*.pkl")).open("rb") as fh:
        windows = len(pickle.load(fh)[1].rows)
    files = [f.name for f in kept.glob("*.pkl")]
    sections = sum(f.startswith("section-") for f in files)
    return windows * (len(files) - sections + sections / 3)
