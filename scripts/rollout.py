"""Straight line through the wet patch vs a detour through the packed lane, on one field:
print the soil damage vs time trade-off and plot it (OUT/rollout.png, OUT/rollout.json)."""

from __future__ import annotations

import argparse

from envs.scripted import compare_detour


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--config", default=None, help="env settings YAML: the env section (dt, speed, field, sim, ...) "
                    "or a full settings file with an env: section (default: the built-in defaults)")
    ap.add_argument("--out", default="out/rollout", help="output directory")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--speed", type=float, default=1.0, help="driving speed, m/s")
    ap.add_argument("--detour-y", type=float, default=8.4, help="y of the detour's straight part, m")
    args = ap.parse_args(argv)
    compare_detour(args.config, args.out, seed=args.seed, speed=args.speed, detour_y=args.detour_y)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
