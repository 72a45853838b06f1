"""Observation and action spaces of one soil-traverse environment."""

from __future__ import annotations

import numpy as np
from gymnasium import spaces

from envs.core import TraverseConfig


def action_space(cfg: TraverseConfig) -> spaces.Box:
    """Box of (speed [m/s], curvature [1/m]) within the platform's limits."""
    return spaces.Box(np.array([cfg.speed[0], -cfg.curvature_max], np.float32),
                      np.array([cfg.speed[1], cfg.curvature_max], np.float32), dtype=np.float32)


def observation_space(cfg: TraverseConfig, soil_hi: np.ndarray) -> spaces.Dict:
    """Dict of the local heightmap (2, S, S), soil (T + 2, S, S), state (5,) and goal (3,)."""
    S, C = cfg.obs_size, len(soil_hi)
    big = 1e4
    return spaces.Dict({
        "heightmap": spaces.Box(-2.0, 2.0, (2, S, S), np.float32),
        "soil": spaces.Box(np.zeros((C, S, S), np.float32),
                           np.broadcast_to(soil_hi[:, None, None], (C, S, S)).astype(np.float32),
                           dtype=np.float32),
        "state": spaces.Box(-big, big, (5,), np.float32),
        "goal": spaces.Box(-big, big, (3,), np.float32),
    })
