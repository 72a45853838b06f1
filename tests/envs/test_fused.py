"""The fused CPU kernels of a step (envs._step_numba) against the torch ops with the numba
relaxation: same field layers, rewards, info and observations to float32 rounding."""

import dataclasses
import math

import numpy as np
import pytest
import torch
from env_configs import small_config

from envs import core
from envs.params import make_params

pytest.importorskip("numba")

# x, y [m], yaw [deg] on the 8 m x 5 m field: the middle, the four edges, a corner, the wet patch
STARTS = [(2.0, 2.5, 0.0), (0.1, 2.5, 180.0), (7.9, 1.0, 0.0), (3.0, 0.08, -90.0), (5.0, 4.93, 90.0),
          (0.12, 0.12, 225.0), (4.5, 2.5, 30.0), (2.5, 3.5, -45.0), (6.0, 2.0, 135.0), (1.5, 1.5, 10.0)]


def _actions(n: int, t: int) -> torch.Tensor:
    """(n, 2): driving forward and back (revisits), straight and on the tightest arcs, one standing."""
    v = np.where(np.arange(n) % 3 == 0, 1.0, 0.6) * (1 if (t // 8) % 2 == 0 else -1)
    k = np.array([[0.0, 0.8, -0.8, 0.3, -0.3][i % 5] for i in range(n)])
    v[n - 1] = 0.0
    return torch.tensor(np.stack([v, k], 1), dtype=torch.float32)


def _start(params, n: int) -> core.TraverseState:
    starts = np.array([STARTS[i % len(STARTS)] for i in range(n)])
    pose = np.column_stack([starts[:, :2], np.radians(starts[:, 2])])
    state = core.empty_state(params, n)
    return core.reset_episodes(params, state, np.arange(n), pose, np.tile([6.5, 2.5], (n, 1)))


def _close(a: torch.Tensor, b: torch.Tensor, atol: float, what: str):
    a, b = a.double(), b.double()
    assert torch.equal(torch.isfinite(a), torch.isfinite(b)), what
    fin = torch.isfinite(a)
    assert torch.equal(a[~fin], b[~fin]), what
    err = (a[fin] - b[fin]).abs().max().item() if fin.any() else 0.0
    assert err <= atol, f"{what}: max abs difference {err}"


def _rollout_pair(sim: dict, n: int = 10, steps: int = 16, wheel_scale: float = 1.0,
                  visit_length: float | None = None):
    fused = make_params(small_config(sim={"backend": "numba", **sim}, max_steps=100))
    assert fused.fused
    if wheel_scale != 1.0:
        fused = dataclasses.replace(fused, wheels=fused.wheels * wheel_scale)
    if visit_length is not None:
        fused = dataclasses.replace(fused, visit_length=visit_length)
    eager = dataclasses.replace(fused, fused=False)
    a, b = _start(fused, n), _start(eager, n)
    for t in range(steps):
        act = _actions(n, t)
        a, ra, ta, tra, ia = core.step(fused, a, act)
        b, rb, tb, trb, ib = core.step(eager, b, act)
        for name in ("h", "ref", "ref_odom", "passes"):
            _close(getattr(a, name), getattr(b, name), 2e-6, f"step {t} {name}")
        _close(ra, rb, 2e-5, f"step {t} reward")
        assert torch.equal(ta, tb) and torch.equal(tra, trb)
        for key in ia:
            _close(ia[key], ib[key], 1e-6 if key != "relax_iterations" else 0, f"step {t} info {key}")
        oa, ob = core.observation(fused, a), core.observation(eager, b)
        for key in oa:
            _close(torch.from_numpy(oa[key]), torch.from_numpy(ob[key]), 2e-6, f"step {t} obs {key}")
    return a, ia


@pytest.mark.parametrize("fixed_iter", [4, None])
def test_fused_step_matches_the_torch_ops(fixed_iter):
    state, _ = _rollout_pair({"fixed_iter": fixed_iter})
    assert state.passes.max() == 1                      # rear wheels in an ongoing visit


@pytest.mark.parametrize("fixed_iter", [4, None])
def test_fused_step_matches_the_torch_ops_on_revisits(fixed_iter):
    """Visits of 0.3 m: the rear wheels and the drive back enter cells again."""
    state, _ = _rollout_pair({"fixed_iter": fixed_iter}, visit_length=0.3)
    assert state.passes.max() >= 3


def test_fused_step_with_overlapping_windows_and_a_wide_reference_disc():
    """Wheels 0.3x as far apart: a robot's windows share cells (later ones written last); a
    reference disc of 2 cells radius (`sinkage.reference_height` in each window)."""
    state, _ = _rollout_pair({"ref_radius": 1.5, "fixed_iter": 6}, n=6, steps=6, wheel_scale=0.3)
    assert state.passes.max() >= 1


def test_fused_step_of_one_robot_runs_the_serial_kernel():
    _rollout_pair({"fixed_iter": 4}, n=1, steps=4)


def test_fused_relaxation_is_the_numba_relaxation():
    """A window relaxed by the fused kernel equals `relax(..., backend="numba")` bit for bit."""
    from envs import _step_numba as sn
    from torchsoil.sim.relaxation import face_tan, relax

    rng = np.random.default_rng(0)
    h = torch.tensor(rng.normal(0, 0.03, (3, 17, 17)), dtype=torch.float32)
    tan = torch.tensor(rng.uniform(0.3, 0.8, (3, 17, 17)), dtype=torch.float32)
    for fixed_iter in (4, None):
        want = relax(h, tan, 0.05, None, 0.01, 2000, fixed_iter, 4.0, "numba")
        for b in range(3):
            got = h[b].numpy().copy()
            tb = face_tan(tan[b:b + 1])[0].numpy().copy()
            n = sn.relax_window(got, tb, 1 / 0.05, 0.05 / 4.0, 0.01, fixed_iter or 2000, fixed_iter is not None,
                                np.empty(17), np.empty((17, 17), np.float32))
            assert n == want.iterations[b].item()
            assert np.array_equal(got, want.h[b].numpy())
    assert math.isfinite(float(want.h.sum()))
