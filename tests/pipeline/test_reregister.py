"""Re-registration: a sweep seeded by a wrong pose lands on the reference map, and a
sweep that does not fit is refused."""

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from tests.pipeline.toyscene import ToyScene
from torchsoil.pipeline import icp
from torchsoil.pipeline.reregister import interpolate_poses, register_sweep
from torchsoil.settings import ReregisterConfig


def reference(scene, stamps, rng):
    """P_ref from true poses (no motion distortion: the robot is slow here, so every point is
    seen from about where it is at the middle of the stamps)."""
    pts = []
    for t in stamps:
        for sensor in ("lidar_front", "lidar_back"):
            xyz, _ = scene.sweep(sensor, t, rng)
            xyz = xyz[np.isfinite(xyz).all(1)]
            pts.append(icp.apply(scene.pose(t) @ scene.extrinsics[sensor], xyz))
    ref = icp.voxel_downsample(np.concatenate(pts), 0.1)
    tree = cKDTree(ref)
    view = scene.pose(np.array([stamps.mean()]))[0, :3, 3]
    normals = icp.orient_to_viewpoints(ref, icp.pca_normals(ref, tree, ref)[0], np.broadcast_to(view, ref.shape))
    return icp.Target(ref, normals, tree)


def test_wrong_seed_is_corrected_and_bad_fit_refused():
    scene = ToyScene(speed=0.01, columns=256)
    rng = np.random.default_rng(0)
    stamps = np.arange(0.0, 1.0, 0.1)
    target = reference(scene, stamps, rng)
    true = scene.pose(stamps)
    wrong = true.copy()
    wrong[:, :3, 3] += (0.04, -0.03, 0.02)  # T_ref off by 5 cm and 0.3 degrees
    wrong[:, :3, :3] = Rotation.from_euler("xyz", (0.003, -0.004, 0.005)).as_matrix() @ \
        wrong[:, :3, :3]
    xyz, tns = scene.sweep("lidar_back", 0.5, rng)
    ok = np.isfinite(xyz).all(1)
    base = icp.apply(scene.extrinsics["lidar_back"], xyz[ok].astype(np.float64))
    cfg = ReregisterConfig()
    _, T, fit, rmse, accepted, degenerate = register_sweep(
        base, tns[ok] * 1e-9, 0.5, stamps, wrong, target, cfg)
    truth = scene.pose(0.5)
    assert accepted and not degenerate and fit > 0.8
    assert np.linalg.norm(T[:3, 3] - truth[:3, 3]) < 0.005
    assert Rotation.from_matrix(T[:3, :3].T @ truth[:3, :3]).magnitude() < np.deg2rad(0.03)
    # re-registration off: the seed (T_ref at that time) is used as it is
    cfg = cfg.replace(enabled=False)
    _, T_off, *_ = register_sweep(base, tns[ok] * 1e-9, 0.5, stamps, wrong, target, cfg)
    np.testing.assert_allclose(T_off, interpolate_poses(stamps, wrong, np.array([0.5]))[0])
    # a seed beyond the accepted correction is refused rather than used
    cfg = ReregisterConfig(max_shift=0.01)
    *_, accepted, _ = register_sweep(base, tns[ok] * 1e-9, 0.5, stamps, wrong, target, cfg)
    assert not accepted


def test_interpolation_between_and_beyond_poses():
    P = np.repeat(np.eye(4)[None], 2, 0)
    P[1, :3, 3] = (1.0, 0.0, 0.0)
    P[1, :3, :3] = Rotation.from_euler("z", 0.2).as_matrix()
    out = interpolate_poses(np.array([0.0, 1.0]), P, np.array([0.5, 2.0]))
    np.testing.assert_allclose(out[0, :3, 3], (0.5, 0, 0))
    assert np.isclose(Rotation.from_matrix(out[0, :3, :3]).as_euler("xyz")[2], 0.1)
    np.testing.assert_allclose(out[1], P[1])
