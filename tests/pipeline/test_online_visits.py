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


def test_the_back_lidar_s_view_of_ground_still_to_be_driven_stays_out_of_the_after_layers():
    """Hand-built rows: row 1 along y = 0 (x 0 -> 8 m), a headland, row 2 back along y = 2.5 m
    (beyond the visit reach of row 1, so its ground is visited once, by row 2). The back lidar
    sees row 2's cell (4, 2.5) from row 1 at its untouched 0 m, then behind row 2 dug to -20 mm;
    a cell at (4, -1.4) m no visit reaches is seen at +10 mm. H_b of the dug cell is -20 mm (not
    the -10 mm mean of both views), the far cell keeps its +10 mm, and H_f is the untouched
    ground the front lidar saw."""
    from types import SimpleNamespace

    from torchsoil.io.bag import Recording
    from torchsoil.pipeline.online import OnlinePipeline
    from torchsoil.robot import paper_platform
    from torchsoil.settings import load_settings

    p = OnlinePipeline(paper_platform(), load_settings().pipeline, Recording([], []))
    p.L, p.mapper, p.fuse_flags = np.eye(4), SimpleNamespace(stamps=[], flags=[]), []
    row1 = np.column_stack([np.linspace(0, 8, 81), np.zeros(81)])
    turn = np.column_stack([np.full(5, 8.0), np.linspace(0.5, 2.0, 5)])
    row2 = np.column_stack([np.linspace(8, 0, 81), np.full(81, 2.5)])
    xy = np.vstack([row1, turn, row2])
    t = np.arange(len(xy)) * 0.1 + 100.0
    for ti, (x, y) in zip(t, xy, strict=True):
        T = np.eye(4)
        T[:2, 3] = x, y
        p.ok_stamps.append(float(ti)), p.ok_poses.append(T)
    p._track()
    t_pass = t[81 + 5 + 40]                                   # row 2 abeam x = 4 m

    def patch(cx, cy, z, n=40):                               # n points spread over the cell
        g = np.random.default_rng(0).uniform(-0.009, 0.009, (n, 2))
        return np.column_stack([cx + g[:, 0], cy + g[:, 1], np.full(n, z)])

    p._route("front", patch(4.0, 2.5, 0.0), np.full(40, t[20]))          # front, from row 1
    p._route("back", patch(4.0, 2.5, 0.0), np.full(40, t[60]))           # back, across from row 1
    p._route("back", patch(4.0, 2.5, -0.02), np.full(40, t_pass + 1.5))  # back, behind row 2
    p._route("back", patch(4.0, -1.4, 0.01), np.full(40, t[60]))          # never visited
    p._route("front", patch(4.0, -1.4, 0.01), np.full(40, t[20]))
    tp = p.terrain()
    at = lambda x, y: tuple(tp.grid.index(np.array([[x, y]]))[0])       # noqa: E731
    assert tp.h_back[at(4.0, 2.5)] == pytest.approx(-0.02, abs=1e-6)
    assert tp.h_front[at(4.0, 2.5)] == pytest.approx(0.0, abs=1e-6)
    assert tp.h_back[at(4.0, -1.4)] == pytest.approx(0.01, abs=1e-6)
    assert tp.extras["measured_back"][at(4.0, -1.4)] and tp.extras["measured_back"][at(4.0, 2.5)]
