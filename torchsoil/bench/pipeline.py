"""Lidar pipeline benchmark: processing time per stage and against the recording length.

Runs `process_bag` on the synthetic `road` recording (torchsoil.synth; 20 s, or 5 s when
quick).
`pipeline_realtime_factor` = processing (wall) time / recording duration (< 1: faster than
real time); `pipeline_cpu_realtime_factor` the same with the process's CPU time, which does
not depend on what else shares the cores. Accuracy against the truth
(torchsoil.synth.evaluate) as `pipeline_road_*` and, unless quick, `pipeline_sturn_*` (the
25 s S-turn on a side slope of the lateral_load_transfer scenario), `pipeline_keyhole_*` (out
and back through a keyhole turn of radius 1.5 m, no IMU) and `pipeline_headland_*` (three
rows joined by U-turns), with `pipeline_<name>_realtime_factor`.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path


def _recording(out: Path, duration: float | None, scenario: str = "road", imu: bool = True) -> tuple[Path, object]:
    from torchsoil.robot import Robot
    from torchsoil.synth.record import make_recording

    make_recording(scenario, out, 0, 0.02, "mcap", True, duration, None, progress=False, imu=imu)
    return out, Robot.from_yaml(out.parent / f"{out.name}.robot.yaml")


def run(quick: bool = False) -> dict[str, float]:
    from torchsoil.pipeline.run import process_bag

    with tempfile.TemporaryDirectory() as tmp:
        bag, robot = _recording(Path(tmp) / "road", 5.0 if quick else 20.0)
        t0, c0 = time.perf_counter(), time.process_time()
        res = process_bag(bag, robot)
        total, cpu = time.perf_counter() - t0, time.process_time() - c0
        out = {"pipeline_realtime_factor": total / res.duration,
               "pipeline_cpu_realtime_factor": cpu / res.duration,
               "pipeline_total_s": total, "pipeline_recording_s": res.duration}
        out.update({f"pipeline_{k}_s": v for k, v in res.timings.items()})
        out.update(_accuracy("road", bag, res))
        if not quick:
            for name, scenario, imu in (("sturn", "lateral_load_transfer", True), ("keyhole", "keyhole", False),
                                        ("headland", "headland", True)):
                bag, robot = _recording(Path(tmp) / name, None, scenario, imu)
                t0 = time.perf_counter()
                res = process_bag(bag, robot)
                out[f"pipeline_{name}_realtime_factor"] = (time.perf_counter() - t0) / res.duration
                out.update(_accuracy(name, bag, res))
    return out


def _accuracy(name: str, bag: Path, res) -> dict[str, float]:
    from torchsoil.synth.evaluate import pipeline_errors
    from torchsoil.synth.truthfile import load_truth

    return {f"pipeline_{name}_{k}": v for k, v in pipeline_errors(res.terrain, load_truth(bag)).items()}


if __name__ == "__main__":
    import json

    print(json.dumps(run(quick=True), indent=1))
