"""Pure tensor functions of the soil-traverse environment, batched over N robots.

Kinematics of the dual-steering platform, local patches cut from an (N, X, Y) field, the
geometry of each wheel's short segment per step, the soil deformation of one step (the
simulator's stages `taper`, `reference_height`, `sink`, `deposit`, `relax`), observation
sampling and the reward. All lengths in metres, angles in radians, times in seconds.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch

from torchsoil.grid import Grid
from torchsoil.sim.deposition import deposit
from torchsoil.sim.relaxation import relax
from torchsoil.sim.sinkage import reference_height, sink, taper


def step_pose(pose: torch.Tensor, speed: torch.Tensor, curvature: torch.Tensor,
              dt: float) -> torch.Tensor:
    """Move base_link along a circular arc (symmetric dual steering: yaw rate = v * kappa).

    Args:
        pose: (N, 3) x [m], y [m], yaw [rad].
        speed: (N,) m/s (negative: reverse).
        curvature: (N,) 1/m, left positive.
        dt: s.

    Returns:
        (N, 3) pose after dt, exact for a constant arc.
    """
    ds = speed * dt
    dyaw = ds * curvature
    chord = ds * torch.sinc(dyaw / (2 * math.pi))       # 2 sin(dyaw/2) / kappa
    mid = pose[:, 2] + dyaw / 2
    return torch.stack([pose[:, 0] + chord * torch.cos(mid), pose[:, 1] + chord * torch.sin(mid),
                        pose[:, 2] + dyaw], dim=1)


def to_world(pose: torch.Tensor, body_xy: torch.Tensor) -> torch.Tensor:
    """Body-frame points (M, 2) -> world (N, M, 2) for poses (N, 3)."""
    c, s = torch.cos(pose[:, 2])[:, None], torch.sin(pose[:, 2])[:, None]
    bx, by = body_xy[None, :, 0], body_xy[None, :, 1]
    return torch.stack([pose[:, 0:1] + c * bx - s * by, pose[:, 1:2] + s * bx + c * by], dim=-1)


def patch_origin(center_xy: torch.Tensor, grid: Grid, size: int) -> torch.Tensor:
    """(N, 2) int64 index of cell [0, 0] of the size x size patch centred at `center_xy` (N, 2),
    shifted so the patch lies inside the field."""
    o = torch.tensor(grid.origin, dtype=center_xy.dtype, device=center_xy.device)
    c = torch.round((center_xy - o) / grid.dx).long() - size // 2
    hi = torch.tensor([grid.shape[0] - size, grid.shape[1] - size], device=c.device)
    return torch.minimum(c.clamp_min(0), hi)


def patch_index(origin: torch.Tensor, size: int, grid: Grid) -> torch.Tensor:
    """(N, size*size) flat indices into a row-major (X, Y) field of the patches at `origin` (N, 2)."""
    ar = torch.arange(size, device=origin.device)
    i = origin[:, 0, None, None] + ar[None, :, None]
    j = origin[:, 1, None, None] + ar[None, None, :]
    return (i * grid.shape[1] + j).flatten(1)


class WheelWindows(NamedTuple):
    """W x W cell windows around each wheel's segment of one step, flattened to E = N*K*W*W
    entries (robot-major, then wheel, then cell).

    cell: (E,) int64 flat index into the (N, P, P) patch stack; dist: (E,) distance to the
    segment, m; lateral: (E,) signed offset from its line, left positive, m; along: (E,)
    position along the segment's line from its start (not clamped to the segment), m;
    length: (E,) segment length, m; wheel: (E,) int64 wheel k; robot: (E,) int64 robot n.
    """

    cell: torch.Tensor
    dist: torch.Tensor
    lateral: torch.Tensor
    along: torch.Tensor
    length: torch.Tensor
    wheel: torch.Tensor
    robot: torch.Tensor


def wheel_windows(start: torch.Tensor, end: torch.Tensor, heading: torch.Tensor,
                  patch_origin_ij: torch.Tensor, size: int, window: int, grid: Grid) -> WheelWindows:
    """Geometry of the cells near each wheel's straight segment for one step.

    Args:
        start, end: (N, K, 2) wheel centres before and after the step, m.
        heading: (N,) yaw used as the direction of a wheel that does not move, rad.
        patch_origin_ij: (N, 2) int64 field index of cell [0, 0] of each robot's patch.
        size: patch edge P, cells; window: W, cells (W <= P).
    """
    N, K = start.shape[:2]
    dt = start.dtype
    dev = start.device
    mid = (start + end) / 2
    o = torch.tensor(grid.origin, dtype=dt, device=dev)
    w0 = torch.round((mid - o) / grid.dx).long() - window // 2 - patch_origin_ij[:, None]
    w0 = w0.clamp(0, size - window)                                     # (N, K, 2) in the patch
    ar = torch.arange(window, device=dev)
    ii = w0[..., 0, None] + ar                                           # (N, K, W)
    jj = w0[..., 1, None] + ar
    xs = grid.origin[0] + (patch_origin_ij[:, None, 0, None] + ii).to(dt) * grid.dx
    ys = grid.origin[1] + (patch_origin_ij[:, None, 1, None] + jj).to(dt) * grid.dx
    u = end - start
    length = torch.linalg.vector_norm(u, dim=-1)                         # (N, K)
    still = length < 1e-9
    ux = torch.where(still, torch.cos(heading)[:, None], u[..., 0] / length.clamp_min(1e-9))
    uy = torch.where(still, torch.sin(heading)[:, None], u[..., 1] / length.clamp_min(1e-9))
    rx = (xs - start[..., 0, None])[..., :, None]                        # (N, K, W, 1)
    ry = (ys - start[..., 1, None])[..., None, :]                        # (N, K, 1, W)
    ux4, uy4, len4 = ux[..., None, None], uy[..., None, None], length[..., None, None]
    along = rx * ux4 + ry * uy4
    lateral = ry * ux4 - rx * uy4
    foot = along.clamp(min=0.0).minimum(len4)
    dist = torch.sqrt((rx - foot * ux4) ** 2 + (ry - foot * uy4) ** 2)
    robot = torch.arange(N, device=dev)[:, None, None, None]
    cell = (robot * size + ii[..., :, None]) * size + jj[..., None, :]
    shape = (N, K, window, window)
    wheel = torch.arange(K, device=dev)[None, :, None, None].expand(shape)
    return WheelWindows(cell.flatten(), dist.flatten(), lateral.flatten(), along.flatten(),
                        len4.expand(shape).flatten(), wheel.flatten(), robot.expand(shape).flatten())


class StepSoil(NamedTuple):
    """Outcome of one step on N patches.

    h: (N, P, P) surface after the step, m; ref: (E,) reference height used at each entry's
    cell, m; covered: (E,) bool, the entry's cell is under some wheel this step; owner: (E,)
    bool, the entry's wheel dug its cell (one entry per covered cell); removed, deposited:
    (N,) volumes, m^3; iterations: (N,) relaxation updates.
    """

    h: torch.Tensor
    ref: torch.Tensor
    covered: torch.Tensor
    owner: torch.Tensor
    removed: torch.Tensor
    deposited: torch.Tensor
    iterations: torch.Tensor


def deform(h: torch.Tensor, tan_beta: torch.Tensor, win: WheelWindows, ref: torch.Tensor,
           visit: torch.Tensor, depth: torch.Tensor, chi: torch.Tensor, n_wheels: int,
           radius: float, flat_fraction: float, dx: float, band_width: float,
           ref_radius: float = 0.5, fixed_iter: int | None = 4, tau: float = 0.01,
           max_iter: int = 2000, eps_scale: float = 4.0, backend: str = "auto") -> StepSoil:
    """Wheels dig, deposit beside their ruts and the surface relaxes, on N local patches.

    The N patches are one (1, N*P, P) surface for the simulator's sparse stages (`sink`,
    `deposit`), then relax as (N, P, P). Deposition bins are 2 cells of a wheel's segment
    extended by the footprint radius at both ends, one set per robot and wheel, so the soil
    dug ahead of the segment's end lands beside it too.
    A cell in an ongoing visit keeps the reference height of that visit, so the rear wheel in
    the front wheel's rut and overlapping steps dig no deeper (the simulator's min over
    poses); a later visit digs again from the surface it finds.

    Args:
        h: (N, P, P) surface, m.
        tan_beta: (N, P, P) tangent of the angle of repose per cell.
        win: E wheel-window entries of this step (`wheel_windows`).
        ref: (E,) reference height of the entry's cell in its ongoing visit, m.
        visit: (E,) bool, the entry's cell is in an ongoing visit (`ref` applies).
        depth: (E,) sinkage d of the entry's wheel track at its cell, m.
        chi: (E,) displacement-compaction ratio at the entry's cell.
        n_wheels: K.
        radius: footprint radius (half the wheel width), m.
        flat_fraction: tyre taper f.
        dx: cell edge, m.
        band_width: width of the deposition band beside each rut, m.
        ref_radius: reference disc radius as a fraction of `radius`.
        fixed_iter: relaxation iterations (capped); None relaxes to convergence (tau, max_iter).
        backend: relaxation backend ("auto", "numba", "torch").
    """
    N, P = h.shape[0], h.shape[1]
    flat = (1, N * P, P)
    cells = N * P * P
    covered = win.dist <= radius                                         # (E,)
    s = taper(win.lateral / radius, flat_fraction)
    h_ref = reference_height(h, ref_radius * radius, dx).reshape(-1).clone()
    ref_used = torch.where(visit, ref, h_ref[win.cell])
    h_ref[win.cell] = ref_used
    h_dug, removed = sink(h.reshape(flat), h_ref.reshape(flat), win.cell, covered[None], s[None],
                          depth[None])
    # Owner of a cell: the covering wheel with the largest taper (as in the simulator).
    key = torch.where(covered, s + 1, torch.zeros_like(s))
    best = key.new_zeros(cells).scatter_reduce(0, win.cell, key, "amax")[win.cell]
    owner = covered & (key == best)
    covered_any = best > 0                                               # (E,)
    lat = win.lateral.abs()
    pos = win.along + radius                                             # from the rear cap
    band = ((lat > radius) & (lat <= radius + band_width) & (pos >= 0)
            & (pos <= win.length + 2 * radius) & ~covered_any & ~visit)
    n_bins = int((win.length.max().item() + 2 * radius) // (2 * dx)) + 1
    bins = ((win.robot * n_wheels + win.wheel) * n_bins
            + (pos / (2 * dx)).floor().long().clamp(0, n_bins - 1))
    source = torch.zeros(cells, dtype=h.dtype, device=h.device)
    source[win.cell] = removed.reshape(-1)[win.cell] * chi               # chi at the dug cell
    added, _lost = deposit(source.reshape(flat), win.cell, owner[None], band[None], bins,
                           N * n_wheels * n_bins, torch.ones(1, dtype=h.dtype, device=h.device))
    h_pre = (h_dug + added).reshape(h.shape)
    rr = relax(h_pre, tan_beta, dx, None, tau, max_iter, fixed_iter, eps_scale, backend)
    area = dx * dx
    return StepSoil(rr.h, ref_used, covered_any, owner, removed.reshape(N, -1).sum(1) * area,
                    added.reshape(N, -1).sum(1) * area, rr.iterations)


def body_grid_index(pose: torch.Tensor, offsets: torch.Tensor, grid: Grid
                    ) -> tuple[torch.Tensor, torch.Tensor]:
    """Nearest field cells of body-frame points around each robot.

    Args:
        pose: (N, 3) robot poses.
        offsets: (M, 2) body-frame points, m.

    Returns:
        flat (N, M) int64 row-major cell index (clamped onto the field) and inside (N, M)
        bool, the point lies on the field.
    """
    w = to_world(pose, offsets.to(pose.dtype))
    ij = torch.round((w - torch.tensor(grid.origin, dtype=w.dtype, device=w.device)) / grid.dx).long()
    X, Y = grid.shape
    inside = (ij[..., 0] >= 0) & (ij[..., 0] < X) & (ij[..., 1] >= 0) & (ij[..., 1] < Y)
    return ij[..., 0].clamp(0, X - 1) * Y + ij[..., 1].clamp(0, Y - 1), inside


def goal_in_body(pose: torch.Tensor, goal: torch.Tensor) -> torch.Tensor:
    """(N, 3) goal x, y in the robot frame [m] and its distance [m]; goal (N|1, 2) world."""
    rx, ry = goal[:, 0] - pose[:, 0], goal[:, 1] - pose[:, 1]
    c, s = torch.cos(pose[:, 2]), torch.sin(pose[:, 2])
    return torch.stack([c * rx + s * ry, -s * rx + c * ry, torch.hypot(rx, ry)], dim=1)


class Damage(NamedTuple):
    """Soil-damage measures of one step, all (N,): displaced (dug) and compacted (dug but not
    deposited) volume [m^3], deepest rut below the initial surface under the wheels [m] and
    cells entered by the robot again after an earlier visit [-]."""

    displaced: torch.Tensor
    compacted: torch.Tensor
    rut_depth: torch.Tensor
    repeat_cells: torch.Tensor


def reward(progress: torch.Tensor, damage: Damage, weights: dict[str, float]) -> torch.Tensor:
    """(N,) progress to the goal [m] times w_progress minus the weighted soil damage and a
    time cost per step (keys: progress, displaced, compacted, rut_depth, repeat_cells, time)."""
    return (weights["progress"] * progress - weights["displaced"] * damage.displaced
            - weights["compacted"] * damage.compacted - weights["rut_depth"] * damage.rut_depth
            - weights["repeat_cells"] * damage.repeat_cells - weights["time"])
