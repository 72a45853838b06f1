"""Run outputs written as they happen: params.csv and reference.csv one row per window
(flushed, so an interrupted run keeps what it did and `--resume` continues), and TensorBoard
scalars and images."""

from __future__ import annotations

import csv
import errno
import io
import math
import os
from pathlib import Path

import numpy as np

from torchsoil.estimate import figures
from torchsoil.estimate.estimator import Estimator
from torchsoil.io.terrain_pair import TerrainPair


class CsvLog:
    """Append-only CSV with a fixed header; `resume=True` keeps existing rows."""

    def __init__(self, path: Path, columns: list[str], resume: bool):
        self.path = Path(path)
        self.columns = columns
        self.rows: list[dict] = []
        if resume and self.path.exists():
            with self.path.open(newline="") as f:
                reader = csv.DictReader(f)
                if reader.fieldnames != columns:
                    raise ValueError(f"{self.path}: columns {reader.fieldnames} do not match this run's "
                                     f"{columns}; resume with the same robot and options, or start afresh")
                self.rows = [_parse(r) for r in reader]
        else:
            with self.path.open("w", newline="") as f:
                csv.DictWriter(f, columns).writeheader()

    def keep(self, n: int) -> None:
        """Keep only the first n rows, in memory and in the file (the lines as written): a run
        killed between writing a window's rows to two logs leaves one row too many in one."""
        if n >= len(self.rows):
            return
        with self.path.open(newline="") as f:
            lines = f.read().splitlines(keepends=True)
        tmp = self.path.with_suffix(self.path.suffix + ".tmp")
        with tmp.open("w", newline="") as f:
            f.writelines(lines[: n + 1])               # the header, then n rows
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, self.path)
        self.rows = self.rows[:n]

    def append(self, row: dict) -> None:
        """Write `row` (flushed to disk). A full disk raises DiskFull and leaves the file as it was
        before the row (no partial line): what was written stays readable and `--resume` continues."""
        line = io.StringIO(newline="")
        csv.DictWriter(line, self.columns).writerow({k: _fmt(row[k]) for k in self.columns})
        with self.path.open("ab", buffering=0) as f:
            end = f.seek(0, os.SEEK_END)
            try:
                f.write(line.getvalue().encode())
                os.fsync(f.fileno())
            except OSError as e:
                if e.errno != errno.ENOSPC:
                    raise
                f.truncate(end)
                raise DiskFull(self.path) from e
        self.rows.append(row)


class DiskFull(OSError):
    """No space left to write a run's output; what was written before stays readable."""

    def __init__(self, path: Path):
        super().__init__(errno.ENOSPC, f"no space left on the device writing {path}: the {path.name} rows "
                                       "written so far are kept; free some space and run again with --resume")


def _fmt(v):
    if isinstance(v, float):
        return "nan" if math.isnan(v) else f"{v:.7g}"
    return v


def _parse(row: dict) -> dict:
    out = {}
    for k, v in row.items():
        if k == "flags":
            out[k] = v or ""
        elif k == "iterations":
            out[k] = int(v)
        else:
            out[k] = float(v)
    return out


class TensorBoardLog:
    """Parameter curves and costs per window; measured vs simulated H_delta images."""

    def __init__(self, log_dir: Path, enabled: bool = True):
        self.writer = None
        if enabled:
            from torch.utils.tensorboard import SummaryWriter

            self.writer = SummaryWriter(str(log_dir))

    def window(self, step: int, row: dict, reference: dict, names: tuple[str, ...]) -> None:
        if self.writer is None:
            return
        for n in names:
            if not math.isnan(row[n]):
                unit = "deg" if n == "beta" else ("m" if n.startswith("d") else "")
                self.writer.add_scalar(f"params/{n}" + (f"_{unit}" if unit else ""), row[n], step)
        for key in ("residual", "prediction"):
            if not math.isnan(row[key]):
                self.writer.add_scalar(f"cost/{key}_m", row[key], step)
        for key, value in reference.items():
            if not math.isnan(value):
                self.writer.add_scalar(f"cost/{key}_m", value, step)
        self.writer.add_scalar("run/seconds", row["seconds"], step)
        self.writer.add_scalar("run/iterations", row["iterations"], step)

    def figure(self, tag: str, fig, step: int) -> None:
        if self.writer is not None:
            self.writer.add_figure(tag, fig, step)

    def close(self) -> None:
        if self.writer is not None:
            self.writer.close()


REFERENCE = ["s", "visit", "signal", "floor"]  # reference.csv columns


def param_columns(names: list[str]) -> list[str]:
    """params.csv columns for parameters `names`; visit: which visit of the window's ground the
    row fits (0 first; 0 without visit layers); passes_before: wheel passes that ground had
    had before it; rut_depth: measured rut depth of that visit, m; latency: from the arrival
    of the sweep that completed the window's ground to its row, s (NaN when not streamed)."""
    return ["s", "visit", "passes_before", "t", "x", "y", *names, "map_offset", "rut_depth", "residual",
            "prediction", "iterations", "seconds", "latency", "flags"]


def window_logs(out: Path, names: list[str], resume: bool) -> tuple[CsvLog, CsvLog, int]:
    """params.csv and reference.csv in out, and the windows both hold (a window is written once
    both its rows are: a run killed between the two leaves a row too many, dropped here)."""
    params = CsvLog(out / "params.csv", param_columns(names), resume)
    reference = CsvLog(out / "reference.csv", REFERENCE, resume)
    n_done = min(len(params.rows), len(reference.rows))
    params.keep(n_done)
    reference.keep(n_done)
    return params, reference, n_done


def multipass_outputs(est: Estimator, rows: list[dict], reference: list[dict], out: Path) -> str:
    """passes.npz, passes.png and multipass.png of a per-visit run; the multi-pass table
    (Markdown) for summary.md."""
    from torchsoil.estimate import visits

    layers = visits.pass_layers(est.pair, est.passes, est.visit_back)
    np.savez_compressed(out / "passes.npz", **layers)
    figures.pass_maps(est.pair, layers, out / "passes.png")
    table = visits.multipass_table(rows, est.names, reference)
    figures.multipass(table, out / "multipass.png")
    return visits.multipass_markdown(table)


def save_simulated(path: Path, pair: TerrainPair, h_sim: np.ndarray) -> None:
    out = TerrainPair(pair.dx, pair.origin, pair.h_front, pair.h_back, pair.poses, pair.wheels,
                      pair.wheel_width, pair.wheel_flat_fraction, {"h_sim": h_sim.astype(np.float32)})
    out.save(path)


def simulated_error(run_dir: Path, truth_surface: np.ndarray, pair: TerrainPair, width: float = 2.0) -> float:
    """Mean |h_sim - truth| [m] within `width` wheel widths of the wheel paths, on stitched cells."""
    from torchsoil.estimate.windows import path_index

    with np.load(Path(run_dir) / "simulated.npz") as f:
        h_sim = f["h_sim"]
    idx = path_index(pair.grid, pair.poses, pair.robot, width * pair.wheel_width + 0.1)
    zone = (idx.wheel_dist <= width * pair.wheel_width) & np.isfinite(h_sim) & np.isfinite(truth_surface)
    return float(np.mean(np.abs(h_sim[zone] - truth_surface[zone]))) if zone.any() else math.nan
