"""The lidar pipeline as one call: a recording in, a terrain pair out (paper section III).

    result = process_bag("run.bag", robot, load_settings("my.yaml").pipeline)
    result.terrain.save("terrain.npz")

Stages: read (torchsoil.io.bag) -> fuse front + back in base_link -> reference map and
trajectory (mapping), levelled to gravity by the IMU or else the ground (gravity) ->
re-registration of each stream onto P_ref (reregister) -> corridor extraction and
rasterization (raster). Sweeps the stages could not use are flagged per
sweep (`scan_flags` in the output, bit names in `mapping.FLAG_NAMES`) and summarised in
`result.problems` with their times.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import NamedTuple

import numpy as np
import yaml
from scipy.spatial.transform import Rotation

from torchsoil.io.bag import Recording, count_messages, frame_name, stream_recording, xyzrpy_matrix
from torchsoil.pipeline import mapping
from torchsoil.pipeline.online import OnlinePipeline
from torchsoil.pipeline.resume import Checkpoints
from torchsoil.robot import Robot
from torchsoil.settings import PipelineConfig, ReadConfig
from torchsoil.terrain import TerrainPair


class PipelineResult(NamedTuple):
    """terrain: the terrain pair (with extras); mapping: the MappingResult (T_ref, P_ref);
    timings: seconds per stage; problems: messages naming flagged sweeps and times;
    duration: recording length, s."""

    terrain: TerrainPair
    mapping: mapping.MappingResult
    timings: dict[str, float]
    problems: list[str]
    duration: float


def extrinsics_for(rec: Recording, cfg: ReadConfig, streams: dict[str, str]) -> dict[str, np.ndarray]:
    """{topic: base_T_sensor (4, 4)} for streams {topic: frame_id}.

    Each topic's pose is, in this order: a cfg.extrinsics entry keyed by the topic, one keyed
    by its frame, the bag's transforms (/tf_static and /tf, chains composed). Topics and frames
    are compared without a leading slash. Raises ValueError naming the frame when no pose is
    known, and when two topics publish in one frame and are not both given per topic (the
    frame cannot tell them apart: one would silently get the other's pose).
    """
    given = {frame_name(k): xyzrpy_matrix(v) for k, v in cfg.extrinsics.items()}
    by_frame = {**rec.extrinsics, **given}
    out: dict[str, np.ndarray] = {}
    topic_of_frame: dict[str, str] = {}
    for topic, frame_id in streams.items():
        if frame_name(topic) in given:
            out[topic] = given[frame_name(topic)]
            continue
        frame = frame_name(frame_id)
        if frame in topic_of_frame:
            other = topic_of_frame[frame]
            raise ValueError(
                f"'{other}' and '{topic}' both publish in frame '{frame}', so the frame cannot tell "
                "their poses apart; give each topic its own extrinsic: in the robot YAML `lidars: "
                f"{{{other}: [x, y, z, roll, pitch, yaw], {topic}: [...]}}` ({cfg.base_frame}, m, rad) "
                "or `--extrinsic TOPIC X Y Z ROLL PITCH YAW`")
        topic_of_frame[frame] = topic
        if frame not in by_frame:
            raise ValueError(f"no extrinsic for frame '{frame}' of '{topic}': neither {cfg.tf_topic} nor /tf "
                             f"links it to '{cfg.base_frame}' (frames there: {sorted(rec.extrinsics)}) nor "
                             "does the configuration (read.extrinsics) or the robot YAML (lidars) give it "
                             "by frame or by topic")
        out[topic] = by_frame[frame]
    return out


def extrinsics_from_robot_yaml(path: str | Path) -> dict[str, list[float]]:
    """Optional `lidars: {frame or topic: [x, y, z, roll, pitch, yaw]}` (m, rad, in base_link)
    of a robot YAML (docs/formats.md section 2), for `ReadConfig.extrinsics`. A key naming a topic
    (`/lidar_back/points`) sets that topic's pose whatever its frame; the IMU's pose may be
    given the same way."""
    doc = yaml.safe_load(Path(path).read_text()) or {}
    out = {}
    for frame, v in (doc.get("lidars") or {}).items():
        try:
            out[str(frame)] = [float(x) for x in v]
            xyzrpy_matrix(out[str(frame)])
        except (TypeError, ValueError) as e:
            raise ValueError(f"{path}: lidars.{frame} must be [x, y, z, roll, pitch, yaw] "
                             f"in metres and radians ({e})") from None
    return out


def poses_to_rows(stamps: np.ndarray, poses: np.ndarray) -> np.ndarray:
    """(S,) times and (S, 4, 4) poses -> (S, 7) FORMATS rows t, x, y, z, roll, pitch, yaw."""
    rpy = Rotation.from_matrix(poses[:, :3, :3]).as_euler("xyz")
    return np.column_stack([stamps, poses[:, :3, 3], rpy])


def rows_to_poses(rows: np.ndarray) -> np.ndarray:
    """(S, 7) FORMATS rows -> (S, 4, 4) pose matrices."""
    P = np.zeros((len(rows), 4, 4))
    P[:, :3, :3] = Rotation.from_euler("xyz", rows[:, 4:]).as_matrix()
    P[:, :3, 3] = rows[:, 1:4]
    P[:, 3, 3] = 1.0
    return P


def flagged_spans(stamps: np.ndarray, flags: np.ndarray, t0: float) -> list[str]:
    """Human-readable runs of flagged sweeps: 'sweeps 40-75 (t = 4.00-7.50 s): degenerate'."""
    out = []
    for bit, name in mapping.FLAG_NAMES.items():
        if bit in (mapping.RETRIED, mapping.MAP_CONFLICT):   # registered after all; said by check_visits
            continue
        on = (flags & bit) != 0
        k = 0
        while k < len(on):
            if not on[k]:
                k += 1
                continue
            j = k
            while j + 1 < len(on) and on[j + 1]:
                j += 1
            out.append(f"sweeps {k}-{j} (t = {stamps[k] - t0:.2f}-{stamps[j] - t0:.2f} s after "
                       f"the start): {name}")
            k = j + 1
    return out


def process_bag(bag_path: str | Path, robot: Robot, config: PipelineConfig | None = None,
                progress: bool = False, spill_dir: str | Path | None = None,
                checkpoints: Checkpoints | None = None) -> PipelineResult:
    """Recording -> terrain pair (H_f, H_b on one grid, T_ref) with per-sweep flags: the
    streaming pipeline (torchsoil.pipeline.online) run over the recording to its end.

    Args:
        bag_path: ROS 2 bag directory or ROS 1 file (docs/formats.md section 1).
        robot: wheel layout (written into the terrain pair; also bounds the ground each
            lidar may measure: ahead of the front wheels, behind the rear wheels).
        config: the pipeline section of the settings (torchsoil.settings.PipelineConfig).
        progress: show a tqdm progress bar.
        spill_dir: directory for heightmap tiles far from the robot (bounded memory).
        checkpoints: where the pipeline's state is kept as it goes (`resume.Checkpoints`, its
            spill directory `spill_dir`); when it holds one, the run goes on from there.
    Raises:
        BagError / ValueError naming the bag, topic or frame when the input is unusable;
        nothing is written by this function.
    """
    cfg = config or PipelineConfig()
    bar = _bars(progress)
    total = count_messages(bag_path, [cfg.read.front_topic, cfg.read.back_topic]) if progress else None
    rec = Recording([], [])
    kept = checkpoints.load() if checkpoints is not None else None
    online, skip = kept if kept is not None else (OnlinePipeline(robot, cfg, rec, spill_dir), 0)
    t_read = time.perf_counter()
    for n, (name, item) in enumerate(stream_recording(
            bag_path, rec, cfg.read.front_topic, cfg.read.back_topic, cfg.read.tf_topic, cfg.read.base_frame,
            progress=bar("read", total), times=cfg.read.times, imu_topic=cfg.read.imu_topic)):
        if n < skip:                     # taken before the checkpoint the run resumed from
            continue
        if n == skip and kept is not None:
            rec.problems, online.rec = online.rec.problems, rec
        if name == "imu":
            online.add_imu(item)
        else:
            online.add_cloud(name, item)
        if checkpoints is not None and checkpoints.due():
            checkpoints.save(online, n + 1)
    online.finish()
    return finish_result(online, rec, bag_path, time.perf_counter() - t_read)


def finish_result(online: OnlinePipeline, rec: Recording, bag_path, wall: float) -> PipelineResult:
    """The whole drive's terrain pair, mapping result, timings and problems of a finished
    OnlinePipeline."""
    t0 = time.perf_counter()
    terrain = online.terrain()
    for name, key in (("front", "valid_front"), ("back", "valid_back")):
        if not terrain.extras[key].any():
            ok = online.stats[name]["ok"]
            raise ValueError(f"{bag_path}: the {name} heightmap is empty ({int(np.sum(ok))} of {len(ok)} {name} "
                             "sweeps re-registered, none with ground in the corridor); nothing to write")
    maps = online.mapping_result()
    extras = {"map_fitness": maps.fitness, "map_rmse": maps.rmse}
    for name in ("front", "back"):
        st = online.stats[name]
        extras[f"rereg_fitness_{name}"] = np.asarray(st["fitness"], np.float64)
        extras[f"rereg_rmse_{name}"] = np.asarray(st["rmse"], np.float64)
    terrain.extras.update(extras)
    timings = dict(online.timings)
    timings["finish"] = time.perf_counter() - t0
    timings["read"] = max(wall - sum(timings.values()), 0.0)
    stamps, flags = terrain.extras["scan_stamps"], terrain.extras["scan_flags"]
    conflicts = check_visits(terrain, online.cfg.mapping.max_visit_shift, rec.start)
    problems = list(rec.problems) + conflicts + flagged_spans(stamps, flags, rec.start)
    for name in ("front", "back"):
        ok = online.stats[name]["ok"]
        kept = float(np.mean(ok)) if len(ok) else 0.0
        if kept < 0.5:
            problems.append(f"only {kept:.0%} of the {name} sweeps were re-registered")
    return PipelineResult(terrain, maps, timings, problems, rec.duration)


def check_visits(terrain: TerrainPair, max_shift: float, t_start: float = 0.0) -> list[str]:
    """Ground driven more than once, checked: the state between visits as the way out left it
    (`visit_back[v]`) and as the way back finds it (`visit_front[v + 1]`) must lie on the same
    cells (`visits.visit_offsets`). Where they lie more than `max_shift` m apart, the map broke
    between the visits: the sweeps of the later visit over that ground get MAP_CONFLICT (their
    windows are flagged) and a problem says so. Writes `visit_shift` (V - 1, 2) [m] into the
    extras. Returns the problems."""
    from torchsoil.visits import visit_offsets

    offsets = visit_offsets(terrain)
    if not offsets:
        return []
    shifts = np.zeros((terrain.visit_front.shape[0] - 1, 2))
    stamps, flags = terrain.extras["scan_stamps"], terrain.extras["scan_flags"]
    problems = []
    for off in offsets:
        shifts[off["visit"] - 1] = off["shift_m"]
        if off["distance_m"] > max_shift:
            flags[(stamps >= off["t0"]) & (stamps <= off["t1"])] |= mapping.MAP_CONFLICT
            problems.append(
                f"the ground between visits {off['visit'] - 1} and {off['visit']} lies "
                f"{100 * off['distance_m']:.0f} cm from where the earlier visit left it (seen again at "
                f"t = {off['t0'] - t_start:.1f}-{off['t1'] - t_start:.1f} s after the start): the map broke "
                "between the visits, so the ruts would double there; its windows are flagged (map_conflict)")
    terrain.extras["visit_shift"] = shifts
    return problems


def _bars(enabled: bool):
    """Factory of progress callbacks: bar(name, total) -> callable(n)."""
    if not enabled:
        return lambda name, total: (lambda n: None)
    from tqdm.auto import tqdm

    def make(name, total):
        b = tqdm(total=total, desc=name, unit="msg" if name == "read" else "sweep", leave=False)
        return b.update

    return make


def write_outputs(result: PipelineResult, out_dir: str | Path) -> dict[str, Path]:
    """Write `terrain.npz` (docs/formats.md section 3 + extras), `trajectory.csv` (t, x, y, z,
    roll, pitch, yaw of T_ref) and PNGs of H_f, H_b and H_delta (diverging colour map:
    blue excavation, red deposition). Each file is written to a temporary name first."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from torchsoil.figures import coarse, coarse_extent

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    tp = result.terrain
    paths = {"terrain": tp.save(out / "terrain.npz")}
    traj = out / "trajectory.csv"
    np.savetxt(traj.with_suffix(".tmp"), tp.poses, delimiter=",", fmt="%.9f",
               header="t,x,y,z,roll,pitch,yaw", comments="")
    traj.with_suffix(".tmp").replace(traj)
    paths["trajectory"] = traj
    hd = tp.h_delta
    lim = float(np.nanpercentile(np.abs(hd), 99)) if np.isfinite(hd).any() else 0.01
    for name, h, kw in (("h_front", tp.h_front, {"cmap": "viridis"}),
                        ("h_back", tp.h_back, {"cmap": "viridis"}),
                        ("h_delta", hd, {"cmap": "RdBu_r", "vmin": -lim, "vmax": lim})):
        fig, ax = plt.subplots(figsize=(4, 8))
        h, f = coarse(h)
        x0, x1, y0, y1 = coarse_extent(tp.origin, tp.dx, tp.h_front.shape, f)
        im = ax.imshow(h, origin="lower", extent=(y0, y1, x0, x1), aspect="equal", **kw)
        ax.plot(tp.poses[:, 2], tp.poses[:, 1], "k-", lw=0.5)
        ax.set_xlabel("y [m]")
        ax.set_ylabel("x [m]")
        ax.set_title({"h_front": "H_f (before)", "h_back": "H_b (after)",
                      "h_delta": "H_delta = H_b - H_f"}[name])
        fig.colorbar(im, ax=ax, label="m")
        png = out / f"{name}.png"
        fig.savefig(png.with_suffix(".tmp.png"), dpi=120, bbox_inches="tight")
        plt.close(fig)
        png.with_suffix(".tmp.png").replace(png)
        paths[name] = png
    return paths
