"""Benchmarks of torchsoil (`torchsoil bench` or `python scripts/bench.py`): every module
contributes its figures through `run(quick) -> dict`; `run_benchmarks` runs them, prints each
figure as it comes and writes OUT/bench.json and OUT/bench_meta.json (the figures' groups, the
machine and the command, for the manual's benchmarks page). Timings, not tests: the test
suite never runs them."""

from __future__ import annotations

import importlib
import json
import os
import pkgutil
import platform
import sys
import time
from pathlib import Path


def run_benchmarks(out_dir: str | Path, only: list[str] | None = None, quick: bool = False) -> Path:
    """Run the benchmark modules (`only`: their names, default all; `quick`: fewer sizes and
    repeats); returns the path of bench.json."""
    import torch

    names = [m.name for m in pkgutil.iter_modules(__path__) if not m.name.startswith("_")]
    unknown = sorted(set(only or ()) - set(names))
    if unknown:
        raise ValueError(f"unknown benchmark module(s) {', '.join(unknown)}; known: {', '.join(names)}")
    names = [n for n in names if not only or n in only]
    results: dict[str, float] = {}
    modules: dict[str, list[str]] = {}
    for name in names:
        print(f"== {name}", flush=True)
        figures = importlib.import_module(f"torchsoil.bench.{name}").run(quick=quick)
        for key, value in figures.items():
            print(f"  {key:48s} {value:12.4g}")
        results.update(figures)
        modules[name] = list(figures)
    results["torch_threads"] = torch.get_num_threads()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / "bench.json").write_text(json.dumps(results, indent=1, sort_keys=True))
    machine = (f"{os.cpu_count()} cores ({platform.processor() or platform.machine()}), python "
               f"{sys.version.split()[0]}, torch {torch.__version__}")
    meta = {"modules": modules, "machine": machine, "date": time.strftime("%Y-%m-%d"),
            "command": "torchsoil bench" + (" --quick" if quick else "")
                       + (" --only " + " ".join(only) if only else "")}
    (out / "bench_meta.json").write_text(json.dumps(meta, indent=1))  # figure groups, for the manual
    print(f"wrote {out / 'bench.json'} ({machine})")
    return out / "bench.json"
