"""Hand-built sessions of one world for the field store's tests: a smooth relief, a robot
driving straight lanes, ruts dug where its wheels went; each session's pair expressed in its own
map frame by a known transform (session -> world)."""

from __future__ import annotations

import math

import numpy as np
from scipy import ndimage

from torchsoil.io.terrain_pair import TerrainPair

DX = 0.02
WHEELS = np.array([[0.4, 0.5, 0], [0.4, -0.5, 1], [-0.4, 0.5, 0], [-0.4, -0.5, 1]])   # two axles, two tracks
WIDTH = 0.2
RUT = 0.02


def planar(yaw: float, tx: float, ty: float, tz: float = 0.0) -> np.ndarray:
    T = np.eye(4)
    T[:2, :2] = [[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]]
    T[:3, 3] = (tx, ty, tz)
    return T


class World:
    """A 14 m x 8 m world heightmap (from (-3, -4)) with a seeded relief, ruts added as
    sessions drive it."""

    def __init__(self, seed: int = 0, relief: float = 0.03, flat_lanes: bool = False):
        rng = np.random.default_rng(seed)
        self.origin = np.array([-3.0, -4.0])
        self.ruts: list[tuple[np.ndarray, float, float]] = []
        shape = (700, 400)
        if flat_lanes:      # no relief at all but straight furrows along x every 1.05 m
            y = self.origin[1] + np.arange(shape[1]) * DX
            self.h = np.broadcast_to(0.01 * np.cos(2 * np.pi * y / 1.05), shape).astype(np.float64).copy()
        else:
            self.h = (ndimage.gaussian_filter(rng.normal(size=shape), 12) * relief * 12
                      + ndimage.gaussian_filter(rng.normal(size=shape), 2) * 0.002)

    @staticmethod
    def _ruts(x: np.ndarray, y: np.ndarray, length: float) -> tuple[np.ndarray, np.ndarray]:
        """Cells (session-frame x, y) under a wheel's track, and wheel passes over each."""
        passes = np.zeros(np.shape(x), np.int64)
        for wx, wy, _ in WHEELS:
            passes += (np.abs(y - wy) <= WIDTH / 2) & (x >= wx) & (x <= length + wx)
        return passes > 0, passes

    def sample(self, xy: np.ndarray) -> np.ndarray:
        u = (xy[..., 0] - self.origin[0]) / DX
        v = (xy[..., 1] - self.origin[1]) / DX
        return ndimage.map_coordinates(self.h, [u, v], order=1, cval=np.nan)

    def drive(self, T: np.ndarray, length: float, t0: float, depth: float = RUT):
        """A session: base_link along its own x from 0 to `length` m at 1 m/s, its frame placed in
        the world by T. Returns (pair in the session frame, (X, Y) wheel passes of this session
        per session cell); the world keeps the ruts."""
        xs = np.arange(-1.0, length + 1.0, DX)
        ys = np.arange(-1.4, 1.4 + 1e-9, DX)
        gx, gy = np.meshgrid(xs, ys, indexing="ij")
        pts = np.stack([gx, gy], -1) @ T[:2, :2].T + T[:2, 3]
        before = self.height(pts) - T[2, 3]
        self.ruts.append((np.linalg.inv(T), length, depth))
        after = self.height(pts) - T[2, 3]
        n = int(length / 0.05) + 1
        x = np.linspace(0.0, length, n)
        poses = np.zeros((n, 7))
        poses[:, 0], poses[:, 1] = t0 + x, x
        pair = TerrainPair(DX, np.array([xs[0], ys[0]]), before.astype(np.float32), after.astype(np.float32), poses,
                           WHEELS.copy(), WIDTH)
        return pair, self._ruts(gx, gy, length)[1]

    def height(self, xy: np.ndarray) -> np.ndarray:
        """World height at world points (..., 2): the relief less every session's ruts, each a
        trough of its depth with walls 2 cm wide (a continuous surface: any grid samples it
        alike)."""
        h = self.sample(xy)
        for Ti, length, depth in self.ruts:
            s = xy @ Ti[:2, :2].T + Ti[:2, 3]
            h = h - depth * self._trough(s[..., 0], s[..., 1], length)
        return h

    @staticmethod
    def _trough(x, y, length):
        """Depth share (0..1) of the ruts of one session at its frame's (x, y)."""
        out = np.zeros(np.shape(x))
        for wy in np.unique(WHEELS[:, 1]):
            lateral = np.clip((WIDTH / 2 + 0.01 - np.abs(y - wy)) / 0.02, 0, 1)
            along = np.clip((np.minimum(x - WHEELS[:, 0].min(), length + WHEELS[:, 0].max() - x) + 0.01) / 0.02, 0, 1)
            out = np.maximum(out, lateral * along)
        return out
