import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from torchsoil.sim.relaxation import max_slope_excess, relax

BACKENDS = ["torch", "numba"]


def pile(X=24, Y=20, height=0.05, dtype=torch.float64, seed=0):
    """A square heap on rough ground: slopes far above any angle of repose."""
    g = torch.Generator().manual_seed(seed)
    h = 0.002 * torch.randn(1, X, Y, generator=g, dtype=dtype)
    h[:, X // 2 - 2:X // 2 + 2, Y // 2 - 2:Y // 2 + 2] += height
    return h


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-12), (torch.float32, 1e-6)])
def test_volume_conserved(backend, dtype, tol):
    h = pile(dtype=dtype)
    out = relax(h, torch.tensor([math.tan(math.radians(25))], dtype=dtype), 0.02, backend=backend)
    assert out.iterations.item() > 5
    assert abs(out.h.sum().item() - h.sum().item()) <= tol * h.abs().sum().item()


@pytest.mark.parametrize("backend", BACKENDS)
def test_converged_slopes_bounded(backend):
    h = pile()
    tb = torch.tensor([math.tan(math.radians(30))], dtype=torch.float64)
    out = relax(h, tb, 0.02, tau=0.01, backend=backend)
    assert not out.capped.item()
    assert max_slope_excess(out.h, tb[:, None, None], 0.02).item() < 0.01
    assert max_slope_excess(h, tb[:, None, None], 0.02).item() > 1.0


@settings(max_examples=15, deadline=None)
@given(height=st.floats(0.005, 0.08), beta=st.floats(5, 80), seed=st.integers(0, 1000),
       dx=st.sampled_from([0.015, 0.02, 0.05]))
def test_invariants_hypothesis(height, beta, seed, dx):
    h = pile(height=height, seed=seed)
    tb = torch.tensor([math.tan(math.radians(beta))], dtype=torch.float64)
    out = relax(h, tb, dx)
    assert abs(out.h.sum().item() - h.sum().item()) < 1e-11
    if not out.capped.item():
        assert max_slope_excess(out.h, tb[:, None, None], dx).item() < 0.01
    # relaxation only moves soil downhill: the peak never rises, the lowest cell never sinks
    assert out.h.max() <= h.max() + 1e-12 and out.h.min() >= h.min() - 1e-12


def test_backends_agree_and_batch_independent():
    h = torch.cat([pile(seed=s) for s in range(3)])
    tb = torch.tan(torch.tensor([20.0, 35.0, 60.0], dtype=torch.float64) * math.pi / 180)
    a = relax(h, tb, 0.02, backend="torch")
    b = relax(h, tb, 0.02, backend="numba")
    assert torch.allclose(a.h, b.h, atol=1e-12)
    assert a.iterations.tolist() == b.iterations.tolist()
    assert len(set(a.iterations.tolist())) == 3  # elements stop on their own
    for i in range(3):
        one = relax(h[i:i + 1], tb[i:i + 1], 0.02, backend="numba")
        assert torch.allclose(one.h[0], b.h[i], atol=1e-12)


@pytest.mark.parametrize("backend", BACKENDS)
def test_cap_flag_and_fixed_iterations(backend):
    h = pile()
    tb = torch.tensor([math.tan(math.radians(20))], dtype=torch.float64)
    capped = relax(h, tb, 0.02, max_iter=3, backend=backend)
    assert capped.capped.item() and capped.iterations.item() == 3
    fixed = relax(h, tb, 0.02, fixed_iter=5, backend=backend)
    assert fixed.iterations.item() == 5 and not fixed.capped.item()


@pytest.mark.parametrize("backend", BACKENDS)
def test_domain_blocks_flux(backend):
    h = pile()
    domain = torch.zeros(h.shape[1:], dtype=torch.bool)
    domain[6:18, 5:15] = True
    out = relax(h, torch.tensor([0.3], dtype=torch.float64), 0.02, domain=domain, backend=backend)
    assert torch.equal(out.h[0][~domain], h[0][~domain])
    assert abs(out.h[0][domain].sum() - h[0][domain].sum()) < 1e-12


def test_numba_adjoint_matches_torch_autograd():
    h0 = pile(X=12, Y=10, seed=3)
    tb0 = torch.tan(torch.tensor([math.radians(25)], dtype=torch.float64))
    w = torch.randn(h0.shape, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    grads = []
    for backend in BACKENDS:
        h = h0.clone().requires_grad_(True)
        tb = tb0.clone().requires_grad_(True)
        (relax(h, tb, 0.02, backend=backend).h * w).sum().backward()
        grads.append((h.grad, tb.grad))
    assert torch.allclose(grads[0][0], grads[1][0], atol=1e-10)
    assert torch.allclose(grads[0][1], grads[1][1], rtol=1e-8)


@pytest.mark.parametrize("backend", BACKENDS)
def test_gradcheck_fixed_iterations(backend):
    h = pile(X=8, Y=7, height=0.03).requires_grad_(True)
    # distinct angles per cell: a face takes the steeper of its two cells' (no ties to split)
    g = torch.Generator().manual_seed(1)
    tb = (math.tan(math.radians(30)) + 0.2 * torch.rand(1, 8, 7, generator=g, dtype=torch.float64)).requires_grad_(True)
    fn = lambda h, tb: relax(h, tb, 0.02, fixed_iter=4, backend=backend).h  # noqa: E731
    assert torch.autograd.gradcheck(fn, (h, tb), eps=1e-7, atol=1e-6)


def test_non_contiguous_input():
    h = pile().transpose(1, 2).contiguous().transpose(1, 2)
    assert not h.is_contiguous()
    tb = torch.tensor([0.5], dtype=torch.float64)
    a = relax(h, tb, 0.02, backend="numba")
    b = relax(h.contiguous(), tb, 0.02, backend="torch")
    assert torch.allclose(a.h, b.h, atol=1e-12)


def test_unknown_backend():
    with pytest.raises(ValueError, match="backend"):
        relax(pile(), torch.tensor([0.5], dtype=torch.float64), 0.02, backend="cuda-magic")


@pytest.mark.parametrize("backend", BACKENDS)
def test_cohesive_trench_stands_on_both_sides(backend):
    """A trench cut in flat ground, its cells settling at 80 deg and the ground around at 20
    deg: every face that touches the trench is a cut face, so both walls stand as cut, and the
    mirrored trench relaxes to the mirrored surface."""
    X, Y, dx = 12, 21, 0.02
    h = torch.zeros(1, X, Y, dtype=torch.float64)
    h[:, :, 8:13] = -0.05                                   # 5 cells wide, 50 mm deep
    tb = torch.full((1, X, Y), math.tan(math.radians(20)), dtype=torch.float64)
    tb[:, :, 8:13] = math.tan(math.radians(80))
    out = relax(h, tb, dx, backend=backend)
    assert torch.equal(out.h, h)                            # 2.5 = 50 mm / 20 mm < tan 80 deg
    loose = relax(h, torch.full_like(tb, math.tan(math.radians(20))), dx, backend=backend)
    assert (loose.h - h).abs().max().item() > 0.01          # at 20 deg the same walls collapse
    flipped = relax(torch.flip(h, [2]), torch.flip(tb, [2]), dx, backend=backend).h
    assert torch.allclose(torch.flip(flipped, [2]), out.h, atol=1e-12)
    assert max_slope_excess(out.h, tb, dx).item() < 0
