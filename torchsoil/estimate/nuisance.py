"""Map nuisance: the vertical offset and tilt between the after map H_b and the before map H_f.

Real pipelines leave them (lidar extrinsic errors, re-registration residuals): H_b sits a
millimetre or two above or below H_f and leans by a few hundredths of a degree. Neither is
physics, yet the forward model would have to explain them. They are fitted on ground the
wheels did not touch (the estimator's noise-floor distance from every wheel path, or farther),
where H_b - H_f is measurement alone, and removed from H_b before anything is estimated:

    H_b - H_f = c(s) + a (x - x0) + b (y - y0) + noise    on untouched cells,

with c(s) piecewise linear in the drive's arc length s (knots every `knot_spacing` m: an offset
that drifts along the drive) and (a, b) a plane over the world (the tilt). The fit is robust
(Huber weights, iterated), so a berm reaching into that ground or a blob of bad cells does
not move it. Each knot's drift is pulled toward none as if `min_cells` more cells had measured
none there: where the drive comes back over its own track the untouched ground takes the
arc length of the later pass, and a knot of the earlier one may be left with a handful of
cells behind the start, whose noise would otherwise read as millimetres of drift.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from scipy import linalg

from torchsoil.settings import NuisanceConfig


class OffsetField:
    """The (X, Y) map offset of a MapNuisance [m], 0 outside the drive's reach (NaN s), computed
    where it is read rather than kept over the whole grid (a 200 m drive's grid is 14 MB of
    float64 a layer): `field[i0:i1, j0:j1]` a crop, `np.asarray(field)` the whole grid (any
    other index reads from it). Each cell's value is the same expression on the same numbers
    either way, so a crop equals the whole grid's cells bit for bit.

    s: (X, Y) the path index's arc length [m] (windows.PathIndex.s, shared, not copied). xs, ys:
    (X,), (Y,) cell centres [m]. coef: the offset [m] and, with a tilt, the slopes about (x0,
    y0). knots, along: (K,) the along-drive term's knots [m] and values [m]."""

    def __init__(self, s, xs, ys, coef, knots, along, slope, x0, y0):
        self.s, self.xs, self.ys = s, xs, ys
        self.coef0, self.knots, self.along = float(coef[0]), knots, along
        self.slope, self.x0, self.y0 = slope, x0, y0

    @property
    def shape(self) -> tuple[int, int]:
        return self.s.shape

    def __getitem__(self, key) -> np.ndarray:
        if not (isinstance(key, tuple) and len(key) == 2 and all(isinstance(k, slice) for k in key)):
            return self[:, :][key]             # a mask or indices: read from the whole grid
        s = self.s[key]
        reach = np.isfinite(s)
        X, Y = np.nonzero(reach)
        out = np.zeros(s.shape, np.float64)
        out[reach] = (self.coef0 + np.interp(s[reach], self.knots, self.along)
                      + self.slope[0] * (self.xs[key[0]][X] - self.x0) + self.slope[1] * (self.ys[key[1]][Y] - self.y0))
        return out

    def __array__(self, dtype=None, copy=None) -> np.ndarray:
        out = self[:, :]
        return out if dtype is None else out.astype(dtype)


class MapNuisance(NamedTuple):
    """Fitted offset of H_b relative to H_f.

    field: (X, Y) offset to subtract from H_b, m (0 outside the drive's reach; an OffsetField,
    read by crops or np.asarray). offset: its median over the untouched cells, m.
    drift: (max - min) of the along-drive term c(s), m.
    slope: (2,) dz/dx, dz/dy of the tilt [-]; tilt_deg: its steepest angle, degrees. n_cells:
    untouched cells used. sigma: robust std of H_b - H_f there after the fit, m. knots: (K,)
    arc lengths of the knots of c(s), m; along: (K,) c at the knots, m.
    """

    field: OffsetField
    offset: float
    drift: float
    slope: tuple[float, float]
    tilt_deg: float
    n_cells: int
    sigma: float
    knots: np.ndarray
    along: np.ndarray

    def describe(self) -> str:
        """One line for reports: what was removed."""
        s = f"offset {1e3 * self.offset:+.2f} mm"
        if len(self.knots) > 1:
            s += f" (drifting by {1e3 * self.drift:.2f} mm along the drive)"
        if self.slope != (0.0, 0.0):
            s += f", tilt {self.tilt_deg:.3f} deg"
        return s + f" between H_b and H_f, fitted on {self.n_cells} untouched cells"

    def summary(self) -> dict:
        return {"offset_mm": round(1e3 * self.offset, 3), "drift_mm": round(1e3 * self.drift, 3),
                "tilt_deg": round(self.tilt_deg, 4), "slope": [float(v) for v in self.slope],
                "cells": int(self.n_cells), "sigma_mm": round(1e3 * self.sigma, 3)}


def _hat_rows(s: np.ndarray, knots: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The piecewise-linear basis ("hat" functions) on knots (K,) (K >= 2) at positions s (N,),
    two non-zeros per row: (N,) the knot k left of each position (its right neighbour k + 1
    carries the rest) and (N,) the weight u of k + 1 (1 - u on k); constant beyond the ends."""
    k = np.clip(np.searchsorted(knots, s, side="right") - 1, 0, len(knots) - 2)
    u = np.clip((s - knots[k]) / (knots[k + 1] - knots[k]), 0.0, 1.0)
    return k, u


def _huber_hats(s: np.ndarray, knots: np.ndarray, y: np.ndarray, ridge: float, iters: int = 8,
                c: float = 1.345) -> tuple[np.ndarray, float]:
    """`_huber_lstsq` on the hat basis of knots (K,) at positions s (N,), ridge > 0, without
    forming the (N, K) basis: its normal equations are tridiagonal, summed in O(N) and solved
    banded, so the drift along an hour's drive (thousands of knots, millions of cells) costs
    what one along a 20 m drive does per cell. Returns the knot values (K,) and the robust std."""
    K = len(knots)
    k, u = _hat_rows(s, knots)
    v = 1.0 - u
    w = np.ones(len(y))
    coef = np.zeros(K)
    sigma = float(np.std(y)) or 1.0
    for _ in range(iters):
        band = np.zeros((2, K))                              # upper form: off-diagonal, diagonal
        band[0, 1:] = np.bincount(k, w * u * v, K - 1)
        band[1] = np.bincount(k, w * v * v, K) + np.bincount(k + 1, w * u * u, K) + ridge
        coef = linalg.solveh_banded(band, np.bincount(k, w * v * y, K) + np.bincount(k + 1, w * u * y, K))
        r = y - (v * coef[k] + u * coef[k + 1])
        sigma = 1.4826 * float(np.median(np.abs(r - np.median(r)))) or 1e-12
        a = np.abs(r) / (c * sigma)
        w = np.where(a <= 1, 1.0, 1.0 / np.maximum(a, 1e-12))
    return coef, sigma


def _huber_lstsq(A: np.ndarray, y: np.ndarray, iters: int = 8, c: float = 1.345,
                 ridge: float = 0.0) -> tuple[np.ndarray, float]:
    """Robust least squares (Huber weights, IRLS): coefficients (P,) and the robust std of the
    residuals (MAD). ridge: each coefficient is pulled toward 0 as if that many more rows had
    measured 0 for it alone (a coefficient few rows support stays near 0)."""
    w = np.ones(len(y))
    coef = np.zeros(A.shape[1])
    sigma = float(np.std(y)) or 1.0
    prior = math.sqrt(ridge) * np.eye(A.shape[1])
    for _ in range(iters):
        sw = np.sqrt(w)
        coef = np.linalg.lstsq(np.vstack([A * sw[:, None], prior]), np.concatenate([y * sw, np.zeros(A.shape[1])]),
                               rcond=None)[0]
        r = y - A @ coef
        sigma = 1.4826 * float(np.median(np.abs(r - np.median(r)))) or 1e-12
        a = np.abs(r) / (c * sigma)
        w = np.where(a <= 1, 1.0, 1.0 / np.maximum(a, 1e-12))
    return coef, sigma


def fit_map_nuisance(h_front: np.ndarray, h_back: np.ndarray, grid, index, wheel_width: float,
                     untouched: float, corridor: float, cfg: NuisanceConfig) -> MapNuisance | None:
    """Fit the offset (and tilt) of H_b relative to H_f; None when disabled.

    h_front, h_back: (X, Y) maps, m (NaN where unmeasured). grid: their Grid. index: the
    drive's windows.PathIndex. untouched: distance from every wheel path beyond which the
    ground counts as untouched, in wheel widths. corridor: width of the ground the estimator
    uses, m. Raises ValueError when fewer than cfg.min_cells untouched cells are measured in
    both maps (nothing to fit the nuisance on: switch it off, or widen the corridor).
    """
    if not cfg.offset:
        return None
    cells = (np.isfinite(h_front) & np.isfinite(h_back) & np.isfinite(index.s)
             & (index.wheel_dist >= untouched * wheel_width) & (index.offset <= corridor / 2))
    n = int(cells.sum())
    if n < cfg.min_cells:
        raise ValueError(f"map offset: only {n} untouched cells measured in both maps (need {cfg.min_cells}); "
                         "set estimator.nuisance.offset=false or widen estimator.corridor")
    ii, jj = np.nonzero(cells)
    xs, ys = grid.centers()
    s = index.s[cells]
    length = float(index.arc[-1])
    if cfg.knot_spacing > 0 and length > cfg.knot_spacing:
        knots = np.linspace(0.0, length, int(math.ceil(length / cfg.knot_spacing)) + 1)
    else:
        knots = np.array([0.0])
    x0, y0 = float(xs[ii].mean()), float(ys[jj].mean())
    y = (h_back[cells] - h_front[cells]).astype(np.float64)
    # first the offset and the plane, then what drifts along the drive on top of them (the
    # along-drive term alone would also absorb the tilt's component along a straight drive)
    A = np.ones((n, 1))
    if cfg.tilt:
        A = np.concatenate([A, np.stack([xs[ii] - x0, ys[jj] - y0], axis=1)], axis=1)
    coef, sigma = _huber_lstsq(A, y)
    slope = (float(coef[1]), float(coef[2])) if cfg.tilt else (0.0, 0.0)
    along = np.zeros(len(knots))
    if len(knots) > 1:                       # a knot few cells reach (ground driven again) keeps the offset
        along, sigma = _huber_hats(s, knots, y - A @ coef, ridge=float(cfg.min_cells))
    field = OffsetField(index.s, xs, ys, coef, knots, along, slope, x0, y0)
    return MapNuisance(field=field, offset=float(coef[0] + np.median(np.interp(s, knots, along))),
                       drift=float(along.max() - along.min()), slope=slope,
                       tilt_deg=math.degrees(math.atan(math.hypot(*slope))), n_cells=n, sigma=sigma,
                       knots=knots, along=along)
