"""Gymnasium registration by string entry points; only the env imports gymnasium."""

import subprocess
import sys

import gymnasium as gym
import numpy as np
from env_configs import small_config
from gymnasium.utils.env_checker import check_env

from envs import ENV_ID, register_envs
from envs.soil_traverse import SoilTraverseEnv
from envs.vector import SoilTraverseVectorEnv


def test_register_make_and_make_vec():
    register_envs()
    register_envs()                                   # idempotent
    spec = gym.spec(ENV_ID)
    assert spec.entry_point == "envs.soil_traverse:SoilTraverseEnv"
    assert spec.vector_entry_point == "envs.vector:SoilTraverseVectorEnv"
    env = gym.make(ENV_ID, config=small_config(), render_mode="rgb_array")
    assert isinstance(env.unwrapped, SoilTraverseEnv)
    check_env(env.unwrapped)
    obs, _ = env.reset(seed=0)
    assert env.observation_space.contains(obs)
    venv = gym.make_vec(ENV_ID, num_envs=2, config=small_config())
    assert isinstance(venv, SoilTraverseVectorEnv) and venv.num_envs == 2
    venv.reset(seed=0)
    obs, r, term, trunc, info = venv.step(np.zeros((2, 2), np.float32))
    assert r.shape == (2,)


def _python(code):
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout


def test_torchsoil_does_not_import_gymnasium_and_make_by_module_prefix_registers():
    assert _python("import sys, torchsoil; print('gymnasium' in sys.modules)").strip() == "False"
    out = _python("import gymnasium\n"
                  "env = gymnasium.make('torchsoil:torchsoil/SoilTraverse-v0')\n"
                  "print(type(env.unwrapped).__name__)")
    assert out.strip() == "SoilTraverseEnv"
