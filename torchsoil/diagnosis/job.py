"""The job behind scripts/diagnose.py: input (recording or terrain pair) in, DIR out."""

from __future__ import annotations

from pathlib import Path

from tqdm import tqdm

from torchsoil.diagnosis.report import write_all
from torchsoil.diagnosis.run import DiagnosisConfig, diagnose, n_steps
from torchsoil.robot import Robot
from torchsoil.runner import load_input


def diagnose_input(input_path: str | Path, out_dir: str | Path, config: dict, robot: Robot | None = None,
                   cfg: DiagnosisConfig | None = None, progress: bool = True, tensorboard: bool = True) -> dict:
    """Diagnose a terrain pair (.npz) or a recording (bag, through the lidar pipeline).

    Writes out_dir/diagnosis.json, report.md, figures and TensorBoard events; returns the
    diagnosis.json dict."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    pair = load_input(input_path, out, robot, config)
    cfg = cfg or DiagnosisConfig()
    with tqdm(total=n_steps(cfg), unit="pass", desc="diagnosing", disable=not progress) as bar:
        diag = diagnose(pair, config, cfg, progress=bar)
        bar.update(bar.total - bar.n)
    write_all(diag, pair, out, Path(input_path).name, tb=tensorboard)
    return diag.summary
