"""Rasterization: mean, count, variance per cell; filling from neighbours; corridor."""

import numpy as np

from torchsoil.pipeline.raster import Accumulator, corridor


def test_plane_is_reproduced_and_holes_filled():
    grid, mask = corridor(np.array([[0.0, 0.0], [1.0, 0.0]]), 0.4, 0.02)
    assert mask.any() and not mask.all()
    cx, cy = grid.centers()
    X, Y = np.meshgrid(cx, cy, indexing="ij")
    plane = 0.3 * X - 0.2 * Y + 0.05
    hole = np.zeros(grid.shape, bool)
    hole[20, 5:8] = True  # a short gap with measured neighbours
    pts = np.stack([X[~hole], Y[~hole], plane[~hole]], 1)
    acc = Accumulator(grid, mask)
    acc.add(pts)
    hm = acc.heightmap(fill_radius=2)
    inside = mask & ~hole
    np.testing.assert_allclose(hm.h[inside], plane[inside], atol=1e-6)
    np.testing.assert_allclose(hm.h[20, 6], plane[20, 6], atol=1e-6)  # symmetric neighbours
    assert hm.valid[20, 5:8].all() and not hm.measured[20, 5:8].any()
    assert not hm.valid[~mask].any() and np.isnan(hm.h[~mask]).all()


def test_mean_count_variance_and_unfillable_cells():
    grid, mask = corridor(np.array([[0.0, 0.0], [2.0, 0.0]]), 1.0, 0.1)
    acc = Accumulator(grid, mask)
    i, j = 5, 5
    x, y = grid.origin[0] + i * grid.dx, grid.origin[1] + j * grid.dx
    acc.add(np.array([[x, y, 1.0], [x + 0.01, y, 3.0], [50.0, 50.0, 7.0]]))
    hm = acc.heightmap(fill_radius=1)
    assert hm.count[i, j] == 2 and hm.h[i, j] == 2.0 and hm.var[i, j] == 1.0
    assert hm.count.sum() == 2  # the far point is outside the corridor
    assert hm.valid[i + 1, j] and not hm.valid[i + 3, j]  # beyond the fill radius: NaN
    assert np.isnan(hm.h[i + 3, j])
