"""Incremental maps of the mapper: the local map and the reference map P_ref keep the oldest
point per voxel, `forget` drops exactly the far voxels, `reference` equals a brute-force
selection with normals computed over everything held, and the voxel-grid search equals a
KD-tree."""

import numpy as np
import pytest
from scipy.spatial import cKDTree

from torchsoil.pipeline import icp
from torchsoil.pipeline.mapping import LocalMap, ReferenceMap


def scene(rng, n=3000, x0=0.0):
    """Ground with a wall and a post, jittered (no ties between neighbour distances)."""
    ground = np.column_stack([rng.uniform(x0 - 8, x0 + 8, (n, 2)), rng.normal(0, 0.01, n)])
    wall = np.column_stack([np.full(n // 4, x0 + 5.0) + rng.normal(0, 0.01, n // 4),
                            rng.uniform(-4, 4, n // 4), rng.uniform(0, 2, n // 4)])
    a = rng.uniform(0, 2 * np.pi, n // 8)
    post = np.column_stack([x0 - 2 + 0.3 * np.cos(a), 3 + 0.3 * np.sin(a), rng.uniform(0, 2, n // 8)])
    return np.concatenate([ground, wall, post])


def brute_reference(points, views, center, radius, normal_radius):
    """What `reference` must return: the selection and normals over all held points."""
    sel = np.flatnonzero(np.hypot(points[:, 0] - center[0], points[:, 1] - center[1]) <= radius)
    n, _ = icp.pca_normals(points, cKDTree(points), points[sel], radius=normal_radius)
    return points[sel], icp.orient_to_viewpoints(points[sel], n, views[sel])


def test_oldest_point_kept_per_voxel():
    ref = ReferenceMap(voxel=1.0, normal_radius=0.6)   # voxels centred on whole metres
    ref.add(np.array([[0.1, 0.1, 0.1], [0.4, 0.4, 0.4], [1.0, 0.2, 0.2]]), np.array([0.0, 0, 0]))
    ref.add(np.array([[-0.3, 0.3, 0.3], [2.0, 0.2, 0.2], [2.1, 0.1, 0.1], [0.8, 0.1, 0.1]]), np.array([9.0, 0, 0]))
    pts, views = ref.global_map()
    np.testing.assert_array_equal(pts, [[0.1, 0.1, 0.1], [1.0, 0.2, 0.2], [2.0, 0.2, 0.2]])
    np.testing.assert_array_equal(views, [[0, 0, 0], [0, 0, 0], [9, 0, 0]])


def test_reference_map_equals_unique_over_all_sweeps():
    rng = np.random.default_rng(0)
    ref = ReferenceMap(voxel=0.2, normal_radius=0.6)
    sweeps = [(scene(rng, 1500, x0=k), np.array([k, 0.0, 1.0])) for k in range(5)]
    for pts, c in sweeps:
        ref.add(pts, c)
    allp = np.concatenate([p for p, _ in sweeps])
    allv = np.concatenate([np.broadcast_to(c, p.shape) for p, c in sweeps])
    _, first = np.unique(icp.voxel_keys(allp, 0.2), return_index=True)
    first = np.sort(first)
    pts, views = ref.global_map()
    np.testing.assert_array_equal(pts, allp[first])
    np.testing.assert_array_equal(views, allv[first])


def test_forget_drops_exactly_the_far_voxels():
    rng = np.random.default_rng(1)
    ref = ReferenceMap(voxel=0.2, normal_radius=0.6)
    ref.add(rng.uniform(-20, 20, (20000, 3)), np.zeros(3))
    before, _ = ref.global_map()
    keep_xy = np.array([[0.0, 0.0], [5.0, 5.0], [-8.0, 3.0]])
    dropped = ref.forget(keep_xy, 6.0)
    d = np.min(np.linalg.norm(before[:, None, :2] - keep_xy[None], axis=2), axis=1)
    after, _ = ref.global_map()
    np.testing.assert_array_equal(after, before[d <= 6.0])
    assert dropped == int((d > 6.0).sum()) > 0
    assert ref.forget(keep_xy, 6.0) == 0
    # a forgotten voxel can be filled again, a held one not
    ref.add(np.array([[15.05, 15.05, 0.05], np.round(after[0] / 0.2) * 0.2]), np.zeros(3))
    assert len(ref) == len(after) + 1
    # memory follows what is held
    assert ref.forget(np.array([[100.0, 100.0]]), 1.0) == len(after) + 1
    assert len(ref) == 0 and len(ref._buf["points"]) == 1024
    assert len(ref.reference(np.zeros(3), 5.0).points) == 0
    ref.add(np.zeros((0, 3)), np.zeros(3))
    ref.add(after, np.zeros(3))
    np.testing.assert_array_equal(ref.global_map()[0], after)


@pytest.mark.parametrize("radius", [3.0, 7.5, 50.0])
def test_reference_equals_brute_force_as_the_map_grows_and_forgets(radius):
    rng = np.random.default_rng(2)
    ref = ReferenceMap(voxel=0.2, normal_radius=0.6)
    for k in range(6):
        ref.add(scene(rng, 1500, x0=1.5 * k), np.array([1.5 * k, 0.0, 1.0]))
        if k == 3:
            ref.forget(np.array([[4.5, 0.0]]), 9.0)
        center = np.array([1.5 * k, 0.5, 0.0])
        target = ref.reference(center, radius)
        pts, views = ref.global_map()
        want_p, want_n = brute_reference(pts, views, center, radius, 0.6)
        np.testing.assert_array_equal(target.points, want_p)
        np.testing.assert_allclose(target.normals, want_n, atol=1e-9)
        d, i = target.tree.query(want_p[:50], distance_upper_bound=0.3)
        np.testing.assert_array_equal(i, np.arange(50))


def test_reference_normals_of_a_plane_are_its_normal():
    rng = np.random.default_rng(3)
    normal = np.array([0.1, -0.2, 1.0]) / np.linalg.norm([0.1, -0.2, 1.0])
    xy = rng.uniform(-5, 5, (4000, 2))
    z = -(normal[0] * xy[:, 0] + normal[1] * xy[:, 1]) / normal[2]
    ref = ReferenceMap(voxel=0.2, normal_radius=0.6)
    ref.add(np.column_stack([xy, z]), np.array([0.0, 0.0, 1.0]))
    target = ref.reference(np.zeros(3), 4.0)
    inner = np.hypot(target.points[:, 0], target.points[:, 1]) < 3.0
    np.testing.assert_allclose(target.normals[inner], np.broadcast_to(normal, (inner.sum(), 3)), atol=1e-9)


def test_local_map_equals_rebuilding_from_scratch():
    """The incremental local map holds what the former full re-voxelisation held."""
    rng = np.random.default_rng(4)
    local = LocalMap(0.2, 6.0, 0.6)
    held = np.zeros((0, 3))
    for k in range(6):
        pts, c = scene(rng, 1500, x0=2.0 * k), np.array([2.0 * k, 0.0, 0.0])
        local.add(pts, c)
        cat = np.concatenate([held, pts])
        _, first = np.unique(icp.voxel_keys(cat, 0.2), return_index=True)
        keep = np.sort(first)
        keep = keep[np.linalg.norm(cat[keep, :2] - c[:2], axis=1) < 6.0]
        held = cat[keep]
        np.testing.assert_array_equal(local.points, held)
        np.testing.assert_array_equal(local.target.points, held)
        new = local.age == 0
        n, good = icp.pca_normals(held, cKDTree(held), held[new], radius=0.6)
        np.testing.assert_allclose(np.abs(local.normals[new]), np.abs(n), atol=1e-9)
        np.testing.assert_array_equal(local.good[new], good)
    assert len(local.global_map()[0]) > len(local.points)
    local.add(np.zeros((0, 3)), np.array([100.0, 0.0, 0.0]))  # nothing near any more
    assert len(local.points) == 0 and len(local.target.points) == 0


@pytest.mark.parametrize("cell", [0.1, 0.3, 0.6])
def test_voxel_index_equals_kd_tree(cell):
    rng = np.random.default_rng(5)
    pts = np.concatenate([scene(rng, 2000), rng.uniform(-10, 10, (500, 3))])
    q = np.concatenate([pts[::2] + rng.normal(0, 0.1, (len(pts[::2]), 3)), rng.uniform(-12, 12, (300, 3))])
    index, tree = icp.VoxelIndex(pts, cell), cKDTree(pts)
    for k, bound in ((1, 0.3), (1, 0.5), (1, 1.5), (1, np.inf), (12, 0.6), (3, 0.25)):
        dt, it = tree.query(q, k=k, distance_upper_bound=bound)
        for workers in (1, 2):
            d, i = index.query(q, k=k, distance_upper_bound=bound, workers=workers)
            np.testing.assert_array_equal(i, it)
            np.testing.assert_allclose(d, dt, rtol=1e-12)
    d, i = index.query(q[0], distance_upper_bound=0.5)
    assert np.ndim(d) == 0 and i == tree.query(q[0], distance_upper_bound=0.5)[1]
    d, i = icp.VoxelIndex(np.zeros((0, 3))).query(q, distance_upper_bound=0.5)
    assert np.isinf(d).all() and (i == 0).all()


def test_voxel_grouping_equals_unique():
    rng = np.random.default_rng(6)
    pts = rng.uniform(-3, 3, (5000, 3))
    keys = icp.voxel_keys(pts, 0.25)
    k = np.floor(pts / 0.25 + 0.5).astype(np.int64) + (1 << 20)   # centred on multiples
    np.testing.assert_array_equal(keys, k[:, 0] + (k[:, 1] << 21) + (k[:, 2] << 42))
    _, first, inv, cnt = np.unique(keys, return_index=True, return_inverse=True, return_counts=True)
    np.testing.assert_array_equal(icp.voxel_first(pts, 0.25), first)
    want = np.stack([np.bincount(inv, weights=pts[:, i]) for i in range(3)], 1) / cnt[:, None]
    np.testing.assert_allclose(icp.voxel_downsample(pts, 0.25), want, rtol=1e-12, atol=1e-12)


def test_reference_normals_are_cached_until_their_neighbourhood_changes():
    rng = np.random.default_rng(7)
    ref = ReferenceMap(voxel=0.2, normal_radius=0.6)
    ref.add(scene(rng, 3000), np.array([0.0, 0.0, 1.0]))
    ref.reference(np.zeros(3), 6.0)
    first = ref.stamp.copy()
    ref.reference(np.zeros(3), 6.0)
    np.testing.assert_array_equal(ref.stamp, first)  # nothing recomputed
    patch = np.column_stack([rng.uniform(2.0, 2.4, (50, 2)), rng.normal(0.3, 0.01, 50)])
    ref.add(patch, np.array([0.0, 0.0, 1.0]))
    ref.reference(np.zeros(3), 6.0)
    old = np.arange(len(first))
    redone = ref.stamp[old] != first
    near = np.min(np.linalg.norm(ref.points[old, None] - ref.points[len(first):][None], axis=2), axis=1) < 0.6
    np.testing.assert_array_equal(redone[first >= 0], near[first >= 0])
