"""ICP: recovers a known transform on a structured scene, and names weak directions."""

import numpy as np
from scipy.spatial.transform import Rotation

from torchsoil.pipeline import icp


def scene(rng, landmarks=True):
    ground = np.column_stack([rng.uniform(-10, 10, (4000, 2)), rng.normal(0, 1e-4, 4000)])
    parts = [ground]
    if landmarks:
        wall = np.column_stack([np.full(800, 6.0), rng.uniform(-5, 5, 800), rng.uniform(0, 3, 800)])
        a = rng.uniform(0, 2 * np.pi, 600)
        pole = np.column_stack([-3 + 0.2 * np.cos(a), 4 + 0.2 * np.sin(a), rng.uniform(0, 3, 600)])
        side = np.column_stack([rng.uniform(-5, 5, 800), np.full(800, -7.0), rng.uniform(0, 3, 800)])
        parts += [wall, pole, side]
    return np.concatenate(parts)


def transform(rotvec, t):
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    T[:3, 3] = t
    return T


def test_recovers_known_transform():
    rng = np.random.default_rng(0)
    pts = scene(rng)
    target = icp.make_target(icp.voxel_downsample(pts, 0.1), 0.6)
    truth = transform([0.0, 0.01, 0.03], [0.15, -0.1, 0.02])
    source = icp.apply(np.linalg.inv(truth), pts[::3])
    res = icp.register(source, target, np.eye(4), max_dist=0.5)
    np.testing.assert_allclose(res.transform[:3, 3], truth[:3, 3], atol=5e-3)
    dR = Rotation.from_matrix(res.transform[:3, :3].T @ truth[:3, :3]).magnitude()
    assert dR < np.deg2rad(0.05)
    assert res.fitness > 0.95
    assert icp.weak_directions(res.hessian, 2e-3).shape[1] == 0


def test_flat_ground_is_degenerate_and_prediction_kept():
    rng = np.random.default_rng(1)
    pts = scene(rng, landmarks=False)
    target = icp.make_target(pts, 0.6)
    pred = transform([0, 0, 0.02], [0.3, 0.1, 0.0])
    res = icp.register(pts[::4], target, pred, max_dist=0.5)
    weak = icp.weak_directions(res.hessian, 2e-3)
    assert weak.shape[1] == 3  # x, y and yaw are free on a plane
    free = np.abs(weak).sum(1)
    assert free[[2, 3, 4]].min() > 0.5 and free[[0, 1, 5]].max() < 1e-3
    T = icp.project_update(pred, res.transform, weak)
    np.testing.assert_allclose(T[:2, 3], pred[:2, 3], atol=1e-6)


def test_voxel_downsample_is_centroid_per_voxel():
    pts = np.array([[0.01, 0.01, 0.01], [0.03, 0.04, -0.04], [1.03, 0.0, 0.0], [1.07, 0.0, 0.0]])
    out = icp.voxel_downsample(pts, 0.1)   # voxels centred on multiples of 0.1: [-0.05, 0.05), ...
    assert len(out) == 3
    np.testing.assert_allclose(sorted(out[:, 0]), [0.02, 1.03, 1.07])


def test_points_on_the_origin_planes_do_not_straddle_voxels():
    """A lidar column at azimuth zero on the robot's symmetry plane gives points with y = 0
    exactly; a nanometre either way must not move them to another voxel."""
    p = np.array([[4.78, 0.0, -0.008], [4.78, 1e-9, -0.008], [4.78, -1e-9, -0.008]])
    assert len(set(icp.voxel_keys(p, 0.2).tolist())) == 1
    assert len(set(icp.voxel_keys(p.astype(np.float32), 0.2).tolist())) == 1


def test_thinning_is_stable_when_one_voxel_comes_or_goes():
    """Taking every k-th voxel, one more voxel shifts every pick after it; the hashed pick
    changes at most one besides the voxel itself."""
    rng = np.random.default_rng(0)
    vox = icp.voxel_downsample(rng.uniform(-20, 20, (20000, 3)), 0.2)
    a = icp.thin(vox, 3000, 0.2)
    b = icp.thin(np.delete(vox, len(vox) // 3, axis=0), 3000, 0.2)
    assert len(a) == len(b) == 3000
    common = {tuple(p) for p in a} & {tuple(p) for p in b}
    assert len(common) >= 2998
    assert len(icp.thin(vox[:100], 3000, 0.2)) == 100
    evenly = vox[np.linspace(0, len(vox) - 1, 3000).astype(np.int64)]   # the old way, for contrast
    shifted = np.delete(vox, len(vox) // 3, axis=0)
    old_b = shifted[np.linspace(0, len(shifted) - 1, 3000).astype(np.int64)]
    assert len({tuple(p) for p in evenly} & {tuple(p) for p in old_b}) < 2500


def test_far_face_seen_after_passing_does_not_pull_the_fit_back():
    """A 0.2 m slab entered the map from its near face (seen from x = -5); from x = +5 its far
    face is what the sensor sees. Matched to the near face it drags the sweep back along x;
    with viewpoint-oriented normals and `one_sided` only the walls that face the sensor count."""
    rng = np.random.default_rng(1)
    ground = np.column_stack([rng.uniform(-10, 10, (3000, 2)), np.zeros(3000)])
    near_face = np.column_stack([np.zeros(600), rng.uniform(-2, 2, 600), rng.uniform(0, 2, 600)])
    far_face = near_face + [0.2, 0.0, 0.0]
    wall_x = np.column_stack([np.full(800, 9.0), rng.uniform(-5, 5, 800), rng.uniform(0, 3, 800)])
    wall_y = np.column_stack([rng.uniform(-5, 10, 800), np.full(800, 6.0), rng.uniform(0, 3, 800)])
    mapped = np.concatenate([ground, near_face, wall_x, wall_y])
    views = np.where(np.arange(len(mapped))[:, None] < len(ground) + len(near_face), [-5.0, 0, 1], [5.0, 0, 1])
    n = icp.orient_to_viewpoints(mapped, icp.estimate_normals(mapped, 0.6), views)
    target = icp.make_target(mapped, 0.6, n)
    robot = transform([0, 0, 0], [5.0, 0, 0])
    source = icp.apply(np.linalg.inv(robot), np.concatenate([ground[::2], far_face, wall_x[::2], wall_y[::2]]))
    shift = {}
    for one_sided in (False, True):
        res = icp.register(source, target, robot, max_dist=0.5, ground_z=0.97, one_sided=one_sided)
        shift[one_sided] = res.transform[0, 3] - robot[0, 3]
    assert shift[False] < -0.02          # pulled back towards the near face
    assert abs(shift[True]) < 2e-3


def test_facing_keeps_ground_and_structure_seen_from_the_sensor():
    p = np.array([[1.0, 0, 0], [1.0, 0, 0], [3.0, 0, 1]])   # ground above the sensor: kept anyway
    n = np.array([[-1.0, 0, 0], [1.0, 0, 0], [0.0, 0, 1]])
    np.testing.assert_array_equal(icp.facing(p, n, np.zeros(3)), [True, False, True])


def test_nearest_tracker_answers_as_a_fresh_search_while_the_queries_move():
    rng = np.random.default_rng(3)
    index = icp.VoxelIndex(icp.voxel_downsample(scene(rng), 0.2), 0.6)    # a map: one point per voxel
    q = scene(rng)[::7] + rng.normal(0, 0.05, (1, 3))
    tracker = index.tracker(len(q), 0.3)
    for step in range(8):   # small moves (an ICP's updates), then a jump
        T = transform([0, 0, 0.0005 * step], [0.002 * step, -0.001 * step, 0.001]) if step < 7 else transform(
            [0, 0, 0.3], [0.5, 0.2, 0.0])
        p = icp.apply(T, q)
        np.testing.assert_array_equal(tracker.query(p), index.query(p, distance_upper_bound=0.3)[1])
        if step == 6:
            assert tracker.searched < 1.5 * len(q)    # most answers were kept while the moves were small
    assert index.tracker(len(q), 3.0) is None   # beyond the grid's reach: plain queries
