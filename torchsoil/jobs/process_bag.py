"""The job behind `torchsoil process-bag`: a recording through the lidar pipeline into DIR, with
checkpoints as it goes, so that a run that was stopped goes on from its last one (`resume`)."""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

from torchsoil.io.extrinsics import pipeline_settings
from torchsoil.pipeline.outputs import write_outputs
from torchsoil.pipeline.resume import Checkpoints
from torchsoil.pipeline.run import process_bag
from torchsoil.robot import Robot
from torchsoil.settings import Settings


def process_bag_job(bag: str | Path, out_dir: str | Path, settings: Settings, robot: Robot,
                    robot_yaml: str | Path | None = None, extrinsics: dict[str, list[float]] | None = None,
                    resume: bool = False) -> str:
    """Run the pipeline on `bag` (torchsoil.pipeline.run.process_bag) and write its outputs
    (terrain.npz, trajectory.csv, PNGs) into out_dir; returns a line saying what was processed,
    how fast, and what was written. The pipeline's state is checkpointed in out_dir/checkpoint
    every pipeline.checkpoint_s (its far tiles in out_dir/tiles); `resume` goes on from the last
    checkpoint of the same recording, robot and settings (or from the start, said on stderr, when
    there is none). An unusable recording leaves nothing behind; an interrupted run keeps its
    checkpoint. robot_yaml (`lidars:`) and extrinsics ({frame or topic: [x, y, z, roll, pitch,
    yaw]}, m, rad) give lidar extrinsics over the recording's. Problems (flagged sweeps) go to
    stderr as warnings."""
    cfg = pipeline_settings(settings, robot_yaml, extrinsics)
    out = Path(out_dir)
    key = (str(Path(bag).resolve()), cfg.replace(checkpoint_s=0).model_dump_json(), repr(robot))
    checkpoints = Checkpoints(out / "checkpoint", out / "tiles", cfg.checkpoint_s, key)
    if not resume:
        checkpoints.clear()
        shutil.rmtree(out / "tiles", ignore_errors=True)
    fresh = not out.exists()
    try:
        result = process_bag(bag, robot, cfg, progress=True, spill_dir=out / "tiles", checkpoints=checkpoints)
    except Exception:          # an unusable recording: nothing left behind (an interrupt keeps the checkpoint)
        checkpoints.clear()
        shutil.rmtree(out / "tiles", ignore_errors=True)
        if fresh and out.exists() and not any(out.iterdir()):
            out.rmdir()
        raise
    for p in result.problems:
        print(f"warning: {p}", file=sys.stderr)
    if resume:
        print(f"resumed from the checkpoint taken after {checkpoints.resumed} of the recording's messages"
              if checkpoints.resumed is not None else f"note: {out} held no checkpoint of this recording and "
              "settings to resume from: processed from the start", file=sys.stderr)
    paths = write_outputs(result, out)
    checkpoints.clear()
    shutil.rmtree(out / "tiles", ignore_errors=True)
    t = sum(result.timings.values())
    return (f"processed {result.duration:.1f} s of recording in {t:.1f} s ({t / max(result.duration, 1e-9):.2f} x "
            "real time); wrote " + ", ".join(str(p) for p in paths.values()))
