"""State of N soil-traverse episodes on one device, stepped as one tensor op.

`TraverseBatch` owns what really is state (N deformed fields, reference heights of the
ongoing visits, pass counts, poses, step counters, paths); the physics lives in the pure
functions of `envs.dynamics`. `SoilTraverseEnv` (N = 1) and `SoilTraverseVectorEnv` are thin
Gymnasium classes over it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import yaml

from envs import dynamics as dyn
from envs.field import FieldConfig, SoilField, field_from_params_csv, make_field
from torchsoil.config import dataclass_from_dict
from torchsoil.robot import Robot, paper_platform
from torchsoil.sim.params import BETA_BOUNDS, CHI_BOUNDS, D_BOUNDS
from torchsoil.sim.simulate import MAX_TAN_BETA

DEFAULT_CONFIG = Path(__file__).resolve().parent.parent / "torchsoil/configs/env/soil_traverse.yaml"

DEFAULT_WEIGHTS = {"progress": 1.0, "displaced": 40.0, "compacted": 40.0, "rut_depth": 1.0,
                   "repeat_cells": 0.001, "time": 0.01, "goal": 10.0, "off_field": 10.0}


@dataclass(frozen=True)
class TraverseConfig:
    """Episode, platform, relaxation, observation and reward settings (section `env`).

    dt: control period, s. speed: (min, max) m/s. curvature_max: 1/m (symmetric dual
    steering). start: (x, y, yaw_deg); start_jitter: (m, m, deg) uniform half-ranges.
    goal: (x, y) m; goal_jitter: m; goal_radius: m. max_steps: truncation. relaxation:
    "capped" (exactly `fixed_iter` updates per step) or "converged" (tau, max_iter).
    obs_size: cells per side of the local patches; obs_dx: their spacing, m. soil_noise:
    relative standard deviation of the observed soil parameters (0: true values).
    relax_margin: cells of relaxation room around each wheel's footprint and bands. weights:
    reward weights (see `envs.dynamics.reward`, plus goal bonus and off-field penalty).
    """

    dt: float = 0.2
    speed: tuple[float, float] = (-0.5, 1.0)
    curvature_max: float = 0.8
    start: tuple[float, float, float] = (2.0, 5.0, 0.0)
    start_jitter: tuple[float, float, float] = (0.2, 0.2, 5.0)
    goal: tuple[float, float] = (18.0, 5.0)
    goal_jitter: float = 0.0
    goal_radius: float = 0.5
    max_steps: int = 400
    relaxation: str = "capped"
    fixed_iter: int = 4
    tau: float = 0.01
    max_iter: int = 2000
    eps_scale: float = 4.0
    backend: str = "auto"
    band_width: float = 1.0
    ref_radius: float = 0.5
    obs_size: int = 24
    obs_dx: float = 0.1
    soil_noise: float = 0.0
    relax_margin: int = 2
    weights: dict = field(default_factory=lambda: dict(DEFAULT_WEIGHTS))

    def __post_init__(self):
        if self.relaxation not in ("capped", "converged"):
            raise ValueError(f"env.relaxation must be 'capped' or 'converged', got {self.relaxation!r}")
        if not (self.dt > 0 and self.speed[0] <= self.speed[1] and self.curvature_max >= 0):
            raise ValueError(f"need dt > 0, speed min <= max, curvature_max >= 0; got dt={self.dt}, "
                             f"speed={self.speed}, curvature_max={self.curvature_max}")
        unknown = set(self.weights) - set(DEFAULT_WEIGHTS)
        if unknown:
            raise ValueError(f"unknown reward weights {sorted(unknown)}; known: {sorted(DEFAULT_WEIGHTS)}")
        object.__setattr__(self, "weights", {**DEFAULT_WEIGHTS, **self.weights})
        if self.max_steps < 1 or self.obs_size < 1 or self.fixed_iter < 0 or self.relax_margin < 0:
            raise ValueError(f"need max_steps, obs_size >= 1 and fixed_iter, relax_margin >= 0; got "
                             f"{self.max_steps}, {self.obs_size}, {self.fixed_iter}, {self.relax_margin}")

    @classmethod
    def from_dict(cls, d: dict | None) -> TraverseConfig:
        d = dict(d or {})
        for key in ("speed", "start", "start_jitter", "goal"):
            if key in d:
                d[key] = tuple(float(v) for v in d[key])
        return dataclass_from_dict(cls, d, "env")


def _merge(base: dict, over: dict) -> dict:
    """Mappings merged key by key (recursively); lists and values in `over` replace."""
    out = dict(base)
    for k, v in over.items():
        out[k] = _merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def load_config(config: str | Path | dict | None) -> dict:
    """The env config: configs/env/soil_traverse.yaml overridden by `config` (a YAML path or a
    dict with sections `env`, `field`, `robot`, `params_csv`; lists replace, mappings merge)."""
    base = yaml.safe_load(DEFAULT_CONFIG.read_text()) or {}
    if config is None:
        return base
    if isinstance(config, (str, Path)):
        path = Path(config)
        if not path.exists():
            raise FileNotFoundError(f"env config not found: {path}")
        config = yaml.safe_load(path.read_text()) or {}
    if not isinstance(config, dict):
        raise ValueError(f"env config must be a mapping, got {type(config).__name__}")
    unknown = set(config) - {"env", "field", "robot", "params_csv"}
    if unknown:
        raise ValueError(f"unknown env config sections {sorted(unknown)}; use env, field, robot, params_csv")
    return _merge(base, config)


def build(config: str | Path | dict | None = None) -> tuple[TraverseConfig, SoilField, Robot]:
    """Env settings, field and robot from a config (path, dict or None for the default)."""
    cfg = load_config(config)
    robot = Robot.from_yaml(cfg["robot"]) if cfg.get("robot") else paper_platform()
    fcfg = FieldConfig.from_dict(cfg.get("field"))
    if cfg.get("params_csv"):
        soil_field = field_from_params_csv(cfg["params_csv"], fcfg)
    else:
        soil_field = make_field(FieldConfig(**{**fcfg.__dict__, "n_tracks": robot.n_tracks}))
    if soil_field.n_tracks != robot.n_tracks:
        raise ValueError(f"field has {soil_field.n_tracks} sinkage tracks, robot uses {robot.n_tracks}")
    return TraverseConfig.from_dict(cfg.get("env")), soil_field, robot


def visit_length(robot: Robot, curvature_max: float, step: float) -> float:
    """Distance [m] base_link drives while one visit of a cell lasts: from the first wheel
    touching it to the last wheel of the same track leaving it, straight or on the tightest
    arc, plus one step. Within it the rear wheels reuse the front wheels' reference height."""
    w, r = robot.wheels, robot.wheel_width / 2
    longest = 0.0
    for t in range(robot.n_tracks):
        wx, wy = w[w[:, 2] == t, 0], w[w[:, 2] == t, 1]
        longest = max(longest, wx.max() - wx.min() + 2 * r)
        for k in (curvature_max, -curvature_max):
            if k == 0:
                continue
            R = 1.0 / k
            phi = np.arctan2(wx * np.sign(R), np.abs(R - wy))       # angle of each wheel about the ICR
            rho = np.hypot(wx, R - wy).min()
            longest = max(longest, abs(R) * (phi.max() - phi.min() + 2 * r / rho))
    return float(longest + step + 0.1)


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

    def __init__(self, num_envs: int, config: TraverseConfig, soil_field: SoilField, robot: Robot,
                 device: str | torch.device = "cpu"):
        if num_envs < 1:
            raise ValueError(f"num_envs must be >= 1, got {num_envs}")
        self.n, self.cfg, self.robot = int(num_envs), config, robot
        self.device = torch.device(device)
        self.field = soil_field.to(self.device)
        g = self.grid = soil_field.grid
        X, Y = g.shape
        self.track = torch.as_tensor(robot.track, device=self.device)
        self.wheels = torch.as_tensor(robot.wheels[:, :2], dtype=torch.float32, device=self.device)
        self.radius = robot.wheel_width / 2
        r = self.radius
        step_max = max(abs(config.speed[0]), abs(config.speed[1])) * config.dt
        S = config.obs_size
        ar = (torch.arange(S, dtype=torch.float32) - (S - 1) / 2) * config.obs_dx
        self.obs_offsets = torch.stack(torch.meshgrid(ar, ar, indexing="ij"), -1).reshape(-1, 2).to(self.device)
        T = soil_field.n_tracks
        tan_beta = torch.tan(self.field.soil[T + 1]).clamp(max=MAX_TAN_BETA)
        # per field cell, one row: tan(beta), h0, d_1..d_T, chi, beta (one gather per use)
        self.cell_table = torch.cat([tan_beta[None], self.field.h0[None], self.field.soil]
                                    ).reshape(T + 4, -1).T.contiguous()
        self.visit_length = visit_length(robot, config.curvature_max, step_max)
        # one window size for every step, from the fastest wheel on the tightest arc, so an
        # episode's result does not depend on the rest of the batch
        reach = float(np.hypot(robot.wheels[:, 0], robot.wheels[:, 1]).max())
        wheel_step = step_max * (1 + config.curvature_max * reach)
        self.window = dyn.window_size(torch.zeros(1, 2), torch.tensor([[wheel_step, 0.0]]), self.radius,
                                      config.band_width * g.dx, config.relax_margin, g.dx)
        if self.window > min(X, Y):
            raise ValueError(f"the field ({X} x {Y} cells) is smaller than a wheel window of "
                             f"{self.window} cells")
        self.lo = torch.tensor([g.origin[0] + r, g.origin[1] + r], device=self.device)
        self.hi = torch.tensor([g.origin[0] + (X - 1) * g.dx - r, g.origin[1] + (Y - 1) * g.dx - r],
                               device=self.device)
        self.soil_lo = np.array([D_BOUNDS[0]] * T + [CHI_BOUNDS[0], BETA_BOUNDS[0]], np.float32)
        self.soil_hi = np.array([D_BOUNDS[1]] * T + [CHI_BOUNDS[1], BETA_BOUNDS[1]], np.float32)
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
        c, g = self.cfg, self.grid
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
                         self.robot.wheel_flat_fraction, g.dx, c.band_width * g.dx, c.ref_radius,
                         c.fixed_iter if c.relaxation == "capped" else None, c.tau, c.max_iter,
                         c.eps_scale, c.backend)
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
        reward = dyn.reward(d_before - d_after, damage, c.weights)
        reached = d_after <= c.goal_radius
        off = ((end < self.lo) | (end > self.hi)).flatten(1).any(1)
        reward = reward + c.weights["goal"] * reached - c.weights["off_field"] * (off & ~reached)
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
