#!/usr/bin/env python
"""Write a synthetic recording (rosbag2 + robot YAML + truth) or only its terrain pair.

    python scripts/make_recording.py --scenario watered --out runs/watered [--seed 0]
    python scripts/make_recording.py --scenario watered --out runs/watered.npz --pair-only
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def main(argv=None) -> int:
    from torchsoil.synth.scenario import available

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    names = ", ".join(available())
    ap.add_argument("--scenario", required=True, help=f"name ({names}) or YAML path")
    ap.add_argument("--out", required=True, type=Path, help="bag directory to create (or .npz with --pair-only)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--dx", type=float, default=0.02, help="terrain cell edge, m")
    ap.add_argument("--storage", choices=["mcap", "sqlite3"], default="mcap")
    ap.add_argument("--no-compress", action="store_true", help="mcap without zstd chunk compression")
    ap.add_argument("--duration", type=float, default=None, help="record only the first seconds")
    ap.add_argument("--columns", type=int, choices=[512, 1024, 2048], default=None)
    ap.add_argument("--organized", action="store_true", help="organized clouds (32 x columns, NaN = no return)")
    ap.add_argument("--pair-only", action="store_true", help="write only the terrain pair .npz")
    a = ap.parse_args(argv)
    try:
        if a.pair_only:
            import numpy as np

            from torchsoil.synth.scenario import make_terrain_pair

            out = a.out if a.out.suffix == ".npz" else a.out.with_name(a.out.name + ".npz")
            out.parent.mkdir(parents=True, exist_ok=True)
            np.savez_compressed(out, **make_terrain_pair(a.scenario, a.seed, a.dx))
            print(f"wrote {out}")
            return 0
        from torchsoil.synth.record import make_recording

        stats = make_recording(a.scenario, a.out, a.seed, a.dx, a.storage, not a.no_compress,
                               a.duration, a.columns, a.organized or None, progress=True)
    except (FileNotFoundError, FileExistsError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(json.dumps({k: round(v, 3) for k, v in stats.items()}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
