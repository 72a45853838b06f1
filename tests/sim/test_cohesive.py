"""Two-angle (cohesive) relaxation: hand-built surfaces whose outcome the physics fixes."""

import math

import pytest
import torch

from torchsoil.sim.cohesive import relax_two_angle
from torchsoil.sim.relaxation import max_slope_excess, relax

BACKENDS = ["torch", "numba"]
DX = 0.02
TAU = 0.01


def tan(deg):
    return torch.tensor([math.tan(math.radians(deg))], dtype=torch.float64)


def ramp(deg, X=24, Y=6, start=8, cells=6):
    """(1, X, Y) a flat floor, a face at `deg` over `cells` cells from x index `start`, a flat top."""
    i = torch.arange(X, dtype=torch.float64).clamp(start, start + cells) - start
    return (i * DX * math.tan(math.radians(deg)))[None, :, None].expand(1, X, Y).clone()


def slopes(h):
    """(1, X - 1, Y) |dh/dx| between neighbours along x."""
    return ((h[:, 1:] - h[:, :-1]) / DX).abs()


@pytest.mark.parametrize("backend", BACKENDS)
def test_a_bare_cut_face_below_the_intact_angle_stands(backend):
    h = ramp(60)
    r = relax_two_angle(h, torch.zeros_like(h), tan(32), tan(70), DX, backend=backend)
    assert torch.equal(r.h, h) and r.iterations.item() == 0 and not r.capped.item()


@pytest.mark.parametrize("backend", BACKENDS)
def test_a_bare_cut_face_above_the_intact_angle_fails_to_it(backend):
    h = ramp(60)
    r = relax_two_angle(h, torch.zeros_like(h), tan(32), tan(45), DX, backend=backend)
    assert not r.capped.item() and r.iterations.item() > 10
    assert abs(r.h.sum().item() - h.sum().item()) < 1e-12
    s = slopes(r.h)
    assert s.max().item() <= 1.0 + TAU and s.max().item() > 0.9      # down to tan 45 = 1, no further
    assert r.loose.sum().item() > 0                                   # what failed is loose now
    assert (r.h - r.loose <= h + 1e-12).all()                         # intact ground only loses


@pytest.mark.parametrize("backend", BACKENDS)
def test_a_loose_heap_on_an_intact_floor_settles_at_the_loose_angle(backend):
    h = torch.zeros(1, 24, 24, dtype=torch.float64)
    h[:, 10:14, 10:14] = 0.05                     # slopes 2.5 < tan 70: the floor never fails
    r = relax_two_angle(h, h.clone(), tan(32), tan(70), DX, backend=backend)
    assert not r.capped.item()
    assert abs(r.h.sum().item() - h.sum().item()) < 1e-12
    assert torch.allclose(r.h - r.loose, torch.zeros_like(h), atol=1e-15)     # the floor is untouched
    assert max_slope_excess(r.h, tan(32)[:, None, None], DX).item() < 2 * TAU
    assert max_slope_excess(h, tan(32)[:, None, None], DX).item() > 1.5


@pytest.mark.parametrize("backend", BACKENDS)
def test_a_loose_layer_slides_off_an_intact_wall_and_stops_where_it_runs_out(backend):
    wall = ramp(60, X=30, start=14, cells=8)          # intact face at 60 deg: loose 32 < 60 < intact 70
    loose = torch.zeros_like(wall)
    loose[:, 14:] = 0.01                               # 1 cm of loose soil on the face and the top
    h = wall + loose
    r = relax_two_angle(h, loose, tan(32), tan(70), DX, backend=backend)
    assert not r.capped.item()
    assert abs(r.h.sum().item() - h.sum().item()) < 1e-12
    assert abs(r.loose.sum().item() - loose.sum().item()) < 1e-12         # no intact ground failed
    assert torch.allclose(r.h - r.loose, wall, atol=1e-12)               # the intact wall is untouched
    assert (r.h >= wall - 1e-12).all()                                   # never below the intact surface
    assert r.loose[:, 16:23].max().item() < 1e-12                        # the face is bare again
    assert abs(r.loose[:, :16].sum().item() - loose[:, 14:23].sum().item()) < 1e-12   # its soil, at the toe
    assert torch.equal(r.loose[:, 23:], loose[:, 23:])                   # the flat top keeps its layer
    toe = slopes(r.h)[:, :13]
    assert toe.max().item() <= math.tan(math.radians(32)) + 2 * TAU     # heaped at the loose angle


def rough(B=2, X=14, Y=12, seed=1):
    g = torch.Generator().manual_seed(seed)
    h = 0.01 * torch.randn(B, X, Y, generator=g, dtype=torch.float64)
    h[:, 4:8, 3:7] += 0.04
    return h, torch.relu(0.02 * torch.randn(B, X, Y, generator=g, dtype=torch.float64))


@pytest.mark.parametrize("backend", BACKENDS)
def test_one_angle_is_the_single_angle_relaxation(backend):
    h, loose = rough()
    tb = torch.tensor([0.5, 0.8], dtype=torch.float64)
    a = relax_two_angle(h, loose, tb, tb, DX, backend=backend)
    b = relax(h, tb, DX, backend=backend)
    assert torch.allclose(a.h, b.h, atol=1e-15, rtol=0) and a.iterations.tolist() == b.iterations.tolist()


def test_backends_agree_values_and_gradients():
    h0, l0 = rough()
    domain = torch.ones(h0.shape[1:], dtype=torch.bool)
    domain[0] = False
    w = torch.sin(torch.arange(h0[0].numel(), dtype=torch.float64)).reshape(h0.shape[1:])
    out = {}
    for backend in BACKENDS:
        x = [t.clone().requires_grad_() for t in (h0, l0, torch.tensor([0.6, 0.7]).double(),
                                                 torch.tensor([1.5, 2.5]).double())]
        r = relax_two_angle(*x, DX, domain, backend=backend)
        ((r.h * w).sum() + 0.3 * (r.loose * w).sum()).backward()
        out[backend] = [r.h, r.loose, *(t.grad for t in x)]
        assert not r.capped.any() and (r.iterations > 5).all()
    for a, b in zip(out["torch"], out["numba"], strict=True):
        assert torch.allclose(a, b, atol=1e-12, rtol=1e-10)


@pytest.mark.parametrize("backend", BACKENDS)
def test_gradients_match_finite_differences(backend):
    g = torch.Generator().manual_seed(3)
    h = (0.02 * torch.randn(1, 6, 5, generator=g, dtype=torch.float64)).requires_grad_()
    loose = (0.002 + 0.01 * torch.rand(1, 6, 5, generator=g, dtype=torch.float64)).requires_grad_()
    tl, ti = tan(30).requires_grad_(), tan(50).requires_grad_()

    def f(h, loose, tl, ti):
        r = relax_two_angle(h, loose, tl, ti, DX, fixed_iter=6, backend=backend)
        return r.h, r.loose

    assert torch.autograd.gradcheck(f, (h, loose, tl, ti), eps=1e-7, atol=1e-6)


def test_batch_elements_do_not_interact():
    h, loose = rough(B=3, seed=5)
    tl, ti = torch.tensor([0.5, 0.6, 0.7]).double(), torch.tensor([1.0, 3.0, 0.7]).double()
    both = relax_two_angle(h, loose, tl, ti, DX)
    for b in range(3):
        one = relax_two_angle(h[b:b + 1], loose[b:b + 1], tl[b:b + 1], ti[b:b + 1], DX)
        assert torch.equal(one.h[0], both.h[b]) and one.iterations.item() == both.iterations[b].item()


def test_bad_input_is_refused():
    h = ramp(30)
    with pytest.raises(ValueError, match="loose thickness"):
        relax_two_angle(h, -torch.ones_like(h), tan(30), tan(60), DX)
    with pytest.raises(ValueError, match="tan\\(beta_loose\\) <= tan\\(beta_intact\\)"):
        relax_two_angle(h, torch.zeros_like(h), tan(60), tan(30), DX)
    with pytest.raises(ValueError, match="backend"):
        relax_two_angle(h, torch.zeros_like(h), tan(30), tan(60), DX, backend="cuda")
    with pytest.raises(ValueError, match="both be"):
        relax_two_angle(h, torch.zeros(1, 3, 3, dtype=h.dtype), tan(30), tan(60), DX)

