"""Map offset and tilt between H_b and H_f: recovered on untouched ground, removed before
estimation, switchable. Expected values are the ones put into the maps by hand."""

from __future__ import annotations

import math

import numpy as np
import pytest
from synthetic_pair import sim_pair

from torchsoil.estimate.estimator import Estimator
from torchsoil.estimate.nuisance import fit_map_nuisance
from torchsoil.estimate.windows import path_index
from torchsoil.grid import Grid
from torchsoil.io.terrain_pair import TerrainPair
from torchsoil.robot import paper_platform
from torchsoil.settings import EstimatorConfig, NuisanceConfig, load_settings


def _straight(length=6.0, dx=0.02):
    robot = paper_platform()
    grid = Grid.covering(-1.0, -1.6, length + 1.0, 1.6, dx)
    t = np.arange(0.0, length + 1e-9, 0.05)
    poses = np.zeros((len(t), 7))
    poses[:, 0], poses[:, 1] = t, t
    return robot, grid, poses


def test_offset_and_tilt_recovered_despite_ruts():
    robot, grid, poses = _straight()
    idx = path_index(grid, poses, robot, 1.6)
    rng = np.random.default_rng(1)
    hf = rng.normal(0.0, 0.003, grid.shape)
    xs, ys = grid.centers()
    X, Y = np.meshgrid(xs, ys, indexing="ij")
    tilt = math.radians(0.05)                              # 0.05 deg about the x axis: dz/dy
    hb = hf + 0.0015 + math.tan(tilt) * Y + rng.normal(0.0, 0.003, grid.shape)
    near = idx.wheel_dist < robot.wheel_width
    hb[near] -= 0.04                                       # ruts 4 cm deep: must not pull the fit
    hb[rng.random(grid.shape) < 0.01] = np.nan             # dropouts
    cfg = NuisanceConfig(knot_spacing=0.0)
    fit = fit_map_nuisance(hf, hb, grid, idx, robot.wheel_width, 2.5, 3.0, cfg)
    # the plane is centred on the untouched cells; compare the fitted surface with the truth there
    truth = 0.0015 + math.tan(tilt) * Y
    zone = np.isfinite(idx.s) & (idx.wheel_dist > 2.5 * robot.wheel_width)
    assert np.abs(fit.field[zone] - truth[zone]).max() < 2e-4
    assert fit.slope[1] == pytest.approx(math.tan(tilt), abs=1e-4)
    assert abs(fit.slope[0]) < 5e-5
    assert fit.tilt_deg == pytest.approx(0.05, abs=0.01)
    assert "tilt" in fit.describe() and "+1.5" in fit.describe()


def test_offset_drifting_along_the_drive():
    robot, grid, poses = _straight(length=12.0)
    idx = path_index(grid, poses, robot, 1.6)
    rng = np.random.default_rng(2)
    hf = rng.normal(0.0, 0.002, grid.shape)
    s = np.nan_to_num(idx.s)
    drift = 0.002 * np.sin(np.pi * s / 12.0)               # up 2 mm mid-drive and back: not a plane
    hb = hf + drift + rng.normal(0.0, 0.002, grid.shape)
    fit = fit_map_nuisance(hf, hb, grid, idx, robot.wheel_width, 2.5, 3.0,
                           NuisanceConfig(tilt=False, knot_spacing=2.0))
    zone = np.isfinite(idx.s)
    assert np.abs(fit.field[zone] - drift[zone]).mean() < 2e-4
    constant = fit_map_nuisance(hf, hb, grid, idx, robot.wheel_width, 2.5, 3.0,
                                NuisanceConfig(tilt=False, knot_spacing=0.0))
    assert np.abs(constant.field[zone] - drift[zone]).mean() > 5e-4


def test_a_knot_few_cells_reach_does_not_drift():
    """A constant 1 mm offset, but the untouched ground of the first 3.5 m is unmeasured
    (an out-and-back's return leg covers it) except 20 cells behind the start, 5 mm off (a
    blob). Knot 0 rests on those 20 cells alone: fitted freely it would drift by the blob's
    5 mm; pulled toward none as if min_cells = 200 more cells had measured none there, it
    keeps at most 20 / 220 of it (about 0.5 mm)."""
    robot, grid, poses = _straight(length=12.0)
    idx = path_index(grid, poses, robot, 1.6)
    rng = np.random.default_rng(4)
    hf = rng.normal(0.0, 0.002, grid.shape)
    hb = hf + 0.001 + rng.normal(0.0, 0.002, grid.shape)
    untouched = np.isfinite(idx.s) & (idx.wheel_dist >= 2.5 * robot.wheel_width) & (idx.offset <= 1.5)
    early = np.argwhere(untouched & (idx.s < 3.5))
    hb[tuple(early.T)] = np.nan
    blob = early[np.argsort(idx.s[tuple(early.T)])[:20]]
    hb[tuple(blob.T)] = hf[tuple(blob.T)] + 0.006
    cfg = NuisanceConfig(tilt=False, knot_spacing=4.0, min_cells=200)
    fit = fit_map_nuisance(hf, hb, grid, idx, robot.wheel_width, 2.5, 3.0, cfg)
    assert fit.drift < 0.8e-3
    assert fit.offset == pytest.approx(0.001, abs=2e-4)


def test_switch_off_and_too_little_ground():
    robot, grid, poses = _straight()
    idx = path_index(grid, poses, robot, 1.6)
    h = np.zeros(grid.shape)
    assert fit_map_nuisance(h, h, grid, idx, robot.wheel_width, 2.5, 3.0, NuisanceConfig(offset=False)) is None
    with pytest.raises(ValueError, match="nuisance.offset=false"):
        fit_map_nuisance(h, np.full(grid.shape, np.nan), grid, idx, robot.wheel_width, 2.5, 3.0, NuisanceConfig())


def test_estimator_removes_a_map_offset():
    """The same drive with H_b raised by 2 mm: with the nuisance term the parameters match those of
    the drive without offset; without it, the map offset leaks into them."""
    pair, _ = sim_pair(length=4.0, seed=3)
    raised = TerrainPair(pair.dx, pair.origin, pair.h_front, pair.h_back + np.float32(0.002), pair.poses,
                         pair.wheels, pair.wheel_width)

    def params(p, on):
        est = EstimatorConfig().replace(nuisance={"offset": on})
        e = Estimator(p, est, load_settings().sim, device="cpu")
        rows = [o.row for o in e.run() if o.fit is not None]
        return e, np.array([[r["d1"], r["d2"], r["chi"]] for r in rows]), rows

    _, ref, _ = params(pair, False)
    e, on, rows = params(raised, True)
    _, off, _ = params(raised, False)
    assert e.nuisance.offset == pytest.approx(0.002, abs=3e-4)
    assert all(r["map_offset"] == pytest.approx(0.002, abs=4e-4) for r in rows)
    assert np.abs(on[:, :2] - ref[:, :2]).mean() < 0.5 * np.abs(off[:, :2] - ref[:, :2]).mean()


def test_drift_along_the_drive_solved_banded_as_the_dense_robust_fit_would():
    # the drift's hat basis is fitted without forming it (tridiagonal normal equations); the
    # same Huber fit on the dense basis, built here by interpolating each knot's unit vector
    # and solved by numpy's lstsq, gives the same knot values and robust std
    from torchsoil.estimate.nuisance import _huber_hats, _huber_lstsq

    rng = np.random.default_rng(4)
    knots = np.linspace(0.0, 40.0, 9)
    s = np.sort(rng.uniform(-1.0, 41.0, 3000))                # a few positions beyond the ends
    s = s[(s < 14.0) | (s > 21.0)]                             # a knot (at 15 and 20 m) few cells reach
    truth = np.sin(knots / 7.0) * 1e-3
    y = np.interp(s, knots, truth) + rng.normal(0.0, 3e-4, len(s))
    y[rng.choice(len(s), 60, replace=False)] += 0.01          # outliers the Huber weights put down
    dense = np.stack([np.interp(s, knots, np.eye(len(knots))[i]) for i in range(len(knots))], axis=1)
    for ridge in (50.0, 2.0):
        want, want_sigma = _huber_lstsq(dense, y, ridge=ridge)
        got, got_sigma = _huber_hats(s, knots, y, ridge=ridge)
        assert np.allclose(got, want, rtol=0, atol=1e-12) and math.isclose(got_sigma, want_sigma, rel_tol=1e-9)
    reached = [0, 1, 2, 5, 6, 7, 8]                            # with a light ridge, the drift put in
    assert np.abs(got[reached] - truth[reached]).max() < 1e-4


def test_offset_field_crops_equal_the_whole_grid_and_the_formula():
    """The lazy map offset: by hand on a 4 x 3 grid, c + c(s) + slope . (x - x0, y - y0) on the
    cells the drive reaches, 0 elsewhere; any crop is the same cells of the whole grid, bit for bit."""
    from torchsoil.estimate.nuisance import OffsetField

    s = np.array([[0.0, 1.0, np.nan], [2.0, 3.0, 4.0], [np.nan, 5.0, 6.0], [7.0, 8.0, 9.0]])
    xs, ys = np.array([0.0, 0.1, 0.2, 0.3]), np.array([1.0, 1.1, 1.2])
    knots, along = np.array([0.0, 10.0]), np.array([0.0, 0.01])        # c(s) = 0.001 s
    f = OffsetField(s, xs, ys, [0.002], knots, along, (0.01, -0.02), 0.1, 1.1)
    whole = np.asarray(f)
    i, j = 3, 1                                                          # s = 8
    assert whole[i, j] == pytest.approx(0.002 + 0.008 + 0.01 * (0.3 - 0.1) - 0.02 * (1.1 - 1.1))
    assert whole[0, 2] == 0.0 and whole[2, 0] == 0.0 and whole.shape == f.shape
    for sl in [(slice(1, 3), slice(0, 2)), (slice(0, 4), slice(2, 3)), (slice(2, 9), slice(1, 9))]:
        assert np.array_equal(f[sl], whole[sl])
    assert np.array_equal(f[np.isfinite(s)], whole[np.isfinite(s)])
