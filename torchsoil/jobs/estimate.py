"""The estimation job behind `torchsoil estimate`: input in, run directory out.

DIR/params.csv and DIR/reference.csv grow one row per window, or, on a terrain pair with
visit layers, one per visit of a window's ground (keyed by s and visit); DIR/simulated.npz
(the simulated H_b stitched over windows) is rewritten every few windows; figures and
summary.md come at the end, with passes.npz, passes.png and multipass.png for ground driven
more than once (docs/visits.md). `resume=True` continues an interrupted run from its last row.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from tqdm import tqdm

from torchsoil.estimate import figures
from torchsoil.estimate.estimator import Estimator, Stitcher
from torchsoil.estimate.outputs import TensorBoardLog, multipass_outputs, save_simulated, window_logs
from torchsoil.estimate.tiles import SimTiles, sim_piece, stitch_tiles
from torchsoil.io.extrinsics import pipeline_settings
from torchsoil.io.terrain_pair import TerrainPair
from torchsoil.jobs import provenance
from torchsoil.jobs.common import load_input, run_record, torch_threads
from torchsoil.memory import release
from torchsoil.robot import Robot
from torchsoil.settings import Settings

DEMO = Path("data") / "demo"  # the bundled demo recording, in a source checkout
SAVE_EVERY = 10  # windows between rewrites of simulated.npz
OUTPUTS = ("params.csv", "reference.csv", "simulated.npz", "summary.md", "fig4_parameters.png",
           "fig6_difference_maps.png", "tensorboard", "terrain_pair.npz", "terrain_pair.json", "pipeline", "tiles",
           "trajectory.csv", "passes.npz", "passes.png", "multipass.png", "export", "pieces")


def demo_input() -> tuple[Path, Path]:
    """The bundled demo recording and its robot YAML (data/demo/ under the current directory or
    the source checkout); FileNotFoundError when there is none."""
    import torchsoil

    for root in (Path.cwd(), Path(torchsoil.__file__).resolve().parents[1]):
        if (root / DEMO / "demo").exists():
            return root / DEMO / "demo", root / DEMO / "demo.robot.yaml"
    raise FileNotFoundError("no INPUT given and no bundled demo recording here (data/demo/demo of a "
                            "source checkout); give a bag or terrain-pair .npz")


def estimate(input_path: str | Path, out_dir: str | Path, settings: Settings | None = None,
             robot: Robot | None = None, resume: bool = False, overwrite: bool = False,
             tensorboard: bool = True, progress: bool = True, robot_yaml: str | Path | None = None,
             threads: int | None = None, extrinsics: dict[str, list[float]] | None = None,
             realtime: bool = False) -> Path:
    """Run the sliding-window estimator on a recording or terrain pair; returns out_dir.

    A recording streams through the pipeline (torchsoil.estimate.live): each window is fitted as soon as
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


def _estimate(pair: TerrainPair, out: Path, settings: Settings, resume: bool, tensorboard: bool,
              progress: bool, name: str) -> None:
    est = Estimator(pair, settings.estimator, settings.sim, per_visit=True)
    names = list(est.names)
    params, reference, n_done = window_logs(out, names, resume)
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
                save_simulated(sim_path, pair, stitch.h_sim)
            bar.set_postfix(res=f"{1e3 * o.row['residual']:.2f}mm", flags=o.row["flags"] or "-")
            bar.update(1)
    finally:
        bar.close()
        tb.close()
        save_simulated(sim_path, pair, stitch.h_sim)
    last = [i for i, r in enumerate(params.rows) if i + 1 == len(params.rows) or params.rows[i + 1]["s"] != r["s"]]
    rows, refs = [params.rows[i] for i in last], [reference.rows[i] for i in last]   # each window's last visit
    figures.parameter_curves(rows, refs, est.names, out / "fig4_parameters.png")
    figures.difference_maps(pair, est.h_start, stitch.h_sim, rows, out / "fig6_difference_maps.png",
                            h_back=est.h_back)
    e = settings.estimator
    meta = {"input": name, "window": e.window, "stride": e.stride, "grad": e.grad,
            "removed": est.nuisance.describe() if est.nuisance is not None else "no map offset"}
    if est.per_visit:
        meta["multipass"] = multipass_outputs(est, params.rows, reference.rows, out)
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


def _estimate_live(bag: Path, robot: Robot, out: Path, settings: Settings, resume: bool, tensorboard: bool,
                   progress: bool, realtime: bool, cache: dict) -> None:
    """Stream `bag` through LiveEstimator, writing each window's rows as it is fitted; at the end
    the pipeline outputs, terrain_pair.npz, simulated.npz, figures and summary.md. On resume the
    recording is streamed through the pipeline again, but the windows already in params.csv are
    not refitted (simulated.npz then holds the windows fitted after the resume)."""
    from torchsoil.estimate.live import play

    run = LiveRun(out, robot, settings, resume, tensorboard)
    bar = tqdm(unit="window", disable=None if progress and not realtime else True, desc="estimating")
    try:
        for w in play(bag, run.live, realtime=realtime):
            run.add(w)
            if realtime:
                r = w.output.row
                print(f"window {w.index:4d}  s {r['s']:7.2f} m  d1 {1e3 * r['d1']:6.1f} mm  chi {r['chi']:.2f}  "
                      f"beta {r['beta']:5.1f} deg  latency {1e3 * (w.done - w.ready):4.0f} ms  {r['flags']}")
            bar.update(1)
    finally:
        run.close()
        bar.close()
    run.finish(bag, cache)


class LiveRun:
    """The outputs of a streamed run, written as its windows come (params.csv, reference.csv,
    TensorBoard, the simulated change stitched in tiles) and at its end (`finish`: the pipeline
    outputs, terrain pair or pieces, figures, summary.md). `live` is its LiveEstimator (spilling
    far tiles to out/tiles); resume: continue params.csv (the windows in it are not refitted)."""

    def __init__(self, out: Path, robot: Robot, settings: Settings, resume: bool, tensorboard: bool = True):
        import shutil
        import time

        from torchsoil.estimate.live import LiveEstimator

        self.out, self.settings = out, settings
        e = settings.estimator
        tiles = out / "tiles"
        if tiles.exists() and not resume:
            shutil.rmtree(tiles)
        self.live = LiveEstimator(robot, settings, spill_dir=str(tiles) if e.online.spill else None)
        self.names = _param_names(robot)
        self.params, self.reference, _ = window_logs(out, self.names, resume)
        self.live.resume(self.params.rows)
        self.tb = TensorBoardLog(out / "tensorboard", tensorboard)
        self.sims = SimTiles(tiles / "sim" if e.online.spill else None)   # each window's simulated change
        self.whole = True          # the drive still fits in one terrain pair (estimator.online.max_cells)
        self.latency: list[float] = []
        self.t_start = time.perf_counter()

    def add(self, w) -> None:
        """One LiveWindow: its rows written (latency: from its ground complete to its row, s)."""
        o, k = w.output, w.index
        self.latency.append(w.done - w.ready)
        row = {c: math.nan for c in self.params.columns} | o.row | {"latency": w.done - w.ready}
        self.params.append(row)
        self.reference.append({"s": o.row["s"], "visit": o.row["visit"], **o.reference})
        self.tb.window(k, row, o.reference, self.names)
        self.whole = self.whole and self.live.pipeline.grid_cells() <= self.settings.estimator.online.max_cells
        if o.h_sim is not None:
            self.sims.add(*sim_piece(w))

    def close(self) -> None:
        """Stop the fits' worker thread and close TensorBoard."""
        self.live.close()
        self.tb.close()

    def finish(self, source, cache: dict | None = None) -> None:
        """After the last window (live.finish() fed to `add`, `close` called): figures,
        summary.md, and the drive's terrain as one pair (pipeline/, terrain_pair.npz,
        simulated.npz, Fig. 6) or, over estimator.online.max_cells, as pieces/. source: the
        recording's name for the outputs; cache: terrain_pair.npz's cache key (None: none)."""
        import time

        out, settings, live, e = self.out, self.settings, self.live, self.settings.estimator
        wall = time.perf_counter() - self.t_start
        lat = np.asarray(self.latency) if self.latency else np.full(1, np.nan)
        meta = {"input": str(source), "window": e.window, "stride": e.stride, "grad": e.grad,
                "removed": "map offset and tilt fitted per stretch as the windows came (see map_offset)"
                if e.nuisance.offset else "no map offset"}
        duration = float(np.ptp(live.pipeline.trajectory()[0])) if live.pipeline.ok_stamps else 0.0
        meta["online"] = (f"streamed in {wall:.1f} s for a {duration:.1f} s drive ({wall / max(duration, 1e-9):.2f} x "
                          f"real time); window latency median {1e3 * np.nanmedian(lat):.0f} ms, "
                          f"max {1e3 * np.nanmax(lat):.0f} ms")
        rows = self.params.rows
        figures.parameter_curves(rows, self.reference.rows, self.names, out / "fig4_parameters.png")
        if self.whole:
            _finish_whole(live, source, out, settings, self.sims, rows, wall, cache)
        else:
            live.pipeline.flush()
            self.sims.flush()
            stamps, poses = live.pipeline.trajectory()
            from torchsoil.io.trajectory import poses_to_rows

            np.savetxt(out / "trajectory.csv", poses_to_rows(stamps, poses), delimiter=",", fmt="%.9f",
                       header="t,x,y,z,roll,pitch,yaw", comments="")
            n = write_pieces(live.pipeline, self.sims, out / "pieces", e.online.piece_length, e.front_smoothing)
            meta["online"] += (f"; the drive's heightmaps ({live.pipeline.grid_cells():,} cells, more than "
                               f"estimator.online.max_cells) are left as tiles in tiles/front and tiles/back "
                               "(torchsoil.pipeline.raster.Tiles) and the simulated change stitched over windows "
                               f"in tiles/sim (estimate.tiles.SimTiles), and written as {n} terrain pairs of "
                               f"{e.online.piece_length:g} m of the drive each in pieces/ (`torchsoil export` reads "
                               "them), not assembled into one")
        figures.write_summary(out / "summary.md", rows, self.reference.rows, meta)


def _finish_whole(live, bag, out: Path, settings: Settings, sims: SimTiles, rows: list[dict], wall: float,
                  cache: dict | None) -> None:
    """The whole drive as one terrain pair: pipeline outputs, terrain_pair.npz (the cache of a
    later run), simulated.npz and the difference maps."""
    from torchsoil.pipeline.outputs import write_outputs
    from torchsoil.pipeline.run import finish_result

    result = finish_result(live.pipeline, live.rec, bag, wall)
    release()
    for problem in result.problems:
        print(f"warning: {problem}")
    write_outputs(result, out / "pipeline")
    pair = result.terrain
    pair.save(out / "terrain_pair.npz")
    if cache is not None:
        provenance.mark_cache(out / "terrain_pair.npz", cache)
    est = Estimator(pair, settings.estimator, settings.sim)
    h_sim = (est.h_start + stitch_tiles(pair, sims)).astype(np.float32)   # each window's change on the final H_f
    save_simulated(out / "simulated.npz", pair, h_sim)
    figures.difference_maps(pair, est.h_start, h_sim, rows, out / "fig6_difference_maps.png", h_back=est.h_back)


def write_pieces(pipeline, sims: SimTiles, folder: Path, length: float, front_smoothing: float) -> int:
    """The drive's terrain as pieces of `length` m of its path, one at a time (bounded memory):
    folder/piece_NNN.npz, each a terrain pair (docs/formats.md section 3) of its stretch with
    extras h_sim (the simulated H_b, as simulated.npz), arc0 (the path length before the
    piece's first pose, m) and grid_shape; returns how many. Cells near a piece's ends are in
    the next piece too, with the same values (both from the drive's tiles)."""
    import shutil

    from torchsoil.estimate.windows import path_arc, smooth_heightmap
    from torchsoil.io.trajectory import poses_to_rows

    if folder.exists():
        shutil.rmtree(folder)
    folder.mkdir(parents=True)
    stamps, poses = pipeline.trajectory()
    arc = path_arc(poses_to_rows(stamps, poses))
    cuts = np.unique(np.r_[np.searchsorted(arc, np.arange(0.0, arc[-1], length)), len(arc) - 1])
    for k, (a, b) in enumerate(zip(cuts[:-1], cuts[1:], strict=True)):
        piece = pipeline.terrain(stamps[a], stamps[b])
        h_sim = smooth_heightmap(np.asarray(piece.h_front, np.float64), front_smoothing) + stitch_tiles(piece, sims)
        keep = {"h_sim": h_sim.astype(np.float32), "arc0": np.float64(arc[a]),
                "grid_shape": np.asarray(piece.h_front.shape, np.int64)}
        TerrainPair(piece.dx, piece.origin, piece.h_front, piece.h_back, piece.poses, piece.wheels, piece.wheel_width,
                    piece.wheel_flat_fraction, keep, visit_front=piece.visit_front, visit_back=piece.visit_back,
                    visit_time=piece.visit_time).save(folder / f"piece_{k:03d}.npz")
        del piece, h_sim
        release()
    return len(cuts) - 1


def _param_names(robot: Robot) -> list[str]:
    from torchsoil.sim import ParamSpec

    return list(ParamSpec.base(robot.n_tracks).names)


