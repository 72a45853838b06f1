"""The estimation job behind `torchsoil estimate`: input in, run directory out.

DIR/params.csv and DIR/reference.csv grow one row per window, or, on a terrain pair with
visit layers, one per visit of a window's ground (keyed by s and visit); DIR/simulated.npz
(the simulated H_b stitched over windows) is rewritten every few windows; figures and
summary.md come at the end, with passes.npz, passes.png and multipass.png for ground driven
more than once (docs/visits.md). `resume=True` continues an interrupted run from its last row.
"""

from __future__ import annotations

import math
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from torchsoil import figures, provenance
from torchsoil.estimator import Estimator, Stitcher
from torchsoil.logging import CsvLog, TensorBoardLog
from torchsoil.memory import release
from torchsoil.robot import Robot
from torchsoil.settings import PipelineConfig, Settings
from torchsoil.terrain import TerrainPair

SAVE_EVERY = 10  # windows between rewrites of simulated.npz
OUTPUTS = ("params.csv", "reference.csv", "simulated.npz", "summary.md", "fig4_parameters.png",
           "fig6_difference_maps.png", "tensorboard", "terrain_pair.npz", "terrain_pair.json", "pipeline", "tiles",
           "trajectory.csv", "passes.npz", "passes.png", "multipass.png")
REFERENCE = ["s", "visit", "signal", "floor"]  # reference.csv columns


def param_columns(names: list[str]) -> list[str]:
    """params.csv columns for parameters `names`; visit: which visit of the window's ground the
    row fits (0 first; 0 without visit layers); passes_before: wheel passes that ground had
    had before it; rut_depth: measured rut depth of that visit, m; latency: from the arrival
    of the sweep that completed the window's ground to its row, s (NaN when not streamed)."""
    return ["s", "visit", "passes_before", "t", "x", "y", *names, "map_offset", "rut_depth", "residual",
            "prediction", "iterations", "seconds", "latency", "flags"]


def pipeline_settings(settings: Settings, robot_yaml: str | Path | None,
                      extrinsics: dict[str, list[float]] | None = None) -> PipelineConfig:
    """The pipeline section with the robot YAML's `lidars:` extrinsics added, then
    `extrinsics` ({frame or topic: [x, y, z, roll, pitch, yaw]}, m, rad); each overrides the
    ones before it for the frames or topics it names."""
    extra = {}
    if robot_yaml:
        from torchsoil.pipeline.run import extrinsics_from_robot_yaml

        extra = extrinsics_from_robot_yaml(robot_yaml)
    extra.update(extrinsics or {})
    cfg = settings.pipeline
    return cfg.replace(read={"extrinsics": {**cfg.read.extrinsics, **extra}}) if extra else cfg


def load_input(path: str | Path, out_dir: Path, robot: Robot | None, pipeline: PipelineConfig | None = None,
               cache: dict | None = None) -> TerrainPair:
    """A terrain pair from an .npz, or from a bag through the lidar pipeline, with the
    pipeline's own outputs in out_dir/pipeline. The bag's terrain pair is cached as
    out_dir/terrain_pair.npz under `cache` (a provenance.cache_key: the input, robot and
    pipeline settings that made it); a cache made by anything else is recomputed."""
    path = Path(path)
    if path.suffix == ".npz":
        pair = TerrainPair.load(path)
    else:
        if robot is None:
            raise ValueError(f"{path}: a bag needs a robot description (--robot NAME or PATH)")
        cached = out_dir / "terrain_pair.npz"
        if cache is not None and provenance.cache_valid(cached, cache):
            pair = TerrainPair.load(cached)
        else:
            from torchsoil.pipeline.run import process_bag, write_outputs

            result = process_bag(path, robot, pipeline or PipelineConfig(), progress=True)
            for problem in result.problems:
                print(f"warning: {problem}")
            write_outputs(result, out_dir / "pipeline")
            pair = result.terrain
            pair.save(cached)
            if cache is not None:
                provenance.mark_cache(cached, cache)
    if robot is not None:
        pair.wheels, pair.wheel_width = robot.wheels, robot.wheel_width
        pair.wheel_flat_fraction = robot.wheel_flat_fraction
    return pair


def run_record(job: str, input_path: str | Path, settings: Settings, pipeline: PipelineConfig,
               robot: Robot | None, sections: tuple[str, ...]) -> dict:
    """run.json of a job: the input's identity, the robot, the other settings sections the
    job reads and, for a recording (not a terrain pair), the pipeline settings (with the
    robot's extrinsics)."""
    used = {name: getattr(settings, name).model_dump(mode="json") for name in sections}
    if Path(input_path).suffix != ".npz":
        used["pipeline"] = pipeline.model_dump(mode="json")
    return provenance.run_record(input_path, used, robot.to_dict() if robot is not None else None, job)


@contextmanager
def torch_threads(n: int | None):
    """Within the block, torch uses n intra-op threads (None: unchanged); restored after."""
    old = torch.get_num_threads()
    if n is not None:
        torch.set_num_threads(int(n))
    try:
        yield
    finally:
        torch.set_num_threads(old)


def estimate(input_path: str | Path, out_dir: str | Path, settings: Settings | None = None,
             robot: Robot | None = None, resume: bool = False, overwrite: bool = False,
             tensorboard: bool = True, progress: bool = True, robot_yaml: str | Path | None = None,
             threads: int | None = None, extrinsics: dict[str, list[float]] | None = None,
             realtime: bool = False) -> Path:
    """Run the sliding-window estimator on a recording or terrain pair; returns out_dir.

    A recording streams through the pipeline (torchsoil.live): each window is fitted as soon as
    its ground is complete and its row written then, in bounded memory; `realtime` plays it
    at its own pace (as on the robot) and prints the rows as they come. A terrain pair, or a
    recording whose pipeline output is already in out_dir, is estimated window by window.

    out_dir/run.json records the input's identity, the robot and the settings; an out_dir
    holding another run is refused (`provenance.OutputMismatch`) unless `overwrite`, and
    `resume` continues only the same run. robot_yaml may carry lidar extrinsics (`lidars:`
    key); extrinsics: {frame or topic: [x, y, z, roll, pitch, yaw]} (m, rad) over those;
    threads: torch intra-op threads during the run (restored after; None: unchanged).
    """
    settings = settings or Settings()
    out = Path(out_dir)
    pipeline = pipeline_settings(settings, robot_yaml, extrinsics)
    record = run_record("estimate", input_path, settings, pipeline, robot, ("sim", "estimator"))
    provenance.claim(out, record, resume=resume, overwrite=overwrite, outputs=OUTPUTS)
    cache = provenance.cache_key(record, "pipeline")
    streamed = Path(input_path).suffix != ".npz" and not provenance.cache_valid(out / "terrain_pair.npz", cache)
    with torch_threads(threads):
        if streamed:
            if robot is None:
                raise ValueError(f"{input_path}: a bag needs a robot description (--robot NAME or PATH)")
            _estimate_live(Path(input_path), robot, out, settings.replace(pipeline=pipeline), resume, tensorboard,
                           progress, realtime, cache)
        else:
            pair = load_input(input_path, out, robot, pipeline, cache)
            _estimate(pair, out, settings, resume, tensorboard, progress, str(input_path))
    return out


def _window_logs(out: Path, names: list[str], resume: bool) -> tuple[CsvLog, CsvLog, int]:
    """params.csv and reference.csv in out, and the windows both hold (a window is written once
    both its rows are: a run killed between the two leaves a row too many, dropped here)."""
    params = CsvLog(out / "params.csv", param_columns(names), resume)
    reference = CsvLog(out / "reference.csv", REFERENCE, resume)
    n_done = min(len(params.rows), len(reference.rows))
    params.keep(n_done)
    reference.keep(n_done)
    return params, reference, n_done


def _estimate(pair: TerrainPair, out: Path, settings: Settings, resume: bool, tensorboard: bool,
              progress: bool, name: str) -> None:
    est = Estimator(pair, settings.estimator, settings.sim, per_visit=True)
    names = list(est.names)
    params, reference, n_done = _window_logs(out, names, resume)
    sim_path = out / "simulated.npz"
    restored = None
    if resume and sim_path.exists() and n_done:
        with np.load(sim_path) as f:
            restored = f["h_sim"]
    stitch = Stitcher(pair.h_front.shape, est.index.s, restored)
    start, done, theta = _resume_point(est, params.rows)
    tb = TensorBoardLog(out / "tensorboard", tensorboard)
    every = settings.estimator.image_every
    bar = tqdm(total=len(est.windows), initial=start, unit="window", disable=None if progress else True,
               desc="estimating")
    try:
        for o in est.run(start=start, theta=theta, skip=done):
            params.append({**o.row, "latency": math.nan})
            reference.append({"s": o.row["s"], "visit": o.row["visit"], **o.reference})
            if not o.final:     # an earlier visit of the window's ground: its rows only
                continue
            k = est.window_of(o.row["s"])
            tb.window(k, o.row, o.reference, est.names)
            if o.h_sim is not None:
                stitch.add(o.data, o.h_sim)
                if every > 0 and k % every == 0:
                    wd = o.data
                    tb.figure("h_delta/window", figures.window_figure(
                        wd.h_measured.cpu().numpy(), wd.h_front[0].cpu().numpy(), wd.h_back.cpu().numpy(),
                        o.h_sim.cpu().numpy(), wd.weight.cpu().numpy(), f"window {k}, s = {o.row['s']:.1f} m"), k)
            if (k + 1) % SAVE_EVERY == 0:
                _save_simulated(sim_path, pair, stitch.h_sim)
            bar.set_postfix(res=f"{1e3 * o.row['residual']:.2f}mm", flags=o.row["flags"] or "-")
            bar.update(1)
    finally:
        bar.close()
        tb.close()
        _save_simulated(sim_path, pair, stitch.h_sim)
    last = [i for i, r in enumerate(params.rows) if i + 1 == len(params.rows) or params.rows[i + 1]["s"] != r["s"]]
    rows, refs = [params.rows[i] for i in last], [reference.rows[i] for i in last]   # each window's last visit
    figures.parameter_curves(rows, refs, est.names, out / "fig4_parameters.png")
    figures.difference_maps(pair, est.h_start, stitch.h_sim, rows, out / "fig6_difference_maps.png",
                            h_back=est.h_back)
    e = settings.estimator
    meta = {"input": name, "window": e.window, "stride": e.stride, "grad": e.grad,
            "removed": est.nuisance.describe() if est.nuisance is not None else "no map offset"}
    if est.per_visit:
        meta["multipass"] = _multipass_outputs(est, params.rows, reference.rows, out)
    figures.write_summary(out / "summary.md", params.rows, reference.rows, meta)


def _resume_point(est: Estimator, rows: list[dict]) -> tuple[int, set, dict]:
    """Where a resumed run continues: the window of the last row (its other visits may be
    missing), the (s, visit) keys already written, and each visit's warm start (its last fit)."""
    done = {(round(float(r["s"]), 6), int(r.get("visit", 0))) for r in rows}
    theta: dict = {}
    for r in rows:
        free = est.free_from_row(r)
        if free is not None:
            theta[int(r.get("visit", 0))] = free
    start = est.window_of(rows[-1]["s"]) if rows else 0
    return start, done, theta


def _multipass_outputs(est: Estimator, rows: list[dict], reference: list[dict], out: Path) -> str:
    """passes.npz, passes.png and multipass.png of a per-visit run; the multi-pass table
    (Markdown) for summary.md."""
    from torchsoil import visits

    layers = visits.pass_layers(est.pair, est.passes, est.visit_back)
    np.savez_compressed(out / "passes.npz", **layers)
    figures.pass_maps(est.pair, layers, out / "passes.png")
    table = visits.multipass_table(rows, est.names, reference)
    figures.multipass(table, out / "multipass.png")
    return visits.multipass_markdown(table)


def _estimate_live(bag: Path, robot: Robot, out: Path, settings: Settings, resume: bool, tensorboard: bool,
                   progress: bool, realtime: bool, cache: dict) -> None:
    """Stream `bag` through LiveEstimator, writing each window's rows as it is fitted; at the end
    the pipeline outputs, terrain_pair.npz, simulated.npz, figures and summary.md. On resume the
    recording is streamed through the pipeline again, but the windows already in params.csv are
    not refitted (simulated.npz then holds the windows fitted after the resume)."""
    import shutil
    import time

    from torchsoil.live import LiveEstimator, play

    e = settings.estimator
    tiles = out / "tiles"
    if tiles.exists() and not resume:
        shutil.rmtree(tiles)
    live = LiveEstimator(robot, settings, spill_dir=str(tiles) if e.online.spill else None)
    names = _param_names(robot)
    params, reference, n_done = _window_logs(out, names, resume)
    live.resume(params.rows)
    tb = TensorBoardLog(out / "tensorboard", tensorboard)
    sims = SimTiles(tiles / "sim" if e.online.spill else None)   # each window's simulated change, stitched
    whole = True                  # the drive still fits in one terrain pair (estimator.online.max_cells)
    latency: list[float] = []
    t_start = time.perf_counter()
    bar = tqdm(unit="window", disable=None if progress and not realtime else True, desc="estimating")
    try:
        for w in play(bag, live, realtime=realtime):
            o, k = w.output, w.index
            latency.append(w.done - w.ready)
            params.append({**o.row, "latency": w.done - w.ready})
            reference.append({"s": o.row["s"], "visit": o.row["visit"], **o.reference})
            tb.window(k, o.row, o.reference, names)
            whole = whole and live.pipeline.grid_cells() <= e.online.max_cells
            if o.h_sim is not None:
                sims.add(*_sim_piece(w))
            if realtime:
                r = o.row
                print(f"window {k:4d}  s {r['s']:7.2f} m  d1 {1e3 * r['d1']:6.1f} mm  chi {r['chi']:.2f}  "
                      f"beta {r['beta']:5.1f} deg  latency {1e3 * (w.done - w.ready):4.0f} ms  {r['flags']}")
            bar.update(1)
    finally:
        live.close()
        bar.close()
        tb.close()
    wall = time.perf_counter() - t_start
    lat = np.asarray(latency) if latency else np.full(1, np.nan)
    meta = {"input": str(bag), "window": e.window, "stride": e.stride, "grad": e.grad,
            "removed": "map offset and tilt fitted per stretch as the windows came (see map_offset)"
            if e.nuisance.offset else "no map offset"}
    duration = float(np.ptp(live.pipeline.trajectory()[0])) if live.pipeline.ok_stamps else 0.0
    meta["online"] = (f"streamed in {wall:.1f} s for a {duration:.1f} s drive ({wall / max(duration, 1e-9):.2f} x "
                      f"real time); window latency median {1e3 * np.median(lat):.0f} ms, "
                      f"max {1e3 * np.max(lat):.0f} ms")
    figures.parameter_curves(params.rows, reference.rows, names, out / "fig4_parameters.png")
    if whole:
        _finish_whole(live, bag, out, settings, sims, params.rows, wall, cache)
    else:
        live.pipeline.flush()
        sims.flush()
        stamps, poses = live.pipeline.trajectory()
        from torchsoil.pipeline.run import poses_to_rows

        np.savetxt(out / "trajectory.csv", poses_to_rows(stamps, poses), delimiter=",", fmt="%.9f",
                   header="t,x,y,z,roll,pitch,yaw", comments="")
        meta["online"] += (f"; the drive's heightmaps ({live.pipeline.grid_cells():,} cells, more than "
                           f"estimator.online.max_cells) are left as tiles in tiles/front and tiles/back "
                           "(torchsoil.pipeline.raster.Tiles) and the simulated change stitched over windows "
                           "in tiles/sim (runner.SimTiles), not assembled into one terrain pair")
    figures.write_summary(out / "summary.md", params.rows, reference.rows, meta)


def _finish_whole(live, bag: Path, out: Path, settings: Settings, sims: SimTiles, rows: list[dict], wall: float,
                  cache: dict) -> None:
    """The whole drive as one terrain pair: pipeline outputs, terrain_pair.npz (the cache of a
    later run), simulated.npz and the difference maps."""
    from torchsoil.pipeline.run import finish_result, write_outputs

    result = finish_result(live.pipeline, live.rec, bag, wall)
    release()
    for problem in result.problems:
        print(f"warning: {problem}")
    write_outputs(result, out / "pipeline")
    pair = result.terrain
    pair.save(out / "terrain_pair.npz")
    provenance.mark_cache(out / "terrain_pair.npz", cache)
    est = Estimator(pair, settings.estimator, settings.sim)
    h_sim = (est.h_start + _stitch(pair, sims)).astype(np.float32)   # each window's change on the final H_f
    _save_simulated(out / "simulated.npz", pair, h_sim)
    figures.difference_maps(pair, est.h_start, h_sim, rows, out / "fig6_difference_maps.png", h_back=est.h_back)


def _param_names(robot: Robot) -> list[str]:
    from torchsoil.sim import ParamSpec

    return list(ParamSpec.base(robot.n_tracks).names)


def _sim_piece(w) -> tuple:
    """A LiveWindow's simulated height change on its ground: lattice indices (i0, j0) of its
    crop, h_sim minus the surface its simulation started from (X, Y) [m], and each cell's
    distance to the window centre along the drive (inf off its ground). The change, not h_sim:
    a window fitted before the world frame's levelling was corrected (an IMU bias told at the
    end) or on a stretch with its own map offset lies in another frame than the final maps
    (on the demo drive a ramp of 0.5 mm per metre in the stitched H_b)."""
    o, pair = w.output, w.pair
    i0, _, j0, _ = o.data.crop
    gi, gj = (int(round(v / pair.dx)) for v in pair.origin)
    dist = np.where(o.data.ground.cpu().numpy(), w.dist, np.inf).astype(np.float32)
    change = (o.h_sim - o.data.h_front[0]).detach().cpu().numpy().astype(np.float32)
    return gi + i0, gj + j0, change, dist


class SimTiles:
    """The simulated height change stitched over windows as they come, in square tiles of `size`
    lattice cells (cell (I, J) at (I dx, J dx), as the corridor grids): per cell the change [m]
    (NaN where no window simulated) of the window whose centre is nearest along the drive, and
    that distance [m] (inf: none), as `estimator.Stitcher`. Tiles no window touched in the last
    `keep` windows go to `spill_dir` (None: all kept in memory), so memory is set by the ground
    near the robot, not by the drive's length (a tile of 128 x 128 cells: 128 kB)."""

    def __init__(self, spill_dir: str | Path | None = None, size: int = 128, keep: int = 20):
        self.size, self.keep, self.spill_dir = size, keep, spill_dir
        self.tiles: dict[tuple[int, int], np.ndarray] = {}   # (2, size, size) float32: change, distance
        self.used: dict[tuple[int, int], int] = {}          # the window that last touched each tile
        self.spilled: set[tuple[int, int]] = set()
        self.n = 0
        if spill_dir is not None:
            Path(spill_dir).mkdir(parents=True, exist_ok=True)

    def _path(self, k: tuple[int, int]) -> Path:
        return Path(self.spill_dir) / f"sim_{k[0]}_{k[1]}.npy"

    def _tile(self, k: tuple[int, int], create: bool) -> np.ndarray | None:
        if k in self.tiles:
            return self.tiles[k]
        if k in self.spilled:
            return np.load(self._path(k))
        if not create:
            return None
        tile = np.empty((2, self.size, self.size), np.float32)
        tile[0], tile[1] = np.nan, np.inf
        return tile

    def add(self, i0: int, j0: int, change: np.ndarray, dist: np.ndarray) -> None:
        """A window's piece (`_sim_piece`): its change (X, Y) [m] and each cell's distance to its
        centre [m] (inf off its ground) at lattice cells [i0:i0+X, j0:j0+Y]."""
        s, (ni, nj) = self.size, change.shape
        for a in range(i0 // s, (i0 + ni - 1) // s + 1):
            for b in range(j0 // s, (j0 + nj - 1) // s + 1):
                k = (a, b)
                tile = self._tile(k, create=True)
                self.tiles[k], self.used[k] = tile, self.n
                self.spilled.discard(k)
                x0, x1, y0, y1 = max(i0, a * s), min(i0 + ni, (a + 1) * s), max(j0, b * s), min(j0 + nj, (b + 1) * s)
                d = dist[x0 - i0:x1 - i0, y0 - j0:y1 - j0]
                t = tile[:, x0 - a * s:x1 - a * s, y0 - b * s:y1 - b * s]
                take = d < t[1]
                t[1][take] = d[take]
                t[0][take] = change[x0 - i0:x1 - i0, y0 - j0:y1 - j0][take]
        self.n += 1
        self.flush(self.n - self.keep)

    def flush(self, before: float = np.inf) -> None:
        """The tiles no window touched since window `before` (default: all) to spill_dir (when there
        is one): `sim_A_B.npy`, (2, size, size) float32 change [m] and distance [m] of lattice cells
        [A size:(A+1) size, B size:(B+1) size]."""
        if self.spill_dir is None:
            return
        for k in [k for k, n in self.used.items() if n < before]:
            np.save(self._path(k), self.tiles.pop(k))
            self.spilled.add(k)
            del self.used[k]

    def region(self, i0: int, i1: int, j0: int, j1: int) -> np.ndarray:
        """The stitched change (i1 - i0, j1 - j0) [m] of lattice cells [i0:i1, j0:j1] (NaN where
        no window simulated), read from memory or disk."""
        out = np.full((i1 - i0, j1 - j0), np.nan, np.float32)
        s = self.size
        for a in range(i0 // s, (i1 - 1) // s + 1):
            for b in range(j0 // s, (j1 - 1) // s + 1):
                tile = self._tile((a, b), create=False)
                if tile is None:
                    continue
                x0, x1, y0, y1 = max(i0, a * s), min(i1, (a + 1) * s), max(j0, b * s), min(j1, (b + 1) * s)
                out[x0 - i0:x1 - i0, y0 - j0:y1 - j0] = tile[0, x0 - a * s:x1 - a * s, y0 - b * s:y1 - b * s]
        return out


def _stitch(pair: TerrainPair, sims: SimTiles) -> np.ndarray:
    """Simulated height change over the whole pair's grid (NaN where no window simulated)."""
    gi, gj = (int(round(v / pair.dx)) for v in pair.origin)
    return sims.region(gi, gi + pair.h_front.shape[0], gj, gj + pair.h_front.shape[1])


def _save_simulated(path: Path, pair: TerrainPair, h_sim: np.ndarray) -> None:
    out = TerrainPair(pair.dx, pair.origin, pair.h_front, pair.h_back, pair.poses, pair.wheels,
                      pair.wheel_width, pair.wheel_flat_fraction, {"h_sim": h_sim.astype(np.float32)})
    out.save(path)


def simulated_error(run_dir: Path, truth_surface: np.ndarray, pair: TerrainPair, width: float = 2.0) -> float:
    """Mean |h_sim - truth| [m] within `width` wheel widths of the wheel paths, on stitched cells."""
    from torchsoil.windows import path_index

    with np.load(Path(run_dir) / "simulated.npz") as f:
        h_sim = f["h_sim"]
    idx = path_index(pair.grid, pair.poses, pair.robot, width * pair.wheel_width + 0.1)
    zone = (idx.wheel_dist <= width * pair.wheel_width) & np.isfinite(h_sim) & np.isfinite(truth_surface)
    return float(np.mean(np.abs(h_sim[zone] - truth_surface[zone]))) if zone.any() else math.nan


