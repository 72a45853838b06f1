"""Forward-simulation benchmark on one paper window (0.8 m of ground + footprint margin by a
3 m corridor, every wheel passing over it), per cell size, batch size and stage. Torch runs
single-threaded (the relaxation kernel still uses one thread per batch element)."""

from __future__ import annotations

import math
import time
from functools import partial

import numpy as np
import torch

from torchsoil.grid import Grid
from torchsoil.robot import paper_platform
from torchsoil.sim import ParamSpec, SimConfig, simulate, wheel_geometry
from torchsoil.sim.relaxation import relax
from torchsoil.sim.sinkage import reference_height

WINDOW = 0.8  # m


def paper_window(dx: float, seed: int = 0, noise: float = 0.003):
    """(grid, poses (N, 3) x y yaw, robot, h_front (X, Y) float64) for one straight window."""
    robot = paper_platform()
    margin = robot.wheel_width / 2
    grid = Grid.covering(-margin, -1.5, WINDOW + margin, 1.5, dx)
    reach = robot.wheels[:, 0].max() + margin
    xs = np.arange(-reach - 0.05, WINDOW + reach + 0.05 + 1e-9, 0.01)
    poses = np.column_stack([xs, np.zeros_like(xs), np.zeros_like(xs)])
    rng = np.random.default_rng(seed)
    h = torch.as_tensor(rng.normal(0.0, noise, grid.shape))
    return grid, poses, robot, h


def _forward_backward(h, geom, theta, cfg):
    theta = theta.clone().requires_grad_(True)
    simulate(h, geom, theta, cfg).h.sum().backward()


def _reference_backward(h, radius, dx):
    reference_height(h, radius, dx).sum().backward()


def _median_ms(fn, repeat: int) -> float:
    fn()
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return 1e3 * float(np.median(times))


def run(quick: bool = False) -> dict[str, float]:
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # as the estimation job runs: window tensors are too small to share
    try:
        return _run(quick)
    finally:
        torch.set_num_threads(threads)


def _run(quick: bool) -> dict[str, float]:
    out: dict[str, float] = {}
    repeat = 5 if quick else 20
    dxs = (0.02,) if quick else (0.015, 0.02, 0.03, 0.05, 0.075)
    spec = ParamSpec.base(2)
    for dx in dxs:
        grid, poses, robot, h = paper_window(dx)
        geom = wheel_geometry(grid, poses, robot, dtype=torch.float64)
        out[f"sim_cells_dx{dx}"] = float(np.prod(grid.shape))
        out[f"sim_geometry_ms_dx{dx}"] = _median_ms(partial(wheel_geometry, grid, poses, robot), 3)
        for B in (1, 5):
            theta = spec.make(B, d1=0.03, d2=0.025, chi=0.8, beta=math.radians(30))
            cfg = SimConfig()
            res = simulate(h, geom, theta, cfg)
            key = f"dx{dx}_b{B}"
            out[f"sim_forward_ms_{key}"] = _median_ms(partial(simulate, h, geom, theta, cfg), repeat)
            t_relax = _median_ms(partial(relax, res.h_unrelaxed, torch.tan(theta[:, 3]), dx, geom.domain),
                                 repeat)
            out[f"sim_relax_ms_{key}"] = t_relax
            out[f"sim_sink_deposit_ms_{key}"] = out[f"sim_forward_ms_{key}"] - t_relax
            it = float(res.iterations.double().mean())
            out[f"sim_relax_iterations_{key}"] = it
            out[f"sim_cell_iterations_per_s_{key}"] = B * it * float(geom.domain.sum()) / (t_relax / 1e3)
            if B == 5:
                torch_cfg = SimConfig(backend="torch")
                out[f"sim_forward_torch_ms_{key}"] = _median_ms(
                    partial(simulate, h, geom, theta, torch_cfg), max(3, repeat // 4))
                out[f"sim_forward_backward_ms_{key}"] = _median_ms(
                    partial(_forward_backward, h, geom, theta, cfg), repeat)
                wheel_cfg = SimConfig(dig_order="wheel")          # axles dig in turn
                out[f"sim_forward_wheel_order_ms_{key}"] = _median_ms(
                    partial(simulate, h, geom, theta, wheel_cfg), repeat)
                out[f"sim_forward_backward_wheel_order_ms_{key}"] = _median_ms(
                    partial(_forward_backward, h, geom, theta, wheel_cfg), repeat)
                hb = h.expand(B, -1, -1).clone().requires_grad_(True)  # a trailing wheel's reference, with its gradient
                out[f"sim_reference_height_ms_{key}"] = _median_ms(
                    partial(_reference_backward, hb, robot.wheel_width / 2, dx), repeat)
    grid, poses, robot, h = paper_window(0.02)
    geom = wheel_geometry(grid, poses, robot, dtype=torch.float64)
    for deg in (20, 30, 45):
        theta = spec.make(1, d1=0.03, d2=0.025, chi=0.8, beta=math.radians(deg))
        out[f"sim_relax_iterations_beta{deg}"] = float(simulate(h, geom, theta).iterations[0])
    return out
