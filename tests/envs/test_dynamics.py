"""Pure functions of envs.dynamics: kinematics, segment geometry, one deformation step."""

import math

import numpy as np
import pytest
import torch

from envs import dynamics as dyn
from torchsoil.grid import Grid
from torchsoil.sim.sinkage import taper


def test_step_pose_straight_and_arc():
    pose = torch.tensor([[1.0, 2.0, 0.3], [0.0, 0.0, 0.0]], dtype=torch.float64)
    out = dyn.step_pose(pose, torch.tensor([2.0, 1.0], dtype=torch.float64),
                        torch.tensor([0.0, 0.5], dtype=torch.float64), 0.5)
    assert torch.allclose(out[0], torch.tensor([1 + math.cos(0.3), 2 + math.sin(0.3), 0.3], dtype=torch.float64))
    # arc of radius 2 m turned by 0.25 rad from the origin: (R sin a, R (1 - cos a))
    R, a = 2.0, 0.25
    assert torch.allclose(out[1], torch.tensor([R * math.sin(a), R * (1 - math.cos(a)), a], dtype=torch.float64))


def test_step_pose_full_circle_returns():
    pose = torch.tensor([[3.0, -1.0, 1.0]], dtype=torch.float64)
    kappa = 0.8
    n = 100
    dt = 2 * math.pi / kappa / n
    p = pose
    for _ in range(n):
        p = dyn.step_pose(p, torch.ones(1, dtype=torch.float64), torch.full((1,), kappa, dtype=torch.float64), dt)
    assert torch.allclose(p[0, :2], pose[0, :2], atol=1e-9)
    assert math.isclose(p[0, 2].item() - 1.0, 2 * math.pi, rel_tol=1e-9)


def _windows(start, end, yaw=0.0, window=20):
    grid = Grid(0.05, (0.0, 0.0), (100, 100))
    s = torch.tensor([[start]], dtype=torch.float32)
    e = torch.tensor([[end]], dtype=torch.float32)
    return dyn.wheel_windows(s, e, torch.tensor([yaw]), window, grid), grid


def _at(win, i, j):
    k = (win.field == i * 100 + j).nonzero()
    assert len(k) == 1, "cell not in the window"
    return int(k[0])


def test_wheel_windows_geometry():
    win, grid = _windows((0.5, 1.0), (0.7, 1.0))                 # segment along +x
    on_line = _at(win, 12, 20)                                    # (0.6, 1.0)
    assert win.dist[on_line] == pytest.approx(0.0, abs=1e-6)
    assert win.lateral[on_line] == pytest.approx(0.0, abs=1e-6)
    assert win.along[on_line] == pytest.approx(0.1, abs=1e-6)
    left = _at(win, 12, 22)                                       # (0.6, 1.1): left of +x
    assert win.lateral[left] == pytest.approx(0.1, abs=1e-6)
    assert win.dist[left] == pytest.approx(0.1, abs=1e-6)
    ahead = _at(win, 18, 21)                                      # (0.9, 1.05): beyond the end
    assert win.dist[ahead] == pytest.approx(math.hypot(0.2, 0.05), abs=1e-6)
    assert win.along[ahead] == pytest.approx(0.4, abs=1e-6)       # not clamped
    assert torch.allclose(win.length, torch.tensor(0.2), atol=1e-6)
    assert win.shape == (1, 1, 20, 20) and len(win.field.unique()) == 400


def test_wheel_windows_standing_wheel_uses_heading_and_stay_on_the_field():
    win, grid = _windows((1.0, 1.0), (1.0, 1.0), yaw=math.pi / 2)
    c = _at(win, 18, 20)                                          # (0.9, 1.0): left of +y heading
    assert win.lateral[c] == pytest.approx(0.1, abs=1e-6)
    assert win.dist[c] == pytest.approx(0.1, abs=1e-6)
    edge, _ = _windows((0.0, 4.95), (0.1, 4.95))                  # at the field's corner
    assert edge.field.min() >= 0 and edge.field.max() < 100 * 100
    assert _at(edge, 0, 99) >= 0


def _one_step(N=1, d=0.03, chi=0.6, beta_deg=30.0, fixed_iter=4, backend="torch", visit=False,
              h=None, ref=None):
    grid = Grid(0.05, (0.0, 0.0), (60, 60))
    wheels = torch.tensor([[0.0, 0.5], [0.0, -0.5]])
    pose0 = torch.tensor([[1.4, 1.5, 0.2]] * N)
    pose1 = dyn.step_pose(pose0, torch.full((N,), 1.0), torch.full((N,), 0.3), 0.2)
    start, end = dyn.to_world(pose0, wheels), dyn.to_world(pose1, wheels)
    W = dyn.window_size(start, end, 0.07, 0.05, 2, 0.05)
    win = dyn.wheel_windows(start, end, pose0[:, 2], W, grid)
    h = torch.zeros(N * 2, W, W) if h is None else h
    E = win.field.shape[0]
    ref_e = torch.zeros(E) if ref is None else ref
    out = dyn.deform(h, torch.full((N * 2, W, W), math.tan(math.radians(beta_deg))), win, ref_e,
                     torch.full((E,), visit), torch.full((E,), d), torch.full((E,), chi),
                     0.07, 0.0, 0.05, 0.05, fixed_iter=fixed_iter, backend=backend)
    return out, win, h


@pytest.mark.parametrize("backend", ["torch", "numba"])
def test_deform_volume_balance(backend):
    out, win, h = _one_step(backend=backend)
    dv = (out.h - h).sum().item() * 0.05**2
    assert out.removed.item() > 0
    # relaxation conserves volume: the net change is what was dug and not deposited
    assert dv == pytest.approx(-(out.removed - out.deposited).item(), abs=1e-7)
    # all of chi * dug lands in the bands (the windows hold every band cell)
    assert out.deposited.item() == pytest.approx(0.6 * out.removed.item(), rel=1e-4)


def _expected_cut(win, d, radius=0.07):
    """Per window cell, the cut s * d of the window's wheel (0 outside its footprint)."""
    return taper(win.lateral / radius) * (win.dist <= radius) * d


def test_deform_rut_depth_equals_sinkage_on_flat_ground():
    out, win, h = _one_step(d=0.03, fixed_iter=0)
    cut = _expected_cut(win, 0.03)
    got = -out.h.reshape(-1)
    assert torch.allclose(got[cut > 0], cut[cut > 0], atol=1e-6)
    assert cut.max().item() == pytest.approx(0.03, abs=2e-3)     # the taper peaks on the wheel line


def test_deform_ongoing_visit_digs_no_deeper_new_visit_does():
    first, win, _ = _one_step(fixed_iter=0)
    h1 = first.h
    again, _, _ = _one_step(fixed_iter=0, h=h1.clone(), ref=first.ref, visit=True)
    assert again.removed.item() == pytest.approx(0.0, abs=1e-9)
    second, _, _ = _one_step(fixed_iter=0, h=h1.clone(), visit=False, ref=h1.reshape(-1))
    cut = _expected_cut(win, 0.03)
    got = -second.h.reshape(-1)
    assert torch.allclose(got[cut > 0], 2 * cut[cut > 0], atol=1e-6)   # a second pass digs again


def test_deform_batch_elements_are_independent():
    single, _, _ = _one_step(N=1, backend="numba")
    batch, _, _ = _one_step(N=3, backend="numba")
    for n in range(3):
        assert torch.allclose(batch.h[2 * n:2 * n + 2], single.h, atol=1e-7)
    assert torch.allclose(batch.removed, single.removed.expand(3))


def test_body_grid_index_rotation():
    grid = Grid(0.1, (0.0, 0.0), (50, 40))
    pose = torch.tensor([[2.0, 1.0, math.pi / 2]])
    flat, inside = dyn.body_grid_index(pose, torch.tensor([[0.0, 0.0], [1.0, 0.0], [0.0, 100.0]]), grid)
    assert flat[0, 0].item() == 20 * 40 + 10
    assert flat[0, 1].item() == 20 * 40 + 20            # 1 m ahead is +y when facing +y
    assert inside[0].tolist() == [True, True, False]


def test_goal_in_body_and_reward():
    g = dyn.goal_in_body(torch.tensor([[1.0, 1.0, math.pi / 2]]), torch.tensor([[1.0, 3.0]]))
    assert torch.allclose(g, torch.tensor([[2.0, 0.0, 2.0]]), atol=1e-6)
    w = {"progress": 2.0, "displaced": 10.0, "compacted": 5.0, "rut_depth": 1.0,
         "repeat_cells": 0.5, "time": 0.1}
    dmg = dyn.Damage(*(torch.tensor([v]) for v in (0.01, 0.02, 0.03, 2.0)))
    r = dyn.reward(torch.tensor([0.2]), dmg, w)
    assert r.item() == pytest.approx(0.4 - 0.1 - 0.1 - 0.03 - 1.0 - 0.1)
    assert np.isfinite(r.item())
