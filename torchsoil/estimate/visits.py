"""Ground driven more than once: wheel passes per cell and visit, the poses of one visit, and
measured rut depth (docs/formats.md section 3, visits v1.1).

A terrain pair with visit layers holds, per cell, the surface before and after each visit v
(`visit_front`, `visit_back`, (V, X, Y), m) and the time base_link passed closest
(`visit_time`, s). These functions are pure: arrays in, arrays out.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from torchsoil.sim.geometry import resample_poses, wheel_positions


def visit_counts(visit_time: np.ndarray) -> np.ndarray:
    """(V, X, Y) visit times [s] (NaN: no such visit) -> (X, Y) int number of visits per cell."""
    return np.isfinite(visit_time).sum(0)


def wheel_passes(poses: np.ndarray, wheels: np.ndarray, wheel_width: float, grid, visit_time: np.ndarray
                 ) -> np.ndarray:
    """Wheel passes over each cell during each of its visits.

    A wheel passes a cell when its centre comes within half a wheel width of the cell's centre;
    one pass is one stretch of the drive during which it stays that near (a wheel leaving for
    more than a wheel width of its own travel and coming back passes again). Each pass belongs
    to the cell's visit whose `visit_time` is nearest the pass.

    Args:
        poses: (N, 7) base_link poses [t, x, y, z, roll, pitch, yaw] (s, m, rad).
        wheels: (K, 3) wheel contact centres in base_link x, y [m] and track index.
        wheel_width: m.
        grid: the cells' Grid (dx, origin, shape (X, Y)).
        visit_time: (V, X, Y) per-cell visit times, s; NaN where the cell has no such visit.

    Returns:
        (V, X, Y) int64 wheel passes per visit (0 where the cell has no such visit).
    """
    V, X, Y = visit_time.shape
    out = np.zeros((V, X * Y), np.int64)
    step = grid.dx / 2
    dense = resample_poses(np.asarray(poses, np.float64)[:, [0, 1, 2, 6]], wheels[:, :2], step)
    pts = wheel_positions(dense, wheels[:, :2])                                   # (K, M, 2)
    K, M = pts.shape[:2]
    vt = visit_time.reshape(V, -1)
    cand = np.flatnonzero(np.isfinite(vt).any(0))                                 # cells with a visit
    if len(cand) == 0 or M == 0:
        return out.reshape(V, X, Y)
    xs, ys = grid.centers()
    ci, cj = np.unravel_index(cand, (X, Y))
    hits = cKDTree(np.stack([xs[ci], ys[cj]], 1)).query_ball_point(pts.reshape(-1, 2), wheel_width / 2)
    counts = np.fromiter(map(len, hits), np.int64, K * M)
    if counts.sum() == 0:
        return out.reshape(V, X, Y)
    sample = np.repeat(np.arange(K * M), counts)
    cell = np.concatenate([h for h in hits if h]).astype(np.int64)
    wheel, m = np.divmod(sample, M)
    order = np.lexsort((m, wheel, cell))
    cell, wheel, m = cell[order], wheel[order], m[order]
    gap = max(1, int(np.ceil(wheel_width / step)))                                # a wheel width of travel
    new = np.r_[True, (cell[1:] != cell[:-1]) | (wheel[1:] != wheel[:-1]) | (m[1:] - m[:-1] > gap)]
    c, t = cand[cell[new]], dense[m[new], 0]                                      # one per pass
    dt = np.abs(vt[:, c] - t[None])                                               # (V, P)
    v = np.argmin(np.where(np.isfinite(dt), dt, np.inf), 0)
    np.add.at(out, (v, c), 1)
    return out.reshape(V, X, Y)


def passes_before(passes: np.ndarray) -> np.ndarray:
    """(V, X, Y) wheel passes per visit -> (V, X, Y) wheel passes the cell had before visit v."""
    return np.cumsum(passes, 0) - passes


def track_heading(times_before: np.ndarray, t: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    """(X, Y) heading [rad] of base_link when it last passed each cell before: times_before
    (v, X, Y) the `visit_time` layers of the visits before [s, NaN: no such visit], t (N,)
    and yaw (N,) [rad, unwrapped] the poses' times and headings. A cell no earlier visit
    passed takes the nearest cell's; NaN everywhere when none did."""
    shape = np.shape(times_before)[1:]
    last = np.full(shape, np.nan)
    for tv in times_before:
        last = np.where(np.isfinite(tv), tv, last)
    ok = np.isfinite(last)
    if not ok.any():
        return last
    if not ok.all():
        last = last[tuple(ndimage.distance_transform_edt(~ok, return_distances=False, return_indices=True))]
    return np.interp(last, t, yaw)


def visit_poses(poses: np.ndarray, arc: np.ndarray, times: np.ndarray, reach: float) -> np.ndarray:
    """The poses of one visit over some ground: those whose base_link arc length lies within
    `reach` [m] of the arc lengths at which it passed the ground's cells (`times`, (G,) s, the
    ground's `visit_time` for that visit), with one more on each side. poses (N, 7), arc (N,)
    base_link arc length at each pose, m. Returns (n, 7)."""
    a = np.interp([np.min(times), np.max(times)], poses[:, 0], arc)
    sel = np.flatnonzero((arc >= a[0] - reach) & (arc <= a[1] + reach))
    if len(sel) == 0:
        sel = np.array([int(np.searchsorted(poses[:, 0], np.median(times)).clip(0, len(poses) - 1))])
    return np.asarray(poses[max(sel[0] - 1, 0):sel[-1] + 2], np.float64)


def visit_stretches(arc: np.ndarray, gap: float) -> np.ndarray:
    """The stretch of the drive each visit of some ground is: (V, G) base_link arc lengths [m]
    at which visit v passed each of G cells -> (V, 2) [first, last] arc length of its main
    stretch. Sorted, a visit's arc lengths break where two neighbours lie more than `gap` [m]
    apart (one pass over contiguous ground is contiguous; a cell whose v-th visit was another
    pass, as ground at the edge of a neighbouring row's reach, lies a turn away); the main
    stretch is the run holding the most cells (the earliest of equal ones). A visit with no
    finite arc length gets [inf, -inf]: it holds no cell."""
    arc = np.asarray(arc, np.float64)
    out = np.tile([np.inf, -np.inf], (arc.shape[0], 1))
    for v, a in enumerate(arc):
        a = np.sort(a[np.isfinite(a)])
        if len(a) == 0:
            continue
        cut = np.flatnonzero(np.diff(a) > gap) + 1
        starts, ends = np.r_[0, cut], np.r_[cut, len(a)]
        k = int(np.argmax(ends - starts))
        out[v] = a[starts[k]], a[ends[k] - 1]
    return out


def rut_depth(h_front: np.ndarray, h_back: np.ndarray, ruts: np.ndarray) -> float:
    """Mean depth [m] of the ruts (positive: the surface went down) on the (X, Y) bool `ruts`
    cells where both (X, Y) surfaces [m] are measured; NaN where none is."""
    d = (h_front - h_back)[ruts]
    d = d[np.isfinite(d)]
    return float(d.mean()) if len(d) else float("nan")


def pass_layers(pair, passes: np.ndarray, visit_back: list[np.ndarray] | np.ndarray) -> dict[str, np.ndarray]:
    """The layers of passes.npz on the pair's grid.

    Args:
        pair: a terrain pair with visit layers (its `visit_front`, `visit_time`, grid).
        passes: (V, X, Y) wheel passes per visit (`wheel_passes`).
        visit_back: (V, X, Y) surface after each visit [m], net of the map offset.

    Returns:
        dx (), origin (2,) as the pair; visits (X, Y) int visits per cell; passes (X, Y) int
        wheel passes in all; passes_visit (V, X, Y) int per visit; rut_depth_visit (V, X, Y)
        float32 depth each visit dug (H_f - H_b of the visit, positive down), m; rut_depth
        (X, Y) float32 their sum over the measured visits (NaN where none is), m.
    """
    rut = np.asarray(pair.visit_front, np.float64) - np.asarray(visit_back, np.float64)
    measured = np.isfinite(rut).any(0)
    total = np.where(measured, np.nansum(rut, 0), np.nan)
    return {"dx": np.float64(pair.dx), "origin": np.asarray(pair.origin, np.float64),
            "visits": visit_counts(pair.visit_time).astype(np.int16), "passes": passes.sum(0).astype(np.int16),
            "passes_visit": passes.astype(np.int16), "rut_depth_visit": rut.astype(np.float32),
            "rut_depth": total.astype(np.float32)}


def multipass_table(rows: list[dict], names, reference: list[dict] | None = None) -> list[dict]:
    """Measured rut depth and fitted sinkage against the pass number, over the windows whose
    ground was driven more than once (params.csv rows with `visit` and `passes_before`).

    One entry per (visit, passes_before) among the fitted rows of those windows: visit,
    passes_before (wheel passes before the visit, rounded), windows (rows counted), rut and
    rut_sd (mean and standard deviation over windows of the measured rut depth, m), d and d_sd
    (of each window's sinkage, the mean over its tracks, m), and with `reference` (the
    reference.csv rows, one per row) prediction_floor: the mean prediction cost over the mean
    noise floor, on the rows where both are measured (NaN where none is)."""
    tracks = [n for n in names if n[:1] == "d" and n[1:].isdigit()]
    again = {r["s"] for r in rows if int(r.get("visit", 0)) > 0}
    refs = reference if reference is not None else [{}] * len(rows)
    groups: dict[tuple[int, int], list[tuple[dict, dict]]] = {}
    for r, f in zip(rows, refs, strict=True):
        pb = float(r.get("passes_before", 0))
        if r["s"] in again and np.isfinite(float(r["residual"])) and np.isfinite(pb):
            groups.setdefault((int(r["visit"]), int(round(pb))), []).append((r, f))
    table = []
    for (visit, pb), group in sorted(groups.items()):
        rut = np.array([float(r["rut_depth"]) for r, _ in group])
        d = np.array([np.mean([float(r[n]) for n in tracks]) for r, _ in group])
        cost = np.array([(float(r["prediction"]), float(f.get("floor", "nan"))) for r, f in group])
        rut, cost = rut[np.isfinite(rut)], cost[np.isfinite(cost).all(1)]
        table.append({"visit": visit, "passes_before": pb, "windows": len(group),
                      "rut": float(rut.mean()) if len(rut) else float("nan"),
                      "rut_sd": float(rut.std()) if len(rut) else float("nan"),
                      "d": float(d.mean()), "d_sd": float(d.std()),
                      "prediction_floor": float(cost[:, 0].mean() / cost[:, 1].mean()) if len(cost) else float("nan")})
    return table


def multipass_markdown(table: list[dict]) -> str:
    """The multi-pass table (`multipass_table`) as Markdown, depths in mm."""
    if not table:
        return "No ground was driven more than once."
    lines = ["| visit | wheel passes before | windows | measured rut depth [mm] | fitted sinkage d [mm] "
             "| prediction / noise floor |", "| --- | --- | --- | --- | --- | --- |"]
    lines += [f"| {e['visit']} | {e['passes_before']} | {e['windows']} "
              f"| {1e3 * e['rut']:.1f} ± {1e3 * e['rut_sd']:.1f} | {1e3 * e['d']:.1f} ± {1e3 * e['d_sd']:.1f} "
              f"| {e.get('prediction_floor', float('nan')):.2f} |" for e in table]
    return "\n".join(lines)
