"""Re-registration: each front and each back sweep alone onto the sparse reference map
P_ref, seeded by T_ref at the sweep's time (paper section III).

Both streams then live in the one frame the mapper built, so an error P_ref carries is
common to H_f and H_b and cancels in H_delta. A sweep whose registration fails (too few
matches, large residual, or a correction far from the seed) is flagged and dropped rather
than allowed to pollute a heightmap; in directions the scene leaves unconstrained the seed
is kept.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from torchsoil.pipeline import _kernels as _k
from torchsoil.pipeline import icp
from torchsoil.pipeline.deskew import deskew
from torchsoil.settings import ReregisterConfig


def interpolate_poses(stamps: np.ndarray, poses: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(S,) times [s] and (S, 4, 4) poses -> (Q, 4, 4) poses at times t (Q,), linear in
    position, slerp in rotation, held constant beyond the ends. Only the bracketing poses
    of each time are touched (as scipy's Slerp, without converting all S rotations)."""
    t = np.clip(np.asarray(t, dtype=np.float64), stamps[0], stamps[-1])
    out = np.repeat(np.eye(4)[None], len(t), axis=0)
    if len(stamps) == 1:
        out[:] = poses[0]
        return out
    for i in range(3):
        out[:, i, 3] = np.interp(t, stamps, poses[:, i, 3])
    i = np.clip(np.searchsorted(stamps, t, side="right") - 1, 0, len(stamps) - 2)
    alpha = (t - stamps[i]) / (stamps[i + 1] - stamps[i])
    if len(t) <= 4:  # a seed or a motion: skip the vectorised rotation machinery
        for q in range(len(t)):
            R0, R1 = poses[i[q], :3, :3], poses[i[q] + 1, :3, :3]
            step = _k.rotvec_of(np.ascontiguousarray(R0.T @ R1))
            out[q, :3, :3] = R0 @ _k.rotation(step * alpha[q])
        return out
    R0 = Rotation.from_matrix(poses[i, :3, :3])
    step = (R0.inv() * Rotation.from_matrix(poses[i + 1, :3, :3])).as_rotvec()
    out[:, :3, :3] = (R0 * Rotation.from_rotvec(step * alpha[:, None])).as_matrix()
    return out


def motion_at(stamps: np.ndarray, poses: np.ndarray, t: float, dt: float) -> np.ndarray:
    """(4, 4) motion of the robot frame over [t, t + dt] along the trajectory."""
    a, b = interpolate_poses(stamps, poses, np.array([t, t + dt]))
    if t + dt > stamps[-1]:  # extrapolate at the end with the last interval
        a, b = interpolate_poses(stamps, poses, np.array([stamps[-1] - dt, stamps[-1]]))
    return np.linalg.inv(a) @ b


def register_sweep(points: np.ndarray, t: np.ndarray, stamp: float, ref_stamps: np.ndarray,
                   ref_poses: np.ndarray, target: icp.Target, cfg: ReregisterConfig,
                   period: float = 0.1) -> tuple[np.ndarray, np.ndarray, float, float, bool, bool]:
    """One sweep in base_link (points (N, 3) m, times t (N,) s after `stamp`) onto `target`.

    Returns (de-skewed points (N, 3) in base_link at `stamp`, pose (4, 4), fitness, rmse,
    accepted, degenerate).
    """
    seed = interpolate_poses(ref_stamps, ref_poses, np.array([stamp]))[0]
    pts = deskew(points, t, motion_at(ref_stamps, ref_poses, stamp, period), period)
    if not cfg.enabled:
        return pts, seed, np.nan, np.nan, True, False
    near = pts[_k.within_range(pts, float(cfg.max_range))]
    src = icp.thin(icp.voxel_downsample(near, cfg.voxel), cfg.max_points, cfg.voxel)
    if len(src) < 50:
        return pts, seed, 0.0, np.inf, False, False
    res = icp.register(src, target, seed, cfg.max_dist, cfg.max_iter, one_sided=cfg.one_sided)
    weak = icp.weak_directions(res.hessian, cfg.degenerate_eigen)
    T = icp.project_update(seed, res.transform, weak)
    D = np.linalg.inv(seed) @ T
    shift = np.linalg.norm(D[:3, 3])
    turn = np.degrees(np.linalg.norm(_k.rotvec_of(np.ascontiguousarray(D[:3, :3]))))
    ok = (res.fitness >= cfg.min_fitness and res.rmse <= cfg.max_rmse
          and shift <= cfg.max_shift and turn <= cfg.max_turn)
    return pts, T, res.fitness, res.rmse, bool(ok), bool(weak.shape[1])
