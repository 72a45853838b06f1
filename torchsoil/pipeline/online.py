"""The lidar pipeline fed sweep by sweep, in bounded memory (paper section III, online).

`OnlinePipeline` takes decoded sweeps of both lidars (and IMU samples) as they arrive:
front and back are fused and registered into the reference map and trajectory (mapping.Mapper),
the world frame is levelled once the first seconds are in (gravity), and each stream's sweep
is re-registered onto the reference map near it (reregister) and rasterized into tiles of a
fixed lattice (raster.Tiles) as soon as the trajectory around it is known. Ground driven more
than once keeps every visit: the registered path feeds a per-cell visit tracker
(visit_tracker), and each point goes to the tiles of its cell's visit (one layer per visit and
stream). Nothing else is kept: sweeps are dropped once rasterized, and with a spill directory
the tiles far from the robot go to disk. `terrain(...)` assembles a terrain pair of any stretch
(or the whole drive) from the tiles; `process_bag` is this pipeline run over a recording to
its end.
"""

from __future__ import annotations

import bisect
import os
import time
from collections import defaultdict
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from torchsoil.io.bag import ImuSample, Recording, imu_data
from torchsoil.io.pointcloud import Cloud
from torchsoil.io.terrain_pair import TerrainPair
from torchsoil.pipeline import _kernels as _k
from torchsoil.pipeline import gravity, icp, mapping
from torchsoil.pipeline.mapping import Mapper, Sweep
from torchsoil.pipeline.raster import Heightmap, Tiles, corridor
from torchsoil.pipeline.reregister import register_sweep
from torchsoil.pipeline.visit_tracker import VisitTracker, visit_gap, visit_reach
from torchsoil.robot import Robot
from torchsoil.settings import PipelineConfig

STREAMS = ("front", "back")
REF_OK = ~(mapping.POOR_FIT | mapping.EMPTY)
IMU_WAIT = 3.0   # s: how long a sweep waits for a late IMU's samples (beyond, the IMU is taken as silent)


_POOL: dict[int, ThreadPoolExecutor] = {}


def _stream_pool() -> ThreadPoolExecutor:
    """The lasting worker thread that re-registers the front stream (OnlinePipeline._reregister),
    one per process (a forked child does not inherit the parent's thread)."""
    pid = os.getpid()
    if pid not in _POOL:
        _POOL.clear()
        _POOL[pid] = ThreadPoolExecutor(max_workers=1, thread_name_prefix="rereg-front")
    return _POOL[pid]


class OnlinePipeline:
    """Sweeps in, rasterized ground out, as the robot drives.

    Args:
        robot: wheel layout (bounds the ground each lidar may measure).
        cfg: the pipeline settings.
        rec: the recording's state as read so far: `extrinsics` (frame -> (4, 4), updated as
            transforms arrive) and `problems` (torchsoil.io.bag.Recording).
        spill_dir: directory for tiles far from the robot (None: all kept in memory).
    Feed `add_cloud("front" | "back", cloud)` and `add_imu(sample)` in arrival order, then
    `finish()`. `ground_stamp` is the time of the last back sweep rasterized: the ground
    behind the robot at that time is measured before and after.

    Visits: `visits` (VisitTracker) follows the registered path (levelled like the tiles). A
    front point at time t on a cell goes to front layer v = the visits of the cell base_link
    had passed closest by t (the surface before visit v), a back point to back layer v - 1
    (the surface after visit v - 1); `tiles[stream][v]` holds layer v. A back point on ground
    no visit has passed yet (v = 0: the back lidar looking across at a row still to be driven)
    goes to `tiles["back_before"][0]`, the H_b of ground never visited: mixed into back layer
    0 it would blend the surface before the first visit into the one after it.
    """

    def __init__(self, robot: Robot, cfg: PipelineConfig, rec: Recording, spill_dir=None):
        self.robot, self.cfg, self.rec = robot, cfg, rec
        self.topics = {"front": cfg.read.front_topic, "back": cfg.read.back_topic}
        self.ext: dict[str, np.ndarray] | None = None
        self.held: list[tuple[str, Cloud]] = []          # clouds waiting for their extrinsics
        self.frames: dict[str, str] = {}
        self.front_wait: list[Sweep] = []                # front sweeps waiting for a back partner
        self.back_pool: list[Sweep] = []                 # recent back sweeps, fusion partners
        self.back_wait: list[Sweep] = []                 # back sweeps not yet known to have a front partner
        self.last_front = self.mapped_front = -np.inf    # stamps, s
        self.imu_last = -np.inf                          # the latest IMU sample's time, s
        self.queue: dict[str, list[Sweep]] = {n: [] for n in STREAMS}  # waiting for re-registration
        self.period: float | None = None
        self.first_stamps: list[float] = []
        self.mapper: Mapper | None = None
        self.fuse_flags: list[int] = []
        self.imu: list[ImuSample] = []
        self.gyro = mapping.Gyro()                       # rate gyro in base_link, for the mapper
        self.gyro_R: np.ndarray | None = None            # base_link <- IMU rotation
        self.gyro_early: list[ImuSample] = []            # samples before the IMU's transform was known
        self.L: np.ndarray | None = None                 # levelling (4, 4)
        self.D = np.eye(3)                               # its later correction (gravity_and_bias)
        self.refined = False
        self.ok_stamps: list[float] = []
        self.ok_poses: list[np.ndarray] = []
        self.spill_dir = spill_dir
        self.tiles: dict[str, list[Tiles]] = {n: [] for n in (*STREAMS, "back_before")}  # one per visit layer
        rc = cfg.raster
        self.visits = VisitTracker(rc.dx, visit_reach(robot, rc.visit_margin),
                                   rc.visit_gap if rc.visit_gap is not None else visit_gap(robot),
                                   spill_dir=None if spill_dir is None else f"{spill_dir}/visits")
        self.n_tracked = 0                               # ok poses fed to the visit tracker
        self.stats = {n: defaultdict(list) for n in STREAMS}
        self.target: icp.Target | None = None
        self.target_at = (np.full(3, np.inf), 0)
        self.timings: dict[str, float] = defaultdict(float)
        self.ground_stamp = -np.inf
        self.on_ground = None    # called (no arguments) each time a sweep's mapping rasterized new back ground
        self.keep_every = 1      # one sweep in keep_every is fed (a live node behind thins them): no gap
        self.n_final = 0
        self.finished = False
        edge = robot.wheel_width / 2 + cfg.raster.wheel_margin
        self.keep_beyond = {"front": robot.wheels[:, 0].max() + edge, "back": robot.wheels[:, 0].min() - edge}

    # ------------------------------------------------------------------ input
    def add_cloud(self, name: str, cloud: Cloud) -> None:
        """One decoded sweep of stream `name` (sweep-start stamp, sensor frame)."""
        if self.ext is None:
            self.held.append((name, cloud))
            self.frames.setdefault(name, cloud.frame)
            if not self._resolve(final=False):
                return
            self._start_gyro()          # the transforms have come: the IMU's too, before the sweeps are mapped
            held, self.held = self.held, []
            for n, c in held:
                self._take(n, c)
            return
        self._take(name, cloud)

    def add_imu(self, sample: ImuSample) -> None:
        before, self.imu_last = self.imu_last, max(self.imu_last, sample.t)
        if not self.refined:
            self.imu.append(sample)
        if self.gyro_R is None:
            self.gyro_early.append(sample)
            del self.gyro_early[:-1000]
            self._start_gyro()
            return
        self.gyro.add(sample.t, self.gyro_R @ np.asarray(sample.gyro, np.float64))
        if self.front_wait and self.mapper is not None and before < self.front_wait[0].stamp <= self.imu_last:
            self._fuse(final=False)      # the oldest waiting sweep may have waited for this sample

    def _imu_behind(self, t: float) -> bool:
        """Whether the IMU, whose samples are coming, has not reached time t [s] yet: what is
        done at t then waits for it, so that the result does not depend on whether the IMU's
        messages came before or after the lidars' (on a live graph they race). An IMU more
        than IMU_WAIT s behind the front lidar is silent, not late: nothing waits for it."""
        return -np.inf < self.imu_last < t and self.last_front - self.imu_last < IMU_WAIT

    def _start_gyro(self) -> None:
        """The rate gyro from the samples that waited for the IMU's transform, once it is known."""
        if self.gyro_R is not None or not self.gyro_early:
            return
        try:
            self.gyro_R = self._imu_pose(self.gyro_early[-1])[:3, :3]
        except ValueError:         # its transform not known yet: the samples wait for it (the last 1000)
            return
        early, self.gyro_early = self.gyro_early, []
        for s in early:
            self.gyro.add(s.t, self.gyro_R @ np.asarray(s.gyro, np.float64))

    def finish(self) -> None:
        """The end of the recording: everything still held is registered and rasterized."""
        if self.ext is None:
            self._resolve(final=True)
            held, self.held = self.held, []
            for n, c in held:
                self._take(n, c)
        self._fuse(final=True)
        if self.mapper is None:
            raise ValueError("no front sweep with points: nothing to map")
        t0 = time.perf_counter()
        for k in self.mapper.finish():
            self._final(k)
        self.mapper.check_degenerate()
        self.timings["mapping"] += time.perf_counter() - t0
        self._level(final=True)
        self._refine(final=True)
        self._reregister(final=True)
        self.finished = True

    def _resolve(self, final: bool) -> bool:
        """Both streams' extrinsics, once both have a sweep and the transforms are known;
        raises the reason when still unknown after 50 sweeps or at the end."""
        from torchsoil.io.extrinsics import extrinsics_for

        if len(self.frames) < 2 and not final:
            return False
        if len(self.frames) < 2:
            missing = [self.topics[n] for n in STREAMS if n not in self.frames]
            raise ValueError(f"no sweep could be read on {missing}")
        try:
            ext = extrinsics_for(self.rec, self.cfg.read, {self.topics[n]: self.frames[n] for n in STREAMS})
        except ValueError:
            if final or len(self.held) > 50:
                raise
            return False
        self.ext = {n: ext[self.topics[n]] for n in STREAMS}
        return True

    def _take(self, name: str, cloud: Cloud) -> None:
        T = self.ext[name]
        sw = Sweep(cloud.stamp, icp.apply(T, cloud.xyz), cloud.t.astype(np.float64))
        q = self.queue[name]
        if q and sw.stamp <= q[-1].stamp:
            self.rec.problems.append(f"{self.topics[name]} sweep at t={sw.stamp:.3f} s out of order: skipped")
            return
        q.append(sw)
        if name == "front":
            self.front_wait.append(sw)
            self.last_front = sw.stamp
            if len(self.first_stamps) < 6:
                self.first_stamps.append(sw.stamp)
        else:
            self.back_pool.append(sw)
            self.back_wait.append(sw)
        self._fuse(final=False)

    # ----------------------------------------------------------------- stages
    def _fuse(self, final: bool) -> None:
        """Each front sweep with the back sweep nearest in time (within half a period), once no
        nearer one can come, into the mapper; a back sweep with no front sweep within 1.5
        periods either way once the front has started (the front lidar silent or frozen) goes in
        alone, so the map and the trajectory go on. Sweeps enter the mapper in time order."""
        if self.period is None:
            if len(self.first_stamps) < 6 and not final:
                return
            steps = np.diff(self.first_stamps)
            self.period = float(np.median(steps)) if len(steps) else 0.1
        P = self.period
        while self.front_wait or self.back_wait:
            f = self.front_wait[0] if self.front_wait else None
            b = self.back_wait[0] if self.back_wait else None
            if b is not None and (f is None or b.stamp < f.stamp):
                # b's front partners are mapped, f, or later: decided once a front came after it
                if f is None and not (final or self.last_front >= b.stamp + 1.5 * P or len(self.back_wait) >= 10):
                    return
                self.back_wait.pop(0)
                # alone only inside a silence of the front lidar (not before its first sweep, nor a
                # back sweep stamped a period off by its driver's convention)
                alone = (self.mapped_front > -np.inf and b.stamp - self.mapped_front > 1.5 * P
                         and (f is None or f.stamp - b.stamp > 1.5 * P))
                if alone:
                    self._map(b, mapping.MISSING_FRONT)
                continue
            waiting = not any(b.stamp >= f.stamp + P / 2 for b in self.back_pool[-3:])
            if not final and waiting and len(self.front_wait) < 10:   # a silent back lidar holds 1 s at most
                return
            if not final and self._imu_behind(f.stamp) and f.stamp > self.last_front - IMU_WAIT:   # gyro up to f
                return
            self.front_wait.pop(0)
            self.mapped_front = f.stamp
            near = [b for b in self.back_pool if abs(b.stamp - f.stamp) <= P / 2]
            flag = 0
            if near:
                b = min(near, key=lambda b: abs(b.stamp - f.stamp))
                f = Sweep(f.stamp, np.concatenate([f.points, b.points]),
                          np.concatenate([f.t, b.t + (b.stamp - f.stamp)]))
            else:
                flag = mapping.MISSING_BACK
            self.back_pool = [b for b in self.back_pool if b.stamp > f.stamp - P]
            self._map(f, flag)

    def _map(self, sweep: Sweep, flag: int) -> None:
        t0 = time.perf_counter()
        if self.mapper is None:
            self.mapper = Mapper(self.cfg.mapping, self.period)
            self.mapper.gyro = self.gyro
        self.mapper.spacing = self.period * self.keep_every
        self.fuse_flags.append(flag)
        done = self.mapper.add(sweep)
        self.timings["mapping"] += time.perf_counter() - t0
        for k in done:
            self._final(k)
        self._level(final=False)
        self._refine(final=False)
        ground = self.ground_stamp
        self._reregister(final=False)
        if self.on_ground is not None and self.ground_stamp != ground:
            self.on_ground()

    def _final(self, k: int) -> None:
        m = self.mapper
        self.n_final = k + 1
        if m.flags[k] & (mapping.POOR_FIT | mapping.EMPTY) == 0:
            self.ok_stamps.append(m.stamps[k])
            self.ok_poses.append(m.poses[k])

    def _level(self, final: bool) -> None:
        """The levelling rotation, once the first `level.window` s are registered (with an IMU)
        or the robot is `level.radius` m from the start (by the ground), or at the end."""
        if self.L is not None or not self.ok_poses:
            return
        cfg, m = self.cfg.level, self.mapper
        imu = imu_data(self.imu) if self.imu else None
        use_imu = imu is not None and cfg.source in ("auto", "imu")
        if not final:
            if cfg.source == "none":
                pass
            elif use_imu and (self.ok_stamps[-1] < self.ok_stamps[0] + cfg.window + 2 * self.period
                              or self._imu_behind(self.ok_stamps[0] + cfg.window + 2 * self.period)):
                return
            elif not use_imu and np.linalg.norm(self.ok_poses[-1][:2, 3]) < cfg.radius:
                return
        t0 = time.perf_counter()
        imu_T = self._imu_pose(imu) if use_imu else None
        pts, views = m.local.global_map()
        normals = np.zeros_like(pts)
        if cfg.source in ("auto", "ground") and not use_imu and len(pts):
            from scipy.spatial import cKDTree

            normals, _ = icp.pca_normals(pts, cKDTree(pts), pts, radius=self.cfg.mapping.normal_radius)
        R, notes = gravity.level(np.asarray(self.ok_stamps), np.asarray(self.ok_poses), pts, normals, imu, imu_T,
                                 cfg)
        self.rec.problems.extend(notes)
        self.L = np.eye(4)
        self.L[:3, :3] = R
        if not use_imu or cfg.bias_window <= 0:
            self.imu, self.refined = [], True
        self.timings["mapping"] += time.perf_counter() - t0

    def _refine(self, final: bool) -> None:
        """Gravity and the accelerometer's bias from the first `level.bias_window` s of IMU
        samples (gravity.gravity_and_bias), once the trajectory covers them or at the end: the
        correction D of the levelling turns the trajectory, P_ref and the heightmaps from then on."""
        cfg = self.cfg.level
        if self.refined or self.L is None or not self.imu:
            return
        if not final and (self.ok_stamps[-1] < self.ok_stamps[0] + cfg.bias_window
                          or self._imu_behind(self.ok_stamps[0] + cfg.bias_window)):
            return
        imu = imu_data(self.imu)
        imu_T = self._imu_pose(imu)
        self.imu, self.refined = [], True
        stamps, poses = np.asarray(self.ok_stamps), np.asarray(self.ok_poses)
        try:
            g, bias, turn = gravity.gravity_and_bias(stamps, poses, imu, imu_T, cfg.bias_window)
        except ValueError:
            return                                   # too short: the first levelling stands
        self.D = gravity.levelling_rotation(g) @ self.L[:3, :3].T
        if not bias.any():                           # too straight a start to tell the bias
            self.rec.problems.append(
                f"the robot turned by {turn:.0f} deg over the IMU's first {cfg.bias_window:g} s: too little to tell "
                "the accelerometer's bias from a tilt, so the map is levelled to within its horizontal bias / g "
                "(0.057 deg per mg; a turn early in the drive removes this)")

    def _imu_pose(self, imu) -> np.ndarray:
        """(4, 4) the IMU's pose in base_link, looked up like a lidar's."""
        from torchsoil.io.extrinsics import extrinsics_for

        return extrinsics_for(self.rec, self.cfg.read, {imu.topic: imu.frame})[imu.topic]

    def _reregister(self, final: bool) -> None:
        """Re-register and rasterize every queued sweep whose time the trajectory now covers:
        the two streams at once (the front's on a worker thread; the compiled loops release
        the interpreter lock), each stream's sweeps in their order. Each sweep's pose window
        and target are taken first, in the order of one stream after the other, so the result
        does not depend on the threads."""
        if self.L is None or not self.ok_stamps:
            return
        t0 = time.perf_counter()
        self._track()
        jobs = {}
        for name in STREAMS:
            q, jobs[name] = self.queue[name], []
            while q and (final or q[0].stamp + self.period <= self.ok_stamps[-1]):
                jobs[name].append(self._job(q.pop(0)))
        if jobs["front"] and jobs["back"]:
            front = _stream_pool().submit(self._rasterize_all, "front", jobs["front"])
            self._rasterize_all("back", jobs["back"])
            front.result()
        else:
            for name in STREAMS:
                self._rasterize_all(name, jobs[name])
        if self.spill_dir is not None and self.n_final % 50 == 0:
            self._bound_memory()
        self.timings["reregister_raster"] += time.perf_counter() - t0

    def _track(self) -> None:
        """The registered poses not yet fed to the visit tracker, in the tiles' frame (L)."""
        if self.n_tracked < len(self.ok_poses):
            xyz = np.asarray(self.ok_poses[self.n_tracked:])[:, :3, 3]
            self.visits.add(self.ok_stamps[self.n_tracked:], xyz @ self.L[:2, :3].T)
            self.n_tracked = len(self.ok_poses)

    def _layer(self, name: str, v: int) -> Tiles:
        """Stream `name`'s tiles of visit layer v (made, with the layers below, when missing)."""
        layers = self.tiles.setdefault(name, [])        # (a checkpoint of before back_before has none)
        while len(layers) <= v:
            k = len(layers)
            sub = name if k == 0 else f"{name}_visit{k}"
            layers.append(Tiles(self.cfg.raster.dx, spill_dir=None if self.spill_dir is None else
                                f"{self.spill_dir}/{sub}"))
        return layers[v]

    def _bound_memory(self) -> None:
        """Tiles beyond the raster range (plus a corridor) of the robot's last second go to disk;
        reference-map voxels beyond the mapper's and the re-registration's reach are dropped."""
        xy = np.asarray(self.ok_poses[-10:])[:, :2, 3]
        radius = self.cfg.raster.max_range + self.cfg.raster.corridor_width
        for tiles in (*(t for layers in self.tiles.values() for t in layers), self.visits):
            tiles.spill(xy @ self.L[:2, :2].T, radius)
        reach = max(self.cfg.mapping.map_radius, self.cfg.reregister.max_range + 2.0) + 10.0
        self.mapper.local.forget(xy, reach)

    def _job(self, sw: Sweep) -> tuple:
        """(sweep, its stamps (K,) and poses (K, 4, 4) of T_ref around it, target), the
        target None for a sweep of fewer than 50 points (not registered)."""
        if len(sw.points) < 50:
            return sw, None, None, None
        i = max(bisect.bisect_left(self.ok_stamps, sw.stamp - 3 * self.period) - 1, 0)
        j = bisect.bisect_right(self.ok_stamps, sw.stamp + 3 * self.period) + 1
        stamps, poses = np.asarray(self.ok_stamps[i:j]), np.asarray(self.ok_poses[i:j])
        seed = poses[int(np.argmin(np.abs(stamps - sw.stamp)))]
        return sw, stamps, poses, self._target(seed[:3, 3])

    def _rasterize_all(self, name: str, jobs: list[tuple]) -> None:
        for job in jobs:
            self._rasterize(name, *job)

    def _rasterize(self, name: str, sw: Sweep, stamps, poses, target) -> None:
        """One sweep of stream `name` re-registered onto `target` and rasterized (touches only
        that stream's stats and tiles, and `ground_stamp` for the back stream)."""
        st = self.stats[name]
        st["stamp"].append(sw.stamp)
        if target is None:
            st["fitness"].append(np.nan), st["rmse"].append(np.nan), st["ok"].append(False), st["empty"].append(True)
            return
        pts, T, fit, rmse, ok, _ = register_sweep(sw.points, sw.t, sw.stamp, stamps, poses, target,
                                                  self.cfg.reregister, self.period)
        st["fitness"].append(fit), st["rmse"].append(rmse), st["ok"].append(ok), st["empty"].append(False)
        if not ok:
            return
        x = pts[:, 0]       # each lidar's ground: ahead of the front wheels, behind the rear ones
        beyond = x > self.keep_beyond[name] if name == "front" else x < self.keep_beyond[name]
        sel = _k.within_range(sw.points, float(self.cfg.raster.max_range))
        sel = sel[beyond[sel]]
        self._route(name, icp.apply(self.L @ T, pts[sel]), sw.stamp + sw.t[sel])
        if name == "back":
            self.ground_stamp = sw.stamp

    def _route(self, name: str, world: np.ndarray, t: np.ndarray) -> None:
        """Stream `name`'s (N, 3) points [m, the tiles' frame] measured at times t (N,) [s] into
        their visit layers (class docstring): front layer v before visit v, back layer v after
        it, back_before where no visit had passed yet (the path must be tracked beyond t)."""
        layer = self.visits.passed(world[:, :2], t)
        if name == "back":                    # ground no visit has passed yet: back_before
            before = layer == 0
            self._layer("back_before", 0).add(world[before])
            world, layer = world[~before], layer[~before] - 1
        for v in range(int(layer.max(initial=0)) + 1):
            self._layer(name, v).add(world if v == 0 and not layer.any() else world[layer == v])

    def _target(self, center: np.ndarray) -> icp.Target:
        """The reference map near `center` (mapper frame), rebuilt every metre or 10 sweeps."""
        at, n = self.target_at
        if self.target is None or np.linalg.norm(center - at) > 1.0 or self.n_final - n >= 10:
            radius = self.cfg.reregister.max_range + 2.0
            self.target = self.mapper.local.reference(center, radius)
            self.target_at = (center.copy(), self.n_final)
        return self.target

    # ----------------------------------------------------------------- output
    def trajectory(self) -> tuple[np.ndarray, np.ndarray]:
        """T_ref so far, levelled: stamps (S,) s and poses (S, 4, 4) of the sweeps the mapper
        registered (not poor fits nor empty)."""
        poses = np.asarray(self.ok_poses).reshape(-1, 4, 4)
        return np.asarray(self.ok_stamps), self._world() @ poses

    def _world(self) -> np.ndarray:
        """(4, 4) rotation from the mapper's world to the levelled one: D L (identity before
        the first levelling)."""
        W = np.eye(4)
        if self.L is not None:
            W[:3, :3] = self.D @ self.L[:3, :3]
        return W

    def scan_flags(self) -> tuple[np.ndarray, np.ndarray]:
        """Stamps (S,) and flags (S,) of every mapped sweep: the mapper's, the fusion's and the
        re-registration's (a stream's failed or empty sweep flags the mapped sweep nearest in time)."""
        m = self.mapper
        n = self.n_final
        stamps = np.asarray(m.stamps[:n])
        flags = np.asarray(m.flags[:n], np.int64) | np.asarray(self.fuse_flags[:n], np.int64)
        for name, bit in (("front", mapping.REREG_FRONT_FAILED), ("back", mapping.REREG_BACK_FAILED)):
            st = self.stats[name]
            if not st["stamp"] or not n:
                continue
            s = np.asarray(st["stamp"])
            j = np.clip(np.searchsorted(stamps, s), 1, max(n - 1, 1))
            j = np.where(np.abs(stamps[j - 1] - s) <= np.abs(stamps[np.minimum(j, n - 1)] - s), j - 1,
                         np.minimum(j, n - 1))
            empty, ok = np.asarray(st["empty"]), np.asarray(st["ok"])
            np.bitwise_or.at(flags, j[empty], mapping.EMPTY)
            np.bitwise_or.at(flags, j[~empty & ~ok], bit)
        return stamps, flags

    def terrain(self, t0: float = -np.inf, t1: float = np.inf) -> TerrainPair:
        """The terrain pair of the stretch driven between t0 and t1 (s; default: all so far): the
        corridor around that part of T_ref, H_f and H_b from the tiles, poses and per-sweep flags
        of the stretch as extras (docs/formats.md section 3).

        H_f is the first view (front layer 0); H_b per cell the back layer of its last visit
        (back_before where never visited). Where a cell of the grid was visited twice or more, the
        visit layers too: `visit_front`, `visit_back` (V, X, Y) float32 [m] and `visit_time`
        (V, X, Y) float64 [s, the poses' clock], NaN where a cell has fewer than v + 1 visits.
        The extras valid/measured/count/var_front and _back are those of H_f and H_b."""
        stamps, poses = self.trajectory()
        sel = (stamps >= t0) & (stamps <= t1)
        if sel.sum() < 2:
            raise ValueError(f"fewer than two registered poses between t = {t0:.2f} and {t1:.2f} s")
        stamps, poses = stamps[sel], poses[sel]
        rc = self.cfg.raster
        grid, mask = corridor(poses[:, :2, 3], rc.corridor_width, rc.dx)
        i0, j0 = (int(round(o / rc.dx)) for o in grid.origin)
        (I, J), n = grid.shape, np.zeros(grid.shape, np.int32)                 # visits per cell
        for a in range(0, I, 256):                                             # a block of rows at a time
            n[a:a + 256] = np.isfinite(self.visits.region(i0 + a, i0 + min(a + 256, I), j0, j0 + J)[1]).sum(0)
        n[~mask] = 0
        V = max(int(n.max()), 1)
        xs, ys = grid.centers()

        def layer(name: str, v: int) -> Heightmap:
            h = self._layer(name, v).heightmap(grid, mask, rc.fill_radius)
            if np.array_equal(self.D, np.eye(3)):
                return h
            d = self.D                                   # tiles hold heights levelled by L: turn by D
            return h._replace(h=(h.h + d[2, 0] * xs[:, None] + d[2, 1] * ys[None, :] + (d[2, 2] - 1) * h.h).astype(
                np.float32))

        fronts = [layer("front", v) for v in range(V)]
        backs = [layer("back", v) for v in range(V)]
        hf = fronts[0]
        last = np.maximum(n - 1, 0)[None]
        hb = Heightmap(*(np.take_along_axis(np.stack(f), last, 0)[0] for f in zip(*backs, strict=True)))
        before = layer("back_before", 0)             # never visited: the back lidar's view across
        take = (n == 0) & before.valid
        hb = Heightmap(*(np.where(take, b, a) for a, b in zip(hb, before, strict=True)))
        visits = {}
        if V > 1:
            there = n[None] > np.arange(V)[:, None, None]
            times = self.visits.region(i0, i0 + I, j0, j0 + J)[1][:V]
            visits = {"visit_front": np.where(there, np.stack([h.h for h in fronts]), np.nan).astype(np.float32),
                      "visit_back": np.where(there, np.stack([h.h for h in backs]), np.nan).astype(np.float32),
                      "visit_time": np.where(there, times, np.nan)}
        scan_stamps, flags = self.scan_flags()
        keep = (scan_stamps >= stamps[0] - 1.0) & (scan_stamps <= stamps[-1] + 1.0)
        extras = {"valid_front": hf.valid, "valid_back": hb.valid,
                  "measured_front": hf.measured, "measured_back": hb.measured,
                  "count_front": hf.count, "count_back": hb.count, "var_front": hf.var, "var_back": hb.var,
                  "scan_stamps": scan_stamps[keep], "scan_flags": flags[keep], "roi_mask": mask}
        from torchsoil.io.trajectory import poses_to_rows

        return TerrainPair(grid.dx, np.array(grid.origin), hf.h, hb.h, poses_to_rows(stamps, poses),
                           self.robot.wheels, self.robot.wheel_width, self.robot.wheel_flat_fraction, extras,
                           **visits)

    def mapping_result(self) -> mapping.MappingResult:
        """The mapper's result (P_ref as held), levelled."""
        res = self.mapper.result()
        return mapping.rotate_world(res, self._world()[:3, :3])

    def grid_cells(self) -> int:
        """Cells of the whole drive's terrain pair so far (the corridor's bounding box)."""
        _, poses = self.trajectory()
        if len(poses) == 0:
            return 0
        xy = poses[:, :2, 3]
        span = xy.max(0) - xy.min(0) + self.cfg.raster.corridor_width
        return int(np.prod(np.floor(span / self.cfg.raster.dx) + 2))

    def flush(self) -> None:
        """Every tile to the spill directory (when there is one)."""
        for tiles in (*(t for layers in self.tiles.values() for t in layers), self.visits):
            tiles.spill(np.zeros((1, 2)), -np.inf)
