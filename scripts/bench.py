"""Benchmarks: print a table and write DIR/bench.json (a flat object of named figures).

Every module in torchsoil/bench/ contributes its figures through `run(quick) -> dict`.
"""

from __future__ import annotations

import argparse
import importlib
import json
import pkgutil
import platform
import sys
from pathlib import Path

import torch

import torchsoil.bench


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--out", default="out/bench", help="directory for bench.json")
    ap.add_argument("--only", nargs="*", help="benchmark modules to run (default: all)")
    ap.add_argument("--quick", action="store_true", help="fewer sizes and repeats")
    args = ap.parse_args(argv)
    names = [m.name for m in pkgutil.iter_modules(torchsoil.bench.__path__)]
    names = [n for n in names if not args.only or n in args.only]
    results: dict[str, float] = {}
    for name in names:
        print(f"== {name}", flush=True)
        figures = importlib.import_module(f"torchsoil.bench.{name}").run(quick=args.quick)
        for key, value in figures.items():
            print(f"  {key:48s} {value:12.4g}")
        results.update(figures)
    results["torch_threads"] = torch.get_num_threads()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "bench.json").write_text(json.dumps(results, indent=1, sort_keys=True))
    print(f"wrote {out / 'bench.json'} ({platform.processor() or platform.machine()}, "
          f"python {sys.version.split()[0]}, torch {torch.__version__})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
