"""The recorder's visit layers (docs/formats.md section 3, visits v1.1) on a drive that comes
back over its own ruts (tests/conftest.py `out_and_back`): in the terrain pair with the pair's
measurement noise, drawn per layer; in the truth without."""

import numpy as np
import pytest

from torchsoil.io.terrain_pair import TerrainPair
from torchsoil.synth.record import sidecar


@pytest.fixture(scope="module")
def layers(out_and_back):
    bag, truth = out_and_back
    with np.load(sidecar(bag, "pair.npz")) as f:
        pair = {k: f[k] for k in f.files}
    return pair, truth


def test_pair_and_truth_carry_one_layer_per_visit(layers):
    pair, truth = layers
    states, n = truth["states"], truth["n_visits"]
    assert (n == 2).sum() > 1000 and states.shape[0] == 3
    tp = TerrainPair.from_mapping(pair)
    assert tp.n_visits == 2 and pair["visit_front"].dtype == np.float32 and pair["visit_time"].dtype == np.float32
    for v in range(2):
        there = n > v
        assert np.all(np.isnan(pair["visit_front"][v][~there])) and np.all(np.isnan(pair["visit_time"][v][~there]))
        np.testing.assert_array_equal(truth["visit_front"][v][there], states[v][there])       # clean in the truth
        np.testing.assert_array_equal(truth["visit_back"][v][there], states[v + 1][there])
        np.testing.assert_array_equal(pair["visit_time"][v], np.where(there, truth["pass_time"][v], np.nan))
        for key, state in (("visit_front", states[v]), ("visit_back", states[v + 1])):
            noise = (pair[key][v] - state)[there]
            assert np.nanstd(noise) == pytest.approx(0.003, rel=0.1)            # the pair's 3 mm
    # the first view before and each cell's last after are H_f and H_b themselves (FORMATS v1.1);
    # the two views of the state between the visits have noises of their own
    np.testing.assert_array_equal(pair["visit_front"][0][n > 0], pair["h_front"][n > 0])
    last = np.take_along_axis(pair["visit_back"], np.maximum(n - 1, 0)[None], 0)[0]
    np.testing.assert_array_equal(last[n > 0], pair["h_back"][n > 0])
    twice = n == 2
    a, b = pair["visit_back"][0][twice] - states[1][twice], pair["visit_front"][1][twice] - states[1][twice]
    ok = np.isfinite(a) & np.isfinite(b)
    assert abs(np.corrcoef(a[ok], b[ok])[0, 1]) < 0.05


def test_visit_time_is_when_base_link_passed_closest(layers):
    """Against the true path: at pass_time[v] base_link is as near the cell as it ever came
    during visit v (between the end of visit v - 1 and the end of visit v), on the ruts of the
    straight legs (x 1.5-2.5 m: a wheel is near the cell whenever base_link passes it; elsewhere
    a visit may begin after base_link was nearest, when a wheel first comes near)."""
    _, truth = layers
    poses, ends, n, states = truth["poses"], truth["visit_time"], truth["n_visits"], truth["states"]
    xs, ys = truth.grid.centers()
    legs = (xs[:, None] > poses[0, 1] + 1.5) & (xs[:, None] < poses[0, 1] + 2.5)
    ii, jj = np.nonzero((n == 2) & legs & (states[0] - states[1] > 0.005))
    pick = np.random.default_rng(0).choice(len(ii), 40, replace=False)
    t = np.linspace(poses[0, 0], poses[-1, 0], 20001)
    x, y = np.interp(t, poses[:, 0], poses[:, 1]), np.interp(t, poses[:, 0], poses[:, 2])
    for i, j in zip(ii[pick], jj[pick], strict=True):
        d = np.hypot(x - xs[i], y - ys[j])
        for v in range(2):
            inside = (t > (ends[v - 1, i, j] if v else -np.inf)) & (t <= ends[v, i, j])
            at = np.interp(truth["pass_time"][v, i, j], t, d)
            assert at <= d[inside].min() + 0.01
