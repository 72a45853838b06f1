"""Table I of the paper from estimation runs: residual and prediction cost per model variant,
with the deformation signal and noise floor as reference rows (x 1e-3 m)."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from torchsoil.jobs.estimate import estimate
from torchsoil.robot import Robot
from torchsoil.settings import load_settings

# settings overrides of each variant of the paper's Table I
VARIANTS = {"proposed": [], "merged_sinkage": ["estimator.merged_sinkage=true"],
            "capped_relaxation": ["sim.fixed_iter=5"]}


def _read(path: Path, key: str) -> np.ndarray:
    with Path(path).open() as f:
        return np.array([float(r[key]) for r in csv.DictReader(f)])


def _cells(v: np.ndarray) -> str:
    v = v[np.isfinite(v)] * 1e3
    return f"{v.mean():.2f} | {v.std():.2f} | {v.min():.1f}/{v.max():.1f}" if len(v) else "n/a | n/a | n/a"


def ablation_table(runs: dict[str, Path]) -> str:
    """Markdown table from {variant name: run directory}; reference rows from the first run.
    Also the mean seconds per window of each variant."""
    first = next(iter(runs.values()))
    lines = ["| variant | residual mean | std | min/max | prediction mean | std | min/max | s/window |",
             "| --- | --- | --- | --- | --- | --- | --- | --- |",
             f"| deformation signal | {_cells(_read(first / 'reference.csv', 'signal'))} | / | / | / | |",
             f"| noise floor | {_cells(_read(first / 'reference.csv', 'floor'))} | / | / | / | |"]
    for name, run in runs.items():
        p = Path(run) / "params.csv"
        lines.append(f"| {name} | {_cells(_read(p, 'residual'))} | {_cells(_read(p, 'prediction'))} | "
                     f"{np.mean(_read(p, 'seconds')):.3f} |")
    return "\n".join(lines)


def ablation(input_path: str | Path, out_dir: str | Path, configs: list[str] = (), overrides: list[str] = (),
             robot: Robot | None = None, robot_yaml: str | Path | None = None, threads: int | None = 1,
             extrinsics: dict[str, list[float]] | None = None) -> str:
    """Estimate `input_path` once per variant of VARIANTS into out_dir/<variant> (settings: the
    defaults, `configs`, `overrides`, then the variant's own), and write the table
    (`ablation_table`) to out_dir/ablation.md; returns it."""
    runs = {}
    for name, variant in VARIANTS.items():
        settings = load_settings(*configs, overrides=[*overrides, *variant])
        runs[name] = estimate(input_path, Path(out_dir) / name, settings, robot=robot, tensorboard=False,
                              robot_yaml=robot_yaml, threads=threads, overwrite=False, extrinsics=extrinsics)
    table = ablation_table(runs)
    (Path(out_dir) / "ablation.md").write_text(table + "\n")
    return table
