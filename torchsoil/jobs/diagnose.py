"""The job behind `torchsoil diagnose`: input (recording or terrain pair) in, DIR out."""

from __future__ import annotations

from pathlib import Path

from tqdm import tqdm

from torchsoil.diagnosis.checkpoint import PassCache
from torchsoil.diagnosis.parallel import pass_pool
from torchsoil.diagnosis.phases import diagnose, n_steps
from torchsoil.diagnosis.report import write_all
from torchsoil.engines import default_workers
from torchsoil.io.extrinsics import pipeline_settings
from torchsoil.jobs import provenance
from torchsoil.jobs.common import load_input, run_record, torch_threads
from torchsoil.robot import Robot
from torchsoil.settings import Settings

MAX_PASS_WORKERS = 4     # a diagnosis's default local pass workers at most
OUTPUTS = ("diagnosis.json", "report.md", "residual_map.png", "residual_vs_covariate.png", "cross_sections.png",
           "prediction_costs.png", "tensorboard", "terrain_pair.npz", "terrain_pair.json", "pipeline", "passes")


def diagnose_input(input_path: str | Path, out_dir: str | Path, settings: Settings | None = None,
                   robot: Robot | None = None, progress: bool = True, tensorboard: bool = True,
                   overwrite: bool = False, robot_yaml: str | Path | None = None, threads: int | None = None,
                   extrinsics: dict[str, list[float]] | None = None, rows: list | None = None,
                   resume: bool = False, workers: int | None = 1, engine: str = "local") -> dict:
    """Diagnose a terrain pair (.npz) or a recording (bag, through the lidar pipeline).

    Writes out_dir/run.json (what made the folder; another run's folder is refused unless
    `overwrite`), diagnosis.json, report.md, figures and TensorBoard events; returns the
    diagnosis.json dict. Each finished estimator pass is kept in out_dir/passes
    (checkpoint.PassCache): the same diagnosis run again into out_dir (after an interruption)
    reads them back and runs only the rest (`resume`: out_dir must hold such a run's run.json).
    robot_yaml (`lidars:`) and extrinsics ({frame or
    topic: [x, y, z, roll, pitch, yaw]}, m, rad) give lidar extrinsics over the recording's. rows: a list that
    receives the base model's window rows (params.csv rows: s [m], d1..dT [m], chi, beta [deg],
    costs [m], flags), for summaries of many diagnoses (torchsoil.jobs.fleet). workers, engine: the
    independent passes run as that many tasks at once on the local process pool or Ray
    (diagnosis.parallel; workers 1 on the local engine: all in this process; None: `pass_workers`'
    default); same results."""
    settings = settings or Settings()
    workers = pass_workers(workers, engine, settings.fleet)
    out = Path(out_dir)
    pipeline = pipeline_settings(settings, robot_yaml, extrinsics)
    record = run_record("diagnose", input_path, settings, pipeline, robot, ("sim", "estimator", "diagnosis"))
    provenance.claim(out, record, resume=resume, overwrite=overwrite, outputs=OUTPUTS)
    pair = load_input(input_path, out, robot, pipeline, provenance.cache_key(record, "pipeline"))
    cfg = settings.diagnosis
    with torch_threads(threads), tqdm(total=n_steps(cfg), unit="pass", desc="diagnosing",
                                      disable=not progress) as bar:
        key = provenance.cache_key(record, "sim", "estimator", "diagnosis", "pipeline") | {
            "torchsoil": record["torchsoil"]}
        cache = PassCache(out / "passes", key, every=cfg.checkpoint_s)
        kept = len(cache)
        if kept and progress:
            tqdm.write(f"resuming: {kept} kept results (finished passes, section scores, a pass in progress) "
                       f"in {cache.dir} are read back")
        with pass_pool(workers, engine, cache, bar) as pool:
            diag = diagnose(pair, cfg, settings.estimator, settings.sim, progress=bar, cache=cache, pool=pool)
        bar.update(bar.total - bar.n)
    if rows is not None:
        rows.extend(diag.base.rows)
    write_all(diag, pair, out, Path(input_path).name, tb=tensorboard)
    return diag.summary


def pass_workers(given: int | None, engine: str, fleet) -> int:
    """The pass workers of one diagnosis: `given`, or by default on the local engine as many as
    the cores and memory hold (`engines.default_workers` of the fleet settings), at most
    MAX_PASS_WORKERS (a diagnosis has a few tens of independent passes, each worker holds the
    drive's maps); on Ray, 1 (the cluster's own)."""
    if given is not None:
        return given
    return min(MAX_PASS_WORKERS, default_workers(fleet)) if engine == "local" else 1
