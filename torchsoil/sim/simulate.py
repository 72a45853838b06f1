"""The forward model S(H_f, T_ref, F, theta) of the paper (Algorithm 1), batched over theta."""

from __future__ import annotations

import math
from typing import NamedTuple

import torch

from torchsoil.grid import Grid
from torchsoil.robot import Robot
from torchsoil.settings import SimConfig
from torchsoil.sim.cohesive import relax_two_angle
from torchsoil.sim.deposition import deposit
from torchsoil.sim.dig import dig
from torchsoil.sim.geometry import WheelGeometry, footprint, wheel_geometry
from torchsoil.sim.params import ParamSpec
from torchsoil.sim.relaxation import relax
from torchsoil.sim.sinkage import reference_height, revisit_reference, sink

MAX_TAN_BETA = math.tan(math.radians(89.9))  # beta = 90 deg: nothing flows; avoids tan overflow


class Modifiers(NamedTuple):
    """Hooks through which model extensions change the base physics (all optional).

    Attributes:
        depth_scale: (B, K, N) factor on the sinkage of wheel k at resampled pose n, or (B, E)
            one per geometry entry (WheelGeometry.cell: a cell near one wheel's path), for
            soil that changes cell by cell (ground driven before).
        radius_scale: (B,) factor on the footprint radius (contact patch wider or narrower).
        tan_beta_intact: (B,) tangent of the angle intact ground (native, or cut by the
            wheels) stands up to, >= tan(beta): cohesive soil. The deposits are then loose soil
            that settles at beta, and `cohesive.relax_two_angle` replaces the single-angle
            relaxation (soil flows beyond beta only as far as it carries loose soil).
        chi_scale: (B,) factor on the deposit share chi (the result clipped to [0, 1]).
        beta_scale: (B,) factor on the angle of repose beta (the result clipped to
            [0.5, 89] deg).
    """

    depth_scale: torch.Tensor | None = None
    radius_scale: torch.Tensor | None = None
    tan_beta_intact: torch.Tensor | None = None
    chi_scale: torch.Tensor | None = None
    beta_scale: torch.Tensor | None = None


class SimResult(NamedTuple):
    """h: (B, X, Y) simulated surface, m; h_unrelaxed: (B, X, Y) after sinkage and deposition;
    removed, deposited, lost: (B,) volumes, m^3; iterations: (B,) relaxation updates;
    capped: (B,) bool, relaxation stopped by the iteration cap."""

    h: torch.Tensor
    h_unrelaxed: torch.Tensor
    removed: torch.Tensor
    deposited: torch.Tensor
    lost: torch.Tensor
    iterations: torch.Tensor
    capped: torch.Tensor


BETA_MIN, BETA_MAX = math.radians(0.5), math.radians(89.0)   # a scaled angle of repose, rad


def _check_heights(h: torch.Tensor, shape) -> torch.Tensor:
    if h.ndim == 2:
        h = h[None]
    if h.ndim != 3 or tuple(h.shape[1:]) != tuple(shape):
        raise ValueError(f"heights must be (B, X, Y) = (B, {shape[0]}, {shape[1]}), got {tuple(h.shape)}")
    bad = ~torch.isfinite(h.detach())
    if bad.any():
        b, i, j = torch.nonzero(bad)[0].tolist()
        raise ValueError(f"heights contain {int(bad.sum())} NaN/inf cells (first: batch {b}, "
                         f"cell [{i}, {j}]); fill or crop them before simulating")
    return h


def simulate(h_front: torch.Tensor, geom: WheelGeometry, theta: torch.Tensor,
             config: SimConfig | None = None, spec: ParamSpec | None = None,
             modifiers: Modifiers | None = None, h_ref: torch.Tensor | None = None) -> SimResult:
    """Simulate the robot's passage over h_front for a batch of parameter sets.

    Args:
        h_front: (X, Y) or (B, X, Y) surface before the robot, m (finite everywhere).
        geom: wheel-path geometry from `wheel_geometry` on the same grid.
        theta: (B, P) parameters (d_1..d_T [m], chi, beta [rad], then any extension
            parameters, which are read through `modifiers`).
        config: simulator settings.
        spec: parameter layout and bounds (default: the base layout for geom's tracks).
        modifiers: extension hooks (see `Modifiers`).
        h_ref: (B|1, X, Y) reference height; default: h_front smoothed over a disc of
            radius config.ref_radius * wheel_width / 2.

    Returns:
        SimResult with (B, X, Y) surfaces on theta's device and dtype.
    """
    config = config or SimConfig()
    modifiers = modifiers or Modifiers()
    spec = spec or ParamSpec.base(geom.n_tracks)
    theta = spec.check(theta)
    h = _check_heights(h_front.to(theta.dtype), geom.shape)
    B = theta.shape[0]
    if h.shape[0] not in (1, B):
        raise ValueError(f"h_front batch {h.shape[0]} does not match theta batch {B}")
    T = geom.n_tracks
    d = theta[:, [spec.index(f"d{k + 1}") for k in range(T)]]
    chi, beta = theta[:, spec.index("chi")], theta[:, spec.index("beta")]
    dt = theta.dtype
    if modifiers.chi_scale is not None:
        chi = (chi * modifiers.chi_scale.to(dt).expand(B)).clamp(0.0, 1.0)
    if modifiers.beta_scale is not None:
        beta = (beta * modifiers.beta_scale.to(dt).expand(B)).clamp(BETA_MIN, BETA_MAX)
    fp = geom.nominal if modifiers.radius_scale is None else footprint(geom, modifiers.radius_scale, dt)
    depth = d[:, geom.track[geom.wheel]]                                   # (B, E)
    if modifiers.depth_scale is not None and modifiers.depth_scale.ndim == 2:
        depth = depth * modifiers.depth_scale.to(dt).expand(B, -1)
    elif modifiers.depth_scale is not None:
        K, N = geom.n_wheels, geom.poses.shape[0]
        scale = modifiers.depth_scale.to(dt).reshape(B, K * N)
        depth = depth * scale[:, geom.wheel * N + geom.pose]
    if h_ref is None:
        h_ref = reference_height(h, config.ref_radius * geom.radius, geom.dx)
    if config.dig_order == "wheel" and geom.order is not None:
        h_pre, removed, added, lost = dig_in_turn(h, h_ref, geom, fp, depth, chi, config)
    else:
        h_pre, removed, added, lost = dig(h, h_ref, geom.cell, fp.covered, fp.s.to(dt), depth, fp.owner, fp.band,
                                          geom.bin, geom.n_bins * geom.n_wheels, chi, config.backend)

    tan_beta = torch.tan(beta).clamp(max=MAX_TAN_BETA)
    relax_args = (geom.dx, geom.domain, config.tau, config.max_iter, config.fixed_iter, config.eps_scale)
    if modifiers.tan_beta_intact is None:
        rr = relax(h_pre, tan_beta, *relax_args, config.backend)
    else:
        intact = modifiers.tan_beta_intact.to(dt).clamp(max=MAX_TAN_BETA).expand(B)
        rr = relax_two_angle(h_pre, added, tan_beta, intact, *relax_args, backend=config.backend)
    cell = geom.dx**2
    return SimResult(rr.h, h_pre, removed.flatten(1).sum(1) * cell,
                     added.flatten(1).sum(1) * cell, lost * cell, rr.iterations, rr.capped)


def dig_in_turn(h: torch.Tensor, h_ref: torch.Tensor, geom: WheelGeometry, fp, depth: torch.Tensor,
                chi: torch.Tensor, config: SimConfig):
    """The axles dig in the order they meet the ground (sim.dig_order "wheel"), each from the
    surface the axles ahead of it left, their spoil beside the rut included: the wheels of a
    turn dig (`sink`) and lay their share chi beside their ruts (`deposit`) before the next
    turn digs. On the cells an earlier turn dug, a trailing wheel's reference height is that
    surface's `revisit_reference` (sim.revisit_ref; "footprint": the mean over its whole
    footprint, the level a wheel that spans the rut rests on), h_ref elsewhere. Relaxation
    waits until every turn has dug.

    h: (B|1, X, Y) surface before the robot, m; h_ref: (B|1, X, Y) its reference height, m;
    fp: `footprint(geom, ...)`; depth: (B, E) sinkage of each wheel-cell entry, m; chi: (B,).
    Returns h_unrelaxed (B, X, Y), removed (B, X, Y) [m], added (B, X, Y) [m], lost (B,) [m]."""
    B = max(h.shape[0], depth.shape[0])
    out = h.expand(B, -1, -1)
    dug = removed = added = lost = None
    s = fp.s.to(out.dtype)
    for r in range(int(geom.order.max()) + 1 if geom.order.numel() else 0):
        m = geom.order == r
        if not bool(m.any()):
            continue
        ref = h_ref if dug is None else revisit_reference(out, h_ref, dug, config.revisit_ref, config.ref_radius,
                                                          geom.radius, geom.dx)
        cut, rem = sink(out, ref, geom.cell[m], fp.covered[:, m], s[:, m], depth[:, m])
        add, gone = deposit(rem, geom.cell, fp.owner, fp.band, geom.bin, geom.n_bins * geom.n_wheels, chi)
        out = cut + add
        c = fp.covered[:, m].to(out.dtype)
        now = torch.zeros(c.shape[0], out[0].numel(), dtype=out.dtype, device=out.device)
        now = now.scatter_reduce(1, geom.cell[m].expand(c.shape[0], -1), c, "amax").reshape(-1, *out.shape[1:]) > 0
        dug = now if dug is None else dug | now
        removed, added, lost = ((rem, add, gone) if removed is None else
                                (removed + rem, added + add, lost + gone))
    if removed is None:
        zero = torch.zeros_like(out)
        return out, zero, zero, out.new_zeros(B)
    return out, removed, added, lost


def simulate_path(h_front: torch.Tensor, grid: Grid, poses, robot: Robot, theta: torch.Tensor,
                  config: SimConfig | None = None, **kwargs) -> SimResult:
    """Convenience: geometry for (grid, poses, robot), then `simulate`."""
    config = config or SimConfig()
    geom = wheel_geometry(grid, poses, robot, pose_spacing=config.pose_spacing,
                          band_width=config.band_width, relax_margin=config.relax_margin,
                          device=theta.device, dtype=theta.dtype)
    return simulate(h_front, geom, theta, config, **kwargs)
