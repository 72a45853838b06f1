"""The pipeline's checks of its own output: runs of flagged sweeps said with their times, and
ground driven more than once checked for a map that broke between the visits."""

from __future__ import annotations

import numpy as np

from torchsoil.io.terrain_pair import TerrainPair
from torchsoil.pipeline import mapping


def flagged_spans(stamps: np.ndarray, flags: np.ndarray, t0: float) -> list[str]:
    """Human-readable runs of flagged sweeps: 'sweeps 40-75 (t = 4.00-7.50 s): degenerate'."""
    out = []
    for bit, name in mapping.FLAG_NAMES.items():
        if bit in (mapping.RETRIED, mapping.MAP_CONFLICT):   # registered after all; said by check_visits
            continue
        on = (flags & bit) != 0
        k = 0
        while k < len(on):
            if not on[k]:
                k += 1
                continue
            j = k
            while j + 1 < len(on) and on[j + 1]:
                j += 1
            out.append(f"sweeps {k}-{j} (t = {stamps[k] - t0:.2f}-{stamps[j] - t0:.2f} s after "
                       f"the start): {name}")
            k = j + 1
    return out


def check_visits(terrain: TerrainPair, max_shift: float, t_start: float = 0.0) -> list[str]:
    """Ground driven more than once, checked: the state between visits as the way out left it
    (`visit_back[v]`) and as the way back finds it (`visit_front[v + 1]`) must lie on the same
    cells (`visit_offsets`). Where they lie more than `max_shift` m apart, the map broke
    between the visits: the sweeps of the later visit over that ground get MAP_CONFLICT (their
    windows are flagged) and a problem says so. Writes `visit_shift` (V - 1, 2) [m] into the
    extras. Returns the problems."""
    from torchsoil.pipeline.checks import visit_offsets

    offsets = visit_offsets(terrain)
    if not offsets:
        return []
    shifts = np.zeros((terrain.visit_front.shape[0] - 1, 2))
    stamps, flags = terrain.extras["scan_stamps"], terrain.extras["scan_flags"]
    problems = []
    for off in offsets:
        shifts[off["visit"] - 1] = off["shift_m"]
        if off["distance_m"] > max_shift:
            flags[(stamps >= off["t0"]) & (stamps <= off["t1"])] |= mapping.MAP_CONFLICT
            problems.append(
                f"the ground between visits {off['visit'] - 1} and {off['visit']} lies "
                f"{100 * off['distance_m']:.0f} cm from where the earlier visit left it (seen again at "
                f"t = {off['t0'] - t_start:.1f}-{off['t1'] - t_start:.1f} s after the start): the map broke "
                "between the visits, so the ruts would double there; its windows are flagged (map_conflict)")
    terrain.extras["visit_shift"] = shifts
    return problems


def ground_offset(before: np.ndarray, after: np.ndarray, dx: float, max_shift: float = 0.2
                  ) -> tuple[np.ndarray, float, int]:
    """Where the ground of one map lies in another: the horizontal shift of `after` (X, Y) [m]
    that best matches `before` (X, Y) [m] on the cells both measure (NaN: not measured).

    Used on the two views of the state between visits (`visit_back[v]`, `visit_front[v + 1]`):
    on a map that holds, the ruts of the way out and of the way back lie on the same cells
    and the shift is zero. Searched over whole cells within `max_shift` m each way, comparing
    the maps net of their mean difference (a vertical offset is not a shift); the ruts and
    berms carry the signal.

    Returns (shift (2,) in m along x and y: `after` sampled at cell (i + sx, j + sy) matches
    `before` at (i, j); the RMS height difference at that shift, m; the cells compared there).
    A shift on the edge of the search means the maps lie at least that far apart. No common
    cells: (NaN, NaN), NaN, 0.
    """
    a, b = np.asarray(before, np.float64), np.asarray(after, np.float64)
    r = int(round(max_shift / dx))
    X, Y = a.shape
    best = (np.full(2, np.nan), np.nan, 0)
    for sx in range(-r, r + 1):
        for sy in range(-r, r + 1):
            aa = a[max(0, -sx):X - max(0, sx), max(0, -sy):Y - max(0, sy)]
            bb = b[max(0, sx):X + min(0, sx), max(0, sy):Y + min(0, sy)]
            d = aa - bb
            d = d[np.isfinite(d)]
            if len(d) < 100:
                continue
            rms = float(np.sqrt(np.mean((d - d.mean()) ** 2)))
            if not rms >= best[1]:
                best = (np.array([sx, sy], np.float64) * dx, rms, len(d))
    return best


def visit_offsets(pair, max_shift: float = 0.2, evidence: float = 0.8) -> list[dict]:
    """The shift between the two views of the ground between each pair of visits (the back
    lidar's after visit v, the front lidar's before visit v + 1; `ground_offset`), for a pair
    with visit layers. Where the map holds they lie on the same cells; where it broke, the way
    back sees the ruts of the way out displaced (and the estimator would see doubled ruts).

    A shift counts only where it explains the difference: its RMS below `evidence` times the
    RMS without a shift (flat ground, with nothing to align, gives shift 0).

    Returns per v (0 .. V - 2) a dict: visit (v + 1), shift_m (2,) [m], distance_m, rms_m and
    rms0_m (RMS height difference at the shift and unshifted, m), cells, and t0, t1 (s, the
    poses' clock: when visit v + 1 passed those cells). No common cells: not listed."""
    out = []
    if getattr(pair, "visit_front", None) is None:
        return out
    for v in range(pair.visit_front.shape[0] - 1):
        a, b = np.asarray(pair.visit_back[v], np.float64), np.asarray(pair.visit_front[v + 1], np.float64)
        both = np.isfinite(a) & np.isfinite(b)
        if both.sum() < 100:
            continue
        ii, jj = np.flatnonzero(both.any(1)), np.flatnonzero(both.any(0))
        box = (slice(ii[0], ii[-1] + 1), slice(jj[0], jj[-1] + 1))
        shift, rms, n = ground_offset(a[box], b[box], pair.dx, max_shift)
        d0 = (a - b)[both]
        rms0 = float(np.sqrt(np.mean((d0 - d0.mean()) ** 2)))
        if not rms < evidence * rms0:
            shift, rms = np.zeros(2), rms0
        times = np.asarray(pair.visit_time[v + 1], np.float64)[both]
        out.append({"visit": v + 1, "shift_m": shift, "distance_m": float(np.hypot(*shift)), "rms_m": rms,
                    "rms0_m": rms0, "cells": int(both.sum()),
                    "t0": float(np.nanmin(times)), "t1": float(np.nanmax(times))})
    return out
