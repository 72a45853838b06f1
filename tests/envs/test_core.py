"""The pure functions of envs.core: state, transition, reward, episode ends."""

import numpy as np
import pytest
import torch
from env_configs import small_config

from envs import core
from envs import dynamics as dyn
from envs.params import make_params


@pytest.fixture(scope="module")
def params():
    return make_params(small_config(start_jitter=[0, 0, 0]))


def _started(params, n=2):
    state = core.empty_state(params, n)
    rngs = [np.random.default_rng(i) for i in range(n)]
    return core.reset_episodes(params, state, np.arange(n), *core.sample_starts(params, rngs))


def test_state_layers_are_named_and_reset(params):
    state = _started(params)
    X, Y = params.grid.shape
    for name in ("h", "ref", "ref_odom", "passes"):
        assert getattr(state, name).shape == (2, X, Y)
    assert torch.equal(state.h[1], params.field.h0)
    assert torch.isinf(state.ref_odom).all() and (state.ref_odom < 0).all()
    assert torch.allclose(state.pose[0], torch.tensor([2.0, 2.5, 0.0]))
    assert torch.equal(state.path[:, 0], state.pose[0, :2].expand(params.config.max_steps + 1, 2))


def test_transition_updates_only_the_layers_in_place(params):
    """Documented: the layers are written in place (shared with the new state); the other
    tensors of the input are left alone; the same input gives the same output."""
    state = _started(params)
    pristine, twin = core.clone_state(state), core.clone_state(state)
    action = torch.tensor([[1.0, 0.0], [0.5, 0.4]])
    new, out = core.transition(params, state, action)
    assert new.h is state.h and new.passes is state.passes
    assert not torch.equal(state.h, pristine.h) and state.passes.sum() > 0
    for name in ("pose", "control", "odom", "steps", "goal", "path"):
        assert torch.equal(getattr(state, name), getattr(pristine, name)), name
    assert all(torch.equal(a, b) for a, b in zip(state.totals, pristine.totals, strict=True))
    again, out2 = core.transition(params, twin, action)
    for a, b in zip(new[:-1], again[:-1], strict=True):
        assert torch.equal(a, b)
    assert torch.equal(out.damage.displaced, out2.damage.displaced) and out.damage.displaced.min() > 0
    assert new.steps.tolist() == [1, 1] and torch.equal(new.path[1], new.pose[:, :2])


def test_reward_terminal_truncated_on_a_made_outcome(params):
    w = params.weights
    zero = torch.zeros(3)
    out = core.StepOutcome(progress=torch.tensor([0.2, 0.0, 0.0]), damage=dyn.Damage(zero, zero, zero, zero),
                           relax_iterations=zero, reached=torch.tensor([True, False, False]),
                           off_field=torch.tensor([True, True, False]))
    r = core.reward(out, w)
    assert r.tolist() == pytest.approx([0.2 * w["progress"] - w["time"] + w["goal"],
                                        -w["time"] - w["off_field"], -w["time"]])
    term = core.terminal(out)
    assert term.tolist() == [True, True, False]
    state = core.empty_state(params, 3)._replace(steps=torch.tensor([40, 40, 40]))
    assert core.truncated(params, state, term).tolist() == [False, False, True]
    info = core.step_info(state, out)
    assert info["off_field"].tolist() == [False, True, False]          # reaching the goal wins


def test_observation_and_render_are_functions_of_the_state(params):
    state = _started(params)
    obs = core.observation(params, state)
    assert obs["heightmap"].shape == (2, 2, 8, 8) and obs["goal"][0, 0] == pytest.approx(4.5, abs=1e-5)
    img = core.render(params, state, 1)
    assert img.shape == (*params.grid.shape[::-1], 3)
