"""The paper's ablation study (Table I) on one input: the proposed model, merged sinkage and
capped relaxation, each a full estimation run in OUT/<variant>/, then one table.

    python scripts/ablation.py BAG_OR_NPZ [--robot ROBOT.yaml] --out DIR
"""

from __future__ import annotations

import argparse
from pathlib import Path

VARIANTS = {"proposed": [], "merged_sinkage": ["estimator.merged_sinkage=true"],
            "capped_relaxation": ["sim.fixed_iter=5"]}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("input")
    ap.add_argument("--robot")
    ap.add_argument("--out", required=True)
    ap.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE")
    args = ap.parse_args(argv)

    from torchsoil.ablation import ablation_table
    from torchsoil.config import load_config
    from torchsoil.robot import Robot
    from torchsoil.runner import estimate

    robot = Robot.from_yaml(args.robot) if args.robot else None
    runs = {}
    for name, overrides in VARIANTS.items():
        runs[name] = estimate(args.input, Path(args.out) / name, load_config(overrides=args.set + overrides),
                              robot=robot, tensorboard=False)
    table = ablation_table(runs)
    (Path(args.out) / "ablation.md").write_text(table + "\n")
    print(table)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
