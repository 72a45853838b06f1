"""Rasterization: mean, count, variance per cell; filling from neighbours; corridor; tiles that
spill to disk and come back exactly."""

import numpy as np

from torchsoil.pipeline.raster import Tiles, corridor


def test_plane_is_reproduced_and_holes_filled():
    grid, mask = corridor(np.array([[0.0, 0.0], [1.0, 0.0]]), 0.4, 0.02)
    assert mask.any() and not mask.all()
    cx, cy = grid.centers()
    X, Y = np.meshgrid(cx, cy, indexing="ij")
    plane = 0.3 * X - 0.2 * Y + 0.05
    hole = np.zeros(grid.shape, bool)
    hole[20, 5:8] = True  # a short gap with measured neighbours
    pts = np.stack([X[~hole], Y[~hole], plane[~hole]], 1)
    tiles = Tiles(grid.dx, size=16)
    tiles.add(pts)
    hm = tiles.heightmap(grid, mask, fill_radius=2)
    inside = mask & ~hole
    np.testing.assert_allclose(hm.h[inside], plane[inside], atol=1e-6)
    np.testing.assert_allclose(hm.h[20, 6], plane[20, 6], atol=1e-6)  # symmetric neighbours
    assert hm.valid[20, 5:8].all() and not hm.measured[20, 5:8].any()
    assert not hm.valid[~mask].any() and np.isnan(hm.h[~mask]).all()


def test_mean_count_variance_and_unfillable_cells():
    grid, mask = corridor(np.array([[0.0, 0.0], [2.0, 0.0]]), 1.0, 0.1)
    tiles = Tiles(grid.dx)
    i, j = 5, 5
    x, y = grid.origin[0] + i * grid.dx, grid.origin[1] + j * grid.dx
    tiles.add(np.array([[x, y, 1.0], [x + 0.01, y, 3.0], [50.0, 50.0, 7.0]]))
    hm = tiles.heightmap(grid, mask, fill_radius=1)
    assert hm.count[i, j] == 2 and hm.h[i, j] == 2.0 and hm.var[i, j] == 1.0
    assert hm.count.sum() == 2  # the far point is outside the corridor
    assert hm.valid[i + 1, j] and not hm.valid[i + 3, j]  # beyond the fill radius: NaN
    assert np.isnan(hm.h[i + 3, j])


def test_tiles_hold_every_cell_on_the_lattice_across_tile_edges_and_signs():
    """Points on both sides of zero and across tile edges land in cell round(x / dx): the sums
    over a region equal a direct count made by hand."""
    rng = np.random.default_rng(0)
    dx = 0.05
    pts = np.column_stack([rng.uniform(-3, 3, (5000, 2)), rng.normal(0, 1, 5000)])
    tiles = Tiles(dx, size=8)
    tiles.add(pts[:2500])
    tiles.add(pts[2500:])
    count, total, sumsq = tiles.region(-70, 70, -65, 75)
    ij = np.round(pts[:, :2] / dx).astype(int) - [-70, -65]
    direct = np.zeros((140, 140))
    np.add.at(direct, (ij[:, 0], ij[:, 1]), 1)
    np.testing.assert_array_equal(count, direct)
    np.add.at(direct, (ij[:, 0], ij[:, 1]), pts[:, 2] - 1)   # now the sum of z
    np.testing.assert_allclose(total, direct, atol=1e-9)
    assert np.isclose(sumsq.sum(), np.sum(pts[:, 2] ** 2))


def test_tiles_spilled_to_disk_come_back_exactly(tmp_path):
    """Tiles far from the robot go to disk, the rest stay; points falling in a spilled tile
    again reload it, and every sum is what it would have been in memory."""
    rng = np.random.default_rng(1)
    a = np.column_stack([rng.uniform(0, 2, (3000, 1)), rng.uniform(-1, 1, (3000, 1)), rng.normal(0, 1, 3000)])
    b = a + [30.0, 0.0, 0.0]
    kept, spilled = Tiles(0.02, size=32), Tiles(0.02, size=32, spill_dir=str(tmp_path))
    for t in (kept, spilled):
        t.add(a)
        t.add(b)
    n = spilled.spill(np.array([[31.0, 0.0]]), radius=5.0)
    assert n > 0 and spilled.spilled and all(k[0] * 32 * 0.02 > 20 for k in spilled.tiles)
    assert spilled.memory() < kept.memory()
    spilled.add(a[:100])           # the robot comes back: the spilled tiles reload
    kept.add(a[:100])
    for r in ((-5, 110, -55, 55), (1490, 1610, -55, 55)):
        for x, y in zip(kept.region(*r), spilled.region(*r), strict=True):
            np.testing.assert_array_equal(x, y)


def test_a_heightmap_made_a_block_of_rows_at_a_time_is_the_one_made_whole(tmp_path):
    """Rows 7 at a time (fill radius 3: blocks read 3 rows either side) against one block: the
    same heights, counts, variances and fills, holes across block edges included."""
    grid, mask = corridor(np.array([[0.0, 0.0], [1.5, 0.3]]), 0.6, 0.02)
    cx, cy = grid.centers()
    X, Y = np.meshgrid(cx, cy, indexing="ij")
    rng = np.random.default_rng(1)
    keep = rng.uniform(size=X.shape) > 0.3          # 30 % holes, filled from up to 3 cells away
    z = 0.1 * np.sin(5 * X) + 0.05 * Y + rng.normal(0, 0.003, X.shape)
    tiles = Tiles(grid.dx, size=16, spill_dir=str(tmp_path))
    tiles.add(np.stack([X[keep], Y[keep], z[keep]], 1))
    tiles.spill(np.zeros((1, 2)), -np.inf)
    whole = tiles.heightmap(grid, mask, fill_radius=3, rows=10 ** 6)
    blocks = tiles.heightmap(grid, mask, fill_radius=3, rows=7)
    assert grid.shape[0] > 7 * 5 and (whole.valid & ~whole.measured).sum() > 100
    for a, b in zip(whole, blocks, strict=True):
        np.testing.assert_array_equal(a, b)
