"""Simulated spinning lidars (Ouster OS1-32 like): vectorized ray casting against the
time-varying heightfield and the landmarks, with range noise, dropouts and per-point
capture times (motion distortion).

A sweep of `columns` azimuth columns takes 1 / rate_hz; column c is captured at
c / columns of the sweep, from the sensor pose at that instant, and its points are given in
the sensor frame at that instant (as a real sensor reports them).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np

from torchsoil.grid import Grid

KIND_NONE, KIND_GROUND, KIND_CYLINDER, KIND_BOX = 0, 1, 2, 3
MAX_SLOPE = 0.9       # terrain slope bound used for the ray-marching step, m/m
MIN_STEP = 0.01       # m
MIN_RANGE = 0.3       # m, the sensor sees nothing closer
MAX_RANGE = 60.0      # m
XYZ_STEPS = 1024.0    # point coordinates are multiples of 1 / XYZ_STEPS m


@dataclass(frozen=True)
class LidarSpec:
    """One spinning lidar.

    name: frame name (e.g. "lidar_front"); xyz: (3,) mount position in base_link, m;
    rpy: (3,) mount roll, pitch, yaw in base_link, rad (pitch > 0 tilts it down);
    beams: number of rings; vfov_deg: vertical field of view, deg (symmetric);
    columns: azimuth columns per sweep; rate_hz: sweeps per second.
    """

    name: str
    xyz: tuple[float, float, float]
    rpy: tuple[float, float, float]
    beams: int = 32
    vfov_deg: float = 45.0
    columns: int = 1024
    rate_hz: float = 10.0

    def __post_init__(self):
        if self.columns < 8 or self.beams < 1:
            raise ValueError(f"lidar {self.name}: columns >= 8 and beams >= 1 needed")
        if not 0 < self.rate_hz <= 100:
            raise ValueError(f"lidar {self.name}: rate_hz must be in (0, 100], got {self.rate_hz}")

    def elevations(self) -> np.ndarray:
        """(beams,) elevation of each ring, rad; ring 0 is the top beam."""
        h = math.radians(self.vfov_deg) / 2
        return np.linspace(h, -h, self.beams)

    def azimuths(self) -> np.ndarray:
        """(columns,) azimuth of each column in the sensor frame, rad (clockwise from +x
        seen from above, as the sensor spins)."""
        return -2 * math.pi * np.arange(self.columns) / self.columns

    def directions(self) -> np.ndarray:
        """(beams, columns, 3) unit ray directions in the sensor frame."""
        el, az = self.elevations()[:, None], self.azimuths()[None, :]
        return np.stack(np.broadcast_arrays(np.cos(el) * np.cos(az), np.cos(el) * np.sin(az),
                                            np.sin(el)), -1)

    def transform(self) -> np.ndarray:
        """(4, 4) base_link <- sensor."""
        T = np.eye(4)
        T[:3, :3] = rpy_matrix(*self.rpy)
        T[:3, 3] = self.xyz
        return T


def paper_lidars(columns: int = 1024, rate_hz: float = 10.0, beams: int = 32, tilt_deg: float = 30.0
                 ) -> list[LidarSpec]:
    """Front and back OS1-32 of the paper's platform: 0.95 m ahead of / behind the
    chassis centre, 1.0 m up, each tilted `tilt_deg` down towards its own side (30: little
    overlap); `beams` rings over the same field of view (fewer: smaller bags for long drives)."""
    tilt = math.radians(tilt_deg)
    return [LidarSpec("lidar_front", (0.95, 0.0, 1.0), (0.0, tilt, 0.0), columns=columns, rate_hz=rate_hz,
                      beams=beams),
            LidarSpec("lidar_back", (-0.95, 0.0, 1.0), (0.0, tilt, math.pi), columns=columns,
                      rate_hz=rate_hz, beams=beams)]


def rpy_matrix(roll, pitch, yaw) -> np.ndarray:
    """R = Rz(yaw) Ry(pitch) Rx(roll) for scalars (3, 3) or arrays (N, 3, 3)."""
    r, p, y = (np.asarray(a, dtype=np.float64) for a in (roll, pitch, yaw))
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    R = np.stack([
        np.stack([cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr], -1),
        np.stack([sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr], -1),
        np.stack([-sp, cp * sr, cp * cr], -1)], -2)
    return R


def matrix_quaternion(R: np.ndarray) -> np.ndarray:
    """(3, 3) rotation -> (4,) quaternion x, y, z, w."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(R).as_quat()


@dataclass
class Scene:
    """What the rays can hit.

    field: grid of h_field; h_field: (X, Y) float32 initial surface, m.
    win: (i0, j0) of the deforming window inside the field; states: (V+1, Xw, Yw) float32
    surfaces after 0..V visits; visit_time: (V, Xw, Yw) float32 time [s] each visit ends.
    cylinders: (C, 5) x, y, r, z0, z1; boxes: (N, 8) cx, cy, cz, hl, hw, hh, yaw, kind.
    """

    field: Grid
    h_field: np.ndarray
    win: tuple[int, int]
    states: np.ndarray
    visit_time: np.ndarray
    cylinders: np.ndarray
    boxes: np.ndarray

    def __post_init__(self):
        self.hmax = float(np.nanmax(self.h_field)) + 0.05     # m, rays above it going up hit no ground


@numba.njit(cache=True, inline="always")
def _cell(i, j, t, hf, i0, j0, st, vt):
    ii, jj = i - i0, j - j0
    if 0 <= ii < st.shape[1] and 0 <= jj < st.shape[2]:
        k = 0
        for v in range(vt.shape[0]):
            if vt[v, ii, jj] <= t:
                k = v + 1
        return st[k, ii, jj]
    return hf[i, j]


@numba.njit(cache=True, inline="always")
def _height(x, y, t, ox, oy, dx, hf, i0, j0, st, vt):
    u = (x - ox) / dx
    v = (y - oy) / dx
    i = int(math.floor(u))
    j = int(math.floor(v))
    if i < 0 or j < 0 or i + 1 >= hf.shape[0] or j + 1 >= hf.shape[1]:
        return math.nan
    fu, fv = u - i, v - j
    return ((1 - fu) * (1 - fv) * _cell(i, j, t, hf, i0, j0, st, vt)
            + fu * (1 - fv) * _cell(i + 1, j, t, hf, i0, j0, st, vt)
            + (1 - fu) * fv * _cell(i, j + 1, t, hf, i0, j0, st, vt)
            + fu * fv * _cell(i + 1, j + 1, t, hf, i0, j0, st, vt))


@numba.njit(cache=True, inline="always")
def _slab(lo, ld, half, tmin, tmax):
    """Intersect the ray's [tmin, tmax] with one slab |lo + t ld| <= half (empty: tmin > tmax)."""
    if abs(ld) < 1e-12:
        if abs(lo) > half:
            return 1e30, -1e30
        return tmin, tmax
    t1 = (-half - lo) / ld
    t2 = (half - lo) / ld
    if t1 > t2:
        t1, t2 = t2, t1
    return max(tmin, t1), min(tmax, t2)


@numba.njit(cache=True)
def _march(ox_, oy_, oz_, dxw, dyw, dzw, horiz, best, t, ox, oy, dx, hf, hmax, i0, j0, st, vt):
    """Conservative sphere tracing of one ray on the heightfield up to range `best`; returns
    the hit range (bisection-refined) or `best` when the ray hits nothing closer."""
    rate = -dzw + MAX_SLOPE * horiz
    s = MIN_RANGE
    prev = s
    while s < best:
        z = oz_ + s * dzw
        h = _height(ox_ + s * dxw, oy_ + s * dyw, t, ox, oy, dx, hf, i0, j0, st, vt)
        if math.isnan(h):
            return best
        gap = z - h
        if gap <= 0:
            lo_s, hi_s = prev, s             # bisection between above and below
            for _ in range(12):
                m = 0.5 * (lo_s + hi_s)
                hm = _height(ox_ + m * dxw, oy_ + m * dyw, t, ox, oy, dx, hf, i0, j0, st, vt)
                if oz_ + m * dzw - hm > 0:
                    lo_s = m
                else:
                    hi_s = m
            return 0.5 * (lo_s + hi_s)
        if dzw >= 0 and z > hmax:
            return best
        prev = s
        s += max(gap / rate if rate > 1e-6 else 1e9, MIN_STEP)
    return best


@numba.njit(cache=True, parallel=True)
def _cast(org, rot, dirs, times, ox, oy, dx, hf, hmax, i0, j0, st, vt, cyl, box, out_r, out_k):
    """Cast beams x columns rays. org (C, 3), rot (C, 3, 3) sensor pose per column (world);
    dirs (B, C, 3) in the sensor frame; times (C,) s. Writes range (inf: none) and kind."""
    nb, nc = dirs.shape[0], dirs.shape[1]
    for c in numba.prange(nc):
        ox_, oy_, oz_ = org[c, 0], org[c, 1], org[c, 2]
        t = times[c]
        for b in range(nb):
            sx, sy, sz = dirs[b, c, 0], dirs[b, c, 1], dirs[b, c, 2]
            dxw = rot[c, 0, 0] * sx + rot[c, 0, 1] * sy + rot[c, 0, 2] * sz
            dyw = rot[c, 1, 0] * sx + rot[c, 1, 1] * sy + rot[c, 1, 2] * sz
            dzw = rot[c, 2, 0] * sx + rot[c, 2, 1] * sy + rot[c, 2, 2] * sz
            best = MAX_RANGE
            kind = KIND_NONE
            # vertical cylinders
            a = dxw * dxw + dyw * dyw
            for q in range(cyl.shape[0]):
                if a < 1e-12:
                    break
                px, py = ox_ - cyl[q, 0], oy_ - cyl[q, 1]
                bq = px * dxw + py * dyw
                cq = px * px + py * py - cyl[q, 2] * cyl[q, 2]
                disc = bq * bq - a * cq
                if disc < 0:
                    continue
                s = (-bq - math.sqrt(disc)) / a
                if s < MIN_RANGE or s >= best:
                    continue
                z = oz_ + s * dzw
                if cyl[q, 3] <= z <= cyl[q, 4]:
                    best = s
                    kind = KIND_CYLINDER
            # yawed boxes (slab test in the box frame)
            for q in range(box.shape[0]):
                cy_, sy_ = math.cos(box[q, 6]), math.sin(box[q, 6])
                px, py, pz = ox_ - box[q, 0], oy_ - box[q, 1], oz_ - box[q, 2]
                tmin, tmax = -1e30, 1e30
                tmin, tmax = _slab(cy_ * px + sy_ * py, cy_ * dxw + sy_ * dyw, box[q, 3], tmin, tmax)
                tmin, tmax = _slab(-sy_ * px + cy_ * py, -sy_ * dxw + cy_ * dyw, box[q, 4], tmin, tmax)
                tmin, tmax = _slab(pz, dzw, box[q, 5], tmin, tmax)
                ok = True
                if ok and tmin <= tmax and MIN_RANGE <= tmin < best:
                    best = tmin
                    kind = KIND_BOX
            s = _march(ox_, oy_, oz_, dxw, dyw, dzw, math.sqrt(a), best, t, ox, oy, dx, hf, hmax,
                       i0, j0, st, vt)
            if s < best:
                best = s
                kind = KIND_GROUND
            out_r[b, c] = best if kind != KIND_NONE else math.inf
            out_k[b, c] = kind


def base_poses_at(traj_poses: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World pose of base_link at times t (M,): positions (M, 3), rotations (M, 3, 3)."""
    tt = traj_poses[:, 0]
    p = np.stack([np.interp(t, tt, traj_poses[:, c]) for c in range(1, 7)], -1)
    return p[:, :3], rpy_matrix(p[:, 3], p[:, 4], p[:, 5])


def scan(scene: Scene, spec: LidarSpec, traj_poses: np.ndarray, t_start: float,
         rng: np.random.Generator, range_noise: float = 0.01, dropout: float = 0.02) -> dict:
    """One sweep starting at t_start [s] (trajectory time).

    Returns organized (beams, columns) arrays: xyz (.., 3) float32 in the sensor frame at
    each point's capture time (NaN: no return), intensity float32, t_ns uint32 (after
    t_start), ring uint16, kind uint8 (0 none, 1 ground, 2 cylinder, 3 box), range float64
    (noise-free, inf: none)."""
    C = spec.columns
    dt = np.arange(C) / C / spec.rate_hz
    times = t_start + dt
    pos, R = base_poses_at(traj_poses, times)
    T = spec.transform()
    org = pos + np.einsum("cij,j->ci", R, T[:3, 3])
    rot = R @ T[:3, :3]
    dirs = spec.directions()
    out_r = np.empty((spec.beams, C))
    out_k = np.empty((spec.beams, C), dtype=np.uint8)
    f = scene.field
    _cast(org, rot, dirs, times.astype(np.float64), f.origin[0], f.origin[1], f.dx,
          scene.h_field, scene.hmax, scene.win[0], scene.win[1],
          scene.states, scene.visit_time, scene.cylinders, scene.boxes, out_r, out_k)
    noisy = out_r + range_noise * rng.standard_normal(out_r.shape)
    drop = rng.random(out_r.shape) < dropout
    valid = np.isfinite(out_r) & ~drop & (noisy > MIN_RANGE)
    out_k[~valid] = KIND_NONE
    rq = np.where(valid, np.round(noisy * 1000) / 1000, np.nan)   # mm range resolution
    # coordinates on a 2^-10 m (~1 mm) lattice, like a sensor's mm range resolution
    xyz = (np.round(rq[..., None] * dirs * XYZ_STEPS) / XYZ_STEPS).astype(np.float32)
    base = np.array([0, 30.0, 80.0, 120.0], dtype=np.float32)[out_k]
    inten = base * (0.6 + 0.4 * np.abs(dirs[..., 2])) + rng.uniform(0, 5, out_r.shape)
    inten = np.where(valid, np.round(inten), 0.0).astype(np.float32)
    t_ns = np.broadcast_to(np.round(dt * 1e9).astype(np.uint32), out_r.shape).copy()
    ring = np.broadcast_to(np.arange(spec.beams, dtype=np.uint16)[:, None], out_r.shape).copy()
    return {"xyz": xyz, "intensity": inten, "t_ns": t_ns, "ring": ring, "kind": out_k,
            "range": out_r}
