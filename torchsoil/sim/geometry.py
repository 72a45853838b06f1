"""Wheel-path geometry on the grid: where each wheel passes, computed once per trajectory.

Everything here depends on the trajectory, the robot and the grid only, never on the soil
parameters, so an estimator computes it once per window and reuses it for every simulation.
The wheel-cell incidence is sparse: E entries (wheel k, cell c) for the cells within reach of
wheel k's footprint or deposition band; everything else on the grid is left alone.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch
from scipy.spatial import cKDTree

from torchsoil.grid import Grid
from torchsoil.robot import Robot

INF = float("inf")


class Footprint(NamedTuple):
    """Which entries dig and which receive deposits, at one footprint radius.

    covered: (B|1, E) bool, the entry's cell lies inside wheel k's swept footprint.
    s:       (B|1, E) centrality taper of wheel k at the cell, in [0, 1].
    owner:   (B|1, E) bool, wheel k is the one that digs the cell (the most central wheel;
             ties go to the lower wheel index).
    band:    (B|1, E) bool, the cell lies in wheel k's deposition band and in no footprint.
    covered_any: (B|1, X, Y) bool, the cell lies inside some footprint.
    """

    covered: torch.Tensor
    s: torch.Tensor
    owner: torch.Tensor
    band: torch.Tensor
    covered_any: torch.Tensor


class WheelGeometry(NamedTuple):
    """Sparse geometry of K wheel paths on an (X, Y) grid.

    cell:    (E,) int64 flat cell index i * Y + j of each entry.
    wheel:   (E,) int64 wheel index k of each entry.
    dist:    (E,) distance from the cell centre to wheel k's nearest pose, m.
    lateral: (E,) signed offset of the cell from wheel k's centre line there, left positive, m.
    pose:    (E,) int64 index of that pose in `poses`.
    bin:     (E,) int64 deposition bin: k * n_bins + arc-length bin (2 cells) of the pose.
    track:   (K,) int64 sinkage parameter index of each wheel.
    domain:  (X, Y) bool relaxation domain (cells near any wheel path).
    poses:   (N, 4) resampled poses t [s], x, y [m], yaw [rad].
    shape:   (X, Y).
    n_bins:  deposition bins per wheel.
    radius:  nominal footprint radius (half the wheel width), m.
    flat_fraction: tyre taper f (docs/formats.md section 2).
    dx:      cell edge, m.
    band_width: deposition band width, m.
    nominal: Footprint at the nominal radius, precomputed.
    section_exponent: exponent e of the taper (sim.sinkage.taper; 1: docs/formats.md's).
    order:   (E,) int64 turn of the entry's wheel at its pose: 0 for the axle that meets the
             ground first in the direction of travel, 1 for the next one, ...
             (`dig_order`; SimConfig.dig_order "wheel").
    """

    cell: torch.Tensor
    wheel: torch.Tensor
    dist: torch.Tensor
    lateral: torch.Tensor
    pose: torch.Tensor
    bin: torch.Tensor
    track: torch.Tensor
    domain: torch.Tensor
    poses: torch.Tensor
    shape: tuple[int, int]
    n_bins: int
    radius: float
    flat_fraction: float
    dx: float
    band_width: float
    nominal: Footprint
    section_exponent: float = 1.0
    order: torch.Tensor | None = None

    @property
    def n_tracks(self) -> int:
        return int(self.track.max().item()) + 1

    @property
    def n_wheels(self) -> int:
        return int(self.track.shape[0])


def footprint(geom: WheelGeometry, radius_scale: torch.Tensor | None = None,
              dtype=None) -> Footprint:
    """Footprint masks at the nominal radius times radius_scale ((B,) or None)."""
    from torchsoil.sim.sinkage import taper

    dtype = dtype or geom.dist.dtype
    dist, lateral = geom.dist.to(dtype)[None], geom.lateral.to(dtype)[None]
    radius = geom.radius if radius_scale is None else geom.radius * radius_scale.to(dtype)[:, None]
    covered = dist <= radius
    s = taper(lateral / radius, geom.flat_fraction, geom.section_exponent)
    B = covered.shape[0]
    X, Y = geom.shape
    cell = geom.cell.expand(B, -1)
    covered_any = torch.zeros(B, X * Y, dtype=dtype, device=dist.device).scatter_reduce(
        1, cell, covered.to(dtype), "amax") > 0
    rank = torch.where(covered, s + 1, torch.zeros_like(s)) - 1e-6 * geom.wheel.to(dtype)
    best = torch.full((B, X * Y), -INF, dtype=dtype, device=dist.device).scatter_reduce(
        1, cell, rank, "amax")
    owner = covered & (rank == best.gather(1, cell))
    band = (dist > radius) & (dist <= radius + geom.band_width) & ~covered_any.gather(1, cell)
    return Footprint(covered, s, owner, band, covered_any.reshape(B, X, Y))


def planar_poses(poses) -> np.ndarray:
    """Poses as (N, 4) t, x, y, yaw from docs/formats.md (N, 7) [t, x, y, z, roll, pitch, yaw]
    or (N, 3) [x, y, yaw] (t then counts poses)."""
    p = np.asarray(poses, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] not in (3, 4, 7) or len(p) == 0:
        raise ValueError(f"poses must be (N, 7), (N, 4) or (N, 3) with N >= 1, got {p.shape}")
    if not np.all(np.isfinite(p)):
        raise ValueError("poses contain NaN or infinite values")
    if p.shape[1] == 7:
        return p[:, [0, 1, 2, 6]].copy()
    if p.shape[1] == 3:
        return np.column_stack([np.arange(len(p), dtype=np.float64), p])
    return p.copy()


def wheel_positions(poses: np.ndarray, wheels_xy: np.ndarray) -> np.ndarray:
    """(N, 4) poses, (K, 2) wheel offsets in base_link -> (K, N, 2) world wheel centres, m."""
    c, s = np.cos(poses[:, 3]), np.sin(poses[:, 3])
    wx, wy = wheels_xy[:, 0:1], wheels_xy[:, 1:2]
    x = poses[None, :, 1] + c[None] * wx - s[None] * wy
    y = poses[None, :, 2] + s[None] * wx + c[None] * wy
    return np.stack([x, y], axis=-1)


def resample_poses(poses: np.ndarray, wheels_xy: np.ndarray, max_step: float) -> np.ndarray:
    """Insert poses (linear in t, x, y, unwrapped yaw) so no wheel moves more than max_step [m]
    between consecutive poses. (N, 4) -> (M, 4)."""
    p = poses.copy()
    p[:, 3] = np.unwrap(p[:, 3])
    if len(p) < 2:
        return p
    w = wheel_positions(p, wheels_xy)
    step = np.linalg.norm(np.diff(w, axis=1), axis=-1).max(axis=0)  # (N-1,)
    n_sub = np.maximum(1, np.ceil(step / max_step).astype(np.int64))
    per = np.repeat(n_sub, n_sub)                                   # each inserted pose's n
    frac = (np.arange(per.size) - np.repeat(np.cumsum(n_sub) - n_sub, n_sub)) / per   # k / n, k < n
    seg = np.repeat(np.arange(len(p) - 1), n_sub)
    out = p[seg] + frac[:, None] * (p[seg + 1] - p[seg])
    return np.vstack([out, p[-1:]])


def _headings(w: np.ndarray, yaw: np.ndarray, eps: float) -> np.ndarray:
    """Travel direction of one wheel path (N, 2), falling back to yaw where it stands still."""
    if len(w) < 2:
        return yaw.copy()
    d = np.gradient(w, axis=0)
    moving = np.linalg.norm(d, axis=1) > eps
    return np.where(moving, np.arctan2(d[:, 1], d[:, 0]), yaw)


def dig_order(poses: np.ndarray, wheels_x: np.ndarray, eps: float = 1e-9) -> np.ndarray:
    """(K, N) int64 turn of each wheel at each pose: how many axles (distinct body-frame x of
    the wheels, m) meet the ground before it in the direction the robot moves there (forward
    or reversing; standing still counts as forward). poses: (N, 4) t, x, y, yaw."""
    v = np.gradient(poses[:, 1:3], axis=0) if len(poses) > 1 else np.zeros((len(poses), 2))
    forward = v[:, 0] * np.cos(poses[:, 3]) + v[:, 1] * np.sin(poses[:, 3]) >= -eps
    x = np.round(np.asarray(wheels_x, np.float64), 6)
    axles = np.unique(x)
    ahead = (axles[None, :] > x[:, None]).sum(1)     # (K,) axles in front
    behind = (axles[None, :] < x[:, None]).sum(1)    # (K,) axles behind
    return np.where(forward[None, :], ahead[:, None], behind[:, None]).astype(np.int64)


def wheel_geometry(
    grid: Grid,
    poses,
    robot: Robot,
    *,
    pose_spacing: float = 0.5,
    band_width: float = 1.0,
    relax_margin: float = 2.0,
    max_radius_scale: float = 1.5,
    device=None,
    dtype=torch.float32,
) -> WheelGeometry:
    """Precompute where each wheel passes on the grid.

    Args:
        grid: the heightmap grid.
        poses: base_link poses, (N, 7) docs/formats.md rows, (N, 4) t, x, y, yaw or (N, 3) x, y, yaw.
        robot: wheel layout.
        pose_spacing: resample so wheels move at most this many cells per pose.
        band_width: deposition band width beside the rut, in cells.
        relax_margin: relaxation domain half-width beyond the footprint, in wheel widths.
        max_radius_scale: largest footprint-radius scale a model extension may ask for.
    """
    dx = grid.dx
    p = resample_poses(planar_poses(poses), robot.wheels[:, :2], pose_spacing * dx)
    w = wheel_positions(p, robot.wheels[:, :2])  # (K, N, 2)
    radius = robot.wheel_width / 2
    reach = radius * max_radius_scale + (band_width + 0.5) * dx
    domain_reach = radius + relax_margin * robot.wheel_width
    bin_len = 2 * dx
    xs, ys = grid.centers()
    cells = np.stack(np.meshgrid(xs, ys, indexing="ij"), axis=-1).reshape(-1, 2)
    arcs = np.concatenate([np.zeros((len(w), 1)),
                           np.cumsum(np.linalg.norm(np.diff(w, axis=1), axis=-1), axis=1)], axis=1)
    n_bins = int(np.floor(arcs[:, -1].max() / bin_len)) + 1
    near = np.full(len(cells), np.inf)
    cols = {n: [] for n in ("cell", "wheel", "dist", "lateral", "pose", "bin", "order")}
    turn = dig_order(p, robot.wheels[:, 0])
    far = max(reach, domain_reach)
    for k in range(len(w)):
        head = _headings(w[k], p[:, 3], 1e-6 * dx)
        lo, hi = w[k].min(0) - far, w[k].max(0) + far  # only cells in the path's bounding box
        box = np.flatnonzero(np.all((cells >= lo) & (cells <= hi), axis=1))
        d = np.full(len(cells), np.inf)
        i = np.zeros(len(cells), dtype=np.int64)
        d[box], i[box] = cKDTree(w[k]).query(cells[box], distance_upper_bound=far)
        near = np.minimum(near, d)
        c = np.flatnonzero(d <= reach)
        rel = cells[c] - w[k, i[c]]
        h = head[i[c]]
        cols["cell"].append(c)
        cols["wheel"].append(np.full(len(c), k))
        cols["dist"].append(d[c])
        cols["lateral"].append(-np.sin(h) * rel[:, 0] + np.cos(h) * rel[:, 1])
        cols["pose"].append(i[c])
        cols["order"].append(turn[k, i[c]])
        cols["bin"].append(k * n_bins + np.floor(arcs[k, i[c]] / bin_len).astype(np.int64))
    col = {n: np.concatenate(v) for n, v in cols.items()}
    ints = dict(device=device, dtype=torch.int64)
    floats = dict(device=device, dtype=dtype)
    geom = WheelGeometry(
        cell=torch.as_tensor(col["cell"], **ints),
        wheel=torch.as_tensor(col["wheel"], **ints),
        dist=torch.as_tensor(col["dist"], **floats),
        lateral=torch.as_tensor(col["lateral"], **floats),
        pose=torch.as_tensor(col["pose"], **ints),
        bin=torch.as_tensor(col["bin"], **ints),
        track=torch.as_tensor(robot.track, **ints),
        domain=torch.as_tensor((near <= domain_reach).reshape(grid.shape), device=device),
        poses=torch.as_tensor(p, dtype=torch.float64, device=device),
        shape=grid.shape,
        n_bins=n_bins,
        radius=radius,
        flat_fraction=robot.wheel_flat_fraction,
        dx=dx,
        band_width=band_width * dx,
        nominal=None,
        section_exponent=robot.wheel_section_exponent,
        order=torch.as_tensor(col["order"], **ints),
    )
    return geom._replace(nominal=footprint(geom))
