import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from torchsoil.sim.sinkage import contact_height, disc_offsets, reference_height, revisit_reference, taper


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


@pytest.mark.parametrize("radius_cells", [0.9, 1.5, 2.3, 3.5])
def test_reference_height_is_the_mean_of_the_cells_within_the_radius_that_exist(radius_cells):
    """Cell by cell with a plain loop: near the edge the mean is over the cells inside the map."""
    g = torch.Generator().manual_seed(3)
    h = torch.randn(2, 9, 7, dtype=torch.float64, generator=g)
    ref = reference_height(h, radius_cells * 0.02, 0.02)
    for x in range(9):
        for y in range(7):
            near = [(i, j) for i in range(9) for j in range(7) if (i - x) ** 2 + (j - y) ** 2 <= radius_cells ** 2]
            want = torch.stack([h[:, i, j] for i, j in near]).mean(0)
            assert torch.allclose(ref[:, x, y], want, atol=1e-12), (x, y)


def test_disc_offsets_symmetric():
    off = set(disc_offsets(1.75))
    assert (0, 0) in off and (1, 1) in off and (2, 0) not in off
    assert all((-i, -j) in off and (j, i) in off for i, j in off)


def trench(depth=0.03, half=1, shape=(9, 9)):
    """(1, X, Y) ground at 0 with a trench `depth` m deep along x, 2 half + 1 cells wide."""
    h = torch.zeros(1, *shape, dtype=torch.float64)
    c = shape[1] // 2
    h[:, :, c - half:c + half + 1] = -depth
    return h


def test_contact_height_spans_a_rut_narrower_than_the_footprint():
    """Footprint radius 2 cells (0.04 m at dx 0.02 m): 13 cells, 11 of them in a 3-cell trench,
    so a wheel over the trench rests 11/13 of its depth down; the paper's disc (half that
    radius, 5 cells, all in the trench) sits on its floor."""
    h = trench(0.03)
    assert float(contact_height(h, 0.04, 0.02)[0, 4, 4]) == pytest.approx(-0.03 * 11 / 13)
    assert float(reference_height(h, 0.02, 0.02)[0, 4, 4]) == pytest.approx(-0.03)


@given(a=st.floats(-1, 1), b=st.floats(-0.5, 0.5), c=st.floats(-0.5, 0.5))
@settings(max_examples=20, deadline=None)
def test_contact_height_of_a_plane_is_the_plane(a, b, c):
    """Away from the map edge, fresh planar ground: the wheel's contact is the surface itself."""
    i = torch.arange(12, dtype=torch.float64)[:, None]
    j = torch.arange(12, dtype=torch.float64)[None, :]
    h = (a + b * i * 0.02 + c * j * 0.02)[None]
    got = contact_height(h, 0.07, 0.02)
    torch.testing.assert_close(got[:, 4:8, 4:8], h[:, 4:8, 4:8])


def test_revisit_reference_changes_only_the_dug_cells():
    h = trench(0.03)
    fresh = reference_height(h, 0.02, 0.02)
    dug = torch.zeros(9, 9, dtype=torch.bool)
    dug[:, 3:6] = True
    got = revisit_reference(h, fresh, dug, "footprint", 0.5, 0.04, 0.02)
    assert float(got[0, 4, 4]) == pytest.approx(-0.03 * 11 / 13)
    torch.testing.assert_close(got[:, ~dug], fresh[:, ~dug])
    torch.testing.assert_close(revisit_reference(h, fresh, dug, "disc", 0.5, 0.04, 0.02), fresh)
    with pytest.raises(ValueError, match="footprint"):
        revisit_reference(h, fresh, dug, "floor", 0.5, 0.04, 0.02)
