"""The per-cell visit tracker (torchsoil.pipeline.visit_tracker) on paths worked out by hand:
dx 0.1 m, reach 0.5 m, gap 2 m, base_link at 1 m/s (so time = distance travelled)."""

import numpy as np
import pytest

from torchsoil.pipeline.visit_tracker import VisitTracker, visit_gap, visit_reach
from torchsoil.robot import paper_platform

DX, REACH, GAP = 0.1, 0.5, 2.0


def tracker(**kw):
    return VisitTracker(DX, REACH, GAP, size=16, **kw)   # small tiles: paths cross tile edges


def line(x0, x1, t0=0.0, step=0.1):
    """Positions every `step` m from (x0, 0) to (x1, 0) at 1 m/s from time t0: t (N,), xy (N, 2)."""
    n = int(round(abs(x1 - x0) / step)) + 1
    x = np.linspace(x0, x1, n)
    return t0 + np.abs(x - x0), np.column_stack([x, np.zeros(n)])


def visits_at(tr, x, y):
    """(start times, closest-pass times) [s] of the visits of the cell at (x, y) m."""
    i, j = round(x / DX), round(y / DX)
    start, close = tr.region(i, i + 1, j, j + 1)
    n = int(np.isfinite(close[:, 0, 0]).sum())
    return start[:n, 0, 0], close[:n, 0, 0]


def test_a_straight_path_visits_each_cell_once():
    tr = tracker()
    tr.add(*line(0.0, 10.0))
    start, close = tr.region(0, 101, -8, 9)                    # x 0..10 m, y -0.8..0.8 m
    y = np.arange(-8, 9) * DX
    n = np.isfinite(close).sum(0)
    assert np.all(n[:, np.abs(y) <= REACH + 1e-9] == 1) and np.all(n[:, np.abs(y) > REACH + 1e-9] == 0)
    # the cell at (4, 0.3): base_link came within 0.5 m at x = 4 - 0.4 and passed closest at x = 4
    s, c = visits_at(tr, 4.0, 0.3)
    np.testing.assert_allclose(s, [3.6], atol=1e-9)
    np.testing.assert_allclose(c, [4.0], atol=1e-9)
    s, _ = visits_at(tr, 0.2, 0.0)                             # within reach of the first position
    np.testing.assert_allclose(s, [0.0])


def test_out_and_back_gives_two_visits_with_their_times():
    tr = tracker()
    t_out, xy_out = line(0.0, 5.0)
    t_back, xy_back = line(5.0, 0.0, t0=5.0)
    tr.add(t_out, xy_out)
    tr.add(t_back[1:], xy_back[1:])                            # fed in two calls
    s, c = visits_at(tr, 2.0, 0.3)
    np.testing.assert_allclose(c, [2.0, 8.0], atol=1e-9)       # out at t = 2, back at t = 5 + 3
    np.testing.assert_allclose(s, [1.6, 7.6], atol=1e-9)
    # x = 3.4: left at x = 3.9, back there after 2 x 1.1 m > gap; x = 3.6: after 1.8 m, one visit
    assert len(visits_at(tr, 3.4, 0.0)[1]) == 2
    s, c = visits_at(tr, 3.6, 0.0)
    assert len(c) == 1 and c[0] == pytest.approx(3.6)
    # the queries: visits passed (base_link closest) and started by each time
    xy = np.tile([2.0, 0.3], (5, 1))
    np.testing.assert_array_equal(tr.passed(xy, np.array([1.5, 1.99, 2.01, 7.99, 8.01])), [0, 0, 1, 1, 2])
    np.testing.assert_array_equal(tr.started(xy, np.array([1.59, 1.61, 2.0, 7.61, 9.0])), [0, 1, 1, 2, 2])
    assert tr.passed(np.array([[2.0, 0.8], [50.0, 50.0]]), 100.0).tolist() == [0, 0]   # out of reach, no tile


def test_a_cell_near_throughout_a_tight_turn_is_one_visit():
    """Two laps of a circle of radius 0.3 m (3.8 m of path, more than the gap): its centre
    never leaves reach, so one visit; a cell 2.5 m away is never visited."""
    a = np.linspace(0.0, 4 * np.pi, 121)
    xy = np.column_stack([2.0 + 0.3 * np.cos(a), 0.3 * np.sin(a)])
    t = 0.3 * a
    tr = tracker()
    tr.add(t, xy)
    s, c = visits_at(tr, 2.0, 0.0)
    assert len(s) == 1 and s[0] == 0.0
    assert len(visits_at(tr, 4.5, 0.0)[0]) == 0
    # but leaving the same cell for more than the gap and coming back is a second visit
    tr.add(*line(2.3, 6.0, t0=t[-1] + 1.0))
    tr.add(*line(6.0, 2.0, t0=t[-1] + 1.0 + 3.7))
    assert len(visits_at(tr, 2.0, 0.0)[0]) == 2


def test_standing_still_adds_no_visit():
    tr = tracker()
    tr.add(np.arange(0.0, 50.0, 0.1), np.tile([1.0, 0.0], (500, 1)))    # 50 s in one place
    tr.add(*line(1.0, 3.0, t0=50.0))
    tr.add(np.arange(52.1, 90.0, 0.1), np.tile([3.0, 0.0], (379, 1)))
    s, c = visits_at(tr, 1.0, 0.2)
    assert len(s) == 1 and s[0] == 0.0 and c[0] == 0.0
    s, c = visits_at(tr, 2.0, 0.0)
    np.testing.assert_allclose(s, [50.5], atol=1e-9)
    np.testing.assert_allclose(c, [51.0], atol=1e-9)
    assert tr.started(np.array([[1.0, 0.0]]), 1e9).tolist() == [1]


def test_a_long_segment_is_exact_and_spilled_tiles_come_back(tmp_path):
    """One 20 m diagonal segment (cut into pieces inside): times interpolate along it; tiles
    spilled to disk answer the same, and come back when the path returns."""
    tr = tracker(spill_dir=str(tmp_path))
    tr.add(np.array([0.0, 20.0]), np.array([[0.0, 0.0], [20 / np.sqrt(2), 20 / np.sqrt(2)]]))
    x = 5.0 / np.sqrt(2)
    cell = np.array([[round(x / DX) * DX, round(x / DX) * DX]])
    before = visits_at(tr, *cell[0])
    assert len(before[1]) == 1 and before[1][0] == pytest.approx(np.hypot(*cell[0]), abs=1e-9)
    assert tr.spill(np.zeros((1, 2)), -np.inf) > 0 and tr.memory() == 0
    np.testing.assert_array_equal(visits_at(tr, *cell[0])[1], before[1])
    assert tr.passed(cell, 100.0).tolist() == [1]
    tr.add(np.array([40.0]), np.array([[0.0, 0.0]]))               # and back: a second visit
    assert len(visits_at(tr, *cell[0])[1]) == 2 and tr.memory() > 0


def test_bad_input_is_refused():
    tr = tracker()
    tr.add(*line(0.0, 1.0))
    with pytest.raises(ValueError, match="backwards"):
        tr.add(np.array([0.5]), np.array([[1.0, 0.0]]))
    with pytest.raises(ValueError, match=r"\(N, 2\)"):
        tr.add(np.array([2.0, 3.0]), np.zeros((2, 3)))
    with pytest.raises(ValueError, match="finite"):
        tr.add(np.array([2.0]), np.array([[np.nan, 0.0]]))
    with pytest.raises(ValueError, match="reach must be a positive length"):
        VisitTracker(DX, 0.0, GAP)


def test_reach_and_gap_of_the_paper_platform():
    """Beside a straight drive: |y| 0.5 m + 0.14 m x (0.5 + 2) = 0.85 m; under a corner wheel's
    footprint: hypot(0.69, 0.5) + 0.07 = 0.922 m, the reach (a pivot digs there while base_link
    stays put); with a wide relaxation margin the straight drive's reach is the larger. The gap
    is twice the wheelbase (1.38 m) plus a wheel width."""
    robot = paper_platform()
    assert visit_reach(robot, 2.0) == pytest.approx((0.69**2 + 0.5**2) ** 0.5 + 0.07)
    assert visit_reach(robot, 2.0) == pytest.approx(0.9221, abs=1e-4)
    assert visit_reach(robot, 4.0) == pytest.approx(0.5 + 0.14 * 4.5)
    assert visit_gap(robot) == pytest.approx(3.04)
