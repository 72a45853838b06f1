"""State of N soil-traverse episodes on one device, stepped as one tensor op.

`TraverseBatch` owns what really is state (N deformed fields, reference heights of the
ongoing visits, pass counts, poses, step counters, paths); the static parameters are
`envs.params.TraverseParams` and the physics lives in the pure functions of
`envs.dynamics`. `SoilTraverseEnv` (N = 1) and `SoilTraverseVectorEnv` are thin Gymnasium
classes over it.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from envs import dynamics as dyn
from envs.params import TraverseParams


class TraverseBatch:
    """N episodes on one field: state tensors (N, X, Y) and one batched `step`.

    Attributes:
        state: (N*X*Y, 4) per episode and cell: surface h [m], reference height of the
        cell's last visit [m], odometer when that visit began [m] (-inf: never), robot passes.
        A visit lasts while the robot drives less than `visit_length` m (its length on its
        tightest arc plus a step), so its rear wheels dig no deeper than its front wheels.
        h, passes: (N, X, Y) views.  odom: (N,) distance driven, m.
        pose: (N, 3) x, y [m], yaw [rad].  control: (N, 2) last speed [m/s], curvature [1/m].
        steps: (N,) int64.  goal: (N, 2) m.  path: (max_steps + 1, N, 2) base_link positions.
        totals: dict of (N,) episode sums of the damage measures.
    """

    def __init__(self, num_envs: int, params: TraverseParams):
        if num_envs < 1:
            raise ValueError(f"num_envs must be >= 1, got {num_envs}")
        self.n, self.params, self.cfg, self.robot = int(num_envs), params, params.config, params.robot
        self.device, self.field, self.grid = params.device, params.field, params.grid
        X, Y = self.grid.shape
        self.track, self.wheels, self.radius = params.track, params.wheels, params.radius
        self.obs_offsets, self.cell_table = params.obs_offsets, params.cell_table
        self.visit_length, self.window, self.lo, self.hi = params.visit_length, params.window, params.lo, params.hi
        self.soil_lo, self.soil_hi = params.soil_lo, params.soil_hi
        config = params.config
        kw = dict(device=self.device)
        # per episode and cell, one row: h, ref, ref_odom, passes (one gather, one write per step)
        self.state = torch.zeros((self.n * X * Y, 4), **kw)
        self.odom = torch.zeros(self.n, **kw)
        self.pose = torch.zeros((self.n, 3), **kw)
        self.control = torch.zeros((self.n, 2), **kw)
        self.steps = torch.zeros(self.n, dtype=torch.int64, **kw)
        self.goal = torch.zeros((self.n, 2), **kw)
        self.path = torch.zeros((config.max_steps + 1, self.n, 2), **kw)
        self.totals = {k: torch.zeros(self.n, **kw) for k in ("displaced", "compacted", "rut_depth")}

    def _layer(self, k: int) -> torch.Tensor:
        return self.state[:, k].view(self.n, *self.grid.shape)

    @property
    def h(self) -> torch.Tensor:
        """(N, X, Y) current surface, m (a view)."""
        return self._layer(0)

    @property
    def passes(self) -> torch.Tensor:
        """(N, X, Y) robot passes per cell (a float view)."""
        return self._layer(3)

    # ----------------------------------------------------------------- reset
    def reset(self, ids: np.ndarray | list[int], rngs: list[np.random.Generator]) -> None:
        """Reset episodes `ids`, drawing their start pose and goal from rngs (one per id)."""
        c = self.cfg
        ids_t = torch.as_tensor(np.asarray(ids, dtype=np.int64), device=self.device)
        starts, goals = [], []
        for rng in rngs:
            j = rng.uniform(-1.0, 1.0, size=3) * np.asarray(c.start_jitter)
            starts.append([c.start[0] + j[0], c.start[1] + j[1], math.radians(c.start[2] + j[2])])
            ang = rng.uniform(0, 2 * math.pi)
            rad = c.goal_jitter * math.sqrt(rng.uniform())
            goals.append([c.goal[0] + rad * math.cos(ang), c.goal[1] + rad * math.sin(ang)])
        rows = self.state.view(self.n, -1, 4)
        rows[ids_t] = torch.stack([self.field.h0.reshape(-1), torch.zeros_like(self.field.h0.reshape(-1)),
                                   torch.full_like(self.field.h0.reshape(-1), -math.inf),
                                   torch.zeros_like(self.field.h0.reshape(-1))], 1)
        self.pose[ids_t] = torch.tensor(starts, dtype=torch.float32, device=self.device)
        self.goal[ids_t] = torch.tensor(goals, dtype=torch.float32, device=self.device)
        self.control[ids_t] = 0.0
        self.odom[ids_t] = 0.0
        self.steps[ids_t] = 0
        self.path[:, ids_t] = self.pose[ids_t, :2]
        for v in self.totals.values():
            v[ids_t] = 0.0

    # ------------------------------------------------------------------ step
    def step(self, action: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, dict]:
        """Advance all N episodes by one control period.

        Args:
            action: (N, 2) speed [m/s], curvature [1/m]; clipped to the platform's limits.

        Returns:
            reward (N,), terminated (N,) bool, truncated (N,) bool, info of (N,) tensors.
        """
        c, s, g = self.cfg, self.cfg.sim, self.grid
        N, (X, Y) = self.n, self.grid.shape
        a = action.to(self.device, torch.float32).reshape(N, 2)
        if not torch.isfinite(a).all():
            bad = torch.nonzero(~torch.isfinite(a).all(1))[0].item()
            raise ValueError(f"actions must be finite; row {bad} is {a[bad].tolist()}")
        v = a[:, 0].clamp(*c.speed)
        kappa = a[:, 1].clamp(-c.curvature_max, c.curvature_max)
        pose0, pose1 = self.pose, dyn.step_pose(self.pose, v, kappa, c.dt)
        start, end = dyn.to_world(pose0, self.wheels), dyn.to_world(pose1, self.wheels)
        self.odom = self.odom + (v * c.dt).abs()

        W = self.window
        win = dyn.wheel_windows(start, end, pose0[:, 2], W, g)
        gidx = win.robot * (X * Y) + win.field                                # (E,) state cell
        shape = (N * len(self.track), W, W)
        st = self.state.index_select(0, gidx)                                 # (E, 4)
        h_e, ref_e, odom_e, pas_e = st.unbind(1)
        odom_now = self.odom[win.robot]
        visit = (odom_now - odom_e) <= self.visit_length
        cells = self.cell_table.index_select(0, win.field)                   # (E, T + 4)
        depth = cells.gather(1, 2 + self.track[win.wheel][:, None])[:, 0]
        out = dyn.deform(h_e.view(shape), cells[:, 0].reshape(shape), win, ref_e, visit,
                         depth, cells[:, -2], self.radius,
                         self.robot.wheel_flat_fraction, g.dx, s.band_width * g.dx, s.ref_radius,
                         s.fixed_iter, s.tau, s.max_iter, s.eps_scale, s.backend)
        cov = out.covered
        entered = cov & ~visit
        h_new = out.h.reshape(-1)
        self.state.index_copy_(0, gidx, torch.stack([
            h_new, torch.where(cov, out.ref, ref_e), torch.where(entered, odom_now, odom_e),
            pas_e + entered.to(pas_e.dtype)], 1))
        repeat = (entered & (pas_e > 0)).view(N, -1).sum(1).to(torch.float32)
        rut = torch.where(cov, cells[:, 1] - h_new, torch.zeros_like(h_new))
        rut = rut.view(N, -1).amax(1).clamp_min(0)

        d_before = torch.linalg.vector_norm(self.goal - pose0[:, :2], dim=1)
        d_after = torch.linalg.vector_norm(self.goal - pose1[:, :2], dim=1)
        self.pose = torch.cat([pose1[:, :2], torch.remainder(pose1[:, 2:] + math.pi, 2 * math.pi) - math.pi], 1)
        self.control = torch.stack([v, kappa], 1)
        self.steps += 1
        self.path[self.steps.clamp(max=c.max_steps), torch.arange(N, device=self.device)] = pose1[:, :2]

        damage = dyn.Damage(out.removed, (out.removed - out.deposited).clamp_min(0), rut, repeat)
        w = self.params.weights
        reward = dyn.reward(d_before - d_after, damage, w)
        reached = d_after <= c.goal_radius
        off = ((end < self.lo) | (end > self.hi)).flatten(1).any(1)
        reward = reward + w["goal"] * reached - w["off_field"] * (off & ~reached)
        terminated = reached | off
        truncated = (self.steps >= c.max_steps) & ~terminated
        for k, val in (("displaced", damage.displaced), ("compacted", damage.compacted)):
            self.totals[k] += val
        self.totals["rut_depth"] = torch.maximum(self.totals["rut_depth"], rut)
        info = {"displaced": damage.displaced, "compacted": damage.compacted, "rut_depth": rut,
                "repeat_cells": damage.repeat_cells, "relax_iterations": out.iterations.to(self.device),
                "reached_goal": reached, "off_field": off & ~reached,
                "episode_displaced": self.totals["displaced"].clone(),
                "episode_compacted": self.totals["compacted"].clone(),
                "episode_max_rut": self.totals["rut_depth"].clone()}
        return reward, terminated, truncated, info

    # ----------------------------------------------------------- observation
    def observe(self, rngs: list[np.random.Generator] | None = None) -> dict[str, np.ndarray]:
        """Observations of all N episodes as float32 numpy arrays (see the env docstring).

        rngs: one generator per episode for the soil-parameter noise (needed if soil_noise > 0).
        """
        c, S, N = self.cfg, self.cfg.obs_size, self.n
        pose = self.pose
        flat, inside = dyn.body_grid_index(pose, self.obs_offsets, self.grid)   # (N, M)
        XY = self.grid.shape[0] * self.grid.shape[1]
        base = torch.arange(N, device=self.device)[:, None] * XY
        h = self.state.index_select(0, (flat + base).reshape(-1))[:, 0].view(N, -1)
        cells = self.cell_table.index_select(0, flat.reshape(-1)).view(N, -1, self.cell_table.shape[1])
        h0 = cells[..., 1]
        centre = dyn.body_grid_index(pose, self.obs_offsets[:1] * 0, self.grid)[0]
        rel = h - self.state.index_select(0, (centre + base).reshape(-1))[:, 0].view(N, 1)
        zero = torch.zeros_like(h)
        height = torch.stack([torch.where(inside, rel, zero), torch.where(inside, h - h0, zero)], 1)
        height = height.reshape(N, 2, S, S).clamp(-2.0, 2.0)
        soil = torch.where(inside[..., None], cells[..., 2:], torch.zeros_like(cells[..., 2:]))
        soil = soil.transpose(1, 2).reshape(N, -1, S, S)                       # (N, T + 2, S, S)
        soil = soil.cpu().numpy()
        if c.soil_noise > 0:
            if rngs is None or len(rngs) != N:
                raise ValueError("soil_noise > 0 needs one random generator per environment")
            noise = np.stack([r.standard_normal(soil.shape[1:]) for r in rngs]).astype(np.float32)
            soil = np.clip(soil * (1 + c.soil_noise * noise), 0.0, self.soil_hi[:, None, None])
        state = torch.stack([self.control[:, 0], self.control[:, 1], pose[:, 0], pose[:, 1], pose[:, 2]], 1)
        goal = dyn.goal_in_body(pose, self.goal)
        return {"heightmap": height.cpu().numpy(),
                "soil": soil.astype(np.float32, copy=False),
                "state": state.clamp(-1e4, 1e4).cpu().numpy(),
                "goal": goal.clamp(-1e4, 1e4).cpu().numpy()}

    # ---------------------------------------------------------------- render
    def render(self, i: int = 0, depth_range: float = 0.04) -> np.ndarray:
        """(Y, X, 3) uint8 top view of H_delta = h - h0 of episode i (x right, y up), with
        the path (black) and the wheels at the current pose (red)."""
        from matplotlib import colormaps

        g = self.grid
        dh = (self.h[i] - self.field.h0).cpu().numpy()
        img = colormaps["RdBu"](np.clip(0.5 + dh / (2 * depth_range), 0, 1))[..., :3]
        img = (img * 255).astype(np.uint8).transpose(1, 0, 2).copy()        # (Y, X, 3)
        n = int(self.steps[i].clamp(max=self.cfg.max_steps)) + 1
        pts = self.path[:n, i].cpu().numpy()
        ij = np.round((pts - np.asarray(g.origin)) / g.dx).astype(np.int64)
        ok = (ij[:, 0] >= 0) & (ij[:, 0] < g.shape[0]) & (ij[:, 1] >= 0) & (ij[:, 1] < g.shape[1])
        img[ij[ok, 1], ij[ok, 0]] = 0
        w = dyn.to_world(self.pose[i:i + 1], self.wheels)[0].cpu().numpy()
        rc = max(1, int(round(self.radius / g.dx)))
        for wx, wy in w:
            ci, cj = int(round((wx - g.origin[0]) / g.dx)), int(round((wy - g.origin[1]) / g.dx))
            img[max(cj - rc, 0):cj + rc + 1, max(ci - rc, 0):ci + rc + 1] = (220, 30, 30)
        return img[::-1].copy()
