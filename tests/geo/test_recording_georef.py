"""A recording with RTK GNSS through the pipeline and the export (tests/conftest.py
`out_and_back`: a light-bulb turn and back over its own ruts): each wheel's contact point, in
UTM by the fitted georeference of the pipeline's own trajectory, lies where the recorder's
datum puts the true one."""

from __future__ import annotations

import numpy as np
import rasterio

from torchsoil.geo.georef import Georef
from torchsoil.jobs.export import export


def wheel_points(rows: np.ndarray, wheel: np.ndarray) -> np.ndarray:
    c, s = np.cos(rows[:, 6]), np.sin(rows[:, 6])
    return np.column_stack([rows[:, 1] + c * wheel[0] - s * wheel[1], rows[:, 2] + s * wheel[0] + c * wheel[1]])


def kabsch(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a (N, 2) moved rigidly onto b (N, 2) by least squares."""
    am, bm = a.mean(0), b.mean(0)
    u, _, vt = np.linalg.svd((a - am).T @ (b - bm))
    r = (u @ np.diag([1.0, np.sign(np.linalg.det(u @ vt))]) @ vt).T
    return (a - am) @ r.T + bm


def test_rut_positions_in_utm_match_the_truth_as_well_as_the_trajectory_does(out_and_back, out_and_back_pair, tmp_path):
    bag, truth = out_and_back
    res, _ = out_and_back_pair
    pair = res.terrain
    run = tmp_path / "run"
    run.mkdir()
    pair.save(run / "terrain.npz")
    lines = export(run, tmp_path / "out", bag=bag, formats=("geotiff",))
    g = Georef.load(tmp_path / "out" / "georef.json")
    assert g.kind == "gnss", lines
    datum = Georef(**truth.meta["datum"])
    assert g.epsg == datum.epsg
    assert g.fit["outliers"] == 0 and g.fit["residual_rms_m"] < 0.025
    t_true = truth["poses"][:, 0] + truth.t0
    rows = pair.poses[(pair.poses[:, 0] >= t_true[0]) & (pair.poses[:, 0] <= t_true[-1])]
    true_rows = np.column_stack([rows[:, 0]] + [np.interp(rows[:, 0], t_true, np.unwrap(truth["poses"][:, k])
                                                          if k == 6 else truth["poses"][:, k]) for k in range(1, 7)])
    for wheel in pair.wheels:
        ours, true = wheel_points(rows, wheel), wheel_points(true_rows, wheel)
        err = np.linalg.norm(g.to_crs(ours) - datum.to_crs(true), axis=1)
        assert np.sqrt(np.mean(err**2)) < 0.015 and np.median(err) < 0.01, (wheel, err.max())
        # the georeference adds next to nothing to the trajectory's own error: the best rigid
        # fit of our points onto the truth's (Kabsch, in the map) leaves about as much
        best = np.linalg.norm(kabsch(ours, true) - true, axis=1)
        assert np.sqrt(np.mean(err**2)) < np.sqrt(np.mean(best**2)) + 0.003
    with rasterio.open(tmp_path / "out" / "soil.tif") as src:
        assert src.crs.to_epsg() == datum.epsg
        np.testing.assert_array_equal(src.read(list(src.descriptions).index("h_back") + 1), pair.h_back.T[::-1])
