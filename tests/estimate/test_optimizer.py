import pytest
import torch

from torchsoil.estimate.optimizer import fit, gradient

TARGET = torch.tensor([0.03, 0.8, 0.6], dtype=torch.float64)
SCALE = torch.tensor([0.005, 0.1, 0.1], dtype=torch.float64)
LO = torch.tensor([0.0, 0.0, 0.035], dtype=torch.float64)
HI = torch.tensor([0.3, 2.0, 1.57], dtype=torch.float64)


def l1(theta):  # (B, 3) -> (B,): an L1 bowl like the paper's cost
    return ((theta - TARGET) / SCALE).abs().sum(1) * 1e-3


GD_LR = 0.05 * SCALE**2 / 1e-3  # GD steps of 0.05 scale units on this bowl
START = torch.tensor([0.01, 0.2, 0.3], dtype=torch.float64)


@pytest.mark.parametrize("rule", ["rprop", "gd"])
def test_converges_to_minimum(rule):
    res = fit(l1, START, LO, HI, scale=SCALE, rule=rule, lr=GD_LR, max_iter=400, step_tol=0.01)
    assert torch.all(((res.theta - TARGET) / SCALE).abs() < 0.1)


def test_rprop_beats_gd_on_l1():
    """Fixed-rate GD on an L1 cost crawls at a fixed speed and never settles; sign steps with
    adaptive sizes stop near the minimum in far fewer evaluations."""
    a = fit(l1, START, LO, HI, scale=SCALE, rule="rprop", max_iter=400, step_tol=0.01)
    b = fit(l1, START, LO, HI, scale=SCALE, rule="gd", lr=GD_LR, max_iter=400, step_tol=0.01)
    assert a.converged and a.iterations < 60 < b.iterations
    assert torch.all(((a.theta - TARGET) / SCALE).abs() < 0.02)


def test_projection_keeps_bounds():
    far = torch.tensor([0.5, 3.0, 0.0], dtype=torch.float64)  # minimum outside the box
    res = fit(lambda t: ((t - far) / SCALE).abs().sum(1), TARGET.clone(), LO, HI, scale=SCALE, max_iter=200)
    assert torch.all(res.theta >= LO) and torch.all(res.theta <= HI)
    assert torch.allclose(res.theta, torch.maximum(torch.minimum(far, HI), LO), atol=1e-3)
    assert res.converged


def test_fd_gradient_matches_autograd():
    def smooth(t):
        return ((t - TARGET) ** 2 * torch.tensor([100.0, 1.0, 3.0], dtype=t.dtype)).sum(1)

    theta = torch.tensor([0.05, 0.5, 0.9], dtype=torch.float64)
    _, g_auto = gradient(smooth, theta, HI, "autograd")
    _, g_fd = gradient(smooth, theta, HI, "fd", torch.full((3,), 1e-7, dtype=torch.float64))
    assert torch.allclose(g_auto, g_fd, rtol=1e-4)
    # at the upper bound the step goes backwards and stays inside the box
    seen = []
    _, g_edge = gradient(lambda t: seen.append(t.clone()) or smooth(t), HI.clone(), HI, "fd",
                         torch.full((3,), 1e-7, dtype=torch.float64))
    assert torch.all(seen[0] <= HI)
    with pytest.raises(ValueError, match="gradient mode"):
        gradient(smooth, theta, HI, "magic")
