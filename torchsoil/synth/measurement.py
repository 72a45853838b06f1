"""The measurement model of a synthetic terrain pair: what real before/after maps have on
top of the true surfaces, drawn per drive from the seed within the ranges of the scenario's
`measurement` section (torchsoil.settings.MeasurementConfig).

- per-cell noise of standard deviation `noise`: Gaussian, or Student-t with `noise_dof`
  degrees of freedom scaled to the same standard deviation (heavier tails);
- a vertical offset and a tilt of H_b against H_f (lidar extrinsics, re-registration);
- lost cells (NaN), independently in each map: single-cell dropouts, blobs (discs) and
  occlusion streaks (thin lines along the heading, behind the robot).

Each nuisance has its own random stream, so switching one on leaves the others' draws and,
with all off, the noise is that of the generator before these nuisances existed.
"""

from __future__ import annotations

import math

import numpy as np

from torchsoil.grid import Grid
from torchsoil.settings import MeasurementConfig


def apply_measurement(h_front: np.ndarray, h_back: np.ndarray, grid: Grid, poses: np.ndarray,
                      cfg: MeasurementConfig, seed: int, noise: float | None = None,
                      half_width: float = 1.0, layer: int = 0) -> tuple[np.ndarray, np.ndarray, dict]:
    """Measured (h_front, h_back) float32 (X, Y) [m, NaN where lost] from the true surfaces
    (X, Y) [m] on `grid`, for the drive's poses (N, 7) [t, x, y, z, roll, pitch, yaw].

    noise: overrides cfg.noise, m; half_width: occlusion streaks start within this many m
    of the path; layer: which measurement of the drive this pair of maps is (0: the terrain
    pair's H_f and H_b, v + 1: the visit layers of visit v): each layer has its own noise and
    lost cells, while the noise law, offset and tilt (the lidars' own) are the drive's. Returns
    also what was drawn: {noise_dof (None: Gaussian),
    offset [m], tilt_x_deg, tilt_y_deg (H_b - H_f rises by tan(tilt) per m along x, y from
    the grid centre), lost_front, lost_back (fractions of cells)}."""
    sd = cfg.noise if noise is None else float(noise)
    r_noise = np.random.default_rng(np.random.SeedSequence([int(seed), 11] + ([int(layer)] if layer else [])))
    r_dof, r_offset, r_tilt, r_front, r_back = (np.random.default_rng(s) for s in
                                                np.random.SeedSequence([int(seed), 13]).spawn(5))
    if layer:                                     # a layer's own lost cells
        lost = np.random.SeedSequence([int(seed), 13, int(layer)]).spawn(2)
        r_front, r_back = (np.random.default_rng(s) for s in lost)
    dof = None if cfg.noise_dof is None else float(r_dof.uniform(*cfg.noise_dof))
    hf = h_front + per_cell_noise(r_noise, h_front.shape, sd, dof)
    hb = h_back + per_cell_noise(r_noise, h_back.shape, sd, dof)
    offset = float(r_offset.uniform(-cfg.offset, cfg.offset)) if cfg.offset > 0 else 0.0
    tilt = r_tilt.uniform(-cfg.tilt_deg, cfg.tilt_deg, 2) if cfg.tilt_deg > 0 else np.zeros(2)
    xs, ys = grid.centers()
    slope = np.tan(np.radians(tilt))
    hb = hb + offset + slope[0] * (xs - xs.mean())[:, None] + slope[1] * (ys - ys.mean())[None, :]
    hf = np.where(lost_cells(r_front, grid, poses, cfg, half_width), np.nan, hf).astype(np.float32)
    hb = np.where(lost_cells(r_back, grid, poses, cfg, half_width), np.nan, hb).astype(np.float32)
    drawn = {"noise_dof": dof, "offset": offset, "tilt_x_deg": float(tilt[0]), "tilt_y_deg": float(tilt[1]),
             "lost_front": float(np.isnan(hf).mean()), "lost_back": float(np.isnan(hb).mean())}
    return hf, hb, drawn


def per_cell_noise(rng: np.random.Generator, shape, sd: float, dof: float | None) -> np.ndarray:
    """Independent noise of standard deviation sd [m]: Gaussian (dof None) or Student-t with
    dof > 2 degrees of freedom, scaled by sqrt((dof - 2) / dof) to that standard deviation."""
    if dof is None:
        return sd * rng.standard_normal(shape)
    return sd * math.sqrt((dof - 2.0) / dof) * rng.standard_t(dof, shape)


def lost_cells(rng: np.random.Generator, grid: Grid, poses: np.ndarray, cfg: MeasurementConfig,
               half_width: float = 1.0) -> np.ndarray:
    """(X, Y) bool: cells one map lost (dropouts, blobs, occlusion streaks starting within
    half_width m of the path; see module doc)."""
    X, Y = grid.shape
    dx = grid.dx
    lost = rng.random((X, Y)) < rng.uniform(*cfg.dropout)
    xs, ys = grid.centers()
    for _ in range(rng.poisson(cfg.blobs * X * Y * dx * dx)):           # discs anywhere on the grid
        cx, cy, r = rng.uniform(xs[0], xs[-1]), rng.uniform(ys[0], ys[-1]), rng.uniform(*cfg.blob_radius)
        i0, i1 = np.searchsorted(xs, [cx - r, cx + r])
        j0, j1 = np.searchsorted(ys, [cy - r, cy + r])
        lost[i0:i1, j0:j1] |= (xs[i0:i1, None] - cx) ** 2 + (ys[None, j0:j1] - cy) ** 2 <= r * r
    xy = poses[:, 1:3]
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xy, axis=0), axis=1))])
    for _ in range(rng.poisson(cfg.streaks * arc[-1])):
        # behind an occluder (a clod, a wheel) at a random place along the path, running along the
        # heading (+-15 deg), 1 or 2 cells wide
        s = rng.uniform(0.0, arc[-1])
        x, y, yaw = (np.interp(s, arc, poses[:, c]) for c in (1, 2, 6))
        side = rng.uniform(-half_width, half_width)
        x0, y0 = x - math.sin(yaw) * side, y + math.cos(yaw) * side
        head = yaw + math.radians(rng.uniform(-15.0, 15.0))
        t = np.arange(0.0, rng.uniform(*cfg.streak_length), dx / 2)
        width = rng.integers(1, 3)
        for w in range(width):
            px = x0 + t * math.cos(head) - w * dx * math.sin(head)
            py = y0 + t * math.sin(head) + w * dx * math.cos(head)
            i = np.round((px - grid.origin[0]) / dx).astype(int)
            j = np.round((py - grid.origin[1]) / dx).astype(int)
            ok = (i >= 0) & (i < X) & (j >= 0) & (j < Y)
            lost[i[ok], j[ok]] = True
    return lost
