"""State and pure functions of N soil-traverse episodes on one device.

Gymnasium's functional pattern: static parameters (`envs.params.TraverseParams`), a state
of named tensors (`TraverseState`) and functions of them,

    state = empty_state(params, n)
    state = reset_episodes(params, state, ids, *sample_starts(params, rngs))
    state, outcome = transition(params, state, action)
    r, term = reward(outcome, params.weights), terminal(outcome)
    trunc = truncated(params, state, term)
    obs = observation(params, state, rngs)

with the physics in `envs.dynamics`. `SoilTraverseEnv` (N = 1) and `SoilTraverseVectorEnv`
are thin Gymnasium classes over them.

In place: the per-cell layers (h, ref, ref_odom, passes; N*X*Y each) are updated in place
by `transition` and `reset_episodes` and shared with the state they return (copying them
every step would cost more than the step). Every other tensor of the input state is left as
it was. To keep a state, `clone_state` it first.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
import torch

from envs import dynamics as dyn
from envs.params import TraverseParams


class Totals(NamedTuple):
    """Episode sums, each (N,): displaced and compacted volume [m^3], deepest rut [m]."""

    displaced: torch.Tensor
    compacted: torch.Tensor
    max_rut: torch.Tensor


class TraverseState(NamedTuple):
    """What changes during N episodes.

    Attributes:
        h: (N, X, Y) current surface, m.
        ref: (N, X, Y) reference height of the cell's ongoing (or last) visit, m. A visit
            lasts while the robot drives less than `params.visit_length` m after it began,
            so its rear wheels dig no deeper than its front wheels.
        ref_odom: (N, X, Y) odometer when that visit began, m (-inf: never visited).
        passes: (N, X, Y) robot passes over the cell (float).
        pose: (N, 3) x, y [m], yaw [rad] of base_link.
        control: (N, 2) last speed [m/s] and curvature [1/m].
        odom: (N,) distance driven, m.
        steps: (N,) int64 steps since reset.
        goal: (N, 2) m.
        path: (max_steps + 1, N, 2) base_link positions after each step (the start first).
        totals: episode sums of the damage measures.
    """

    h: torch.Tensor
    ref: torch.Tensor
    ref_odom: torch.Tensor
    passes: torch.Tensor
    pose: torch.Tensor
    control: torch.Tensor
    odom: torch.Tensor
    steps: torch.Tensor
    goal: torch.Tensor
    path: torch.Tensor
    totals: Totals

    @property
    def num_envs(self) -> int:
        return self.pose.shape[0]


class StepOutcome(NamedTuple):
    """What one step did, each (N,): progress towards the goal [m], the soil damage
    (`dynamics.Damage`), most relaxation updates over the robot's windows, goal reached
    (bool), a wheel off the field (bool, also when the goal was reached)."""

    progress: torch.Tensor
    damage: dyn.Damage
    relax_iterations: torch.Tensor
    reached: torch.Tensor
    off_field: torch.Tensor


def clone_state(state: TraverseState) -> TraverseState:
    """A copy of every tensor of the state."""
    return TraverseState(*(t.clone() for t in state[:-1]), Totals(*(t.clone() for t in state.totals)))


# ------------------------------------------------------------------------------- reset
def empty_state(params: TraverseParams, num_envs: int) -> TraverseState:
    """N episodes on the undeformed field at the origin; reset them before stepping."""
    if num_envs < 1:
        raise ValueError(f"num_envs must be >= 1, got {num_envs}")
    n, (X, Y) = int(num_envs), params.grid.shape
    kw = dict(device=params.device)
    h0 = params.field.h0
    return TraverseState(
        h=h0.repeat(n, 1, 1), ref=torch.zeros((n, X, Y), **kw),
        ref_odom=torch.full((n, X, Y), -math.inf, **kw), passes=torch.zeros((n, X, Y), **kw),
        pose=torch.zeros((n, 3), **kw), control=torch.zeros((n, 2), **kw), odom=torch.zeros(n, **kw),
        steps=torch.zeros(n, dtype=torch.int64, **kw), goal=torch.zeros((n, 2), **kw),
        path=torch.zeros((params.config.max_steps + 1, n, 2), **kw),
        totals=Totals(*(torch.zeros(n, **kw) for _ in range(3))))


def sample_starts(params: TraverseParams, rngs: list[np.random.Generator]) -> tuple[np.ndarray, np.ndarray]:
    """Start poses (M, 3) x, y [m], yaw [rad] and goals (M, 2) [m], one per generator: the
    configured start plus uniform jitter, the goal plus a uniform disc of `goal_jitter`."""
    c = params.config
    starts, goals = [], []
    for rng in rngs:
        j = rng.uniform(-1.0, 1.0, size=3) * np.asarray(c.start_jitter)
        starts.append([c.start[0] + j[0], c.start[1] + j[1], math.radians(c.start[2] + j[2])])
        ang = rng.uniform(0, 2 * math.pi)
        rad = c.goal_jitter * math.sqrt(rng.uniform())
        goals.append([c.goal[0] + rad * math.cos(ang), c.goal[1] + rad * math.sin(ang)])
    return np.array(starts, dtype=np.float64).reshape(-1, 3), np.array(goals, dtype=np.float64).reshape(-1, 2)


def reset_episodes(params: TraverseParams, state: TraverseState, ids, pose, goal) -> TraverseState:
    """The state with episodes `ids` back on the undeformed field at `pose` (M, 3) with goal
    (M, 2) (`sample_starts`). Their field layers are reset in place (see the module docstring)."""
    dev = params.device
    ids_t = torch.as_tensor(np.asarray(ids, dtype=np.int64), device=dev)
    pose_t = torch.as_tensor(np.asarray(pose), dtype=torch.float32, device=dev).reshape(-1, 3)
    goal_t = torch.as_tensor(np.asarray(goal), dtype=torch.float32, device=dev).reshape(-1, 2)
    state.h[ids_t] = params.field.h0
    state.ref[ids_t] = 0.0
    state.ref_odom[ids_t] = -math.inf
    state.passes[ids_t] = 0.0

    def put(t, v):
        t = t.clone()
        t[ids_t] = v
        return t

    path = state.path.clone()
    path[:, ids_t] = pose_t[:, :2]
    return state._replace(
        pose=put(state.pose, pose_t), goal=put(state.goal, goal_t), control=put(state.control, 0.0),
        odom=put(state.odom, 0.0), steps=put(state.steps, 0), path=path,
        totals=Totals(*(put(t, 0.0) for t in state.totals)))


# -------------------------------------------------------------------------- transition
def transition(params: TraverseParams, state: TraverseState, action: torch.Tensor
               ) -> tuple[TraverseState, StepOutcome]:
    """Advance all N episodes by one control period.

    Args:
        action: (N, 2) speed [m/s], curvature [1/m]; clipped to the platform's limits.

    Returns:
        the new state (its field layers are the input's, updated in place) and the outcome.
    """
    c, N = params.config, state.num_envs
    a = action.to(params.device, torch.float32).reshape(N, 2)
    if not torch.isfinite(a).all():
        bad = torch.nonzero(~torch.isfinite(a).all(1))[0].item()
        raise ValueError(f"actions must be finite; row {bad} is {a[bad].tolist()}")
    v = a[:, 0].clamp(*c.speed)
    kappa = a[:, 1].clamp(-c.curvature_max, c.curvature_max)
    pose0, pose1 = state.pose, dyn.step_pose(state.pose, v, kappa, c.dt)
    start, end = dyn.to_world(pose0, params.wheels), dyn.to_world(pose1, params.wheels)
    odom = state.odom + (v * c.dt).abs()
    damage, iterations = soil_step(params, state, start, end, pose0[:, 2], odom)

    d_before = torch.linalg.vector_norm(state.goal - pose0[:, :2], dim=1)
    d_after = torch.linalg.vector_norm(state.goal - pose1[:, :2], dim=1)
    steps = state.steps + 1
    path = state.path.index_put((steps.clamp(max=c.max_steps), torch.arange(N, device=params.device)),
                                pose1[:, :2])
    t = state.totals
    new = state._replace(
        pose=torch.cat([pose1[:, :2], torch.remainder(pose1[:, 2:] + math.pi, 2 * math.pi) - math.pi], 1),
        control=torch.stack([v, kappa], 1), odom=odom, steps=steps, path=path,
        totals=Totals(t.displaced + damage.displaced, t.compacted + damage.compacted,
                      torch.maximum(t.max_rut, damage.rut_depth)))
    off = ((end < params.lo) | (end > params.hi)).flatten(1).any(1)
    return new, StepOutcome(d_before - d_after, damage, iterations, d_after <= c.goal_radius, off)


def soil_step(params: TraverseParams, state: TraverseState, start: torch.Tensor, end: torch.Tensor,
              heading: torch.Tensor, odom: torch.Tensor) -> tuple[dyn.Damage, torch.Tensor]:
    """The wheels dig, deposit and the surface relaxes in each wheel's window (`dynamics.deform`);
    the field layers of `state` are updated in place. With `params.fused` in one numba kernel
    (`envs._step_numba.soil_step`), else in torch ops (`soil_step_torch`); the two agree to
    float32 rounding.

    Args:
        start, end: (N, K, 2) wheel centres before and after the step, m.
        heading: (N,) yaw before the step, rad.  odom: (N,) odometer after the step, m.

    Returns:
        the step's damage and (N,) relaxation updates (most over a robot's windows).
    """
    if params.fused:
        from envs import _step_numba

        return _step_numba.soil_step(params, state, start, end, heading, odom)
    return soil_step_torch(params, state, start, end, heading, odom)


def soil_step_torch(params: TraverseParams, state: TraverseState, start: torch.Tensor, end: torch.Tensor,
                    heading: torch.Tensor, odom: torch.Tensor) -> tuple[dyn.Damage, torch.Tensor]:
    """`soil_step` in torch ops over the E = N*K*W*W window entries (any device; one gather
    and one write per layer). Arguments and result as `soil_step`."""
    s, g = params.config.sim, params.grid
    N, (X, Y), W = state.num_envs, g.shape, params.window
    win = dyn.wheel_windows(start, end, heading, W, g)
    gidx = win.robot * (X * Y) + win.field                                # (E,) cell of the state
    layers = (state.h.view(-1), state.ref.view(-1), state.ref_odom.view(-1), state.passes.view(-1))
    h_e, ref_e, odom_e, pas_e = (t.index_select(0, gidx) for t in layers)
    odom_now = odom[win.robot]
    visit = (odom_now - odom_e) <= params.visit_length
    cells = params.cell_table.index_select(0, win.field)                  # (E, T + 4)
    depth = cells.gather(1, 2 + params.track[win.wheel][:, None])[:, 0]
    shape = (N * len(params.track), W, W)
    out = dyn.deform(h_e.view(shape), cells[:, 0].reshape(shape), win, ref_e, visit, depth, cells[:, -2],
                     params.radius, params.robot.wheel_flat_fraction, g.dx, s.band_width * g.dx,
                     s.ref_radius, s.fixed_iter, s.tau, s.max_iter, s.eps_scale, s.backend)
    cov = out.covered
    entered = cov & ~visit
    h_new = out.h.reshape(-1)
    written = (h_new, torch.where(cov, out.ref, ref_e), torch.where(entered, odom_now, odom_e),
               pas_e + entered.to(pas_e.dtype))
    for layer, values in zip(layers, written, strict=True):
        layer.index_copy_(0, gidx, values)
    repeat = (entered & (pas_e > 0)).view(N, -1).sum(1).to(torch.float32)
    rut = torch.where(cov, cells[:, 1] - h_new, torch.zeros_like(h_new))
    rut = rut.view(N, -1).amax(1).clamp_min(0)
    damage = dyn.Damage(out.removed, (out.removed - out.deposited).clamp_min(0), rut, repeat)
    return damage, out.iterations.to(params.device)


def reward(outcome: StepOutcome, weights: dict[str, float]) -> torch.Tensor:
    """(N,) `dynamics.reward` of the step plus the goal bonus, minus the off-field penalty."""
    r = dyn.reward(outcome.progress, outcome.damage, weights)
    return r + weights["goal"] * outcome.reached - weights["off_field"] * (outcome.off_field & ~outcome.reached)


def terminal(outcome: StepOutcome) -> torch.Tensor:
    """(N,) bool: the goal is reached or a wheel left the field."""
    return outcome.reached | outcome.off_field


def truncated(params: TraverseParams, state: TraverseState, terminated: torch.Tensor) -> torch.Tensor:
    """(N,) bool: the step limit is reached (and the episode did not end otherwise)."""
    return (state.steps >= params.config.max_steps) & ~terminated


def step_info(state: TraverseState, outcome: StepOutcome) -> dict[str, torch.Tensor]:
    """The info dict of a step, (N,) tensors (see the env docstring)."""
    d = outcome.damage
    return {"displaced": d.displaced, "compacted": d.compacted, "rut_depth": d.rut_depth,
            "repeat_cells": d.repeat_cells, "relax_iterations": outcome.relax_iterations,
            "reached_goal": outcome.reached, "off_field": outcome.off_field & ~outcome.reached,
            "episode_displaced": state.totals.displaced.clone(),
            "episode_compacted": state.totals.compacted.clone(), "episode_max_rut": state.totals.max_rut.clone()}


def step(params: TraverseParams, state: TraverseState, action: torch.Tensor
         ) -> tuple[TraverseState, torch.Tensor, torch.Tensor, torch.Tensor, dict[str, torch.Tensor]]:
    """One control period of all N episodes: `transition`, then reward, terminated, truncated
    (all (N,)) and the info dict of (N,) tensors."""
    state, out = transition(params, state, action)
    term = terminal(out)
    return state, reward(out, params.weights), term, truncated(params, state, term), step_info(state, out)


# ------------------------------------------------------------------------- observation
def observation(params: TraverseParams, state: TraverseState,
                rngs: list[np.random.Generator] | None = None) -> dict[str, np.ndarray]:
    """Observations of all N episodes as float32 numpy arrays (see the env docstring).

    rngs: one generator per episode for the soil-parameter noise (needed if soil_noise > 0).
    """
    c, N = params.config, state.num_envs
    pose = state.pose
    if params.fused:
        from envs import _step_numba

        height, soil = _step_numba.observe(params, pose, state.h)
    else:
        height, soil = _patches(params, state)
    if c.soil_noise > 0:
        if rngs is None or len(rngs) != N:
            raise ValueError("soil_noise > 0 needs one random generator per environment")
        noise = np.stack([r.standard_normal(soil.shape[1:]) for r in rngs]).astype(np.float32)
        soil = np.clip(soil * (1 + c.soil_noise * noise), 0.0, params.soil_hi[:, None, None])
    st = torch.stack([state.control[:, 0], state.control[:, 1], pose[:, 0], pose[:, 1], pose[:, 2]], 1)
    goal = dyn.goal_in_body(pose, state.goal)
    return {"heightmap": height,
            "soil": soil.astype(np.float32, copy=False),
            "state": st.clamp(-1e4, 1e4).cpu().numpy(),
            "goal": goal.clamp(-1e4, 1e4).cpu().numpy()}


def _patches(params: TraverseParams, state: TraverseState) -> tuple[np.ndarray, np.ndarray]:
    """The heightmap (N, 2, S, S) [m] and true soil (N, T + 2, S, S) patches of `observation`
    in torch ops (any device), as float32 numpy arrays."""
    S, N, g = params.config.obs_size, state.num_envs, params.grid
    pose = state.pose
    flat, inside = dyn.body_grid_index(pose, params.obs_offsets, g)          # (N, M)
    base = torch.arange(N, device=params.device)[:, None] * (g.shape[0] * g.shape[1])
    h_all = state.h.view(-1)
    h = h_all.index_select(0, (flat + base).reshape(-1)).view(N, -1)
    cells = params.cell_table.index_select(0, flat.reshape(-1)).view(N, -1, params.cell_table.shape[1])
    h0 = cells[..., 1]
    centre = dyn.body_grid_index(pose, params.obs_offsets[:1] * 0, g)[0]
    rel = h - h_all.index_select(0, (centre + base).reshape(-1)).view(N, 1)
    zero = torch.zeros_like(h)
    height = torch.stack([torch.where(inside, rel, zero), torch.where(inside, h - h0, zero)], 1)
    height = height.reshape(N, 2, S, S).clamp(-2.0, 2.0)
    soil = torch.where(inside[..., None], cells[..., 2:], torch.zeros_like(cells[..., 2:]))
    soil = soil.transpose(1, 2).reshape(N, -1, S, S)                       # (N, T + 2, S, S)
    return height.cpu().numpy(), soil.cpu().numpy()


# ------------------------------------------------------------------------------ render
def render(params: TraverseParams, state: TraverseState, i: int = 0, depth_range: float = 0.04) -> np.ndarray:
    """(Y, X, 3) uint8 top view of H_delta = h - h0 of episode i (x right, y up), with
    the path (black) and the wheels at the current pose (red)."""
    from matplotlib import colormaps

    g = params.grid
    dh = (state.h[i] - params.field.h0).cpu().numpy()
    img = colormaps["RdBu"](np.clip(0.5 + dh / (2 * depth_range), 0, 1))[..., :3]
    img = (img * 255).astype(np.uint8).transpose(1, 0, 2).copy()        # (Y, X, 3)
    n = int(state.steps[i].clamp(max=params.config.max_steps)) + 1
    pts = state.path[:n, i].cpu().numpy()
    ij = np.round((pts - np.asarray(g.origin)) / g.dx).astype(np.int64)
    ok = (ij[:, 0] >= 0) & (ij[:, 0] < g.shape[0]) & (ij[:, 1] >= 0) & (ij[:, 1] < g.shape[1])
    img[ij[ok, 1], ij[ok, 0]] = 0
    w = dyn.to_world(state.pose[i:i + 1], params.wheels)[0].cpu().numpy()
    rc = max(1, int(round(params.radius / g.dx)))
    for wx, wy in w:
        ci, cj = int(round((wx - g.origin[0]) / g.dx)), int(round((wy - g.origin[1]) / g.dx))
        img[max(cj - rc, 0):cj + rc + 1, max(ci - rc, 0):ci + rc + 1] = (220, 30, 30)
    return img[::-1].copy()
