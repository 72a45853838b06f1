"""Wheel-path geometry on the grid: where each wheel passes, computed once per trajectory.

Everything here depends on the trajectory, the robot and the grid only, never on the soil
parameters, so an estimator computes it once per window and reuses it for every simulation.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch
from scipy.spatial import cKDTree

from torchsoil.grid import Grid
from torchsoil.robot import Robot

FAR = 1e6  # m, distance stored for cells out of reach of every pose


class WheelGeometry(NamedTuple):
    """Per-cell geometry of K wheel paths on an (X, Y) grid.

    dist:       (K, X, Y) distance from the cell centre to the nearest pose of wheel k, m
                (FAR beyond the search radius).
    lateral:    (K, X, Y) signed offset of the cell from wheel k's centre line at that pose,
                left positive, m.
    pose_index: (K, X, Y) int64, index of that pose in `poses`.
    bin_index:  (K, X, Y) int64, deposition bin (k * n_bins + arc-length bin of the pose).
    track:      (K,) int64, sinkage parameter index of each wheel.
    domain:     (X, Y) bool, relaxation domain (cells near any wheel path).
    poses:      (N, 4) resampled poses t [s], x, y [m], yaw [rad].
    n_bins:     deposition bins per wheel.
    radius:     nominal footprint radius (half the wheel width), m.
    flat_fraction: tyre taper f (FORMATS.md section 2).
    dx:         cell edge, m.
    band_width: deposition band width, m.
    """

    dist: torch.Tensor
    lateral: torch.Tensor
    pose_index: torch.Tensor
    bin_index: torch.Tensor
    track: torch.Tensor
    domain: torch.Tensor
    poses: torch.Tensor
    n_bins: int
    radius: float
    flat_fraction: float
    dx: float
    band_width: float

    @property
    def n_tracks(self) -> int:
        return int(self.track.max().item()) + 1

    @property
    def shape(self) -> tuple[int, int]:
        return tuple(self.dist.shape[1:])


def planar_poses(poses) -> np.ndarray:
    """Poses as (N, 4) t, x, y, yaw from FORMATS.md (N, 7) [t, x, y, z, roll, pitch, yaw]
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
    frac = np.concatenate([np.arange(n) / n for n in n_sub])
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
        poses: base_link poses, (N, 7) FORMATS.md rows, (N, 4) t, x, y, yaw or (N, 3) x, y, yaw.
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
    reach = max(radius * max_radius_scale + (band_width + 1) * dx,
                radius + relax_margin * robot.wheel_width) + dx
    bin_len = 2 * dx
    xs, ys = grid.centers()
    cells = np.stack(np.meshgrid(xs, ys, indexing="ij"), axis=-1).reshape(-1, 2)
    K, N = w.shape[:2]
    dist = np.full((K, len(cells)), FAR)
    lateral = np.zeros((K, len(cells)))
    pidx = np.zeros((K, len(cells)), dtype=np.int64)
    bins = np.zeros((K, len(cells)), dtype=np.int64)
    arcs = np.concatenate([np.zeros((K, 1)), np.cumsum(np.linalg.norm(np.diff(w, axis=1), axis=-1), 1)], 1)
    n_bins = int(np.floor(arcs[:, -1].max() / bin_len)) + 1
    for k in range(K):
        head = _headings(w[k], p[:, 3], 1e-6 * dx)
        d, i = cKDTree(w[k]).query(cells, distance_upper_bound=reach)
        hit = np.isfinite(d)
        ih = i[hit]
        rel = cells[hit] - w[k, ih]
        dist[k, hit] = d[hit]
        lateral[k, hit] = -np.sin(head[ih]) * rel[:, 0] + np.cos(head[ih]) * rel[:, 1]
        pidx[k, hit] = ih
        bins[k, hit] = k * n_bins + np.floor(arcs[k, ih] / bin_len).astype(np.int64)
    domain = dist.min(axis=0) <= radius + relax_margin * robot.wheel_width
    shape = (K, *grid.shape)
    kw = dict(device=device)
    return WheelGeometry(
        dist=torch.as_tensor(dist.reshape(shape), dtype=dtype, **kw),
        lateral=torch.as_tensor(lateral.reshape(shape), dtype=dtype, **kw),
        pose_index=torch.as_tensor(pidx.reshape(shape), **kw),
        bin_index=torch.as_tensor(bins.reshape(shape), **kw),
        track=torch.as_tensor(robot.track, **kw),
        domain=torch.as_tensor(domain.reshape(grid.shape), **kw),
        poses=torch.as_tensor(p, dtype=torch.float64, **kw),
        n_bins=n_bins,
        radius=radius,
        flat_fraction=robot.wheel_flat_fraction,
        dx=dx,
        band_width=band_width * dx,
    )
