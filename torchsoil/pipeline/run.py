"""The lidar pipeline as one call: a recording in, a terrain pair out (paper section III).

    result = process_bag("run.bag", robot, load_settings("my.yaml").pipeline)
    result.terrain.save("terrain.npz")

Stages: read (torchsoil.io.bag) -> fuse front + back in base_link -> reference map and
trajectory (mapping), levelled to gravity by the IMU or else the ground (gravity) ->
re-registration of each stream onto P_ref (reregister) -> corridor extraction and
rasterization (raster). Sweeps the stages could not use are flagged per
sweep (`scan_flags` in the output, bit names in `mapping.FLAG_NAMES`) and summarised in
`result.problems` with their times.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import NamedTuple

import numpy as np

from torchsoil.io.bag import Recording, count_messages, stream_recording
from torchsoil.io.terrain_pair import TerrainPair
from torchsoil.pipeline import mapping
from torchsoil.pipeline.checks import check_visits, flagged_spans
from torchsoil.pipeline.online import OnlinePipeline
from torchsoil.pipeline.resume import Checkpoints
from torchsoil.robot import Robot
from torchsoil.settings import PipelineConfig


class PipelineResult(NamedTuple):
    """terrain: the terrain pair (with extras); mapping: the MappingResult (T_ref, P_ref);
    timings: seconds per stage; problems: messages naming flagged sweeps and times;
    duration: recording length, s."""

    terrain: TerrainPair
    mapping: mapping.MappingResult
    timings: dict[str, float]
    problems: list[str]
    duration: float


def process_bag(bag_path: str | Path, robot: Robot, config: PipelineConfig | None = None,
                progress: bool = False, spill_dir: str | Path | None = None,
                checkpoints: Checkpoints | None = None) -> PipelineResult:
    """Recording -> terrain pair (H_f, H_b on one grid, T_ref) with per-sweep flags: the
    streaming pipeline (torchsoil.pipeline.online) run over the recording to its end.

    Args:
        bag_path: ROS 2 bag directory or ROS 1 file (docs/formats.md section 1).
        robot: wheel layout (written into the terrain pair; also bounds the ground each
            lidar may measure: ahead of the front wheels, behind the rear wheels).
        config: the pipeline section of the settings (torchsoil.settings.PipelineConfig).
        progress: show a tqdm progress bar.
        spill_dir: directory for heightmap tiles far from the robot (bounded memory).
        checkpoints: where the pipeline's state is kept as it goes (`resume.Checkpoints`, its
            spill directory `spill_dir`); when it holds one, the run goes on from there.
    Raises:
        BagError / ValueError naming the bag, topic or frame when the input is unusable;
        nothing is written by this function.
    """
    cfg = config or PipelineConfig()
    bar = _bars(progress)
    total = count_messages(bag_path, [cfg.read.front_topic, cfg.read.back_topic]) if progress else None
    rec = Recording([], [])
    kept = checkpoints.load() if checkpoints is not None else None
    online, skip = kept if kept is not None else (OnlinePipeline(robot, cfg, rec, spill_dir), 0)
    t_read = time.perf_counter()
    for n, (name, item) in enumerate(stream_recording(
            bag_path, rec, cfg.read.front_topic, cfg.read.back_topic, cfg.read.tf_topic, cfg.read.base_frame,
            progress=bar("read", total), times=cfg.read.times, imu_topic=cfg.read.imu_topic)):
        if n < skip:                     # taken before the checkpoint the run resumed from
            continue
        if n == skip and kept is not None:
            rec.problems, online.rec = online.rec.problems, rec
        if name == "imu":
            online.add_imu(item)
        else:
            online.add_cloud(name, item)
        if checkpoints is not None and checkpoints.due():
            checkpoints.save(online, n + 1)
    online.finish()
    return finish_result(online, rec, bag_path, time.perf_counter() - t_read)


def finish_result(online: OnlinePipeline, rec: Recording, bag_path, wall: float) -> PipelineResult:
    """The whole drive's terrain pair, mapping result, timings and problems of a finished
    OnlinePipeline."""
    t0 = time.perf_counter()
    terrain = online.terrain()
    for name, key in (("front", "valid_front"), ("back", "valid_back")):
        if not terrain.extras[key].any():
            ok = online.stats[name]["ok"]
            raise ValueError(f"{bag_path}: the {name} heightmap is empty ({int(np.sum(ok))} of {len(ok)} {name} "
                             "sweeps re-registered, none with ground in the corridor); nothing to write")
    maps = online.mapping_result()
    extras = {"map_fitness": maps.fitness, "map_rmse": maps.rmse}
    for name in ("front", "back"):
        st = online.stats[name]
        extras[f"rereg_fitness_{name}"] = np.asarray(st["fitness"], np.float64)
        extras[f"rereg_rmse_{name}"] = np.asarray(st["rmse"], np.float64)
    terrain.extras.update(extras)
    timings = dict(online.timings)
    timings["finish"] = time.perf_counter() - t0
    timings["read"] = max(wall - sum(timings.values()), 0.0)
    stamps, flags = terrain.extras["scan_stamps"], terrain.extras["scan_flags"]
    conflicts = check_visits(terrain, online.cfg.mapping.max_visit_shift, rec.start)
    problems = list(rec.problems) + conflicts + flagged_spans(stamps, flags, rec.start)
    for name in ("front", "back"):
        ok = online.stats[name]["ok"]
        kept = float(np.mean(ok)) if len(ok) else 0.0
        if kept < 0.5:
            problems.append(f"only {kept:.0%} of the {name} sweeps were re-registered")
    return PipelineResult(terrain, maps, timings, problems, rec.duration)


def _bars(enabled: bool):
    """Factory of progress callbacks: bar(name, total) -> callable(n)."""
    if not enabled:
        return lambda name, total: (lambda n: None)
    from tqdm.auto import tqdm

    def make(name, total):
        b = tqdm(total=total, desc=name, unit="msg" if name == "read" else "sweep", leave=False)
        return b.update

    return make


