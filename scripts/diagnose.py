"""Diagnose model mismatch on a drive: locate it, name the physics left out, fit it, show the
held-out prediction improve.

    python scripts/diagnose.py pair.npz --out out/diag
    python scripts/diagnose.py BAG --robot configs/robot/paper_platform.yaml --out out/diag

Writes DIR/diagnosis.json (FORMATS.md section 4), report.md, residual_map.png,
residual_vs_covariate.png, cross_sections.png, prediction_costs.png and TensorBoard events.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("input", help="terrain-pair .npz or recording (ROS 2 bag directory / ROS 1 .bag)")
    ap.add_argument("--out", required=True, help="output directory")
    ap.add_argument("--robot", help="robot YAML (needed for a recording; default for a pair: its own wheels)")
    ap.add_argument("--config", help="YAML overriding configs/default.yaml")
    ap.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                    help="override an estimator/sim setting (repeatable)")
    ap.add_argument("--n-fit", type=int, default=4, help="catalogue candidates fitted (leading by evidence)")
    ap.add_argument("--no-tensorboard", action="store_true")
    args = ap.parse_args(argv)

    from torchsoil.config import load_config
    from torchsoil.diagnosis.job import diagnose_input
    from torchsoil.diagnosis.run import DiagnosisConfig
    from torchsoil.robot import Robot

    if not Path(args.input).exists():
        ap.error(f"input not found: {args.input}")
    robot = Robot.from_yaml(args.robot) if args.robot else None
    summary = diagnose_input(args.input, args.out, load_config(args.config, args.set), robot,
                             DiagnosisConfig(n_fit=args.n_fit), tensorboard=not args.no_tensorboard)
    print(json.dumps({k: summary[k] for k in ("verdict", "missing_physics", "where")}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
