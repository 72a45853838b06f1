#!/usr/bin/env python
"""Lidar pipeline: a recording in, a terrain pair, the trajectory and heightmap PNGs out.

    python scripts/process_bag.py BAG --robot configs/robot/paper_platform.yaml --out DIR
        [--config configs/pipeline.yaml] [--no-reregister]
        [--extrinsic lidar_front X Y Z ROLL PITCH YAW] ...
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from torchsoil.io.bag import BagError
from torchsoil.pipeline.run import PipelineConfig, extrinsics_from_robot_yaml, process_bag, write_outputs
from torchsoil.robot import Robot


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("bag", type=Path, help="ROS 2 bag directory or ROS 1 .bag file")
    ap.add_argument("--robot", type=Path, required=True, help="robot YAML (FORMATS.md section 2)")
    ap.add_argument("--out", type=Path, required=True, help="output directory")
    ap.add_argument("--config", type=Path, default=None, help="pipeline YAML (stage defaults)")
    ap.add_argument("--no-reregister", action="store_true",
                    help="ablation: rasterize with T_ref, without re-registration")
    ap.add_argument("--extrinsic", nargs=7, action="append", default=[],
                    metavar=("FRAME", "X", "Y", "Z", "ROLL", "PITCH", "YAW"),
                    help="override a lidar's pose in base_link (m, rad)")
    a = ap.parse_args(argv)
    try:
        cfg = PipelineConfig.from_yaml(a.config) if a.config else PipelineConfig()
        robot = Robot.from_yaml(a.robot)
        cfg.read.extrinsics.update(extrinsics_from_robot_yaml(a.robot))
        for frame, *values in a.extrinsic:
            cfg.read.extrinsics[frame] = [float(v) for v in values]
        if a.no_reregister:
            cfg.reregister.enabled = False
        result = process_bag(a.bag, robot, cfg, progress=True)
    except (BagError, ValueError, FileNotFoundError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    for p in result.problems:
        print(f"warning: {p}", file=sys.stderr)
    paths = write_outputs(result, a.out)
    t = sum(result.timings.values())
    print(f"processed {result.duration:.1f} s of recording in {t:.1f} s "
          f"({t / max(result.duration, 1e-9):.2f} x real time); wrote "
          + ", ".join(str(p) for p in paths.values()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
