"""Small terrain pairs made with the simulator itself, for estimator tests (known truth)."""

from __future__ import annotations

import math

import numpy as np
import torch
from scipy import ndimage

from torchsoil.grid import Grid
from torchsoil.io.terrain_pair import TerrainPair
from torchsoil.robot import paper_platform
from torchsoil.sim import ParamSpec, simulate, wheel_geometry


def sim_pair(length=4.0, d1=0.03, d2=0.025, chi=0.8, beta_deg=35.0, noise=0.003, seed=0, dx=0.02,
             speed=1.0, stop=None, blur=0.0) -> tuple[TerrainPair, np.ndarray]:
    """A straight drive over smooth random ground; H_b simulated with constant parameters.

    Returns the pair (noisy maps) and the noise-free simulated H_b. stop: (t0, t1) during
    which the robot stands still. blur: the change H_b - H_f measured through a Gaussian of this
    sigma, cells (scipy's, as a lidar raster spreads a rut's walls)."""
    robot = paper_platform()
    grid = Grid.covering(-1.0, -1.6, length + 1.0, 1.6, dx)
    t = np.arange(0.0, length / speed + (stop[1] - stop[0] if stop else 0.0) + 1e-9, 0.05)
    x = speed * t
    if stop is not None:
        t0, t1 = stop
        x = np.where(t < t0, speed * t, np.where(t < t1, speed * t0, speed * (t - (t1 - t0))))
    poses = np.zeros((len(t), 7))
    poses[:, 0], poses[:, 1], poses[:, 2] = t, x, 0.003
    rng = np.random.default_rng(seed)
    h0 = ndimage.gaussian_filter(rng.normal(0, 1, grid.shape), 3)
    h0 *= 0.006 / h0.std()
    geom = wheel_geometry(grid, poses, robot, dtype=torch.float64)
    theta = ParamSpec.base(2).make(1, d1=d1, d2=d2, chi=chi, beta=math.radians(beta_deg))
    hb = simulate(torch.as_tensor(h0), geom, theta).h[0].numpy()
    if blur > 0:
        hb = h0 + ndimage.gaussian_filter(hb - h0, blur, mode="nearest", truncate=3.0)
    pair = TerrainPair(dx, np.array(grid.origin), (h0 + rng.normal(0, noise, h0.shape)).astype(np.float32),
                       (hb + rng.normal(0, noise, h0.shape)).astype(np.float32), poses, robot.wheels,
                       robot.wheel_width)
    return pair, hb
