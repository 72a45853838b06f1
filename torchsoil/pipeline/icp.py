"""Point-to-plane ICP onto a fixed target with a prebuilt KD-tree, and surface normals.

Shared by the mapper and the re-registration: the target (a local or the global map)
keeps one `Target` (points, normals, KD-tree) across many registrations, which a
per-call library ICP would rebuild every time. Normals come from Open3D.

The update is parametrised about the current sensor position c: a point p moves to
c + R(w) (p - c) + v with w, v (3,) each, so the 6 x 6 normal matrix separates rotation
about the robot from translation, and its weak eigenvectors name the directions the
scene does not constrain (a flat field: x, y and yaw).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation


class Target(NamedTuple):
    """Registration target: points (M, 3) [m], unit normals (M, 3), KD-tree over points."""

    points: np.ndarray
    normals: np.ndarray
    tree: cKDTree


class IcpResult(NamedTuple):
    """transform: (4, 4) source-to-target pose; fitness: share of source points with a
    correspondence within the final distance; rmse: robust point-to-plane RMS over those,
    m; hessian: (6, 6) normal matrix per correspondence at the final pose, ordered
    (rotation x, y, z, translation x, y, z); n_corr: correspondences; iterations."""

    transform: np.ndarray
    fitness: float
    rmse: float
    hessian: np.ndarray
    n_corr: int
    iterations: int


def estimate_normals(points: np.ndarray, radius: float, max_nn: int = 20) -> np.ndarray:
    """(M, 3) points [m] -> (M, 3) unit normals (Open3D hybrid search), oriented +z."""
    import open3d as o3d

    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, np.float64)))
    pc.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=radius, max_nn=max_nn))
    n = np.asarray(pc.normals)
    n = np.where(n[:, 2:3] < 0, -n, n)
    return n


def make_target(points: np.ndarray, normal_radius: float, normals: np.ndarray | None = None
                ) -> Target:
    """Target from (M, 3) points; normals estimated within `normal_radius` m if not given."""
    points = np.ascontiguousarray(points, dtype=np.float64)
    if normals is None:
        normals = estimate_normals(points, normal_radius)
    return Target(points, normals, cKDTree(points))


def voxel_keys(points: np.ndarray, voxel: float) -> np.ndarray:
    """(N, 3) points -> (N,) int64 key of the cubic voxel of edge `voxel` m holding each
    (exact within +/- 2^20 voxels of the origin)."""
    k = np.floor(np.asarray(points) / voxel).astype(np.int64) + (1 << 20)
    return k[:, 0] + (k[:, 1] << 21) + (k[:, 2] << 42)


def voxel_downsample(points: np.ndarray, voxel: float) -> np.ndarray:
    """(N, 3) -> (M, 3): the centroid of the points in each cubic voxel of edge `voxel` m."""
    if len(points) == 0:
        return np.zeros((0, 3))
    _, inv, cnt = np.unique(voxel_keys(points, voxel), return_inverse=True, return_counts=True)
    out = np.stack([np.bincount(inv, weights=points[:, i], minlength=len(cnt))
                    for i in range(3)], axis=1)
    return out / cnt[:, None]


def pca_normals(points: np.ndarray, tree: cKDTree, query: np.ndarray, k: int = 12,
                radius: float = 0.6, min_spread: float = 0.05) -> tuple[np.ndarray, np.ndarray]:
    """Unit normals (Q, 3), oriented +z, of the surface through `points` at the `query`
    points (Q, 3): smallest principal axis of the k nearest neighbours within `radius` m.

    Returns (normals, good): `good` (Q,) is False where the neighbourhood is not a surface
    patch (fewer than 5 neighbours, or points along a line such as a single lidar ring on
    the ground, whose second principal spread is below `min_spread` of the first). Those
    normals are zero, so they add nothing to a point-to-plane fit until recomputed.
    """
    if len(query) == 0:
        return np.zeros((0, 3)), np.zeros(0, bool)
    d, idx = tree.query(query, k=min(k, len(points)), distance_upper_bound=radius)
    d, idx = d.reshape(len(query), -1), idx.reshape(len(query), -1)
    ok = np.isfinite(d)
    idx = np.where(ok, idx, 0)
    nb = points[idx]  # (Q, k, 3)
    w = ok[..., None].astype(np.float64)
    cnt = np.maximum(w.sum(1), 1.0)
    mean = (nb * w).sum(1) / cnt
    c = (nb - mean[:, None]) * w
    cov = np.einsum("qki,qkj->qij", c, c) / cnt[..., None]
    vals, vecs = np.linalg.eigh(cov)
    n = vecs[:, :, 0]
    good = (ok.sum(1) >= 5) & (vals[:, 1] > min_spread * np.maximum(vals[:, 2], 1e-12))
    n = np.where(n[:, 2:3] < 0, -n, n)
    n[~good] = 0.0
    return n, good


def thin(points: np.ndarray, max_points: int) -> np.ndarray:
    """At most `max_points` of (N, 3) points, evenly spaced in their order (deterministic)."""
    if len(points) <= max_points:
        return points
    return points[np.linspace(0, len(points) - 1, max_points).astype(np.int64)]


def apply(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(4, 4) transform applied to (N, 3) points."""
    return points @ T[:3, :3].T + T[:3, 3]


def register(source: np.ndarray, target: Target, init: np.ndarray, max_dist: float,
             max_iter: int = 30, kernel: float | None = None, tol: float = 1e-4,
             workers: int = 1, ground_z: float | None = None, one_sided: bool = False) -> IcpResult:
    """Point-to-plane ICP of (S, 3) source points onto `target`, starting at `init` (4, 4).

    max_dist: correspondence gate, m. kernel: scale of the Geman-McClure robust weight, m
    (default max_dist / 3). Stops when the update is below `tol` (rad and m). workers:
    threads for the nearest-neighbour queries. ground_z: matches whose target normal has a
    z component above this are ground and constrain only z, roll and pitch (their pull on
    x, y and yaw is dropped, as in two-step ground / structure registration): a lidar's ground
    rings move with the robot and otherwise bias the fit towards standing still.
    one_sided: the target's steep normals point towards the sensor that saw them (see
    `orient_to_viewpoints`); a match on a steep surface that faces away from the robot is
    dropped, since the robot cannot see that side of it. Without this, the far face of a
    pole or post seen after passing it pairs with its near face in the map (kept from the
    approach), which pulls every sweep back along the path (lag builds up in the map).
    """
    kernel = max_dist / 3 if kernel is None else kernel
    T = np.array(init, dtype=np.float64)
    H = np.zeros((6, 6))
    it = 0
    for it in range(1, max_iter + 1):  # noqa: B007 - `it` is reported
        p = apply(T, source)
        d, idx = target.tree.query(p, distance_upper_bound=max_dist, workers=workers)
        ok = np.isfinite(d)
        if ok.sum() < 6:
            return IcpResult(T, float(ok.mean()) if len(ok) else 0.0, np.inf, H, int(ok.sum()), it)
        p, q, n = p[ok], target.points[idx[ok]], target.normals[idx[ok]]
        c = T[:3, 3]
        if one_sided:
            seen = facing(p, n, c)
            if seen.sum() < 6:
                return IcpResult(T, float(seen.sum() / len(source)), np.inf, H, int(seen.sum()), it)
            p, q, n = p[seen], q[seen], n[seen]
        r = np.einsum("ij,ij->i", p - q, n)
        J = np.hstack([np.cross(p - c, n), n])
        if ground_z is not None:
            ground = n[:, 2] > ground_z
            J[np.ix_(ground, [2, 3, 4])] = 0.0
        w = (kernel**2 / (kernel**2 + r**2)) ** 2
        H = (J * w[:, None]).T @ J
        g = (J * w[:, None]).T @ r
        delta = -np.linalg.solve(H + 1e-9 * np.eye(6), g)
        R = Rotation.from_rotvec(delta[:3]).as_matrix()
        step = np.eye(4)
        step[:3, :3] = R
        step[:3, 3] = c - R @ c + delta[3:]
        T = step @ T
        if np.abs(delta).max() < tol:
            break
    p = apply(T, source)
    d, idx = target.tree.query(p, distance_upper_bound=max_dist, workers=workers)
    ok = np.isfinite(d)
    if one_sided:
        ok[ok] = facing(p[ok], target.normals[idx[ok]], T[:3, 3])
    if ok.sum() == 0:
        return IcpResult(T, 0.0, np.inf, H, 0, it)
    r = np.einsum("ij,ij->i", p[ok] - target.points[idx[ok]], target.normals[idx[ok]])
    w = (kernel**2 / (kernel**2 + r**2)) ** 2
    rmse = float(np.sqrt(np.sum(w * r**2) / np.sum(w)))
    return IcpResult(T, float(ok.mean()), rmse, H / max(int(ok.sum()), 1), int(ok.sum()), it)


STEEP = 0.7   # |normal z| below this: a wall, pole or post face (oriented to its viewer)


def facing(p: np.ndarray, n: np.ndarray, center: np.ndarray) -> np.ndarray:
    """(K,) True where a match of point p (K, 3) onto a target surface with normal n (K, 3)
    is plausible from a sensor at `center` (3,): gentle surfaces (|n_z| >= STEEP) always,
    steep ones only where their viewpoint-oriented normal faces the sensor."""
    toward = np.einsum("ij,ij->i", n, center[None, :] - p) > 0
    return toward | (np.abs(n[:, 2]) >= STEEP)


def orient_to_viewpoints(points: np.ndarray, normals: np.ndarray, viewpoints: np.ndarray) -> np.ndarray:
    """Normals (M, 3) of steep surfaces (|n_z| < STEEP) flipped to point from points (M, 3)
    towards the sensor positions viewpoints (M, 3) that saw them (the visible side); gentle
    ones keep their +z orientation (a sensor at ground height sees the ground edge-on)."""
    flip = (np.einsum("ij,ij->i", normals, viewpoints - points) < 0) & (np.abs(normals[:, 2]) < STEEP)
    return np.where(flip[:, None], -normals, normals)


def weak_directions(hessian: np.ndarray, threshold: float) -> np.ndarray:
    """(6, 6) per-correspondence normal matrix -> (6, k) orthonormal directions whose
    eigenvalue is below `threshold` (the directions the scene leaves unconstrained)."""
    vals, vecs = np.linalg.eigh(hessian)
    return vecs[:, vals < threshold]


def project_update(T_pred: np.ndarray, T_icp: np.ndarray, weak: np.ndarray) -> np.ndarray:
    """Keep the ICP correction of `T_pred` only along the constrained directions: the
    correction (about the predicted position) loses its components along `weak` (6, k)."""
    if weak.shape[1] == 0:
        return T_icp
    c = T_pred[:3, 3]
    D = T_icp @ np.linalg.inv(T_pred)
    w = Rotation.from_matrix(D[:3, :3]).as_rotvec()
    v = D[:3, 3] - (c - D[:3, :3] @ c)
    delta = np.concatenate([w, v])
    delta = delta - weak @ (weak.T @ delta)
    R = Rotation.from_rotvec(delta[:3]).as_matrix()
    step = np.eye(4)
    step[:3, :3] = R
    step[:3, 3] = c - R @ c + delta[3:]
    return step @ T_pred
