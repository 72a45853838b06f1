"""Projected gradient descent on the soil parameters of one window (paper eq. update).

Two update rules, both projected onto the parameter bounds after every step:
- `gd`: the paper's theta_i <- clip(theta_i - alpha_i dC/dtheta_i).
- `rprop` (default): per-parameter step sizes that grow by 1.2 while the gradient keeps its
  sign and halve when it flips; the step uses only the sign. The cost is an L1 norm, whose
  gradient keeps its size up to the optimum, so fixed learning rates either crawl or
  oscillate; sign steps with adaptive sizes converge in a few tens of steps without tuning
  per window (scripts/bench.py compares both).
Gradients come from autograd through the simulator, or from forward finite differences with
the 1 + P simulations in one batched call.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import torch


class FitResult(NamedTuple):
    """theta: (P,) best parameters found; cost: their cost, m; iterations: gradient
    evaluations; converged: every step fell below the tolerance before the cap."""

    theta: torch.Tensor
    cost: float
    iterations: int
    converged: bool


def gradient(objective: Callable[[torch.Tensor], torch.Tensor], theta: torch.Tensor,
             upper: torch.Tensor, mode: str = "autograd", fd_step: torch.Tensor | None = None
             ) -> tuple[float, torch.Tensor]:
    """Cost and gradient at theta (P,). objective maps (B, P) -> (B,) costs."""
    if mode == "autograd":
        t = theta.detach().clone().requires_grad_(True)
        c = objective(t[None])[0]
        (g,) = torch.autograd.grad(c, t)
        return float(c.detach()), g
    if mode != "fd":
        raise ValueError(f"unknown gradient mode {mode!r}; use autograd or fd")
    step = torch.where(theta + fd_step > upper, -fd_step, fd_step)  # stay inside the bounds
    batch = theta.detach().repeat(len(theta) + 1, 1)
    batch[1:] += torch.diag(step)
    with torch.no_grad():
        c = objective(batch)
    return float(c[0]), (c[1:] - c[0]) / step


def fit(objective, theta0: torch.Tensor, lower: torch.Tensor, upper: torch.Tensor, *, scale: torch.Tensor,
        rule: str = "rprop", step: float = 0.5, lr: torch.Tensor | None = None, max_iter: int = 40,
        step_tol: float = 0.02, grad: str = "autograd", fd_step: torch.Tensor | None = None) -> FitResult:
    """Minimise objective over the box [lower, upper] from theta0 (all (P,), parameter units).

    scale: (P,) the unit each parameter's steps are measured in (rprop steps and step_tol).
    """
    theta = theta0.detach().clone().clamp(lower, upper)
    steps = torch.full_like(theta, step)
    prev = torch.zeros_like(theta)
    best, best_it = (float("inf"), theta.clone()), 0
    converged = False
    it = 0
    for it in range(1, max_iter + 1):  # noqa: B007 (it is the iteration count returned)
        cost, g = gradient(objective, theta, upper, grad, fd_step)
        if cost < best[0]:
            best, best_it = (cost, theta.clone()), it
        # a parameter at a bound whose gradient points outward cannot move: it has converged
        pinned = ((theta <= lower) & (g > 0)) | ((theta >= upper) & (g < 0)) | (g == 0)
        if rule == "gd":
            new = (theta - lr * g).clamp(lower, upper)
            moved = (new - theta).abs() / scale
            theta = new
            if bool(((moved < step_tol) | pinned).all()) or it - best_it > 3:
                converged = True  # settled, or no better point in the last 3 steps
                break
            continue
        if rule != "rprop":
            raise ValueError(f"unknown update rule {rule!r}; use rprop or gd")
        sign = torch.sign(g)
        flip = sign * prev < 0
        steps = torch.where(flip, steps * 0.5, torch.where(sign * prev > 0, steps * 1.2, steps)).clamp(max=4.0)
        sign = torch.where(flip, torch.zeros_like(sign), sign)  # after a flip, wait one step
        prev = sign
        if bool(((steps < step_tol) | pinned).all()):
            converged = True
            break
        theta = (theta - sign * steps * scale).clamp(lower, upper)
    if not converged:  # the last step's cost is not known yet
        with torch.no_grad():
            cost = float(objective(theta[None])[0])
        if cost < best[0]:
            best = (cost, theta.clone())
    return FitResult(best[1], best[0], it, converged)
