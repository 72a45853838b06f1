"""Lidar pipeline output against a recording's truth: trajectory and heightmap errors.

For evaluations and benchmarks only (the pipeline never reads the truth). The pipeline's
world frame is base_link at the first sweep, so the estimate is first put into the truth's
frame by the first pose; `ate_aligned` uses the best rigid fit of the whole path instead
(the usual absolute trajectory error), and heightmap errors are also given after removing
the best-fit plane (the world frame is not levelled: a small tilt of the first pose tilts
the whole map without changing H_delta).
"""

from __future__ import annotations

import numpy as np

from torchsoil.synth.truthfile import TruthFile


def truth_poses(truth: TruthFile, stamps: np.ndarray) -> np.ndarray:
    """(S, 4, 4) true base_link poses at bag times `stamps` (S,) [s], interpolated."""
    from torchsoil.io.trajectory import rows_to_poses
    from torchsoil.pipeline.reregister import interpolate_poses

    tr = truth["poses"]
    return interpolate_poses(tr[:, 0], rows_to_poses(tr), np.asarray(stamps, np.float64) - truth.t0)


def _rigid_fit(P: np.ndarray, Q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """R (3, 3), t (3,) minimising |R P + t - Q| over (N, 3) point pairs (Kabsch)."""
    mp, mq = P.mean(0), Q.mean(0)
    U, _, Vt = np.linalg.svd((P - mp).T @ (Q - mq))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    return R, mq - R @ mp


def pipeline_errors(terrain, truth: TruthFile) -> dict[str, float]:
    """Errors of a pipeline terrain pair (poses (S, 7) with bag-time stamps, H_f, H_b) against
    the truth: ate_first_m / ate_aligned_m (RMS position error, first-pose / best-fit
    aligned), yaw_rms_deg, h_front_rms_m / h_back_rms_m (valid cells, first-pose aligned),
    h_front_plane_rms_m / h_back_plane_rms_m (after removing the best-fit plane),
    h_delta_mean_m / h_delta_std_m (all cells where both maps are valid)."""
    from torchsoil.io.trajectory import rows_to_poses

    est = rows_to_poses(terrain.poses)
    true = truth_poses(truth, terrain.poses[:, 0])
    A = true[0] @ np.linalg.inv(est[0])
    W = A @ est
    err = W[:, :3, 3] - true[:, :3, 3]
    R, t = _rigid_fit(W[:, :3, 3], true[:, :3, 3])
    err_al = W[:, :3, 3] @ R.T + t - true[:, :3, 3]
    yaw = np.arctan2(W[:, 1, 0], W[:, 0, 0]) - np.arctan2(true[:, 1, 0], true[:, 0, 0])
    yaw = np.angle(np.exp(1j * yaw))
    out = {"ate_first_m": float(np.sqrt(np.mean(np.sum(err**2, 1)))),
           "ate_aligned_m": float(np.sqrt(np.mean(np.sum(err_al**2, 1)))),
           "yaw_rms_deg": float(np.degrees(np.sqrt(np.mean(yaw**2))))}
    for name, h, layer in (("front", terrain.h_front, "h_before"), ("back", terrain.h_back, "h_after")):
        d, xy = _against(terrain, h, truth[layer], truth, A)
        M = np.column_stack([np.ones(len(d)), xy])
        rest = d - M @ np.linalg.lstsq(M, d, rcond=None)[0]
        out[f"h_{name}_rms_m"] = float(np.sqrt(np.mean(d**2)))
        out[f"h_{name}_plane_rms_m"] = float(np.sqrt(np.mean(rest**2)))
    hd = terrain.h_delta
    out["h_delta_mean_m"] = float(np.nanmean(hd))
    out["h_delta_std_m"] = float(np.nanstd(hd))
    return out


def _against(terrain, h: np.ndarray, layer: np.ndarray, truth: TruthFile, A: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray]:
    """Height differences [m] of the (X, Y) map h of `terrain` (its cells placed by the (4, 4)
    alignment A into the truth's frame) against the truth's (X', Y') `layer`, where both are
    finite: (K,) differences and (K, 2) the cells' truth-frame x, y."""
    X, Y = np.meshgrid(*terrain.grid.centers(), indexing="ij")
    v = np.isfinite(h)
    p = np.column_stack([X[v], Y[v], h[v], np.ones(v.sum())]) @ A.T
    ij = truth.grid.index(p[:, :2])
    inside = np.all((ij >= 0) & (ij < np.array(truth.grid.shape)), axis=1)
    d = p[inside, 2] - layer[ij[inside, 0], ij[inside, 1]]
    ok = np.isfinite(d)
    return d[ok], p[inside][ok, :2]


def visit_errors(terrain, truth: TruthFile) -> dict[str, float]:
    """The visit layers of a pipeline terrain pair against the truth's surface at each visit
    (`states`, `n_visits`: the recorder's world), on the cells both count two visits or more:
    visit_front_rms_m[v] (the surface before visit v, states[v]) and visit_back_rms_m[v] (after
    it, states[v + 1]), each net of its mean (a map offset is not a visit's error), m; and the
    cells compared. Where the pair has no visit layers: {}."""
    from torchsoil.io.trajectory import rows_to_poses

    if getattr(terrain, "visit_front", None) is None:
        return {}
    est = rows_to_poses(terrain.poses)
    A = truth_poses(truth, terrain.poses[:1, 0])[0] @ np.linalg.inv(est[0])
    states, twice = truth["states"], truth["n_visits"] >= 2
    again = np.isfinite(terrain.visit_time[1])                  # the pair's cells with two visits or more
    out: dict[str, float] = {}
    for v in range(min(terrain.visit_front.shape[0], states.shape[0] - 1)):
        for name, h, state in (("front", terrain.visit_front[v], states[v]),
                               ("back", terrain.visit_back[v], states[v + 1])):
            d, _ = _against(terrain, np.where(again, h, np.nan), np.where(twice, state, np.nan), truth, A)
            if len(d):
                out[f"visit_{name}_rms_m_{v}"] = float(np.std(d))
                out[f"visit_{name}_cells_{v}"] = len(d)
    return out
