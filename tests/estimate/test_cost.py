import math

import numpy as np
import pytest
import torch
from scipy import ndimage

from torchsoil.estimate.cost import raster_blur, weighted_l1


def test_weighted_l1_by_hand():
    h = torch.tensor([[[0.0, 1.0], [2.0, 3.0]]])
    target = torch.zeros(2, 2)
    weight = torch.tensor([[1.0, 0.0], [1.0, 1.0]])
    assert float(weighted_l1(h, target, weight)[0]) == pytest.approx((0 + 2 + 3) / 3)


@pytest.mark.parametrize("sigma", [1.0, 2.0])
def test_raster_blur_is_scipys_gaussian(sigma):
    """The same kernel as scipy.ndimage.gaussian_filter (edge cells repeated, cut at 3 sigma)."""
    rng = np.random.default_rng(0)
    h = rng.normal(0.0, 0.01, (2, 23, 31))
    ours = raster_blur(torch.as_tensor(h), sigma).numpy()
    for b in range(2):
        ref = ndimage.gaussian_filter(h[b], sigma, mode="nearest", truncate=3.0)
        np.testing.assert_allclose(ours[b], ref, atol=1e-12)


def test_raster_blur_by_hand():
    """A unit spike spreads as the Gaussian's weights, which sum to one; a plane stays a plane."""
    h = torch.zeros(15, 15, dtype=torch.float64)
    h[7, 7] = 1.0
    out = raster_blur(h, 1.0)
    w = np.exp(-0.5 * np.arange(-3, 4) ** 2)
    w /= w.sum()
    assert float(out[7, 7]) == pytest.approx(w[3] ** 2)
    assert float(out[7, 8]) == pytest.approx(w[3] * w[4])
    assert float(out[5, 9]) == pytest.approx(w[1] * w[5])
    assert float(out.sum()) == pytest.approx(1.0)
    assert float(out[0, 0]) == 0.0 and float(out[7, 11]) == 0.0          # cut at 3 sigma
    x, y = torch.meshgrid(torch.arange(15.0), torch.arange(9.0), indexing="ij")
    plane = (0.01 * x - 0.02 * y).double()
    inner = (slice(3, -3), slice(3, -3))
    assert torch.allclose(raster_blur(plane, 1.0)[inner], plane[inner], atol=1e-9)
    assert raster_blur(plane, 0.0) is plane


def test_raster_blur_gradient_against_finite_differences():
    h = torch.randn(1, 9, 8, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda t: raster_blur(t, 0.8), (h,))
    assert math.isfinite(float(raster_blur(h, 0.8).detach().sum()))
