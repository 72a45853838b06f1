"""Observation and action spaces of one soil-traverse environment."""

from __future__ import annotations

import numpy as np
from gymnasium import spaces

from envs.params import TraverseParams


def action_space(params: TraverseParams) -> spaces.Box:
    """Box of (speed [m/s], curvature [1/m]) within the platform's limits."""
    c = params.config
    return spaces.Box(np.array([c.speed[0], -c.curvature_max], np.float32),
                      np.array([c.speed[1], c.curvature_max], np.float32), dtype=np.float32)


def observation_space(params: TraverseParams) -> spaces.Dict:
    """Dict of the local heightmap (2, S, S), soil (T + 2, S, S), state (5,) and goal (3,)."""
    S, soil_hi = params.config.obs_size, params.soil_hi
    C = len(soil_hi)
    big = 1e4
    return spaces.Dict({
        "heightmap": spaces.Box(-2.0, 2.0, (2, S, S), np.float32),
        "soil": spaces.Box(np.zeros((C, S, S), np.float32),
                           np.broadcast_to(soil_hi[:, None, None], (C, S, S)).astype(np.float32),
                           dtype=np.float32),
        "state": spaces.Box(-big, big, (5,), np.float32),
        "goal": spaces.Box(-big, big, (3,), np.float32),
    })
