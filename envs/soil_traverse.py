"""SoilTraverse: drive a field robot to a goal while its wheels deform the soil.

## Description
A four-wheel dual-steering robot (the paper's platform, wheel layout from the robot YAML)
crosses a field heightmap (default 20 m x 10 m at dx = 0.05 m) whose soil parameters vary
in space: wet patches of deep sinkage and packed lanes (`env.field`), or an estimator run's
`params.csv` along a recorded path (`env.params_csv`). Every step the wheels dig,
deposit beside their ruts and the surface relaxes, with the simulator's own stages
(`torchsoil.sim`: taper, reference height, sink, deposit, relax) on a square window around
each wheel's segment of the step (no flux across the window edge). Relaxation is capped
(`env.sim.fixed_iter` updates per step) or run to convergence (`fixed_iter: null`). A cell keeps the reference height
of the robot's ongoing visit, so rear wheels in the front wheels' ruts dig no deeper; a
later visit (a loop, a return trip) digs again.

## Action Space
`Box(2,)` float32: speed [m/s] in `env.speed` (default [-0.5, 1.0]) and curvature [1/m] in
[-curvature_max, curvature_max] (default 0.8, left positive). Symmetric dual steering: the
robot follows an arc of that curvature, front and rear wheels on the same track.

## Observation Space
`Dict`, float32, S = `obs_size` cells at spacing `obs_dx` m, centred on the robot and
aligned with its frame (x forward, y left):

| key | shape | content (0 off the field) |
| --- | --- | --- |
| heightmap | (2, S, S) | [0] surface minus the surface under base_link, m; [1] H_delta = |
| | | surface minus the initial surface (ruts < 0, berms > 0), m |
| soil | (T + 2, S, S) | d_1..d_T [m], chi [-], beta [rad]; true, or with relative noise |
| | | `soil_noise` |
| state | (5,) | speed [m/s], curvature [1/m], x [m], y [m], yaw [rad] |
| goal | (3,) | goal x, y in the robot frame [m], distance [m] |

## Rewards
Per step: `w_progress * (distance gained towards the goal) - w_displaced * dug volume
- w_compacted * (dug - deposited volume) - w_rut_depth * deepest rut under the wheels
- w_repeat_cells * cells entered again - w_time`, plus `w_goal` on reaching the goal and
minus `w_off_field` on leaving the field (weights: `env.weights`).

## Starting State
base_link at `env.start` (x, y, yaw_deg) plus uniform jitter `env.start_jitter`, on the
undeformed field; the goal at `env.goal` plus a uniform disc of radius `goal_jitter`.

## Episode End
Terminated when base_link is within `goal_radius` of the goal or a wheel leaves the field;
truncated after `max_steps` steps.

## Arguments
`gymnasium.make("torchsoil:torchsoil/SoilTraverse-v0", config=None, render_mode=None,
device="cpu")`, `gymnasium.make_vec(..., num_envs=N, config=...)` the same. config is the
env section of the settings tree, `torchsoil.settings.EnvConfig` (every key, default and
unit there):

- None: the defaults (the 20 m x 10 m field above, the paper's platform);
- an `EnvConfig`;
- a dict or a YAML path: a document of the env section, e.g. `{"max_steps": 200, "sim":
  {"fixed_iter": null}, "field": {"size": [8, 5]}}`, or of the full settings tree (its
  `env:` section). It is merged onto the defaults (mappings merge, lists replace); unknown
  keys and bad values raise `torchsoil.settings.SettingsError` naming the key (`env.bogus`).

Keys: `dt` [s], `speed` (min, max) [m/s], `curvature_max` [1/m], `start` (x, y, yaw_deg) and
`start_jitter`, `goal`, `goal_jitter`, `goal_radius` [m], `max_steps`, `obs_size` [cells],
`obs_dx` [m], `soil_noise` [-], `weights` (reward weights above), `field` (size, dx,
roughness, seed, soil, patches, lanes), `robot` (a shipped robot name or a robot YAML path),
`params_csv` (replay an estimator run's soil) and `sim`, the physics of a step with the
simulator's meaning and units: `fixed_iter` (relaxation updates per step; null: until `tau`,
at most `max_iter`), `relax_margin` (relaxation room around each wheel's rut and bands, in
wheel widths; rounded up to whole cells), `band_width` [cells], `ref_radius`, `eps_scale`,
`backend` (auto, numba, torch). `pose_spacing` is not used (one segment per wheel and step).

`render_mode="rgb_array"` returns a (Y, X, 3) top view of H_delta with the path (black) and
the wheels (red). device: where the state lives ("cpu", "cuda").

The info dict holds this step's `displaced`, `compacted` [m^3], `rut_depth` [m],
`repeat_cells`, `relax_iterations`, `reached_goal`, `off_field` and the episode sums
`episode_displaced`, `episode_compacted` [m^3] and `episode_max_rut` [m].
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import torch

from envs import core
from envs.params import make_params
from envs.spaces import action_space, observation_space


class SoilTraverseEnv(gym.Env):
    """One soil-traverse episode over the pure functions of `envs.core`; see the module docstring.

    Attributes:
        params: `envs.params.TraverseParams`, the static parameters (`params.config`: settings).
        state: `envs.core.TraverseState` with N = 1.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 5}

    def __init__(self, config=None, render_mode: str | None = None, device: str = "cpu"):
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode must be one of {self.metadata['render_modes']} or None, "
                             f"got {render_mode!r}")
        self.params = make_params(config, device)
        self.state = core.empty_state(self.params, 1)
        self.render_mode = render_mode
        self.action_space = action_space(self.params)
        self.observation_space = observation_space(self.params)
        self._ready = False

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        pose, goal = core.sample_starts(self.params, [self.np_random])
        self.state = core.reset_episodes(self.params, self.state, [0], pose, goal)
        self._ready = True
        return self._obs(), {}

    def step(self, action):
        if not self._ready:
            raise RuntimeError("call reset() before step()")
        a = np.asarray(action, dtype=np.float32)
        if a.shape != (2,):
            raise ValueError(f"action must be (speed m/s, curvature 1/m) of shape (2,), got {a.shape}")
        self.state, reward, term, trunc, info = core.step(self.params, self.state, torch.from_numpy(a)[None])
        info = {k: (bool(v[0]) if v.dtype == torch.bool else float(v[0])) for k, v in info.items()}
        return self._obs(), float(reward[0]), bool(term[0]), bool(trunc[0]), info

    def render(self):
        if self.render_mode == "rgb_array":
            return core.render(self.params, self.state, 0)
        return None

    def _obs(self):
        return {k: v[0] for k, v in core.observation(self.params, self.state, [self.np_random]).items()}
