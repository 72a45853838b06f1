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


class WheelWindows(NamedTuple):
    """W x W field windows around each wheel's segment of one step, as E = N*K*W*W entries
    (robot-major, then wheel, then row and column of the window).

    field: (E,) int64 row-major index of the entry's field cell; dist: (E,) distance to the
    segment, m; lateral: (E,) signed offset from its line, left positive, m; along: (E,)
    position along the segment's line from its start (not clamped to the segment), m;
    length: (E,) segment length, m; wheel: (E,) int64 wheel k; robot: (E,) int64 robot n;
    shape: (N, K, W, W).
    """

    field: torch.Tensor
    dist: torch.Tensor
    lateral: torch.Tensor
    along: torch.Tensor
    length: torch.Tensor
    wheel: torch.Tensor
    robot: torch.Tensor
    shape: tuple[int, int, int, int]


def window_size(start: torch.Tensor, end: torch.Tensor, radius: float, band_width: float,
                margin: int, dx: float) -> int:
    """Cells per side of square windows that hold every wheel's swept footprint, its deposition
    bands and `margin` cells of relaxation room, for the longest segment of the batch."""
    longest = float(torch.linalg.vector_norm(end - start, dim=-1).max())
    return int(math.ceil((longest + 2 * (radius + band_width)) / dx)) + 1 + 2 * margin


def segment_frames(start: torch.Tensor, end: torch.Tensor, heading: torch.Tensor, window: int,
                   grid: Grid) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Per wheel, its window's first cell and its segment's direction and length.

    Args:
        start, end: (N, K, 2) wheel centres before and after the step, m.
        heading: (N,) yaw used as the direction of a wheel that does not move, rad.
        window: W, cells per side, centred on the segment and shifted onto the field.
        grid: the field grid (at least W cells each way).

    Returns:
        w0 (N, K, 2) int64 field cell (i, j) of the window's first entry; ux, uy (N, K) unit
        direction of the segment; length (N, K) segment length, m.
    """
    dt, dev = start.dtype, start.device
    X, Y = grid.shape
    mid = (start + end) / 2
    o = torch.tensor(grid.origin, dtype=dt, device=dev)
    w0 = torch.round((mid - o) / grid.dx).long() - window // 2
    w0 = torch.minimum(w0.clamp_min(0), torch.tensor([X - window, Y - window], device=dev))
    u = end - start
    length = torch.linalg.vector_norm(u, dim=-1)                         # (N, K)
    still = length < 1e-9
    ux = torch.where(still, torch.cos(heading)[:, None], u[..., 0] / length.clamp_min(1e-9))
    uy = torch.where(still, torch.sin(heading)[:, None], u[..., 1] / length.clamp_min(1e-9))
    return w0, ux, uy, length


def wheel_windows(start: torch.Tensor, end: torch.Tensor, heading: torch.Tensor, window: int,
                  grid: Grid) -> WheelWindows:
    """Geometry of the cells near each wheel's straight segment for one step.

    Args:
        start, end: (N, K, 2) wheel centres before and after the step, m.
        heading: (N,) yaw used as the direction of a wheel that does not move, rad.
        window: W, cells per side, centred on the segment and shifted onto the field.
        grid: the field grid (at least W cells each way).
    """
    N, K = start.shape[:2]
    dt, dev = start.dtype, start.device
    Y = grid.shape[1]
    w0, ux, uy, length = segment_frames(start, end, heading, window, grid)
    ar = torch.arange(window, device=dev)
    ii = w0[..., 0, None] + ar                                           # (N, K, W)
    jj = w0[..., 1, None] + ar
    xs = grid.origin[0] + ii.to(dt) * grid.dx
    ys = grid.origin[1] + jj.to(dt) * grid.dx
    rx = (xs - start[..., 0, None])[..., :, None]                        # (N, K, W, 1)
    ry = (ys - start[..., 1, None])[..., None, :]                        # (N, K, 1, W)
    ux4, uy4, len4 = ux[..., None, None], uy[..., None, None], length[..., None, None]
    along = rx * ux4 + ry * uy4
    lateral = ry * ux4 - rx * uy4
    foot = along.clamp(min=0.0).minimum(len4)
    dist = torch.sqrt((rx - foot * ux4) ** 2 + (ry - foot * uy4) ** 2)
    shape = (N, K, window, window)
    field = ii[..., :, None] * Y + jj[..., None, :]
    wheel = torch.arange(K, device=dev)[None, :, None, None].expand(shape)
    robot = torch.arange(N, device=dev)[:, None, None, None].expand(shape)
    return WheelWindows(field.flatten(), dist.flatten(), lateral.flatten(), along.flatten(),
                        len4.expand(shape).flatten(), wheel.flatten(), robot.flatten(), shape)


class StepSoil(NamedTuple):
    """Outcome of one step on the N*K wheel windows.

    h: (N*K, W, W) surface after the step, m; ref: (E,) reference height used at each entry,
    m; covered: (E,) bool, under the wheel this step; removed, deposited: (N,) volumes, m^3;
    iterations: (N,) most relaxation updates over a robot's windows.
    """

    h: torch.Tensor
    ref: torch.Tensor
    covered: torch.Tensor
    removed: torch.Tensor
    deposited: torch.Tensor
    iterations: torch.Tensor


def deform(h: torch.Tensor, tan_beta: torch.Tensor, win: WheelWindows, ref: torch.Tensor,
           visit: torch.Tensor, depth: torch.Tensor, chi: torch.Tensor, radius: float,
           flat_fraction: float, dx: float, band_width: float, ref_radius: float = 0.5,
           fixed_iter: int | None = 4, tau: float = 0.01, max_iter: int = 2000,
           eps_scale: float = 4.0, backend: str = "auto") -> StepSoil:
    """Wheels dig, deposit beside their ruts and the surface relaxes, in each wheel's window.

    The N*K windows are one (1, N*K*W, W) surface for the simulator's sparse stages (`sink`,
    `deposit`), then relax as (N*K, W, W) with no flux across the window edges. Deposition
    bins are 2 cells of a wheel's segment extended by the footprint radius at both ends, so
    the soil dug ahead of the segment's end lands beside it too. A cell in an ongoing visit
    keeps the reference height of that visit, so the rear wheel in the front wheel's rut and
    overlapping steps dig no deeper (the simulator's min over poses); a later visit digs again
    from the surface it finds.

    Args:
        h: (N*K, W, W) surface in the windows, m.
        tan_beta: (N*K, W, W) tangent of the angle of repose per cell.
        win: the windows' E = N*K*W*W entries (`wheel_windows`).
        ref: (E,) reference height of the cell in its ongoing visit, m.
        visit: (E,) bool, the cell is in an ongoing visit (`ref` applies).
        depth: (E,) sinkage d of the window's wheel track at the cell, m.
        chi: (E,) displacement-compaction ratio at the cell.
        radius: footprint radius (half the wheel width), m.
        flat_fraction: tyre taper f.
        dx: cell edge, m.
        band_width: width of the deposition band beside each rut, m.
        ref_radius: reference disc radius as a fraction of `radius`.
        fixed_iter: relaxation iterations (capped); None relaxes to convergence (tau, max_iter).
        backend: relaxation backend ("auto", "numba", "torch").
    """
    N, K, W = win.shape[:3]
    M, E = N * K, h.numel()
    flat = (1, M * W, W)
    cell = torch.arange(E, device=h.device)
    covered = win.dist <= radius                                         # (E,)
    s = taper(win.lateral / radius, flat_fraction)
    h_ref = torch.where(visit, ref, reference_height(h, ref_radius * radius, dx).reshape(-1))
    h_dug, removed = sink(h.reshape(flat), h_ref.reshape(flat), cell, covered[None], s[None],
                          depth[None])
    lat = win.lateral.abs()
    pos = win.along + radius                                             # from the rear cap
    band = ((lat > radius) & (lat <= radius + band_width) & (pos >= 0)
            & (pos <= win.length + 2 * radius) & ~covered & ~visit)
    n_bins = int((win.length.max().item() + 2 * radius) // (2 * dx)) + 1
    window_id = win.robot * K + win.wheel
    bins = window_id * n_bins + (pos / (2 * dx)).floor().long().clamp(0, n_bins - 1)
    one = torch.ones(1, dtype=h.dtype, device=h.device)
    added, _lost = deposit((removed.reshape(-1) * chi).reshape(flat), cell, covered[None],
                           band[None], bins, M * n_bins, one)
    h_pre = (h_dug + added).reshape(h.shape)
    rr = relax(h_pre, tan_beta, dx, None, tau, max_iter, fixed_iter, eps_scale, backend)
    area = dx * dx
    return StepSoil(rr.h, h_ref, covered, removed.reshape(N, -1).sum(1) * area,
                    added.reshape(N, -1).sum(1) * area, rr.iterations.reshape(N, K).amax(1))


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
