"""Reference map P_ref and trajectory T_ref: fused front + back sweeps registered
incrementally, scan to local map, by point-to-plane ICP (paper section III).

Why this registration: on a ground-dominated farm scene with poles and sheds, KISS-ICP's
defaults lost about 1 m in the first second (it starts at zero velocity while the robot
already moves) whereas point-to-plane scan-to-local-map ICP with 0.2 m voxels reached
sub-centimetre error (MEASURED.md). Here the first two sweeps are registered with a wide
correspondence gate to measure the initial velocity, then the run restarts with that
velocity, so a robot already moving at the first sweep is tracked from the start.

Sweeps whose normal matrix has weak directions (a landmark-free stretch: the ground fixes
z, roll and pitch only) keep the constant-velocity prediction along those directions and
are flagged DEGENERATE; sweeps that do not match the map are flagged POOR_FIT and follow
the prediction; near-zero speed is flagged STATIONARY.
"""

from __future__ import annotations

from collections import deque
from typing import NamedTuple

import numpy as np
from scipy.spatial import cKDTree

from torchsoil.pipeline import _kernels as _k
from torchsoil.pipeline import icp
from torchsoil.pipeline.deskew import deskew
from torchsoil.settings import MappingConfig

# per-sweep flags (bit mask), shared by all stages
EMPTY = 1           # no usable points
DEGENERATE = 2      # scene leaves some pose directions unconstrained
POOR_FIT = 4        # registration failed; pose from the motion model
STATIONARY = 8      # robot (nearly) standing still
REREG_FRONT_FAILED = 16   # front sweep dropped by re-registration
REREG_BACK_FAILED = 32    # back sweep dropped by re-registration
MISSING_BACK = 64   # no back sweep close in time
RETRIED = 128       # registered again from other starts (the motion changed, or the first fit was weak)
MISSING_FRONT = 256  # no front sweep close in time: the back sweep was mapped alone
GAP = 512           # first sweep after more than 3 periods without one (both lidars silent)
MAP_CONFLICT = 1024  # taken on a visit that finds the ground of the visit before displaced (a broken map)

PROBLEMS = ~RETRIED  # the bits that mark a sweep's ground as doubtful (a retried sweep did register)

FLAG_NAMES = {EMPTY: "empty", DEGENERATE: "degenerate", POOR_FIT: "poor_fit",
              STATIONARY: "stationary", RETRIED: "retried", REREG_FRONT_FAILED: "rereg_front_failed",
              REREG_BACK_FAILED: "rereg_back_failed", MISSING_BACK: "missing_back",
              MISSING_FRONT: "missing_front", GAP: "gap", MAP_CONFLICT: "map_conflict"}


def flag_names(flags: int) -> list[str]:
    return [name for bit, name in FLAG_NAMES.items() if flags & bit]


class Sweep(NamedTuple):
    """A sweep in the robot frame: stamp [s]; points (N, 3) in base_link [m];
    t (N,) capture time of each point after `stamp`, s."""

    stamp: float
    points: np.ndarray
    t: np.ndarray


class MappingResult(NamedTuple):
    """stamps (S,) [s]; poses (S, 4, 4) base_link in world at each stamp; map_points (M, 3)
    and map_normals (M, 3) of P_ref [m] (wall and pole normals turned towards where they
    were seen from: icp.orient_to_viewpoints); fitness (S,), rmse (S,) [m], flags (S,) int."""

    stamps: np.ndarray
    poses: np.ndarray
    map_points: np.ndarray
    map_normals: np.ndarray
    fitness: np.ndarray
    rmse: np.ndarray
    flags: np.ndarray


def voxel_pick(points: np.ndarray, voxel: float) -> np.ndarray:
    """Indices of one point (the first) per cubic voxel of edge `voxel` m, in voxel-key order."""
    return icp.voxel_first(points, voxel)


class ReferenceMap:
    """P_ref held incrementally: one point per cubic voxel of edge `voxel` m (the oldest: the
    first point added into a voxel stays), with the robot position it was seen from.

    Memory grows with the ground covered, not with the number of sweeps, and `forget` drops
    the voxels far from where the robot still works. Adding costs in proportion to the
    points added (a persistent voxel hash, buffers grown by doubling). `reference` serves the
    part near a position as an ICP target; its normals are cached per voxel and recomputed
    only where a voxel's neighbourhood (within `normal_radius`) changed since.
    """

    _FIELDS = {"points": ((3,), np.float64), "views": ((3,), np.float64), "keys": ((), np.int64),
               "born": ((), np.int64), "normals": ((3,), np.float64), "stamp": ((), np.int64)}

    def __init__(self, voxel: float, normal_radius: float):
        self.voxel, self.normal_radius = voxel, normal_radius
        self.n = 0
        self.epoch = 0  # advanced by every add and forget; `born` and `stamp` refer to it
        self._buf = {name: np.empty((0, *shape), dtype) for name, (shape, dtype) in self._FIELDS.items()}
        self._table = np.full(16, -1, np.int64)

    # the held voxels, in the order they entered (views of the buffers): points (M, 3), the
    # robot position each was seen from (M, 3), voxel keys (M,), epoch each entered (M,),
    # cached oriented normals (M, 3) and the epoch each was computed at (M,; -1: none)
    points = property(lambda self: self._buf["points"][:self.n])
    views = property(lambda self: self._buf["views"][:self.n])
    keys = property(lambda self: self._buf["keys"][:self.n])
    born = property(lambda self: self._buf["born"][:self.n])
    normals = property(lambda self: self._buf["normals"][:self.n])
    stamp = property(lambda self: self._buf["stamp"][:self.n])

    def __len__(self) -> int:
        return self.n

    def _reserve(self, need: int) -> None:
        cap = len(self._buf["keys"])
        if need > cap:
            cap = max(need, 2 * cap, 1024)
            for name, (shape, dtype) in self._FIELDS.items():
                buf = np.empty((cap, *shape), dtype)
                buf[:self.n] = self._buf[name][:self.n]
                self._buf[name] = buf
        if 2 * need > len(self._table):
            size = 1 << int(np.ceil(np.log2(4 * need)))
            self._table = _k.table_build(self._buf["keys"], self.n, size)

    def add(self, world_points: np.ndarray, center: np.ndarray) -> None:
        """Insert (N, 3) world points [m] seen from `center` (3,): each fills its voxel unless
        the voxel is occupied already (or an earlier point of the same call filled it)."""
        world_points = np.ascontiguousarray(world_points, dtype=np.float64).reshape(-1, 3)
        self.epoch += 1
        keys = icp.voxel_keys(world_points, self.voxel)
        self._reserve(self.n + len(keys))
        new = _k.table_insert(self._table, self._buf["keys"], self.n, keys)  # appends the keys
        a, b = self.n, self.n + len(new)
        self._buf["points"][a:b] = world_points[new]
        self._buf["views"][a:b] = center
        self._buf["born"][a:b] = self.epoch
        self._buf["normals"][a:b] = 0.0
        self._buf["stamp"][a:b] = -1
        self.n = b

    def global_map(self) -> tuple[np.ndarray, np.ndarray]:
        """The held points (M, 3), in the order they entered, and the robot position (M, 3)
        each was seen from, m."""
        return self.points.copy(), self.views.copy()

    def forget(self, keep_xy: np.ndarray, radius: float) -> int:
        """Drop the voxels whose point lies farther than `radius` m (horizontally) from every
        position of keep_xy (K, 2) (e.g. the recent trajectory); returns how many were dropped.
        Cached normals of kept voxels whose neighbourhood lost points are recomputed on use."""
        if self.n == 0:
            return 0
        keep_xy = np.asarray(keep_xy, dtype=np.float64).reshape(-1, 2)
        if len(keep_xy) == 0:
            d = np.full(self.n, np.inf)
        else:
            bound = np.nextafter(float(radius), np.inf)  # the query's bound is strict
            d, _ = cKDTree(keep_xy).query(self.points[:, :2], distance_upper_bound=bound)
        keep = d <= radius
        dropped = int(self.n - keep.sum())
        if dropped == 0:
            return 0
        self.epoch += 1
        self.stamp[keep & (d > radius - self.normal_radius)] = -1
        kept = {name: getattr(self, name)[keep] for name in self._FIELDS}
        self.n = len(kept["keys"])
        if 4 * self.n < len(self._buf["keys"]):  # give memory back after a large cut
            self._buf = {name: np.empty((max(2 * self.n, 1024), *shape), dtype)
                         for name, (shape, dtype) in self._FIELDS.items()}
        for name, arr in kept.items():
            self._buf[name][:self.n] = arr
        size = 1 << int(np.ceil(np.log2(max(4 * self.n, 16))))
        self._table = _k.table_build(self._buf["keys"], self.n, size)
        return dropped

    def reference(self, center: np.ndarray, radius: float) -> icp.Target:
        """The held points within `radius` m (horizontally, <=) of `center` (3,), in the order
        they entered, with their normals (icp.pca_normals within normal_radius over all held
        points, turned towards the viewpoints by icp.orient_to_viewpoints; zero where the
        neighbourhood is not a surface) and a search index: an ICP target."""
        c = np.asarray(center, dtype=np.float64)
        points, stamp = self.points, self.stamp
        dxy = np.hypot(points[:, 0] - c[0], points[:, 1] - c[1])
        ext = np.flatnonzero(dxy <= radius + self.normal_radius)  # holds every neighbourhood used
        sel = ext[dxy[ext] <= radius]
        pts = points[ext]
        index = icp.VoxelIndex(pts, 3 * self.voxel)
        todo = stamp[sel] < 0
        cached = sel[~todo]
        if len(cached):   # only points that entered after the oldest cached normal can have changed one
            born = self.born[ext]
            young = np.flatnonzero(born > stamp[cached].min())
            if len(young):
                changed = icp.VoxelIndex(pts[young], 3 * self.voxel).any_newer(points[cached], stamp[cached],
                                                                               born[young], self.normal_radius)
                todo[np.flatnonzero(~todo)[changed]] = True
        redo = sel[todo]
        if len(redo):
            n, _ = icp.pca_normals(pts, index, points[redo], radius=self.normal_radius)
            self.normals[redo] = icp.orient_to_viewpoints(points[redo], n, self.views[redo])
            stamp[redo] = self.epoch
        out = points[sel]
        return icp.Target(out, self.normals[sel], icp.VoxelIndex(out, 3 * self.voxel))


class LocalMap:
    """Voxelised world points near the robot (one point per voxel, oldest kept), with
    normals turned towards the robot position from which each point was first seen.

    Every point added also feeds the reference map P_ref (`ref`, a ReferenceMap), reached
    through `reference`, `forget` and `global_map`.
    """

    def __init__(self, voxel: float, radius: float, normal_radius: float):
        self.voxel, self.radius, self.normal_radius = voxel, radius, normal_radius
        self.points = np.zeros((0, 3))
        self.normals = np.zeros((0, 3))
        self.good = np.zeros(0, bool)
        self.age = np.zeros(0, np.int64)
        self.views = np.zeros((0, 3))
        self.keys = np.zeros(0, np.int64)
        self.retries = 10
        self.target: icp.Target | None = None
        self.ref = ReferenceMap(voxel, normal_radius)

    def global_map(self) -> tuple[np.ndarray, np.ndarray]:
        """P_ref as held: every point added, one per voxel (oldest kept), minus what `forget`
        dropped: points (M, 3), and the robot position (M, 3) each was seen from, m."""
        return self.ref.global_map()

    def reference(self, center: np.ndarray, radius: float) -> icp.Target:
        """P_ref within `radius` m of `center` as an ICP target (see ReferenceMap.reference)."""
        return self.ref.reference(center, radius)

    def forget(self, keep_xy: np.ndarray, radius: float) -> int:
        """Drop P_ref voxels farther than `radius` m from every point of keep_xy (K, 2)."""
        return self.ref.forget(keep_xy, radius)

    def add(self, world_points: np.ndarray, center: np.ndarray) -> None:
        """Insert (N, 3) world points [m] seen from `center` (3,) into the local map (new
        voxels only; voxels beyond `radius` of center are dropped) and into P_ref."""
        world_points = np.ascontiguousarray(world_points, dtype=np.float64).reshape(-1, 3)
        center = np.ascontiguousarray(center, dtype=np.float64)
        self.ref.add(world_points, center)
        keys = icp.voxel_keys(world_points, self.voxel)
        new = _k.fresh(self.keys, keys)  # earlier (older) points keep their voxel
        pts, normals, good, age, views, self.keys, _ = _k.local_merge(
            self.points, self.normals, self.good, self.age, self.views, self.keys, world_points[new], keys[new],
            center, float(self.radius))
        index = icp.VoxelIndex(pts, 3 * self.voxel)
        # a normal is computed when its point enters the map and again, for a few sweeps,
        # while its neighbourhood is not yet a surface patch (e.g. one ground ring)
        redo = np.flatnonzero(~good & (age < self.retries))
        if len(redo):
            normals[redo], good[redo] = icp.pca_normals(pts, index, pts[redo], radius=self.normal_radius)
            normals[redo] = icp.orient_to_viewpoints(pts[redo], normals[redo], views[redo])
        self.points, self.normals, self.good, self.age, self.views = pts, normals, good, age, views
        self.target = icp.Target(pts, normals, index)


class _Fit(NamedTuple):
    """One registration of a sweep: ICP result, pose (4, 4; the seed where poor), de-skewed
    points (N, 3), poor / weak (degenerate) flags, truncated cost at the pose (icp.truncated_cost)."""

    res: icp.IcpResult
    T: np.ndarray
    pts: np.ndarray
    poor: bool
    weak: bool
    cost: float


def _angle_deg(T: np.ndarray) -> float:
    """Rotation angle of a (4, 4) transform, degrees."""
    return float(np.degrees(np.linalg.norm(_k.rotvec_of(np.ascontiguousarray(T[:3, :3])))))


def _left_jacobian(phi: np.ndarray) -> np.ndarray:
    """(3, 3) V of the SE(3) exponential for the rotation vector phi (3,): translation = V rho."""
    th = float(np.linalg.norm(phi))
    K = np.array([[0.0, -phi[2], phi[1]], [phi[2], 0.0, -phi[0]], [-phi[1], phi[0], 0.0]])
    if th < 1e-9:
        return np.eye(3) + K / 2
    return np.eye(3) + (1 - np.cos(th)) / th**2 * K + (th - np.sin(th)) / th**3 * K @ K


def _arc_motion(w: np.ndarray, v: np.ndarray, dt: float) -> np.ndarray:
    """(4, 4) motion over dt s at constant body rates: rotation w (3,) rad/s and velocity
    v (3,) m/s in the robot frame (the exponential of the twist: a turning robot moves on an
    arc, which matters once dt spans a large turn, e.g. after a gap in the sweeps)."""
    phi = np.asarray(w, np.float64) * dt
    M = np.eye(4)
    M[:3, :3] = _k.rotation(np.ascontiguousarray(phi))
    M[:3, 3] = _left_jacobian(phi) @ (np.asarray(v, np.float64) * dt)
    return M


def _motion_over(velocity: np.ndarray, dt: float) -> np.ndarray:
    """Motion per second (4, 4: rotation by the rate w, translation the body velocity v) ->
    motion over dt seconds at those constant rates (on an arc)."""
    return _arc_motion(_k.rotvec_of(np.ascontiguousarray(velocity[:3, :3])), velocity[:3, 3], dt)


def _velocity(T_prev: np.ndarray, T_curr: np.ndarray, dt: float) -> np.ndarray:
    """The constant rates (as `_motion_over` takes them) that move T_prev to T_curr in dt s."""
    if dt <= 0:
        return np.eye(4)
    D = np.linalg.inv(T_prev) @ T_curr
    phi = _k.rotvec_of(np.ascontiguousarray(D[:3, :3]))
    out = np.eye(4)
    out[:3, :3] = _k.rotation(np.ascontiguousarray(phi / dt))
    out[:3, 3] = np.linalg.solve(_left_jacobian(phi), D[:3, 3]) / dt
    return out


def _pick(sweep: Sweep, cfg: MappingConfig) -> Sweep:
    """The sweep's points within max_range, one per voxel of edge voxel / 2 (as `voxel_pick`)."""
    pts = np.ascontiguousarray(sweep.points, dtype=np.float64)
    near = _k.within_range(pts, float(cfg.max_range))
    pick = near[voxel_pick(pts[near], cfg.voxel / 2)]
    return Sweep(sweep.stamp, pts[pick], sweep.t[pick])


def _prepare(sweep: Sweep, velocity: np.ndarray, period: float, cfg: MappingConfig,
             picked: Sweep | None = None) -> np.ndarray:
    """Downsampled, range-limited, de-skewed points of a sweep (robot frame at its stamp);
    `picked`: its `_pick`, when already taken."""
    p = picked if picked is not None else _pick(sweep, cfg)
    return deskew(p.points, p.t, _motion_over(velocity, period), period)


class Gyro:
    """The IMU's rate gyro, turned into base_link: rotation of the robot over an interval.

    `add(t, w)` samples in time order (t s, w (3,) rad/s in base_link); `rotation(t0, t1)` the
    (3, 3) rotation of base_link from t0 to t1 (each sample held until the next), or None where
    the samples do not cover the interval. Samples older than `keep` s before the newest are
    dropped (bounded memory)."""

    def __init__(self, keep: float = 10.0):
        self.keep = keep
        self.t: deque[float] = deque()
        self.w: deque[np.ndarray] = deque()

    def add(self, t: float, w: np.ndarray) -> None:
        if self.t and t <= self.t[-1]:
            return
        self.t.append(float(t))
        self.w.append(np.asarray(w, np.float64))
        while self.t[-1] - self.t[0] > self.keep:
            self.t.popleft(), self.w.popleft()

    def rotation(self, t0: float, t1: float) -> np.ndarray | None:
        if len(self.t) < 2 or t0 < self.t[0] or t1 > self.t[-1] or t1 <= t0:
            return None
        t = np.asarray(self.t)
        i0 = max(int(np.searchsorted(t, t0, side="right")) - 1, 0)
        i1 = int(np.searchsorted(t, t1, side="left"))
        edges = np.clip(t[i0:i1 + 1], t0, t1)
        if len(edges) > 1 and np.max(np.diff(edges)) > 0.1:   # a hole in the samples
            return None
        R = np.eye(3)
        for j in range(i0, i1):
            dt = edges[j - i0 + 1] - edges[j - i0]
            if dt > 0:
                R = R @ _k.rotation(np.ascontiguousarray(self.w[j] * dt))
        return R


class Mapper:
    """Incremental registration of fused sweeps into P_ref and T_ref (scan to local map).

    `add(sweep)` each time-ordered fused sweep (base_link), `finish()` at the end; both return
    the indices of the sweeps whose pose became final (`stamps`, `poses` (4, 4), `fitness`,
    `rmse`, `flags` per index). The first sweeps are held until the initial velocity is
    measured (over `cfg.startup_baseline` s). The world frame is base_link at the first usable
    sweep (`rotate_world` levels it afterwards); `local` holds the local and reference maps.
    """

    def __init__(self, cfg: MappingConfig | None = None, period: float = 0.1):
        self.cfg = cfg = cfg or MappingConfig()
        self.period = period
        self.spacing = period          # expected time between sweeps (more when a live node thins them), s
        self.local = LocalMap(cfg.voxel, cfg.map_radius, cfg.normal_radius)
        self.stamps: list[float] = []
        self.poses: list[np.ndarray] = []
        self.fitness: list[float] = []
        self.rmse: list[float] = []
        self.flags: list[int] = []
        self.held: list[Sweep] = []     # sweeps waiting for the initial velocity
        self.velocity: np.ndarray | None = None
        self.prev: int | None = None    # last registered sweep
        self.first: int | None = None   # first usable sweep
        self.done: list[int] = []       # registered sweeps (velocity baselines)
        self.costs: deque[float] = deque(maxlen=10)   # truncated costs of the last registrations
        self.gyro: Gyro | None = None   # set by the caller when the recording has an IMU
        self._picked: tuple[Sweep | None, Sweep | None] = (None, None)   # the last sweep fitted and its _pick

    def add(self, sweep: Sweep) -> list[int]:
        if self.stamps and sweep.stamp <= self.stamps[-1]:
            raise ValueError(f"sweep stamps must increase; sweep {len(self.stamps)} at t={sweep.stamp:.3f} s "
                             f"follows t={self.stamps[-1]:.3f} s")
        self.stamps.append(float(sweep.stamp))
        self.poses.append(np.eye(4))
        self.fitness.append(0.0)
        self.rmse.append(np.inf)
        self.flags.append(0)
        if self.velocity is not None:
            return [self._register(len(self.stamps) - 1, sweep)]
        self.held.append(sweep)
        usable = [s for s in self.held if len(s.points) >= 50]
        if usable and sweep.stamp - usable[0].stamp > self.cfg.startup_baseline + self.period / 4 and len(usable) >= 2:
            return self._start()
        return []

    def finish(self) -> list[int]:
        if self.velocity is None:
            if sum(len(s.points) >= 50 for s in self.held) < 2:
                raise ValueError(f"mapping needs at least two sweeps with points; "
                                 f"{sum(len(s.points) >= 50 for s in self.held)} of {len(self.held)} have 50 or more")
            return self._start()
        return []

    def _start(self) -> list[int]:
        """Initial velocity from the first usable sweep and the last within the baseline, then
        the held sweeps registered."""
        cfg, held = self.cfg, self.held
        base = len(self.stamps) - len(held)
        usable = [k for k, s in enumerate(held) if len(s.points) >= 50]
        later = [k for k in usable[1:]
                 if held[k].stamp - held[usable[0]].stamp <= cfg.startup_baseline + self.period / 4]
        k1 = later[-1] if later else usable[1]
        self.velocity = _startup_velocity(held[usable[0]], held[k1], held[k1].stamp - held[usable[0]].stamp,
                                          self.period, cfg)
        self.held = []
        return [self._register(base + k, s) for k, s in enumerate(held)]

    def _register(self, k: int, sweep: Sweep) -> int:
        cfg = self.cfg
        empty = len(sweep.points) < 50
        if self.prev is None:   # the first usable sweep starts the map
            if empty:
                self.flags[k] |= EMPTY
                return k
            self.local.add(_prepare(sweep, self.velocity, self.period, cfg), np.zeros(3))
            self.fitness[k], self.rmse[k], self.prev, self.first = 1.0, 0.0, k, k
            self.done.append(k)
            return k
        dt = self.stamps[k] - self.stamps[self.prev]
        T_pred = self.poses[self.prev] @ self._predict(self.stamps[self.prev], dt)
        if empty:
            self.flags[k] |= EMPTY
            self.poses[k] = T_pred
            return k
        gate = cfg.startup_dist if len(self.done) == 1 else cfg.max_dist
        T_prev = self.poses[self.prev]
        fit = self._fit(sweep, T_prev, T_pred, dt, gate)
        turn = _angle_deg(np.linalg.inv(T_pred) @ fit.T)
        if dt > 3 * self.spacing:   # no sweep for a while: the prediction is a guess
            self.flags[k] |= GAP
        usual = float(np.median(self.costs)) if len(self.costs) >= 3 else np.inf
        if (fit.poor or fit.weak or turn > cfg.retry_turn or fit.cost > cfg.retry_cost * usual
                or self.flags[k] & GAP):
            fit = self._retry(sweep, T_prev, T_pred, dt, gate, fit, bool(self.flags[k] & GAP))
            self.flags[k] |= RETRIED
        res, T, pts = fit.res, fit.T, fit.pts
        self.fitness[k], self.rmse[k] = res.fitness, res.rmse
        if fit.poor:
            self.flags[k] |= POOR_FIT
            T = T_pred
        elif fit.weak:
            self.flags[k] |= DEGENERATE
        self.poses[k] = T
        self.done.append(k)
        if not fit.poor:
            self.costs.append(fit.cost)
        stamps = np.asarray(self.stamps)
        base = _baseline(self.done, stamps, cfg.velocity_window + self.period / 4)
        stepped = _angle_deg(np.linalg.inv(T_pred) @ T) > cfg.retry_turn
        if stepped and not self.flags[k] & (POOR_FIT | DEGENERATE):
            # the motion changed (a steering step): the last interval alone predicts the next
            self.velocity = _velocity(T_prev, T, dt)
        elif not self.flags[k] & DEGENERATE:   # a degenerate pose is partly the prediction: coast
            self.velocity = _velocity(self.poses[base], T, stamps[k] - stamps[base])
        if len(self.done) > 64:
            del self.done[:-32]
        if np.linalg.norm(self.velocity[:3, 3]) < cfg.stationary_speed:
            self.flags[k] |= STATIONARY
        if not self.flags[k] & POOR_FIT:
            self.local.add(icp.apply(T, pts), T[:3, 3])
        self.prev = k
        return k

    def _predict(self, t0: float, dt: float) -> np.ndarray:
        """(4, 4) motion over [t0, t0 + dt]: the constant rates, with the rotation measured by
        the rate gyro where it covers the interval (a steering step is then no surprise)."""
        R = self.gyro.rotation(t0, t0 + dt) if self.gyro is not None and self.cfg.use_gyro else None
        if R is None:
            return _motion_over(self.velocity, dt)
        return _arc_motion(_k.rotvec_of(np.ascontiguousarray(R)) / dt, self.velocity[:3, 3], dt)

    def _fit(self, sweep: Sweep, T_prev: np.ndarray, seed: np.ndarray, dt: float, gate: float,
             wide: float | None = None, iters: int | None = None) -> _Fit:
        """The sweep de-skewed with the motion from T_prev to `seed` over dt s, registered from
        `seed` onto the local map (first with a `wide` gate when given, then with `gate`), in
        at most `iters` ICP iterations (default mapping.max_iter)."""
        cfg = self.cfg
        if getattr(self, "_picked", (None,))[0] is not sweep:   # retries de-skew the same points with other motions
            self._picked = (sweep, _pick(sweep, cfg))
        pts = _prepare(sweep, _velocity(T_prev, seed, dt), self.period, cfg, self._picked[1])
        src = icp.thin(icp.voxel_downsample(pts, cfg.source_voxel), cfg.max_points, cfg.source_voxel)
        kw = {"workers": cfg.workers, "ground_z": cfg.ground_z, "one_sided": cfg.one_sided}
        start, iters = seed, iters or cfg.max_iter
        if wide is not None:
            start = icp.register(src, self.local.target, seed, wide, iters, **kw).transform
        res = icp.register(src, self.local.target, start, gate, iters, **kw)
        poor = res.fitness < cfg.min_fitness or not np.isfinite(res.rmse)
        weak = icp.weak_directions(res.hessian, cfg.degenerate_eigen)
        T = seed if poor else icp.project_update(seed, res.transform, weak)
        return _Fit(res, T, pts, poor, bool(weak.shape[1]),
                    icp.truncated_cost(src, T, self.local.target, cfg.voxel / 2))

    def _retry(self, sweep: Sweep, T_prev: np.ndarray, T_pred: np.ndarray, dt: float, gate: float,
               first: _Fit, gap: bool) -> _Fit:
        """The registration again from other starts: the first result, and the motion from the
        last pose at the present speed and predicted rates, with every change of yaw rate that
        adds or loses up to 2 max_yaw_rate dt of yaw (in retry_step steps; on arcs), each
        de-skewed with its own motion (after a `gap`, registered with a wide gate first). The
        start with the lowest truncated cost wins if the scene fixes it in every direction and
        it beats the first result's cost by the factor retry_gain; then it is de-skewed with its
        own motion and refined."""
        cfg = self.cfg
        span = min(2.0 * cfg.max_yaw_rate * dt, 180.0)
        yaws = np.arange(-span, span + 1e-9, cfg.retry_step) if span >= cfg.retry_step else np.zeros(1)
        w = _k.rotvec_of(np.ascontiguousarray((np.linalg.inv(T_prev) @ T_pred)[:3, :3])) / dt   # predicted rates
        seeds = [T_prev @ _arc_motion(w + [0.0, 0.0, np.radians(a) / dt], self.velocity[:3, 3], dt) for a in yaws]
        wide = max(gate, cfg.startup_dist) if gap else None
        # a third of the iterations ranks the starts; the winner is refined in full below
        fits = [self._fit(sweep, T_prev, s, dt, gate, wide, max(cfg.max_iter // 3, 1)) for s in seeds]
        # another start must fit clearly better, and be fixed in every direction: where the scene
        # leaves one free, a start's pose along it is its own guess, not a measurement
        best = min(fits, key=lambda f: (f.poor or f.weak, f.cost))
        if best.poor or best.weak or (not first.poor and not best.cost < cfg.retry_gain * first.cost):
            best = first
        if best.poor or best.weak:   # nothing better: the prediction stands where the scene is silent
            return best
        return self._fit(sweep, T_prev, best.T, dt, gate)

    def check_degenerate(self) -> None:
        """ValueError when more than cfg.max_degenerate_share of the sweeps are degenerate."""
        flags, stamps = np.asarray(self.flags), np.asarray(self.stamps)
        degenerate = (flags & DEGENERATE) != 0
        if len(flags) and degenerate.mean() > self.cfg.max_degenerate_share:
            k = np.flatnonzero(degenerate)
            raise ValueError(
                f"registration is degenerate for {degenerate.sum()} of {len(flags)} sweeps (first at "
                f"t = {stamps[k[0]] - stamps[0]:.2f} s, last at t = {stamps[k[-1]] - stamps[0]:.2f} "
                "s after the start): the scene has no structure that fixes the motion along the "
                "ground (a landmark-free field?), so the trajectory, and with it the heightmaps, "
                "would be unreliable; nothing written")

    def result(self) -> MappingResult:
        """Everything registered so far, with P_ref as the reference map holds it."""
        p_ref, views = self.local.global_map()
        normals, _ = icp.pca_normals(p_ref, cKDTree(p_ref), p_ref, radius=self.cfg.normal_radius)
        normals = icp.orient_to_viewpoints(p_ref, normals, views)
        return MappingResult(np.asarray(self.stamps), np.asarray(self.poses).reshape(-1, 4, 4), p_ref, normals,
                             np.asarray(self.fitness), np.asarray(self.rmse), np.asarray(self.flags, np.int64))


def build_map(sweeps: list[Sweep], cfg: MappingConfig | None = None, progress=None
              ) -> MappingResult:
    """Register fused sweeps incrementally into P_ref and T_ref (a `Mapper` run to the end).

    sweeps: time-ordered fused sweeps in base_link. The world frame is base_link at the
    first usable sweep (`rotate_world` levels it afterwards). progress: optional callable(n) advanced once per sweep.
    """
    if len(sweeps) == 0:
        raise ValueError("mapping needs at least one sweep")
    stamps = np.array([s.stamp for s in sweeps])
    period = float(np.median(np.diff(stamps))) if len(sweeps) > 1 else 0.1
    mapper = Mapper(cfg, period)
    for sw in sweeps:
        mapper.add(sw)
        if progress is not None:
            progress(1)
    mapper.finish()
    mapper.check_degenerate()
    return mapper.result()


def rotate_world(maps: MappingResult, R: np.ndarray) -> MappingResult:
    """The trajectory and P_ref in the world frame turned by R (3, 3) about its origin (the
    first sweep's base_link): poses R T, points and normals R p."""
    L = np.eye(4)
    L[:3, :3] = R
    return maps._replace(poses=L @ maps.poses, map_points=maps.map_points @ R.T,
                         map_normals=maps.map_normals @ R.T)


def _baseline(done: list[int], stamps: np.ndarray, window: float) -> int:
    """Earliest registered sweep within `window` s before the newest one (at least the one
    before it): the velocity over a longer baseline is steadier. Callers pass the window with a
    quarter period to spare: a window of whole periods would otherwise pick its baseline by
    the stamps' last nanoseconds (jitter, or the rounding of another stamp convention)."""
    last = done[-1]
    j = len(done) - 2
    while j > 0 and stamps[last] - stamps[done[j - 1]] <= window:
        j -= 1
    return done[max(j, 0)]


def _startup_velocity(s0: Sweep, s1: Sweep, dt: float, period: float, cfg: MappingConfig
                      ) -> np.ndarray:
    """Motion per second between the first two sweeps (robot possibly already moving),
    from two rounds: zero-velocity guess with a wide gate, then de-skewed with the result."""
    velocity = np.eye(4)
    for _ in range(2):
        p0 = _prepare(s0, velocity, period, cfg)
        p1 = _prepare(s1, velocity, period, cfg)
        ref = icp.voxel_downsample(p0, cfg.voxel / 2)
        tree = cKDTree(ref)
        target = icp.Target(ref, icp.pca_normals(ref, tree, ref, radius=cfg.normal_radius)[0],
                            tree)
        T0 = _motion_over(velocity, dt)
        res = icp.register(icp.voxel_downsample(p1, cfg.voxel), target, T0, cfg.startup_dist,
                           cfg.max_iter)
        if res.fitness < cfg.min_fitness:
            return np.eye(4)
        velocity = _velocity(np.eye(4), res.transform, dt)
    return velocity
