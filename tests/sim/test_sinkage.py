import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from torchsoil.sim.sinkage import disc_offsets, reference_height, taper


@pytest.mark.parametrize("f", [0.0, 0.3, 0.9])
def test_taper_shape(f):
    q = torch.linspace(-1.2, 1.2, 241, dtype=torch.float64)
    s = taper(q, f)
    assert s.min() >= 0 and s.max() <= 1
    assert torch.all(s[q.abs() <= f] == 1)
    assert torch.all(s[q.abs() >= 1] == 0)
    assert torch.allclose(s, taper(-q, f))  # symmetric across the wheel
    half = s[q >= 0]
    assert torch.all(half[1:] <= half[:-1] + 1e-15)  # non-increasing outward


@settings(max_examples=20, deadline=None)
@given(a=st.floats(-0.3, 0.3), b=st.floats(-0.3, 0.3), c=st.floats(-1, 1),
       radius=st.floats(0.01, 0.07), dx=st.sampled_from([0.015, 0.02, 0.05]))
def test_reference_height_of_plane_is_plane(a, b, c, radius, dx):
    x = torch.arange(20, dtype=torch.float64)[:, None] * dx
    y = torch.arange(17, dtype=torch.float64)[None] * dx
    h = (a * x + b * y + c)[None]
    r = math.ceil(radius / dx)
    ref = reference_height(h, radius, dx)
    inner = (slice(None), slice(r, 20 - r), slice(r, 17 - r))
    assert torch.allclose(ref[inner], h[inner], atol=1e-12)  # symmetric disc: the mean is the centre


def test_disc_offsets_symmetric():
    off = set(disc_offsets(1.75))
    assert (0, 0) in off and (1, 1) in off and (2, 0) not in off
    assert all((-i, -j) in off and (j, i) in off for i, j in off)
