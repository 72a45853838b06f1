"""The pipeline on a drive that comes back over its own ruts (tests/conftest.py `out_and_back`,
`out_and_back_pair`):
every visit kept as its own layer, scored against the recorder's truth."""

import numpy as np
import pytest

from torchsoil.estimate.visits import visit_counts
from torchsoil.io.terrain_pair import TerrainPair
from torchsoil.pipeline.outputs import write_outputs


def on_grid(truth, layer, grid):
    truth.arrays["_layer"] = np.asarray(layer, np.float64)
    return truth.on_grid("_layer", grid)


def rms(a, b, cells):
    d = (a - b)[cells]
    d = d[np.isfinite(d)]
    assert len(d) > 300, "too few cells to score"
    return float(np.sqrt(np.mean(d**2)))


@pytest.fixture(scope="session")
def scored(out_and_back_pair):
    """The pair, the truth's states (before, between, after the visits) on its grid less the
    maps' offset (the median on ground never visited), and the revisited rut cells: two visits
    in the truth and in the pair, dug more than 5 mm by the first."""
    res, truth = out_and_back_pair
    tp = res.terrain
    g = tp.grid
    states = [on_grid(truth, s, g) for s in truth["states"]]
    n_true = on_grid(truth, truth["n_visits"], g)
    offset = np.nanmedian((tp.h_front - states[0])[n_true == 0])
    states = [s + offset for s in states]
    n = visit_counts(tp.visit_time) if tp.visit_time is not None else np.ones(g.shape, int)
    ruts = (n_true == 2) & (n == 2) & (states[0] - states[1] > 0.005)
    return tp, truth, states, ruts


def test_revisited_ruts_get_two_visits(scored):
    tp, truth, states, ruts = scored
    assert tp.n_visits == 2 and ruts.sum() > 1000
    n = visit_counts(tp.visit_time)
    both = n == 2
    # the visit layers are NaN beyond a cell's visits, H_f is the first view, H_b the last
    assert np.all(np.isnan(tp.visit_front[1][n < 2])) and np.all(np.isnan(tp.visit_time[0][n == 0]))
    np.testing.assert_array_equal(tp.visit_front[0][n >= 1], tp.h_front[n >= 1])
    last = np.take_along_axis(tp.visit_back, np.maximum(n - 1, 0)[None], 0)[0]
    np.testing.assert_array_equal(last[n >= 1], tp.h_back[n >= 1])
    # visit_time in the poses' clock (the bag's), float64, close to the truth's closest passes
    assert tp.visit_time.dtype == np.float64
    assert np.nanmin(tp.visit_time) >= tp.poses[0, 0] - 1.0 and np.nanmax(tp.visit_time) <= tp.poses[-1, 0] + 1.0
    for v in range(2):
        true = on_grid(truth, truth["pass_time"][v], tp.grid) + truth.t0
        assert np.nanmedian(np.abs(tp.visit_time[v] - true)[both & ruts]) < 0.1
    assert np.all(tp.visit_time[1][both] > tp.visit_time[0][both] + 3.0)


def test_each_visit_sees_its_own_surface(scored):
    """On the revisited ruts, the surface before the second visit is the one between the visits
    (states[1]), not the untouched ground that H_f and the first layer show."""
    tp, _, states, ruts = scored
    between = rms(tp.visit_front[1], states[1], ruts)
    assert between < 0.6 * rms(tp.visit_front[0], states[1], ruts) and between < 0.015
    assert rms(tp.h_front, states[0], ruts) < 0.6 * rms(tp.h_front, states[1], ruts)
    assert rms(tp.visit_back[0], states[1], ruts) < 0.015         # after the first visit
    assert rms(tp.h_back, states[2], ruts) < 0.015                # after the last


def test_visit_layers_are_written(out_and_back_pair, tmp_path):
    res, _ = out_and_back_pair
    write_outputs(res, tmp_path)
    back = TerrainPair.load(tmp_path / "terrain.npz")
    for key in ("visit_front", "visit_back", "visit_time"):
        np.testing.assert_array_equal(getattr(back, key), getattr(res.terrain, key))
    assert back.visit_time.dtype == np.float64
