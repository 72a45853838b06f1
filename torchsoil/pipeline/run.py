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

from torchsoil.io.bag import Recording, count_messages, frame_name, read_recording, xyzrpy_matrix
from torchsoil.pipeline import gravity, icp, mapping
from torchsoil.pipeline.mapping import Sweep, build_map
from torchsoil.pipeline.raster import Accumulator, corridor
from torchsoil.pipeline.reregister import register_sweep
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
    of a robot YAML (FORMATS.md section 2), for `ReadConfig.extrinsics`. A key naming a topic
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


def fuse(front: list[Sweep], back: list[Sweep], period: float) -> tuple[list[Sweep], np.ndarray]:
    """Each front sweep merged with the back sweep nearest in time (within half a period; the
    first in `back` on a tie); returns fused sweeps (stamped like the front ones) and (S,) flags
    (MISSING_BACK)."""
    out, flags = [], np.zeros(len(front), dtype=np.int64)
    nearest = np.full(len(front), -1)
    if back:
        bstamps = np.array([b.stamp for b in back])
        order = np.argsort(bstamps, kind="stable")
        sb = bstamps[order]
        fstamps = np.array([f.stamp for f in front])
        hi = np.minimum(np.searchsorted(sb, fstamps), len(sb) - 1)  # first at or after
        lo = np.searchsorted(sb, sb[np.maximum(hi - 1, 0)])  # first of the stamp before
        d_lo, d_hi = np.abs(sb[lo] - fstamps), np.abs(sb[hi] - fstamps)
        pick = np.where((d_lo < d_hi) | ((d_lo == d_hi) & (order[lo] < order[hi])), lo, hi)
        nearest = np.where(np.abs(sb[pick] - fstamps) <= period / 2, order[pick], -1)
    for k, f in enumerate(front):
        j = int(nearest[k])
        if j < 0:
            out.append(f)
            flags[k] |= mapping.MISSING_BACK
            continue
        b = back[j]
        out.append(Sweep(f.stamp, np.concatenate([f.points, b.points]),
                         np.concatenate([f.t, b.t + (b.stamp - f.stamp)])))
    return out, flags


def _to_base(clouds, T: np.ndarray) -> list[Sweep]:
    """Sensor clouds -> sweeps in base_link (float64 points, transformed straight from the
    float32 ones without an intermediate copy)."""
    return [Sweep(c.stamp, icp.apply(T, c.xyz), c.t.astype(np.float64)) for c in clouds]


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
                progress: bool = False) -> PipelineResult:
    """Recording -> terrain pair (H_f, H_b on one grid, T_ref) with per-sweep flags.

    Args:
        bag_path: ROS 2 bag directory or ROS 1 file (FORMATS.md section 1).
        robot: wheel layout (written into the terrain pair; also bounds the ground each
            lidar may measure: ahead of the front wheels, behind the rear wheels).
        config: the pipeline section of the settings (torchsoil.settings.PipelineConfig).
        progress: show tqdm progress bars.
    Raises:
        BagError / ValueError naming the bag, topic or frame when the input is unusable;
        nothing is written by this function.
    """
    cfg = config or PipelineConfig()
    timings: dict[str, float] = {}
    bar = _bars(progress)
    t0 = time.perf_counter()
    total = count_messages(bag_path, [cfg.read.front_topic, cfg.read.back_topic]) \
        if progress else None
    rec = read_recording(bag_path, cfg.read.front_topic, cfg.read.back_topic, cfg.read.tf_topic,
                         cfg.read.base_frame, progress=bar("read", total), times=cfg.read.times,
                         imu_topic=cfg.read.imu_topic)
    ext = extrinsics_for(rec, cfg.read, {cfg.read.front_topic: rec.front[0].frame,
                                         cfg.read.back_topic: rec.back[0].frame})
    front = _to_base(rec.front, ext[cfg.read.front_topic])
    back = _to_base(rec.back, ext[cfg.read.back_topic])
    del rec.front[:], rec.back[:]
    timings["read"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    stamps = np.array([s.stamp for s in front])
    period = float(np.median(np.diff(stamps))) if len(stamps) > 1 else 0.1
    fused, flags = fuse(front, back, period)
    maps = build_map(fused, cfg.mapping, progress=bar("mapping", len(fused)))
    imu_T = None
    if rec.imu is not None and cfg.level.source in ("auto", "imu"):
        imu_T = extrinsics_for(rec, cfg.read, {rec.imu.topic: rec.imu.frame})[rec.imu.topic]
    R, notes = gravity.level(maps.stamps, maps.poses, maps.map_points, maps.map_normals, rec.imu, imu_T,
                             cfg.level)
    maps = mapping.rotate_world(maps, R)
    rec.problems.extend(notes)
    flags |= maps.flags
    del fused
    timings["mapping"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    target = icp.make_target(maps.map_points, cfg.mapping.normal_radius, maps.map_normals, 3 * cfg.mapping.voxel)
    ref_ok = (maps.flags & (mapping.POOR_FIT | mapping.EMPTY)) == 0
    ref_stamps, ref_poses = maps.stamps[ref_ok], maps.poses[ref_ok]
    grid, mask = corridor(ref_poses[:, :2, 3], cfg.raster.corridor_width, cfg.raster.dx)
    acc = {"front": Accumulator(grid, mask), "back": Accumulator(grid, mask)}
    wheel_x = robot.wheels[:, 0]
    edge = robot.wheel_width / 2 + cfg.raster.wheel_margin
    tick = bar("re-register", len(front) + len(back))
    keep_x = {"front": lambda x: x > wheel_x.max() + edge, "back": lambda x: x < wheel_x.min() - edge}

    def stream(name: str, sweeps: list[Sweep]):
        """Re-register and rasterize one stream; returns per-sweep fitness, rmse, accepted and
        the indices of empty sweeps."""
        n = len(sweeps)
        fit, rmse, ok = np.full(n, np.nan), np.full(n, np.nan), np.zeros(n, bool)
        empty = np.zeros(n, bool)
        for k, sw in enumerate(sweeps):
            tick(1)
            if len(sw.points) < 50:
                empty[k] = True
                continue
            pts, T, fit[k], rmse[k], ok[k], _ = register_sweep(
                sw.points, sw.t, sw.stamp, ref_stamps, ref_poses, target, cfg.reregister, period)
            if ok[k]:
                sel = np.linalg.norm(sw.points, axis=1) < cfg.raster.max_range
                sel &= keep_x[name](pts[:, 0])
                acc[name].add(icp.apply(T, pts[sel]))
        return fit, rmse, ok, empty

    # the two streams are independent: one thread each (KD-tree queries and numpy release
    # the interpreter lock)
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(max_workers=2) as pool:
        jobs = {name: pool.submit(stream, name, sweeps)
                for name, sweeps in (("front", front), ("back", back))}
        stats = {name: job.result() for name, job in jobs.items()}
    for name, sweeps, fail_bit in (("front", front, mapping.REREG_FRONT_FAILED),
                                   ("back", back, mapping.REREG_BACK_FAILED)):
        _, _, ok, empty = stats[name]
        for k, sw in enumerate(sweeps):
            j = int(np.argmin(np.abs(stamps - sw.stamp)))
            if empty[k]:
                flags[j] |= mapping.EMPTY
            elif not ok[k]:
                flags[j] |= fail_bit
    timings["reregister_raster"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    hf = acc["front"].heightmap(cfg.raster.fill_radius)
    hb = acc["back"].heightmap(cfg.raster.fill_radius)
    for name, hm in (("front", hf), ("back", hb)):
        if not hm.valid.any():
            kept = int(stats[name][2].sum())
            raise ValueError(f"{bag_path}: the {name} heightmap is empty ({kept} of "
                             f"{len(stats[name][2])} {name} sweeps re-registered, none with "
                             "ground in the corridor); nothing to write")
    extras = {
        "valid_front": hf.valid, "valid_back": hb.valid,
        "measured_front": hf.measured, "measured_back": hb.measured,
        "count_front": hf.count, "count_back": hb.count,
        "var_front": hf.var, "var_back": hb.var,
        "scan_stamps": stamps, "scan_flags": flags,
        "map_fitness": maps.fitness, "map_rmse": maps.rmse,
        "rereg_fitness_front": stats["front"][0], "rereg_rmse_front": stats["front"][1],
        "rereg_fitness_back": stats["back"][0], "rereg_rmse_back": stats["back"][1],
        "roi_mask": mask,
    }
    terrain = TerrainPair(grid.dx, np.array(grid.origin), hf.h, hb.h,
                          poses_to_rows(ref_stamps, ref_poses), robot.wheels, robot.wheel_width,
                          robot.wheel_flat_fraction, extras)
    timings["finish"] = time.perf_counter() - t0
    problems = list(rec.problems) + flagged_spans(stamps, flags, rec.start)
    for name in ("front", "back"):
        kept = stats[name][2].mean() if len(stats[name][2]) else 0.0
        if kept < 0.5:
            problems.append(f"only {kept:.0%} of the {name} sweeps were re-registered")
    return PipelineResult(terrain, maps, timings, problems, rec.duration)


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
    """Write `terrain.npz` (FORMATS.md section 3 + extras), `trajectory.csv` (t, x, y, z,
    roll, pitch, yaw of T_ref) and PNGs of H_f, H_b and H_delta (diverging colour map:
    blue excavation, red deposition). Each file is written to a temporary name first."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    tp = result.terrain
    paths = {"terrain": tp.save(out / "terrain.npz")}
    traj = out / "trajectory.csv"
    np.savetxt(traj.with_suffix(".tmp"), tp.poses, delimiter=",", fmt="%.9f",
               header="t,x,y,z,roll,pitch,yaw", comments="")
    traj.with_suffix(".tmp").replace(traj)
    paths["trajectory"] = traj
    x0, y0 = tp.origin
    X, Y = tp.h_front.shape
    extent = (y0 - tp.dx / 2, y0 + (Y - 0.5) * tp.dx, x0 - tp.dx / 2, x0 + (X - 0.5) * tp.dx)
    hd = tp.h_delta
    lim = float(np.nanpercentile(np.abs(hd), 99)) if np.isfinite(hd).any() else 0.01
    for name, h, kw in (("h_front", tp.h_front, {"cmap": "viridis"}),
                        ("h_back", tp.h_back, {"cmap": "viridis"}),
                        ("h_delta", hd, {"cmap": "RdBu_r", "vmin": -lim, "vmax": lim})):
        fig, ax = plt.subplots(figsize=(4, 8))
        im = ax.imshow(h, origin="lower", extent=extent, aspect="equal", **kw)
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
