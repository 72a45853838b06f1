"""Point-to-plane ICP onto a fixed target with a prebuilt search index, and surface normals.

Shared by the mapper and the re-registration: the target (a local or the global map)
keeps one `Target` (points, normals, search index) across many registrations, which a
per-call library ICP would rebuild every time (measured: Open3D's tensor ICP and KISS-ICP's
registration took 6 to 10 times our CPU time per sweep here, and neither has the ground,
one-sided and degenerate-direction handling). The index is a `VoxelIndex` (exact, on a
hashed voxel grid) or a scipy cKDTree; the inner loops are compiled (`_kernels`). Over a
VoxelIndex, the ICP's matches are tracked from iteration to iteration (`NearestTracker`):
a source point is searched again only where its move could have changed its match.

The update is parametrised about the current sensor position c: a point p moves to
c + R(w) (p - c) + v with w, v (3,) each, so the 6 x 6 normal matrix separates rotation
about the robot from translation, and its weak eigenvectors name the directions the
scene does not constrain (a flat field: x, y and yaw).
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from typing import NamedTuple

import numpy as np
from scipy.spatial import cKDTree

from torchsoil.pipeline import _kernels as _k


class Target(NamedTuple):
    """Registration target: points (M, 3) [m], unit normals (M, 3), and a search structure
    over the points answering `query(x, k, distance_upper_bound)` like scipy's cKDTree (a
    cKDTree or a `VoxelIndex`)."""

    points: np.ndarray
    normals: np.ndarray
    tree: cKDTree | VoxelIndex


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


def make_target(points: np.ndarray, normal_radius: float, normals: np.ndarray | None = None,
                cell: float = 0.6) -> Target:
    """Target from (M, 3) points; normals estimated within `normal_radius` m if not given.
    Its search structure is a `VoxelIndex` with cells of `cell` m (a few map voxels)."""
    points = np.ascontiguousarray(points, dtype=np.float64)
    if normals is None:
        normals = estimate_normals(points, normal_radius)
    return Target(points, normals, VoxelIndex(points, cell))


_POOLS: dict[int, ThreadPoolExecutor] = {}


def _pool(workers: int) -> ThreadPoolExecutor:
    """A lasting thread pool of `workers` threads (the grid kernels release the interpreter lock)."""
    if workers not in _POOLS:
        _POOLS[workers] = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="voxelindex")
    return _POOLS[workers]


class VoxelIndex:
    """Exact nearest-neighbour search within a bounded distance over a hashed grid of cubic
    cells (edge `cell` m; a few map voxels: 0.6 m suits the 0.2 m voxel map), answering the
    `cKDTree.query` calls of the pipeline (k nearest, `distance_upper_bound`; same
    conventions: inf distance and index n where none).

    Building is linear in the points and a query visits only the cells that can hold a
    closer point: on the 0.2 m voxel map with the ICP gates (0.3 and 0.5 m) about four times
    as fast as a KD-tree, and as fast for the 12 nearest within 0.6 m (normals). Queries
    without a bound, or a bound above 6 cells, go to a KD-tree built on first use. `workers`
    threads (-1: all cores) share large queries, as cKDTree's.
    """

    _offsets: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    def __init__(self, points: np.ndarray, cell: float = 0.6):
        self.data = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
        self.n, self.cell = len(self.data), float(cell)
        self._grid = _k.grid_build(self.data, self.cell) if self.n else None
        self._tree: cKDTree | None = None

    @classmethod
    def offsets(cls, reach: int) -> tuple[np.ndarray, np.ndarray]:
        """Cell offsets within `reach` cells, sorted by their least squared distance in cells."""
        if reach not in cls._offsets:
            r = np.arange(-reach, reach + 1)
            o = np.stack(np.meshgrid(r, r, r, indexing="ij"), -1).reshape(-1, 3).astype(np.int64)
            lb = (np.maximum(np.abs(o) - 1, 0) ** 2).sum(1)
            order = np.argsort(lb, kind="stable")
            cls._offsets[reach] = (np.ascontiguousarray(o[order]), lb[order].astype(np.float64))
        return cls._offsets[reach]

    def query(self, x: np.ndarray, k: int = 1, distance_upper_bound: float = np.inf, workers: int = 1
              ) -> tuple[np.ndarray, np.ndarray]:
        x = np.asarray(x, dtype=np.float64)
        single = x.ndim == 1
        q = np.ascontiguousarray(x.reshape(-1, 3))
        r = float(distance_upper_bound)
        if self.n == 0:
            d, i = np.full((len(q), k), np.inf), np.zeros((len(q), k), np.int64)
        elif not np.isfinite(r) or r > 6 * self.cell:
            if self._tree is None:
                self._tree = cKDTree(self.data)
            d, i = self._tree.query(q, k=k, distance_upper_bound=r, workers=workers)
            d, i = d.reshape(len(q), k), i.reshape(len(q), k)
        else:
            d, i = self._search(q, int(k), r, workers)
        if k == 1:
            d, i = d[:, 0], i[:, 0]
        return (d[0], i[0]) if single else (d, i)

    def _search(self, q: np.ndarray, k: int, r: float, workers: int) -> tuple[np.ndarray, np.ndarray]:
        """(Q, k) distances and indices from the grid; split over `workers` threads (-1: all
        cores) when there are enough queries to pay for it."""
        def run(part: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            if k == 1:
                d, i = _k.grid_nn(part, r, self.cell, *self._grid)
                return d[:, None], i[:, None]
            return _k.grid_knn(part, k, r, self.cell, *self._grid, *self.offsets(int(np.ceil(r / self.cell))))

        workers = (os.cpu_count() or 1) if workers < 0 else max(int(workers), 1)
        if workers == 1 or len(q) < 1024:
            return run(q)
        parts = list(_pool(workers).map(run, np.array_split(q, workers)))
        return np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts])

    def tracker(self, n_queries: int, r: float) -> NearestTracker | None:
        """A NearestTracker of `n_queries` moving queries within `r` m on this index (None
        where the index is empty or r is beyond the grid's reach: query then)."""
        if self.n == 0 or not 0 < 1.25 * r <= 6 * self.cell:
            return None
        return NearestTracker(self, n_queries, r)

    def any_newer(self, query: np.ndarray, since: np.ndarray, born: np.ndarray, radius: float) -> np.ndarray:
        """(Q,) True where a point closer than `radius` to query (Q, 3) has born (n,) above
        since (Q,) (its neighbourhood changed after `since`)."""
        q = np.ascontiguousarray(query, dtype=np.float64).reshape(-1, 3)
        if self.n == 0 or len(q) == 0:
            return np.zeros(len(q), bool)
        reach = int(np.ceil(radius / self.cell))
        return _k.grid_any_newer(q, np.ascontiguousarray(since, np.int64), np.ascontiguousarray(born, np.int64),
                                 float(radius), self.cell, *self._grid, *self.offsets(reach))


class NearestTracker:
    """Nearest neighbours within `r` m on a VoxelIndex of a fixed set of S queries that move a
    little between calls (an ICP's source points, pose after pose): `query(p)` with p (S, 3)
    returns the (S,) indices VoxelIndex.query(p, distance_upper_bound=r) would (n where none),
    searching again only the queries whose answer may have changed since their last search
    (each search also bounds the second nearest, within 1.25 r; `_kernels.grid_match`).
    `searched` counts the searches."""

    def __init__(self, index: VoxelIndex, n_queries: int, r: float):
        self.index, self.r, self.R = index, float(r), 1.25 * float(r)
        self.at = np.full((n_queries, 3), np.nan)        # where each query was last searched, m
        self.near = np.full(n_queries, index.n, np.int64)
        self.bound = np.zeros(n_queries)
        self.searched = 0

    def query(self, p: np.ndarray) -> np.ndarray:
        ix = self.index
        idx = np.empty(len(p), np.int64)
        self.searched += _k.grid_match(np.ascontiguousarray(p, dtype=np.float64), self.r, self.R, ix.cell, *ix._grid,
                                       ix.data, self.at, self.near, self.bound, idx)
        return idx


def voxel_keys(points: np.ndarray, voxel: float) -> np.ndarray:
    """(N, 3) points -> (N,) int64 key of the cubic voxel of edge `voxel` m holding each
    (exact within +/- 2^20 voxels of the origin). Voxels are centred on multiples of the edge,
    so points on a plane through the origin (a lidar's azimuth-zero column on a robot's
    symmetry plane, flat ground at z = 0) lie mid-voxel, not on a boundary where the
    slightest change of a point switches its voxel."""
    points = np.asarray(points)
    if points.dtype == np.float64 and points.ndim == 2 and points.shape[1] == 3:
        return _k.voxel_keys(np.ascontiguousarray(points), float(voxel))
    k = np.floor(points / voxel + 0.5).astype(np.int64) + (1 << 20)
    return k[:, 0] + (k[:, 1] << 21) + (k[:, 2] << 42)


def voxel_first(points: np.ndarray, voxel: float) -> np.ndarray:
    """Indices of the first point in each cubic voxel of edge `voxel` m, in the order of the
    voxels' keys (as np.unique(keys, return_index=True))."""
    if len(points) == 0:
        return np.zeros(0, dtype=np.int64)
    keys = voxel_keys(points, voxel)
    first, _ = _k.first_of_keys(keys)
    return first[np.argsort(keys[first])]


def voxel_downsample(points: np.ndarray, voxel: float) -> np.ndarray:
    """(N, 3) -> (M, 3): the centroid of the points in each cubic voxel of edge `voxel` m,
    in the order of the voxels' keys."""
    if len(points) == 0:
        return np.zeros((0, 3))
    points = np.ascontiguousarray(points, dtype=np.float64)
    keys = voxel_keys(points, voxel)
    first, inv = _k.first_of_keys(keys)
    out = _k.centroids(points, inv, len(first))
    return out[np.argsort(keys[first])]


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
    cov, cnt = _k.covariances(_contiguous(points), np.ascontiguousarray(idx, dtype=np.int64),
                              np.ascontiguousarray(d, dtype=np.float64))
    vals, vecs = np.linalg.eigh(cov)
    n = vecs[:, :, 0]
    good = (cnt >= 5) & (vals[:, 1] > min_spread * np.maximum(vals[:, 2], 1e-12))
    n = np.where(n[:, 2:3] < 0, -n, n)
    n[~good] = 0.0
    return n, good


def thin(points: np.ndarray, max_points: int, voxel: float) -> np.ndarray:
    """At most `max_points` of the (N, 3) voxel points (one per cubic voxel of edge `voxel` m),
    in their order: those whose voxel key hashes lowest. The pick is deterministic and stable:
    a voxel that appears or vanishes changes at most one other pick, where taking every k-th
    point would shift all picks after it (and a sweep moved by a nanometre could register on
    a different subset)."""
    if len(points) <= max_points:
        return points
    h = _mix(voxel_keys(points, voxel).view(np.uint64))
    keep = np.sort(np.argpartition(h, max_points)[:max_points])
    return points[keep]


def _mix(x: np.ndarray) -> np.ndarray:
    """splitmix64 finaliser: (N,) uint64 -> well-spread (N,) uint64."""
    x = x ^ (x >> np.uint64(30))
    x = x * np.uint64(0xBF58476D1CE4E5B9)
    x = x ^ (x >> np.uint64(27))
    x = x * np.uint64(0x94D049BB133111EB)
    return x ^ (x >> np.uint64(31))


def apply(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(4, 4) transform applied to (N, 3) points (float64 out)."""
    points = np.asarray(points)
    if points.ndim == 2 and points.shape[1] == 3 and points.dtype in (np.float64, np.float32):
        T = np.asarray(T, dtype=np.float64)
        return _k.transform(points, np.ascontiguousarray(T[:3, :3]), np.ascontiguousarray(T[:3, 3]))
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
    source = np.ascontiguousarray(source, dtype=np.float64)
    tp, tn = _contiguous(target.points), _contiguous(target.normals)
    use_ground = ground_z is not None
    gz = float(ground_z) if use_ground else 0.0
    T = np.array(init, dtype=np.float64)
    H = np.zeros((6, 6))
    Hk, g = np.zeros((6, 6)), np.zeros(6)
    n_src = len(source)
    tracker = target.tree.tracker(n_src, max_dist) if isinstance(target.tree, VoxelIndex) and workers == 1 else None

    def nearest(p: np.ndarray) -> np.ndarray:
        if tracker is not None:
            return tracker.query(p)
        return target.tree.query(p, distance_upper_bound=max_dist, workers=workers)[1]

    it = 0
    for it in range(1, max_iter + 1):  # noqa: B007 - `it` is reported
        p = apply(T, source)
        idx = nearest(p)
        c = T[:3, 3].copy()
        n_ok, n_used = _k.icp_system(p, idx, tp, tn, c, gz, use_ground, one_sided, STEEP, kernel, Hk, g)
        if n_ok < 6:
            return IcpResult(T, n_ok / n_src if n_src else 0.0, np.inf, H, n_ok, it)
        if n_used < 6:
            return IcpResult(T, n_used / n_src, np.inf, H, n_used, it)
        H = Hk.copy()
        T, size = _k.icp_step(T, H, g)
        if size < tol:  # converged: the matches of this last, sub-tolerance step still hold
            break
    else:
        idx = None
    p = apply(T, source)
    if idx is None:
        idx = nearest(p)
    n_used, sw, swr = _k.icp_residual(p, idx, tp, tn, T[:3, 3].copy(), one_sided, STEEP, kernel)
    if n_used == 0:
        return IcpResult(T, 0.0, np.inf, H, 0, it)
    rmse = float(np.sqrt(swr / sw))
    return IcpResult(T, n_used / n_src, rmse, H / n_used, n_used, it)


def truncated_cost(source: np.ndarray, T: np.ndarray, target: Target, tol: float) -> float:
    """Mean truncated point-to-plane cost of the (S, 3) source points placed by T (4, 4):
    min(r, tol)^2 / tol^2 per point, r its distance to the nearest target point's plane (that
    point within 2 tol; none: the full 1). Ranks candidate poses of one sweep: 0 where every
    point lies on the map, 1 where none does."""
    if len(source) == 0:
        return 1.0
    p = apply(T, source)
    d, i = target.tree.query(p, distance_upper_bound=2 * tol)
    ok = np.flatnonzero(np.isfinite(d))
    r = np.abs(np.einsum("ij,ij->i", target.normals[i[ok]], p[ok] - target.points[i[ok]]))
    return float((np.sum(np.minimum(r, tol) ** 2) / tol**2 + (len(source) - len(ok))) / len(source))


def _contiguous(a: np.ndarray) -> np.ndarray:
    return a if a.flags.c_contiguous and a.dtype == np.float64 else np.ascontiguousarray(a, dtype=np.float64)


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
    w = _k.rotvec_of(np.ascontiguousarray(D[:3, :3]))
    v = D[:3, 3] - (c - D[:3, :3] @ c)
    delta = np.concatenate([w, v])
    delta = delta - weak @ (weak.T @ delta)
    R = _k.rotation(np.ascontiguousarray(delta[:3]))
    step = np.eye(4)
    step[:3, :3] = R
    step[:3, 3] = c - R @ c + delta[3:]
    return step @ T_pred
