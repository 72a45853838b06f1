"""What the jobs share: an input (terrain pair or recording) loaded, the run record of run.json,
torch's threads for the duration of a job."""

from __future__ import annotations

from contextlib import contextmanager
from pathlib import Path

import torch

from torchsoil.io.terrain_pair import TerrainPair
from torchsoil.jobs import provenance
from torchsoil.robot import Robot
from torchsoil.settings import PipelineConfig, Settings


def load_input(path: str | Path, out_dir: Path, robot: Robot | None, pipeline: PipelineConfig | None = None,
               cache: dict | None = None) -> TerrainPair:
    """A terrain pair from an .npz, or from a bag through the lidar pipeline, with the
    pipeline's own outputs in out_dir/pipeline. The bag's terrain pair is cached as
    out_dir/terrain_pair.npz under `cache` (a provenance.cache_key: the input, robot and
    pipeline settings that made it); a cache made by anything else is recomputed."""
    path = Path(path)
    if path.suffix == ".npz":
        pair = TerrainPair.load(path)
    else:
        if robot is None:
            raise ValueError(f"{path}: a bag needs a robot description (--robot NAME or PATH)")
        cached = out_dir / "terrain_pair.npz"
        if cache is not None and provenance.cache_valid(cached, cache):
            pair = TerrainPair.load(cached)
        else:
            from torchsoil.pipeline.outputs import write_outputs
            from torchsoil.pipeline.run import process_bag

            result = process_bag(path, robot, pipeline or PipelineConfig(), progress=True)
            for problem in result.problems:
                print(f"warning: {problem}")
            write_outputs(result, out_dir / "pipeline")
            pair = result.terrain
            pair.save(cached)
            if cache is not None:
                provenance.mark_cache(cached, cache)
    if robot is not None:
        pair.wheels, pair.wheel_width = robot.wheels, robot.wheel_width
        pair.wheel_flat_fraction = robot.wheel_flat_fraction
    return pair


def run_record(job: str, input_path: str | Path, settings: Settings, pipeline: PipelineConfig,
               robot: Robot | None, sections: tuple[str, ...]) -> dict:
    """run.json of a job: the input's identity, the robot, the other settings sections the
    job reads and, for a recording (not a terrain pair), the pipeline settings (with the
    robot's extrinsics)."""
    used = {name: getattr(settings, name).model_dump(mode="json") for name in sections}
    if Path(input_path).suffix != ".npz":
        used["pipeline"] = pipeline.model_dump(mode="json")
    return provenance.run_record(input_path, used, robot.to_dict() if robot is not None else None, job)


@contextmanager
def torch_threads(n: int | None):
    """Within the block, torch uses n intra-op threads (None: unchanged); restored after."""
    old = torch.get_num_threads()
    if n is not None:
        torch.set_num_threads(int(n))
    try:
        yield
    finally:
        torch.set_num_threads(old)
