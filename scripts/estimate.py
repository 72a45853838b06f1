"""Estimate soil parameters along a recorded drive (the paper's sliding-window estimator).

    python scripts/estimate.py                      # the bundled demo recording -> out/demo
    python scripts/estimate.py BAG_OR_NPZ --robot configs/robot/paper_platform.yaml --out DIR
    python scripts/estimate.py pair.npz --set estimator.grad=fd --set sim.fixed_iter=5

Writes DIR/params.csv, reference.csv, simulated.npz, summary.md, fig4_parameters.png,
fig6_difference_maps.png and TensorBoard events (tensorboard --logdir DIR/tensorboard).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
DEMO = ROOT / "data" / "demo" / "demo"          # the bundled recording (rosbag2, mcap)
DEMO_ROBOT = ROOT / "data" / "demo" / "demo.robot.yaml"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("input", nargs="?", help="rosbag (ROS 2 directory or ROS 1 .bag) or terrain-pair .npz "
                                             "(default: the bundled demo recording)")
    ap.add_argument("--robot", help="robot YAML (default: the one beside the demo, or the pair's own wheels)")
    ap.add_argument("--config", help="YAML overriding configs/default.yaml")
    ap.add_argument("--pipeline-config", help="lidar pipeline settings for a bag (default: configs/pipeline.yaml)")
    ap.add_argument("--out", help="output directory (default: out/<input name>)")
    ap.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                    help="override one setting, e.g. estimator.window=1.0 (repeatable)")
    ap.add_argument("--grad", choices=["autograd", "fd"], help="gradient: autograd (default) or finite differences")
    ap.add_argument("--merged-sinkage", action="store_true", help="ablation: one sinkage for all tracks")
    ap.add_argument("--capped", type=int, metavar="N", help="ablation: relaxation capped at N iterations")
    ap.add_argument("--resume", action="store_true", help="continue an interrupted run in --out")
    ap.add_argument("--no-tensorboard", action="store_true")
    args = ap.parse_args(argv)

    from torchsoil.config import load_config
    from torchsoil.robot import Robot
    from torchsoil.runner import estimate

    overrides = list(args.set)
    if args.grad:
        overrides.append(f"estimator.grad={args.grad}")
    if args.merged_sinkage:
        overrides.append("estimator.merged_sinkage=true")
    if args.capped:
        overrides.append(f"sim.fixed_iter={args.capped}")
    source = Path(args.input) if args.input else DEMO
    out = Path(args.out) if args.out else ROOT / "out" / (source.stem if args.input else "demo")
    try:
        config = load_config(args.config, overrides)
        if not source.exists():
            raise FileNotFoundError(f"{source} does not exist" + ("" if args.input else
                                    " (the bundled demo recording; see data/demo/README.md to regenerate it)"))
        robot_path = args.robot or (DEMO_ROBOT if not args.input else None)
        robot = Robot.from_yaml(robot_path) if robot_path else None
        estimate(source, out, config, robot=robot, resume=args.resume, tensorboard=not args.no_tensorboard,
                 robot_yaml=robot_path, pipeline_yaml=args.pipeline_config)
    except (ValueError, FileNotFoundError, KeyError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(f"wrote {out}: params.csv, summary.md, fig4_parameters.png, fig6_difference_maps.png, tensorboard/")
    print((out / "summary.md").read_text())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
