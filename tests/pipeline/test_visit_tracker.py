"""The per-cell visit tracker on hand-made paths (cells on the 2 cm lattice, reach 0.5 m,
gap 1 m): when each cell's visits start and when base_link passes closest."""

import numpy as np
import pytest

from torchsoil.pipeline.visit_tracker import VisitTracker

DX, REACH, GAP = 0.02, 0.5, 1.0


def cell(tracker, x, y):
    """Start times and closest-pass times (V,) of the cell holding (x, y)."""
    i, j = int(round(x / DX)), int(round(y / DX))
    starts, times = tracker.region(i, i + 1, j, j + 1)
    return starts[:, 0, 0], times[:, 0, 0]


def straight(x0, x1, t0, speed=1.0, y=0.0, step=0.1):
    x = np.arange(x0, x1 + 1e-9, step) if x1 > x0 else np.arange(x0, x1 - 1e-9, -step)
    return t0 + np.abs(x - x0) / speed, np.column_stack([x, np.full_like(x, y)])


def test_a_straight_pass_is_one_visit_closest_when_abreast():
    """At 1 m/s along y = 0 from x = 0: the cell (3, 0.3) comes within 0.5 m at x = 2.6
    (t = 2.6 s, sqrt(0.5^2 - 0.3^2) = 0.4 m before) and is passed closest at x = 3 (t = 3 s)."""
    tr = VisitTracker(DX, REACH, GAP)
    tr.add(*straight(0.0, 6.0, 0.0))
    starts, times = cell(tr, 3.0, 0.3)
    assert np.isfinite(starts).sum() == 1
    assert starts[0] == pytest.approx(2.6, abs=0.02) and times[0] == pytest.approx(3.0, abs=0.02)
    _, far = cell(tr, 3.0, 0.6)
    assert not np.isfinite(far).any()                      # beyond reach: no visit


def test_out_and_back_on_the_same_line_is_two_visits():
    """Out to x = 6 (t = 6 s) and back: the cell at x = 2 is passed at t = 2 s and again at
    t = 6 + 4 = 10 s; the number of visits passed by a time counts them."""
    tr = VisitTracker(DX, REACH, GAP)
    t, xy = straight(0.0, 6.0, 0.0)
    tb, xyb = straight(6.0, 0.0, 6.0)
    tr.add(t, xy)
    tr.add(tb[1:], xyb[1:])
    _, times = cell(tr, 2.0, 0.0)
    assert times[:2] == pytest.approx([2.0, 10.0], abs=0.02) and np.isfinite(times).sum() == 2
    p = np.array([[2.0, 0.0]] * 3)
    assert tr.passed(p, np.array([1.0, 5.0, 11.0])).tolist() == [0, 1, 2]
    # near the turning point the cell never left reach for more than the gap: one visit
    _, end = cell(tr, 5.9, 0.0)
    assert np.isfinite(end).sum() == 1


def test_a_tight_turn_stays_one_visit_and_standing_still_adds_none():
    """Round a circle of radius 0.3 m (inside the reach) twice: its centre stays within reach
    all the time, one visit. Standing still at a point for 5 s: one visit."""
    tr = VisitTracker(DX, REACH, GAP)
    a = np.linspace(0, 4 * np.pi, 200)
    tr.add(a, 0.3 * np.column_stack([np.cos(a), np.sin(a)]))
    _, times = cell(tr, 0.0, 0.0)
    assert np.isfinite(times).sum() == 1
    still = VisitTracker(DX, REACH, GAP)
    still.add(np.linspace(0, 5, 51), np.zeros((51, 2)))
    _, times = cell(still, 0.1, 0.1)
    assert np.isfinite(times).sum() == 1


def test_bad_input_is_refused():
    tr = VisitTracker(DX, REACH, GAP)
    tr.add([1.0], [[0.0, 0.0]])
    with pytest.raises(ValueError, match="backwards"):
        tr.add([0.5], [[0.1, 0.0]])
    with pytest.raises(ValueError, match="finite"):
        tr.add([2.0], [[np.nan, 0.0]])
    with pytest.raises(ValueError, match="positive"):
        VisitTracker(DX, 0.0, GAP)
