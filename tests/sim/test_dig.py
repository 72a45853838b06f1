"""The fused numba dig (sink + deposit) against the torch ops it replaces: the same surfaces,
volumes and gradients, ties of the min included (torch's conventions)."""

import pytest
import torch

from torchsoil.sim.dig import dig

pytest.importorskip("numba")


def _case(B=3, X=9, Y=11, E=160, n_bins=12, seed=0, batched=False, ties=True, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    nb = B if batched else 1
    h = torch.rand(nb, X, Y, generator=g, dtype=dtype) * 0.02
    h_ref = torch.rand(nb, X, Y, generator=g, dtype=dtype) * 0.02
    cell = torch.randint(0, X * Y, (E,), generator=g)
    covered = torch.rand(nb, E, generator=g) < 0.5
    s = torch.rand(nb, E, generator=g, dtype=dtype)
    if ties:   # flat taper: entries of one wheel digging the same cell reach the same floor
        s = torch.where(torch.rand(nb, E, generator=g) < 0.5, torch.ones_like(s), s)
        cell[E // 2:] = cell[:E - E // 2]
        h_ref[..., 0, :] = h[..., 0, :] - 0.01        # h equal to the floor there: min(h, floor) tied
    depth = (torch.rand(B, E, generator=g, dtype=dtype) * 0.03)
    if ties:
        depth[:, 1::2] = 0.01
    owner = covered & (torch.rand(nb, E, generator=g) < 0.7)
    band = ~covered & (torch.rand(nb, E, generator=g) < 0.6)
    bins = torch.randint(0, n_bins, (E,), generator=g)
    bins[bins == n_bins - 1] = n_bins - 2                  # a bin without any entry
    band[:, bins == 3] = False                            # a bin whose soil is lost
    chi = torch.rand(B, generator=g, dtype=dtype)
    chi[0] = 0.0
    return h, h_ref, cell, covered, s, depth, owner, band, bins, n_bins, chi


@pytest.mark.parametrize("batched", [False, True])
@pytest.mark.parametrize("B", [1, 3])
def test_numba_dig_equals_the_torch_ops(batched, B):
    args = _case(B=B, batched=batched)
    h, h_ref, cell, covered, s, depth, owner, band, bins, n_bins, chi = args
    leaves = [t.clone().requires_grad_(True) for t in (h, h_ref, s, depth, chi)]
    outs = {}
    for backend in ("torch", "numba"):
        lv = [t.detach().clone().requires_grad_(True) for t in leaves]
        hh, hr, ss, dd, cc = lv
        pre, removed, added, lost = dig(hh, hr, cell, covered, ss, dd, owner, band, bins, n_bins, cc, backend)
        w = torch.linspace(-1, 2, pre.numel(), dtype=pre.dtype).reshape(pre.shape)
        loss = (w * pre).sum() + 0.3 * (w.flip(-1) * removed).sum() - 0.7 * added.sum() + 2.0 * lost.sum()
        loss.backward()
        outs[backend] = (pre, removed, added, lost, *(t.grad for t in lv))
    names = ("h_pre", "removed", "added", "lost", "dh", "dh_ref", "ds", "ddepth", "dchi")
    for name, a, b in zip(names, outs["torch"], outs["numba"], strict=True):
        assert a.shape == b.shape, name
        assert torch.allclose(a, b, rtol=1e-12, atol=1e-15), (name, (a - b).abs().max())
    assert torch.equal(outs["torch"][0], outs["numba"][0])           # the surface, to the bit
    assert (outs["torch"][3] > 0).any()                              # the lost bin was exercised


def test_numba_dig_float32_and_no_grad():
    args = list(_case(B=2, dtype=torch.float32))
    with torch.no_grad():
        a = dig(*args, backend="torch")
        b = dig(*args, backend="numba")
    for x, y in zip(a, b, strict=True):
        assert x.dtype == y.dtype == torch.float32
        assert torch.equal(x, y)


def test_unknown_backend_is_refused():
    with pytest.raises(ValueError, match="dig backend"):
        dig(*_case(B=1), backend="cuda-magic")


def test_numba_dig_gradients_of_the_parameters_alone():
    """As the estimator calls it: only depth and chi require gradients."""
    h, h_ref, cell, covered, s, depth, owner, band, bins, n_bins, chi = _case(B=2)
    grads = []
    for backend in ("torch", "numba"):
        d, c = depth.clone().requires_grad_(True), chi.clone().requires_grad_(True)
        pre = dig(h, h_ref, cell, covered, s, d, owner, band, bins, n_bins, c, backend)[0]
        grads.append(torch.autograd.grad((pre * pre).sum(), (d, c)))
    for a, b in zip(*grads, strict=True):
        assert torch.allclose(a, b, rtol=1e-12, atol=1e-15)
        assert a.abs().sum() > 0
