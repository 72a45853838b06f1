"""The batched vector env: agreement with single envs, autoreset, shapes, errors."""

import numpy as np
import pytest
from env_configs import small_config

from envs.soil_traverse import SoilTraverseEnv
from envs.vector import SoilTraverseVectorEnv


def test_vector_env_i_matches_single_env_seeded_seed_plus_i(config):
    N, seed = 3, 11
    venv = SoilTraverseVectorEnv(N, config)
    vobs, _ = venv.reset(seed=seed)
    singles = [SoilTraverseEnv(config) for _ in range(N)]
    sobs = [e.reset(seed=seed + i)[0] for i, e in enumerate(singles)]
    for i in range(N):
        for k in sobs[i]:
            np.testing.assert_allclose(vobs[k][i], sobs[i][k], atol=1e-6, err_msg=k)
    rng = np.random.default_rng(0)
    for _ in range(8):
        acts = rng.uniform([-0.5, -0.8], [1.5, 0.8], size=(N, 2)).astype(np.float32)
        vobs, vr, vterm, vtrunc, vinfo = venv.step(acts)
        for i, e in enumerate(singles):
            o, r, term, trunc, info = e.step(acts[i])
            for k in o:
                np.testing.assert_allclose(vobs[k][i], o[k], atol=1e-5, err_msg=k)
            assert vr[i] == pytest.approx(r, abs=1e-5)
            assert (vterm[i], vtrunc[i]) == (term, trunc)
            assert vinfo["displaced"][i] == pytest.approx(info["displaced"], abs=1e-9)
    assert venv.observation_space.contains(vobs)


def test_next_step_autoreset():
    cfg = small_config(start=[2.0, 1.0, -90.0], start_jitter=[0, 0, 0])
    venv = SoilTraverseVectorEnv(2, cfg)
    obs0, _ = venv.reset(seed=0)
    acts = np.array([[1.5, 0.0], [0.0, 0.0]], np.float32)   # env 0 drives off the field
    for _ in range(20):
        obs, r, term, trunc, info = venv.step(acts)
        if term[0]:
            break
    assert term[0] and info["off_field"][0] and not term[1]
    moved = venv.state.h[0].sum().item()
    obs, r, term, trunc, info = venv.step(acts)               # the autoreset step
    assert r[0] == 0.0 and not term[0] and not trunc[0]
    np.testing.assert_allclose(obs["state"][0], obs0["state"][0])
    assert venv.state.h[0].sum().item() != moved               # the field is undeformed again
    assert np.array_equal(venv.state.passes[0].numpy(), np.zeros_like(venv.state.passes[0].numpy()))
    obs, r, term, trunc, info = venv.step(acts)               # and it drives again
    assert obs["state"][0][2:4] != pytest.approx(obs0["state"][0][2:4])


def test_shapes_render_and_errors(config):
    venv = SoilTraverseVectorEnv(4, config, render_mode="rgb_array")
    obs, _ = venv.reset(seed=[1, 2, 3, 4])
    assert obs["heightmap"].shape == (4, 2, 8, 8) and obs["soil"].shape == (4, 4, 8, 8)
    assert venv.action_space.shape == (4, 2)
    frames = venv.render()
    assert len(frames) == 4 and frames[0].ndim == 3
    with pytest.raises(ValueError, match=r"\(4, 2\)"):
        venv.step(np.zeros((3, 2), np.float32))
    with pytest.raises(ValueError, match="need 4 seeds"):
        venv.reset(seed=[1, 2])
    with pytest.raises(ValueError, match="num_envs"):
        SoilTraverseVectorEnv(0, config)
