"""The single environment: Gymnasium's checker, seeding, pickling, episode ends, soil measures."""

import pickle

import numpy as np
import pytest
import torch
from env_configs import small_config
from gymnasium.utils.env_checker import check_env

from envs.soil_traverse import SoilTraverseEnv
from torchsoil.sim.relaxation import max_slope_excess


def _rollout(env, seed, n=12):
    obs, _ = env.reset(seed=seed)
    env.action_space.seed(seed)
    out = [obs]
    for _ in range(n):
        obs, r, term, trunc, info = env.step(env.action_space.sample())
        out.append((obs, r, term, trunc, info["displaced"]))
        if term or trunc:
            break
    return out


def _same(a, b):
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, tuple):
        return all(_same(x, y) for x, y in zip(a, b, strict=True))
    return np.array_equal(np.asarray(a), np.asarray(b))


def test_check_env_passes(config):
    check_env(SoilTraverseEnv(config, render_mode="rgb_array"), skip_render_check=False)


def test_same_seed_same_rollout_other_seed_differs(config):
    a = _rollout(SoilTraverseEnv(config), seed=7)
    b = _rollout(SoilTraverseEnv(config), seed=7)
    c = _rollout(SoilTraverseEnv(config), seed=8)
    assert len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b, strict=True))
    assert not _same(a[0], c[0])


def test_pickle_round_trip_continues_identically(config):
    env = SoilTraverseEnv(config)
    env.reset(seed=3)
    for _ in range(5):
        env.step(np.array([1.0, 0.2], np.float32))
    twin = pickle.loads(pickle.dumps(env))
    for _ in range(5):
        a = env.step(np.array([0.8, -0.3], np.float32))
        b = twin.step(np.array([0.8, -0.3], np.float32))
        assert _same(a[0], b[0]) and a[1:4] == b[1:4]


def test_straight_drive_reaches_goal_with_bonus():
    env = SoilTraverseEnv(small_config(start_jitter=[0, 0, 0], max_steps=60))
    env.reset(seed=0)
    for _ in range(60):
        obs, r, term, trunc, info = env.step(np.array([1.5, 0.0], np.float32))
        if term or trunc:
            break
    assert term and not trunc and info["reached_goal"]
    assert r > 5.0                                         # the goal bonus (10) dominates
    assert obs["goal"][2] <= 0.5


def test_leaving_the_field_terminates_with_penalty():
    env = SoilTraverseEnv(small_config(start=[2.0, 1.0, -90.0], start_jitter=[0, 0, 0]))
    env.reset(seed=0)
    for _ in range(20):
        obs, r, term, trunc, info = env.step(np.array([1.5, 0.0], np.float32))
        if term:
            break
    assert term and info["off_field"] and not info["reached_goal"] and r < -5.0


def test_truncation_at_step_limit(config):
    env = SoilTraverseEnv(small_config(max_steps=5))
    env.reset(seed=0)
    ends = [env.step(np.array([0.0, 0.0], np.float32))[3] for _ in range(5)]
    assert ends == [False] * 4 + [True]


def test_rut_depth_follows_the_soil_maps():
    """Flat field: the rut under the wheels is the configured sinkage, dry then wet."""
    cfg = small_config(start_jitter=[0, 0, 0], max_steps=60, sim={"fixed_iter": 0})
    cfg["field"]["roughness"] = 0.0
    env = SoilTraverseEnv(cfg)
    env.reset(seed=0)
    ruts = []
    for _ in range(14):
        ruts.append(env.step(np.array([1.0, 0.0], np.float32))[4]["rut_depth"])
    assert ruts[1] == pytest.approx(0.02, abs=1e-4)                  # dry: d = 0.02 m
    assert max(ruts) == pytest.approx(0.08, abs=1e-3)                # wet patch centre: d = 0.08 m
    info = env.step(np.array([1.0, 0.0], np.float32))[4]
    assert info["episode_max_rut"] == pytest.approx(0.08, abs=1e-3)
    assert info["episode_displaced"] > info["episode_compacted"] > 0


def test_driving_a_loop_counts_second_passes():
    cfg = small_config(start=[4.0, 2.5, 0.0], start_jitter=[0, 0, 0], max_steps=80)
    env = SoilTraverseEnv(cfg)
    env.reset(seed=0)
    repeat = 0.0
    for _ in range(50):                                  # 10 m at curvature 0.8: 1.27 loops
        repeat += env.step(np.array([1.0, 0.8], np.float32))[4]["repeat_cells"]
    passes = env.state.passes[0]
    assert int(passes.max()) == 2 and repeat > 0
    assert int((passes == 2).sum()) == pytest.approx(repeat, rel=0.05)


def test_render_shows_ruts_and_path(config):
    env = SoilTraverseEnv(config, render_mode="rgb_array")
    env.reset(seed=0)
    for _ in range(5):
        env.step(np.array([1.0, 0.0], np.float32))
    img = env.render()
    X, Y = env.params.grid.shape
    assert img.shape == (Y, X, 3) and img.dtype == np.uint8
    assert (img == 0).all(-1).sum() >= 5                  # path pixels
    assert SoilTraverseEnv(config).render() is None


def test_bad_actions_and_configs_raise_clear_errors(config):
    env = SoilTraverseEnv(config)
    with pytest.raises(RuntimeError, match="reset"):
        env.step(np.zeros(2, np.float32))
    env.reset(seed=0)
    with pytest.raises(ValueError, match=r"shape \(2,\)"):
        env.step(np.zeros(3, np.float32))
    with pytest.raises(ValueError, match="finite"):
        env.step(np.array([np.nan, 0.0], np.float32))
    with pytest.raises(ValueError, match=r"unknown setting `env.sped`"):
        SoilTraverseEnv({"sped": 1})
    with pytest.raises(ValueError, match=r"`env.sim.fixed_iter` = -1"):
        SoilTraverseEnv({"sim": {"fixed_iter": -1}})
    with pytest.raises(ValueError, match="render_mode"):
        SoilTraverseEnv(config, render_mode="human")


def test_soil_observation_true_or_noisy(config):
    env = SoilTraverseEnv(config)
    obs, _ = env.reset(seed=0)
    S = obs["soil"].shape[-1]
    centre = obs["soil"][:, S // 2, S // 2]
    assert centre[0] == pytest.approx(0.02, abs=1e-6)
    noisy = SoilTraverseEnv(small_config(soil_noise=0.2))
    nobs, _ = noisy.reset(seed=0)
    assert not np.allclose(nobs["soil"], obs["soil"])
    assert noisy.observation_space.contains(nobs)
    rel = nobs["soil"][0] / np.where(obs["soil"][0] > 0, obs["soil"][0], 1) - 1
    assert 0.1 < rel[obs["soil"][0] > 0].std() < 0.3


def test_relaxation_backends_agree_and_converged_mode_runs():
    outs = []
    for backend in ("torch", "numba"):
        env = SoilTraverseEnv(small_config(sim={"backend": backend}, start_jitter=[0, 0, 0]))
        env.reset(seed=0)
        for _ in range(6):
            env.step(np.array([1.0, 0.4], np.float32))
        outs.append(env.state.h[0].clone())
    assert float((outs[0] - outs[1]).abs().max()) < 1e-6


@pytest.mark.parametrize("fixed_iter, settled", [(None, True), (0, False)])
def test_converged_relaxation_leaves_no_slope_above_repose(fixed_iter, settled):
    """Through the wet patch (d = 0.08 m, beta = 20 deg) the rut walls must slump."""
    cfg = small_config(sim={"fixed_iter": fixed_iter}, start_jitter=[0, 0, 0])
    cfg["field"]["roughness"] = 0.0
    env = SoilTraverseEnv(cfg)
    env.reset(seed=0)
    iters = 0
    for _ in range(14):
        iters += env.step(np.array([1.0, 0.0], np.float32))[4]["relax_iterations"]
    p = env.params
    tan_beta = torch.tan(p.field.soil[-1])[None]
    excess = float(max_slope_excess(env.state.h[0][None].double(), tan_beta.double(), p.grid.dx))
    if settled:
        assert iters > 0 and excess < p.config.sim.tau + 1e-3
    else:
        assert iters == 0 and excess > 0.5


def test_field_from_params_csv_in_the_config(tmp_path):
    import csv

    p = tmp_path / "params.csv"
    with open(p, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["s", "t", "x", "y", "d1", "d2", "chi", "beta[deg]", "residual", "prediction",
                    "iterations", "seconds", "flags"])
        for x in np.arange(1.0, 7.5, 0.5):
            w.writerow([x, x, x, 2.5, 0.05, 0.01, 0.5, 30.0, 0, 0, 10, 0.1, ""])
    cfg = small_config(start_jitter=[0, 0, 0], sim={"fixed_iter": 0})
    cfg["params_csv"] = str(p)
    cfg["field"]["roughness"] = 0.0
    env = SoilTraverseEnv(cfg)
    env.reset(seed=0)
    for _ in range(3):
        info = env.step(np.array([1.0, 0.0], np.float32))[4]
    # the left track (y = 3.0) lies within reach of the replayed path: d1 = 0.05 m, not the patch
    assert info["rut_depth"] == pytest.approx(0.05, abs=1e-4)


def test_visit_length_covers_the_wheelbase_straight_and_on_arcs():
    from envs.params import visit_length
    from torchsoil.robot import paper_platform

    robot = paper_platform()
    straight = visit_length(robot, 0.0, 0.2)
    assert straight == pytest.approx(1.38 + 0.14 + 0.2 + 0.1)
    # on the tightest arc the inner rear wheel reaches the inner front wheel's rut later
    assert visit_length(robot, 0.8, 0.2) > straight
