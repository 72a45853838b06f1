"""Batched SoilTraverse: N episodes stepped as one (N, X, Y) tensor op, with autoreset.

Gymnasium's VectorEnv API with next-step autoreset: the step after an episode ends resets
that environment (reward 0, not terminated) instead of moving it. Episode i seeded with
`seed + i` follows the same trajectory as `SoilTraverseEnv` reset with that seed.
"""

from __future__ import annotations

import numpy as np
import torch
from gymnasium.utils import seeding
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from envs import core
from envs.params import make_params
from envs.spaces import action_space, observation_space


class SoilTraverseVectorEnv(VectorEnv):
    """N soil-traverse episodes on one device (CPU or CUDA); config and spaces as `SoilTraverseEnv`.

    Attributes:
        params: `envs.params.TraverseParams`, the static parameters (`params.config`: settings).
        state: `envs.core.TraverseState` of the N episodes.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 5,
                "autoreset_mode": AutoresetMode.NEXT_STEP}

    def __init__(self, num_envs: int = 1, config=None, render_mode: str | None = None,
                 device: str = "cpu"):
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode must be one of {self.metadata['render_modes']} or None, "
                             f"got {render_mode!r}")
        if num_envs < 1:
            raise ValueError(f"num_envs must be >= 1, got {num_envs}")
        self.params = make_params(config, device)
        self.state = core.empty_state(self.params, num_envs)
        self.num_envs = int(num_envs)
        self.render_mode = render_mode
        self.single_action_space = action_space(self.params)
        self.single_observation_space = observation_space(self.params)
        self.action_space = batch_space(self.single_action_space, self.num_envs)
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self._rngs: list[np.random.Generator] | None = None
        self._autoreset = np.zeros(self.num_envs, dtype=bool)

    def reset(self, *, seed: int | list[int] | None = None, options: dict | None = None):
        """Reset all episodes; seed: int (episode i gets seed + i), list of N ints, or None."""
        N = self.num_envs
        if seed is None:
            seeds = [None] * N
        elif isinstance(seed, (int, np.integer)):
            seeds = [int(seed) + i for i in range(N)]
        else:
            seeds = list(seed)
            if len(seeds) != N:
                raise ValueError(f"need {N} seeds, got {len(seeds)}")
        if seed is not None or self._rngs is None:
            self._rngs = [seeding.np_random(s)[0] for s in seeds]
        self.state = core.reset_episodes(self.params, self.state, np.arange(N),
                                         *core.sample_starts(self.params, self._rngs))
        self._autoreset[:] = False
        return core.observation(self.params, self.state, self._rngs), {}

    def step(self, actions):
        if self._rngs is None:
            raise RuntimeError("call reset() before step()")
        a = torch.as_tensor(np.asarray(actions, dtype=np.float32))
        if tuple(a.shape) != (self.num_envs, 2):
            raise ValueError(f"actions must be ({self.num_envs}, 2) speed m/s, curvature 1/m; "
                             f"got {tuple(a.shape)}")
        p = self.params
        self.state, reward, term, trunc, info = core.step(p, self.state, a)
        reward, term, trunc = reward.cpu().numpy(), term.cpu().numpy(), trunc.cpu().numpy()
        info = {k: v.cpu().numpy() for k, v in info.items()}
        done_before = np.flatnonzero(self._autoreset)
        if len(done_before):
            self.state = core.reset_episodes(p, self.state, done_before,
                                             *core.sample_starts(p, [self._rngs[i] for i in done_before]))
            reward[done_before], term[done_before], trunc[done_before] = 0.0, False, False
        self._autoreset = term | trunc
        return core.observation(p, self.state, self._rngs), reward.astype(np.float32), term, trunc, info

    def render(self):
        if self.render_mode == "rgb_array":
            return tuple(core.render(self.params, self.state, i) for i in range(self.num_envs))
        return None
