"""The estimation job behind scripts/estimate.py: input in, run directory out.

DIR/params.csv and DIR/reference.csv grow one row per window; DIR/simulated.npz (the
simulated H_b stitched over windows) is rewritten every few windows; figures and summary.md
come at the end. `resume=True` continues an interrupted run from its last row.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from torchsoil import figures
from torchsoil.estimator import Estimator, Stitcher
from torchsoil.logging import CsvLog, TensorBoardLog
from torchsoil.robot import Robot
from torchsoil.terrain import TerrainPair

SAVE_EVERY = 10  # windows between rewrites of simulated.npz


def load_input(path: str | Path, out_dir: Path, robot: Robot | None, config: dict,
               robot_yaml: str | Path | None = None, pipeline_yaml: str | Path | None = None) -> TerrainPair:
    """A terrain pair from an .npz, or from a bag through the lidar pipeline (cached in out_dir,
    with the pipeline's own outputs in out_dir/pipeline). robot_yaml may carry lidar
    extrinsics (`lidars:` key) that override /tf_static; pipeline_yaml the stage settings."""
    path = Path(path)
    if path.suffix == ".npz":
        pair = TerrainPair.load(path)
    else:
        cached = out_dir / "terrain_pair.npz"
        if cached.exists():
            pair = TerrainPair.load(cached)
        else:
            if robot is None:
                raise ValueError(f"{path}: a bag needs a robot description (--robot configs/robot/X.yaml)")
            from torchsoil.pipeline.run import PipelineConfig, extrinsics_from_robot_yaml, process_bag, write_outputs

            cfg = PipelineConfig.from_yaml(pipeline_yaml) if pipeline_yaml else PipelineConfig()
            if robot_yaml:
                cfg.read.extrinsics.update(extrinsics_from_robot_yaml(robot_yaml))
            result = process_bag(path, robot, cfg, progress=True)
            for problem in result.problems:
                print(f"warning: {problem}")
            write_outputs(result, out_dir / "pipeline")
            pair = result.terrain
            pair.save(cached)
    if robot is not None:
        pair.wheels, pair.wheel_width = robot.wheels, robot.wheel_width
        pair.wheel_flat_fraction = robot.wheel_flat_fraction
    return pair


def estimate(input_path: str | Path, out_dir: str | Path, config: dict, robot: Robot | None = None,
             resume: bool = False, tensorboard: bool = True, progress: bool = True,
             robot_yaml: str | Path | None = None, pipeline_yaml: str | Path | None = None) -> Path:
    """Run the sliding-window estimator; returns out_dir. Arguments as `load_input`."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    meta = {"input": str(input_path), "config": config}
    meta_path = out / "run.json"
    if resume and meta_path.exists():
        old = json.loads(meta_path.read_text())
        if old["config"] != json.loads(json.dumps(config)):
            raise ValueError(f"{out}: --resume with a different configuration than the run being resumed")
    meta_path.write_text(json.dumps(meta, indent=1))

    pair = load_input(input_path, out, robot, config, robot_yaml, pipeline_yaml)
    est = Estimator(pair, config)
    if est.device.type == "cpu":
        # a window's tensors are small: intra-op threads only add synchronisation (and stall on
        # a busy robot computer); the relaxation kernel parallelises over the batch itself
        torch.set_num_threads(1)
    names = list(est.names)
    params = CsvLog(out / "params.csv", ["s", "t", "x", "y", *names, "residual", "prediction",
                                         "iterations", "seconds", "flags"], resume)
    reference = CsvLog(out / "reference.csv", ["s", "signal", "floor"], resume)
    n_done = min(len(params.rows), len(reference.rows))
    params.rows, reference.rows = params.rows[:n_done], reference.rows[:n_done]
    sim_path = out / "simulated.npz"
    restored = None
    if resume and sim_path.exists() and n_done:
        with np.load(sim_path) as f:
            restored = f["h_sim"]
    stitch = Stitcher(pair.h_front.shape, est.index.s, restored)
    theta = None
    for row in reversed(params.rows):
        theta = est.free_from_row(row)
        if theta is not None:
            break
    tb = TensorBoardLog(out / "tensorboard", tensorboard)
    every = int(config["estimator"]["image_every"])
    bar = tqdm(total=len(est.windows), initial=n_done, unit="window", disable=None if progress else True,
               desc="estimating")
    try:
        for k, o in enumerate(est.run(start=n_done, theta=theta), start=n_done):
            params.append(o.row)
            reference.append({"s": o.row["s"], **o.reference})
            tb.window(k, o.row, o.reference, est.names)
            if o.h_sim is not None:
                stitch.add(o.data, o.h_sim)
                if every > 0 and k % every == 0:
                    wd = o.data
                    tb.figure("h_delta/window", figures.window_figure(
                        wd.h_measured.cpu().numpy(), wd.h_front[0].cpu().numpy(), wd.h_back.cpu().numpy(),
                        o.h_sim.cpu().numpy(), wd.weight.cpu().numpy(), f"window {k}, s = {o.row['s']:.1f} m"), k)
            if (k + 1) % SAVE_EVERY == 0:
                _save_simulated(sim_path, pair, stitch.h_sim)
            bar.set_postfix(res=f"{1e3 * o.row['residual']:.2f}mm", flags=o.row["flags"] or "-")
            bar.update(1)
    finally:
        bar.close()
        tb.close()
        _save_simulated(sim_path, pair, stitch.h_sim)
    figures.parameter_curves(params.rows, reference.rows, est.names, out / "fig4_parameters.png")
    figures.difference_maps(pair, est.h_start, stitch.h_sim, params.rows, out / "fig6_difference_maps.png")
    figures.write_summary(out / "summary.md", params.rows, reference.rows,
                          {"input": str(input_path), **{k: config["estimator"][k] for k in ("window", "stride",
                                                                                              "grad")}})
    return out


def _save_simulated(path: Path, pair: TerrainPair, h_sim: np.ndarray) -> None:
    out = TerrainPair(pair.dx, pair.origin, pair.h_front, pair.h_back, pair.poses, pair.wheels,
                      pair.wheel_width, pair.wheel_flat_fraction, {"h_sim": h_sim.astype(np.float32)})
    out.save(path)


def simulated_error(run_dir: Path, truth_surface: np.ndarray, pair: TerrainPair, width: float = 2.0) -> float:
    """Mean |h_sim - truth| [m] within `width` wheel widths of the wheel paths, on stitched cells."""
    from torchsoil.windows import path_index

    with np.load(Path(run_dir) / "simulated.npz") as f:
        h_sim = f["h_sim"]
    idx = path_index(pair.grid, pair.poses, pair.robot, width * pair.wheel_width + 0.1)
    zone = (idx.wheel_dist <= width * pair.wheel_width) & np.isfinite(h_sim) & np.isfinite(truth_surface)
    return float(np.mean(np.abs(h_sim[zone] - truth_surface[zone]))) if zone.any() else math.nan


